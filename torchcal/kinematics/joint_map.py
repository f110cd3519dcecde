"""Controller joint commands <-> URDF joint variables.

Controllers do not always command the URDF's joint variables: the FANUC
controller's J3 is the forearm angle against the horizon, so the URDF (DH)
joint 3 turns by ``q2 + q3`` (Paper II, Table 2). A :class:`JointMap` is the
affine map ``θ = A q + offset`` between the two, plus the controller's joint
limits (the measured range of Table 3), all in SI inside torchcal.
"""

from __future__ import annotations

from dataclasses import dataclass

import torch


@dataclass
class JointMap:
    """θ = coupling @ q + offset, in SI (rad / m) on both sides.

    names: controller joint names (column headers use q1..qN regardless).
    coupling: (n, n) invertible; offset: (n,); limits: (n, 2) controller range;
    prismatic: (n,) bool, whether each controller joint is linear (mm in files).
    """

    names: list[str]
    coupling: torch.Tensor
    offset: torch.Tensor
    limits: torch.Tensor
    prismatic: torch.Tensor

    def __post_init__(self):
        n = len(self.names)
        if self.coupling.shape != (n, n) or self.offset.shape != (n,) or self.limits.shape != (n, 2):
            raise ValueError(
                f"joint map: shapes do not match {n} joints (coupling {tuple(self.coupling.shape)}, "
                f"offset {tuple(self.offset.shape)}, limits {tuple(self.limits.shape)})"
            )
        if torch.linalg.matrix_rank(self.coupling) < n:
            raise ValueError("joint map: coupling matrix is singular")
        bad = ~(self.limits[:, 0] < self.limits[:, 1])
        if bad.any():
            i = int(bad.nonzero()[0])
            raise ValueError(f"joint map: joint '{self.names[i]}' lower limit is not below its upper limit")

    @property
    def n(self) -> int:
        return len(self.names)

    @classmethod
    def identity(cls, limits: torch.Tensor, prismatic: torch.Tensor, names: list[str] | None = None) -> "JointMap":
        """A controller that commands the URDF joints directly."""
        n = limits.shape[0]
        return cls(
            names or [f"q{i + 1}" for i in range(n)],
            torch.eye(n, dtype=torch.float64),
            torch.zeros(n, dtype=torch.float64),
            limits.to(torch.float64),
            torch.as_tensor(prismatic, dtype=torch.bool),
        )

    def to(self, device=None) -> "JointMap":
        return JointMap(self.names, self.coupling.to(device), self.offset.to(device), self.limits.to(device), self.prismatic.to(device))

    def to_joint(self, q: torch.Tensor) -> torch.Tensor:
        """Controller commands (..., n) -> URDF joint variables (..., n)."""
        return q @ self.coupling.T.to(q) + self.offset.to(q)

    def to_command(self, theta: torch.Tensor) -> torch.Tensor:
        """URDF joint variables (..., n) -> controller commands (..., n)."""
        return torch.linalg.solve(self.coupling.to(theta), (theta - self.offset.to(theta)).T).T

    def joint_ranges(self) -> torch.Tensor:
        """Range (n, 2) of each URDF joint variable over the controller's limit box."""
        lo, hi = self.limits[:, 0], self.limits[:, 1]
        A = self.coupling
        low = torch.where(A > 0, A * lo, A * hi).sum(1) + self.offset
        high = torch.where(A > 0, A * hi, A * lo).sum(1) + self.offset
        return torch.stack([low, high], 1)

    def within_limits(self, q: torch.Tensor, tol: float = 1e-9) -> torch.Tensor:
        """(..., n) bool: each command inside the controller range."""
        lim = self.limits.to(q)
        return (q >= lim[:, 0] - tol) & (q <= lim[:, 1] + tol)
