"""The gravity ('up') vector of a tracker's level, checked (Paper III (27)).

Low in the package so that the instruments (:mod:`torchcal.models.sensor_rig`,
:mod:`torchcal.measure.sts`) and the sensor CSV reader
(:mod:`torchcal.io.sensor_csv`, which re-exports these names) share it.
"""

from __future__ import annotations

import torch

from ..core.exceptions import ConfigError

GRAVITY_TOL = 1e-6
"""How far from 1 the norm of a configured gravity vector may be."""


class GravityError(ConfigError):
    """A configured gravity vector that is not a unit vector with positive z (Paper III (27))."""


def gravity_from_xy(g_xy: torch.Tensor) -> torch.Tensor:
    """Paper III (27): (..., 2) (g_x, g_y) -> (..., 3) unit vector (g_x, g_y, sqrt(1 - g_x^2 - g_y^2)).

    The vector is the 'up' direction of the level (z component positive); |g_xy| must stay below 1.
    """
    gz2 = (1.0 - (g_xy * g_xy).sum(-1)).clamp(min=1e-12)
    return torch.cat([g_xy, torch.sqrt(gz2)[..., None]], -1)


def check_gravity(g, where: str, tol: float = GRAVITY_TOL) -> torch.Tensor:
    """A gravity ('up') vector in the tracker frame, checked: (3,) float64, unit within ``tol``, z > 0.

    where: what to name in the message (config key, file). Paper III (27)
    parameterizes g by (g_x, g_y) with g_z = +sqrt(1 - g_x^2 - g_y^2): a
    tracker standing upright. Raises :class:`GravityError` naming ``where``.

    Example:
        >>> check_gravity([0.0, 0.6, 0.8], "config 'gravity'").tolist()
        [0.0, 0.6, 0.8]
    """
    try:
        t = torch.as_tensor(g, dtype=torch.float64).flatten().cpu()
    except (TypeError, ValueError, RuntimeError):
        raise GravityError(f"{where}: gravity must be three numbers (g_x, g_y, g_z), got {g!r}") from None
    if t.numel() != 3 or not bool(torch.isfinite(t).all()):
        raise GravityError(f"{where}: gravity must be three finite numbers (g_x, g_y, g_z), got {t.tolist()}")
    norm = float(t.norm())
    if abs(norm - 1.0) > tol:
        raise GravityError(f"{where}: gravity {t.tolist()} is not normalized (norm {norm:.9g}, tolerance {tol:g}); "
                           f"give the unit vector, e.g. {[round(v, 9) for v in (t / norm).tolist()] if norm > 0 else [0.0, 0.0, 1.0]}")
    if not float(t[2]) > 0:
        raise GravityError(f"{where}: gravity {t.tolist()} must point up the tracker's z axis (g_z > 0, Paper III (27))")
    return t


__all__ = ["GRAVITY_TOL", "GravityError", "check_gravity", "gravity_from_xy"]
