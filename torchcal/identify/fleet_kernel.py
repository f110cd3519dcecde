"""The factored linearization and step of :mod:`.structured`, compiled with numba: row by row in registers.

Why one module: the compiled twins of :mod:`.structured`'s torch functions, kept together so that numba's cache
(keyed on this file) and the tests that hold each kernel to its torch form stay in one place.

Why this module exists. The torch form of the factored linearization
(:func:`torchcal.identify.structured.factored_linearization`) walks the chain
as ~200 elementwise ops over (rows, joints, 3, 3) tensors; each streams its
operands through memory with trailing dimensions of 3, so it cost 15-18 ms
per FANUC unit (750 rows, ~4 000 flops a row): 20 µs a row, whatever the
batch. The step's per-row half (a 6 x 6 Cholesky factor per row for the
joint errors, M = I - W^T W, the gradient, the per-pose Gram matrices
E^T M E, the exact products A^T M A x) was likewise dozens of small
(rows, 6, 6) / (rows, 3, 57) torch ops and batched 57 x 9 x 57 products
(1.8 GFLOP/s). Here the same arithmetic runs row by row (pose by pose) in
scalars and small scratch arrays, blocks of poses handed to the threads one
at a time (:func:`dynamic`); each pose's Gram matrix is formed in scratch
right after its rows' elimination (no per-row copies of E and M E through
memory) and written pose-major, where the contraction's batched products read
it. Same formulas as the torch form (chain_frames, so3_exp, so3_right_jacobian,
twist_jacobian, joint_axis_jacobian, the Chebyshev recurrence and its
derivative), except where noted: the small-angle series of :func:`_so3_coeffs`, the joint errors'
elimination by Woodbury (:func:`_eliminate_row`), the order of sums; the tests hold both to rounding. CPU, float64, numba importable
(``TORCHCAL_NO_NUMBA`` unset); everything else takes the torch form.
"""

from __future__ import annotations

import math
import os
from contextlib import contextmanager

import numpy as np
import torch

from ..core.compiled import notice

try:  # numba is a dependency, but the torch form computes the same numbers without it
    import numba

    HAVE_NUMBA = os.environ.get("TORCHCAL_NO_NUMBA", "") == ""
except ImportError:  # pragma: no cover
    numba = None
    HAVE_NUMBA = False

if HAVE_NUMBA:
    njit = numba.njit
    prange = numba.prange
else:  # pragma: no cover
    def njit(*args, **kwargs):
        return lambda f: f

    prange = range

_CHUNK = 64  # rows per task
_GATHER = 8  # tasks per unit of gather_rows
_POSES = 16  # poses per task of a unit (scratch is allocated per task: numba's allocations cost ~µs each)


@njit(cache=True)
def _so3_coeffs(w0, w1, w2):
    """a, b, c of exp(S(w)) = I + a S + b S^2 (so3_exp) and J_r(w) = I - b S + c S^2 (so3_right_jacobian): one
    sin and cos for both. Below theta^2 = 1e-4 (a joint's error rotation is ~1e-4-1e-3 rad) by their series to
    theta^6, whose first omitted term is < 3e-22: no libm calls, and no cancellation in 1 - cos(theta), which
    costs the closed form up to 1e-16 / theta^2 of b's and c's digits (the torch forms switch at 1e-8)."""
    t2 = w0 * w0 + w1 * w1 + w2 * w2
    if t2 < 1e-4:
        return (1.0 - t2 / 6.0 * (1.0 - t2 / 20.0 * (1.0 - t2 / 42.0)),
                0.5 - t2 / 24.0 * (1.0 - t2 / 30.0 * (1.0 - t2 / 56.0)),
                1.0 / 6.0 - t2 / 120.0 * (1.0 - t2 / 42.0 * (1.0 - t2 / 72.0)))
    t = math.sqrt(t2)
    st, ct = math.sin(t), math.cos(t)
    return st / t, (1.0 - ct) / t2, (t - st) / (t2 * t)


@njit(cache=True)
def _rot(out, w0, w1, w2, a, b):
    """out (3, 3) = I + a S(w) + b S(w)^2."""
    # S = [[0, -w2, w1], [w2, 0, -w0], [-w1, w0, 0]]; S^2 = w w^T - |w|^2 I
    n2 = w0 * w0 + w1 * w1 + w2 * w2
    out[0, 0] = 1.0 + b * (w0 * w0 - n2)
    out[0, 1] = -a * w2 + b * w0 * w1
    out[0, 2] = a * w1 + b * w0 * w2
    out[1, 0] = a * w2 + b * w1 * w0
    out[1, 1] = 1.0 + b * (w1 * w1 - n2)
    out[1, 2] = -a * w0 + b * w1 * w2
    out[2, 0] = -a * w1 + b * w2 * w0
    out[2, 1] = a * w0 + b * w2 * w1
    out[2, 2] = 1.0 + b * (w2 * w2 - n2)


@njit(cache=True)
def _mm(out, x, y):
    for i in range(3):
        for j in range(3):
            out[i, j] = x[i, 0] * y[0, j] + x[i, 1] * y[1, j] + x[i, 2] * y[2, j]


@njit(parallel=True, nogil=True, cache=True)
def linearize_rows(qv, s, use_s, tool, unit, coef, bl, T0R, T0p, RJb, Rbb, pts, coupling, offset, ecoup, eoff,
                   lo, width, oR, op, axes, prismatic, tipR, tipp, Kc, Kb, A, obs, scale, p_out, Jv_out, E_out, Phi_out,
                   jac):
    """Residuals p_out (B, 3) (tool point - obs (B, 3)), Jv_out (B, 3, n), factored E_out (B, 3, n A + 6 + 3 T),
    each times the row's scale (B,) (the whitening, where a copy per output would cost more than the row), and
    Phi_out (B, n, K) of rows (jac False: the residuals alone, the other outputs untouched; Phi_out's K is read)
    qv (B, n) (commands plus joint errors), s (B, n), tool (B,), unit (B,): every unit's masked coef
    (M, n, 6, Kc), backlash (M, n, Kb), base T0 (M, 3, 3) / (M, 3), its twist Jacobian factors RJb, Rbb
    (M, 3, 3) and tool points pts (M, T, 3)."""
    B, n = qv.shape
    K = Phi_out.shape[2]
    ne = n * A
    nchunks = (B + _CHUNK - 1) // _CHUNK
    for c in prange(nchunks):
        theta = np.empty(n)
        u = np.empty(n)
        bs = np.empty((n, K))
        dbs = np.empty((n, K))
        e = np.empty((n, 6))
        de = np.empty((n, 6))
        jR = np.empty((n, 3, 3))
        jp = np.empty((n, 3))
        Ex = np.empty((n, 3, 3))
        R = np.empty((3, 3))
        Rn = np.empty((3, 3))
        M3 = np.empty((3, 3))
        RJ = np.empty((3, 3))
        Jax = np.empty((3, n))
        slope = np.empty((3, n))
        Je = np.empty((3, 6))
        rb = np.empty(n)  # J_r(e_i)'s coefficients, from the chain's pass
        rc = np.empty(n)
        for r in range(c * _CHUNK, min(B, (c + 1) * _CHUNK)):
            mu = unit[r]
            for i in range(n):
                x = offset[i]
                y = eoff[i]
                for j in range(n):
                    x += coupling[i, j] * qv[r, j]
                    y += ecoup[i, j] * qv[r, j]
                theta[i] = x
                u[i] = y
            for i in range(n):
                lam = 2.0 * (u[i] - lo[i]) / width[i] - 1.0
                bs[i, 0] = 1.0
                dbs[i, 0] = 0.0
                if K > 1:
                    bs[i, 1] = lam
                    dbs[i, 1] = 1.0
                for k in range(2, K):
                    bs[i, k] = 2.0 * lam * bs[i, k - 1] - bs[i, k - 2]
                    dbs[i, k] = (2.0 * bs[i, k - 1] + 2.0 * lam * dbs[i, k - 1] - dbs[i, k - 2]) if jac else 0.0
                sc = 2.0 / width[i]
                for k in range(K):
                    dbs[i, k] *= sc
                for t in range(6):
                    x = 0.0
                    y = 0.0
                    for k in range(Kc):
                        x += bs[i, k] * coef[mu, i, t, k]
                        y += dbs[i, k] * coef[mu, i, t, k]
                    e[i, t] = x
                    de[i, t] = y
                if Kb > 0 and use_s:
                    x = 0.0
                    y = 0.0
                    for k in range(Kb):
                        x += bs[i, k] * bl[mu, i, k]
                        y += dbs[i, k] * bl[mu, i, k]
                    e[i, 2] += x * s[r, i]
                    de[i, 2] += y * s[r, i]
            # the chain: Π origin_i · E_i · joint_i(θ_i), rotations and translations apart (chain_frames)
            for a in range(3):
                for b in range(3):
                    R[a, b] = T0R[mu, a, b]
            p0, p1, p2 = T0p[mu, 0], T0p[mu, 1], T0p[mu, 2]
            for i in range(n):
                p0 += R[0, 0] * op[i, 0] + R[0, 1] * op[i, 1] + R[0, 2] * op[i, 2]
                p1 += R[1, 0] * op[i, 0] + R[1, 1] * op[i, 1] + R[1, 2] * op[i, 2]
                p2 += R[2, 0] * op[i, 0] + R[2, 1] * op[i, 1] + R[2, 2] * op[i, 2]
                _mm(Rn, R, oR[i])
                ea, eb, rc[i] = _so3_coeffs(e[i, 0], e[i, 1], e[i, 2])
                rb[i] = eb  # J_r's a is exp's b
                _rot(Ex[i], e[i, 0], e[i, 1], e[i, 2], ea, eb)
                p0 += Rn[0, 0] * e[i, 3] + Rn[0, 1] * e[i, 4] + Rn[0, 2] * e[i, 5]
                p1 += Rn[1, 0] * e[i, 3] + Rn[1, 1] * e[i, 4] + Rn[1, 2] * e[i, 5]
                p2 += Rn[2, 0] * e[i, 3] + Rn[2, 1] * e[i, 4] + Rn[2, 2] * e[i, 5]
                _mm(R, Rn, Ex[i])
                for a in range(3):
                    for b in range(3):
                        jR[i, a, b] = R[a, b]
                jp[i, 0], jp[i, 1], jp[i, 2] = p0, p1, p2
                if prismatic[i]:
                    d0, d1, d2 = axes[i, 0] * theta[i], axes[i, 1] * theta[i], axes[i, 2] * theta[i]
                    p0 += R[0, 0] * d0 + R[0, 1] * d1 + R[0, 2] * d2
                    p1 += R[1, 0] * d0 + R[1, 1] * d1 + R[1, 2] * d2
                    p2 += R[2, 0] * d0 + R[2, 1] * d1 + R[2, 2] * d2
                else:
                    _rot(M3, axes[i, 0], axes[i, 1], axes[i, 2], math.sin(theta[i]), 1.0 - math.cos(theta[i]))
                    _mm(Rn, R, M3)
                    for a in range(3):
                        for b in range(3):
                            R[a, b] = Rn[a, b]
            p0 += R[0, 0] * tipp[0] + R[0, 1] * tipp[1] + R[0, 2] * tipp[2]
            p1 += R[1, 0] * tipp[0] + R[1, 1] * tipp[1] + R[1, 2] * tipp[2]
            p2 += R[2, 0] * tipp[0] + R[2, 1] * tipp[1] + R[2, 2] * tipp[2]
            _mm(Rn, R, tipR)
            tl = tool[r]
            t0, t1, t2 = pts[mu, tl, 0], pts[mu, tl, 1], pts[mu, tl, 2]
            x0 = Rn[0, 0] * t0 + Rn[0, 1] * t1 + Rn[0, 2] * t2 + p0
            x1 = Rn[1, 0] * t0 + Rn[1, 1] * t1 + Rn[1, 2] * t2 + p1
            x2 = Rn[2, 0] * t0 + Rn[2, 1] * t1 + Rn[2, 2] * t2 + p2
            sc = scale[r]
            p_out[r, 0], p_out[r, 1], p_out[r, 2] = (x0 - obs[r, 0]) * sc, (x1 - obs[r, 1]) * sc, (x2 - obs[r, 2]) * sc
            if not jac:
                continue
            for q in range(E_out.shape[2]):
                E_out[r, 0, q] = 0.0
                E_out[r, 1, q] = 0.0
                E_out[r, 2, q] = 0.0
            for i in range(n):
                # twist_jacobian's point rows: [-S(p - o) R J_r(eps), R exp(S(eps))^T]
                _rot(M3, e[i, 0], e[i, 1], e[i, 2], -rb[i], rc[i])
                _mm(RJ, jR[i], M3)
                d0, d1, d2 = x0 - jp[i, 0], x1 - jp[i, 1], x2 - jp[i, 2]
                for k in range(3):
                    c0, c1, c2 = RJ[0, k], RJ[1, k], RJ[2, k]
                    Je[0, k] = -(d1 * c2 - d2 * c1)
                    Je[1, k] = -(d2 * c0 - d0 * c2)
                    Je[2, k] = -(d0 * c1 - d1 * c0)
                    for a in range(3):  # R exp(S(eps))^T: column k = R @ row k of exp
                        Je[a, 3 + k] = jR[i, a, 0] * Ex[i, k, 0] + jR[i, a, 1] * Ex[i, k, 1] + jR[i, a, 2] * Ex[i, k, 2]
                z0 = jR[i, 0, 0] * axes[i, 0] + jR[i, 0, 1] * axes[i, 1] + jR[i, 0, 2] * axes[i, 2]
                z1 = jR[i, 1, 0] * axes[i, 0] + jR[i, 1, 1] * axes[i, 1] + jR[i, 1, 2] * axes[i, 2]
                z2 = jR[i, 2, 0] * axes[i, 0] + jR[i, 2, 1] * axes[i, 1] + jR[i, 2, 2] * axes[i, 2]
                if prismatic[i]:
                    Jax[0, i], Jax[1, i], Jax[2, i] = z0, z1, z2
                else:
                    Jax[0, i] = z1 * d2 - z2 * d1
                    Jax[1, i] = z2 * d0 - z0 * d2
                    Jax[2, i] = z0 * d1 - z1 * d0
                for a in range(3):
                    x = 0.0
                    for t in range(6):
                        x += Je[a, t] * de[i, t]
                    slope[a, i] = x
                    for t in range(6):
                        E_out[r, a, i * A + t] = Je[a, t]
                    if A == 7:
                        E_out[r, a, i * A + 6] = Je[a, 2] * s[r, i] if use_s else 0.0
            for a in range(3):
                for j in range(n):
                    x = 0.0
                    for i in range(n):
                        x += Jax[a, i] * coupling[i, j] + slope[a, i] * ecoup[i, j]
                    Jv_out[r, a, j] = x * sc
            # base twist: twist_jacobian at the base frame; tools: the flange rotation on the row's tool
            d0, d1, d2 = x0 - T0p[mu, 0], x1 - T0p[mu, 1], x2 - T0p[mu, 2]
            for k in range(3):
                c0, c1, c2 = RJb[mu, 0, k], RJb[mu, 1, k], RJb[mu, 2, k]
                E_out[r, 0, ne + k] = -(d1 * c2 - d2 * c1)
                E_out[r, 1, ne + k] = -(d2 * c0 - d0 * c2)
                E_out[r, 2, ne + k] = -(d0 * c1 - d1 * c0)
                for a in range(3):
                    E_out[r, a, ne + 3 + k] = Rbb[mu, a, k]
                    E_out[r, a, ne + 6 + 3 * tl + k] = Rn[a, k]
            for a in range(3):
                for q in range(E_out.shape[2]):
                    E_out[r, a, q] *= sc
            for i in range(n):
                for k in range(K):
                    Phi_out[r, i, k] = bs[i, k]


# fast-math without nnan/ninf: cholesky_rows tests its pivots for NaN
_FAST = {"contract", "arcp", "nsz", "reassoc"}


@njit(cache=True, fastmath=_FAST)
def _finish_row(L, S, r, j0):
    """Row r of the factor L (P, P) of S from column j0 on (its earlier columns done, rows above r finished):
    its entries, its pivot and zeros right of it. -> False where the pivot is not positive (also NaN)."""
    Lr = L[r]
    for jj in range(j0, r):
        Lj = L[jj]
        y = S[r, jj]
        for k in range(jj):
            y -= Lr[k] * Lj[k]
        Lr[jj] = y / Lj[jj]
    x = S[r, r]
    for k in range(r):
        x -= Lr[k] * Lr[k]
    if not x > 0.0:
        return False
    Lr[r] = math.sqrt(x)
    for k in range(r + 1, L.shape[0]):
        Lr[k] = 0.0
    return True


@njit(parallel=True, nogil=True, cache=True, fastmath=_FAST)
def cholesky_rows(S, L, info):
    """L (m, P, P) lower triangular with L L^T = S (m, P, P) (its lower triangle read), one unit per task;
    info (m,): 0, or the index + 1 of the first pivot that is not positive (torch.linalg.cholesky_ex's
    convention; that unit's L is then incomplete). Row by row (Cholesky-Banachiewicz), two rows and four
    columns a pass: each load of a row's entries serves four dot products and each load of the four columns
    two, eight sums in registers (the dot products' loads, not their multiplications, bound this on a CPU):
    0.57-0.91 ms a FANUC unit (P = 285) against 1.0-1.4 ms two columns a pass, and 1.0 ms for
    torch.linalg.cholesky, on one thread."""
    m, P, _ = S.shape
    for u in prange(m):
        Lu, Su = L[u], S[u]
        info[u] = 0
        i = 0
        while i < P:
            two = i + 1 < P
            i2 = i + 1 if two else i  # the second row (the first again where there is none: read, not written)
            Li, Lk = Lu[i], Lu[i2]
            j = 0
            while j + 3 < i:  # columns j..j+3 of rows i, i + 1: all their terms from the finished rows j..j+3
                La, Lb, Lc, Ld = Lu[j], Lu[j + 1], Lu[j + 2], Lu[j + 3]
                ya, yb, yc, yd = Su[i, j], Su[i, j + 1], Su[i, j + 2], Su[i, j + 3]
                za, zb, zc, zd = Su[i2, j], Su[i2, j + 1], Su[i2, j + 2], Su[i2, j + 3]
                for k in range(j):
                    li, lk = Li[k], Lk[k]
                    a, b, c, d = La[k], Lb[k], Lc[k], Ld[k]
                    ya -= li * a
                    yb -= li * b
                    yc -= li * c
                    yd -= li * d
                    za -= lk * a
                    zb -= lk * b
                    zc -= lk * c
                    zd -= lk * d
                ya = ya / La[j]
                yb = (yb - ya * Lb[j]) / Lb[j + 1]
                yc = (yc - ya * Lc[j] - yb * Lc[j + 1]) / Lc[j + 2]
                yd = (yd - ya * Ld[j] - yb * Ld[j + 1] - yc * Ld[j + 2]) / Ld[j + 3]
                Li[j], Li[j + 1], Li[j + 2], Li[j + 3] = ya, yb, yc, yd
                if two:
                    za = za / La[j]
                    zb = (zb - za * Lb[j]) / Lb[j + 1]
                    zc = (zc - za * Lc[j] - zb * Lc[j + 1]) / Lc[j + 2]
                    zd = (zd - za * Ld[j] - zb * Ld[j + 1] - zc * Ld[j + 2]) / Ld[j + 3]
                    Lk[j], Lk[j + 1], Lk[j + 2], Lk[j + 3] = za, zb, zc, zd
                j += 4
            # row i's last columns and pivot, then row i + 1's (row i finished)
            if not _finish_row(Lu, Su, i, j):
                info[u] = i + 1
                break
            if not two:
                break
            if not _finish_row(Lu, Su, i2, j):
                info[u] = i2 + 1
                break
            i += 2


@njit(parallel=True, nogil=True, cache=True, fastmath=_FAST)
def cholesky_solve_rows(L, b, x):
    """x (m, P) with L L^T x = b (m, P), L (m, P, P) from :func:`cholesky_rows`."""
    m, P = b.shape
    for u in prange(m):
        Lu, xu = L[u], x[u]
        for i in range(P):
            y = b[u, i]
            Li = Lu[i]
            for k in range(i):
                y -= Li[k] * xu[k]
            xu[i] = y / Li[i]
        for i in range(P - 1, -1, -1):  # L^T x = y by rows of L (contiguous): x_i known, out of the rows above
            xi = xu[i] / Lu[i, i]
            xu[i] = xi
            Li = Lu[i]
            for k in range(i):
                xu[k] -= xi * Li[k]


def available(device) -> bool:
    """Whether the compiled kernel serves tensors on ``device`` (CPU, numba importable)."""
    return HAVE_NUMBA and torch.device(device).type == "cpu"


@torch.no_grad()
def factored_linearization_fused(model, st, params: dict, q, tool, direction, v, obs, scale=None, out=None,
                                 jac: bool = True):
    """:func:`torchcal.identify.structured.factored_linearization` by :func:`linearize_rows` (same arguments,
    same results to rounding). scale: (m, R) each row's whitening, applied to the residual, Jv and E (None: 1).
    out: (name, shape, like) -> the tensor to write an output into (a :class:`~.workspace.Workspace`'s take
    bound to a slot; None: allocated). jac: False, the residual (m, R, 3) alone (a trial point's)."""
    from ..kinematics.transforms import so3_exp, twist_to_transform
    from ..models.jacobian import so3_right_jacobian

    je = model.joint_errors
    m, R, n = q.shape
    B = m * R
    f64 = dict(dtype=torch.float64, device=q.device)
    coef = (params["joint_errors.coef"] * je.mask).contiguous()
    Kb = st.Kb
    bl = (params["joint_errors.backlash"] * je.backlash_mask).contiguous() if Kb > 0 else torch.zeros(m, n, 1, **f64)
    twist = params["base.twist"]
    T0 = model.base.nominal @ twist_to_transform(twist)  # (m, 4, 4)
    T0R, T0p = T0[:, :3, :3].contiguous(), T0[:, :3, 3].contiguous()
    RJb = (T0R @ so3_right_jacobian(twist[:, :3])).contiguous()
    Rbb = (T0R @ so3_exp(twist[:, :3]).transpose(-1, -2)).contiguous()
    pts = (model.tools.nominal + params["tools.delta"]).contiguous()
    use_s = direction is not None and Kb > 0
    s = direction.reshape(B, n).to(**f64).contiguous() if direction is not None else torch.zeros(B, n, **f64)
    unit = torch.arange(m, device=q.device).repeat_interleave(R)
    qv = (q + v).reshape(B, n).contiguous()
    if out is None:
        def out(name, shape, like):
            return like.new_empty(shape)
    like = q.new_empty(0, dtype=torch.float64)
    p_out = out("p", (B, 3), like)
    rows = B if jac else 1  # a residual alone: the other outputs only lend the kernel their shapes
    Jv, E, Phi = out("Jv", (rows, 3, n), like), out("E", (rows, 3, st.ne + st.Nd), like), out("Phi", (rows, n, st.K), like)
    sc = torch.ones(B, **f64) if scale is None else scale.reshape(B).to(**f64)
    npy = lambda t: t.detach().contiguous().numpy()  # noqa: E731
    with dynamic():
        linearize_rows(npy(qv), npy(s), use_s, npy(tool.reshape(B)), npy(unit), npy(coef), npy(bl), npy(T0R), npy(T0p),
                       npy(RJb), npy(Rbb), npy(pts), npy(model.coupling), npy(model.offset), npy(model.error_coupling),
                       npy(model.error_offset), npy(je.ranges[:, 0]), npy(je.ranges[:, 1] - je.ranges[:, 0]),
                       npy(model.origins[:, :3, :3]), npy(model.origins[:, :3, 3]), npy(model.axes),
                       npy(model.prismatic), npy(model.tip[:3, :3]), npy(model.tip[:3, 3]), st.Kc, Kb, st.A,
                       npy(obs.reshape(B, 3).to(**f64)), npy(sc), p_out.numpy(), Jv.numpy(), E.numpy(), Phi.numpy(),
                       bool(jac))
    if not jac:
        return p_out.view(m, R, 3)
    return p_out.view(m, R, 3), Jv.view(m, R, 3, n), E.view(m, R, 3, -1), Phi.view(m, R, n, st.K)


@njit(parallel=True, nogil=True, cache=True, fastmath=True)
def gram_last(ZT, YT, n, A, pair, Gs, Gsd, Gdd):
    """Per-pose Gram matrices G_p = sum over the pose's rows of E_r^T Y_r, the pose axis last and innermost
    (unit stride: the products vectorize over poses, whatever the column count). ZT, YT: (m, S, Q, Pp), the
    S = T d rows and coordinates of every pose (zero where a pose has fewer rows). Written where the
    contraction reads them: Gs (npair, m, A, A, Pp) the joint pairs i <= j (pair (n, n) their index),
    Gsd (m, n, A, Nd, Pp) structured x dense, Gdd (m, Nd, Nd) dense x dense summed over the poses."""
    m, S, Q, Pp = ZT.shape
    ne = n * A
    Nd = Q - ne
    for job in prange(m * Q):
        u = job // Q
        q1 = job % Q
        acc = np.empty(Pp)
        q0 = (q1 // A) * A if q1 < ne else ne
        for q2 in range(q0, Q):
            for p in range(Pp):
                acc[p] = 0.0
            for s in range(S):
                for p in range(Pp):
                    acc[p] += ZT[u, s, q1, p] * YT[u, s, q2, p]
            if q1 < ne:
                i, a = q1 // A, q1 % A
                if q2 < ne:
                    j, b = q2 // A, q2 % A
                    k = pair[i, j]
                    for p in range(Pp):
                        Gs[k, u, a, b, p] = acc[p]
                else:
                    for p in range(Pp):
                        Gsd[u, i, a, q2 - ne, p] = acc[p]
            else:
                x = 0.0
                for p in range(Pp):
                    x += acc[p]
                Gdd[u, q1 - ne, q2 - ne] = x
                Gdd[u, q2 - ne, q1 - ne] = x


def pose_last(t: torch.Tensor, slots: torch.Tensor) -> torch.Tensor:
    """(m, R, d, Q) per-row values -> (m, T d, Q, Pp) per pose, pose axis last (zero where a pose has fewer rows)."""
    m, R, d, Q = t.shape
    Pp, T = slots.shape[1:]
    g = torch.cat([t, t.new_zeros(m, 1, d, Q)], 1)[torch.arange(m)[:, None, None], slots]  # (m, Pp, T, d, Q)
    return g.permute(0, 2, 3, 4, 1).reshape(m, T * d, Q, Pp).contiguous()


def gram_fused(ZT: torch.Tensor, YT: torch.Tensor, n: int, A: int):
    """(Gs (npair, m, A, A, Pp), Gsd (m, n, A, Nd, Pp), Gdd (m, Nd, Nd), pi, pj) of :func:`gram_last` from
    the pose-last E and M E (m, T d, Q, Pp) (:func:`pose_last`, or written so by :func:`schur_rows`)."""
    m, S, Q, Pp = ZT.shape
    pi, pj = torch.triu_indices(n, n)
    pair = torch.zeros(n, n, dtype=torch.long)
    pair[pi, pj] = torch.arange(pi.numel())
    Nd = Q - n * A
    Gs = torch.empty(pi.numel(), m, A, A, Pp, dtype=ZT.dtype)
    Gsd = torch.empty(m, n, A, Nd, Pp, dtype=ZT.dtype)
    Gdd = torch.empty(m, Nd, Nd, dtype=ZT.dtype)
    gram_last(ZT.numpy(), YT.numpy(), n, A, pair.numpy(), Gs.numpy(), Gsd.numpy(), Gdd.numpy())
    return Gs, Gsd, Gdd, pi, pj


def pose_blocks(Pp: int) -> int:
    """Tasks per unit of :func:`schur_rows` and :func:`apply_rows`: its poses in blocks of :data:`_POSES`."""
    return (Pp + _POSES - 1) // _POSES


@contextmanager
def dynamic():
    """Hand a parallel kernel's tasks to the threads one at a time: with numba's static split, a thread that
    shares its core with another process holds up the whole call (as torchcal.compensate.fused does). Every
    kernel call of this module runs inside it, so it is also where a cold cache is announced (once a process)."""
    if HAVE_NUMBA:
        notice("fleet")
        with numba.parallel_chunksize(1):
            yield
    else:  # pragma: no cover
        yield


@njit(parallel=True, nogil=True, cache=True)
def gather_rows(src, index, out):
    """out[u, t] = src[u, index[t]]: src (m, F), index (N,), out (m, N)."""
    m, N = out.shape
    for job in prange(m * _GATHER):
        u, c = job // _GATHER, job % _GATHER
        for t in range(c * N // _GATHER, (c + 1) * N // _GATHER):
            out[u, t] = src[u, index[t]]


@njit(cache=True, fastmath=True)
def _eliminate_row(f, C, E, V, w_v, mu, Dinv, gv, Mr, Y, h, hh):
    """One row, from views of it (f (d,), C (d, n), E (d, Q), V, w_v (n,)): its joint errors eliminated into
    the views Dinv (n,), gv (n,), Mr (d, d) and Y = Mr E (d, Q); h = E^T y (Q,), y the row's residual with the
    joint errors' response out, and hh (Q,) E's squared column norms: the row's terms of the gradient and of
    the diagonal of A^T A before its basis values (:func:`schur_rows` adds them in). d = 3 (point targets).

    The damped H_vv = C^T C + diag(w_v), its diagonal times 1 + mu, is D + C^T C with D diagonal
    (D_i = mu |C_i|^2 + (1 + mu) w_v,i), a rank-3 update of a diagonal. So (Woodbury) C H_vv^-1 = Mr C D^-1
    with Mr = I - C H_vv^-1 C^T = (I + C D^-1 C^T)^-1: a 3 x 3 inverse per row instead of the torch form's
    6 x 6 Cholesky factor and its inverse (half of this kernel's time went there), and no cancellation in
    I - W^T W where the joint errors explain most of a row. The residual with the joint errors' response
    out, f - C H_vv^-1 g_v (g_v = C^T f + w_v V), is Mr (f - C D^-1 (w_v V)); the joint-error step
    (:func:`apply_rows`) is H_vv^-1 x = D^-1 x - D^-1 C^T Mr C D^-1 x."""
    Q = E.shape[1]
    n = C.shape[1]
    f0, f1, f2 = f[0], f[1], f[2]
    n00, n01, n02, n11, n12, n22 = 1.0, 0.0, 0.0, 1.0, 0.0, 1.0  # N = I + C D^-1 C^T
    r0, r1, r2 = f0, f1, f2  # f - C D^-1 (w_v V)
    for i in range(n):
        c0, c1, c2 = C[0, i], C[1, i], C[2, i]
        w = w_v[i]
        di = 1.0 / (mu * (c0 * c0 + c1 * c1 + c2 * c2) + (1.0 + mu) * w)
        Dinv[i] = di
        wv = w * V[i]
        gv[i] = c0 * f0 + c1 * f1 + c2 * f2 + wv
        r0 -= c0 * (di * wv)
        r1 -= c1 * (di * wv)
        r2 -= c2 * (di * wv)
        a0, a1, a2 = c0 * di, c1 * di, c2 * di
        n00 += a0 * c0
        n01 += a0 * c1
        n02 += a0 * c2
        n11 += a1 * c1
        n12 += a1 * c2
        n22 += a2 * c2
    # N is symmetric positive definite with eigenvalues >= 1: its adjugate over its determinant (>= 1)
    a00, a01, a02 = n11 * n22 - n12 * n12, n02 * n12 - n01 * n22, n01 * n12 - n02 * n11
    a11, a12, a22 = n00 * n22 - n02 * n02, n01 * n02 - n00 * n12, n00 * n11 - n01 * n01
    idet = 1.0 / (n00 * a00 + n01 * a01 + n02 * a02)
    m00, m01, m02, m11, m12, m22 = a00 * idet, a01 * idet, a02 * idet, a11 * idet, a12 * idet, a22 * idet
    Mr[0, 0], Mr[0, 1], Mr[0, 2] = m00, m01, m02
    Mr[1, 0], Mr[1, 1], Mr[1, 2] = m01, m11, m12
    Mr[2, 0], Mr[2, 1], Mr[2, 2] = m02, m12, m22
    y0 = m00 * r0 + m01 * r1 + m02 * r2
    y1 = m01 * r0 + m11 * r1 + m12 * r2
    y2 = m02 * r0 + m12 * r1 + m22 * r2
    # Y = Mr E, E^T y and the squared column norms, three coordinates (d = 3) per column: vectorized over Q
    E0, E1, E2 = E[0], E[1], E[2]
    Y0, Y1, Y2 = Y[0], Y[1], Y[2]
    for q in range(Q):
        e0, e1, e2 = E0[q], E1[q], E2[q]
        Y0[q] = m00 * e0 + m01 * e1 + m02 * e2
        Y1[q] = m01 * e0 + m11 * e1 + m12 * e2
        Y2[q] = m02 * e0 + m12 * e1 + m22 * e2
        h[q] = e0 * y0 + e1 * y1 + e2 * y2
        hh[q] = e0 * e0 + e1 * e1 + e2 * e2


@njit(parallel=True, nogil=True, cache=True, fastmath=True)
def schur_rows(f, C, E, Phi, V, w_v, mu, slots, n, A, pair, gram, Dinv_o, gv_o, M_o, Gs, Gsd, Gdd_b, gx_b, dg_b):
    """The per-row half of a factored Gauss-Newton step and the per-pose Gram matrices, one task per block of
    poses (:func:`pose_blocks`), every unit's. gram=False: the rows' terms alone (Gs, Gsd, Gdd_b untouched): the
    units whose normal matrix is another unit's (:func:`torchcal.identify.structured.structured_steps`' shared).

    Each row's joint errors eliminated (:func:`_eliminate_row`): Dinv_o, gv_o (m, R, n), M_o (m, R, d, d).
    Each pose's G_p = sum over its rows of E_r^T M_r E_r, formed in
    scratch and written pose-major, the units of a pose together: Gs (npair, Pp, m, A, A) the joint pairs
    i <= j (pair (n, n) their index), Gsd (n, Pp, m, A, Nd), both flattened. A task walks its poses and, for
    each, the units, so its writes advance through each pair's block in order (with the pose axis last, as
    :func:`gram_last` writes it, or a task per unit, they jump by pages and miss the TLB and the prefetcher: 1.5
    ms a unit, as much as the products); and the contraction reads a pair's block as one (Pp, m A A) matrix.
    Per block, the dense x dense Gdd_b (m, NB, Nd, Nd) summed over its poses, the extended gradient gx_b and
    diagonal dg_b (m, NB, size) summed over its rows (each row with its own basis values): no two threads add
    into one place, and the result does not depend on the thread count."""
    m, R, d, Q = E.shape
    Pp, T = slots.shape[1], slots.shape[2]
    K = Phi.shape[3]
    ne = n * A
    ns = ne * K
    Nd = Q - ne
    NB = gx_b.shape[1]
    for b in prange(NB):
        Hp = np.empty((T, Q))  # the pose's rows' E^T y and squared column norms
        HHp = np.empty((T, Q))
        Yp = np.empty((T * d, Q))  # the pose's rows' M E, stacked
        rows = np.empty(T, dtype=np.int64)
        Gf = np.empty(Q * Q)
        G = Gf.reshape((Q, Q))
        for u in range(m):
            gx_b[u, b] = 0.0
            dg_b[u, b] = 0.0
            if gram:
                Gdd_b[u, b] = 0.0
        for p in range(b * _POSES, min(Pp, (b + 1) * _POSES)):
            for u in range(m):
                gxl, dgl = gx_b[u, b], dg_b[u, b]
                nr = 0
                for t in range(T):
                    r = slots[u, p, t]
                    if r >= R:
                        continue
                    _eliminate_row(f[u, r], C[u, r], E[u, r], V[u, r], w_v[u, r], mu[u], Dinv_o[u, r], gv_o[u, r],
                                   M_o[u, r], Yp[nr * d:(nr + 1) * d], Hp[nr], HHp[nr])
                    rows[nr] = r
                    nr += 1
                # the rows' terms of the extended gradient and diagonal, each row with its own basis values, the
                # pose's rows together: one load and store of gxl, dgl per nr products, not per product
                for i in range(n):
                    for a in range(A):
                        col = i * A + a
                        o = col * K
                        if nr == 3:
                            Pa, Pb, Pc = Phi[u, rows[0], i], Phi[u, rows[1], i], Phi[u, rows[2], i]
                            xa, xb, xc, ea, eb, ec = Hp[0, col], Hp[1, col], Hp[2, col], HHp[0, col], HHp[1, col], HHp[2, col]
                            for k in range(K):
                                pa, pb, pc = Pa[k], Pb[k], Pc[k]
                                gxl[o + k] += xa * pa + xb * pb + xc * pc
                                dgl[o + k] += ea * (pa * pa) + eb * (pb * pb) + ec * (pc * pc)
                        else:
                            for t in range(nr):
                                Pt = Phi[u, rows[t], i]
                                x, e = Hp[t, col], HHp[t, col]
                                for k in range(K):
                                    gxl[o + k] += x * Pt[k]
                                    dgl[o + k] += e * (Pt[k] * Pt[k])
                for q in range(ne, Q):
                    for t in range(nr):
                        gxl[ns + q - ne] += Hp[t, q]
                        dgl[ns + q - ne] += HHp[t, q]
                if not gram:
                    continue
                # upper blocks only: a structured row from its joint's first column on (pairs i <= j, the joint's
                # own block whole, as the contraction reads it), a dense row from the diagonal. Row views from
                # column q0, so that the inner loop runs from 0 (no negative-index wraparound: it vectorizes), and
                # a row's three coordinates (d = 3) per pass: a third of the loads and stores of G
                for q1 in range(Q):
                    q0 = (q1 // A) * A if q1 < ne else q1
                    Gr = G[q1, q0:]
                    if nr == 0:
                        Gr[:] = 0.0
                    if nr == 3:  # the usual three tool points: nine coordinate rows per pass, a third of G's traffic
                        Ea, Eb, Ec = E[u, rows[0]], E[u, rows[1]], E[u, rows[2]]
                        z0, z1, z2, z3, z4, z5 = Ea[0, q1], Ea[1, q1], Ea[2, q1], Eb[0, q1], Eb[1, q1], Eb[2, q1]
                        z6, z7, z8 = Ec[0, q1], Ec[1, q1], Ec[2, q1]
                        Y0, Y1, Y2, Y3, Y4 = Yp[0, q0:], Yp[1, q0:], Yp[2, q0:], Yp[3, q0:], Yp[4, q0:]
                        Y5, Y6, Y7, Y8 = Yp[5, q0:], Yp[6, q0:], Yp[7, q0:], Yp[8, q0:]
                        for q2 in range(Gr.size):
                            Gr[q2] = ((z0 * Y0[q2] + z1 * Y1[q2] + z2 * Y2[q2]) + (z3 * Y3[q2] + z4 * Y4[q2] + z5 * Y5[q2])
                                      + (z6 * Y6[q2] + z7 * Y7[q2] + z8 * Y8[q2]))
                        continue
                    for t in range(nr):
                        Er = E[u, rows[t]]
                        z0, z1, z2 = Er[0, q1], Er[1, q1], Er[2, q1]
                        Y0, Y1, Y2 = Yp[3 * t, q0:], Yp[3 * t + 1, q0:], Yp[3 * t + 2, q0:]
                        if t == 0:
                            for q2 in range(Gr.size):
                                Gr[q2] = z0 * Y0[q2] + z1 * Y1[q2] + z2 * Y2[q2]
                        else:
                            for q2 in range(Gr.size):
                                Gr[q2] += z0 * Y0[q2] + z1 * Y1[q2] + z2 * Y2[q2]
                # flat offsets: a 5-d index per entry costs more than the entry's share of the product
                for i in range(n):
                    for j in range(i, n):
                        o = ((pair[i, j] * Pp + p) * m + u) * A * A
                        for a in range(A):
                            g = (i * A + a) * Q + j * A
                            for c in range(A):
                                Gs[o + a * A + c] = Gf[g + c]
                    o = ((i * Pp + p) * m + u) * A * Nd
                    for a in range(A):
                        g = (i * A + a) * Q + ne
                        for c in range(Nd):
                            Gsd[o + a * Nd + c] = Gf[g + c]
                Gl = Gdd_b[u, b]
                for c1 in range(Nd):
                    for c2 in range(c1, Nd):
                        Gl[c1, c2] += G[ne + c1, ne + c2]
        for u in range(m if gram else 0):
            Gl = Gdd_b[u, b]
            for c1 in range(Nd):
                for c2 in range(c1 + 1, Nd):
                    Gl[c2, c1] = Gl[c1, c2]


@njit(parallel=True, nogil=True, cache=True, fastmath=True)
def gradient_rows(r, E, Phi, M, slots, n, A, gx_b):
    """The extended gradient of another whitened residual r (m, R, d) through a step's row projectors M (m, R, d, d)
    (:func:`schur_rows`' M_o): per block of poses (:func:`pose_blocks`), gx_b (m, NB, size) the sum over its rows of
    E_r^T M_r r_r, each row with its own basis values Phi (m, R, n, K); the joint errors' prior term is zero. The
    second right-hand side of geodesic acceleration: the projectors are read, not formed again, and no Gram
    block is touched. d = 3 (point targets)."""
    m, R, d, Q = E.shape
    Pp, T = slots.shape[1], slots.shape[2]
    K = Phi.shape[3]
    ne = n * A
    ns = ne * K
    NB = gx_b.shape[1]
    for b in prange(NB):
        h = np.empty(Q)
        for u in range(m):
            gx_b[u, b] = 0.0
        for p in range(b * _POSES, min(Pp, (b + 1) * _POSES)):
            for u in range(m):
                gxl = gx_b[u, b]
                for t in range(T):
                    row = slots[u, p, t]
                    if row >= R:
                        continue
                    Mr, f = M[u, row], r[u, row]
                    y0 = Mr[0, 0] * f[0] + Mr[0, 1] * f[1] + Mr[0, 2] * f[2]
                    y1 = Mr[1, 0] * f[0] + Mr[1, 1] * f[1] + Mr[1, 2] * f[2]
                    y2 = Mr[2, 0] * f[0] + Mr[2, 1] * f[1] + Mr[2, 2] * f[2]
                    E0, E1, E2 = E[u, row, 0], E[u, row, 1], E[u, row, 2]
                    for q in range(Q):
                        h[q] = E0[q] * y0 + E1[q] * y1 + E2[q] * y2
                    for i in range(n):
                        Pt = Phi[u, row, i]
                        for a in range(A):
                            x = h[i * A + a]
                            o = (i * A + a) * K
                            for k in range(K):
                                gxl[o + k] += x * Pt[k]
                    for q in range(ne, Q):
                        gxl[ns + q - ne] += h[q]


@njit(parallel=True, nogil=True, cache=True, fastmath=True)
def apply_rows(E, Phi, dbx, slots, n, A, final, M, Dinv, gv, f, C, sx_b, dv, lin):
    """A db of every row (E_r times the step's extended values weighted by the row's basis values), one task per
    block of poses (:func:`pose_blocks`), every unit's; final=False: the extended product A^T M A db, each block's
    rows summed into sx_b (m, NB, size); final=True: the joint-error steps dv = -H_vv^-1 (g_v + C^T A db)
    (m, R, n) from :func:`schur_rows`' Dinv, gv and M (Woodbury, as :func:`_eliminate_row` says) and the
    linearized residual lin = f + A db + C dv (m, R, d)."""
    m, R, d, Q = E.shape
    Pp, T = slots.shape[1], slots.shape[2]
    K = Phi.shape[3]
    ne = n * A
    Nd = Q - ne
    ns = ne * K
    NB = (Pp + _POSES - 1) // _POSES
    for b in prange(NB):  # a block of poses, every unit's: the scratch allocated once a task (numba: ~µs each)
        wq = np.empty(Q)
        Adb = np.empty(d)
        MA = np.empty(d)
        tmp = np.empty(n)
        sxl = np.empty(sx_b.shape[2])  # zeroed per unit below
        for u in range(m):
            dbu = dbx[u]
            if not final:
                sxl[:] = 0.0
            for p in range(b * _POSES, min(Pp, (b + 1) * _POSES)):
                for t in range(T):
                    r = slots[u, p, t]
                    if r >= R:
                        continue
                    Pr, Er = Phi[u, r], E[u, r]
                    for i in range(n):
                        for a in range(A):
                            col = i * A + a
                            x = 0.0
                            for k in range(K):
                                x += Pr[i, k] * dbu[col * K + k]
                            wq[col] = x
                    for q in range(Nd):
                        wq[ne + q] = dbu[ns + q]
                    for a in range(d):
                        x = 0.0
                        for q in range(Q):
                            x += Er[a, q] * wq[q]
                        Adb[a] = x
                    if not final:
                        for a in range(d):
                            MA[a] = M[u, r, a, 0] * Adb[0] + M[u, r, a, 1] * Adb[1] + M[u, r, a, 2] * Adb[2]
                        for i in range(n):
                            for a in range(A):
                                col = i * A + a
                                h = E[u, r, 0, col] * MA[0] + E[u, r, 1, col] * MA[1] + E[u, r, 2, col] * MA[2]
                                for k in range(K):
                                    sxl[col * K + k] += h * Phi[u, r, i, k]
                        for q in range(Nd):
                            sxl[ns + q] += E[u, r, 0, ne + q] * MA[0] + E[u, r, 1, ne + q] * MA[1] + E[u, r, 2, ne + q] * MA[2]
                    else:
                        s0 = s1 = s2 = 0.0  # C D^-1 x, x = g_v + C^T A db
                        for i in range(n):
                            c0, c1, c2 = C[u, r, 0, i], C[u, r, 1, i], C[u, r, 2, i]
                            y = Dinv[u, r, i] * (gv[u, r, i] + c0 * Adb[0] + c1 * Adb[1] + c2 * Adb[2])
                            tmp[i] = y
                            s0 += c0 * y
                            s1 += c1 * y
                            s2 += c2 * y
                        t0 = M[u, r, 0, 0] * s0 + M[u, r, 0, 1] * s1 + M[u, r, 0, 2] * s2
                        t1 = M[u, r, 1, 0] * s0 + M[u, r, 1, 1] * s1 + M[u, r, 1, 2] * s2
                        t2 = M[u, r, 2, 0] * s0 + M[u, r, 2, 1] * s1 + M[u, r, 2, 2] * s2
                        for i in range(n):
                            dv[u, r, i] = Dinv[u, r, i] * (C[u, r, 0, i] * t0 + C[u, r, 1, i] * t1 + C[u, r, 2, i] * t2) - tmp[i]
                        for a in range(d):
                            x = f[u, r, a] + Adb[a]
                            for j in range(n):
                                x += C[u, r, a, j] * dv[u, r, j]
                            lin[u, r, a] = x
            if not final:
                for q in range(sxl.size):
                    sx_b[u, b, q] = sxl[q]
