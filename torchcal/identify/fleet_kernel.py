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
it. Same formulas, term for term, as the torch form
(chain_frames, so3_exp with its Taylor branch, so3_right_jacobian,
twist_jacobian, joint_axis_jacobian, the Chebyshev recurrence and its
derivative); the tests hold both to rounding. CPU, float64, numba importable
(``TORCHCAL_NO_NUMBA`` unset); everything else takes the torch form.
"""

from __future__ import annotations

import math
import os
from contextlib import contextmanager

import numpy as np
import torch

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
def _exp_coeffs(w0, w1, w2):
    """a, b of exp(S(w)) = I + a S + b S^2 (so3_exp, Taylor branch below theta^2 = 1e-8)."""
    t2 = w0 * w0 + w1 * w1 + w2 * w2
    if t2 < 1e-8:
        return 1.0 - t2 / 6.0 + t2 * t2 / 120.0, 0.5 - t2 / 24.0 + t2 * t2 / 720.0
    t = math.sqrt(t2)
    return math.sin(t) / t, (1.0 - math.cos(t)) / t2


@njit(cache=True)
def _rj_coeffs(w0, w1, w2):
    """a, b of J_r(w) = I - a S + b S^2 (so3_right_jacobian, Taylor branch below theta^2 = 1e-8)."""
    t2 = w0 * w0 + w1 * w1 + w2 * w2
    if t2 < 1e-8:
        return 0.5 - t2 / 24.0, 1.0 / 6.0 - t2 / 120.0
    t = math.sqrt(t2)
    return (1.0 - math.cos(t)) / t2, (t - math.sin(t)) / (t2 * t)


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


@njit(parallel=True, cache=True)
def linearize_rows(qv, s, use_s, tool, unit, coef, bl, T0R, T0p, RJb, Rbb, pts, coupling, offset, ecoup, eoff,
                   lo, width, oR, op, axes, prismatic, tipR, tipp, Kc, Kb, A, obs, scale, p_out, Jv_out, E_out, Phi_out):
    """Residuals p_out (B, 3) (tool point - obs (B, 3)), Jv_out (B, 3, n), factored E_out (B, 3, n A + 6 + 3 T),
    each times the row's scale (B,) (the whitening, where a copy per output would cost more than the row), and
    Phi_out (B, n, K) of rows
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
                    dbs[i, k] = 2.0 * bs[i, k - 1] + 2.0 * lam * dbs[i, k - 1] - dbs[i, k - 2]
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
                ea, eb = _exp_coeffs(e[i, 0], e[i, 1], e[i, 2])
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
            for q in range(E_out.shape[2]):
                E_out[r, 0, q] = 0.0
                E_out[r, 1, q] = 0.0
                E_out[r, 2, q] = 0.0
            for i in range(n):
                # twist_jacobian's point rows: [-S(p - o) R J_r(eps), R exp(S(eps))^T]
                ra, rb = _rj_coeffs(e[i, 0], e[i, 1], e[i, 2])
                _rot(M3, e[i, 0], e[i, 1], e[i, 2], -ra, rb)
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


def available(device) -> bool:
    """Whether the compiled kernel serves tensors on ``device`` (CPU, numba importable)."""
    return HAVE_NUMBA and torch.device(device).type == "cpu"


@torch.no_grad()
def factored_linearization_fused(model, st, params: dict, q, tool, direction, v, obs, scale=None):
    """:func:`torchcal.identify.structured.factored_linearization` by :func:`linearize_rows` (same arguments,
    same results to rounding). scale: (m, R) each row's whitening, applied to the residual, Jv and E (None: 1)."""
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
    p_out = torch.empty(B, 3, **f64)
    Jv = torch.empty(B, 3, n, **f64)
    E = torch.empty(B, 3, st.ne + st.Nd, **f64)
    Phi = torch.empty(B, n, st.K, **f64)
    sc = torch.ones(B, **f64) if scale is None else scale.reshape(B).to(**f64)
    npy = lambda t: t.detach().contiguous().numpy()  # noqa: E731
    with dynamic():
        linearize_rows(npy(qv), npy(s), use_s, npy(tool.reshape(B)), npy(unit), npy(coef), npy(bl), npy(T0R), npy(T0p),
                       npy(RJb), npy(Rbb), npy(pts), npy(model.coupling), npy(model.offset), npy(model.error_coupling),
                       npy(model.error_offset), npy(je.ranges[:, 0]), npy(je.ranges[:, 1] - je.ranges[:, 0]),
                       npy(model.origins[:, :3, :3]), npy(model.origins[:, :3, 3]), npy(model.axes),
                       npy(model.prismatic), npy(model.tip[:3, :3]), npy(model.tip[:3, 3]), st.Kc, Kb, st.A,
                       npy(obs.reshape(B, 3).to(**f64)), npy(sc), p_out.numpy(), Jv.numpy(), E.numpy(), Phi.numpy())
    return p_out.view(m, R, 3), Jv.view(m, R, 3, n), E.view(m, R, 3, -1), Phi.view(m, R, n, st.K)


@njit(parallel=True, cache=True, fastmath=True)
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
    shares its core with another process holds up the whole call (as torchcal.compensate.fused does)."""
    if HAVE_NUMBA:
        with numba.parallel_chunksize(1):
            yield
    else:  # pragma: no cover
        yield


@njit(parallel=True, cache=True)
def gather_rows(src, index, out):
    """out[u, t] = src[u, index[t]]: src (m, F), index (N,), out (m, N)."""
    m, N = out.shape
    for job in prange(m * _GATHER):
        u, c = job // _GATHER, job % _GATHER
        for t in range(c * N // _GATHER, (c + 1) * N // _GATHER):
            out[u, t] = src[u, index[t]]


@njit(cache=True, fastmath=True)
def _eliminate_row(f, C, E, Phi, V, w_v, damp, A, H, L, gv, yy, h, hh, ph, ph2, Li, W, zz, Mr, Y, gxl, dgl):
    """One row, from views of it (f (d,), C (d, n), E (d, Q), Phi (n, K), V, w_v (n,)): its joint errors
    eliminated (H_vv = C^T C + diag(w_v), its diagonal times damp = 1 + mu; L L^T = H_vv) into the views
    Li = L^-1 (n, n), W = Li C^T (n, d), zz = Li g_v (n,), Mr = I - W^T W (d, d); Y = Mr E (d, Q); the row's
    terms of the extended gradient (its residual with the joint errors' response out, yy = f - W^T zz) and of
    the diagonal of A^T A added into gxl, dgl (size,). d = 3 (point targets). H, L (n, n), gv (n,), yy (d,),
    h, hh (Q,), ph, ph2 (K,): scratch."""
    d, Q = E.shape
    n, K = Phi.shape
    ne = n * A
    ns = ne * K
    for i in range(n):
        for j in range(n):
            x = 0.0
            for c in range(d):
                x += C[c, i] * C[c, j]
            H[i, j] = x
        H[i, i] += w_v[i]
        x = 0.0
        for c in range(d):
            x += C[c, i] * f[c]
        gv[i] = x + w_v[i] * V[i]
    for i in range(n):
        H[i, i] *= damp
    for i in range(n):
        for j in range(i + 1):
            x = H[i, j]
            for k in range(j):
                x -= L[i, k] * L[j, k]
            if i == j:
                L[i, i] = math.sqrt(x)
            else:
                L[i, j] = x / L[j, j]
        for j in range(i + 1, n):
            L[i, j] = 0.0
    for j in range(n):
        for i in range(n):
            if i < j:
                Li[i, j] = 0.0
                continue
            x = 1.0 if i == j else 0.0
            for k in range(j, i):
                x -= L[i, k] * Li[k, j]
            Li[i, j] = x / L[i, i]
    for i in range(n):
        for c in range(d):
            x = 0.0
            for k in range(i + 1):
                x += Li[i, k] * C[c, k]
            W[i, c] = x
        x = 0.0
        for k in range(i + 1):
            x += Li[i, k] * gv[k]
        zz[i] = x
    for a in range(d):
        x = f[a]
        for i in range(n):
            x -= W[i, a] * zz[i]
        yy[a] = x
        for b in range(d):
            x = 1.0 if a == b else 0.0
            for i in range(n):
                x -= W[i, a] * W[i, b]
            Mr[a, b] = x
    # Y = Mr E, E^T yy and the squared column norms, three coordinates (d = 3) per column: vectorized over Q
    E0, E1, E2 = E[0], E[1], E[2]
    Y0, Y1, Y2 = Y[0], Y[1], Y[2]
    m00, m01, m02, m11, m12, m22 = Mr[0, 0], Mr[0, 1], Mr[0, 2], Mr[1, 1], Mr[1, 2], Mr[2, 2]  # Mr symmetric
    y0, y1, y2 = yy[0], yy[1], yy[2]
    for q in range(Q):
        e0, e1, e2 = E0[q], E1[q], E2[q]
        Y0[q] = m00 * e0 + m01 * e1 + m02 * e2
        Y1[q] = m01 * e0 + m11 * e1 + m12 * e2
        Y2[q] = m02 * e0 + m12 * e1 + m22 * e2
        h[q] = e0 * y0 + e1 * y1 + e2 * y2
        hh[q] = e0 * e0 + e1 * e1 + e2 * e2
    for i in range(n):
        for k in range(K):
            ph[k] = Phi[i, k]
            ph2[k] = Phi[i, k] * Phi[i, k]
        for a in range(A):
            col = i * A + a
            hc, ec, o = h[col], hh[col], col * K
            for k in range(K):
                gxl[o + k] += hc * ph[k]
                dgl[o + k] += ec * ph2[k]
    for q in range(ne, Q):
        gxl[ns + q - ne] += h[q]
        dgl[ns + q - ne] += hh[q]


@njit(parallel=True, cache=True, fastmath=True)
def schur_rows(f, C, E, Phi, V, w_v, mu, slots, n, A, pair, Li_o, W_o, z_o, M_o, Gs, Gsd, Gdd_b, gx_b, dg_b):
    """The per-row half of a factored Gauss-Newton step and the per-pose Gram matrices, one task per block of
    poses (:func:`pose_blocks`), every unit's.

    Each row's joint errors eliminated (:func:`_eliminate_row`): Li_o (m, R, n, n), W_o (m, R, n, d), z_o
    (m, R, n), M_o = I - W^T W (m, R, d, d). Each pose's G_p = sum over its rows of E_r^T M_r E_r, formed in
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
    Nd = Q - ne
    NB = gx_b.shape[1]
    for b in prange(NB):
        H = np.empty((n, n))
        L = np.empty((n, n))
        gv = np.empty(n)
        yy = np.empty(d)
        h = np.empty(Q)
        hh = np.empty(Q)
        ph = np.empty(K)
        ph2 = np.empty(K)
        Yp = np.empty((T * d, Q))  # the pose's rows' M E, stacked
        rows = np.empty(T, dtype=np.int64)
        Gf = np.empty(Q * Q)
        G = Gf.reshape((Q, Q))
        for u in range(m):
            gx_b[u, b] = 0.0
            dg_b[u, b] = 0.0
            Gdd_b[u, b] = 0.0
        for p in range(b * _POSES, min(Pp, (b + 1) * _POSES)):
            for u in range(m):
                gxl, dgl, Gl = gx_b[u, b], dg_b[u, b], Gdd_b[u, b]
                nr = 0
                for t in range(T):
                    r = slots[u, p, t]
                    if r >= R:
                        continue
                    _eliminate_row(f[u, r], C[u, r], E[u, r], Phi[u, r], V[u, r], w_v[u, r], 1.0 + mu[u], A, H, L,
                                   gv, yy, h, hh, ph, ph2, Li_o[u, r], W_o[u, r], z_o[u, r], M_o[u, r],
                                   Yp[nr * d:(nr + 1) * d], gxl, dgl)
                    rows[nr] = r
                    nr += 1
                # upper blocks only: a structured row from its joint's first column on (pairs i <= j, the joint's
                # own block whole, as the contraction reads it), a dense row from the diagonal. Row views from
                # column q0, so that the inner loop runs from 0 (no negative-index wraparound: it vectorizes), and
                # a row's three coordinates (d = 3) per pass: a third of the loads and stores of G
                for q1 in range(Q):
                    q0 = (q1 // A) * A if q1 < ne else q1
                    Gr = G[q1, q0:]
                    if nr == 0:
                        Gr[:] = 0.0
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
                for c1 in range(Nd):
                    for c2 in range(c1, Nd):
                        Gl[c1, c2] += G[ne + c1, ne + c2]
        for u in range(m):
            Gl = Gdd_b[u, b]
            for c1 in range(Nd):
                for c2 in range(c1 + 1, Nd):
                    Gl[c2, c1] = Gl[c1, c2]


@njit(parallel=True, cache=True, fastmath=True)
def apply_rows(E, Phi, dbx, slots, n, A, final, M, Li, W, z, f, C, sx_b, dv, lin):
    """A db of every row (E_r times the step's extended values weighted by the row's basis values), one task per
    block of a unit's poses (:func:`pose_blocks`); final=False: the extended product A^T M A db, each block's
    rows summed into sx_b (m, NB, size); final=True: the joint-error steps dv = -Li^T (z + W A db) (m, R, n) and
    the linearized residual lin = f + A db + C dv (m, R, d)."""
    m, R, d, Q = E.shape
    Pp, T = slots.shape[1], slots.shape[2]
    K = Phi.shape[3]
    ne = n * A
    Nd = Q - ne
    ns = ne * K
    NB = (Pp + _POSES - 1) // _POSES
    for job in prange(m * NB):
        u = job // NB
        b = job % NB
        wq = np.empty(Q)
        Adb = np.empty(d)
        MA = np.empty(d)
        tmp = np.empty(n)
        sxl = np.zeros(sx_b.shape[2])
        for p in range(b * _POSES, min(Pp, (b + 1) * _POSES)):
            for t in range(T):
                r = slots[u, p, t]
                if r >= R:
                    continue
                for i in range(n):
                    for a in range(A):
                        col = i * A + a
                        x = 0.0
                        for k in range(K):
                            x += Phi[u, r, i, k] * dbx[u, col * K + k]
                        wq[col] = x
                for q in range(Nd):
                    wq[ne + q] = dbx[u, ns + q]
                for a in range(d):
                    x = 0.0
                    for q in range(Q):
                        x += E[u, r, a, q] * wq[q]
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
                    for i in range(n):
                        x = z[u, r, i]
                        for c in range(d):
                            x += W[u, r, i, c] * Adb[c]
                        tmp[i] = x
                    for j in range(n):
                        x = 0.0
                        for i in range(j, n):
                            x += Li[u, r, i, j] * tmp[i]
                        dv[u, r, j] = -x
                    for a in range(d):
                        x = f[u, r, a] + Adb[a]
                        for j in range(n):
                            x += C[u, r, a, j] * dv[u, r, j]
                        lin[u, r, a] = x
        if not final:
            for q in range(sxl.size):
                sx_b[u, b, q] = sxl[q]
