"""The SmartTRACK sensor (STS) as an instrument: position + yaw, roll and level angles, Paper III (11)-(30), (46).

The tracker software exports the sensor frame s0 as a pose (12): origin p
and rotation R in the tracker frame. The sensor itself measured three angles,
which are its real error sources, so the pose is turned back into them
(17)-(22) and the model's pose likewise (23)-(27):

    a = -R^T p / |p|                        beam direction in s0, (17), (19)
    psi = atan2(-a_1, a_2)                  yaw encoder, range +-180 deg (20)
    theta = asin(a_3)                       roll encoder, range +-55 deg (20)
    x_s2 = R (cos psi, sin psi, 0)          the level sensor's axis, tracker frame (22)
    phi = asin(x_s2 . g)                    level sensor, range +-60 deg (our reading of (21))

Level angle, the reading chosen here: (21) writes phi = arccos(x_s2 . g), the
angle to the gravity vector, but the sensor's range of +-60 deg, Figure 9's
configurations at phi ~ 45 and 60 deg and an accuracy that falls with |phi|
(46) (an accelerometer loses sensitivity as its axis approaches gravity) only
fit an inclination of x_s2 from the horizontal plane: phi = 90 deg -
arccos(x_s2 . g) = asin(x_s2 . g), 0 when x_s2 is level, positive when it
points up (g of (27) points up: z component positive). For identification
the two readings give the same residual up to its sign; they differ in the
validity range and in sigma_phi (46), which take the inclination.

Residual (28)-(30): (p_hat - p, wrap(psi_hat - psi), theta_hat - theta,
phi_hat - phi), (R, 6), m and rad, whitened by the block-diagonal covariance
(32): the tracker's (R, 3, 3) position covariance and the angle variances (46).
"""

from __future__ import annotations

import logging
import math
from typing import NamedTuple

import torch

from ..core.exceptions import TorchcalError
from ..core.measurements import Measurements
from .base import Instrument, closed_form_declined
from .pose import pose_covariance
from .weights import CovarianceWeight

log = logging.getLogger("torchcal")

YAW_RANGE_DEG = 180.0
ROLL_RANGE_DEG = 55.0
LEVEL_RANGE_DEG = 60.0
"""Measurement ranges (+- deg) of the yaw and roll encoders and the level sensor, Paper III 3.2."""

SIGMA_ENCODER_DEG = 0.0005
"""sigma_psi = sigma_theta of (46), deg."""

MIN_DISTANCE_M = 1e-6
"""A sensor closer than this to the tracker origin (a failed 0, 0, 0 reading) has no beam direction."""


class SensorRangeError(TorchcalError, ValueError):
    """STS rows outside the sensor's angle ranges (or at the tracker origin); lists rows and angles.

    rows: the offending rows (file rows, ``Measurements.rows``); valid: (R,) bool mask of the input.
    """

    def __init__(self, message: str, rows=(), valid=None):
        super().__init__(message)
        self.rows = list(rows)
        self.valid = valid


# ------------------------------------------------------------------ pure functions
def level_sigma_deg(phi_deg: torch.Tensor) -> torch.Tensor:
    """Level-sensor standard deviation (46), deg: 0.0025 for |phi| <= 30 deg, else 0.00017 |phi| - 0.0026.  (...) -> (...)."""
    a = phi_deg.abs()
    return torch.where(a <= 30.0, torch.full_like(a, 0.0025), 0.00017 * a - 0.0026)


def paper3_angle_sigmas(angles: torch.Tensor) -> torch.Tensor:
    """(R, 3) measured psi, theta, phi (rad) -> (R, 3) standard deviations (rad) of (46)."""
    deg = math.pi / 180.0
    enc = torch.full_like(angles[:, 0], SIGMA_ENCODER_DEG * deg)
    return torch.stack([enc, enc, level_sigma_deg(angles[:, 2] / deg) * deg], -1)


def sts_angles(R: torch.Tensor, p: torch.Tensor, g: torch.Tensor) -> torch.Tensor:
    """Yaw, roll and level angles (..., 3), rad, of sensor poses, (17)-(22) / (23)-(27).

    R: (..., 3, 3) sensor frame s0 in the tracker frame; p: (..., 3) its
    origin, tracker frame (m, non-zero); g: (3,) or (..., 3) unit 'up'
    direction in the tracker frame. Differentiable (atan2 forms, finite
    derivatives inside the sensor's ranges).

    Example:
        >>> import torch
        >>> R, p = torch.eye(3, dtype=torch.float64), torch.tensor([2.0, 0.0, 0.0], dtype=torch.float64)
        >>> ang = sts_angles(R, p, torch.tensor([0.0, 0.0, 1.0], dtype=torch.float64))  # s0 = tracker axes, 2 m along x
        >>> [round(math.degrees(a), 6) + 0.0 for a in ang.tolist()]  # yaw turns y_s2 onto the beam; x_s2 level
        [90.0, 0.0, 0.0]
    """
    a = -(R.transpose(-1, -2) @ p[..., None])[..., 0] / p.norm(dim=-1, keepdim=True)
    a1, a2, a3 = a.unbind(-1)
    psi = torch.atan2(-a1, a2)
    c = torch.hypot(a1, a2)
    theta = torch.atan2(a3, c)
    x_s0 = torch.stack([a2 / c, -a1 / c, torch.zeros_like(c)], -1)  # (cos psi, sin psi, 0)
    x = (R @ x_s0[..., None])[..., 0]
    g = g.expand_as(x)
    s = (x * g).sum(-1)
    phi = torch.atan2(s, torch.linalg.cross(x, g).norm(dim=-1))
    return torch.stack([psi, theta, phi], -1)


def angle_jacobians(R: torch.Tensor, p: torch.Tensor, g_xy: torch.Tensor):
    """Closed-form derivatives of :func:`sts_angles` with the gravity of Paper III (27).

    R: (B, 3, 3), p: (B, 3) sensor poses; g_xy: (2,) (g_x, g_y).
    -> d(psi, theta, phi) / d p (B, 3, 3), / d omega (B, 3, 3) for a rotation R -> exp(S(omega)) R
    (omega in the tracker frame), / d (g_x, g_y) (B, 3, 2). With a = -R^T p / |p| (the beam in s0):
    dpsi = (a1 da2 - a2 da1) / c^2, dtheta = (c da3 - a3 dc) / |a|^2, dphi = ds / |x × g| (s = x . g).
    """
    from .gravity import gravity_from_xy

    r = p.norm(dim=-1)[:, None, None]  # (B, 1, 1)
    u = (R.transpose(1, 2) @ p[..., None])  # (B, 3, 1)
    a = -u[..., 0] / r[..., 0]
    Rt = R.transpose(1, 2)
    da_dp = -Rt / r + (u / r**3) @ p[:, None, :]
    Sp = torch.zeros_like(R)
    Sp[:, 0, 1], Sp[:, 0, 2], Sp[:, 1, 0] = -p[:, 2], p[:, 1], p[:, 2]
    Sp[:, 1, 2], Sp[:, 2, 0], Sp[:, 2, 1] = -p[:, 0], -p[:, 1], p[:, 0]
    da_dw = -(Rt @ Sp) / r  # u' = R^T S(p) omega
    a1, a2, a3 = a[:, 0:1], a[:, 1:2], a[:, 2:3]
    c2 = a1 * a1 + a2 * a2
    c = torch.sqrt(c2)
    g = gravity_from_xy(g_xy).to(R)
    cps, sps = a2 / c, -a1 / c  # cos psi, sin psi
    x_s0 = torch.cat([cps, sps, torch.zeros_like(c)], -1)
    x = (R @ x_s0[..., None])[..., 0]
    h = torch.linalg.cross(x, g.expand_as(x), dim=-1).norm(dim=-1, keepdim=True)
    perp = (R @ torch.cat([-sps, cps, torch.zeros_like(c)], -1)[..., None])[..., 0]  # R dx_s0 / dpsi

    def angles_from(da):  # da: (B, 3, k) -> (B, 3, k) psi, theta, phi rows (phi without the omega x x term)
        dpsi = (a1[..., None] * da[:, 1:2] - a2[..., None] * da[:, 0:1]) / c2[..., None]
        dc = (a1[..., None] * da[:, 0:1] + a2[..., None] * da[:, 1:2]) / c[..., None]
        dtheta = (c[..., None] * da[:, 2:3] - a3[..., None] * dc) / (c2 + a3 * a3)[..., None]
        ds = (perp * g).sum(-1)[:, None, None] * dpsi
        return dpsi, dtheta, ds

    dpsi, dth, ds = angles_from(da_dp)
    dA_dp = torch.cat([dpsi, dth, ds / h[..., None]], 1)
    dpsi, dth, ds = angles_from(da_dw)
    ds = ds + torch.linalg.cross(x, g.expand_as(x), dim=-1)[:, None, :]  # d(x . g) = (omega × x) . g = omega . (x × g)
    dA_dw = torch.cat([dpsi, dth, ds / h[..., None]], 1)
    gz = g[2]
    dg = torch.stack([torch.stack([g.new_ones(()), g.new_zeros(()), -g[0] / gz]),
                      torch.stack([g.new_zeros(()), g.new_ones(()), -g[1] / gz])], -1)  # (3, 2)
    dA_dg = torch.cat([torch.zeros_like(x[:, None, :2]).expand(-1, 2, 2), (x @ dg)[:, None, :] / h[..., None]], 1)
    return dA_dp, dA_dw, dA_dg


def sts_rotation(p: torch.Tensor, angles: torch.Tensor, g: torch.Tensor, branch: torch.Tensor | float = 1.0) -> torch.Tensor:
    """The sensor frame R (..., 3, 3) the tracker software reports for a sensor at p reading ``angles``: inverse of :func:`sts_angles`.

    p: (..., 3) m; angles: (..., 3) psi, theta, phi rad; g: unit 'up' (3,)
    or (..., 3); branch: +-1, which of the two level axes x_s2 (perpendicular to the beam,
    inclined by phi) is meant. The level must be reachable: |sin phi| <= the
    horizontal part of the beam direction (else NaN). Used by simulators and tests.
    """
    b = p / p.norm(dim=-1, keepdim=True)
    g = g.expand_as(b)
    gp = g - (g * b).sum(-1, keepdim=True) * b
    ng = gp.norm(dim=-1, keepdim=True)
    u = gp / ng
    w = torch.linalg.cross(b, u)
    psi, theta, phi = angles.unbind(-1)
    a = torch.sin(phi)[..., None] / ng
    x2 = a * u + torch.as_tensor(branch, dtype=p.dtype, device=p.device).expand(psi.shape)[..., None] * torch.sqrt(1 - a * a) * w
    y2 = -b
    z2 = torch.linalg.cross(x2, y2)
    R_s2 = torch.stack([x2, y2, z2], -1)
    cz, sz, cx, sx = torch.cos(psi), torch.sin(psi), torch.cos(theta), torch.sin(theta)
    o = torch.zeros_like(psi)
    F = torch.stack([torch.stack([cz, -sz * cx, sz * sx], -1), torch.stack([sz, cz * cx, -cz * sx], -1),
                     torch.stack([o, sx, cx], -1)], -2)  # F_STS of (11)
    return R_s2 @ F.transpose(-1, -2)


def wrap_angle(x: torch.Tensor) -> torch.Tensor:
    """Angles to [-pi, pi); derivative 1."""
    return torch.remainder(x + math.pi, 2 * math.pi) - math.pi


class STSValidity(NamedTuple):
    """Per row: valid (R,) bool, angles (R, 3) rad (NaN where undefined), problems [(row index, angle, message)]."""

    valid: torch.Tensor
    angles: torch.Tensor
    problems: list


def sts_validity(xyz: torch.Tensor, rotation: torch.Tensor, gravity: torch.Tensor) -> STSValidity:
    """Measured angles of every row and which rows lie inside the sensor's ranges (yaw +-180, roll +-55, level +-60 deg).

    xyz: (R, 3) m; rotation: (R, 3, 3); gravity: (3,) unit, the tracker's
    measured 'up' (virtual level). problems hold 0-based row indices.
    """
    deg = 180.0 / math.pi
    dist = xyz.norm(dim=-1)
    near = ~(dist >= MIN_DISTANCE_M)
    safe = torch.where(near[:, None], torch.tensor([1.0, 0.0, 0.0], dtype=xyz.dtype, device=xyz.device), xyz)
    ang = sts_angles(rotation, safe, gravity.to(xyz))
    problems = []
    missing = ~torch.isfinite(xyz).all(-1) | ~torch.isfinite(rotation).all(-1).all(-1)
    for r in missing.nonzero()[:, 0].tolist():
        problems.append((r, "pose", "no measured pose (x, y, z or rotation missing)"))
    near = near & ~missing
    for r in near.nonzero()[:, 0].tolist():
        problems.append((r, "distance", (f"sensor at {dist[r].item() * 1e3:.6g} mm from the tracker origin: no beam "
                                         f"direction (a failed 0, 0, 0 reading?)")))
    valid = ~(near | missing)
    for k, (name, lim) in enumerate((("yaw", YAW_RANGE_DEG), ("roll", ROLL_RANGE_DEG), ("level", LEVEL_RANGE_DEG))):
        a = ang[:, k] * deg
        out = ~near & ~missing & ~(a.abs() <= lim + 1e-9)
        valid = valid & ~out
        for r in out.nonzero()[:, 0].tolist():
            problems.append((r, name, f"{name} angle {a[r].item():.4f} deg is outside the sensor's range +-{lim:g} deg"))
    ang = torch.where((near | missing)[:, None], torch.full_like(ang, float("nan")), ang)
    return STSValidity(valid, ang, sorted(problems, key=lambda t: t[0]))


class STSSelection(NamedTuple):
    """What ``STSInstrument.from_measurements(..., invalid='exclude')`` returns.

    instrument: on the valid rows; data: those rows of the input; excluded:
    file rows (``Measurements.rows``) left out; message: why, row by row
    ('' when none); valid: (R,) bool mask over the input rows.
    """

    instrument: STSInstrument
    data: Measurements
    excluded: list
    message: str
    valid: torch.Tensor


# ------------------------------------------------------------------------ instrument
class STSInstrument(Instrument):
    """SmartTRACK rows: observed (R, 6) = (x, y, z m, psi, theta, phi rad); residual (28)-(30), whitened (32), (46).

    xyz: (R, 3) sensor origin in the tracker frame; angles: (R, 3) measured
    psi, theta, phi (rad, :func:`sts_angles`); position_cov: (R, 3, 3) m^2
    (e.g. a tracker's, Paper III (36)) or a float: isotropic sigma (m);
    angle_sigma: (R, 3) or (3,) rad, default (46) evaluated at the measured
    level angle. The model must give ``sensor_pose(q, tool, direction, v)``
    and ``gravity_vector()``: :class:`~torchcal.models.sensor_rig.SensorRig`.
    Jacobians by autograd (:func:`~torchcal.measure.row_jacobians`).

    Example:
        >>> import torch
        >>> inst = STSInstrument(torch.ones(2, 3, dtype=torch.float64), torch.zeros(2, 3, dtype=torch.float64), 1e-5)
        >>> [round(v, 3) for v in inst.whiten(torch.tensor([[1e-5, 0, 0, 0, 0, 4.363e-5]] * 2, dtype=torch.float64))[0].tolist()]
        [1.0, 0.0, 0.0, 0.0, 0.0, 1.0]
    """

    dim = 6

    def __init__(self, xyz, angles, position_cov, angle_sigma=None):
        xyz = torch.as_tensor(xyz, dtype=torch.float64)
        angles = torch.as_tensor(angles, dtype=torch.float64).to(xyz.device)
        R = xyz.shape[0]
        if xyz.shape != (R, 3) or angles.shape != (R, 3):
            raise ValueError(f"STSInstrument: need xyz (R, 3) and angles (R, 3), got {tuple(xyz.shape)}, {tuple(angles.shape)}")
        bad = (~torch.isfinite(torch.cat([xyz, angles], -1)).all(-1)).nonzero()[:, 0].tolist()
        if bad:
            raise ValueError(f"STSInstrument: rows {bad[:20]} (0-based) have no finite position or angles")
        if isinstance(position_cov, (int, float)):
            if not position_cov > 0:
                raise ValueError(f"STSInstrument: position sigma must be positive, got {position_cov}")
            position_cov = torch.eye(3, dtype=torch.float64, device=xyz.device).expand(R, 3, 3) * float(position_cov) ** 2
        cp = torch.as_tensor(position_cov, dtype=torch.float64).to(xyz.device)
        if cp.shape != (R, 3, 3):
            raise ValueError(f"STSInstrument: position covariance must have shape ({R}, 3, 3), got {tuple(cp.shape)}")
        sa = paper3_angle_sigmas(angles) if angle_sigma is None else torch.as_tensor(angle_sigma, dtype=torch.float64).to(xyz.device)
        sa = sa.expand(R, 3) if sa.shape == (3,) else sa
        if sa.shape != (R, 3) or not bool((sa > 0).all()):
            raise ValueError(f"STSInstrument: angle sigmas must be positive, shape (3,) or ({R}, 3), got {tuple(sa.shape)}")
        cov = torch.zeros(R, 6, 6, dtype=torch.float64, device=xyz.device)
        cov[:, :3, :3] = cp
        cov[:, 3:, 3:] = torch.diag_embed(sa * sa)
        self.observed = torch.cat([xyz, angles], -1)
        self.weight = CovarianceWeight(cov)

    @classmethod
    def from_measurements(cls, data: Measurements, noise=None, gravity=None, angle_sigma=None, invalid: str = "raise"):
        """STS rows from 6-DOF measurements (``xyz`` and ``extra['rotation']``).

        noise: the position noise: an object with ``covariance(p (R, 3)) -> (R, 3, 3)``
        (:class:`torchcal.measure.tracker.TrackerNoise`; None: its Paper III
        values (47), ``TrackerNoise.paper3()``), a float (isotropic sigma, m) or
        an (R, 3, 3) covariance (m^2). gravity: the tracker's measured 'up'
        direction (virtual level), unit (3,), default (0, 0, 1): with it the
        level angle is recovered from the exported rotation (21).
        angle_sigma: see the class. invalid: rows outside the sensor's ranges
        (:func:`sts_validity`) are never used silently: 'raise' (default) raises
        :class:`SensorRangeError` listing them; 'exclude' returns an
        :class:`STSSelection` (instrument and data on the valid rows, the
        excluded file rows, the message), logging a warning.
        """
        if invalid not in ("raise", "exclude"):
            raise ValueError(f"invalid must be 'raise' or 'exclude', got {invalid!r}")
        from .gravity import check_gravity

        rot = data.extra.get("rotation")
        if rot is None:
            raise ValueError(f"{data.source}: no rotations (extra['rotation']); read the rows with "
                             f"torchcal.io.sensor_csv.read_pose_measurements")
        g = check_gravity(torch.tensor([0.0, 0.0, 1.0]) if gravity is None else gravity, "STS gravity")
        rot = torch.as_tensor(rot, dtype=torch.float64).to(data.xyz.device)
        check = sts_validity(data.xyz, rot, g.to(data.xyz.device))
        message = ""
        if check.problems:
            rows = data.rows.tolist()
            bad_rows = sorted({rows[r] for r, _, _ in check.problems})
            listed = "; ".join(f"row {rows[r]}: {m}" for r, _, m in check.problems[:20])
            more = f"; ... and {len(check.problems) - 20} more" if len(check.problems) > 20 else ""
            message = (f"{data.source or 'STS data'}: {len(bad_rows)} of {len(data)} rows outside the STS ranges "
                       f"(yaw +-{YAW_RANGE_DEG:g}, roll +-{ROLL_RANGE_DEG:g}, level +-{LEVEL_RANGE_DEG:g} deg): {listed}{more}")
            if invalid == "raise":
                raise SensorRangeError(message + " (pass invalid='exclude' to leave them out)", bad_rows, check.valid)
            log.warning("%s; excluded", message)
        idx = check.valid.nonzero()[:, 0]
        sub = data if bool(check.valid.all()) else data.subset(idx)
        cov = _position_cov(noise, sub.xyz, len(data), idx)
        inst = cls(sub.xyz, check.angles[idx], cov, angle_sigma)
        if invalid == "exclude":
            return STSSelection(inst, sub, sorted({data.rows.tolist()[r] for r, _, _ in check.problems}), message,
                            check.valid)
        return inst

    # ------------------------------------------------------------------ model
    def predict(self, model, q, tool, direction=None, v=None) -> torch.Tensor:
        T = model.sensor_pose(q, tool, direction, v)
        p = T[:, :3, 3]
        return torch.cat([p, sts_angles(T[:, :3, :3], p, model.gravity_vector())], -1)

    def predict_jacobians(self, model, q, tool, direction=None, v=None):
        """Closed form through the rig's pose Jacobians (:meth:`SensorRig.pose_jacobians`) and the
        derivatives of (17)-(27) w.r.t. the pose and gravity; None for models without them (autograd then)."""
        pj = getattr(model, "pose_jacobians", None)
        if pj is None or closed_form_declined(model):
            return None
        T, J = pj(q, direction, v)
        R, p = T[:, :3, :3], T[:, :3, 3]
        dA_dp, dA_dw, dA_dg = angle_jacobians(R, p, model.gravity.detach())
        B = q.shape[0]
        # every group's columns through the angle derivatives at once: per group, these few products on a small
        # batch cost more in dispatch than in arithmetic
        flat = torch.cat([Jn.reshape(B, 6, -1) for Jn in J.values()], -1)
        full = torch.cat([flat[:, :3], dA_dp @ flat[:, :3] + dA_dw @ flat[:, 3:]], 1)
        sizes = [Jn[0, 0].numel() for Jn in J.values()]
        out = {name: part.reshape(B, 6, *Jn.shape[2:])
               for (name, Jn), part in zip(J.items(), full.split(sizes, -1))}
        out["gravity"] = torch.cat([dA_dg.new_zeros(B, 3, 2), dA_dg], 1)
        pred = torch.cat([p, sts_angles(R, p, model.gravity_vector())], -1)
        return pred, out

    def residual(self, pred: torch.Tensor, observed: torch.Tensor) -> torch.Tensor:
        d = pred - observed
        return torch.cat([d[:, :3], wrap_angle(d[:, 3:])], -1)

    @property
    def angles(self) -> torch.Tensor:
        """(R, 3) measured psi, theta, phi, rad."""
        return self.observed[:, 3:]

    def _new(self, observed, weight) -> STSInstrument:
        out = type(self).__new__(type(self))  # subclasses stay subclasses
        out.observed = observed
        out.weight = weight
        return out

    def subset(self, index) -> STSInstrument:
        return self._new(self.observed[index], self.weight.subset(index))

    def to(self, device) -> STSInstrument:
        return self._new(self.observed.to(device), self.weight.to(device))

    @classmethod
    def cat(cls, instruments: list) -> STSInstrument:
        """Rows of several instruments, in order."""
        instruments = list(instruments)
        if not instruments:
            raise ValueError("STSInstrument.cat: no instruments")
        dev = instruments[0].observed.device
        return cls.__new__(cls)._new(torch.cat([i.observed.to(dev) for i in instruments]),
                                     CovarianceWeight(torch.cat([pose_covariance(i, 6).to(dev) for i in instruments])))


def _position_cov(noise, xyz: torch.Tensor, rows: int, idx: torch.Tensor) -> torch.Tensor:
    """(R', 3, 3) position covariance for the kept rows ``idx`` of ``rows``."""
    if noise is None:
        try:
            from .tracker import TrackerNoise
        except ImportError:  # pragma: no cover - the tracker module ships with the package
            raise ValueError("STSInstrument: no tracker noise model available; pass noise= (sigma in m or (R, 3, 3))") from None
        noise = TrackerNoise.paper3()
    if callable(getattr(noise, "covariance", None)):
        return noise.covariance(xyz)
    if isinstance(noise, (int, float)):
        return torch.eye(3, dtype=xyz.dtype, device=xyz.device).expand(xyz.shape[0], 3, 3) * float(noise) ** 2
    cov = torch.as_tensor(noise, dtype=torch.float64).to(xyz.device)
    if cov.shape != (rows, 3, 3):
        raise ValueError(f"STSInstrument: position covariance must have shape ({rows}, 3, 3), got {tuple(cov.shape)}")
    return cov[idx]


__all__ = [
    "LEVEL_RANGE_DEG",
    "ROLL_RANGE_DEG",
    "SIGMA_ENCODER_DEG",
    "YAW_RANGE_DEG",
    "STSInstrument",
    "STSSelection",
    "STSValidity",
    "SensorRangeError",
    "level_sigma_deg",
    "paper3_angle_sigmas",
    "sts_angles",
    "sts_rotation",
    "sts_validity",
    "wrap_angle",
]
