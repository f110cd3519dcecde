"""Damped least squares (:func:`.damped.damped_least_squares`) pose by pose in one compiled pass.

The batched solver runs each Levenberg-Marquardt iteration as ~100 torch ops
over the rows still active; on the CPU, for the few hundred rows the fast
paths hand it (targets out of reach, poses next to a singularity, corrections
beyond the bound) that is dispatch, not arithmetic: ~2 ms an iteration
whatever the row count, and the slowest row sets the number of iterations.
Here every row runs its own iteration in registers (the flange and its
Jacobian are :func:`.fused.flange_pose`), rows handed to the threads in small
blocks. Same iteration, step for step: the same residual and its exact
Jacobian, Nielsen's damping rule, the step bound, the box around q_ref with
``stop_at_bound``, the stall and window tests; only the linear solve is
Gaussian elimination with partial pivoting here and LAPACK's LU there, so
iterates agree to rounding (the tests hold both to 1e-9 and the same flags).
"""

from __future__ import annotations

import numpy as np
import torch

from .fused import HAVE_NUMBA, flange_pose, flange_scratch, flange_work, inline, kernel_threads, njit, poses_soa, soa
from .fused_targets import pivot

if HAVE_NUMBA:
    import numba

_DCHUNK = 16  # rows per task: a row takes tens of iterations, small blocks balance the threads


@njit(**inline)
def residual_rows(FR, Fp, TR, Tp, b, FJ, length, r, Jr, de):
    """r (6,) = (de_p, length de_r) of (47)-(48) between the flange (FR, Fp column 0) and the target (TR, Tp
    column b), de (6,), and its exact Jacobian Jr (6, n) from the body Jacobian FJ (6, n, 1), as
    :func:`.damped.pose_residual` and :func:`.damped.residual_jacobian`. -> tr(Omega_R)."""
    n = Jr.shape[1]
    OR = np.empty((3, 3))
    for i in range(3):
        for j in range(3):
            OR[i, j] = FR[0, i, 0] * TR[0, j, b] + FR[1, i, 0] * TR[1, j, b] + FR[2, i, 0] * TR[2, j, b]
    vx, vy, vz = Tp[0, b] - Fp[0, 0], Tp[1, b] - Fp[1, 0], Tp[2, b] - Fp[2, 0]
    for i in range(3):
        de[i] = FR[0, i, 0] * vx + FR[1, i, 0] * vy + FR[2, i, 0] * vz
    de[3] = 0.5 * (OR[2, 1] - OR[1, 2])
    de[4] = 0.5 * (OR[0, 2] - OR[2, 0])
    de[5] = 0.5 * (OR[1, 0] - OR[0, 1])
    for k in range(3):
        r[k] = de[k]
        r[3 + k] = length * de[3 + k]
    tr = OR[0, 0] + OR[1, 1] + OR[2, 2]
    G = np.empty((3, 3))  # ½ (tr I - Omega_R)
    for i in range(3):
        for k in range(3):
            G[i, k] = 0.5 * ((tr if i == k else 0.0) - OR[i, k])
    px, py, pz = de[0], de[1], de[2]
    for j in range(n):
        wx, wy, wz = FJ[3, j, 0], FJ[4, j, 0], FJ[5, j, 0]
        # -Jv + S(de_p) Jw
        Jr[0, j] = -FJ[0, j, 0] + (py * wz - pz * wy)
        Jr[1, j] = -FJ[1, j, 0] + (pz * wx - px * wz)
        Jr[2, j] = -FJ[2, j, 0] + (px * wy - py * wx)
        for i in range(3):  # -length G Jw
            Jr[3 + i, j] = length * -(G[i, 0] * wx + G[i, 1] * wy + G[i, 2] * wz)
    return tr


@njit(**inline)
def cost_of(r, q, ref, b, lam2):
    """½ |r|² + ½ lam2 |q - ref[:, b]|² (the damped solve's cost), inf where not finite."""
    c = 0.0
    for k in range(6):
        c += r[k] * r[k]
    c *= 0.5
    if lam2 != 0.0:
        pr = 0.0
        for j in range(q.shape[0]):
            d = q[j] - ref[j, b]
            pr += d * d
        c += 0.5 * lam2 * pr
    return c if np.isfinite(c) else np.inf


@njit(**inline)
def solve_lu(A, x, W):
    """x (n,) <- A (n, n)^-1 x by Gaussian elimination with partial pivoting (W: (n, n + 1) scratch).
    -> False where a pivot is zero (A singular: torch.linalg.solve_ex's info != 0)."""
    n = A.shape[0]
    for i in range(n):
        for j in range(n):
            W[i, j] = A[i, j]
        W[i, n] = x[i]
    for k in range(n):
        if pivot(W, k, n, k, n + 1) == 0.0:  # (a non-finite column too: its step would be discarded anyway)
            return False
        for i in range(k + 1, n):
            f = W[i, k] / W[k, k]
            if f != 0.0:
                for j in range(k + 1, n + 1):
                    W[i, j] -= f * W[k, j]
    for i in range(n - 1, -1, -1):
        s = W[i, n]
        for j in range(i + 1, n):
            s -= W[i, j] * x[j]
        x[i] = s / W[i, i]
    return True


@njit(parallel=True, cache=True)
def damped_soa(q0, sT, use_s, coupling, offset, ecoupling, eoffset, lo, width, table, has_bl,
               oR, op, axes, Ka, Ka2, prismatic, z_axes, tipR, tipp, baseR, basep,
               TR, Tp, ref, max_step, has_step, max_corr, has_corr, stop_at_bound,
               tol, max_iter, damping, length, residual_tol, stall_rtol, window, window_rtol, lam2,
               q_out, conv_out, it_out, step_out, de_out, blk_out, sta_out, threads):
    """Per row b: Levenberg-Marquardt from q0[:, b] (n, M) to the target (TR[..., b], Tp[:, b]) on the modeled
    flange (directions sT (n, M) where use_s), exactly the iteration of :func:`.damped.damped_least_squares`
    (its arguments; max_step / max_corr (n,) per joint, used where has_step / has_corr). Writes q_out (n, M),
    conv_out, blk_out, sta_out (M,) bool, it_out (M,) int64, step_out (M,), de_out (6, M); threads: numba's
    (.fused.kernel_threads)."""
    n, M = q0.shape
    nchunks = (M + _DCHUNK - 1) // _DCHUNK
    work = flange_work(threads, n)
    for c in numba.prange(nchunks):
        th, ue, cs, sn, zs, os_, ws, ds = flange_scratch(work, n)
        mdl = (coupling, offset, ecoupling, eoffset, lo, width, table, has_bl)
        chn = (oR, op, axes, Ka, Ka2, prismatic, z_axes, tipR, tipp)
        scr = (th, ue, cs, sn, zs, os_, ws, ds)
        FR = np.empty((3, 3, 1))
        Fp = np.empty((3, 1))
        FJ = np.empty((6, n, 1))
        qs = np.empty((n, 1))
        ss = np.empty((n, 1))
        q = np.empty(n)
        qt = np.empty(n)
        dq = np.empty(n)
        g = np.empty(n)
        A = np.empty((n, n))
        K = np.empty((n, n))
        W = np.empty((n, n + 1))
        r = np.empty(6)
        rt = np.empty(6)
        de = np.empty(6)
        de_t = np.empty(6)
        Jr = np.empty((6, n))
        Jr_t = np.empty((6, n))
        for b in range(c * _DCHUNK, min(M, (c + 1) * _DCHUNK)):
            for j in range(n):
                x = q0[j, b]
                if has_corr:
                    x = min(max(x, ref[j, b] - max_corr[j]), ref[j, b] + max_corr[j])
                q[j] = x
                qs[j, 0] = x
                ss[j, 0] = sT[j, b]
            flange_pose(qs, 0, ss, use_s, True, mdl, chn, baseR, basep, FR, Fp, FJ, True, scr, 0, False)
            tr = residual_rows(FR, Fp, TR, Tp, b, FJ, length, r, Jr, de)
            near = tr > 1.0
            cost = cost_of(r, q, ref, b, lam2)
            amax = -np.inf
            for j in range(n):
                a = 0.0
                for k in range(6):
                    a += Jr[k, j] * Jr[k, j]
                amax = max(amax, a)
            mu = damping * max(amax, 1e-12)
            nu = 2.0
            it = 0
            step = np.inf
            cost_ref = cost
            hits = 0
            done = False
            conv = False
            blocked = False
            stall = False
            for k_it in range(max_iter):
                # normal equations (plus Tikhonov toward ref)
                amax = -np.inf
                for i in range(n):
                    s = 0.0
                    for k in range(6):
                        s += Jr[k, i] * r[k]
                    g[i] = s
                    for j in range(n):
                        a = 0.0
                        for k in range(6):
                            a += Jr[k, i] * Jr[k, j]
                        A[i, j] = a
                if lam2 != 0.0:
                    for i in range(n):
                        A[i, i] += lam2
                        g[i] += lam2 * (q[i] - ref[i, b])
                for i in range(n):
                    amax = max(amax, A[i, i])
                    for j in range(n):
                        K[i, j] = A[i, j] + (mu if i == j else 0.0)
                    dq[i] = -g[i]
                ok = solve_lu(K, dq, W)
                fin = True
                for j in range(n):
                    if not np.isfinite(dq[j]):
                        fin = False
                if not ok or not fin:
                    for j in range(n):
                        dq[j] = 0.0
                if has_step:
                    big = 0.0
                    for j in range(n):
                        big = max(big, abs(dq[j]) / max_step[j])
                    f = min(1.0 / max(big, 1e-300), 1.0)
                    for j in range(n):
                        dq[j] *= f
                clipped = False
                for j in range(n):
                    x = q[j] + dq[j]
                    if has_corr:
                        xb = min(max(x, ref[j, b] - max_corr[j]), ref[j, b] + max_corr[j])
                        if xb != x:
                            clipped = True
                        x = xb
                    qt[j] = x
                    qs[j, 0] = x
                if has_corr:
                    if stop_at_bound:
                        if clipped:
                            hits += 1
                        blocked = hits >= 2
                    for j in range(n):
                        dq[j] = qt[j] - q[j]
                flange_pose(qs, 0, ss, use_s, True, mdl, chn, baseR, basep, FR, Fp, FJ, True, scr, 0, False)
                tr_t = residual_rows(FR, Fp, TR, Tp, b, FJ, length, rt, Jr_t, de_t)
                cost_t = cost_of(rt, qt, ref, b, lam2)
                # Nielsen: the decrease the linear model predicts for the step taken
                pred = 0.0
                for i in range(n):
                    ad = 0.0
                    for j in range(n):
                        ad += A[i, j] * dq[j]
                    pred -= dq[i] * (g[i] + 0.5 * ad)
                rho = (cost - cost_t) / max(pred, 1e-300)
                acc = cost_t < cost and rho > 0.0
                flat = acc and (cost - cost_t) <= stall_rtol * cost and mu <= 1e-3 * amax
                if acc:
                    for j in range(n):
                        q[j] = qt[j]
                    cost = cost_t
                    for k in range(6):
                        r[k] = rt[k]
                        de[k] = de_t[k]
                        for j in range(n):
                            Jr[k, j] = Jr_t[k, j]
                    near = tr_t > 1.0
                    mu = mu * max(1.0 - (2.0 * rho - 1.0) ** 3, 1.0 / 3.0)
                    nu = 2.0
                else:
                    mu = mu * nu
                    nu = 2.0 * nu
                it += 1
                ss2 = 0.0
                for j in range(n):
                    ss2 += dq[j] * dq[j]
                step = np.sqrt(ss2)
                small = step < tol
                rr = 0.0
                for k in range(6):
                    rr += r[k] * r[k]
                conv = small and np.sqrt(rr) <= residual_tol and near
                stall = ((small or flat) and not conv) or mu > 1e20 or not np.isfinite(cost)
                if (k_it + 1) % window == 0:
                    stall = stall or (not conv and cost > (1.0 - window_rtol) * cost_ref)
                    cost_ref = cost
                if has_corr and stop_at_bound:
                    stall = stall or (blocked and not conv)
                if conv or stall:
                    done = True
                    break
            for j in range(n):
                q_out[j, b] = q[j]
            for k in range(6):
                de_out[k, b] = de[k]
            it_out[b] = it
            step_out[b] = step
            conv_out[b] = done and conv
            bl = done and has_corr and stop_at_bound and blocked
            blk_out[b] = bl
            sta_out[b] = done and stall and not conv and not bl


def solve_damped(fused, q0: torch.Tensor, target: torch.Tensor, direction: torch.Tensor | None, ref: torch.Tensor,
                 *, tol: float, max_iter: int, damping: float, length: float, residual_tol: float, stall_rtol: float,
                 window: int, window_rtol: float, lam: float, max_step, max_correction, stop_at_bound: bool) -> dict:
    """The compiled pass over M rows: q0 (M, n) starts, target (M, 4, 4), direction (M, n) or None, ref (M, n);
    max_step / max_correction: None or (n,) tensors (per joint). -> dict of q (M, n), converged, blocked,
    stationary (M,) bool, iterations (M,) long, step (M,), pose_error (M, 6); float64 CPU tensors."""
    M, n = q0.shape
    f64 = torch.float64
    qT = soa(q0)
    s = qT if direction is None else soa(direction)
    TR, Tp = poses_soa(target)
    none = np.ones(n)
    step_b = none if max_step is None else max_step.to(f64).cpu().numpy()
    corr_b = none if max_correction is None else max_correction.to(f64).cpu().numpy()
    q = np.empty((n, M))
    de = np.empty((6, M))
    it = np.zeros(M, dtype=np.int64)
    step = np.empty(M)
    conv, blk, sta = np.zeros(M, dtype=np.bool_), np.zeros(M, dtype=np.bool_), np.zeros(M, dtype=np.bool_)
    threads = kernel_threads("damped")
    with numba.parallel_chunksize(1):  # dynamic: rows take very different iteration counts
        damped_soa(qT, s, direction is not None, *fused.model, *fused.chain, *fused.base, TR, Tp, soa(ref),
                   step_b, max_step is not None, corr_b, max_correction is not None, bool(stop_at_bound),
                   float(tol), int(max_iter), float(damping), float(length), float(residual_tol), float(stall_rtol),
                   int(window), float(window_rtol), float(lam) ** 2, q, conv, it, step, de, blk, sta, threads)
    t = torch.from_numpy
    return {"q": t(q).T, "converged": t(conv), "blocked": t(blk), "stationary": t(sta), "iterations": t(it),
            "step": t(step), "pose_error": t(de).T}


__all__ = ["cost_of", "damped_soa", "residual_rows", "solve_damped", "solve_lu"]
