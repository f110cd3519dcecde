"""Repeatability and joint variances: ISO 9283 (Paper II, 5.3) and eqs. (53)-(54) (5.4, Table 5).

ISO 9283 position repeatability of one pose is RP = l̄ + 3 S_l, l_j the
distance of the j-th attained position to the barycentre of all cycles.

The joint variance σ_J² of (32) is the spread of where a joint stops when it
is commanded to the same value again. Paper II measures M positions per
joint, each twice from the same direction, projects both points into the
joint's rotation plane, takes their midpoint (53) and the angles of each
point about the axis relative to the midpoint (54), and fits a normal
distribution to all those angles, for forward and backward approach alike.
"""

from __future__ import annotations

from dataclasses import dataclass

import torch

from ..core import units
from ..kinematics.robot import Robot
from ..core.measurements import Measurements
from .cpa import CPAModel, home_command, fit_circle, single_joint_commands


def iso9283_repeatability(points) -> torch.Tensor:
    """ISO 9283 position repeatability RP = l̄ + 3 S_l (Paper II, 5.3).

    points: (cycles, 3) attained positions of one commanded pose, or
    (poses, cycles, 3) for several poses; any length unit.
    -> () or (poses,) in the same unit. l_j = |x_j - barycentre|, l̄ their
    mean, S_l their sample standard deviation (n - 1). Needs >= 2 cycles.
    """
    x = torch.as_tensor(points, dtype=torch.float64)
    single = x.ndim == 2
    if single:
        x = x[None]
    if x.ndim != 3 or x.shape[-1] != 3:
        raise ValueError(f"repeatability points must be (cycles, 3) or (poses, cycles, 3), got {tuple(x.shape)}")
    if x.shape[1] < 2:
        raise ValueError(f"ISO 9283 repeatability needs at least 2 cycles per pose, got {x.shape[1]}")
    bad = ~torch.isfinite(x).all(-1)
    if bad.any():
        p, c = bad.nonzero()[0].tolist()
        raise ValueError(f"repeatability points: pose {p + 1}, cycle {c + 1} is not finite")
    bary = x.mean(1, keepdim=True)
    l = torch.linalg.norm(x - bary, dim=-1)
    rp = l.mean(1) + 3.0 * l.std(1, correction=1)
    return rp[0] if single else rp


# ------------------------------------------------------------ joint variance


def rotation_plane_coordinates(points: torch.Tensor, axis_point, axis_dir) -> torch.Tensor:
    """Coordinates (..., 2) of points (..., 3) in a joint's rotation plane, relative to its axis.

    axis_point: (3,) a point on the axis; axis_dir: (3,) its direction (any
    length). The in-plane basis (e1, e2) is right-handed about axis_dir, so
    angles grow with positive joint motion.
    """
    c = torch.as_tensor(axis_point, dtype=points.dtype, device=points.device)
    w = torch.as_tensor(axis_dir, dtype=points.dtype, device=points.device)
    w = w / torch.linalg.norm(w)
    # start e1 from the coordinate axis least parallel to w: never a degenerate cross product
    k = int(torch.argmin(w.abs()))
    ek = torch.zeros(3, dtype=w.dtype, device=w.device)
    ek[k] = 1.0
    e1 = torch.linalg.cross(w, ek)
    e1 = e1 / torch.linalg.norm(e1)
    e2 = torch.linalg.cross(w, e1)
    d = points - c
    return torch.stack([d @ e1, d @ e2], -1)


def _wrap(a: torch.Tensor) -> torch.Tensor:
    return torch.atan2(torch.sin(a), torch.cos(a))


def pair_angular_errors(points_1: torch.Tensor, points_2: torch.Tensor, axis_point, axis_dir) -> torch.Tensor:
    """Angular errors (2M,) of (53)-(54), rad: each of the M pairs' two points against their midpoint."""
    p1 = torch.as_tensor(points_1, dtype=torch.float64)
    p2 = torch.as_tensor(points_2, dtype=torch.float64).to(p1.device)
    if p1.shape != p2.shape or p1.ndim != 2 or p1.shape[1] != 3:
        raise ValueError(f"pairs must be two (M, 3) arrays, got {tuple(p1.shape)} and {tuple(p2.shape)}")
    bad = ~(torch.isfinite(p1).all(1) & torch.isfinite(p2).all(1))
    if bad.any():
        raise ValueError(f"joint variance pairs: position {int(bad.nonzero()[0]) + 1} has a non-finite point")
    xy1 = rotation_plane_coordinates(p1, axis_point, axis_dir)
    xy2 = rotation_plane_coordinates(p2, axis_point, axis_dir)
    xya = 0.5 * (xy1 + xy2)  # (53)
    ang = lambda xy: torch.atan2(xy[:, 1], xy[:, 0])  # noqa: E731
    # (54) with atan2 (the quadrant matters over a whole joint range), wrapped to (-pi, pi]
    return torch.cat([_wrap(ang(xy1) - ang(xya)), _wrap(ang(xy2) - ang(xya))])


def joint_variance_from_pairs(points_1, points_2, axis_point, axis_dir, unbiased: bool = True, sigma_m: float = 0.0) -> torch.Tensor:
    """Joint variance (rad², 0-dim tensor) from M positions each measured twice, eqs. (53)-(54).

    points_1, points_2: (M, 3) first and second measurement of each position
    (same approach direction); axis_point (3,), axis_dir (3,): the joint's axis
    line in the same frame (from CPA, or nominal).
    The angular errors of (54) are fitted with a normal distribution
    (``scipy.stats.norm.fit``). Measured against the midpoint of only two
    attempts they carry half the spread of one attempt (E[(x - x̄)²] =
    σ²(1 - 1/2)), so with ``unbiased=True`` the fitted variance is doubled to
    estimate the per-attempt σ_J² that the noise model (32) needs;
    ``unbiased=False`` returns the fitted variance as Paper II computed it.
    sigma_m: tracker standard deviation (m) per axis; its tangential share
    σ_m²/ρ² (ρ: distance from the axis) is removed from the per-attempt
    variance (clamped at 0).
    """
    from scipy import stats

    err = pair_angular_errors(points_1, points_2, axis_point, axis_dir)
    _, sd = stats.norm.fit(err.cpu().numpy())
    var = sd * sd * (2.0 if unbiased else 1.0)
    if sigma_m > 0:
        p = torch.cat([torch.as_tensor(points_1, dtype=torch.float64), torch.as_tensor(points_2, dtype=torch.float64)])
        rho2 = (rotation_plane_coordinates(p, axis_point, axis_dir) ** 2).sum(-1)
        noise = float((sigma_m**2 / rho2).mean()) * (1.0 if unbiased else 0.5)
        var = max(var - noise, 0.0)
    return torch.tensor(var, dtype=torch.float64, device=err.device)


@dataclass
class JointVariancePlan:
    """Commands of the joint-variance experiment of 5.4, in execution order (SI).

    Each measured row is reached from ``approach`` (the command visited just
    before it), so a sequential simulator or a robot program reproduces the
    approach direction. q, approach: (R, n) controller commands;
    direction: (R, n) approach direction per URDF joint (+1 forward, -1
    backward on the moving joint, 0 elsewhere: the others do not move);
    joint: (R,) 0-based moving joint; position: (R,) 0..M-1; repeat: (R,) 0 or 1;
    forward: (R,) bool.
    """

    q: torch.Tensor
    approach: torch.Tensor
    direction: torch.Tensor
    joint: torch.Tensor
    position: torch.Tensor
    repeat: torch.Tensor
    forward: torch.Tensor

    def __len__(self) -> int:
        return self.q.shape[0]

    def sequence(self) -> tuple[torch.Tensor, torch.Tensor]:
        """The full motion program: commands (2R, n) alternating approach, target; measured (2R,) bool."""
        seq = torch.stack([self.approach, self.q], 1).reshape(-1, self.q.shape[1])
        measured = torch.tensor([False, True], device=self.q.device).repeat(len(self))
        return seq, measured

    def to_measurements(self, tool: int = 0, source: str = "joint variance plan") -> Measurements:
        """Rows to measure (xyz NaN) with their directions; pose id = row index."""
        return Measurements.from_tensors(self.q, torch.full((len(self),), tool, dtype=torch.long), None,
                                         self.direction, source=source)


def joint_variance_plan(robot: Robot, positions: int = 9, approach: float = units.deg_to_rad(5.0), joints=None,
                        home=None, ranges: torch.Tensor | None = None) -> JointVariancePlan:
    """Plan the joint-variance experiment (Paper II, 5.4): M positions per joint, each reached twice
    from below (forward set) and twice from above (backward set).

    positions: M (9 in the paper); approach: how far before the target each
    approach starts (rad / m, on the moving joint's command); joints: 0-based
    joints to plan (all); home: (n,) controller command of the resting joints;
    ranges: (n, 2) controller range to spread positions over (default: the
    joint map's limits); positions sit at the centres of M equal cells, so the
    approach stays inside the range when it is smaller than half a cell.
    Only one URDF joint variable moves per joint (see :func:`single_joint_commands`).
    """
    jm = robot.joint_map
    n = robot.n
    joints = list(range(n)) if joints is None else [int(j) for j in joints]
    lim = (jm.limits if ranges is None else torch.as_tensor(ranges, dtype=torch.float64)).to(home_command(robot, home))
    rows = {k: [] for k in ("q", "approach", "direction", "joint", "position", "repeat", "forward")}
    for j in joints:
        lo, hi = lim[j]
        targets = lo + (hi - lo) * (torch.arange(positions, dtype=torch.float64, device=lo.device) + 0.5) / positions
        for fwd in (True, False):
            s = 1.0 if fwd else -1.0
            tq = targets.repeat_interleave(2)
            q = single_joint_commands(robot, j, tq, home)
            qa = single_joint_commands(robot, j, tq - s * approach, home)
            d = torch.zeros_like(q)
            d[:, j] = s
            rows["q"].append(q)
            rows["approach"].append(qa)
            rows["direction"].append(d)
            rows["joint"].append(torch.full((q.shape[0],), j, dtype=torch.long))
            rows["position"].append(torch.arange(positions).repeat_interleave(2))
            rows["repeat"].append(torch.tensor([0, 1]).repeat(positions))
            rows["forward"].append(torch.full((q.shape[0],), fwd))
    return JointVariancePlan(**{k: torch.cat(v) for k, v in rows.items()})


@dataclass
class JointVarianceTable:
    """Estimated joint variances per joint and approach direction (Table 5), rad² inside.

    joints: 0-based joints; forward, backward: (J,) rad²; axes: (J, 2, 3)
    axis point and direction used for each joint.
    """

    joints: list[int]
    forward: torch.Tensor
    backward: torch.Tensor
    axes: torch.Tensor

    def rows(self) -> list[dict]:
        """Table 5 layout in deg²: [{'joint': 1, 'forward_deg2': ..., 'backward_deg2': ...}, ...]."""
        to_deg2 = lambda v: float(units.rad_to_deg(units.rad_to_deg(v)))  # noqa: E731
        return [{"joint": j + 1, "forward_deg2": to_deg2(f), "backward_deg2": to_deg2(b)}
                for j, f, b in zip(self.joints, self.forward.tolist(), self.backward.tolist())]


def joint_variances(plan: JointVariancePlan, measured, axes=None, unbiased: bool = True, sigma_m: float = 0.0) -> JointVarianceTable:
    """Forward and backward joint variances (Table 5) from a measured :class:`JointVariancePlan`.

    measured: :class:`Measurements` in the plan's row order (its commands are
    checked against the plan) or an (R, 3) tensor of points, metres;
    axes: a :class:`CPAModel`, a pair (points (n, 3), dirs (n, 3)) of axis
    lines, or None to fit each joint's axis as the circle through its own
    4M measured points; unbiased, sigma_m: see :func:`joint_variance_from_pairs`.
    """
    if isinstance(measured, Measurements):
        if measured.q.shape != plan.q.shape:
            raise ValueError(f"{measured.source or 'measurements'}: {tuple(measured.q.shape)} commands, the plan has {tuple(plan.q.shape)}")
        off = (measured.q - plan.q.to(measured.q)).abs().amax(1) > 1e-9
        if off.any():
            r = int(off.nonzero()[0])
            raise ValueError(f"{measured.source or 'measurements'}, row {int(measured.rows[r])}: command differs from the plan's row {r + 1}")
        xyz = measured.xyz
    else:
        xyz = torch.as_tensor(measured, dtype=torch.float64)
    if xyz.shape != (len(plan), 3):
        raise ValueError(f"measured points must be ({len(plan)}, 3), got {tuple(xyz.shape)}")
    bad = ~torch.isfinite(xyz).all(1)
    if bad.any():
        raise ValueError(f"joint variance: row {int(bad.nonzero()[0]) + 1} has no measured point")
    if isinstance(axes, CPAModel):
        axes = (axes.axis_points, axes.axis_dirs)
    joints = sorted(set(plan.joint.tolist()))
    fwd, bwd, used = [], [], []
    for j in joints:
        rows_j = plan.joint == j
        if axes is None:
            circ = fit_circle(xyz[rows_j.to(xyz.device)], f"joint {j + 1} variance axis")
            c, w = circ.center, circ.normal  # sign is irrelevant: only angle differences enter
        else:
            c, w = torch.as_tensor(axes[0][j], dtype=torch.float64), torch.as_tensor(axes[1][j], dtype=torch.float64)
        used.append(torch.stack([c.to(xyz), w.to(xyz)]))
        for forward, out in ((True, fwd), (False, bwd)):
            sel = rows_j & (plan.forward == forward)
            pos = plan.position[sel]
            rep = plan.repeat[sel]
            pts = xyz[sel.to(xyz.device)]
            order = torch.argsort(pos * 2 + rep)
            pos, rep, pts = pos[order], rep[order], pts[order.to(xyz.device)]
            if sel.sum() % 2 or not (torch.equal(rep[0::2], torch.zeros_like(rep[0::2])) and torch.equal(pos[0::2], pos[1::2])):
                raise ValueError(f"joint {j + 1} ({'forward' if forward else 'backward'}): every position needs exactly two measurements")
            out.append(joint_variance_from_pairs(pts[0::2], pts[1::2], c, w, unbiased, sigma_m))
    return JointVarianceTable(joints, torch.stack(fwd), torch.stack(bwd), torch.stack(used))
