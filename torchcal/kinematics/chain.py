"""A serial chain as per-joint float64 tensors (the nominal machine, no error terms)."""

from __future__ import annotations

from dataclasses import dataclass, field

import torch

from .fk import chain_fk, chain_frames


@dataclass
class Chain:
    """Nominal serial chain, SI units, float64.

    joint_names: movable joints from root to tip.
    origins: (n, 4, 4) parent-link frame -> joint frame (fixed joints folded in).
    axes: (n, 3) unit joint axes in the joint frame.
    prismatic: (n,) bool.
    limits: (n, 2) lower/upper joint limits (rad or m); NaN where the URDF has none.
    tip: (4, 4) transform from the last joint's child link to ``end_link``.
    """

    joint_names: list[str]
    origins: torch.Tensor
    axes: torch.Tensor
    prismatic: torch.Tensor
    limits: torch.Tensor
    tip: torch.Tensor
    root_link: str = ""
    end_link: str = ""
    name: str = ""
    link_names: list[str] = field(default_factory=list)

    @property
    def n(self) -> int:
        """Number of movable joints."""
        return len(self.joint_names)

    @property
    def device(self) -> torch.device:
        return self.origins.device

    @property
    def dtype(self) -> torch.dtype:
        return self.origins.dtype

    def to(self, device=None, dtype=None) -> "Chain":
        """A copy on another device / dtype (float64 stays the default)."""
        def mv(t):
            return t.to(device=device, dtype=dtype if t.is_floating_point() else None)

        return Chain(
            self.joint_names, mv(self.origins), mv(self.axes), self.prismatic.to(device), mv(self.limits), mv(self.tip),
            self.root_link, self.end_link, self.name, list(self.link_names),
        )

    def fk(self, theta: torch.Tensor, joint_errors: torch.Tensor | None = None) -> torch.Tensor:
        """End-link pose in the root frame.  theta: (B, n) rad/m -> (B, 4, 4)."""
        return chain_fk(self.origins, self.axes, self.prismatic, theta, joint_errors, self.tip)

    def frames(self, theta: torch.Tensor, joint_errors: torch.Tensor | None = None, base: torch.Tensor | None = None):
        """Joint frames and end pose, see :func:`torchcal.kinematics.fk.chain_frames`."""
        return chain_frames(self.origins, self.axes, self.prismatic, theta, joint_errors, self.tip, base)
