"""A generic 6-DOF probe (Leica T-Mac, the UR10 data, ...): position + small rotation vector, d = 6.

Beyond Paper III, which models its SmartTRACK sensor by its raw angles
(:mod:`.sts`): a probe whose orientation accuracy is given directly per axis
is compared by the rotation between the modeled and the measured frame,

    r = [ p_hat - p ,  log(R_hat R^T) ]          (R, 6): m, rad

The rotation error ``log(R_hat R^T)`` is a rotation vector expressed in the
**tracker frame** (the frame of the measured x, y, z too): ``R_hat = exp(S(w)) R``.
So the per-row standard deviations ``pose_std`` = (sx, sy, sz, srx, sry, srz)
are along / about the tracker's own axes, all six in one frame.

Also here: the rotation conventions of the sensor CSV contract
(:func:`rotation_from_euler`, :func:`euler_from_rotation`, explicit
intrinsic / extrinsic naming), the orthonormality check of measured
rotations (:func:`rotation_defects`) and an autograd-safe SO(3) log map.
"""

from __future__ import annotations

import math

import torch

from ..core.exceptions import TorchcalError
from ..core.measurements import Measurements
from .base import Instrument
from .weights import CovarianceWeight, IsotropicWeight

ORTHONORMAL_TOL = 1e-5
"""Largest |R^T R - I| entry (and |det R - 1|) accepted for a measured rotation: a file written with
6 significant digits passes, a matrix with a swapped sign or a scale does not. Accepted matrices are
projected onto SO(3) (:func:`nearest_rotation`), a change of at most this size."""

DEFAULT_POSE_STD = (1e-5, 1e-5, 1e-5, 1e-4, 1e-4, 1e-4)
"""(sx, sy, sz) m and (srx, sry, srz) rad used where the rows carry no ``pose_std``: 0.01 mm, 0.0057 deg
(about a Leica T-Mac's stated accuracy at a few metres)."""


class RotationError(TorchcalError, ValueError):
    """A rotation (or Euler convention) that cannot be used; the message names the rows."""


# ------------------------------------------------------------------------- SO(3)
def rotation_log(R: torch.Tensor) -> torch.Tensor:
    """Rotation vector w of R = exp(S(w)), |w| <= pi; values and autograd derivatives finite at R = I.

    (..., 3, 3) -> (..., 3). Uses theta = atan2(|vee|, cos) (no acos: its
    derivative is infinite at the identity, where residuals are zero at the
    truth); near pi the axis comes from the symmetric part.

    Example:
        >>> import torch
        >>> from torchcal.kinematics.transforms import so3_exp
        >>> w = torch.tensor([0.3, -0.2, 0.1], dtype=torch.float64)
        >>> torch.allclose(rotation_log(so3_exp(w)), w)
        True
    """
    vee = 0.5 * torch.stack([R[..., 2, 1] - R[..., 1, 2], R[..., 0, 2] - R[..., 2, 0], R[..., 1, 0] - R[..., 0, 1]], -1)
    c = 0.5 * (R.diagonal(dim1=-2, dim2=-1).sum(-1) - 1.0)
    s2 = (vee * vee).sum(-1)
    small = s2 < 1e-12
    s_safe = torch.sqrt(torch.where(small, torch.ones_like(s2), s2))
    theta = torch.atan2(s_safe, c)
    # theta / sin(theta): exact away from 0 and pi, its series at 0 (where c > 0)
    factor = torch.where(small, 1.0 + s2 / 6.0, theta / s_safe)
    w = factor[..., None] * vee
    # at pi, R = 2 a a^T - I: the column of R + I with the largest diagonal is along a (sign free at pi);
    # computed for every row (no data-dependent branch: vmap-able)
    near_pi = small & (c < 0)
    A = 0.5 * (R + torch.eye(3, dtype=R.dtype, device=R.device))
    k = A.diagonal(dim1=-2, dim2=-1).argmax(-1)
    col = torch.take_along_dim(A, k[..., None, None].expand(*k.shape, 3, 1), -1)[..., 0]
    axis = col / col.norm(dim=-1, keepdim=True).clamp(min=1e-300)
    w = torch.where(near_pi[..., None], math.pi * axis, w)
    return w


def rotation_error(R_pred: torch.Tensor, R_obs: torch.Tensor) -> torch.Tensor:
    """Small rotation from the observed to the predicted frame, in the tracker (outer) frame.

    R_pred, R_obs: (..., 3, 3) -> w (..., 3), rad, with R_pred = exp(S(w)) R_obs.
    """
    return rotation_log(R_pred @ R_obs.transpose(-1, -2))


def nearest_rotation(R: torch.Tensor) -> torch.Tensor:
    """The rotation closest to a near-orthonormal matrix (polar factor, via SVD).  (..., 3, 3) -> (..., 3, 3)."""
    U, _, Vh = torch.linalg.svd(R)
    d = torch.linalg.det(U @ Vh)
    D = torch.ones(R.shape[:-1], dtype=R.dtype, device=R.device)
    D[..., 2] = d
    return (U * D[..., None, :]) @ Vh


def rotation_defects(R: torch.Tensor, tol: float = ORTHONORMAL_TOL) -> list[tuple[int, str]]:
    """Rows whose matrix is not a rotation within ``tol``: [(row index, reason)], 0-based.

    R: (B, 3, 3). Reasons: not finite, not orthonormal (largest |R^T R - I|
    entry), a reflection (det < 0).
    """
    out: list[tuple[int, str]] = []
    finite = torch.isfinite(R).all(-1).all(-1)
    Rf = torch.where(finite[:, None, None], R, torch.eye(3, dtype=R.dtype, device=R.device))
    eye = torch.eye(3, dtype=R.dtype, device=R.device)
    ortho = (Rf.transpose(1, 2) @ Rf - eye).abs().amax((1, 2))
    det = torch.linalg.det(Rf)
    for b in (~finite).nonzero()[:, 0].tolist():
        out.append((b, "rotation has a missing or non-finite entry"))
    for b in (finite & (det < 0)).nonzero()[:, 0].tolist():
        out.append((b, f"is a reflection, not a rotation (det = {float(det[b]):.6g})"))
    bad = finite & (det >= 0) & ((ortho > tol) | ((det - 1).abs() > tol))
    for b in bad.nonzero()[:, 0].tolist():
        out.append((b, (f"rotation is not orthonormal: largest |R^T R - I| entry {float(ortho[b]):.3g} "
                        f"(det {float(det[b]):.9g}) exceeds the tolerance {tol:g}")))
    return sorted(out)


# ------------------------------------------------------------------------ Euler
_AXIS = {"x": 0, "y": 1, "z": 2}


def parse_convention(convention: str) -> tuple[bool, tuple[int, int, int]]:
    """'xyz' (extrinsic: lower case, fixed axes) or 'XYZ' (intrinsic: upper case, moving axes), scipy's naming.

    -> (intrinsic, axis indices). Any of the 12 sequences (Tait-Bryan 'xyz', 'zyx', ... and proper
    Euler 'zyz', 'ZXZ', ...); two equal neighbours ('xxy') or mixed case ('xYz') are errors.
    """
    if not isinstance(convention, str) or len(convention) != 3:
        raise RotationError(f"Euler convention must be three axis letters like 'xyz' (extrinsic) or 'XYZ' "
                            f"(intrinsic), got {convention!r}")
    intrinsic = convention.isupper()
    if not (intrinsic or convention.islower()) or set(convention.lower()) - set("xyz"):
        raise RotationError(f"Euler convention {convention!r}: use three of x, y, z, all lower case (extrinsic, "
                            f"rotations about the fixed axes) or all upper case (intrinsic, about the moving axes)")
    axes = tuple(_AXIS[c] for c in convention.lower())
    if axes[0] == axes[1] or axes[1] == axes[2]:
        raise RotationError(f"Euler convention {convention!r}: neighbouring axes must differ")
    return intrinsic, axes


def _elementary(axis: int, angle: torch.Tensor) -> torch.Tensor:
    c, s = torch.cos(angle), torch.sin(angle)
    o, one = torch.zeros_like(angle), torch.ones_like(angle)
    if axis == 0:
        rows = [[one, o, o], [o, c, -s], [o, s, c]]
    elif axis == 1:
        rows = [[c, o, s], [o, one, o], [-s, o, c]]
    else:
        rows = [[c, -s, o], [s, c, o], [o, o, one]]
    return torch.stack([torch.stack(r, -1) for r in rows], -2)


def rotation_from_euler(angles_deg, convention: str = "xyz") -> torch.Tensor:
    """Rotation matrices from Euler angles in degrees.  (..., 3) -> (..., 3, 3).

    convention (scipy's naming): lower case = extrinsic, rotations about the
    fixed axes applied in the order given, 'xyz': R = Rz(c) Ry(b) Rx(a);
    upper case = intrinsic, about the moving axes, 'XYZ': R = Rx(a) Ry(b) Rz(c).
    Angles (a, b, c) are in the order of the letters.

    Example:
        >>> import torch
        >>> R = rotation_from_euler(torch.tensor([90.0, 0.0, 0.0], dtype=torch.float64), "xyz")
        >>> [round(v, 6) for v in (R @ torch.tensor([0.0, 1.0, 0.0], dtype=torch.float64)).tolist()]
        [0.0, 0.0, 1.0]
    """
    intrinsic, axes = parse_convention(convention)
    a = torch.as_tensor(angles_deg, dtype=torch.float64) * (math.pi / 180.0)
    Rs = [_elementary(ax, a[..., i]) for i, ax in enumerate(axes)]
    return Rs[0] @ Rs[1] @ Rs[2] if intrinsic else Rs[2] @ Rs[1] @ Rs[0]


def euler_from_rotation(R: torch.Tensor, convention: str = "xyz") -> torch.Tensor:
    """Euler angles in degrees of rotation matrices, the inverse of :func:`rotation_from_euler`.  (..., 3, 3) -> (..., 3).

    The middle angle is in [-90, 90] deg (Tait-Bryan, e.g. 'xyz') or [0, 180]
    deg (proper Euler, e.g. 'zyz'); the others in (-180, 180]. At gimbal lock
    only the sum (or difference) of the outer angles is defined: the angle of
    the rotation applied last to a vector's frame (the third of an intrinsic,
    the first of an extrinsic sequence) is set to 0, so that
    :func:`rotation_from_euler` still rebuilds R exactly.
    """
    intrinsic, axes = parse_convention(convention)
    R = torch.as_tensor(R, dtype=torch.float64)
    if not intrinsic:  # extrinsic (i, j, k) with (a, b, c) == intrinsic (k, j, i) with (c, b, a)
        axes = axes[::-1]
    i, j, k = axes
    proper = i == k
    if proper:
        k = 3 - i - j
    eps = 1.0 if (j - i) % 3 == 1 else -1.0  # +1 for cyclic (i, j, k)
    if proper:
        b = torch.atan2(torch.hypot(R[..., i, j], R[..., i, k]), R[..., i, i])
        lock = torch.sin(b).abs() < 1e-9
        a = torch.atan2(R[..., j, i], -eps * R[..., k, i])
        c = torch.atan2(R[..., i, j], eps * R[..., i, k])
    else:
        sb = (eps * R[..., i, k]).clamp(-1.0, 1.0)
        b = torch.atan2(sb, torch.hypot(R[..., i, i], R[..., i, j]))
        lock = torch.cos(b).abs() < 1e-9
        a = torch.atan2(-eps * R[..., j, k], R[..., k, k])
        c = torch.atan2(-eps * R[..., i, j], R[..., i, i])
    if bool(lock.any()):
        # gimbal lock: with c = 0, M = R Rj(b)^T = Ri(a)
        M = R @ _elementary(j, b).transpose(-1, -2)
        j1, k1 = (i + 1) % 3, (i + 2) % 3
        a_lock = torch.atan2(M[..., k1, j1], M[..., j1, j1])
        a = torch.where(lock, a_lock, a)
        c = torch.where(lock, torch.zeros_like(c), c)
    out = torch.stack([a, b, c], -1) * (180.0 / math.pi)
    return out.flip(-1) if not intrinsic else out


def euler_mismatch(angles_deg, R: torch.Tensor, convention: str, tol_deg: float = 1e-3) -> list[tuple[int, float]]:
    """Rows where the Euler angles in ``convention`` do not rebuild the given rotation: [(row index, angle deg)].

    angles_deg: (B, 3); R: (B, 3, 3). The angle is that of R_euler^T R; a
    file whose r-columns and Euler columns come from different conventions
    misses by degrees on almost every row.
    """
    Re = rotation_from_euler(angles_deg, convention)
    ang = rotation_log(Re.transpose(-1, -2) @ torch.as_tensor(R, dtype=torch.float64)).norm(dim=-1) * (180.0 / math.pi)
    bad = ~(ang <= tol_deg)
    return [(b, float(ang[b])) for b in bad.nonzero()[:, 0].tolist()]


# ------------------------------------------------------------------- instrument
def pose_observation(xyz: torch.Tensor, rotation: torch.Tensor) -> torch.Tensor:
    """(R, 3) m and (R, 3, 3) -> the (R, 12) row layout of :class:`PoseInstrument`: x, y, z, r11..r33."""
    return torch.cat([xyz, rotation.reshape(rotation.shape[0], 9)], -1)


class PoseInstrument(Instrument):
    """A 6-DOF probe's pose rows: residual (R, 6) = [p_hat - p (m), log(R_hat R^T) (rad, tracker frame)].

    xyz: (R, 3) probe origin in the tracker frame, m; rotation: (R, 3, 3)
    probe frame in the tracker frame; pose_std: (R, 6) or (6,) standard
    deviations (m, m, m, rad, rad, rad) along / about the tracker axes
    (default :data:`DEFAULT_POSE_STD`), or cov: (R, 6, 6) full covariance.
    ``observed`` and :meth:`predict` use the (R, 12) layout x, y, z, r11..r33
    (the residual is not a plain difference of these; no closed-form
    Jacobians, autograd is used). The model must give ``sensor_pose(q,
    tool, direction, v)`` -> (B, 4, 4), e.g. :class:`~torchcal.models.sensor_rig.SensorRig`.

    Example:
        >>> import torch
        >>> R = torch.eye(3, dtype=torch.float64).expand(2, 3, 3)
        >>> inst = PoseInstrument(torch.ones(2, 3, dtype=torch.float64), R)
        >>> inst.residual(inst.observed, inst.observed).shape
        torch.Size([2, 6])
    """

    dim = 6

    def __init__(self, xyz, rotation, pose_std=None, cov=None, check: bool = True, rows=None, source: str = ""):
        xyz = torch.as_tensor(xyz, dtype=torch.float64)
        rotation = torch.as_tensor(rotation, dtype=torch.float64).to(xyz.device)
        R = xyz.shape[0]
        if xyz.shape != (R, 3) or rotation.shape != (R, 3, 3):
            raise ValueError(f"PoseInstrument: need xyz (R, 3) and rotation (R, 3, 3), got {tuple(xyz.shape)} and "
                             f"{tuple(rotation.shape)}")
        # rows: labels for messages (file rows of Measurements); default 0-based indices
        label = (lambda r: f"row {int(rows[r])}") if rows is not None else (lambda r: f"row index {r}")
        where = f"{source}: PoseInstrument" if source else "PoseInstrument"
        if check:
            bad = (~torch.isfinite(xyz).all(-1)).nonzero()[:, 0].tolist()
            if bad:
                raise ValueError(f"{where}: {', '.join(label(r) for r in bad[:20])} without a finite measured x, y, z")
            defects = rotation_defects(rotation)
            if defects:
                raise RotationError(f"{where}: " + "; ".join(f"{label(r)}: {m}" for r, m in defects[:20]))
            rotation = nearest_rotation(rotation)
        self.observed = pose_observation(xyz, rotation)
        if cov is not None:
            cov = torch.as_tensor(cov, dtype=torch.float64).to(xyz.device)
            if pose_std is not None or cov.shape != (R, 6, 6):
                raise ValueError(f"PoseInstrument: give pose_std or cov ({R}, 6, 6), not both; got cov {tuple(cov.shape)}")
            self.weight = CovarianceWeight(cov)
        else:
            std = torch.as_tensor(DEFAULT_POSE_STD if pose_std is None else pose_std, dtype=torch.float64).to(xyz.device)
            if std.shape == (6,):
                std = std.expand(R, 6)
            if std.shape != (R, 6):
                raise ValueError(f"PoseInstrument: pose_std must have shape (6,) or ({R}, 6), got {tuple(std.shape)}")
            bad = (~(std > 0).all(-1)).nonzero()[:, 0].tolist()
            if bad:
                raise ValueError(f"{where}: {', '.join(label(r) for r in bad[:20])}: a standard deviation is not positive")
            self.weight = CovarianceWeight(torch.diag_embed(std * std))

    @classmethod
    def from_measurements(cls, data: Measurements, pose_std=None, cov=None) -> PoseInstrument:
        """The 6-DOF rows of ``data``: ``xyz`` and ``extra['rotation']``, per-row ``extra['pose_std']`` when present.

        pose_std given here overrides the rows' own; neither: :data:`DEFAULT_POSE_STD`.
        """
        rot = data.extra.get("rotation")
        if rot is None:
            raise ValueError(f"{data.source}: no rotations (extra['rotation']); read the rows with "
                             f"torchcal.io.sensor_csv.read_pose_measurements")
        if pose_std is None and cov is None:
            pose_std = data.extra.get("pose_std")
        return cls(data.xyz, rot, pose_std, cov, rows=data.rows.tolist(), source=data.source)

    def predict(self, model, q, tool, direction=None, v=None) -> torch.Tensor:
        T = model.sensor_pose(q, tool, direction, v)
        return pose_observation(T[:, :3, 3], T[:, :3, :3])

    def residual(self, pred: torch.Tensor, observed: torch.Tensor) -> torch.Tensor:
        B = pred.shape[0]
        dp = pred[:, :3] - observed[:, :3]
        w = rotation_error(pred[:, 3:].reshape(B, 3, 3), observed[:, 3:].reshape(B, 3, 3))
        return torch.cat([dp, w], -1)

    @property
    def xyz(self) -> torch.Tensor:
        return self.observed[:, :3]

    @property
    def rotation(self) -> torch.Tensor:
        return self.observed[:, 3:].reshape(-1, 3, 3)

    def _new(self, observed, weight) -> PoseInstrument:
        out = type(self).__new__(type(self))  # subclasses stay subclasses
        out.observed = observed
        out.weight = weight
        return out

    def subset(self, index) -> PoseInstrument:
        return self._new(self.observed[index], self.weight.subset(index))

    def to(self, device) -> PoseInstrument:
        w = self.weight
        if isinstance(w, CovarianceWeight):
            w = w.to(device)
        return self._new(self.observed.to(device), w)

    @classmethod
    def cat(cls, instruments: list) -> PoseInstrument:
        """Rows of several instruments, in order (per-row covariances kept)."""
        instruments = list(instruments)
        if not instruments:
            raise ValueError("PoseInstrument.cat: no instruments")
        dev = instruments[0].observed.device
        covs = [pose_covariance(i, 6).to(dev) for i in instruments]
        return cls.__new__(cls)._new(torch.cat([i.observed.to(dev) for i in instruments]), CovarianceWeight(torch.cat(covs)))


def pose_covariance(inst: Instrument, d: int) -> torch.Tensor:
    """(R, d, d) covariance of an instrument's weight (isotropic ones expanded)."""
    w = inst.weight
    if isinstance(w, CovarianceWeight):
        return w.cov
    if isinstance(w, IsotropicWeight):
        eye = torch.eye(d, dtype=inst.observed.dtype, device=inst.observed.device) * w.sigma ** 2
        return eye.expand(len(inst), d, d)
    raise TypeError(f"cannot concatenate an instrument weighted by {type(w).__name__}")


__all__ = [
    "DEFAULT_POSE_STD",
    "ORTHONORMAL_TOL",
    "PoseInstrument",
    "RotationError",
    "euler_from_rotation",
    "euler_mismatch",
    "nearest_rotation",
    "parse_convention",
    "pose_observation",
    "rotation_defects",
    "rotation_error",
    "rotation_from_euler",
    "rotation_log",
]
