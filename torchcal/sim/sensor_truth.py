"""Paper III's measurement system with known truth: FANUC + SmartTRACK sensor (STS) + laser tracker.

Written from Paper III's text (3.1-3.3, 4.2-4.4, 5.3-5.4, 6.1), independently of
torchcal's Chebyshev model and of the sensor instruments in
:mod:`torchcal.measure`; the robot itself is :class:`~torchcal.sim.TruthRobot`
(Paper II's seven error sources plus gear ripple and load cross-coupling).

Physical set-up (SI, tracker frame LT0 with z up):

- the robot base sits ``tracker_distance`` (2.7 m) in front of the tracker and
  ``base_height`` below its head, turned to face it: the known measurement
  frame ``base_nominal`` = Trans(D, 0, h) Rz(π); the truth adds E_0^m (13)-(15);
- the STS is bolted to the flange by ``mount_nominal`` = Trans(0, 0, 0.12 m)
  Rx(π) (its yaw axis z_s0 opposite the flange z, so upright when the tool
  points down and immune to J6, the noisiest joint), with an unknown mount
  error E_s0^n of (16) (~0.3 mm, ~0.05°);
- true gravity ``gravity`` (the *upward* vertical, unit, tracker frame) is
  tilted from the tracker's z by ``gravity_tilt_deg`` (0.03°) in a seeded
  direction; the model does not know it ((27) has to find it);
- three Active-Target positions on the end effector (6.1): Paper II's Table 4
  tool vectors, a triangle of 66.5 mm circumradius (the paper's circles: 66.43 mm),
  as the truth's tools with their seeded corrections.

What one STS measurement is (``measure_sts``):

1. the robot reaches q + v, v ~ N(0, Σ_v(s)) by approach direction s
   (Paper II Table 5 via the robot YAML's ``repeatability``);
2. the tracker measures the reflector centre p = origin of s0: the true point
   in spherical coordinates (α azimuth, β from the z axis, d distance, (34))
   plus N(0, σ²) on each of α, β, d with σ from (47), converted back;
3. the head turns so that y_s2 points along the beam back to the tracker, (17);
   the encoders read the ψ, θ that do this *on the real head*, whose roll axis
   is tilted from perpendicular to the yaw axis by ``axis_skew_deg``
   (Rz(ψ) Ry(ε) Rx(θ) instead of (11)); the yaw encoder has a once-per-turn
   eccentricity error; each encoder adds N(0, (0.0005°)²) (46);
4. the level sensor (MEMS accelerometer along x_s2) reads the inclination of
   the real x_s2 against true gravity, plus a bias and a cubic scale
   nonlinearity (``level_bias_deg``, ``level_cubic_deg``) and N(0, σ_φ(φ)²) of (46);
5. the SDK rebuilds R_s0^LT0 from (p, ψ, θ, φ) with the *nominal* head (11)
   and the true gravity (the tracker's virtual level is taken as exact), and
   exports (p, R) as (12). Sources 3-4's systematic parts are not in any
   model: Paper III assumes a perfect head.

Level-angle reading. (21) writes φ = arccos(x_s2 · g); taken literally that
is 90° for a level sensor, and (46) / the ±60° range (accelerometer
insensitive "as the measured inclination approaches the gravity vector")
only make sense for an inclination. We simulate **φ = asin(x_s2 · g) =
90° - arccos(x_s2 · g)** with g the upward vertical: 0 when x_s2 is
horizontal, ±60° the sensor's range, σ_φ(φ) of (46) on |φ|. A model using the
literal arccos reading sees the same residual with the opposite sign.

Valid poses: yaw |ψ| ≤ 180°, roll |θ| ≤ 55°, level |φ| ≤ 60° (3.2), checked on
the noise-free pose; :meth:`SensorTruth.sample_commands` draws quasi-random
commands over the joint limits and keeps the valid ones, reporting how many
it rejected. There is no line-of-sight model (the robot never hides the reflector).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
import torch
from torch import nn

from ..core import units
from ..kinematics.robot import Robot
from ..kinematics.transforms import homogeneous, so3_exp
from ..core.measurements import Measurements, first_invalid_direction
from .sampling import approach_directions, quasi_random_commands
from .truth import TruthRobot

AT_TARGETS_MM = ((33.06, 57.73, 161.22), (57.26, -33.86, 161.22), (-33.96, -57.23, 161.22))
"""Three Active-Target positions on the end effector (flange frame, mm): Paper II Table 4."""

SIGMA_ALPHA = 3.5e-6
SIGMA_BETA = 3.5e-6
"""Tracker azimuth / elevation standard deviations (rad), Paper III (47)."""
SIGMA_ENCODER_DEG = 0.0005
"""STS yaw and roll encoder standard deviations (deg), (46)."""
YAW_RANGE_DEG, ROLL_RANGE_DEG, LEVEL_RANGE_DEG = 180.0, 55.0, 60.0
"""Measuring ranges of the STS (3.2)."""


# ----------------------------------------------------------------------------- pure functions
def sigma_distance(d: torch.Tensor) -> torch.Tensor:
    """Tracker distance standard deviation (m) of (47): 5 µm up to 2 m, 2.5 µm per metre beyond.  d: (...) m."""
    return torch.where(d <= 2.0, torch.full_like(d, 5e-6), 2.5e-6 * d)


def sigma_level(phi: torch.Tensor) -> torch.Tensor:
    """Level-sensor standard deviation (rad) of (46) for level angles phi (...) rad.

    0.0025° for |φ| ≤ 30°, 0.00017° |φ|/° - 0.0026° beyond (continuous at 30°, 0.0076° at 60°).
    """
    a = phi.abs() / units.DEG
    return torch.where(a <= 30.0, torch.full_like(a, 0.0025), 0.00017 * a - 0.0026) * units.DEG


def to_spherical(p: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """Tracker coordinates (34): p (..., 3) m -> α azimuth, β angle from +z (rad), d (m), each (...)."""
    d = p.norm(dim=-1)
    return torch.atan2(p[..., 1], p[..., 0]), torch.acos((p[..., 2] / d).clamp(-1.0, 1.0)), d


def from_spherical(alpha: torch.Tensor, beta: torch.Tensor, d: torch.Tensor) -> torch.Tensor:
    """(34): x = d cos α sin β, y = d sin α sin β, z = d cos β.  (...) each -> (..., 3) m."""
    return torch.stack([d * torch.cos(alpha) * torch.sin(beta), d * torch.sin(alpha) * torch.sin(beta),
                        d * torch.cos(beta)], -1)


def tracker_noisy_points(p: torch.Tensor, z: torch.Tensor, sigma_alpha: float = SIGMA_ALPHA,
                         sigma_beta: float = SIGMA_BETA) -> torch.Tensor:
    """Measured points: true points p (R, 3) m with N(0, σ²) on α, β, d, drawn in spherical coordinates.

    z: (R, 3) standard normal draws for (α, β, d); σ_d(d) from (47).
    """
    a, b, d = to_spherical(p)
    return from_spherical(a + sigma_alpha * z[:, 0], b + sigma_beta * z[:, 1], d + sigma_distance(d) * z[:, 2])


def _rz(a: torch.Tensor) -> torch.Tensor:
    c, s, o, i = torch.cos(a), torch.sin(a), torch.zeros_like(a), torch.ones_like(a)
    return torch.stack([torch.stack([c, -s, o], -1), torch.stack([s, c, o], -1), torch.stack([o, o, i], -1)], -2)


def _rx(a: torch.Tensor) -> torch.Tensor:
    c, s, o, i = torch.cos(a), torch.sin(a), torch.zeros_like(a), torch.ones_like(a)
    return torch.stack([torch.stack([i, o, o], -1), torch.stack([o, c, -s], -1), torch.stack([o, s, c], -1)], -2)


def sts_angles(R: torch.Tensor, p: torch.Tensor, g: torch.Tensor) -> torch.Tensor:
    """Yaw, roll and level angle of a perfect STS, Paper III (17)-(22) with the inclination reading.

    R: (B, 3, 3) rotation of the STS base frame s0 in the tracker frame; p: (B, 3)
    m its origin; g: (3,) or (B, 3) upward vertical (unit) in the tracker frame.
    -> (B, 3) rad: ψ = atan2(-a1, a2), θ = asin(a3) with a = -Rᵀ p/|p| (19)-(20),
    φ = asin(x_s2 · g) with x_s2 = R (cos ψ, sin ψ, 0) (22) (module docstring).
    """
    a = -(R.transpose(-1, -2) @ (p / p.norm(dim=-1, keepdim=True))[..., None])[..., 0]
    psi = torch.atan2(-a[..., 0], a[..., 1])
    theta = torch.asin(a[..., 2].clamp(-1.0, 1.0))
    x = (R @ torch.stack([torch.cos(psi), torch.sin(psi), torch.zeros_like(psi)], -1)[..., None])[..., 0]
    phi = torch.asin((x * g).sum(-1).clamp(-1.0, 1.0))
    return torch.stack([psi, theta, phi], -1)


def sts_rotation(p: torch.Tensor, angles: torch.Tensor, g: torch.Tensor, hint: torch.Tensor) -> torch.Tensor:
    """What the SDK exports: R_s0^LT0 (B, 3, 3) rebuilt from p (B, 3), angles (B, 3) = (ψ, θ, φ) and g (3,).

    y_s2 = -p/|p| (17); x_s2 is the unit vector ⟂ y_s2 with x_s2 · g = sin φ, of the
    two such vectors the one nearer ``hint`` (B, 3) (the real sensor knows which
    side it is on); z_s2 = x_s2 × y_s2; R_s0 = R_s2 (Rz(ψ) Rx(θ))ᵀ with the nominal head (11).
    """
    y = -p / p.norm(dim=-1, keepdim=True)
    g = g.expand_as(y)
    h = torch.linalg.cross(y, g, dim=-1)
    gh = h.norm(dim=-1, keepdim=True)  # = |y x g|, the largest x_s2 . g can reach
    h = h / gh
    w = torch.linalg.cross(h, y, dim=-1)  # unit, ⟂ y, w . g = |y x g| > 0
    s = (torch.sin(angles[..., 2:3]) / gh).clamp(-1.0, 1.0)
    c = torch.sqrt(1.0 - s * s)
    cand = torch.stack([c * h + s * w, -c * h + s * w], 1)  # (B, 2, 3)
    pick = (cand * hint[:, None]).sum(-1).argmax(1)
    x = cand[torch.arange(y.shape[0], device=y.device), pick]
    R2 = torch.stack([x, y, torch.linalg.cross(x, y, dim=-1)], -1)
    return R2 @ (_rz(angles[..., 0]) @ _rx(angles[..., 1])).transpose(-1, -2)


def head_angles(R: torch.Tensor, p: torch.Tensor, skew: float) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """Encoder angles of a real head Rz(ψ) Ry(ε) Rx(θ) that points y_s2 back along the beam.

    R: (B, 3, 3), p: (B, 3) as for :func:`sts_angles`; skew: ε rad.
    -> ψ (B,), θ (B,) rad and the real level axis x_s2 (B, 3) in the tracker frame.
    Ry(ε) Rx(θ) e_y = (sin ε sin θ, cos θ, cos ε sin θ) must equal b = -Rᵀ p/|p|
    turned back by Rz(-ψ); for ε = 0 this is (20).
    """
    b = -(R.transpose(-1, -2) @ (p / p.norm(dim=-1, keepdim=True))[..., None])[..., 0]
    se, ce = math.sin(skew), math.cos(skew)
    theta = torch.asin((b[..., 2] / ce).clamp(-1.0, 1.0))
    psi = torch.atan2(b[..., 1], b[..., 0]) - torch.atan2(torch.cos(theta), se * torch.sin(theta))
    psi = torch.atan2(torch.sin(psi), torch.cos(psi))
    x_head = torch.stack([torch.cos(psi) * ce, torch.sin(psi) * ce, torch.full_like(psi, -se)], -1)
    return psi, theta, (R @ x_head[..., None])[..., 0]


def triangle_normal(points: torch.Tensor) -> torch.Tensor:
    """Unit normal (B, 3) of triangles (B, 3, 3) [vertex, xyz]: (p2 - p1) x (p3 - p1), normalized (6.1)."""
    n = torch.linalg.cross(points[:, 1] - points[:, 0], points[:, 2] - points[:, 0], dim=-1)
    return n / n.norm(dim=-1, keepdim=True)


@dataclass
class CommandSample:
    """Valid commands drawn by :meth:`SensorTruth.sample_commands`.

    q: (N, n) commands; direction: (N, n) approach directions in visiting
    order; drawn: how many candidates were drawn; rejected: how many failed the
    range check, per reason ('roll', 'level', 'both').
    """

    q: torch.Tensor
    direction: torch.Tensor
    drawn: int
    rejected: dict

    @property
    def n_rejected(self) -> int:
        return self.drawn - self.q.shape[0]


class SensorTruth(nn.Module):
    """The actual FANUC + STS + tracker of Paper III (module docstring), every error known.

    robot: the FANUC LR Mate 200i (``load_robot("fanuc_lrmate200i")``); seed:
    all drawn errors (robot, mount, gravity direction, sensor head);
    tracker_distance, base_height: robot base position in the tracker frame (m);
    gravity_tilt_deg: true vertical vs the tracker's z; mount_mm / mount_deg:
    size of the mount error E_s0^n; unmodelled: robot gear ripple and
    cross-coupling (TruthRobot) and the STS head errors (axis skew, yaw
    eccentricity, level bias and nonlinearity); noise: False for exact
    measurements (no tracker, encoder, level or joint noise).

    Known to a user (pass to the model): ``base_nominal`` (4, 4),
    ``mount_nominal`` (4, 4), ``targets_nominal`` (3, 3) m. Truth:
    ``robot_truth`` (TruthRobot, tools = the AT targets), ``mount`` (4, 4),
    ``gravity`` (3,), the head errors.

    Example:
        >>> import torchcal
        >>> st = SensorTruth(torchcal.load_robot("fanuc_lrmate200i"), seed=0)
        >>> s = st.sample_commands(5, seed=0)
        >>> m = st.measure_sts(s.q, s.direction, seed=1)
        >>> m.xyz.shape, m.extra["rotation"].shape, bool(st.valid(s.q).all())
        (torch.Size([5, 3]), torch.Size([5, 3, 3]), True)
    """

    def __init__(self, robot: Robot, seed: int, tracker_distance: float = 2.7, base_height: float = -0.5,
                 gravity_tilt_deg: float = 0.03, mount_mm: float = 0.3, mount_deg: float = 0.05,
                 unmodelled: bool = True, noise: bool = True):
        super().__init__()
        if not 0.5 <= tracker_distance <= 10.0:
            raise ValueError(f"SensorTruth: tracker_distance {tracker_distance} m is outside 0.5-10 m")
        f64 = {"dtype": torch.float64}
        self.seed, self.noise, self.unmodelled = int(seed), bool(noise), bool(unmodelled)
        base = homogeneous(_rz(torch.tensor(math.pi, **f64)), torch.tensor([tracker_distance, 0.0, base_height], **f64))
        targets = units.mm_to_m(torch.tensor(AT_TARGETS_MM, **f64))
        self.robot_truth = TruthRobot.fanuc_paper2(robot, targets, seed, base_nominal=base, unmodelled=unmodelled)
        self.robot = robot
        g = np.random.default_rng([int(seed), 3])
        def unit():
            x = g.normal(size=3)
            return x / np.linalg.norm(x)

        def t(a):
            return torch.as_tensor(np.asarray(a, dtype=np.float64))

        self.register_buffer("base_nominal", base)
        self.register_buffer("targets_nominal", targets)
        self.register_buffer("mount_nominal", homogeneous(_rx(torch.tensor(math.pi, **f64)), torch.tensor([0.0, 0.0, 0.12], **f64)))
        err = homogeneous(so3_exp(t(unit() * mount_deg * units.DEG * g.uniform(0.7, 1.0))),
                          t(unit() * mount_mm * units.MM * g.uniform(0.7, 1.0)))
        self.register_buffer("mount", self.mount_nominal @ err)
        az = g.uniform(0.0, 2.0 * np.pi)
        tilt = gravity_tilt_deg * units.DEG
        self.register_buffer("gravity", t([math.sin(tilt) * math.cos(az), math.sin(tilt) * math.sin(az), math.cos(tilt)]))
        # STS head errors Paper III's nominal head (11) lacks (deg): axis skew, yaw eccentricity, level bias / cubic
        on = 1.0 if unmodelled else 0.0
        self.axis_skew = on * float(g.choice([-1.0, 1.0]) * g.uniform(0.002, 0.004)) * units.DEG
        self.yaw_ecc, self.yaw_ecc_phase = on * float(g.uniform(0.0004, 0.0008)) * units.DEG, float(g.uniform(0, 2 * np.pi))
        self.level_bias = on * float(g.choice([-1.0, 1.0]) * g.uniform(0.001, 0.002)) * units.DEG
        self.level_cubic = on * float(g.choice([-1.0, 1.0]) * g.uniform(0.002, 0.004)) * units.DEG
        rep = robot.repeatability
        if rep is None:
            raise ValueError(f"SensorTruth: robot '{robot.name}' declares no joint repeatability (YAML 'repeatability:')")
        self.register_buffer("joint_var_fwd", rep.var_fwd.to(**f64).clone())
        self.register_buffer("joint_var_bwd", rep.var_bwd.to(**f64).clone())

    # ------------------------------------------------------------------ truth
    @property
    def n(self) -> int:
        return self.robot_truth.n

    @property
    def limits(self) -> torch.Tensor:
        """(n, 2) command limits (rad), Paper III Table 2 = the robot YAML's."""
        return self.robot.joint_map.limits.to(self.mount)

    def sensor_pose(self, q: torch.Tensor, direction: torch.Tensor | None = None, v: torch.Tensor | None = None) -> torch.Tensor:
        """True pose of the STS base frame s0 in the tracker frame (B, 4, 4): T_m^LT0 E_0^m F_a(q + v) T_s0^n E_s0^n (13)."""
        return self.robot_truth.flange(q, direction, v, base=True) @ self.mount.to(q)

    def target_points(self, q, tool, direction=None, v=None) -> torch.Tensor:
        """True AT positions (B, 3) m in the tracker frame; tool: (B,) indices 0-2."""
        return self.robot_truth.points(q, tool, direction, v)

    @property
    def virtual_level(self) -> torch.Tensor:
        """(3,) the tracker's own 'up' reading (virtual level) that the SDK rebuilds rotations with.

        Taken as exact (= ``gravity``): pass it to the instrument that turns exported
        rotations back into angles; the model's gravity (27) starts at the tracker's z
        and has to find the 0.03° tilt itself.
        """
        return self.gravity

    def read_head(self, T: torch.Tensor) -> torch.Tensor:
        """Noise-free readings (B, 3) = (ψ, θ, φ) rad of the real head at sensor poses T (B, 4, 4).

        Axis skew and yaw eccentricity enter ψ, θ; φ is the real x_s2's inclination plus bias and cubic term.
        """
        R, p = T[:, :3, :3], T[:, :3, 3]
        psi, theta, x = head_angles(R, p, self.axis_skew)
        phi = torch.asin((x * self.gravity.to(x)).sum(-1).clamp(-1.0, 1.0))
        psi = psi + self.yaw_ecc * torch.sin(psi + self.yaw_ecc_phase)
        phi = phi + self.level_bias + self.level_cubic * (phi / (LEVEL_RANGE_DEG * units.DEG)) ** 3
        return torch.stack([psi, theta, phi], -1)

    def valid(self, q: torch.Tensor, direction: torch.Tensor | None = None) -> torch.Tensor:
        """(B,) bool: roll and level of the noise-free pose inside the STS ranges (3.2)."""
        return self._range_flags(q, direction)[0]

    def _range_flags(self, q, direction=None, margin_deg: float = 0.0):
        with torch.no_grad():
            a = sts_angles_of(self.sensor_pose(q, direction), self.gravity)
        roll = a[:, 1].abs() <= (ROLL_RANGE_DEG - margin_deg) * units.DEG
        level = a[:, 2].abs() <= (LEVEL_RANGE_DEG - margin_deg) * units.DEG
        return roll & level, roll, level

    def sample_commands(self, count: int, seed: int, skip: int = 0, batch: int | None = None,
                        margin_deg: float = 0.5) -> CommandSample:
        """``count`` valid quasi-random commands over the limits, in the order they are drawn.

        Candidates come from one scrambled Sobol sequence (:func:`quasi_random_commands`,
        ``seed``, starting after ``skip`` points); those outside the roll or level
        range are dropped and counted; a pose is kept only ``margin_deg`` inside
        the ranges, so that backlash and joint noise (hundredths of a degree) never
        push it out. Directions follow the visiting order (:func:`approach_directions`).
        -> :class:`CommandSample`.
        """
        if count < 1:
            raise ValueError(f"sample_commands: count must be >= 1, got {count}")
        batch = batch or max(64, 6 * count)
        cands, flags, n_ok, drawn = [], [], 0, 0
        while n_ok < count:
            if drawn > 200 * count + 10_000:
                raise ValueError(f"sample_commands: only {n_ok} of {count} valid poses in {drawn} candidates; "
                                 "the STS cannot see the tracker from this set-up")
            qc = quasi_random_commands(self.limits, batch, seed, skip=skip + drawn).to(self.mount)
            f = torch.stack(self._range_flags(qc, margin_deg=margin_deg), 1)  # (batch, 3): ok, roll ok, level ok
            cands.append(qc)
            flags.append(f)
            n_ok += int(f[:, 0].sum())
            drawn += batch
        qc, f = torch.cat(cands), torch.cat(flags)
        used = int(f[:, 0].nonzero()[count - 1]) + 1  # candidates after the count-th valid one were never needed
        qc, f = qc[:used], f[:used]
        ok, roll, level = f.unbind(1)
        rej = {"roll": int((~roll & level).sum()), "level": int((roll & ~level).sum()), "both": int((~roll & ~level).sum())}
        q = qc[ok]
        return CommandSample(q, approach_directions(q), used, rej)

    # ----------------------------------------------------------- measurement
    def _joint_errors(self, s: torch.Tensor, g: torch.Generator) -> torch.Tensor:
        z = torch.randn(s.shape, generator=g, dtype=torch.float64).to(s)
        var = torch.where(s > 0, self.joint_var_fwd.to(s), torch.where(s < 0, self.joint_var_bwd.to(s),
                                                                       0.5 * (self.joint_var_fwd + self.joint_var_bwd).to(s)))
        return z * var.sqrt() if self.noise else torch.zeros_like(s)

    def _check(self, q, direction, who):
        q = torch.as_tensor(q).to(self.mount)
        if q.ndim != 2 or q.shape[1] != self.n:
            raise ValueError(f"{who}: commands must have shape (N, {self.n}), got {tuple(q.shape)}")
        s = approach_directions(q) if direction is None else torch.as_tensor(direction).to(q)
        if s.shape != q.shape:
            raise ValueError(f"{who}: directions must have shape {tuple(q.shape)}, got {tuple(s.shape)}")
        bad = first_invalid_direction(s)
        if bad is not None:
            raise ValueError(f"{who}: direction at pose {bad[0]}, joint {bad[1] + 1} is {float(s[bad])}, expected -1, 0 or +1")
        return q, s

    def measure_sts(self, q: torch.Tensor, direction: torch.Tensor | None, seed: int, static: bool = False) -> Measurements:
        """One STS measurement per command (module docstring, steps 1-5).

        q: (N, n) commands inside the STS ranges (:meth:`valid`); direction:
        (N, n) approach directions or None (visiting order); seed: all draws.
        -> Measurements, tool 0 (the STS), xyz (N, 3) m measured s0 origin,
        has_direction, and extra: 'rotation' (N, 3, 3) exported R_s0^LT0,
        'sts_angles' (N, 3) measured (ψ, θ, φ) rad (inclination reading),
        'sts_angle_std' (N, 3) the σ of (46) at each row, 'v' (N, n) joint
        errors, 'xyz_exact' (N, 3) / 'rotation_exact' (N, 3, 3) the true pose
        without joint errors (v = 0), 'rotation_true' (N, 3, 3) the true pose reached.
        static: the robot stands still while the rows are read (Paper III 5.3:
        M readings of one configuration): one joint-error draw, that of row 0, for every row.
        Raises ValueError naming the first pose outside the STS ranges.
        """
        q, s = self._check(q, direction, "measure_sts")
        N = q.shape[0]
        ok = self.valid(q, s)
        if not bool(ok.all()):
            i = int((~ok).nonzero()[0])
            a = sts_angles_of(self.sensor_pose(q[i:i + 1], s[i:i + 1]), self.gravity)[0] / units.DEG
            raise ValueError(f"measure_sts: pose {i} is outside the STS ranges (roll {float(a[1]):.1f}°, "
                             f"level {float(a[2]):.1f}°; limits ±{ROLL_RANGE_DEG}°, ±{LEVEL_RANGE_DEG}°); "
                             f"{int((~ok).sum())} of {N} poses are")
        g = torch.Generator().manual_seed(int(seed))
        with torch.no_grad():
            v = self._joint_errors(s, g)
            if static:
                v = v[:1].expand_as(v).clone()
            T = self.sensor_pose(q, s, v)
            exact = self.sensor_pose(q, s)
            head = self.read_head(T)
            z = torch.randn(N, 6, generator=g, dtype=torch.float64).to(q) * (1.0 if self.noise else 0.0)
            std = torch.stack([torch.full_like(head[:, 0], SIGMA_ENCODER_DEG * units.DEG),
                               torch.full_like(head[:, 0], SIGMA_ENCODER_DEG * units.DEG), sigma_level(head[:, 2])], -1)
            angles = head + std * z[:, 3:]
            p = tracker_noisy_points(T[:, :3, 3], z[:, :3])
            R = sts_rotation(p, angles, self.gravity.to(q), hint=self._x_s2(T))
        return Measurements(q, torch.zeros(N, dtype=torch.long, device=q.device), p, s,
                            torch.arange(N, device=q.device), torch.arange(1, N + 1), has_direction=True,
                            source="simulated STS", extra={"rotation": R, "sts_angles": angles, "sts_angle_std": std,
                                                           "v": v, "xyz_exact": exact[:, :3, 3],
                                                           "rotation_exact": exact[:, :3, :3],
                                                           "rotation_true": T[:, :3, :3]})

    def _x_s2(self, T):
        return head_angles(T[:, :3, :3], T[:, :3, 3], self.axis_skew)[2]

    def measure_targets(self, q: torch.Tensor, direction: torch.Tensor | None, seed: int, targets=(0, 1, 2)) -> Measurements:
        """The AT method (6.1): each target position measured in its own set-up over all commands.

        q: (N, n); direction: (N, n) or None; seed: draws; targets: which AT positions.
        -> Measurements tool-major (all poses with targets[0], then targets[1], ...),
        tool = target index, pose = 0..N-1 repeated, xyz (T N, 3) m with spherical
        tracker noise; every row has its own joint errors (each set-up revisits
        the pose). extra: 'v', 'xyz_exact' (v = 0, no noise).
        """
        q, s = self._check(q, direction, "measure_targets")
        tid = torch.as_tensor(targets, dtype=torch.long).reshape(-1)
        if tid.numel() == 0 or bool(((tid < 0) | (tid > 2)).any()):
            raise ValueError(f"measure_targets: targets must be indices 0-2, got {tid.tolist()}")
        N, T = q.shape[0], tid.numel()
        qq, ss = q.repeat(T, 1), s.repeat(T, 1)
        tool = tid.to(q.device).repeat_interleave(N)
        g = torch.Generator().manual_seed(int(seed))
        with torch.no_grad():
            v = self._joint_errors(ss, g)
            z = torch.randn(T * N, 3, generator=g, dtype=torch.float64).to(q) * (1.0 if self.noise else 0.0)
            p = tracker_noisy_points(self.target_points(qq, tool, ss, v), z)
            exact = self.target_points(qq, tool, ss)
        return Measurements(qq, tool, p, ss, torch.arange(N, device=q.device).repeat(T), torch.arange(1, T * N + 1),
                            has_direction=True, source="simulated AT", extra={"v": v, "xyz_exact": exact})

    def describe(self) -> dict:
        """The sensor-side truth in file units (mm, deg) plus the robot's :meth:`TruthRobot.describe`."""
        from ..kinematics.transforms import so3_log

        e = torch.linalg.solve(self.mount_nominal, self.mount)
        tilt = float(torch.acos(self.gravity[2].clamp(-1.0, 1.0)))
        return {
            "mount_error_mm": round(float(units.m_to_mm(e[:3, 3].norm())), 4),
            "mount_error_deg": round(float(units.rad_to_deg(so3_log(e[:3, :3]).norm())), 4),
            "gravity_tilt_deg": round(float(units.rad_to_deg(tilt)), 4),
            "axis_skew_deg": round(self.axis_skew / units.DEG, 5),
            "yaw_eccentricity_deg": round(self.yaw_ecc / units.DEG, 5),
            "level_bias_deg": round(self.level_bias / units.DEG, 5),
            "level_cubic_deg": round(self.level_cubic / units.DEG, 5),
            "tracker_distance_m": round(float(self.base_nominal[:3, 3].norm()), 3),
            "robot": self.robot_truth.describe(),
        }


def sts_angles_of(T: torch.Tensor, g: torch.Tensor) -> torch.Tensor:
    """:func:`sts_angles` of poses T (B, 4, 4) against the upward vertical g (3,)."""
    return sts_angles(T[:, :3, :3], T[:, :3, 3], g.to(T))


__all__ = [
    "AT_TARGETS_MM", "CommandSample", "SensorTruth", "from_spherical", "head_angles", "sigma_distance", "sigma_level",
    "sts_angles", "sts_angles_of", "sts_rotation", "to_spherical", "tracker_noisy_points", "triangle_normal",
]
