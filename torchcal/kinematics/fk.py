"""Batched forward kinematics and geometric Jacobians of a serial chain (pure functions).

The chain is ``Π_i origin_i · E_i · joint_i(θ_i)`` followed by a fixed tip
transform: ``origin_i`` is the URDF joint origin, ``E_i`` the paper's error
transform (19)-(20) placed in the joint frame before the joint moves (identity
for the nominal chain), and ``joint_i`` the rotation about (or translation
along) the joint axis. Rotations and translations are carried separately
because (B, 3, 3) / (B, 3) products cost less than (B, 4, 4) ones.
"""

from __future__ import annotations

import torch

from .transforms import axis_angle_to_matrix, homogeneous, small_matmul


def joint_motion(axes: torch.Tensor, prismatic: torch.Tensor, theta: torch.Tensor):
    """Rotation and translation of each joint's own motion.

    axes: (n, 3) unit; prismatic: (n,) bool; theta: (B, n)
    -> R: (B, n, 3, 3), p: (B, n, 3)
    """
    R = axis_angle_to_matrix(axes.expand(theta.shape + (3,)), torch.where(prismatic, 0.0, theta))
    p = axes * torch.where(prismatic, theta, 0.0)[..., None]
    return R, p


def chain_frames(
    origins: torch.Tensor,
    axes: torch.Tensor,
    prismatic: torch.Tensor,
    theta: torch.Tensor,
    joint_errors: torch.Tensor | None = None,
    tip: torch.Tensor | None = None,
    base: torch.Tensor | None = None,
):
    """Joint frames and end pose of a serial chain.

    origins: (n, 4, 4); axes: (n, 3); prismatic: (n,) bool; theta: (B, n)
    joint_errors: (B, n, 4, 4) or (n, 4, 4) error transforms E_i, or None
    tip: (4, 4) fixed transform after the last joint, or None
    base: (4, 4) or (B, 4, 4) transform applied in front of the chain, or None
    -> joint_R: (B, n, 3, 3) and joint_p: (B, n, 3), the frame in which joint i
       moves (after origin_i · E_i, before joint_i), and end: (B, 4, 4).
    """
    B, n = theta.shape
    dtype, device = theta.dtype, theta.device
    mR, mp = joint_motion(axes, prismatic, theta)
    if base is None:
        R = torch.eye(3, dtype=dtype, device=device).expand(B, 3, 3)
        p = torch.zeros(B, 3, 1, dtype=dtype, device=device)
    else:
        base = base.expand(B, 4, 4)
        R, p = base[:, :3, :3], base[:, :3, 3:]
    # every per-joint operand split off once (one unbind each): a small batch's chain is mostly per-op cost, and
    # indexing inside the loop was a third of its ops. Translations are carried as (B, 3, 1) columns.
    oR, op = origins[:, :3, :3].unbind(0), origins[:, :3, 3:].unbind(0)
    mRs, mps = mR.unbind(1), mp[..., None].unbind(1)
    if joint_errors is not None:
        ERs, Eps = joint_errors[..., :3, :3].unbind(-3), joint_errors[..., :3, 3:].unbind(-3)
    frames_R, frames_p = [], []
    for i in range(n):
        p = p + R @ op[i]
        R = R @ oR[i]
        if joint_errors is not None:
            p = p + small_matmul(R, Eps[i])
            R = small_matmul(R, ERs[i])
        frames_R.append(R)
        frames_p.append(p)
        p = p + small_matmul(R, mps[i])
        R = small_matmul(R, mRs[i])
    if tip is not None:
        p = p + R @ tip[:3, 3:]
        R = R @ tip[:3, :3]
    return torch.stack(frames_R, 1), torch.stack(frames_p, 1)[..., 0], homogeneous(R, p[..., 0])


def chain_fk(origins, axes, prismatic, theta, joint_errors=None, tip=None, base=None) -> torch.Tensor:
    """End pose (B, 4, 4) of the chain; arguments as in :func:`chain_frames`."""
    return chain_frames(origins, axes, prismatic, theta, joint_errors, tip, base)[2]


def geometric_jacobian(joint_R, joint_p, axes, prismatic, point) -> torch.Tensor:
    """Geometric Jacobian of a point fixed to the last link w.r.t. the joint variables.

    joint_R: (B, n, 3, 3), joint_p: (B, n, 3) from :func:`chain_frames`;
    axes: (n, 3); prismatic: (n,); point: (B, 3) in the same frame as joint_p.
    -> (B, 6, n): rows 0-2 linear velocity of the point, rows 3-5 angular
    velocity, per unit joint velocity. Error terms are held fixed (their
    slopes are not included).
    """
    z = small_matmul(joint_R, axes[:, :, None])[..., 0]  # (B, n, 3)
    lin_rev = torch.linalg.cross(z, point[:, None, :] - joint_p, dim=-1)
    pm = prismatic[None, :, None]
    lin = torch.where(pm, z, lin_rev)
    ang = torch.where(pm, torch.zeros_like(z), z)
    return torch.cat([lin, ang], -1).transpose(1, 2)
