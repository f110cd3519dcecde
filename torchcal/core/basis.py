"""Chebyshev series on a normalized range, Paper II (21)-(24) and Paper I (2)-(7).

A joint value q in [q_min, q_max] maps to lam = 2 (q - q_min) / (q_max - q_min) - 1
in [-1, 1] (24); the basis is c_0 = 1, c_1 = lam, c_{k+1} = 2 lam c_k - c_{k-1} (22).
"""

from __future__ import annotations

import torch


def normalize(q: torch.Tensor, lower: torch.Tensor, upper: torch.Tensor) -> torch.Tensor:
    """Map q from [lower, upper] to [-1, 1], eq. (24).  Broadcasts; (...,) -> (...,)."""
    return 2.0 * (q - lower) / (upper - lower) - 1.0


def chebyshev(lam: torch.Tensor, order: int) -> torch.Tensor:
    """Chebyshev polynomials c_0..c_order at lam.  (...,) -> (..., order + 1)."""
    out = [torch.ones_like(lam)]
    if order >= 1:
        out.append(lam)
    for _ in range(2, order + 1):
        out.append(2.0 * lam * out[-1] - out[-2])
    return torch.stack(out, -1)


def chebyshev_with_derivative(lam: torch.Tensor, order: int):
    """Values and d/dlam of c_0..c_order.  (...,) -> two (..., order + 1).

    Uses the same three-term recurrence differentiated, which stays exact at lam = +-1.
    """
    c = [torch.ones_like(lam)]
    d = [torch.zeros_like(lam)]
    if order >= 1:
        c.append(lam)
        d.append(torch.ones_like(lam))
    for _ in range(2, order + 1):
        c.append(2.0 * lam * c[-1] - c[-2])
        d.append(2.0 * c[-2] + 2.0 * lam * d[-1] - d[-2])
    return torch.stack(c, -1), torch.stack(d, -1)


def series(coef: torch.Tensor, basis: torch.Tensor) -> torch.Tensor:
    """Evaluate sum_k coef[..., k] c_k; coef (..., m + 1) and basis (..., m + 1) broadcast -> (...)."""
    return (coef * basis).sum(-1)
