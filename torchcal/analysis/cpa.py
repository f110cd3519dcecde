"""Circle Point Analysis (CPA), the constant-error baseline of Paper II, section 6.1.

Why one module: Circle Point Analysis (Paper II 6.1, Tables 8-12) end to end: the single-joint commands, the circle and axis fits, the DH extraction; one method.

Each joint is turned alone while a tool point is measured; the points lie on
a circle whose centre and plane normal give the joint's actual axis line.
With every axis known at the home configuration the robot is, for constant
(joint-independent) errors, exactly a product of exponentials (POE)

    p_t(q) = Π_i exp(ξ_i (θ_i(q) - θ_i,home)) · m_t,

with ξ_i the screw of axis i and m_t the measured home position of tool t.
From consecutive axis lines the DH / Hayati-Mirmirani parameters of Table 9
are read off (:func:`dh_parameters`, :func:`dh_table`).

Units are SI (m, rad) everywhere except the paper's Table 8 constants (deg)
and the printable :func:`dh_table` (deg, mm).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np
import torch
from torch import nn

from ..core import units
from ..kinematics.fk import chain_frames
from ..kinematics.robot import Robot
from ..kinematics.transforms import axis_angle_to_matrix
from ..core.measurements import Measurements
from .stats import check_xyz

# ----------------------------------------------------------------- commands


@dataclass(frozen=True)
class SweepRange:
    """Start, end and step of one joint's CPA sweep, in controller units (deg, or mm if prismatic)."""

    start: float
    end: float
    step: float

    def values(self, prismatic: bool = False) -> np.ndarray:
        """Commanded values start, start + step, ... <= end (file units).

        A revolute sweep that covers a full turn (end - start >= 360 deg)
        drops its last value when it repeats the first one, as Table 8 counts
        72 points for -180..180 step 5. prismatic: the values are mm, where
        360 means nothing: every value is kept.

        Example:
            >>> len(SweepRange(-180.0, 180.0, 5.0).values())
            72
            >>> len(SweepRange(0.0, 400.0, 100.0).values(prismatic=True))
            5
        """
        if not self.step > 0 or not self.end > self.start:
            raise ValueError(f"sweep range needs start < end and step > 0, got {self}")
        k = np.arange(int(math.floor((self.end - self.start) / self.step + 1e-9)) + 1)
        v = self.start + k * self.step
        if not prismatic and v.size > 1 and v[-1] - v[0] >= 360.0 - 1e-9:
            v = v[:-1]
        return v


PAPER2_TABLE8 = (
    SweepRange(-100.0, 98.0, 3.0),
    SweepRange(-30.0, 50.0, 2.0),
    SweepRange(-30.0, 100.0, 2.0),
    SweepRange(-180.0, 180.0, 5.0),
    SweepRange(-90.0, 90.0, 3.0),
    SweepRange(-180.0, 180.0, 5.0),
)
"""Paper II, Table 8: CPA identification sweeps of the FANUC LR Mate 200i (deg); 67, 41, 66, 72, 61, 72 points."""


def home_command(robot: Robot, home) -> torch.Tensor:
    n = robot.n
    dev = robot.joint_map.coupling.device
    if home is None:
        return torch.zeros(n, dtype=torch.float64, device=dev)
    home = torch.as_tensor(home, dtype=torch.float64, device=dev)
    if home.shape != (n,):
        raise ValueError(f"home command must have shape ({n},), got {tuple(home.shape)}")
    return home


def single_joint_commands(robot: Robot, joint: int, values: torch.Tensor, home=None) -> torch.Tensor:
    """Commands that turn one URDF joint variable alone.

    joint: 0-based; values: (M,) controller values of that joint (SI);
    home: (n,) controller command the other joints keep (default zeros).
    -> q: (M, n) controller commands with q[:, joint] == values and every
    other URDF joint variable θ_j at its home value. For a coupled controller
    (FANUC θ3 = q2 + q3) the other commands follow, e.g. q3 = q3,home - Δq2.
    """
    jm = robot.joint_map
    home = home_command(robot, home)
    values = torch.as_tensor(values, dtype=torch.float64, device=home.device)
    theta_home = jm.to_joint(home[None])[0]
    # q(θ) = home + C^-1[:, j] Δθ_j when only θ_j moves; solve its j-th entry for Δθ_j
    gain = torch.linalg.inv(jm.coupling.to(home))[joint, joint]
    if abs(float(gain)) < 1e-12:
        raise ValueError(f"joint {joint + 1} ('{jm.names[joint]}'): its URDF variable cannot be turned alone by its own command")
    theta = theta_home.expand(values.shape[0], -1).clone()
    theta[:, joint] = theta_home[joint] + (values - home[joint]) / gain
    return jm.to_command(theta)


def cpa_sweep_commands(robot: Robot, table=PAPER2_TABLE8, home=None) -> list[torch.Tensor]:
    """CPA identification commands, one (M_i, n) tensor per joint (SI).

    table: one :class:`SweepRange` per controller joint, in controller units
    (deg / mm), read as the range of the moving joint's own command (Table 8);
    home: (n,) controller command of the resting joints (default zeros).
    Other URDF joints stay at home, so other controller commands may move
    (the FANUC's q3 = -q2 while J2 turns) and may leave the measured range
    of Table 3; check with ``robot.joint_map.within_limits`` if it matters.
    """
    if len(table) != robot.n:
        raise ValueError(f"CPA table has {len(table)} rows for a {robot.n}-joint robot")
    scale = units.joint_scale(robot.joint_map.prismatic)
    out = []
    for i, r in enumerate(table):
        vals = torch.as_tensor(r.values(prismatic=bool(robot.joint_map.prismatic[i])), dtype=torch.float64) * scale[i]
        out.append(single_joint_commands(robot, i, vals, home))
    return out


def cpa_validation_commands(robot: Robot, per_joint: int = 60, seed: int = 0, table=PAPER2_TABLE8, home=None) -> list[torch.Tensor]:
    """CPA validation commands (Table 11): ``per_joint`` quasi-random points on each joint's circle.

    Scrambled Halton values over each table range (low discrepancy, like the
    paper's quasi-random sets), seeded. -> list of (per_joint, n) commands, SI.
    """
    from scipy.stats import qmc

    if len(table) != robot.n:
        raise ValueError(f"CPA table has {len(table)} rows for a {robot.n}-joint robot")
    scale = units.joint_scale(robot.joint_map.prismatic)
    rng = np.random.default_rng(seed)
    out = []
    for i, r in enumerate(table):
        try:
            sampler = qmc.Halton(d=1, scramble=True, rng=rng)
        except TypeError:  # scipy < 1.15 names it seed
            sampler = qmc.Halton(d=1, scramble=True, seed=rng)
        u = sampler.random(per_joint)[:, 0]
        vals = torch.as_tensor(r.start + u * (r.end - r.start), dtype=torch.float64) * scale[i]
        out.append(single_joint_commands(robot, i, vals, home))
    return out


# -------------------------------------------------------------- circle fit


@dataclass
class CircleFit:
    """A circle fitted to 3-D points.

    center: (3,) m; normal: (3,) unit plane normal (sign arbitrary here);
    radius: m; basis: (3, 3) rows e1, e2, normal (right-handed);
    angles: (M,) in-plane angle of each point about the centre from e1 (rad);
    radial: (M,) in-plane distance to the centre minus radius (m);
    out_of_plane: (M,) signed distance from the plane (m);
    residuals: (M,) 3-D distance of each point from the circle (m).
    """

    center: torch.Tensor
    normal: torch.Tensor
    radius: float
    basis: torch.Tensor
    angles: torch.Tensor
    radial: torch.Tensor
    out_of_plane: torch.Tensor
    residuals: torch.Tensor


def _plane(P: np.ndarray, label: str):
    """Centroid and SVD basis (rows: two in-plane directions, then the normal) of points (M, 3)."""
    if P.ndim != 2 or P.shape[1] != 3 or P.shape[0] < 3:
        raise ValueError(f"{label}: need at least 3 points of shape (M, 3), got {P.shape}")
    if not np.isfinite(P).all():
        raise ValueError(f"{label}: points contain NaN/inf")
    c = P.mean(0)
    _, s, Vt = np.linalg.svd(P - c, full_matrices=False)
    if s[0] <= 1e-12 * max(1.0, float(np.abs(P).max())):
        raise ValueError(f"{label}: all points coincide (is the tool point on the joint axis?)")
    if s[1] <= 1e-9 * s[0]:
        raise ValueError(f"{label}: points are collinear; no circle through them")
    basis = Vt.copy()
    basis[2] = np.cross(basis[0], basis[1])  # right-handed
    return c, basis


def fit_circle(points: torch.Tensor, label: str = "circle fit") -> CircleFit:
    """Fit a circle to 3-D points (M, 3), M >= 3, metres.

    Plane by SVD (least-squares plane), then in that plane an algebraic
    (Kasa) circle refined by geometric least squares on the radial distances
    (scipy ``least_squares``, Levenberg-Marquardt): the algebraic fit is
    biased for short noisy arcs, the geometric one is the ML circle in the plane.
    """
    from scipy.optimize import least_squares

    ref = points if isinstance(points, torch.Tensor) else torch.as_tensor(points, dtype=torch.float64)
    P = ref.detach().to("cpu", torch.float64).numpy()
    c0, basis = _plane(P, label)
    X = P - c0
    u, v = X @ basis[0], X @ basis[1]
    A = np.stack([2 * u, 2 * v, np.ones_like(u)], 1)
    sol, *_ = np.linalg.lstsq(A, u * u + v * v, rcond=None)
    a, b, cc = sol
    r0 = math.sqrt(max(cc + a * a + b * b, 0.0))

    def fun(x):
        return np.hypot(u - x[0], v - x[1]) - x[2]

    def jac(x):
        du, dv = u - x[0], v - x[1]
        rho = np.maximum(np.hypot(du, dv), 1e-300)
        return np.stack([-du / rho, -dv / rho, -np.ones_like(u)], 1)

    x0 = np.array([a, b, r0])
    if len(u) > 3:
        res = least_squares(fun, x0, jac=jac, method="lm", xtol=1e-15, ftol=1e-15, gtol=1e-15)
        x = res.x
    else:  # three points: the algebraic circle passes through them exactly
        x = x0
    a, b, r = x
    center = c0 + a * basis[0] + b * basis[1]
    du, dv = u - a, v - b
    w = X @ basis[2] - (center - c0) @ basis[2]
    radial = np.hypot(du, dv) - r
    t = lambda arr: torch.as_tensor(arr, dtype=torch.float64, device=ref.device)  # noqa: E731
    return CircleFit(
        center=t(center), normal=t(basis[2]), radius=float(r), basis=t(basis),
        angles=t(np.arctan2(dv, du)), radial=t(radial), out_of_plane=t(w), residuals=t(np.hypot(radial, w)),
    )


@dataclass
class AxisFit:
    """One joint's identified axis line.

    joint: 0-based; point: (3,) a point on the axis (circle centre), m;
    direction: (3,) unit, the sense in which the joint variable turns
    positively (right-hand rule); radius: of the traced circle (m, NaN for a
    prismatic joint); residuals: (M,) distance of each measured point from the
    fitted circle (line), m; circle: the full :class:`CircleFit` (None if prismatic).
    """

    joint: int
    point: torch.Tensor
    direction: torch.Tensor
    radius: float
    residuals: torch.Tensor
    prismatic: bool = False
    circle: CircleFit | None = None


def fit_joint_axis(points: torch.Tensor, theta: torch.Tensor, joint: int = 0, prismatic: bool = False) -> AxisFit:
    """Axis of one joint from points (M, 3) measured while only its variable θ (M,) moved.

    The sign of the direction follows the motion: a revolute joint turns the
    points positively about +direction as θ grows, a prismatic one moves them
    along +direction. That is the nominal axis direction (the joint's own
    positive sense) in whatever frame the points are measured, no frame
    alignment needed.
    """
    label = f"joint {joint + 1} axis fit"
    theta = torch.as_tensor(theta, dtype=torch.float64)
    th = theta.detach().cpu().numpy()
    if th.shape != (points.shape[0],):
        raise ValueError(f"{label}: {points.shape[0]} points but θ has shape {tuple(th.shape)}")
    order = np.argsort(th)
    dth = np.diff(th[order])
    if (np.abs(dth) > 1e-12).sum() < 2:
        raise ValueError(f"{label}: the joint takes fewer than 3 distinct values")
    if prismatic:
        P = points.detach().to("cpu", torch.float64).numpy()
        c = P.mean(0)
        _, _, Vt = np.linalg.svd(P - c, full_matrices=False)
        d = Vt[0]
        steps = np.diff(P[order], axis=0) @ d
        if (steps * dth).sum() < 0:
            d = -d
        X = P - c
        res = np.linalg.norm(X - np.outer(X @ d, d), axis=1)
        t = lambda arr: torch.as_tensor(arr, dtype=torch.float64, device=points.device)  # noqa: E731
        return AxisFit(joint, t(c), t(d), float("nan"), t(res), True, None)
    circ = fit_circle(points, label)
    phi = circ.angles.cpu().numpy()[order]
    dphi = np.angle(np.exp(1j * np.diff(phi)))  # wrapped steps, fine while one step < 180 deg
    sign = 1.0 if (dphi * dth).sum() >= 0 else -1.0
    if sign < 0:
        circ.normal = -circ.normal
        # (e1, -e2, -n) stays right-handed; angles measured about -n change sign
        circ.basis = torch.stack([circ.basis[0], -circ.basis[1], -circ.basis[2]])
        circ.angles = -circ.angles
        circ.out_of_plane = -circ.out_of_plane
    return AxisFit(joint, circ.center, circ.normal, circ.radius, circ.residuals, False, circ)


# -------------------------------------------------------------- CPA model


class CPAModel(nn.Module):
    """The robot rebuilt from its CPA-identified axes as a product of exponentials.

    p_t(q) = Π_i exp(ξ_i (θ_i(q) - θ_i,home)) · m_t in the measurement frame,
    θ = joint_map(q). ξ_i: rotation about the line (axis_points[i],
    axis_dirs[i]) for a revolute joint, translation along axis_dirs[i] for a
    prismatic one. Exact for any chain whose errors are constant; it cannot
    describe joint-dependent errors (Paper II, 6.2).

    robot: nominal machine (joint map; nominal chain for :meth:`nominal_points`);
    axis_points, axis_dirs: (n, 3) lines at the home configuration, m;
    home_points: (T, 3) measured position of each tool at home, m;
    home: (n,) controller home command (default zeros);
    tools_nominal: (T, 3) nominal tool vectors (flange frame, m) for
    :meth:`nominal_points`; fits: the :class:`AxisFit` of each joint (reports).
    """

    def __init__(self, robot: Robot, axis_points, axis_dirs, home_points, home=None, tools_nominal=None, fits=None):
        super().__init__()
        n = robot.n
        self.robot = robot
        self.fits = list(fits) if fits is not None else None
        f64 = dict(dtype=torch.float64)
        axis_points = torch.as_tensor(axis_points, **f64)
        axis_dirs = torch.as_tensor(axis_dirs, **f64)
        home_points = torch.as_tensor(home_points, **f64)
        if axis_points.shape != (n, 3) or axis_dirs.shape != (n, 3):
            raise ValueError(f"CPA axes must be (n, 3) = ({n}, 3), got {tuple(axis_points.shape)}, {tuple(axis_dirs.shape)}")
        if home_points.ndim != 2 or home_points.shape[1] != 3:
            raise ValueError(f"home_points must be (T, 3), got {tuple(home_points.shape)}")
        norms = axis_dirs.norm(dim=1, keepdim=True)
        if (norms < 1e-12).any():
            raise ValueError(f"CPA axis {int((norms[:, 0] < 1e-12).nonzero()[0]) + 1} has a zero direction")
        jm, chain = robot.joint_map, robot.chain
        self.register_buffer("axis_points", axis_points.clone())
        self.register_buffer("axis_dirs", axis_dirs / norms)
        self.register_buffer("home_points", home_points.clone())
        self.register_buffer("home", home_command(robot, home).to(axis_points.device).clone())
        self.register_buffer("coupling", jm.coupling.clone())
        self.register_buffer("offset", jm.offset.clone())
        self.register_buffer("theta_home", (self.home @ self.coupling.T.to(self.home) + self.offset.to(self.home)).clone())
        # nominal chain, for nominal_points only
        self.register_buffer("origins", chain.origins.clone())
        self.register_buffer("axes", chain.axes.clone())
        self.register_buffer("prismatic", chain.prismatic.clone())
        self.register_buffer("tip", chain.tip.clone())
        self.register_buffer("tools_nominal", None if tools_nominal is None else torch.as_tensor(tools_nominal, **f64).clone())
        # plain Python flags: branching on a device tensor would synchronise per joint
        self._prismatic = [bool(p) for p in chain.prismatic.cpu()]

    @property
    def n(self) -> int:
        return self.axis_points.shape[0]

    def joint_variables(self, q: torch.Tensor) -> torch.Tensor:
        """Controller commands (B, n) -> URDF joint variables (B, n)."""
        return q @ self.coupling.T + self.offset

    def home_transform(self, q: torch.Tensor, v: torch.Tensor | None = None):
        """Rigid motion Π_i exp(ξ_i Δθ_i) of the last link relative to home: R (B, 3, 3), p (B, 3)."""
        qv = q if v is None else q + v
        dtheta = self.joint_variables(qv) - self.theta_home
        B = q.shape[0]
        R = torch.eye(3, dtype=q.dtype, device=q.device).expand(B, 3, 3)
        p = torch.zeros(B, 3, dtype=q.dtype, device=q.device)
        for i in range(self.n):
            w, c, d = self.axis_dirs[i], self.axis_points[i], dtheta[:, i]
            if self._prismatic[i]:
                p = p + (R @ w)[..., :] * d[:, None]
                continue
            Ri = axis_angle_to_matrix(w.expand(B, 3), d)
            # rotation about the line through c: x -> Ri (x - c) + c
            pi = c - (Ri @ c)
            p = p + (R @ pi[..., None])[..., 0]
            R = R @ Ri
        return R, p

    def points(self, q, tool, direction=None, v=None) -> torch.Tensor:
        """Tool t's position (B, 3) in the measurement frame; q: (B, n) rad/m, tool: (B,) long.

        direction is accepted for interface compatibility and ignored (CPA has
        no backlash); v: (B, n) joint positioning errors (controller space) or None.
        """
        R, p = self.home_transform(q, v)
        m = self.home_points[tool]
        return (R @ m[..., None])[..., 0] + p

    def forward(self, q, tool, direction=None, v=None) -> torch.Tensor:
        """Same as :meth:`points`."""
        return self.points(q, tool, direction, v)

    def spec(self) -> dict:
        """What it takes to rebuild this model (SI lists), see :meth:`from_spec`."""
        return {
            "kind": "cpa",
            "robot": self.robot.source or self.robot.name,
            "axis_points": self.axis_points.tolist(),
            "axis_dirs": self.axis_dirs.tolist(),
            "home_points": self.home_points.tolist(),
            "home": self.home.tolist(),
            "tools_nominal": None if self.tools_nominal is None else self.tools_nominal.tolist(),
        }

    @classmethod
    def from_spec(cls, spec: dict, robot: Robot | None = None) -> "CPAModel":
        """Rebuild a model saved with :meth:`spec`."""
        from ..kinematics.robot import load_robot

        robot = robot or load_robot(spec["robot"])
        return cls(robot, spec["axis_points"], spec["axis_dirs"], spec["home_points"], spec["home"], spec.get("tools_nominal"))

    def nominal_points(self, q, tool) -> torch.Tensor:
        """Nominal robot's prediction (B, 3): nominal chain and tools, measurement frame = base."""
        if self.tools_nominal is None:
            raise ValueError("CPAModel.nominal_points needs the nominal tool vectors (pass tools_nominal)")
        F = chain_frames(self.origins, self.axes, self.prismatic, self.joint_variables(q), None, self.tip)[2]
        p_t = self.tools_nominal[tool]
        return (F[:, :3, :3] @ p_t[..., None])[..., 0] + F[:, :3, 3]


def fit_cpa(robot: Robot, sweeps: list[Measurements], home_points, home=None, tools_nominal=None, tol: float = 1e-9) -> CPAModel:
    """Circle Point Analysis: identify every joint axis and build the POE :class:`CPAModel`.

    sweeps: one :class:`Measurements` per joint (in chain order), each measured
    with a single tool while only that URDF joint variable moved (see
    :func:`cpa_sweep_commands`); the joints before it must sit at home (they
    place the axis), the joints after it must not move (they hold the point).
    home_points: (T, 3) measured position of every tool at the home command, m,
    so that the model predicts any tool. home: (n,) controller home (zeros).
    tools_nominal: optional (T, 3) nominal tool vectors for ``nominal_points``.
    tol: how far (rad / m) a resting joint may be from its value.
    """
    n = robot.n
    if len(sweeps) != n:
        raise ValueError(f"CPA needs one sweep per joint: {n}, got {len(sweeps)}")
    jm = robot.joint_map
    home_q = home_command(robot, home)
    theta_home = jm.to_joint(home_q[None])[0]
    fits = []
    for i, s in enumerate(sweeps):
        label = s.source or f"sweep of joint {i + 1}"
        check_xyz(s)
        if s.q.shape[1] != n:
            raise ValueError(f"{label}: commands have {s.q.shape[1]} joints, the robot {n}")
        if torch.unique(s.tool).numel() != 1:
            raise ValueError(f"{label}: a CPA sweep must use one tool, found tools {torch.unique(s.tool).tolist()}")
        theta = jm.to_joint(s.q)
        before = (theta[:, :i] - theta_home[:i].to(theta)).abs()
        after = (theta[:, i + 1:] - theta[:1, i + 1:]).abs()
        for dev, what, start in ((before, "is not at home", 0), (after, "moves during the sweep", i + 1)):
            if dev.numel() and (dev > tol).any():
                r, j = (dev > tol).nonzero()[0].tolist()
                raise ValueError(f"{label}, row {int(s.rows[r])}: URDF joint {start + j + 1} {what} "
                                 f"(off by {float(dev[r, j]):.3g}); CPA turns joint {i + 1} alone")
        fits.append(fit_joint_axis(s.xyz, theta[:, i], i, bool(robot.chain.prismatic[i])))
    points = torch.stack([f.point for f in fits]).to(home_q.device)
    dirs = torch.stack([f.direction for f in fits]).to(home_q.device)
    return CPAModel(robot, points, dirs, home_points, home_q, tools_nominal, fits)


# ------------------------------------------------------ DH from the axes


@dataclass
class DHParameters:
    """Kinematic parameters between consecutive joint axes, rows i = 1..n-1 (SI).

    Standard DH rows: T_i = Rz(θ_i) Tz(d_i) Tx(a_i) Rx(α_i); Hayati-Mirmirani
    rows (``hayati[i]``, nominally parallel axes): T_i = Rz(θ_i) Tx(a_i)
    Rx(α_i) Ry(β_i), d_i = 0 by construction. theta: (n-1,) DH angle at the
    home configuration (rad); theta_offset: (n-1,) constant c_i in
    θ_i^DH = (coupling q)_i + c_i (rad, Table 9's 'q2 - 90.055');
    d, a: (n-1,) m; alpha, beta: (n-1,) rad (beta 0 on DH rows);
    frames: (n, 4, 4) the constructed frames 0..n-1 at home (z_i along axis i+1).
    """

    theta: torch.Tensor
    theta_offset: torch.Tensor
    d: torch.Tensor
    a: torch.Tensor
    alpha: torch.Tensor
    beta: torch.Tensor
    hayati: torch.Tensor
    frames: torch.Tensor = field(repr=False)


def _angle(u, v, axis) -> float:
    """Signed angle from u to v about axis (all (3,), u, v perpendicular to axis)."""
    return math.atan2(float(np.cross(u, v) @ axis), float(u @ v))


def _unit(x, what: str) -> np.ndarray:
    nx = np.linalg.norm(x)
    if nx < 1e-12:
        raise ValueError(f"DH extraction: {what} is undefined (zero vector)")
    return x / nx


def _frame(x, z, o) -> np.ndarray:
    F = np.eye(4)
    F[:3, 0], F[:3, 1], F[:3, 2], F[:3, 3] = x, np.cross(z, x), z, o
    return F


def dh_from_axes(points, dirs, reference, hayati) -> dict:
    """DH / Hayati-Mirmirani frames and parameters from joint axis lines (numpy, SI).

    points, dirs: (n, 3) lines (dirs: positive joint sense); reference: (n, 4, 4)
    frames 0..n-1 used only to settle conventions (where frame 0's origin and
    x axis sit, and the sign of each x_i where the common normal's sign is
    free); hayati: (n-1,) bool rows built the Hayati-Mirmirani way.
    -> dict of numpy arrays theta, d, a, alpha, beta (n-1,) and frames (n, 4, 4).
    """
    P = np.asarray(points, dtype=np.float64)
    Z = np.asarray(dirs, dtype=np.float64)
    Z = Z / np.linalg.norm(Z, axis=1, keepdims=True)
    ref = np.asarray(reference, dtype=np.float64)
    n = P.shape[0]
    # frame 0: on axis 1, at the foot of the reference origin, x from the reference x
    z = Z[0]
    o = P[0] + ((ref[0, :3, 3] - P[0]) @ z) * z
    # x_0: the reference x projected off axis 1 (its y, then z, if x runs along the axis)
    cand = [ref[0, :3, k] - (ref[0, :3, k] @ z) * z for k in range(3)]
    x = _unit(next((v for v in cand if np.linalg.norm(v) > 0.1), cand[0]), "frame 0 x axis")
    frames = [_frame(x, z, o)]
    out = {k: np.zeros(n - 1) for k in ("theta", "d", "a", "alpha", "beta")}
    for i in range(1, n):
        Fp = frames[-1]
        xp, zp, op = Fp[:3, 0], Fp[:3, 2], Fp[:3, 3]
        z, c = Z[i], P[i]
        xref = ref[i, :3, 0]
        if hayati[i - 1]:
            # Hayati-Mirmirani: the new origin is where axis i+1 meets the plane through o_{i-1} normal to z_{i-1}
            den = z @ zp
            if abs(den) < 1e-6:
                raise ValueError(f"DH extraction row {i}: axis {i + 1} lies in the plane normal to axis {i}; not a Hayati row")
            o_new = c + ((op - c) @ zp / den) * z
            r = o_new - op
            if np.linalg.norm(r) > 1e-9:
                xh = r / np.linalg.norm(r)
                if xh @ xref < 0:
                    xh = -xh
            else:
                xh = _unit(xref - (xref @ zp) * zp, f"row {i} x axis")
            yh = np.cross(zp, xh)
            # z in (xh, yh, zp) coordinates is (sin b, -sin a cos b, cos a cos b) for Rx(a) Ry(b) e_z
            beta = math.asin(float(np.clip(z @ xh, -1.0, 1.0)))
            alpha = math.atan2(-float(z @ yh), float(z @ zp))
            ca, sa, cb, sb = math.cos(alpha), math.sin(alpha), math.cos(beta), math.sin(beta)
            Rxy = np.array([[1, 0, 0], [0, ca, -sa], [0, sa, ca]]) @ np.array([[cb, 0, sb], [0, 1, 0], [-sb, 0, cb]])
            R = np.stack([xh, yh, zp], 1) @ Rxy
            F = np.eye(4)
            F[:3, :3], F[:3, 3] = R, o_new
            out["theta"][i - 1] = _angle(xp, xh, zp)
            out["a"][i - 1] = r @ xh
            out["alpha"][i - 1], out["beta"][i - 1], out["d"][i - 1] = alpha, beta, 0.0
        else:
            cr = np.cross(zp, z)
            if np.linalg.norm(cr) < 1e-9:
                raise ValueError(f"DH extraction row {i}: axes {i} and {i + 1} are parallel; use a Hayati-Mirmirani row")
            xn = cr / np.linalg.norm(cr)
            if xn @ xref < 0:  # intersecting axes leave the sign free; follow the reference
                xn = -xn
            # feet of the common normal: op + t1 zp on axis i, c + t2 z on axis i+1
            w0 = op - c
            b, dd, e = zp @ z, zp @ w0, z @ w0
            den = 1.0 - b * b
            t1, t2 = (b * e - dd) / den, (e - b * dd) / den
            foot2 = c + t2 * z
            F = _frame(xn, z, foot2)
            out["theta"][i - 1] = _angle(xp, xn, zp)
            out["d"][i - 1] = t1
            out["a"][i - 1] = (foot2 - (op + t1 * zp)) @ xn
            out["alpha"][i - 1] = _angle(zp, z, xn)
        frames.append(F)
    out["frames"] = np.stack(frames)
    return out


def nominal_axes(robot: Robot, home=None, base: torch.Tensor | None = None):
    """Nominal joint axis lines at the home command.

    -> points (n, 3) m, dirs (n, 3) unit, and the nominal joint frames (n, 4, 4)
    (each joint's frame before it moves), all in the frame ``base`` maps the
    robot base into (identity: the robot base frame).
    """
    home_q = home_command(robot, home)
    theta = robot.joint_map.to_joint(home_q[None])
    ch = robot.chain
    jR, jp, _ = chain_frames(ch.origins, ch.axes, ch.prismatic, theta, None, None, base)
    dirs = (jR[0] @ ch.axes[:, :, None])[..., 0]
    frames = torch.eye(4, dtype=torch.float64, device=jR.device).repeat(robot.n, 1, 1)
    frames[:, :3, :3], frames[:, :3, 3] = jR[0], jp[0]
    return jp[0], dirs, frames


def _wrap(x):
    return (x + np.pi) % (2 * np.pi) - np.pi


def dh_parameters(axes, robot: Robot, home=None, base_nominal: torch.Tensor | None = None, parallel_tol: float = 1e-6):
    """Nominal and identified DH / Hayati-Mirmirani parameters (Paper II, Table 9), SI.

    axes: a :class:`CPAModel` or a pair (points (n, 3), dirs (n, 3)) of axis
    lines at the home command, in the measurement frame; robot: the nominal
    machine; home: (n,) controller home (taken from a CPAModel if given);
    base_nominal: (4, 4) measurement frame -> robot base guess (identity);
    parallel_tol: rows whose nominal axes are parallel within this (rad) use
    Hayati-Mirmirani (the FANUC's joints 2-3).
    -> (nominal, identified) :class:`DHParameters`. Conventions (frame 0, signs
    of free common normals) follow the nominal joint frames, so a URDF written
    in DH form (like the bundled FANUC) gives back its own DH table.
    """
    if isinstance(axes, CPAModel):
        home = axes.home if home is None else home
        pts, dirs = axes.axis_points, axes.axis_dirs
    else:
        pts, dirs = axes
    if robot.chain.prismatic[:-1].any():
        # a prismatic joint's DH variable is d, not θ: not handled by this table
        raise NotImplementedError("DH extraction handles revolute joints only")
    home_q = home_command(robot, home)
    n = robot.n
    base = None if base_nominal is None else torch.as_tensor(base_nominal, dtype=torch.float64, device=home_q.device)
    npts, ndirs, nframes = nominal_axes(robot, home_q, base)
    npts, ndirs, nframes = (t.detach().cpu().numpy() for t in (npts, ndirs, nframes))
    hayati = np.linalg.norm(np.cross(ndirs[:-1], ndirs[1:]), axis=1) < parallel_tol
    nom = dh_from_axes(npts, ndirs, nframes, hayati)
    ident = dh_from_axes(torch.as_tensor(pts).detach().cpu().numpy(), torch.as_tensor(dirs).detach().cpu().numpy(), nom["frames"], hayati)
    theta_home = robot.joint_map.to_joint(home_q[None])[0].cpu().numpy()[: n - 1]
    jm_offset = robot.joint_map.offset.cpu().numpy()[: n - 1]
    for k in ("theta", "alpha", "beta"):
        # nominal angles in (-180, 180] (atan2 may give -180 for 180); identified ones on the nominal's branch
        nom[k] = np.where(np.abs(nom[k] + np.pi) < 1e-9, np.pi, nom[k])
        ident[k] = nom[k] + _wrap(ident[k] - nom[k])
    # θ_i^DH = (coupling q)_i + c_i: c_i = joint-map offset + (DH angle - URDF variable) at home
    nom["offset"] = jm_offset + _wrap(nom["theta"] - theta_home)
    ident["offset"] = nom["offset"] + (ident["theta"] - nom["theta"])
    result = []
    for p in (nom, ident):
        off = p["offset"]
        t = lambda a: torch.as_tensor(np.asarray(a), dtype=torch.float64, device=home_q.device)  # noqa: E731
        result.append(DHParameters(t(p["theta"]), t(off), t(p["d"]), t(p["a"]), t(p["alpha"]), t(p["beta"]),
                                   torch.as_tensor(hayati, device=home_q.device), t(p["frames"])))
    return result[0], result[1]


def _joint_expression(robot: Robot, i: int) -> str:
    row = robot.joint_map.coupling[i].cpu().tolist()
    terms = []
    for j, cj in enumerate(row):
        if abs(cj) < 1e-12:
            continue
        name = f"q{j + 1}"
        if abs(cj - 1) < 1e-12:
            terms.append(f"+ {name}")
        elif abs(cj + 1) < 1e-12:
            terms.append(f"- {name}")
        else:
            terms.append(f"{'+' if cj > 0 else '-'} {abs(cj):g} {name}")
    s = " ".join(terms)
    return s[2:] if s.startswith("+ ") else s


def dh_table(axes, robot: Robot, home=None, base_nominal: torch.Tensor | None = None) -> list[dict]:
    """Table 9: nominal and CPA-identified parameters, for printing (deg, mm).

    axes / robot / home / base_nominal as in :func:`dh_parameters`.
    -> rows {'parameter', 'unit', 'nominal', 'identified', 'expression'}
    ordered θ_i, d_i (DH rows), a_i, α_i, β_i (Hayati rows). θ rows give the
    constant c_i of θ_i = expression + c_i, e.g. θ2: 'q2', -90 -> -90.055.
    """
    nom, ident = dh_parameters(axes, robot, home, base_nominal)
    m = nom.a.shape[0]
    rows = []

    def add(name, unit, conv, key, idx, expr=""):
        for i in idx:
            rows.append({"parameter": f"{name}{i + 1}", "unit": unit, "nominal": float(conv(getattr(nom, key)[i])),
                         "identified": float(conv(getattr(ident, key)[i])), "expression": expr if not callable(expr) else expr(i)})

    hay = nom.hayati.cpu().tolist()
    add("theta", "deg", units.rad_to_deg, "theta_offset", range(m), lambda i: _joint_expression(robot, i))
    add("d", "mm", units.m_to_mm, "d", [i for i in range(m) if not hay[i]])
    add("a", "mm", units.m_to_mm, "a", range(m))
    add("alpha", "deg", units.rad_to_deg, "alpha", range(m))
    add("beta", "deg", units.rad_to_deg, "beta", [i for i in range(m) if hay[i]])
    return rows
