"""Closed-form Jacobians of the error model: the paper's (34)-(45) and (56)-(77), generalized.

Autograd gives the same numbers (the tests check it against ``torch.func``),
but a per-row forward-mode Jacobian costs ~50x a forward pass, while these
need only the joint frames the forward pass already computed. Every function
is pure and batched; shapes in the docstrings.

Conventions: a *twist* e = (eps, delta) parametrizes E = [exp(S(eps)), delta];
a 6-row pose Jacobian stacks the linear velocity of a point (rows 0-2) over
the angular velocity (rows 3-5), both in the chain's root (measurement) frame.
"""

from __future__ import annotations

import torch

from ..core.basis import chebyshev_with_derivative
from ..kinematics.transforms import skew, small_matmul, so3_exp


def so3_right_jacobian(w: torch.Tensor) -> torch.Tensor:
    """Right Jacobian J_r of SO(3): exp(S(w + dw)) = exp(S(w)) exp(S(J_r(w) dw)) + O(dw^2).  (..., 3) -> (..., 3, 3)."""
    t2 = (w * w).sum(-1)
    small = t2 < 1e-8
    t2s = torch.where(small, torch.ones_like(t2), t2)
    t = torch.sqrt(t2s)
    a = torch.where(small, 0.5 - t2 / 24.0, (1.0 - torch.cos(t)) / t2s)
    b = torch.where(small, 1.0 / 6.0 - t2 / 120.0, (t - torch.sin(t)) / (t2s * t))
    K = skew(w)
    eye = torch.eye(3, dtype=w.dtype, device=w.device)
    return eye - a[..., None, None] * K + b[..., None, None] * small_matmul(K, K)


def twist_jacobian(frame_R: torch.Tensor, frame_p: torch.Tensor, twist: torch.Tensor, point: torch.Tensor,
                   rotation: torch.Tensor | None = None) -> torch.Tensor:
    """Pose Jacobian w.r.t. the twist of an error transform E sitting just before a frame.

    frame_R: (..., 3, 3), frame_p: (..., 3): the frame *after* E (world);
    twist: (..., 6) current value of E's twist; point: (..., 3) world point
    carried by the chain after E; rotation: (..., 3, 3) E's rotation exp(S(eps)) where the caller has it
    (None: computed here; a small batch's linearization is mostly such fixed costs).
    -> (..., 6, 6): d(point velocity; angular velocity) / d(eps, delta).
    """
    Jr = so3_right_jacobian(twist[..., :3])
    RJ = small_matmul(frame_R, Jr)
    if rotation is None:
        rotation = so3_exp(twist[..., :3])
    R_before = small_matmul(frame_R, rotation.transpose(-1, -2))
    lin_eps = -small_matmul(skew(point - frame_p), RJ)
    top = torch.cat([lin_eps, R_before], -1)
    bottom = torch.cat([RJ, torch.zeros_like(RJ)], -1)
    return torch.cat([top, bottom], -2)


def joint_axis_jacobian(joint_R: torch.Tensor, joint_p: torch.Tensor, axes: torch.Tensor, prismatic: torch.Tensor, point: torch.Tensor) -> torch.Tensor:
    """Pose Jacobian w.r.t. the joint variables with the error terms held fixed.

    joint_R: (B, n, 3, 3), joint_p: (B, n, 3) joint frames; axes: (n, 3);
    prismatic: (n,); point: (B, 3). -> (B, 6, n).
    """
    z = small_matmul(joint_R, axes[:, :, None])[..., 0]
    lin = torch.where(prismatic[None, :, None], z, torch.linalg.cross(z, point[:, None, :] - joint_p, dim=-1))
    ang = torch.where(prismatic[None, :, None], torch.zeros_like(z), z)
    return torch.cat([lin, ang], -1).transpose(1, 2)


def chebyshev_design(lam: torch.Tensor, K: int, scale: torch.Tensor):
    """Basis values and their derivative w.r.t. the joint variable.

    lam: (B, n) normalized joint variables; K: number of coefficients;
    scale: (n,) d lam / d theta. -> basis, dbasis: (B, n, K).
    """
    c, d = chebyshev_with_derivative(lam, max(K - 1, 0))
    return c[..., :K], d[..., :K] * scale[:, None]
