"""The Gamma law of residual norms (Paper II's "Gamma 99 %"): its maximum-likelihood fit with the location at 0.

scipy.stats.gamma.fit(x, floc=0) gives the same numbers, but importing
scipy.stats costs 1-3 s of every CLI run on a busy 2-core machine (and
scipy.special still 0.3-0.6 s); the fit has a closed form up to one
scalar equation, solved here with torch.special (torch is loaded anyway).
"""

from __future__ import annotations

import math

import numpy as np
import torch


def _digamma(a: float) -> float:
    return float(torch.special.digamma(torch.tensor(a, dtype=torch.float64)))


def _trigamma(a: float) -> float:
    return float(torch.special.polygamma(1, torch.tensor(a, dtype=torch.float64)))


def _gammainc(a: float, x: float) -> float:
    """The regularized lower incomplete gamma function P(a, x)."""
    return float(torch.special.gammainc(torch.tensor(a, dtype=torch.float64), torch.tensor(x, dtype=torch.float64)))


def gamma_mle(x: np.ndarray) -> tuple[float, float] | None:
    """(shape a, scale) of the Gamma law fitted to x (N,) > 0 by maximum likelihood, location 0.

    The shape solves log(a) - digamma(a) = log(mean x) - mean(log x) = s
    (s > 0 unless every x is equal); the scale is mean(x) / a. Minka's
    approximation starts Newton's method (the left side is convex and
    decreasing in a). -> None when every x is (numerically) equal: the
    law degenerates to a point.
    """
    m = float(np.mean(x))
    s = math.log(m) - float(np.mean(np.log(x)))
    if not s > 1e-12:
        return None
    a = (3.0 - s + math.sqrt((s - 3.0) ** 2 + 24.0 * s)) / (12.0 * s)
    for _ in range(50):
        step = (math.log(a) - _digamma(a) - s) / (1.0 / a - _trigamma(a))
        a_new = a - step
        a = a_new if a_new > 0 else a / 2.0
        if abs(step) <= 1e-13 * a:
            break
    return a, m / a


def gamma_ppf(quantile: float, a: float, scale: float) -> float:
    """The ``quantile`` (0 < quantile < 1) of Gamma(a, scale).

    Newton's method on P(a, x) = quantile, kept inside a bracket that
    bisection shrinks whenever a Newton step would leave it (P is
    increasing in x, so the root is unique).
    """
    if not 0.0 < quantile < 1.0:
        raise ValueError(f"quantile must lie in (0, 1), got {quantile}")
    lo, hi = 0.0, max(a, 1.0)
    while _gammainc(a, hi) < quantile:
        lo, hi = hi, 2.0 * hi
    lgam = math.lgamma(a)
    # P(a, x) ~ x^a / (a Gamma(a)) for small x: a start in the far left tail, where halving would take long
    x = math.exp((math.log(quantile) + math.log(a) + lgam) / a)
    if not lo < x < hi:
        x = 0.5 * (lo + hi)
    for _ in range(200):
        f = _gammainc(a, x) - quantile
        if f == 0.0:
            break
        if f < 0:
            lo = x
        else:
            hi = x
        dens = math.exp((a - 1.0) * math.log(x) - x - lgam)
        x_new = x - f / dens if dens > 0 else 0.5 * (lo + hi)
        if not lo < x_new < hi:
            x_new = 0.5 * (lo + hi)
        if abs(x_new - x) <= 1e-15 * x_new:
            x = x_new
            break
        x = x_new
    return x * scale


def gamma_pdf(x: np.ndarray, a: float, scale: float) -> np.ndarray:
    """Density of Gamma(a, scale) at x (N,) >= 0."""
    x = np.asarray(x, dtype=np.float64)
    with np.errstate(divide="ignore"):
        logp = (a - 1.0) * np.log(x) - x / scale - math.lgamma(a) - a * math.log(scale)
    return np.exp(logp)
