"""Fused CPU evaluation of the flange (modeled F_a(q, s) or nominal F_n(q), optionally with its
body Jacobian), compiled with numba.

:class:`.kernel.FlangeKernel` evaluates the flange as ~150 elementwise torch
ops over the pose axis. Each op streams its operands through memory and pays
a dispatch cost, so on the CPU one evaluation costs ~0.7 µs a pose although
it is only ~1 500 flops. Here the same arithmetic runs pose by pose in
registers, all joints in one pass, poses split over the threads: the
compensation's fixed-Jacobian iteration (Paper II (47)-(50)) evaluates the
flange 6-7 times a pose, so this is where its time goes. The Jacobians (at
q_nom for the chord, in the damped path) come from the same pass: joint
axes, origins and error slopes carried to the base frame as the chain is
walked, then taken into the flange frame and through the joint coupling.

Same formulas as the torch kernel, term for term (Chebyshev recurrence, the
exp(S(ε)) series, column rotation for z axes, Rodrigues otherwise, the same
order of products along the chain); the tests hold both to rounding. Used
only on the CPU in float64 when numba is importable; everything else
(CUDA, float32, no numba) takes the torch kernel.
"""

from __future__ import annotations

import os

import numpy as np
import torch

from ..core.compiled import notice

try:  # numba is a dependency, but the torch kernel computes the same numbers without it
    import numba

    HAVE_NUMBA = os.environ.get("TORCHCAL_NO_NUMBA", "") == ""
except ImportError:  # pragma: no cover - exercised only where numba cannot be installed
    numba = None
    HAVE_NUMBA = False

_CHUNK = 512  # poses per task (the unit of the dynamic schedule)
_RAN = [False]  # a compiled kernel has run in this process (numba and its thread pool are loaded)


def warm() -> bool:
    """True once a compiled kernel has run in this process: small batches may take it from then on (what kept
    them on the torch ops was the first call's ~0.6 s of loading)."""
    return _RAN[0]


def mark_warm() -> None:
    """Record that a compiled kernel is about to run (see :func:`warm`)."""
    _RAN[0] = True


def soa(x: torch.Tensor) -> np.ndarray:
    """(B, k) rows -> (k, B) float64 numpy, contiguous: the compiled kernels' pose-last layout."""
    return x.T.to(torch.float64).contiguous().numpy()


def rows(x: torch.Tensor) -> np.ndarray:
    """A CPU tensor as C-contiguous float64 numpy, pose-first as given (no copy when it already is)."""
    return x.to(torch.float64).contiguous().numpy()


def poses_soa(T: torch.Tensor) -> tuple[np.ndarray, np.ndarray]:
    """(B, 4, 4) poses -> rotations (3, 3, B), positions (3, B), float64 numpy, pose-last."""
    return T[:, :3, :3].to(torch.float64).permute(1, 2, 0).contiguous().numpy(), soa(T[:, :3, 3])


def kernel_threads(family: str) -> int:
    """Before a compiled kernel of ``family`` (a key of :data:`torchcal.core.compiled.FAMILIES`) runs: numba's pool
    follows torch's thread setting (torchcal.core.threads.limit_threads sets both, so a caller's limit holds), the
    process counts as warm (:func:`warm`), and a cold cache is announced (its compile takes minutes). -> the
    thread count (the rows of the kernel's work arrays: :func:`flange_work`)."""
    notice(family)
    numba.set_num_threads(max(1, min(torch.get_num_threads(), numba.config.NUMBA_NUM_THREADS)))
    mark_warm()
    return numba.get_num_threads()


# Module-level functions, not closures: numba keys a closure's cache entry on its pickled free
# variables (other dispatchers, whose pickles differ from process to process), so closures were
# recompiled in every process (10-26 s per CLI run); globals resolve at compile time and stay cached.
if HAVE_NUMBA:
    from numba.core import cgutils
    from numba.extending import intrinsic

    njit = numba.njit

    def _without_meminfo(context, builder, ty, value):
        if isinstance(ty, numba.types.Array):
            a = context.make_array(ty)(context, builder, value=value)
            a.meminfo = cgutils.get_null_value(a.meminfo.type)
            return a._getvalue()
        if isinstance(ty, numba.types.BaseTuple):
            for i, t in enumerate(ty):
                value = builder.insert_value(value, _without_meminfo(context, builder, t,
                                                                     builder.extract_value(value, i)), i)
        return value

    @intrinsic
    def borrowed(typingctx, a):
        """The array a (or each array of a tuple) without its reference count (a null meminfo): numba increfs and
        decrefs every array argument of a call it does not inline, an atomic op each (flange_pose: ~50 a call, on
        cache lines the threads share; ~12 % of the targets pass). Only for arrays that outlive the view: a
        kernel's arguments, work arrays it allocated before its parallel loop."""
        return a(a), lambda context, builder, sig, args: _without_meminfo(context, builder, sig.args[0], args[0])
else:  # the decorators become no-ops; available() keeps the torch kernel in use
    def njit(*args, **kwargs):
        return lambda f: f

    def borrowed(a):
        return a


FAST = {"contract", "arcp", "nsz", "reassoc"}
"""LLVM's fast-math flags for the compiled flange and the passes built on it: fused multiply-adds, products by
reciprocals instead of divisions by constants (exp_so3's series), reassociated sums (the Chebyshev series, the
3x3 products). Not nnan / ninf: the passes test np.isfinite. Results move by rounding only (the targets pass:
commands within 3e-12 rad, the same rows converged, for 1.2x fewer cycles; see the README's speed notes)."""
inline = dict(cache=True, fastmath=FAST)
# the helpers of the inner loops: LLVM did not inline them (their calls and tuple returns were ~20 % of the targets
# pass); numba's IR-level inlining prefixes the callee's locals with its name. It costs compile time (the targets
# pass: ~48 -> ~76 s, once: cached; with the chain itself inlined at the pass's three hot call sites the first
# compensate_targets call on a cold cache takes ~150 s instead of ~106 s on 2 cores).
inlined = dict(inline="always", cache=True, fastmath=FAST)


@njit(**inlined)
def series(table, i, lam, Km, has_bl, slope):
    """Chebyshev sums of joint i's six error terms and backlash amplitude at lam, (23);
    slope=True: their derivatives d/dlam instead (differentiated recurrence, as chebyshev_with_derivative)."""
    if slope:
        w0 = w1 = w2 = d0 = d1 = d2 = bl = 0.0
    else:
        w0, w1, w2 = table[i, 0, 0], table[i, 1, 0], table[i, 2, 0]
        d0, d1, d2 = table[i, 3, 0], table[i, 4, 0], table[i, 5, 0]
        bl = table[i, 6, 0] if has_bl else 0.0
    t_prev, t_cur = 1.0, lam  # T_k
    s_prev, s_cur = 0.0, 1.0  # dT_k / dlam
    for k in range(1, Km):
        if k >= 2:
            s_prev, s_cur = s_cur, 2.0 * t_cur - s_prev + 2.0 * lam * s_cur
            t_prev, t_cur = t_cur, 2.0 * lam * t_cur - t_prev
        c = s_cur if slope else t_cur
        w0 += table[i, 0, k] * c
        w1 += table[i, 1, k] * c
        w2 += table[i, 2, k] * c
        d0 += table[i, 3, k] * c
        d1 += table[i, 4, k] * c
        d2 += table[i, 5, k] * c
        if has_bl:
            bl += table[i, 6, k] * c
    return w0, w1, w2, d0, d1, d2, bl

@njit(**inlined)
def exp_so3(w0, w1, w2):
    """exp(S(w)) as a row-major 9-tuple, same series as FlangeKernel.error_rotations."""
    t2 = w0 * w0 + w1 * w1 + w2 * w2
    if t2 < 1e-4:
        a = 1.0 - t2 / 6.0 * (1.0 - t2 / 20.0 * (1.0 - t2 / 42.0 * (1.0 - t2 / 72.0)))
        b = 0.5 * (1.0 - t2 / 12.0 * (1.0 - t2 / 30.0 * (1.0 - t2 / 56.0 * (1.0 - t2 / 90.0))))
    else:
        t = np.sqrt(t2)
        a = np.sin(t) / t
        b = (1.0 - np.cos(t)) / t2
    dg = 1.0 - b * t2
    return (b * w0 * w0 + dg, b * w0 * w1 - a * w2, b * w0 * w2 + a * w1,
            b * w1 * w0 + a * w2, b * w1 * w1 + dg, b * w1 * w2 - a * w0,
            b * w2 * w0 - a * w1, b * w2 * w1 + a * w0, b * w2 * w2 + dg)

@njit(**inlined)
def right_jacobian_apply(w0, w1, w2, v0, v1, v2):
    """J_r(w) v, same series as FlangeKernel.right_jacobian_apply."""
    t2 = w0 * w0 + w1 * w1 + w2 * w2
    if t2 < 1e-8:
        a, b = 0.5 - t2 / 24.0, 1.0 / 6.0 - t2 / 120.0
    else:
        t = np.sqrt(t2)
        a, b = (1.0 - np.cos(t)) / t2, (t - np.sin(t)) / (t2 * t)
    c0, c1, c2 = w1 * v2 - w2 * v1, w2 * v0 - w0 * v2, w0 * v1 - w1 * v0
    cc0, cc1, cc2 = w1 * c2 - w2 * c1, w2 * c0 - w0 * c2, w0 * c1 - w1 * c0
    return v0 - a * c0 + b * cc0, v1 - a * c1 + b * cc1, v2 - a * c2 + b * cc2

@njit(**inline)
def row9(a, i):
    """a[i] of a (m, 3, 3) array as a row-major 9-tuple, read by index (a view a[i] costs a refcount pair)."""
    return (a[i, 0, 0], a[i, 0, 1], a[i, 0, 2], a[i, 1, 0], a[i, 1, 1], a[i, 1, 2], a[i, 2, 0], a[i, 2, 1], a[i, 2, 2])

@njit(**inline)
def mul(r, a):
    """9-tuple @ 9-tuple."""
    return (r[0] * a[0] + r[1] * a[3] + r[2] * a[6], r[0] * a[1] + r[1] * a[4] + r[2] * a[7], r[0] * a[2] + r[1] * a[5] + r[2] * a[8],
            r[3] * a[0] + r[4] * a[3] + r[5] * a[6], r[3] * a[1] + r[4] * a[4] + r[5] * a[7], r[3] * a[2] + r[4] * a[5] + r[5] * a[8],
            r[6] * a[0] + r[7] * a[3] + r[8] * a[6], r[6] * a[1] + r[7] * a[4] + r[8] * a[7], r[6] * a[2] + r[7] * a[5] + r[8] * a[8])

@njit(**inline)
def vec(r, v):
    """9-tuple @ 3-tuple."""
    x, y, z = v
    return r[0] * x + r[1] * y + r[2] * z, r[3] * x + r[4] * y + r[5] * z, r[6] * x + r[7] * y + r[8] * z

@njit(**inlined)
def add_column(outJ, b, n, R, v, w, C, i):
    """Add joint i's world velocity (v, w) per unit motion, taken into the flange frame (R^T), to the
    body-Jacobian columns of the controller commands through the chain rule row C[i] (C (n, n))."""
    vx, vy, vz = v
    wx, wy, wz = w
    col = (R[0] * vx + R[3] * vy + R[6] * vz, R[1] * vx + R[4] * vy + R[7] * vz, R[2] * vx + R[5] * vy + R[8] * vz,
           R[0] * wx + R[3] * wy + R[6] * wz, R[1] * wx + R[4] * wy + R[7] * wz, R[2] * wx + R[5] * wy + R[8] * wz)
    for j in range(n):
        cij = C[i, j]
        if cij != 0.0:
            for r in range(6):
                outJ[r, j, b] += col[r] * cij

@njit(**inlined)
def rotate(m, cs, sn, z_axes, Ka, Ka2, i):
    """M @ joint rotation(θ) (cs, sn: cos θ, sin θ): column rotation for +z axes, Rodrigues otherwise (K = Ka[i],
    K2 = Ka2[i])."""
    if z_axes:
        return (m[0] * cs + m[1] * sn, m[1] * cs - m[0] * sn, m[2],
                m[3] * cs + m[4] * sn, m[4] * cs - m[3] * sn, m[5],
                m[6] * cs + m[7] * sn, m[7] * cs - m[6] * sn, m[8])
    mk, mk2 = mul(m, row9(Ka, i)), mul(m, row9(Ka2, i))
    vc = 1.0 - cs
    return (m[0] + sn * mk[0] + vc * mk2[0], m[1] + sn * mk[1] + vc * mk2[1], m[2] + sn * mk[2] + vc * mk2[2],
            m[3] + sn * mk[3] + vc * mk2[3], m[4] + sn * mk[4] + vc * mk2[4], m[5] + sn * mk[5] + vc * mk2[5],
            m[6] + sn * mk[6] + vc * mk2[6], m[7] + sn * mk[7] + vc * mk2[7], m[8] + sn * mk[8] + vc * mk2[8])

@njit(**inline)
def mul_arr_right(m, K):
    """9-tuple @ (3, 3) array."""
    return (m[0] * K[0, 0] + m[1] * K[1, 0] + m[2] * K[2, 0], m[0] * K[0, 1] + m[1] * K[1, 1] + m[2] * K[2, 1],
            m[0] * K[0, 2] + m[1] * K[1, 2] + m[2] * K[2, 2],
            m[3] * K[0, 0] + m[4] * K[1, 0] + m[5] * K[2, 0], m[3] * K[0, 1] + m[4] * K[1, 1] + m[5] * K[2, 1],
            m[3] * K[0, 2] + m[4] * K[1, 2] + m[5] * K[2, 2],
            m[6] * K[0, 0] + m[7] * K[1, 0] + m[8] * K[2, 0], m[6] * K[0, 1] + m[7] * K[1, 1] + m[8] * K[2, 1],
            m[6] * K[0, 2] + m[7] * K[1, 2] + m[8] * K[2, 2])

@njit(**inline)
def gap(k):
    """Rows of k float64 that fill a cache line: the padding after each thread's rows in a work array (work[t, :m]),
    so that two threads write no common line."""
    return (k + 7) // k


@njit(**inline)
def flange_work(threads, n):
    """:func:`flange_pose`'s scratch for n joints, rows for each thread of a parallel kernel (allocated before its
    loop, so that they outlive it: :func:`flange_scratch`; per thread, not per block of poses: a block's first
    touch of fresh rows cost the 2-thread pass ~4 %): th, ue, cs, sn (n,) the joint variables, the
    error series' variables (command, Paper II (24), or joint variable) and cos, sin of the joint variables (kept
    for a second chain at the same command: ``same_q``); zs, os_, ws, ds (n, 3): each joint's axis after E_i,
    the origin of the frame it moves in, and the velocities of E_i's rotation and translation per unit joint
    motion (world frame)."""
    m1, m3 = n + gap(1), n + gap(3)
    T = threads
    return (np.empty((T, m1)), np.empty((T, m1)), np.empty((T, m1)), np.empty((T, m1)),
            np.empty((T, m3, 3)), np.empty((T, m3, 3)), np.empty((T, m3, 3)), np.empty((T, m3, 3)))


@njit(**inline)
def flange_scratch(work, n):
    """The calling thread's scratch in :func:`flange_work` (numba.get_thread_id() < get_num_threads()), borrowed."""
    t = numba.get_thread_id()
    th, ue, cs, sn, zs, os_, ws, ds = work
    return borrowed((th[t, :n], ue[t, :n], cs[t, :n], sn[t, :n], zs[t, :n], os_[t, :n], ws[t, :n], ds[t, :n]))


def _flange_pose(qT, b, sT, use_s, errors, model, chain, baseR, basep, outR, outp, outJ, jacobian, scratch, ob, same_q):
    """Pose b of :func:`flange_soa`: F_a(q, s) or F_n(q) of column b of qT (n, B) into column ob of
    outR (3, 3, .), outp (3, .) [and outJ (6, n, .)]; model: (coupling, offset, ecoupling, eoffset, lo, width,
    table, has_bl), chain: (oR, op, axes, Ka, Ka2, prismatic, z_axes, tipR, tipp), as :class:`FusedFlange`;
    scratch: (th, ue, cs, sn (n,), zs, os_, ws, ds (n, 3)) (:func:`flange_scratch`); same_q: th, ue, cs, sn
    already hold this command's (the last call's command was this one: the other chain, nominal or modeled, at the
    same command). Grouped in tuples: a call with over 30 arguments compiles to CALL_FUNCTION_EX, which numba
    cannot inline.
    One definition shared by the flange kernel and the targets solver (:mod:`.fused_targets`)."""
    coupling, offset, ecoupling, eoffset, lo, width, table, has_bl = model
    oR, op, axes, Ka, Ka2, prismatic, z_axes, tipR, tipp = chain
    th, ue, cs, sn, zs, os_, ws, ds = scratch
    n = qT.shape[0]
    Km = table.shape[2]
    for i in range(0 if same_q else n):
        x = offset[i]
        for j in range(n):
            x += coupling[i, j] * qT[j, b]
        th[i] = x
        y = eoffset[i]
        for j in range(n):
            y += ecoupling[i, j] * qT[j, b]
        ue[i] = y
        cs[i], sn[i] = np.cos(x), np.sin(x)
    # running pose of the chain in scalars (registers)
    R = (baseR[0, 0], baseR[0, 1], baseR[0, 2], baseR[1, 0], baseR[1, 1], baseR[1, 2],
         baseR[2, 0], baseR[2, 1], baseR[2, 2])
    p0, p1, p2 = basep[0], basep[1], basep[2]
    for i in range(n):
        if errors:
            lam = 2.0 * (ue[i] - lo[i]) / width[i] - 1.0
            w0, w1, w2, d0, d1, d2, bl = series(table, i, lam, Km, has_bl, False)
            if has_bl == 1 and use_s:
                w2 += bl * sT[i, b]
            elif has_bl == 2 and use_s:  # along the joint's own screw (table rows 7-12, FlangeKernel.bl_code)
                g = bl * sT[i, b]
                w0, w1, w2 = w0 + g * table[i, 7, 0], w1 + g * table[i, 8, 0], w2 + g * table[i, 9, 0]
                d0, d1, d2 = d0 + g * table[i, 10, 0], d1 + g * table[i, 11, 0], d2 + g * table[i, 12, 0]
            o = row9(oR, i)
            M = mul(o, exp_so3(w0, w1, w2))
            tx, ty, tz = vec(o, (d0, d1, d2))
            tx, ty, tz = tx + op[i, 0], ty + op[i, 1], tz + op[i, 2]
        else:
            M = row9(oR, i)
            tx, ty, tz = op[i, 0], op[i, 1], op[i, 2]
        gx, gy, gz = vec(R, (tx, ty, tz))
        p0, p1, p2 = p0 + gx, p1 + gy, p2 + gz
        if jacobian:
            ax, ay, az = vec(R, vec(M, (axes[i, 0], axes[i, 1], axes[i, 2])))
            zs[i, 0], zs[i, 1], zs[i, 2] = ax, ay, az
            os_[i, 0], os_[i, 1], os_[i, 2] = p0, p1, p2
            if errors:
                scale = 2.0 / width[i]
                v0, v1, v2, u0, u1, u2, vb = series(table, i, lam, Km, has_bl, True)
                if has_bl == 1 and use_s:
                    v2 += vb * sT[i, b]
                elif has_bl == 2 and use_s:
                    g = vb * sT[i, b]
                    v0, v1, v2 = v0 + g * table[i, 7, 0], v1 + g * table[i, 8, 0], v2 + g * table[i, 9, 0]
                    u0, u1, u2 = u0 + g * table[i, 10, 0], u1 + g * table[i, 11, 0], u2 + g * table[i, 12, 0]
                jw = right_jacobian_apply(w0, w1, w2, v0 * scale, v1 * scale, v2 * scale)
                ws[i, 0], ws[i, 1], ws[i, 2] = vec(R, vec(M, jw))
                ds[i, 0], ds[i, 1], ds[i, 2] = vec(R, vec(o, (u0 * scale, u1 * scale, u2 * scale)))
        if prismatic[i]:
            # travel along the axis after E_i; no rotation
            ux, uy, uz = vec(R, vec(M, (axes[i, 0] * th[i], axes[i, 1] * th[i], axes[i, 2] * th[i])))
            p0, p1, p2 = p0 + ux, p1 + uy, p2 + uz
            A = M
        else:
            A = rotate(M, cs[i], sn[i], z_axes, Ka, Ka2, i)
        R = mul(R, A)
    gx, gy, gz = vec(R, (tipp[0], tipp[1], tipp[2]))
    p0, p1, p2 = p0 + gx, p1 + gy, p2 + gz
    R = mul_arr_right(R, tipR)
    for r in range(3):
        for k in range(3):
            outR[r, k, ob] = R[3 * r + k]
    outp[0, ob], outp[1, ob], outp[2, ob] = p0, p1, p2
    if jacobian:
        for j in range(n):
            for r in range(6):
                outJ[r, j, ob] = 0.0
        for i in range(n):
            wx, wy, wz = (0.0, 0.0, 0.0) if prismatic[i] else (zs[i, 0], zs[i, 1], zs[i, 2])
            rx, ry, rz = p0 - os_[i, 0], p1 - os_[i, 1], p2 - os_[i, 2]
            vx, vy, vz = wy * rz - wz * ry, wz * rx - wx * rz, wx * ry - wy * rx
            if prismatic[i]:
                vx, vy, vz = vx + zs[i, 0], vy + zs[i, 1], vz + zs[i, 2]
            # through the joint variable: θ = A q + offset
            add_column(outJ, ob, n, R, (vx, vy, vz), (wx, wy, wz), coupling, i)
            if errors:
                # the error series' slopes move with u = A_u q + b_u, not with the joint variable
                sx, sy, sz = ws[i, 0], ws[i, 1], ws[i, 2]
                tx, ty, tz = sy * rz - sz * ry + ds[i, 0], sz * rx - sx * rz + ds[i, 1], sx * ry - sy * rx + ds[i, 2]
                add_column(outJ, ob, n, R, (tx, ty, tz), (sx, sy, sz), ecoupling, i)


flange_pose = njit(**inline)(_flange_pose)
# the same chain IR-inlined into its caller: the targets pass (.fused_targets) at its three hot call sites (the
# nominal IK, (47)-(51), the corrected target), where the flags (errors, jacobian) fold to constants and no call
# passes ~30 array structs: full calls 1.26-1.37x quiet on 2 threads, measured side by side (one thread's kernel:
# 1.4x in one bench, 0.92-0.98x in another; which part of the call the gain comes from was not isolated)
flange_pose_inlined = njit(**inlined)(_flange_pose)


@njit(parallel=True, cache=True)
def flange_soa(qT, sT, use_s, errors, coupling, offset, ecoupling, eoffset, lo, width, table, has_bl,
               oR, op, axes, Ka, Ka2, prismatic, z_axes, tipR, tipp, baseR, basep, outR, outp, outJ, jacobian, threads):
    """F_a(q, s) (errors=True) or F_n(q) into outR (3, 3, B), outp (3, B); with jacobian=True also
    the body Jacobian w.r.t. the controller commands into outJ (6, n, B), as FlangeKernel; threads: numba's
    (:func:`kernel_threads`)."""
    n, B = qT.shape
    nchunks = (B + _CHUNK - 1) // _CHUNK
    work = flange_work(threads, n)
    (qT, sT, coupling, offset, ecoupling, eoffset, lo, width, table, oR, op, axes, Ka, Ka2, prismatic, tipR, tipp,
     baseR, basep, outR, outp, outJ) = borrowed((qT, sT, coupling, offset, ecoupling, eoffset, lo, width, table, oR, op,
                                                 axes, Ka, Ka2, prismatic, tipR, tipp, baseR, basep, outR, outp, outJ))
    for c in numba.prange(nchunks):
        th, ue, cs, sn, zs, os_, ws, ds = flange_scratch(work, n)
        for b in range(c * _CHUNK, min(B, (c + 1) * _CHUNK)):
            flange_pose(qT, b, sT, use_s, errors, (coupling, offset, ecoupling, eoffset, lo, width, table, has_bl),
                        (oR, op, axes, Ka, Ka2, prismatic, z_axes, tipR, tipp), baseR, basep, outR, outp, outJ,
                        jacobian, (th, ue, cs, sn, zs, os_, ws, ds), b, False)


def _kernels():
    return flange_soa


def available(device: torch.device, dtype: torch.dtype) -> bool:
    """True where the fused kernel applies: numba importable, CPU tensors, float64."""
    return HAVE_NUMBA and device.type == "cpu" and dtype == torch.float64


class FusedFlange:
    """Numpy views of a :class:`.kernel.FlangeKernel`'s parameter snapshot, fed to the compiled kernel."""

    def __init__(self, k):
        def np_(t):
            return np.ascontiguousarray(t.detach().cpu().numpy())

        self.n = k.n
        self.model = (np_(k.coupling), np_(k.offset[:, 0]), np_(k.error_coupling), np_(k.error_offset[:, 0]),
                      np_(k.lo[:, 0]), np_(k.width[:, 0]), np_(k.table),
                      int(k.bl_code))
        self.chain = (np_(k.oR), np_(k.op), np_(k.axes), np_(k.Ka), np_(k.Ka2), np_(k.prismatic), bool(k.z_axes),
                      np_(k.tipR), np_(k.tipp))
        self.base = (np_(k.baseR), np_(k.basep))
        self.no_base = (np.eye(3), np.zeros(3))

    def _run(self, qT, sT, errors: bool, jacobian: bool):
        B = qT.shape[1]
        R = torch.empty(3, 3, B, dtype=torch.float64)
        p = torch.empty(3, B, dtype=torch.float64)
        J = torch.empty(6, self.n, B if jacobian else 0, dtype=torch.float64)
        q = qT.detach().to(torch.float64).contiguous().numpy()
        s = q if sT is None else sT.detach().to(torch.float64).contiguous().numpy()
        # dynamic scheduling, one block of _CHUNK poses at a time: with a static split a thread that shares its
        # core with another process holds up the whole call (a busy neighbour would cost 2x, not 1.33x)
        threads = kernel_threads("flange")
        with numba.parallel_chunksize(1):
            _kernels()(q, s, sT is not None, errors, *self.model, *self.chain, *(self.base if errors else self.no_base),
                       R.numpy(), p.numpy(), J.numpy(), jacobian, threads)
        return (R, p, J) if jacobian else (R, p)

    def flange(self, qT: torch.Tensor, sT: torch.Tensor | None):
        """qT (n, B), sT (n, B) or None -> R (3, 3, B), p (3, B), as FlangeKernel.flange."""
        return self._run(qT, sT, True, False)

    def flange_jacobian(self, qT: torch.Tensor, sT: torch.Tensor | None):
        """-> R, p, J (6, n, B), as FlangeKernel.flange_jacobian."""
        return self._run(qT, sT, True, True)

    def nominal_flange_jacobian(self, qT: torch.Tensor):
        """-> R, p, J (6, n, B), as FlangeKernel.nominal_flange_jacobian."""
        return self._run(qT, None, False, True)
