"""Does a compensated command stay on its nominal command's branch (configuration)?

A module of its own: compensate() (newton.py, at its size limit) and compensate_targets() both ask it,
and the reading of "branch" deserves one place.

Reading. A controller names the inverse-kinematics solutions of a 6R arm by configuration flags
(shoulder front/back, elbow up/down, wrist flip/no flip). For an arm with a spherical wrist the
determinant of the flange Jacobian factors as det J = f_shoulder(q) · f_elbow(q) · sin θ5 (times a
constant sign), and each flag is the sign of one factor: the wrist flag is the sign of sin θ5, the elbow
flag that of the elbow factor, the shoulder flag that of the wrist centre's radial offset. A change of
any single flag therefore changes the sign of det J of the *controller's* (nominal) kinematics, and
two commands joined by a path on which det J keeps its sign carry the same flags. The test below
needs nothing robot-specific: the branch of q_new is q_nom's when det J_nominal keeps its sign along the
straight joint path q_nom -> q_new (sampled at ``samples`` points). It is defined for square Jacobians
(n = 6); other arms have no det J and are never reported as changed. A nominal command on a singular
surface itself (sigma_min below the solver's floor) has no flags to keep: it is not tested.

Cost: none for the rows that provably keep the sign (:func:`surely_same_branch`: a small move far from any
singular surface), one nominal Jacobian per row at q_new for the others, and ``samples`` more for the rows
whose correction is larger than ``path_above`` (10 deg). The end points decide the flags, which is what a
controller sees; the sampled path only adds a guard against large moves that pass through a surface and
back. Below 10 deg that needs a path that grazes a surface: along a straight joint path the wrist factor
(sin θ5) and the elbow factor (the sine of an affine function of θ3) each cross zero at most once within
half a turn. (A 1 deg threshold sampled 42 % of a random FANUC model's rows and cost a fifth of the whole
compensation.)
"""

from __future__ import annotations

import math

import torch

from .kernel import FlangeKernel

PATH_ABOVE = math.radians(10.0)
"""rad: corrections larger than this get the sampled path test, smaller ones the end points only."""


def det_sign_soa(J: torch.Tensor) -> torch.Tensor:
    """Sign of det J for many square matrices in the pose-last layout.  J: (n, n, B) -> (B,) in {-1, 0, +1}.

    On a GPU: Gaussian elimination with partial pivoting, elementwise over the B matrices (a few dozen
    ops over long rows): torch.linalg.det's batched LU of a million 6 x 6 matrices cost an H200 more than
    the whole compensation it guards (float32 compensation 9.5e6 -> 1.7e6 poses/s). The sign is that of
    the product of the pivots times the parity of the row swaps. On the CPU LAPACK's LU per matrix is
    faster than these elementwise passes (1e5 matrices: ~4x), so it is used there; both are exact up to
    rounding, which only matters on a singular surface, where the test is not asked.
    """
    if J.device.type == "cpu":
        return torch.sign(torch.linalg.det(J.permute(2, 0, 1)))
    return _det_sign_elimination(J)


def _det_sign_elimination(J: torch.Tensor) -> torch.Tensor:
    """:func:`det_sign_soa` by elimination with partial pivoting, elementwise over the pose axis (any device)."""
    A = J.clone()
    n, _, B = A.shape
    sign = torch.ones(B, dtype=A.dtype, device=A.device)
    for k in range(n):
        p = A[k:, k].abs().argmax(0) + k  # (B,) pivot row
        swap = p != k
        if bool(swap.any()):
            idx = p[None, None, :].expand(1, n, B)
            row_p = A.gather(0, idx)  # (1, n, B)
            row_k = A[k:k + 1].clone()
            A.scatter_(0, idx, row_k)
            A[k:k + 1] = row_p
            sign = torch.where(swap, -sign, sign)
        piv = A[k, k]
        sign = sign * torch.sign(piv)
        if k + 1 < n:
            safe = torch.where(piv == 0, torch.ones_like(piv), piv)
            f = A[k + 1:, k] / safe  # (n-k-1, B)
            A[k + 1:, k:] -= f[:, None, :] * A[k, k:][None]
    return sign


def jacobian_lipschitz(kernel: FlangeKernel, length: float) -> float | None:
    """L with ||D (J(q') - J(q))||_2 <= L |q' - q|_1 for the nominal body Jacobian w.r.t. the commands (D: the
    orientation rows times ``length``), or None for an arm with prismatic joints (no bound derived for them).

    Column i of the body Jacobian w.r.t. the joint variables is (ω_i × r_i, ω_i): a unit axis and its lever
    arm to the flange, |r_i| <= R (R: the sum of the joint offsets after joint 1 and the tip, a bound on any
    joint's distance to the flange). Turning a joint by dθ turns ω_i and r_i by at most |dθ| (and moves r_i by at most
    R |dθ|), so a column changes by at most sqrt((2R)² + length²) |dθ| and the matrix by sqrt(n) times that
    (Frobenius); commands enter through the coupling C (θ = C q + b, J_q = J_θ C): ||C||_2 ||C||_1 more.
    """
    if bool(kernel.prismatic.any()):
        return None
    R = float(kernel.op[1:].norm(dim=-1).sum() + kernel.tipp.norm())  # joint 1's own offset is upstream of every axis
    C = kernel.coupling.double().cpu()
    c2, c1 = float(torch.linalg.matrix_norm(C, 2)), float(C.abs().sum(0).max())
    return c2 * c1 * math.sqrt(kernel.n * ((2.0 * R) ** 2 + length ** 2))


def surely_same_branch(q_from: torch.Tensor, q_to: torch.Tensor, sigma_lower: torch.Tensor, lipschitz: float | None
                       ) -> torch.Tensor:
    """Rows whose whole straight path q_from -> q_to provably keeps det J's sign: (B,) bool.

    Weyl: σ_min(D J(q)) moves by at most ||D ΔJ||_2 <= L |q - q_from|_1 along the path, so it stays positive
    (and det J keeps its sign) while L |q_to - q_from|_1 < σ_min(D J(q_from)); sigma_lower: (B,) a lower bound
    of that (1 / ||(D J)^-1||_F, from the inverse the solver has already). Most compensated rows move by a
    calibration-sized step far from any singular surface: they need no Jacobian to be tested.
    """
    if lipschitz is None:
        return torch.zeros(q_from.shape[0], dtype=torch.bool, device=q_from.device)
    return lipschitz * (q_to - q_from).abs().sum(-1) < sigma_lower


def det_sign(kernel: FlangeKernel, qT: torch.Tensor) -> torch.Tensor:
    """Sign of det of the nominal flange Jacobian.  qT: (6, B) -> (B,) in {-1, 0, +1} (float)."""
    _, _, J = kernel.nominal_flange_jacobian(qT.contiguous())
    return det_sign_soa(J)


def branch_changed(kernel: FlangeKernel, q_from: torch.Tensor, q_to: torch.Tensor, check: torch.Tensor | None = None,
                   samples: int = 8, path_above: float = PATH_ABOVE, sign_from: torch.Tensor | None = None) -> torch.Tensor:
    """Rows whose command q_to lies on another branch than q_from (module docstring).

    q_from, q_to: (B, n) commands (rad / m); check: (B,) bool rows to test (default all; the others are
    False); samples: points on the straight path for rows moved more than ``path_above`` (rad, any joint);
    sign_from: (B,) det sign at q_from if known. -> (B,) bool. n != 6: all False.
    """
    B, n = q_from.shape
    out = torch.zeros(B, dtype=torch.bool, device=q_from.device)
    if n != 6 or B == 0:
        return out
    k = torch.arange(B, device=q_from.device) if check is None else check.nonzero()[:, 0]
    if k.numel() == 0:
        return out
    a, b = q_from[k], q_to[k]
    s0 = det_sign(kernel, a.T) if sign_from is None else sign_from[k]
    changed = det_sign(kernel, b.T) != s0
    far = ((b - a).abs().amax(-1) > path_above) & ~changed
    if far.any() and samples > 1:
        f = far.nonzero()[:, 0]
        t = torch.arange(1, samples, dtype=a.dtype, device=a.device) / samples  # interior points
        qa, qb = a[f], b[f]
        path = qa[None] + t[:, None, None] * (qb - qa)[None]  # (samples - 1, m, n)
        s = det_sign(kernel, path.reshape(-1, n).T).reshape(t.numel(), -1)
        changed[f] = (s != s0[f][None]).any(0)
    out[k] = changed
    return out


__all__ = ["PATH_ABOVE", "branch_changed", "det_sign", "det_sign_soa", "jacobian_lipschitz", "surely_same_branch"]
