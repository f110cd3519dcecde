"""Rigid-body transforms as pure tensor functions (float64, any batch shape).

Conventions: rotation matrices act on column vectors; homogeneous transforms
are (..., 4, 4); a *twist* here is the paper's six small error terms
``(eps_x, eps_y, eps_z, delta_x, delta_y, delta_z)`` (rotation first).
"""

from __future__ import annotations

import torch


_BROADCAST_COLUMNS = 8
"""Up to this many columns of the right operand, :func:`small_matmul` off the CPU takes the broadcast form (two
kernels; its temporary is k times the result); wider ones (a Jacobian's parameters) the row form."""


def small_matmul(a: torch.Tensor, b: torch.Tensor) -> torch.Tensor:
    """``a @ b`` for stacks of small blocks: (..., i, k) @ (..., k, j) -> (..., i, j), batch dims broadcast, k of a
    few.

    On the CPU it is ``a @ b``. Elsewhere elementwise: a GPU's batched matmul of tiny blocks runs one tiny
    product per block, ~0.28 ms per call of 75 000 3 x 3 blocks on an H200 (a fleet's linearization makes ~55
    such calls, most of the fleet solve's GPU time). Narrow b (j <= 8: frames, points): one broadcast product
    and a sum (:func:`elementwise_matmul`); wide b (a row's Jacobian, j = the parameters): k multiply-adds of
    rows (:func:`rowwise_matmul`), whose temporaries are only as large as the result. Equal to ``a @ b`` to
    rounding.
    """
    if a.device.type == "cpu":
        return a @ b
    return elementwise_matmul(a, b) if b.shape[-1] <= _BROADCAST_COLUMNS else rowwise_matmul(a, b)


def elementwise_matmul(a: torch.Tensor, b: torch.Tensor) -> torch.Tensor:
    """``a @ b`` (..., i, k) @ (..., k, j) as one broadcast product and a sum over k (:func:`small_matmul`'s
    form for narrow b off the CPU)."""
    return (a[..., :, :, None] * b[..., None, :, :]).sum(-2)


def rowwise_matmul(a: torch.Tensor, b: torch.Tensor) -> torch.Tensor:
    """``a @ b`` (..., i, k) @ (..., k, j) as k multiply-adds of b's rows (:func:`small_matmul`'s form for wide
    b off the CPU)."""
    out = a[..., 0, None] * b[..., 0, None, :]
    for j in range(1, a.shape[-1]):
        out = out + a[..., j, None] * b[..., j, None, :]
    return out


_CPU_CONSTANTS: dict = {}
"""Small constants of the CPU paths, one per (name, dtype), made on first use. Only the CPU's: elsewhere a constant
made from host values is a copy the device may wait on, and the stacked forms below need none."""


def _cpu_constant(name: str, dtype: torch.dtype, make) -> torch.Tensor:
    key = (name, dtype)
    out = _CPU_CONSTANTS.get(key)
    if out is None:
        # a plain CPU tensor whatever the caller's context: one made under inference_mode could never be saved
        # for a backward pass, one made under a default-device context would live elsewhere
        with torch.inference_mode(False):
            out = _CPU_CONSTANTS[key] = make().to(device="cpu", dtype=dtype)
    return out


def _skew_map() -> torch.Tensor:
    """(3, 9): row k holds the coefficients of v_k in S(v) flattened row-major."""
    return torch.tensor([[0, 0, 0, 0, 0, -1, 0, 1, 0], [0, 0, 1, 0, 0, 0, -1, 0, 0], [0, -1, 0, 1, 0, 0, 0, 0, 0]],
                        device="cpu")


def skew(v: torch.Tensor) -> torch.Tensor:
    """Skew-symmetric matrix S(v) with S(v) w = v x w.  v: (..., 3) -> (..., 3, 3)."""
    if v.device.type == "cpu" and v.dtype.is_floating_point:
        # one product with a constant (3, 9) map instead of nine stacked pieces: a small batch's kinematics is
        # mostly per-call cost, and this is in every exponential and Jacobian (exact: each entry is 1 * v_k)
        return (v @ _cpu_constant("skew", v.dtype, _skew_map)).unflatten(-1, (3, 3))
    x, y, z = v.unbind(-1)
    o = torch.zeros_like(x)
    return torch.stack(
        [torch.stack([o, -z, y], -1), torch.stack([z, o, -x], -1), torch.stack([-y, x, o], -1)], -2
    )


def axis_angle_to_matrix(axis: torch.Tensor, angle: torch.Tensor) -> torch.Tensor:
    """Rotation about a unit axis (Rodrigues).  axis: (..., 3) unit, angle: (...) -> (..., 3, 3)."""
    k = skew(axis)
    s = torch.sin(angle)[..., None, None]
    c = torch.cos(angle)[..., None, None]
    eye = torch.eye(3, dtype=axis.dtype, device=axis.device)
    return eye + s * k + (1.0 - c) * small_matmul(k, k)


def orthogonal_unit(a: torch.Tensor) -> torch.Tensor:
    """A unit vector (3,) orthogonal to the unit vector a (3,): the axis farthest from a among x, y, z, with its
    part along a removed (well conditioned for any a)."""
    e = torch.eye(3, dtype=a.dtype, device=a.device)[int(a.abs().argmin())]
    e = e - (e @ a) * a
    return e / e.norm()


def so3_exp(w: torch.Tensor) -> torch.Tensor:
    """Exact rotation matrix exp(S(w)) of a rotation vector.  w: (..., 3) -> (..., 3, 3).

    Uses a Taylor series for tiny angles so that values and autograd
    derivatives stay exact at and near zero (error terms live there).
    """
    theta2 = (w * w).sum(-1)[..., None, None]  # (..., 1, 1): the coefficients broadcast over the matrices
    small = theta2 < 1e-8
    t2 = torch.where(small, 1.0, theta2)
    t = t2.sqrt()
    h = theta2 * theta2
    a = torch.where(small, 1.0 - theta2 / 6.0 + h / 120.0, t.sin() / t)
    b = torch.where(small, 0.5 - theta2 / 24.0 + h / 720.0, (1.0 - t.cos()) / t2)
    k = skew(w)
    if w.device.type == "cpu":
        eye = _cpu_constant("eye3", w.dtype, lambda: torch.eye(3, device="cpu"))
    else:
        eye = torch.eye(3, dtype=w.dtype, device=w.device)
    return eye + a * k + b * small_matmul(k, k)


def so3_log(R: torch.Tensor) -> torch.Tensor:
    """Rotation vector of a rotation matrix (inverse of so3_exp for angles < pi).  (..., 3, 3) -> (..., 3)."""
    cos = ((R.diagonal(dim1=-2, dim2=-1).sum(-1) - 1.0) / 2.0).clamp(-1.0, 1.0)
    theta = torch.acos(cos)
    vee = torch.stack([R[..., 2, 1] - R[..., 1, 2], R[..., 0, 2] - R[..., 2, 0], R[..., 1, 0] - R[..., 0, 1]], -1)
    small = theta < 1e-6
    sin = torch.sin(theta)
    factor = torch.where(small, 0.5 + theta * theta / 12.0, theta / (2.0 * torch.where(small, torch.ones_like(sin), sin)))
    return factor[..., None] * vee


def rpy_to_matrix(rpy: torch.Tensor) -> torch.Tensor:
    """URDF roll-pitch-yaw (fixed axes X, then Y, then Z) to a rotation.  (..., 3) -> (..., 3, 3)."""
    r, p, y = rpy.unbind(-1)
    ex = torch.zeros(rpy.shape[:-1] + (3,), dtype=rpy.dtype, device=rpy.device)
    ax = ex.clone()
    ax[..., 0] = 1.0
    ay = ex.clone()
    ay[..., 1] = 1.0
    az = ex.clone()
    az[..., 2] = 1.0
    return axis_angle_to_matrix(az, y) @ axis_angle_to_matrix(ay, p) @ axis_angle_to_matrix(ax, r)


def matrix_to_rpy(R: torch.Tensor) -> torch.Tensor:
    """Inverse of rpy_to_matrix.  (..., 3, 3) -> (..., 3).

    At pitch = +-90 deg (gimbal lock) only roll -+ yaw is defined: it all goes
    into roll and yaw is 0, so rpy_to_matrix still rebuilds R exactly.
    """
    pitch = torch.atan2(-R[..., 2, 0], torch.hypot(R[..., 0, 0], R[..., 1, 0]))
    lock = torch.cos(pitch) <= 1e-6
    roll = torch.where(lock, torch.atan2(-R[..., 1, 2], R[..., 1, 1]), torch.atan2(R[..., 2, 1], R[..., 2, 2]))
    yaw = torch.where(lock, torch.zeros_like(pitch), torch.atan2(R[..., 1, 0], R[..., 0, 0]))
    return torch.stack([roll, pitch, yaw], -1)


def _broadcast(a: tuple, b: tuple) -> torch.Size:
    """Broadcast shape of two batch shapes (torch.broadcast_shapes imports sympy on first use: ~1 s)."""
    n = max(len(a), len(b))
    a, b = (1,) * (n - len(a)) + tuple(a), (1,) * (n - len(b)) + tuple(b)
    out = []
    for x, y in zip(a, b):
        if x != y and 1 not in (x, y):
            raise RuntimeError(f"shapes {tuple(a)} and {tuple(b)} do not broadcast")
        out.append(y if x == 1 else x)
    return torch.Size(out)


def homogeneous(R: torch.Tensor, p: torch.Tensor) -> torch.Tensor:
    """Assemble (..., 4, 4) from a rotation (..., 3, 3) and a translation (..., 3)."""
    shape = _broadcast(R.shape[:-2], p.shape[:-1])
    top = torch.cat([R.expand(shape + (3, 3)), p.expand(shape + (3,))[..., None]], -1)
    # (0, 0, 0, 1) made on the device: a constant copied from the host makes a GPU wait (a sync per call)
    bottom = torch.nn.functional.pad(R.new_ones(()).expand(shape + (1, 1)), (3, 0))
    return torch.cat([top, bottom], -2)


def invert(T: torch.Tensor) -> torch.Tensor:
    """Inverse of a rigid transform.  (..., 4, 4) -> (..., 4, 4)."""
    Rt = T[..., :3, :3].transpose(-1, -2)
    return homogeneous(Rt, -(Rt @ T[..., :3, 3:4])[..., 0])


def twist_to_transform(e: torch.Tensor) -> torch.Tensor:
    """The paper's small error transform E of (20), kept exactly rigid.

    e: (..., 6) = (eps_x, eps_y, eps_z, delta_x, delta_y, delta_z) -> (..., 4, 4)
    with rotation exp(S(eps)) and translation delta. To first order this is
    matrix (20); unlike (20) it stays a rigid motion for any size of error.
    """
    return homogeneous(so3_exp(e[..., :3]), e[..., 3:])


def transform_to_twist(T: torch.Tensor) -> torch.Tensor:
    """Inverse of twist_to_transform.  (..., 4, 4) -> (..., 6)."""
    return torch.cat([so3_log(T[..., :3, :3]), T[..., :3, 3]], -1)


def kabsch(src: torch.Tensor, dst: torch.Tensor, weights: torch.Tensor | None = None):
    """Least-squares rigid motion (Kabsch / Umeyama without scale) taking ``src`` onto ``dst``.

    src, dst: (..., N, 3); weights: (..., N) non-negative or None.
    -> R (..., 3, 3) proper rotation, t (..., 3) minimising Σ w |R src + t - dst|².
    """
    if weights is None:
        weights = torch.ones(src.shape[:-1], dtype=src.dtype, device=src.device)
    w = weights / weights.sum(-1, keepdim=True)
    cs = (w[..., None] * src).sum(-2)
    cd = (w[..., None] * dst).sum(-2)
    H = ((src - cs[..., None, :]) * w[..., None]).transpose(-1, -2) @ (dst - cd[..., None, :])  # (..., 3, 3)
    # the optimal rotation is the proper rotation nearest to H^T (H = U S V^T -> R = V diag(1, 1, d) U^T)
    R = nearest_rotation(H.transpose(-1, -2))
    t = cd - (R @ cs[..., None])[..., 0]
    return R, t


def nearest_rotation(M: torch.Tensor) -> torch.Tensor:
    """Closest proper rotation (Frobenius) to a 3x3 matrix.  (..., 3, 3) -> (..., 3, 3)."""
    U, _, Vh = torch.linalg.svd(M)
    d = torch.sign(torch.linalg.det(U @ Vh))
    d = torch.where(d == 0, torch.ones_like(d), d)
    D = torch.diag_embed(torch.stack([torch.ones_like(d), torch.ones_like(d), d], -1))
    return U @ D @ Vh


def pose_error(T_from: torch.Tensor, T_to: torch.Tensor) -> torch.Tensor:
    """Error vector de of (47)-(48): translation and half-skew rotation of inv(T_from) @ T_to.

    Returns (..., 6) = (dx, dy, dz, rx, ry, rz) expressed in T_from's frame.
    """
    W = invert(T_from) @ T_to
    rot = 0.5 * torch.stack([W[..., 2, 1] - W[..., 1, 2], W[..., 0, 2] - W[..., 2, 0], W[..., 1, 0] - W[..., 0, 1]], -1)
    return torch.cat([W[..., :3, 3], rot], -1)
