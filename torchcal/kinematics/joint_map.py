"""Controller joint commands <-> URDF joint variables.

Controllers do not always command the URDF's joint variables: the FANUC
controller's J3 is the forearm angle against the horizon, so the URDF (DH)
joint 3 turns by ``q2 + q3`` (Paper II, Table 2). A :class:`JointMap` is the
affine map ``θ = A q + offset`` between the two, plus the controller's joint
limits (the measured range of Table 3), all in SI inside torchcal.

It also says on which variable each joint's error terms depend
(``error_variable``): Paper II (23)-(24) evaluates E_i's Chebyshev series on the
normalized joint *command* q_i over the command range, because the gear of
joint i turns with the command q_i (on the FANUC, J3's gear turns with q3 even
though the DH angle is θ3 = q2 + q3). ``'command'`` is that reading and the
default; ``'joint'`` evaluates them on the URDF joint variable θ_i over its
range (what torchcal did before; old run directories load so).
"""

from __future__ import annotations

from dataclasses import dataclass, field

import torch

ERROR_VARIABLES = ("command", "joint")
"""Where a joint's error terms are evaluated: the controller command q_i (Paper II (24)) or the URDF θ_i."""


@dataclass
class JointMap:
    """θ = coupling @ q + offset, in SI (rad / m) on both sides.

    names: controller joint names (column headers use q1..qN regardless).
    coupling: (n, n) invertible; offset: (n,); limits: (n, 2) controller range;
    prismatic: (n,) bool, whether each controller joint is linear (mm in files);
    error_variable: per joint 'command' (default, Paper II (24)) or 'joint'; a
    single string applies to every joint.
    """

    names: list[str]
    coupling: torch.Tensor
    offset: torch.Tensor
    limits: torch.Tensor
    prismatic: torch.Tensor
    error_variable: list[str] | str = field(default="command")

    def __post_init__(self):
        n = len(self.names)
        self.error_variable = normalize_error_variable(self.error_variable, n, self.names)
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
        return JointMap(self.names, self.coupling.to(device), self.offset.to(device), self.limits.to(device),
                        self.prismatic.to(device), list(self.error_variable))

    def with_error_variable(self, error_variable) -> "JointMap":
        """The same map with another error variable ('command', 'joint' or a per-joint list)."""
        return JointMap(self.names, self.coupling, self.offset, self.limits, self.prismatic, error_variable)

    def follows_joint(self) -> torch.Tensor:
        """(n,) bool: joints whose error terms follow the URDF joint variable θ_i."""
        return torch.tensor([e == "joint" for e in self.error_variable], dtype=torch.bool, device=self.coupling.device)

    def error_map(self):
        """u = A_u q + b_u, the variable each joint's error series is evaluated on.

        -> A_u (n, n), b_u (n,): row i is the identity row (command) or the
        coupling row with its offset (joint).
        """
        m = self.follows_joint()
        eye = torch.eye(self.n, dtype=self.coupling.dtype, device=self.coupling.device)
        A = torch.where(m[:, None], self.coupling, eye)
        b = torch.where(m, self.offset, torch.zeros_like(self.offset))
        return A, b

    def error_ranges(self) -> torch.Tensor:
        """(n, 2) range of each joint's error variable: the command limits, or the URDF variable's range."""
        return torch.where(self.follows_joint()[:, None], self.joint_ranges(), self.limits)

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


def normalize_error_variable(value, n: int, names=None) -> list[str]:
    """'command' / 'joint' / a per-joint list -> a list of n strings, or ValueError naming the joint."""
    if isinstance(value, str):
        value = [value] * n
    value = list(value)
    if len(value) != n:
        raise ValueError(f"error_variable: expected one entry per joint ({n}), got {len(value)}")
    for i, v in enumerate(value):
        if v not in ERROR_VARIABLES:
            name = names[i] if names else f"joint {i + 1}"
            raise ValueError(f"error_variable of '{name}': {v!r} is not one of {ERROR_VARIABLES}")
    return [str(v) for v in value]
