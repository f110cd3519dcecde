"""Compensation solved pose by pose in one compiled pass: the common case of :func:`.targets.compensate_targets`
and of :func:`.newton.compensate` on the CPU.

The batched solvers run each iteration as dozens of torch ops over the pose
axis (targets: the controller's nominal IK, then Paper II's compensation,
then the branch test); on the CPU their time goes to memory traffic and
dispatch, not arithmetic, and each op's barrier waits for the slowest
thread (a busy neighbour core). For a pose well inside the workspace the
work is small: a few Newton steps of the nominal chain from the controller's
seed (targets only), then (47)-(51) with the inverse Jacobian that the last of
those steps formed as the chord for the first step and the modeled Jacobian
after it, refined by Broyden (the fast path of :func:`.newton.compensate`),
then det J's sign at the solution. Here that runs for each pose in
registers (the flange is :func:`.fused.flange_pose`, the same code as the
compiled flange kernel), poses handed to the threads in blocks of 64.

One reading differs from the general targets path and is stated here: the
correction is measured (bounded, and tested for a branch change) from the
controller's nominal IK command for the nominal tool, not from a nominal IK
command for the identified tool: both are commands the controller could have
run for the target, a tool calibration apart, and the first always exists.

A pose leaves the compiled pass with a code saying where it stopped (the
nominal IK did not converge within its trust region, the Jacobian there is
near singular, the chord did not contract, the correction exceeds the bound,
det J changed sign at the end or on the path): those rows are solved
again by the batched path, which is robust there and says why a row fails.
So this pass never flags a row; it only takes the easy ones off the batch.

Why one module: the kernel is one function, and its stages share the pose's registers and scratch.
"""

from __future__ import annotations

import math

import numpy as np
import torch

from .fused import (FAST, HAVE_NUMBA, borrowed, flange_scratch, flange_work, gap, inline, inlined,
                    kernel_threads, njit, rows, soa)
from .fused import flange_pose, flange_pose_inlined

if HAVE_NUMBA:
    import numba

DONE, IK_FAILED, SINGULAR, NOT_CONTRACTING, BEYOND, BRANCH_SIGN = 0, 1, 2, 3, 4, 5
"""Where a pose stopped in :func:`targets_soa` (int8 per row); DONE rows are final, the others go to the general path."""

IK_TRUST = math.radians(20.0)
"""rad / m: a nominal IK step larger than this leaves the pass (a seed far from the target: the general path's
damped solve keeps to the seed's branch)."""

PATH_SAMPLES = 8
"""The straight path's interior points tested for a branch change: t = 1/8 .. 7/8 (as branch.branch_changed)."""

PASS_ITER = 12
"""Updates per linearization in this pass: a row that needs more is not an easy one (near a singularity, or no
solution within reach: it would spend up to 3 x max_iter evaluations here before the batched path takes it)."""

_TCHUNK = 64  # poses per task (the flange kernel's 512 / 8): ~10 flange evaluations a pose, small blocks balance the threads


@njit(**inline)
def pivot(A, k, n, c0, c1):
    """Partial pivoting at step k: the row >= k of column k with the largest magnitude swapped into row k
    (columns c0..c1-1). -> the factor step k contributes to det's sign (-1 per swap, times the pivot's sign),
    0.0 when the column is 0 or not finite."""
    p = k
    big = abs(A[k, k])
    for r in range(k + 1, n):
        if abs(A[r, k]) > big:
            big = abs(A[r, k])
            p = r
    if not (big > 0.0) or not np.isfinite(big):
        return 0.0
    if p == k:
        return 1.0 if A[k, k] > 0.0 else -1.0
    for c in range(c0, c1):
        A[k, c], A[p, c] = A[p, c], A[k, c]
    return -1.0 if A[k, k] > 0.0 else 1.0


@njit(**inline)
def invert_column(J, b, A, P):
    """P (n, n) = inverse of J[:, :, b] (n = 6) by Gauss-Jordan with partial pivoting; A (n, 2n) scratch.
    -> the sign of det J (+1.0 / -1.0), 0.0 when a pivot vanishes or is not finite."""
    n = P.shape[0]
    for r in range(n):
        for c in range(n):
            A[r, c] = J[r, c, b]
            A[r, n + c] = 1.0 if r == c else 0.0
    sign = 1.0
    for k in range(n):
        swap = pivot(A, k, n, 0, 2 * n)
        if swap == 0.0:
            return 0.0
        sign *= swap
        piv = A[k, k]
        inv = 1.0 / piv
        for c in range(k, 2 * n):
            A[k, c] *= inv
        for r in range(n):
            if r != k:
                f = A[r, k]
                if f != 0.0:
                    for c in range(k, 2 * n):
                        A[r, c] -= f * A[k, c]
    for r in range(n):
        for c in range(n):
            P[r, c] = A[r, n + c]
    return sign


@njit(**inline)
def det_sign_column(J, b, A):
    """Sign of det J[:, :, b] (n = 6) by LU with partial pivoting (a third of :func:`invert_column`'s work);
    A (n, >= n) scratch. -> +1.0 / -1.0, 0.0 when a pivot vanishes."""
    n = J.shape[0]
    for r in range(n):
        for c in range(n):
            A[r, c] = J[r, c, b]
    sign = 1.0
    for k in range(n):
        swap = pivot(A, k, n, k, n)
        if swap == 0.0:
            return 0.0
        sign *= swap
        piv = A[k, k]
        for r in range(k + 1, n):
            f = A[r, k] / piv
            if f != 0.0:
                for c in range(k + 1, n):
                    A[r, c] -= f * A[k, c]
    return sign


@njit(**inline)
def path_crosses(q0, q1, qpath, mdl, chn, eyeR, zero_p, PR, Pp, FJ, scr, A, sign0):
    """Whether det J's sign leaves ``sign0`` at an interior point t = k / PATH_SAMPLES of the straight path from
    q0 to q1 ((n,) each): the branch test of a correction larger than the pass's path threshold
    (branch.branch_changed). qpath (n, 1), PR, Pp, FJ, scr, A: scratch."""
    n = q0.shape[0]
    for k in range(1, PATH_SAMPLES):
        t = k / PATH_SAMPLES
        for j in range(n):
            qpath[j, 0] = q0[j] + t * (q1[j] - q0[j])
        flange_pose(qpath, 0, qpath, False, False, mdl, chn, eyeR, zero_p, PR, Pp, FJ, True, scr, 0, False)
        if det_sign_column(FJ, 0, A) != sign0:
            return True
    return False


@njit(**inlined)
def pose_error(R, p, b, GR, Gp, gb, de):
    """de (6,) of (47)-(48) between the flange (R, p column b) and the goal (rotation GR[gb, :3, :3] of a (B, 3+, 3+)
    array of poses, position Gp column gb), in the flange
    frame, as :func:`.kernel.pose_error_soa`: R^T (p_goal - p) and ½ R^T Σ_j a_j × g_j (columns of R, GR).
    -> tr(R^T R_goal) = 1 + 2 cos(angle): the rotation part is sin(angle) axis, which vanishes at a half
    turn too, so a solution also needs the trace above 1 (angle below 90 deg)."""
    wx = wy = wz = 0.0
    tr = 0.0
    for j in range(3):
        ax, ay, az = R[0, j, b], R[1, j, b], R[2, j, b]
        gx, gy, gz = GR[gb, 0, j], GR[gb, 1, j], GR[gb, 2, j]
        wx += ay * gz - az * gy
        wy += az * gx - ax * gz
        wz += ax * gy - ay * gx
        tr += ax * gx + ay * gy + az * gz
    vx, vy, vz = Gp[0, gb] - p[0, b], Gp[1, gb] - p[1, b], Gp[2, gb] - p[2, b]
    for k in range(3):
        de[k] = R[0, k, b] * vx + R[1, k, b] * vy + R[2, k, b] * vz
        de[3 + k] = 0.5 * (R[0, k, b] * wx + R[1, k, b] * wy + R[2, k, b] * wz)
    return tr


@njit(**inlined)
def weighted_fro2(P, length):
    """||P D^-1||_F² for an inverse Jacobian P (n, 6), D the orientation rows times ``length``: 1 / sqrt of it
    bounds sigma_min of D J from below (as newton.nominal_jacobian_inverse's floor)."""
    fro2 = 0.0
    for j in range(P.shape[0]):
        for k in range(6):
            fro2 += P[j, k] * P[j, k] / (1.0 if k < 3 else length * length)
    return fro2


@njit(**inlined)
def weighted_norm(de, length):
    """sqrt(|de_p|² + length² |de_r|²) (m)."""
    return np.sqrt(de[0] * de[0] + de[1] * de[1] + de[2] * de[2]
                   + length * length * (de[3] * de[3] + de[4] * de[4] + de[5] * de[5]))


@njit(**inlined)
def apply(P, de, dq):
    """dq = P de; -> |dq| and max |dq_j|."""
    n = dq.shape[0]
    ss = 0.0
    big = 0.0
    for j in range(n):
        x = 0.0
        for k in range(6):
            x += P[j, k] * de[k]
        dq[j] = x
        ss += x * x
        big = max(big, abs(x))
    return np.sqrt(ss), big


@njit(**inline)
def pose_work(threads, n):
    """:func:`targets_soa`'s arrays that its calls take, for each thread (as .fused.flange_work): A (6, 12),
    P (6, 6) (inverse Jacobian), de (6,), dq (n,); FR (3, 3, 1), Fp (3, 1), FJ (6, n, 1) the flange (and Jacobian) of
    the pose being solved; qpath (n, 1), PR (3, 3, 1), Pp (3, 1) a point of the straight path q_nom -> q and its
    flange (branch test)."""
    k = threads
    return (np.empty((k, 6 + gap(12), 12)), np.empty((k, 6 + gap(6), 6)), np.empty((k, 6 + gap(1))),
            np.empty((k, n + gap(1))), np.empty((k, 3 + gap(3), 3, 1)), np.empty((k, 3 + gap(1), 1)),
            np.empty((k, 6 + gap(n), n, 1)), np.empty((k, n + gap(1), 1)), np.empty((k, 3 + gap(3), 3, 1)),
            np.empty((k, 3 + gap(1), 1)))


@njit(**inline)
def pose_scratch(work, n):
    """The calling thread's arrays in :func:`pose_work`, borrowed (as .fused.flange_scratch)."""
    t = numba.get_thread_id()
    A, P, de, dq, FR, Fp, FJ, qpath, PR, Pp = work
    return borrowed((A[t, :6], P[t, :6], de[t, :6], dq[t, :n], FR[t, :3], Fp[t, :3], FJ[t, :6], qpath[t, :n],
                     PR[t, :3], Pp[t, :3]))


@njit(parallel=True, cache=True, fastmath=FAST)
def targets_soa(seed, sT, use_s, coupling, offset, ecoupling, eoffset, lo, width, table, has_bl,
                oR, op, axes, Ka, Ka2, prismatic, z_axes, tipR, tipp, baseR, basep, eyeR, zero_p,
                T, t_nom, t_act, G1p, G2p, gR, gp, GR2, from_seed, want_command, ik_tol, ik_iter, ik_trust, tol,
                residual_tol, max_iter, contraction, length,
                max_corr, path_above, sigma_floor, refresh, refresh_floor, lipschitz,
                q_out, qn_out, de_out, step_out, it_out, status_out, C, threads):
    """Per pose b: the nominal IK from seed[b] to the flange that puts the nominal tool point t_nom[b] on
    the target T[b] (B, 4, 4), then (47)-(51) for the modeled flange (errors, base, directions sT) to the
    flange for the identified tool point t_act from there, then det J's sign and the nominal tool pose at the
    solution (the corrected target, into C (B, 4, 4)). Writes q_out, qn_out (n, B), de_out (6, B), step_out,
    it_out (B,), status_out (B,) int8 (module constants); G1p, G2p (3, B) the flange goals' positions;
    gR (3, 3), gp (3,): the inverse of the model's tool-set frame (:func:`.toolset.tool_set_frame`), taken on the
    right of the compensation's goal (GR2 (B, 3, 3): that goal's rotations) so that the identified tool set,
    not the bare flange, reaches it;
    (the inputs pose-first as the caller's tensors hold them: no transposed copies);
    from_seed: no IK, the goal is the seed's nominal flange (compensation of commands; T (B, 3, 3), G2p are written);
    want_command: False skips the nominal flange at the solution where the branch test does not need it
    (C may then be (0, 4, 4)); threads: numba's (.fused.kernel_threads)."""
    B, n = seed.shape
    nchunks = (B + _TCHUNK - 1) // _TCHUNK
    flange_w, pose_w = flange_work(threads, n), pose_work(threads, n)
    # the arrays the calls below take, borrowed (.fused.borrowed): the caller's outlive the loop
    (q_out, sT, coupling, offset, ecoupling, eoffset, lo, width, table, oR, op, axes, Ka, Ka2, prismatic, tipR, tipp,
     baseR, basep, eyeR, zero_p, T, G1p, G2p, gR, gp, GR2) = borrowed((q_out, sT, coupling, offset, ecoupling, eoffset,
                                                                       lo, width, table, oR, op, axes, Ka, Ka2,
                                                                       prismatic, tipR, tipp, baseR, basep, eyeR,
                                                                       zero_p, T, G1p, G2p, gR, gp, GR2))
    for c in numba.prange(nchunks):
        th, ue, cs, sn, zs, os_, ws, ds = flange_scratch(flange_w, n)
        mdl = (coupling, offset, ecoupling, eoffset, lo, width, table, has_bl)
        chn = (oR, op, axes, Ka, Ka2, prismatic, z_axes, tipR, tipp)
        scr = (th, ue, cs, sn, zs, os_, ws, ds)
        A, P, de, dq, FR, Fp, FJ, qpath, PR, Pp = pose_scratch(pose_w, n)
        last = np.empty(n)
        sP = np.empty(6)
        qbest = np.empty(n)
        for b in range(c * _TCHUNK, min(B, (c + 1) * _TCHUNK)):
            for j in range(n):
                q_out[j, b] = seed[b, j]
            status = IK_FAILED
            sign0 = 0.0
            if from_seed:  # compensation of commands, Paper II (46): the goal is the seed's nominal flange
                flange_pose(q_out, b, sT, False, False, mdl, chn, eyeR, zero_p, FR, Fp, FJ, True, scr, 0, False)
                for k in range(3):
                    G2p[k, b] = Fp[k, 0]
                    for j in range(3):
                        T[b, k, j] = FR[k, j, 0]
                sign0 = invert_column(FJ, 0, A, P)
                if sign0 != 0.0:
                    status = DONE
            else:
                for k in range(3):  # the flange goals: the tool's orientation, its point taken back to the flange
                    G1p[k, b] = T[b, k, 3] - (T[b, k, 0] * t_nom[b, 0] + T[b, k, 1] * t_nom[b, 1]
                                              + T[b, k, 2] * t_nom[b, 2])
                    G2p[k, b] = T[b, k, 3] - (T[b, k, 0] * t_act[b, 0] + T[b, k, 1] * t_act[b, 1]
                                              + T[b, k, 2] * t_act[b, 2])
            for k in range(3):  # the compensation's goal times the tool-set frame's inverse (identity: unchanged)
                G2p[k, b] += T[b, k, 0] * gp[0] + T[b, k, 1] * gp[1] + T[b, k, 2] * gp[2]
                for j in range(3):
                    GR2[b, k, j] = T[b, k, 0] * gR[0, j] + T[b, k, 1] * gR[1, j] + T[b, k, 2] * gR[2, j]
            # 1. the controller's nominal IK: Newton with the nominal Jacobian, stopped as (51)
            for it in range(0 if from_seed else ik_iter + 1):
                flange_pose_inlined(q_out, b, sT, False, False, mdl, chn, eyeR, zero_p, FR, Fp, FJ, True, scr, 0, False)
                tr = pose_error(FR, Fp, 0, T, G1p, b, de)
                res = weighted_norm(de, length)
                sign0 = invert_column(FJ, 0, A, P)
                if sign0 == 0.0:
                    break
                step, big = apply(P, de, dq)
                if not np.isfinite(step):
                    break
                if step < ik_tol and res <= residual_tol and tr > 1.0:
                    status = DONE
                    break
                if big > ik_trust:
                    break
                for j in range(n):
                    q_out[j, b] += dq[j]
            if status != DONE:
                status_out[b] = status
                continue
            for j in range(n):
                qn_out[j, b] = q_out[j, b]
            # the chord's conditioning, as newton.nominal_jacobian_inverse's floor; 1/||D P||_F <= sigma_min(D J)
            fro2 = weighted_fro2(P, length)
            if fro2 * sigma_floor * sigma_floor >= 1.0:
                status_out[b] = SINGULAR
                continue
            sig_lb = 1.0 / np.sqrt(fro2)
            # 2. (47)-(51): the modeled flange to the identified tool's goal, from the nominal IK's command with
            # its inverse Jacobian as the chord for the first step, the modeled one after it, refined by Broyden
            # (as newton.fixed_jacobian_iterations; the modeled Jacobian at the start saves nothing: over a
            # correction of ~1e-2 rad the chord's error is the geometry's change, not the error slopes); a row
            # that does not contract is linearized again at its best iterate (newton's refresh)
            done = False
            total = 0
            best = np.inf
            cap = min(max_iter, PASS_ITER)
            for attempt in range(refresh + 1):
                if attempt > 0:
                    for j in range(n):
                        q_out[j, b] = qbest[j]
                prev = np.inf
                have_last = False
                singular = False
                for r in range(cap + 1):
                    # the first step (~1e-2 rad) is most of the correction: the modeled Jacobian after it is within
                    # ~1e-4 of the solution's (4 evaluations instead of 6 on Paper II's FANUC)
                    relinearize = r == (1 if attempt == 0 else 0)
                    at_start = r == 0 and attempt == 0  # the nominal IK's command: its joint variables are in the scratch
                    flange_pose_inlined(q_out, b, sT, use_s, True, mdl, chn, baseR, basep, FR, Fp, FJ, relinearize, scr,
                                        0, at_start)
                    if relinearize:
                        have_last = False
                        floor = sigma_floor if attempt == 0 else refresh_floor
                        if invert_column(FJ, 0, A, P) == 0.0:
                            singular = True
                            break
                        fro2 = weighted_fro2(P, length)
                        if fro2 * floor * floor >= 1.0:
                            singular = True
                            break
                    tr = pose_error(FR, Fp, 0, GR2, G2p, b, de)
                    res = weighted_norm(de, length)
                    if res < best:
                        best = res
                        for j in range(n):
                            qbest[j] = q_out[j, b]
                    step, big = apply(P, de, dq)
                    if have_last:  # good Broyden, as newton.fixed_jacobian_iterations
                        ss = 0.0
                        sd = 0.0
                        for j in range(n):
                            ss += last[j] * last[j]
                            sd += last[j] * dq[j]
                        den = ss - sd
                        if abs(den) > 0.1 * ss:
                            f = 1.0 / den
                            for k in range(6):
                                x = 0.0
                                for j in range(n):
                                    x += last[j] * P[j, k]
                                sP[k] = x
                            for j in range(n):
                                for k in range(6):
                                    P[j, k] += dq[j] * f * sP[k]
                            g = ss * f
                            step = 0.0
                            for j in range(n):
                                dq[j] *= g
                                step += dq[j] * dq[j]
                            step = np.sqrt(step)
                    if step < tol and res <= residual_tol and tr > 1.0:
                        done = True
                        break
                    if not np.isfinite(step) or step > contraction * prev or r == cap:
                        break
                    total += 1
                    for j in range(n):
                        q_out[j, b] += dq[j]
                        last[j] = dq[j]
                    prev = step
                    have_last = True
                if done or singular:
                    break
            it_out[b] = total
            if not done:
                status_out[b] = NOT_CONTRACTING
                continue
            for k in range(6):
                de_out[k, b] = de[k]
            step_out[b] = step
            # 3. a calibration-sized correction on the controller's branch (.branch: det J's sign at the end, and on
            # 7 points of the straight path for moves above path_above, as branch.branch_changed)
            l1 = 0.0
            far = 0.0
            beyond = False
            for j in range(n):
                d = abs(q_out[j, b] - qn_out[j, b])
                l1 += d
                far = max(far, d)
                if d > max_corr[j]:
                    beyond = True
            if beyond:
                status_out[b] = BEYOND
                continue
            sure = lipschitz > 0.0 and lipschitz * l1 < sig_lb  # Weyl: .branch.surely_same_branch
            if sure and not want_command:
                status_out[b] = DONE
                continue
            # at the command the compensation's last evaluation confirmed (its joint variables are in the scratch)
            flange_pose_inlined(q_out, b, sT, False, False, mdl, chn, eyeR, zero_p, FR, Fp, FJ, not sure, scr, 0, True)
            if not sure and det_sign_column(FJ, 0, A) != sign0:
                status_out[b] = BRANCH_SIGN
                continue
            if not sure and far > path_above and path_crosses(qn_out[:, b], q_out[:, b], qpath, mdl, chn, eyeR,
                                                              zero_p, PR, Pp, FJ, scr, A, sign0):
                status_out[b] = BRANCH_SIGN
                continue
            if want_command:  # the nominal tool pose there: the corrected target
                for k in range(3):
                    for j in range(3):
                        C[b, k, j] = FR[k, j, 0]
                    C[b, k, 3] = (Fp[k, 0] + FR[k, 0, 0] * t_nom[b, 0] + FR[k, 1, 0] * t_nom[b, 1]
                                  + FR[k, 2, 0] * t_nom[b, 2])
                    C[b, 3, k] = 0.0
                C[b, 3, 3] = 1.0
            status_out[b] = DONE


def solve_targets(fused, target: torch.Tensor, t_nominal: torch.Tensor, t_actual: torch.Tensor, seed: torch.Tensor,
                  direction: torch.Tensor | None, *, ik_tol: float, ik_max_iter: int, tol: float, residual_tol: float,
                  max_iter: int, contraction: float, length: float, max_correction: torch.Tensor | None,
                  path_above: float, sigma_floor: float, refresh: int, refresh_floor: float,
                  lipschitz: float | None, tool_set_inverse: torch.Tensor | None = None) -> dict:
    """The compiled pass over B targets.

    fused: a :class:`.fused.FusedFlange` of the model; target: (B, 4, 4) tool poses (nominal base frame, SI);
    t_nominal, t_actual: (B, 3) the controller's and the identified tool points (flange frame); seed: (B, 6)
    commands; direction: (B, 6) or None; the tolerances as :func:`.newton.compensate` (max_correction: (6,) or
    None); sigma_floor: m / rad, the chord's floor at the nominal IK's command; refresh, refresh_floor:
    re-linearizations of a row that does not contract and their floor (newton's ``refresh`` and
    ``null_damping``); lipschitz: as :func:`.branch.jacobian_lipschitz` (None: every row takes the det test);
    tool_set_inverse: (4, 4) the inverse of the model's tool-set frame (None: identity; t_actual is then the
    identified tool point in that frame). -> dict of q, q_nominal (B, 6), pose_error (B, 6), step (B,),
    iterations (B,) long, status (B,) int8, command (B, 4, 4) (the nominal tool pose at q: the corrected target); float64 CPU tensors; rows with
    status != DONE hold no result.
    """
    B, n = seed.shape
    f64 = torch.float64
    s = np.empty((n, 0)) if direction is None else soa(direction)  # unread without directions
    corr = np.full(n, np.inf) if max_correction is None else max_correction.to(f64).cpu().numpy()
    q, qn = np.empty((n, B)), np.full((n, B), np.nan)
    de, step = np.full((6, B), np.nan), np.full(B, np.nan)
    it, status = np.zeros(B, dtype=np.int64), np.zeros(B, dtype=np.int8)
    C, G1p, G2p = np.empty((B, 4, 4)), np.empty((3, B)), np.empty((3, B))
    gR, gp = _inverse_parts(tool_set_inverse)
    threads = kernel_threads("targets")
    with numba.parallel_chunksize(1):  # dynamic: a thread beside a busy neighbour does not hold up the call
        targets_soa(rows(seed), s, direction is not None, *fused.model, *fused.chain, *fused.base, *fused.no_base,
                    rows(target), rows(t_nominal), rows(t_actual), G1p, G2p, gR, gp, np.empty((B, 3, 3)), False, True,
                    float(ik_tol),
                    int(ik_max_iter), IK_TRUST,
                    float(tol), float(residual_tol), int(max_iter), float(contraction), float(length), corr,
                    float(path_above), float(sigma_floor), int(refresh), float(refresh_floor),
                    -1.0 if lipschitz is None else float(lipschitz), q, qn, de, step, it, status, C, threads)
    t = torch.from_numpy
    return {"q": t(q).T, "q_nominal": t(qn).T, "pose_error": t(de).T, "step": t(step), "iterations": t(it),
            "status": t(status), "command": t(C)}


def solve_commands(fused, q_nom: torch.Tensor, direction: torch.Tensor | None, *, tol: float, residual_tol: float,
                   max_iter: int, contraction: float, length: float, max_correction: torch.Tensor | None,
                   path_above: float, sigma_floor: float, refresh: int, refresh_floor: float,
                   lipschitz: float | None, tool_set_inverse: torch.Tensor | None = None) -> dict:
    """The compiled pass for Paper II's compensation of commands (46)-(52): q_nom (B, 6) -> dict of q (B, 6),
    pose_error (B, 6), step (B,), iterations (B,), status (B,) int8 (rows with status != DONE hold no result);
    arguments as :func:`solve_targets`."""
    B, n = q_nom.shape
    f64 = torch.float64
    s = np.empty((n, 0)) if direction is None else soa(direction)  # unread without directions
    corr = np.full(n, np.inf) if max_correction is None else max_correction.to(f64).cpu().numpy()
    q, qn = np.empty((n, B)), np.empty((n, B))
    de, step = np.full((6, B), np.nan), np.full(B, np.nan)
    it, status = np.zeros(B, dtype=np.int64), np.zeros(B, dtype=np.int8)
    goal, G2p = np.empty((B, 3, 3)), np.empty((3, B))
    none = np.empty((0, 3))
    gR, gp = _inverse_parts(tool_set_inverse)
    threads = kernel_threads("targets")
    with numba.parallel_chunksize(1):
        targets_soa(rows(q_nom), s, direction is not None, *fused.model, *fused.chain, *fused.base, *fused.no_base,
                    goal, none, none, none, G2p, gR, gp, np.empty((B, 3, 3)), True, False, 0.0, 0, 0.0,
                    float(tol), float(residual_tol), int(max_iter), float(contraction), float(length), corr,
                    float(path_above), float(sigma_floor), int(refresh), float(refresh_floor),
                    -1.0 if lipschitz is None else float(lipschitz), q, qn, de, step, it, status,
                    np.empty((0, 4, 4)), threads)
    t = torch.from_numpy
    return {"q": t(q).T, "pose_error": t(de).T, "step": t(step), "iterations": t(it), "status": t(status)}


def _inverse_parts(G_inv: torch.Tensor | None) -> tuple[np.ndarray, np.ndarray]:
    """(4, 4) or None (identity) -> its rotation (3, 3) and translation (3,) as contiguous float64 arrays."""
    if G_inv is None:
        return np.eye(3), np.zeros(3)
    g = G_inv.detach().to(torch.float64).cpu().numpy()
    return np.ascontiguousarray(g[:3, :3]), np.ascontiguousarray(g[:3, 3])


__all__ = ["BEYOND", "BRANCH_SIGN", "DONE", "IK_FAILED", "IK_TRUST", "NOT_CONTRACTING", "SINGULAR", "det_sign_column",
           "invert_column",
           "pose_error", "solve_commands", "solve_targets", "targets_soa"]
