"""3-DOF compensation of commands (``position_only``) pose by pose in one compiled pass.

:func:`.newton.compensate` with ``position_only`` solves for commands that put the tool point c (flange frame)
where the nominal robot puts it, every rotation free, with the smallest correction: the chord iteration of
:func:`.newton.fixed_jacobian_iterations` with the residual and the chord taken in the world frame, the
minimum-norm inverse P = J^T (J J^T)^-1 of the tool point's 3 x n world Jacobian at q_nom, refined by Broyden.
Broyden's rank-1 updates keep P's range, so every iterate stays in q_nom + range(J(q_nom)^T) and the solution is
the point of the solution manifold in that affine space: path-independent, so this pass and the batched one give
the same commands to rounding only while the chord is the same. Hence the chord here is the nominal Jacobian at
q_nom for the whole first linearization (the 6-DOF pass, :mod:`.fused_targets`, switches to the modeled
Jacobian after one step: in 6-DOF the solution is isolated and any chord finds it; here another chord would pick
another point of the manifold).

Each pose runs in registers, as :func:`.fused_targets.targets_soa` does for 6-DOF: the nominal flange and its
Jacobian at q_nom, det J's sign there, the chord, then the iteration on the modeled flange, then the branch test
of :func:`.branch.branch_changed` (det J of the nominal kinematics at the solution, and on 7 points of the straight
path for moves above ``path_above``; the batched path has no Lipschitz shortcut for 3-DOF, so neither has this).
A pose that stops anywhere else leaves with the codes of :mod:`.fused_targets` (SINGULAR: the chord is below its
floor; NOT_CONTRACTING: no convergence within the first linearization; BEYOND; BRANCH_SIGN) and is solved again
from q_nom by the batched path, whose refreshes and damped pass then give the same result as if it had never been
here.
"""

from __future__ import annotations

import numpy as np
import torch

from .fused import (FAST, HAVE_NUMBA, borrowed, flange_pose, flange_pose_inlined, flange_scratch, flange_work,
                    kernel_threads, njit, rows)
from .fused_targets import (BEYOND, BRANCH_SIGN, DONE, NOT_CONTRACTING, PASS_ITER, SINGULAR, det_sign_column,
                            path_crosses, pose_scratch, pose_work)

if HAVE_NUMBA:
    import numba

_PCHUNK = 64  # poses per task, as the 6-DOF pass: ~6 flange evaluations a pose


@njit(parallel=True, cache=True, fastmath=FAST)
def position_soa(q_nom, sT, use_s, coupling, offset, ecoupling, eoffset, lo, width, table, has_bl,
                 oR, op, axes, Ka, Ka2, prismatic, z_axes, tipR, tipp, baseR, basep, eyeR, zero_p,
                 tool, gR, gp, tol, residual_tol, max_iter, contraction, max_corr, path_above, sigma_floor,
                 q_out, de_out, step_out, it_out, status_out, threads):
    """Per pose b of q_nom (B, n): the goal c_goal = F_n(q_nom) G^-1 c (gR (3, 3), gp (3,): G^-1, the tool set's
    frame's inverse; c = tool[b] (B, 3), flange frame), then (47)-(51) for the modeled tool point F_a(q, s) c
    (errors, base, directions sT) with the world-frame residual c_goal - F_a c and the minimum-norm chord of the
    nominal Jacobian of G^-1 c at q_nom, refined by Broyden, then the branch test. Writes q_out (n, B), de_out
    (6, B) (the pose error at the tool point in F_a's frame, as :func:`.kernel.pose_error_soa`), step_out,
    it_out (B,), status_out (B,) int8 (:mod:`.fused_targets`' codes); threads: numba's (.fused.kernel_threads)."""
    B, n = q_nom.shape
    nchunks = (B + _PCHUNK - 1) // _PCHUNK
    flange_w, pose_w = flange_work(threads, n), pose_work(threads, n)
    (q_out, sT, coupling, offset, ecoupling, eoffset, lo, width, table, oR, op, axes, Ka, Ka2, prismatic, tipR, tipp,
     baseR, basep, eyeR, zero_p, tool, gR, gp) = borrowed((q_out, sT, coupling, offset, ecoupling, eoffset, lo, width,
                                                           table, oR, op, axes, Ka, Ka2, prismatic, tipR, tipp, baseR,
                                                           basep, eyeR, zero_p, tool, gR, gp))
    for c in numba.prange(nchunks):
        th, ue, cs, sn, zs, os_, ws, ds = flange_scratch(flange_w, n)
        mdl = (coupling, offset, ecoupling, eoffset, lo, width, table, has_bl)
        chn = (oR, op, axes, Ka, Ka2, prismatic, z_axes, tipR, tipp)
        scr = (th, ue, cs, sn, zs, os_, ws, ds)
        A, P, de, dq, FR, Fp, FJ, qpath, PR, Pp = pose_scratch(pose_w, n)
        last = np.empty(n)
        qbest = np.empty(n)
        GR = np.empty((3, 3))  # the goal's rotation F_n G^-1 (for the reported pose error)
        J3 = np.empty((3, n))  # the chord: world velocity of G^-1 c per unit command
        for b in range(c * _PCHUNK, min(B, (c + 1) * _PCHUNK)):
            for j in range(n):
                q_out[j, b] = q_nom[b, j]
            c0, c1, c2 = tool[b, 0], tool[b, 1], tool[b, 2]
            # 1. the nominal flange and its Jacobian at q_nom: the goal, det J's sign, the chord
            flange_pose(q_out, b, sT, False, False, mdl, chn, eyeR, zero_p, FR, Fp, FJ, True, scr, 0, False)
            sign0 = det_sign_column(FJ, 0, A)
            for k in range(3):
                for j in range(3):
                    GR[k, j] = FR[k, 0, 0] * gR[0, j] + FR[k, 1, 0] * gR[1, j] + FR[k, 2, 0] * gR[2, j]
            t0 = Fp[0, 0] + FR[0, 0, 0] * gp[0] + FR[0, 1, 0] * gp[1] + FR[0, 2, 0] * gp[2]
            t1 = Fp[1, 0] + FR[1, 0, 0] * gp[0] + FR[1, 1, 0] * gp[1] + FR[1, 2, 0] * gp[2]
            t2 = Fp[2, 0] + FR[2, 0, 0] * gp[0] + FR[2, 1, 0] * gp[1] + FR[2, 2, 0] * gp[2]
            t0 += GR[0, 0] * c0 + GR[0, 1] * c1 + GR[0, 2] * c2
            t1 += GR[1, 0] * c0 + GR[1, 1] * c1 + GR[1, 2] * c2
            t2 += GR[2, 0] * c0 + GR[2, 1] * c1 + GR[2, 2] * c2
            # G^-1 c in the nominal flange's frame; its velocity Jv - x × Jw there, turned into the world frame
            x0 = gR[0, 0] * c0 + gR[0, 1] * c1 + gR[0, 2] * c2 + gp[0]
            x1 = gR[1, 0] * c0 + gR[1, 1] * c1 + gR[1, 2] * c2 + gp[1]
            x2 = gR[2, 0] * c0 + gR[2, 1] * c1 + gR[2, 2] * c2 + gp[2]
            for j in range(n):
                wx, wy, wz = FJ[3, j, 0], FJ[4, j, 0], FJ[5, j, 0]
                vx = FJ[0, j, 0] - (x1 * wz - x2 * wy)
                vy = FJ[1, j, 0] - (x2 * wx - x0 * wz)
                vz = FJ[2, j, 0] - (x0 * wy - x1 * wx)
                for k in range(3):
                    J3[k, j] = FR[k, 0, 0] * vx + FR[k, 1, 0] * vy + FR[k, 2, 0] * vz
            # P = J^T (J J^T)^-1 (n x 3, in P[:, :3]): the minimum-norm step, as newton.nominal_jacobian_inverse
            m00 = m01 = m02 = m11 = m12 = m22 = 0.0
            for j in range(n):
                m00 += J3[0, j] * J3[0, j]
                m01 += J3[0, j] * J3[1, j]
                m02 += J3[0, j] * J3[2, j]
                m11 += J3[1, j] * J3[1, j]
                m12 += J3[1, j] * J3[2, j]
                m22 += J3[2, j] * J3[2, j]
            a00, a01, a02 = m11 * m22 - m12 * m12, m02 * m12 - m01 * m22, m01 * m12 - m02 * m11
            a11, a12, a22 = m00 * m22 - m02 * m02, m01 * m02 - m00 * m12, m00 * m11 - m01 * m01
            det = m00 * a00 + m01 * a01 + m02 * a02
            if not (det > 0.0) or not np.isfinite(det):  # J J^T is positive semi-definite: 0 is rank lost
                status_out[b] = SINGULAR
                continue
            inv = 1.0 / det
            fro2 = 0.0
            for j in range(n):
                u0, u1, u2 = J3[0, j], J3[1, j], J3[2, j]
                P[j, 0] = (u0 * a00 + u1 * a01 + u2 * a02) * inv
                P[j, 1] = (u0 * a01 + u1 * a11 + u2 * a12) * inv
                P[j, 2] = (u0 * a02 + u1 * a12 + u2 * a22) * inv
                fro2 += P[j, 0] * P[j, 0] + P[j, 1] * P[j, 1] + P[j, 2] * P[j, 2]
            # the chord's floor: 1 / ||P||_F <= sigma_min(J) (every kept row is a length)
            if not np.isfinite(fro2) or fro2 * sigma_floor * sigma_floor >= 1.0:
                status_out[b] = SINGULAR
                continue
            # 2. (47)-(51) at the tool point, world frame; a row that does not converge on this chord leaves (the
            # batched path re-linearizes it at its best iterate, from q_nom again: the same iterates)
            done = False
            total = 0
            best = np.inf
            prev = np.inf
            have_last = False
            step = np.inf
            cap = min(max_iter, PASS_ITER)
            for r in range(cap + 1):
                flange_pose_inlined(q_out, b, sT, use_s, True, mdl, chn, baseR, basep, FR, Fp, FJ, False, scr, 0,
                                    r == 0)  # at r = 0 the command is q_nom: its joint variables are in the scratch
                p0 = Fp[0, 0] + FR[0, 0, 0] * c0 + FR[0, 1, 0] * c1 + FR[0, 2, 0] * c2
                p1 = Fp[1, 0] + FR[1, 0, 0] * c0 + FR[1, 1, 0] * c1 + FR[1, 2, 0] * c2
                p2 = Fp[2, 0] + FR[2, 0, 0] * c0 + FR[2, 1, 0] * c1 + FR[2, 2, 0] * c2
                e0, e1, e2 = t0 - p0, t1 - p1, t2 - p2
                res = np.sqrt(e0 * e0 + e1 * e1 + e2 * e2)
                if res < best:
                    best = res
                    for j in range(n):
                        qbest[j] = q_out[j, b]
                ss = 0.0
                for j in range(n):
                    x = P[j, 0] * e0 + P[j, 1] * e1 + P[j, 2] * e2
                    dq[j] = x
                    ss += x * x
                step = np.sqrt(ss)
                if have_last:  # good Broyden, as newton.fixed_jacobian_iterations
                    ss = 0.0
                    sd = 0.0
                    for j in range(n):
                        ss += last[j] * last[j]
                        sd += last[j] * dq[j]
                    den = ss - sd
                    if abs(den) > 0.1 * ss:
                        f = 1.0 / den
                        s0 = s1 = s2 = 0.0
                        for j in range(n):
                            s0 += last[j] * P[j, 0]
                            s1 += last[j] * P[j, 1]
                            s2 += last[j] * P[j, 2]
                        for j in range(n):
                            g = dq[j] * f
                            P[j, 0] += g * s0
                            P[j, 1] += g * s1
                            P[j, 2] += g * s2
                        g = ss * f
                        step = 0.0
                        for j in range(n):
                            dq[j] *= g
                            step += dq[j] * dq[j]
                        step = np.sqrt(step)
                if step < tol and res <= residual_tol:
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
            it_out[b] = total
            if not done:
                status_out[b] = NOT_CONTRACTING
                continue
            # the pose error at the tool point in F_a's frame (kernel.pose_error_soa): R^T (goal - p), ½ R^T Σ a × g
            wx = wy = wz = 0.0
            for j in range(3):
                ax, ay, az = FR[0, j, 0], FR[1, j, 0], FR[2, j, 0]
                gx, gy, gz = GR[0, j], GR[1, j], GR[2, j]
                wx += ay * gz - az * gy
                wy += az * gx - ax * gz
                wz += ax * gy - ay * gx
            for k in range(3):
                de_out[k, b] = FR[0, k, 0] * e0 + FR[1, k, 0] * e1 + FR[2, k, 0] * e2
                de_out[3 + k, b] = 0.5 * (FR[0, k, 0] * wx + FR[1, k, 0] * wy + FR[2, k, 0] * wz)
            step_out[b] = step
            # 3. a calibration-sized correction on q_nom's branch (branch.branch_changed)
            far = 0.0
            beyond = False
            for j in range(n):
                d = abs(q_out[j, b] - q_nom[b, j])
                far = max(far, d)
                if d > max_corr[j]:
                    beyond = True
            if beyond:
                status_out[b] = BEYOND
                continue
            # the nominal Jacobian at the command the last evaluation confirmed (its joint variables are in the scratch)
            flange_pose(q_out, b, sT, False, False, mdl, chn, eyeR, zero_p, FR, Fp, FJ, True, scr, 0, True)
            if det_sign_column(FJ, 0, A) != sign0:
                status_out[b] = BRANCH_SIGN
                continue
            if far > path_above and path_crosses(q_nom[b], q_out[:, b], qpath, mdl, chn, eyeR, zero_p, PR, Pp, FJ,
                                                 scr, A, sign0):
                status_out[b] = BRANCH_SIGN
                continue
            status_out[b] = DONE


def solve_positions(fused, q_nom: torch.Tensor, direction: torch.Tensor | None, tool: torch.Tensor, *, tol: float,
                    residual_tol: float, max_iter: int, contraction: float, max_correction: torch.Tensor | None,
                    path_above: float, sigma_floor: float, tool_set_inverse: torch.Tensor | None = None, **_) -> dict:
    """The compiled 3-DOF pass: q_nom (B, 6), direction (B, 6) or None, tool (B, 3) the tool points (flange frame,
    m) -> dict of q (B, 6), pose_error (B, 6), step (B,), iterations (B,) long, status (B,) int8 (rows with
    status != DONE hold no result); fused: a :class:`.fused.FusedFlange`; the settings as
    :func:`.fused_targets.solve_commands` (the 6-DOF pass's others, refresh and the Lipschitz bound, are taken and
    not used: a row that needs a refresh leaves, and the batched 3-DOF path has no Lipschitz shortcut)."""
    from .fused_targets import _inverse_parts

    B, n = q_nom.shape
    s = np.empty((n, 0)) if direction is None else direction.T.to(torch.float64).contiguous().numpy()
    corr = np.full(n, np.inf) if max_correction is None else max_correction.to(torch.float64).cpu().numpy()
    q = np.empty((n, B))
    de, step = np.full((6, B), np.nan), np.full(B, np.nan)
    it, status = np.zeros(B, dtype=np.int64), np.zeros(B, dtype=np.int8)
    gR, gp = _inverse_parts(tool_set_inverse)
    threads = kernel_threads("position")
    with numba.parallel_chunksize(1):  # dynamic: a thread beside a busy neighbour does not hold up the call
        position_soa(rows(q_nom), s, direction is not None, *fused.model, *fused.chain, *fused.base, *fused.no_base,
                     rows(tool), gR, gp, float(tol), float(residual_tol), int(max_iter), float(contraction), corr,
                     float(path_above), float(sigma_floor), q, de, step, it, status, threads)
    t = torch.from_numpy
    return {"q": t(q).T, "pose_error": t(de).T, "step": t(step), "iterations": t(it), "status": t(status)}


__all__ = ["position_soa", "solve_positions"]
