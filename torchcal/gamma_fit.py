"""The Gamma law of residual norms (Paper II's "Gamma 99 %"): its maximum-likelihood fit with the location at 0.

scipy.stats.gamma.fit(x, floc=0) gives the same numbers, but importing
scipy.stats costs 1-3 s of every CLI run on a busy 2-core machine; the
fit has a closed form up to one scalar equation, solved here with
scipy.special (a tenth of the import).
"""

from __future__ import annotations

import math

import numpy as np


def gamma_mle(x: np.ndarray) -> tuple[float, float] | None:
    """(shape a, scale) of the Gamma law fitted to x (N,) > 0 by maximum likelihood, location 0.

    The shape solves log(a) - digamma(a) = log(mean x) - mean(log x) = s
    (s > 0 unless every x is equal); the scale is mean(x) / a. Minka's
    approximation starts Newton's method (the left side is convex and
    decreasing in a). -> None when every x is (numerically) equal: the
    law degenerates to a point.
    """
    from scipy import special

    m = float(np.mean(x))
    s = math.log(m) - float(np.mean(np.log(x)))
    if not s > 1e-12:
        return None
    a = (3.0 - s + math.sqrt((s - 3.0) ** 2 + 24.0 * s)) / (12.0 * s)
    for _ in range(50):
        step = (math.log(a) - float(special.digamma(a)) - s) / (1.0 / a - float(special.polygamma(1, a)))
        a_new = a - step
        a = a_new if a_new > 0 else a / 2.0
        if abs(step) <= 1e-13 * a:
            break
    return a, m / a


def gamma_ppf(quantile: float, a: float, scale: float) -> float:
    """The ``quantile`` of Gamma(a, scale)."""
    from scipy import special

    return float(special.gammaincinv(a, quantile)) * scale


def gamma_pdf(x: np.ndarray, a: float, scale: float) -> np.ndarray:
    """Density of Gamma(a, scale) at x (N,) >= 0."""
    from scipy import special

    x = np.asarray(x, dtype=np.float64)
    with np.errstate(divide="ignore"):
        logp = (a - 1.0) * np.log(x) - x / scale - float(special.gammaln(a)) - a * math.log(scale)
    return np.exp(logp)
