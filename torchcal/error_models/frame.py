"""Static frame errors: the measurement-frame/base correction (26) and tool vectors (27)."""

from __future__ import annotations

import torch
from torch import nn

from ..kinematics.transforms import twist_to_transform
from ..core.params import LENGTH, ParamGroup, term_kinds


class FrameCorrection(nn.Module):
    """A fixed frame with a small 6-DOF correction: ``T = nominal @ E(b)``, Paper II (26), (28).

    nominal: (4, 4) first guess (identity when the measurement frame is the
    robot base, as the papers assume); b = (eps_x, eps_y, eps_z, delta_x,
    delta_y, delta_z) in rad / m, applied on the robot side so that a far
    tracker does not couple its rotation with large lever arms.
    """

    NAMES = ("eps_x", "eps_y", "eps_z", "delta_x", "delta_y", "delta_z")

    def __init__(self, nominal: torch.Tensor | None = None):
        super().__init__()
        if nominal is None:
            nominal = torch.eye(4, dtype=torch.float64)
        self.register_buffer("nominal", nominal.to(torch.float64).clone())
        self.twist = nn.Parameter(torch.zeros(6, dtype=torch.float64))

    def forward(self) -> torch.Tensor:
        """The corrected transform (4, 4)."""
        return self.nominal @ twist_to_transform(self.twist)

    def correction(self) -> torch.Tensor:
        """E(b) alone (4, 4): the base correction seen from the robot's nominal base frame."""
        return twist_to_transform(self.twist)

    def param_groups(self, prefix: str = "base") -> list[ParamGroup]:
        """``twist``: 3 angles (prior 0.1 rad) then 3 lengths (prior 10 mm)."""
        return [ParamGroup(f"{prefix}.twist", "frame", [f"{prefix}.{t}" for t in self.NAMES], term_kinds(self.NAMES),
                           torch.tensor([0.1] * 3 + [1e-2] * 3, dtype=torch.float64), torch.ones(6, dtype=torch.bool))]


class ToolSet(nn.Module):
    """Tool vectors p_T,t = l_t + delta_t for any number of tool configurations, (27), (29).

    nominal: (T, 3) estimated tool vectors in the flange frame, metres.
    """

    def __init__(self, nominal: torch.Tensor):
        super().__init__()
        nominal = torch.as_tensor(nominal, dtype=torch.float64)
        if nominal.ndim != 2 or nominal.shape[1] != 3:
            raise ValueError(f"tool vectors must have shape (T, 3), got {tuple(nominal.shape)}")
        self.register_buffer("nominal", nominal.clone())
        self.delta = nn.Parameter(torch.zeros_like(nominal))

    @property
    def count(self) -> int:
        return self.nominal.shape[0]

    def forward(self) -> torch.Tensor:
        """Corrected tool vectors (T, 3)."""
        return self.nominal + self.delta

    def param_groups(self, prefix: str = "tools") -> list[ParamGroup]:
        """``delta``: lengths, prior 10 mm, named 'tool{t}.d{x,y,z}'."""
        k = self.delta.numel()
        return [ParamGroup(f"{prefix}.delta", "tool", [f"tool{t}.d{a}" for t in range(self.count) for a in "xyz"],
                           [LENGTH] * k, torch.full((k,), 1e-2, dtype=torch.float64), torch.ones_like(self.delta, dtype=torch.bool))]
