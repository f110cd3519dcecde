"""First guesses of the two frames of a 6-DOF measurement loop, from the data alone (no guess needed).

A sensor (or probe) on the flange, measured by a tracker, closes the loop

    T_i = X F(q_i) M            (Paper III (13), (16), errors left out)

with X the robot base in the tracker frame and M the flange -> sensor mount.
This is the robot-world / hand-eye problem. Its closed-form solution here:
relative motions T_i T_j^-1 = X (F_i F_j^-1) X^-1 share their rotation axes
up to R_X (Kabsch on the rotation vectors); R_M is the nearest rotation to
Σ R_Fi^T R_X^T R_Ti; the translations follow from one linear least-squares
problem. The identification then refines both (base and mount corrections).
"""

from __future__ import annotations

import torch

from ..core.exceptions import TorchcalError
from ..measure.pose import rotation_log
from .alignment import kabsch


class HandEyeError(TorchcalError, ValueError):
    """The poses cannot determine the frames (too few, or motions about one axis only)."""


def _nearest_rotation(M: torch.Tensor) -> torch.Tensor:
    U, _, Vh = torch.linalg.svd(M)
    d = torch.sign(torch.linalg.det(U @ Vh))
    D = torch.diag(torch.stack([torch.ones_like(d), torch.ones_like(d), d]))
    return U @ D @ Vh


def hand_eye(F: torch.Tensor, T: torch.Tensor, pairs: int = 8000, seed: int = 0, X: torch.Tensor | None = None,
             M: torch.Tensor | None = None) -> tuple[torch.Tensor, torch.Tensor]:
    """Solve T_i ≈ X F_i M for X (tracker <- base) and M (flange -> sensor).  (N, 4, 4) twice -> (4, 4), (4, 4).

    F: modeled flange poses in the robot base frame; T: measured sensor poses in
    the tracker frame; pairs: random pose pairs (seeded) whose relative
    rotations (0.2-2.9 rad, well-conditioned axes) give R_X; X or M: a known
    frame (only the other one is solved for).

    Example:
        >>> import torch
        >>> from torchcal.kinematics.transforms import homogeneous, rpy_to_matrix
        >>> g = torch.Generator().manual_seed(0)
        >>> F = homogeneous(rpy_to_matrix(torch.rand(50, 3, generator=g, dtype=torch.float64) * 3),
        ...                 torch.rand(50, 3, generator=g, dtype=torch.float64))
        >>> X = homogeneous(rpy_to_matrix(torch.tensor([0.1, -0.2, 2.0], dtype=torch.float64)),
        ...                 torch.tensor([2.0, 0.5, -0.3], dtype=torch.float64))
        >>> M = homogeneous(rpy_to_matrix(torch.tensor([3.1, 0.0, 0.3], dtype=torch.float64)),
        ...                 torch.tensor([0.0, 0.016, 0.1], dtype=torch.float64))
        >>> Xe, Me = hand_eye(F, X @ F @ M)
        >>> bool(torch.allclose(Xe, X, atol=1e-9) and torch.allclose(Me, M, atol=1e-9))
        True
    """
    if F.shape != T.shape or F.ndim != 3 or F.shape[1:] != (4, 4):
        raise ValueError(f"hand_eye: F and T must both be (N, 4, 4), got {tuple(F.shape)} and {tuple(T.shape)}")
    N = F.shape[0]
    if N < 3:
        raise HandEyeError(f"hand_eye: {N} poses cannot determine the tracker frame and the mount (need >= 3)")
    RF, pF, RT, pT = F[:, :3, :3], F[:, :3, 3], T[:, :3, :3], T[:, :3, 3]
    eye = torch.eye(4, dtype=F.dtype, device=F.device)
    if X is not None and M is not None:
        return X.to(F), M.to(F)
    if X is None and M is None:
        g = torch.Generator().manual_seed(seed)
        i, j = torch.randint(N, (pairs,), generator=g), torch.randint(N, (pairs,), generator=g)
        i, j = i.to(F.device), j.to(F.device)
        a = rotation_log(RT[i] @ RT[j].transpose(1, 2))
        b = rotation_log(RF[i] @ RF[j].transpose(1, 2))
        keep = (b.norm(dim=1) > 0.2) & (b.norm(dim=1) < 2.9)
        if int(keep.sum()) < 3:
            raise HandEyeError("hand_eye: the poses rotate too little (or only by ~180°) to determine the frames")
        sv = torch.linalg.svdvals(b[keep])
        if sv[1] < 1e-3 * sv[0]:
            # the flange's turns, not the joints: a program can move every joint a lot and still turn the flange
            # about one direction only (a planar wrist pattern; the UR10's Series D)
            raise HandEyeError("hand_eye: between the poses the flange only turns about one direction, which leaves "
                               "the tracker frame's turn about it (and so the mount's) unknown; measure poses that also "
                               "tilt the tool (other wrist orientations), or give measurement_frame or sensor.mount")
        RX, _ = kabsch(b[keep], a[keep])
        RM = _nearest_rotation((RF.transpose(1, 2) @ RX.T @ RT).sum(0))
        A = torch.cat([RX @ RF, torch.eye(3, dtype=F.dtype, device=F.device).expand(N, 3, 3)], 2).reshape(-1, 6)
        y = (pT - pF @ RX.T).reshape(-1)
        sol = torch.linalg.lstsq(A, y[:, None]).solution[:, 0]
        Xo, Mo = eye.clone(), eye.clone()
        Xo[:3, :3], Xo[:3, 3], Mo[:3, :3], Mo[:3, 3] = RX, sol[3:], RM, sol[:3]
        return Xo, Mo
    if M is None:  # X known: M_i = F_i^-1 X^-1 T_i, averaged on SO(3) and R^3
        Mi = torch.linalg.inv(F) @ torch.linalg.inv(X).to(F) @ T
        Mo = eye.clone()
        Mo[:3, :3], Mo[:3, 3] = _nearest_rotation(Mi[:, :3, :3].sum(0)), Mi[:, :3, 3].mean(0)
        return X.to(F), Mo
    Xi = T @ torch.linalg.inv(M).to(F) @ torch.linalg.inv(F)
    Xo = eye.clone()
    Xo[:3, :3], Xo[:3, 3] = _nearest_rotation(Xi[:, :3, :3].sum(0)), Xi[:, :3, 3].mean(0)
    return Xo, M.to(F)
