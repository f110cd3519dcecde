"""A calibrated serial chain, frozen: everything a fast forward-kinematics backend needs, detached from autograd.

Forward kinematics has one definition, :func:`torchcal.kinematics.fk.chain_frames` (Π origin_i · E_i ·
joint_i(θ_i)), which the models use for identification: (B, 4, 4) tensors, differentiable in every
parameter. Compensation evaluates only the flange, a handful of times per pose, for millions of poses, and
needs no gradients; its backends (:class:`torchcal.compensate.kernel.FlangeKernel`, torch ops in the
pose-last layout, and :mod:`torchcal.compensate.fused`, the same compiled with numba) compute the same
product from this snapshot. A model hands one out (``RobotModel.flange_snapshot()``, the model contract's
:class:`~torchcal.core.contract.CompensatesCommands`): the backends never read a model's internals, and a
snapshot cannot change under them (it is frozen and its tensors are copies).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import torch


@dataclass(frozen=True)
class ChainSnapshot:
    """One robot chain with its joint-dependent errors, Paper II (19)-(25), as detached tensors.

    n joints, K Chebyshev terms of the six error series, Kb backlash terms (0: none):

    - coupling (n, n), offset (n,): controller command q -> URDF joint variable θ = coupling q + offset
    - error_coupling (n, n), error_offset (n,): q -> the error series' variable u (Paper II (24): the command)
    - ranges (n, 2): the interval of u each series is normalized on (λ = 2 (u - lo) / (hi - lo) - 1)
    - coef (n, 6, K): series coefficients of (ε_x, ε_y, ε_z, δ_x, δ_y, δ_z), masked (fixed terms are zero)
    - backlash (n, Kb) or None: the backlash amplitude's series, masked; it adds s_i · Δq_ib(u_i) times
      ``backlash_screw`` (n, 6) to the six terms (13): the turn about (move along) the joint's own axis, ε_z for
      a joint about +z (None: ε_z for every joint)
    - origins (n, 4, 4), axes (n, 3), prismatic (n,) bool: the nominal chain (URDF joint origins and axes)
    - tip (4, 4): last joint frame -> flange; base (4, 4): the identified base correction E_base (26)
    - live: a model whose modeled flange the backends must evaluate by itself (gravity compliance or fine
      joint tables: deflections that depend on the whole configuration), else None

    Example:
        >>> import torch, torchcal
        >>> model = torchcal.RobotModel(torchcal.load_robot("fanuc_lrmate200i"), torch.zeros(1, 3, dtype=torch.float64))
        >>> snap = model.flange_snapshot()
        >>> snap.n, tuple(snap.coef.shape), snap.coef.requires_grad
        (6, (6, 6, 7), False)
    """

    coupling: torch.Tensor
    offset: torch.Tensor
    error_coupling: torch.Tensor
    error_offset: torch.Tensor
    ranges: torch.Tensor
    coef: torch.Tensor
    backlash: torch.Tensor | None
    origins: torch.Tensor
    axes: torch.Tensor
    prismatic: torch.Tensor
    tip: torch.Tensor
    base: torch.Tensor
    live: Any = None
    backlash_screw: torch.Tensor | None = None

    @property
    def n(self) -> int:
        return int(self.axes.shape[0])

    @property
    def dtype(self) -> torch.dtype:
        return self.origins.dtype

    @property
    def device(self) -> torch.device:
        return self.origins.device


__all__ = ["ChainSnapshot"]
