"""The one place where industry units meet SI.

Files, configs and the CLI speak millimetres and degrees (the calibration
engineer's units); everything inside torchcal, like every URDF, is SI: metres
and radians. Convert here and nowhere else.
"""

from __future__ import annotations

import math

import torch

MM = 1e-3
"""Metres per millimetre."""

DEG = math.pi / 180.0
"""Radians per degree."""


def mm_to_m(x):
    """Millimetres to metres (tensor, array or float)."""
    return x * MM


def m_to_mm(x):
    """Metres to millimetres (tensor, array or float)."""
    return x / MM


def deg_to_rad(x):
    """Degrees to radians (tensor, array or float)."""
    return x * DEG


def rad_to_deg(x):
    """Radians to degrees (tensor, array or float)."""
    return x / DEG


def joint_scale(prismatic) -> torch.Tensor:
    """SI units per file unit for each joint: DEG for revolute, MM for prismatic.

    prismatic: (n,) bool. Returns (n,) float64.
    """
    prismatic = torch.as_tensor(prismatic, dtype=torch.bool)
    return torch.where(prismatic, torch.tensor(MM, dtype=torch.float64), torch.tensor(DEG, dtype=torch.float64))


def joints_to_si(q, prismatic):
    """Joint values in file units (deg / mm) to SI (rad / m). q: (..., n)."""
    q = torch.as_tensor(q, dtype=torch.float64)
    return q * joint_scale(prismatic).to(q.device)


def joints_from_si(q, prismatic):
    """Joint values in SI (rad / m) to file units (deg / mm). q: (..., n)."""
    return q / joint_scale(prismatic).to(q.device)


def joint_unit_names(prismatic) -> list[str]:
    """'deg' or 'mm' per joint, for messages and headers."""
    return ["mm" if bool(p) else "deg" for p in prismatic]


PER_NEWTON_METRE = ".tau"
"""Parameter entries named ``*.tau`` (gravity compliance, :mod:`torchcal.error_models.compliance` 'gravity' mode)
are a deflection per N·m of joint torque: their kind is an angle, their unit deg / (N·m)."""


def entry_unit(kind: str, name: str = "") -> str:
    """The file / report unit of a parameter entry of ``kind`` ('angle' -> 'deg', 'length' -> 'mm', else '1'), per
    N·m for a compliance per torque (:data:`PER_NEWTON_METRE`; it read 'deg' in parameters.csv and the report)."""
    base = {"angle": "deg", "length": "mm"}.get(kind, "1")
    return f"{base}/(N·m)" if name.endswith(PER_NEWTON_METRE) and base != "1" else base
