"""Unit slips a valid-looking file can hide: joints in radians, points in metres.

Both give numbers the contract accepts (radians sit inside any degree range;
metres are finite), and both give a fit that "succeeds" on a robot shrunk or
barely moved. The checks compare the file with the robot's own scale; real
data can trip them (a file of near-home poses, a tiny workspace), so every
caller offers the override named in :data:`OVERRIDE`.
"""

from __future__ import annotations

import math

import numpy as np
import torch

from ..core import units
from ..core.exceptions import TorchcalError

OVERRIDE = "--units-checked"
"""The one override name: a CLI flag, and ``data.units_checked: true`` in a fit config."""

MIN_ROWS = 10
"""Fewer rows than this are too few to judge the units by their spread."""

RADIAN_BOUND = 2 * math.pi + 0.05
"""Values (in the file's 'degrees') all within this are what radians look like."""

WIDE_RANGE_DEG = 8 * RADIAN_BOUND
"""A controller range at least this wide (deg) would rarely be used only within +-RADIAN_BOUND."""

SCALE_BOUNDS = (0.02, 50.0)
"""Measured / nominal distance ratios outside these are a unit slip (mm vs m: 1e-3, mm vs um: 1e3)."""

SUSPECT_SCALE = (0.5, 2.0)
"""Ratios outside these, inside :data:`SCALE_BOUNDS`, are named where a fit's nominal residual is implausible: points
in centimetres (0.1) or inches (0.039) 'calibrated' a robot ten times too small, 677 -> 0.019 mm, said only as a
robot description that may not be the robot. Not refused: real data of single-joint motions measured off the
flange sit at 0.15 (the UR10's T-Mac series A and B)."""


class UnitsError(TorchcalError, ValueError):
    """A file whose numbers look like another unit than the contract's (mm, deg)."""


def radian_columns(q: torch.Tensor, robot) -> list[str]:
    """Revolute joint columns that look like radians: every wide-range revolute joint stays within +-2 pi 'deg'.

    q: (R, n) controller commands as read (SI, i.e. the file's degrees converted). -> ['q1', ...] or [].
    """
    jm = robot.joint_map
    if q.shape[0] < MIN_ROWS:
        return []
    deg = units.joints_from_si(q.detach().cpu(), jm.prismatic.cpu()).numpy()
    span = units.joints_from_si(jm.limits.cpu().T, jm.prismatic.cpu()).T.numpy()  # (n, 2) deg / mm
    wide = [j for j in range(jm.n) if not bool(jm.prismatic[j]) and span[j, 1] - span[j, 0] >= WIDE_RANGE_DEG]
    if not wide:
        return []
    a = np.abs(deg[:, wide])
    # all zeros (a home-pose file) is no evidence either way
    if not np.isfinite(a).all() or a.max() > RADIAN_BOUND or a.max() < 0.5:
        return []
    return [f"q{j + 1}" for j in wide]


WIDE_TRAVEL_MM = 100.0
"""A linear axis at least this long (mm) would rarely be used only within its travel read as metres."""


def metre_columns(q: torch.Tensor, robot) -> list[str]:
    """Linear (prismatic) joint columns that look like metres: every long joint stays within its travel / 1000 mm.

    q: (R, n) controller commands as read (SI). -> ['q1', ...] or []. A 4 m rail written in metres
    (0..3.9) is a valid-looking file that drives the carriage 3.9 mm."""
    jm = robot.joint_map
    if q.shape[0] < MIN_ROWS:
        return []
    mm = units.joints_from_si(q.detach().cpu(), jm.prismatic.cpu()).numpy()
    span = units.joints_from_si(jm.limits.cpu().T, jm.prismatic.cpu()).T.numpy()  # (n, 2) deg / mm
    out = []
    for j in range(jm.n):
        if not bool(jm.prismatic[j]) or span[j, 1] - span[j, 0] < WIDE_TRAVEL_MM:
            continue
        a = np.abs(mm[:, j])
        reach = 1.05e-3 * float(np.abs(span[j]).max())
        if np.isfinite(a).all() and 0.05 * reach < a.max() <= reach:  # all zeros (home) is no evidence
            out.append(f"q{j + 1}")
    return out


def metre_message(path, q: torch.Tensor, robot, cols: list[str]) -> str:
    """One line naming the file and the linear joint columns that look like metres."""
    jm = robot.joint_map
    span = units.joints_from_si(jm.limits.cpu().T, jm.prismatic.cpu()).T.numpy()
    j = int(cols[0][1:]) - 1
    top = float(units.joints_from_si(q.detach().cpu(), jm.prismatic.cpu())[:, j].abs().max())
    return (f"{path}: linear joint columns {', '.join(cols)} all stay within {top:.4g} over {q.shape[0]} rows, while "
            f"'{robot.name}' moves e.g. {cols[0]} over [{span[j, 0]:.6g}, {span[j, 1]:.6g}] mm: they look like "
            f"metres; the contract is mm (mm = m * 1000); convert them, or pass {OVERRIDE} (fit, fleet, sweep: "
            "data.units_checked=true) if they really are mm")


def radian_message(path, q: torch.Tensor, robot, cols: list[str]) -> str:
    """One line naming the file and columns: what was seen against the robot's range."""
    jm = robot.joint_map
    span = units.joints_from_si(jm.limits.cpu().T, jm.prismatic.cpu()).T.numpy()
    j = int(cols[0][1:]) - 1
    return (f"{path}: columns {', '.join(cols)} all stay within +-{RADIAN_BOUND:.2f} over {q.shape[0]} rows, while "
            f"'{robot.name}' moves e.g. {cols[0]} over [{span[j, 0]:.6g}, {span[j, 1]:.6g}] deg: the joints look like "
            f"radians; the contract is degrees (deg = rad * 180 / pi)")


def _nominal_points(robot, q: torch.Tensor, tool: torch.Tensor, tools_m: torch.Tensor | None) -> torch.Tensor:
    F = robot.chain.fk(robot.joint_map.to_joint(q.detach().cpu()))
    if tools_m is None:
        return F[:, :3, 3]
    t = tools_m.detach().cpu().to(F.dtype)[tool.cpu().clamp(0, tools_m.shape[0] - 1)]
    return F[:, :3, 3] + (F[:, :3, :3] @ t[:, :, None])[:, :, 0]


def _consecutive_distances(data, robot, tools_m: torch.Tensor | None, q: torch.Tensor, by_tool: bool = False):
    """Measured and nominal (at commands q (R, n)) distances between consecutive rows of one tool, every tool's
    pairs concatenated: -> dm, dn (P,) m; by_tool: {tool: (dm, dn)} instead. Frame-free: the measurement frame
    moves neither."""
    xyz = data.xyz.detach().cpu()
    p = _nominal_points(robot, q, data.tool, tools_m)
    pairs = {}
    for t in torch.unique(data.tool.cpu()).tolist():
        idx = (data.tool.cpu() == t).nonzero()[:, 0]
        if idx.numel() >= 2:
            pairs[int(t)] = ((xyz[idx[1:]] - xyz[idx[:-1]]).norm(dim=1), (p[idx[1:]] - p[idx[:-1]]).norm(dim=1))
    if by_tool:
        return pairs
    empty = torch.zeros(0, dtype=torch.float64)
    return (torch.cat([m for m, _ in pairs.values()]), torch.cat([n for _, n in pairs.values()])) if pairs else (empty, empty)


def _median_ratio(dm: torch.Tensor, dn: torch.Tensor) -> float | None:
    ok = torch.isfinite(dm) & (dn > 1e-3)  # poses a millimetre apart say nothing about the scale
    r = dm[ok] / dn[ok]
    return None if r.numel() < MIN_ROWS // 2 else float(r.median())


def point_scale(data, robot, tools_m: torch.Tensor | None = None) -> float | None:
    """Median measured / nominal distance between consecutive rows of one tool (frame-free); None: too few rows.

    data: Measurements (SI); tools_m: (T, 3) tool vectors, or None (the flange: tool
    vectors are small next to the distances between poses, so the ratio stays near 1).
    """
    return _scales(data, robot, tools_m)[0]


def tool_scales(data, robot, tools_m: torch.Tensor | None = None) -> dict[int, float]:
    """:func:`point_scale` of each tool's rows alone -> {tool: scale}, tools with too few rows left out: one tool's
    points in metres hide behind the others' in the median of all."""
    return _scales(data, robot, tools_m)[1]


def _scales(data, robot, tools_m) -> tuple[float | None, dict[int, float]]:
    """(:func:`point_scale`, :func:`tool_scales`) from one evaluation of the nominal points."""
    if len(data) < MIN_ROWS:
        return None, {}
    pairs = _consecutive_distances(data, robot, tools_m, data.q, by_tool=True)
    if not pairs:
        return None, {}
    every = _median_ratio(torch.cat([m for m, _ in pairs.values()]), torch.cat([n for _, n in pairs.values()]))
    return every, {t: s for t, (dm, dn) in pairs.items() if (s := _median_ratio(dm, dn)) is not None}


def path_scale(xyz: torch.Tensor, q: torch.Tensor, robot) -> float | None:
    """Median measured / nominal-flange distance between consecutive rows of one point's path (a reflector's
    file): xyz (R, 3) m, NaN rows skipped; q (R, n) SI commands. None: too few rows."""
    ok = torch.isfinite(xyz).all(1)
    xyz, q = xyz[ok], q[ok]
    if xyz.shape[0] < MIN_ROWS:
        return None
    p = robot.chain.fk(robot.joint_map.to_joint(q.detach().cpu()))[:, :3, 3]
    return _median_ratio((xyz[1:] - xyz[:-1]).norm(dim=1), (p[1:] - p[:-1]).norm(dim=1))


RADIAN_FIT = (0.8, 1.25)
"""Measured / nominal distance ratios that, with the joints read as radians, say the points fit them."""


def radian_scales(data, robot, tools_m: torch.Tensor | None = None) -> tuple[float, float] | None:
    """(point scale with the joints as read, as degrees; with the revolute joints read as radians), or None.

    The second is :func:`point_scale` of the same rows with every revolute command multiplied by 180 / pi: radians
    read as degrees move the nominal robot ~57x less than the tracker saw, radians read as radians match it.
    """
    s_deg = point_scale(data, robot, tools_m)
    if s_deg is None:
        return None
    revolute = ~robot.joint_map.prismatic.cpu()
    q = data.q.detach().cpu().clone()
    q[:, revolute] = q[:, revolute] * (180.0 / math.pi)
    s_rad = point_scale(_with_q(data, q), robot, tools_m)
    return None if s_rad is None else (s_deg, s_rad)


def _with_q(data, q: torch.Tensor):
    """``data`` with other commands (q: (R, n) SI), every other field the same."""
    import dataclasses

    return dataclasses.replace(data, q=q.to(data.q))


def distance_miss(data, robot, tools_m: torch.Tensor | None, q: torch.Tensor) -> float | None:
    """Median |measured - nominal| distance between consecutive rows of one tool (m) at commands q (R, n): how far
    the point cloud's shape is from the nominal one's, whatever the (unknown) measurement frame. None: too few rows."""
    dm, dn = _consecutive_distances(data, robot, tools_m, q)
    d = (dm - dn).abs()
    return None if d.numel() < MIN_ROWS // 2 else float(d.median())


RADIAN_MISS = (0.2, 0.005)
"""Radians are also refused where, read as radians, the nominal robot's distances between rows miss the measured
ones (:func:`distance_miss`) by less than this fraction of their miss read as degrees, and that miss exceeds this
many metres: on a machine tool the linear axes dominate the distances' ratio, so only their differences tell
rotary axes typed in radians (a B axis of 1.5 read as 1.5 deg swings a 100 mm tool 2.6 mm instead of 100)."""


def check_radians(data, robot, tools_m: torch.Tensor | None = None, path=None) -> tuple[float, float] | None:
    """Raise :class:`UnitsError` when the points fit the joints read as radians and not as degrees.

    Called where :func:`radian_columns` has found joints that look like radians: the points decide.
    -> :func:`radian_scales` (as degrees, as radians) when they do not refuse, None where they cannot tell (too
    few rows, no points); :func:`degrees_confirmed` says whether they confirm degrees.
    """
    scales = radian_scales(data, robot, tools_m) if bool(torch.isfinite(data.xyz).all()) else None
    if scales is None:
        return None
    s_deg, s_rad = scales
    fix = (f"Convert the revolute columns (deg = rad * 180 / pi), or pass {OVERRIDE} (fit, fleet, sweep: "
           f"data.units_checked=true) if they really are degrees")
    if RADIAN_FIT[0] <= s_rad <= RADIAN_FIT[1] and not RADIAN_FIT[0] <= s_deg <= RADIAN_FIT[1]:
        raise UnitsError(
            f"{path or data.source}: columns q1..q{robot.joint_map.n}: the joints are radians: read as radians, the "
            f"nominal robot ('{robot.name}') moves its points as far as the tracker saw (distance ratio {s_rad:.3g}); "
            f"read as degrees, as the contract says, {s_deg:.3g}x less. " + fix)
    revolute = ~robot.joint_map.prismatic.cpu()
    if bool(robot.joint_map.prismatic.any()) and bool(revolute.any()):  # a machine: the distances say little
        q = data.q.detach().cpu()
        as_rad = q.clone()
        as_rad[:, revolute] = q[:, revolute] * (180.0 / math.pi)
        miss_deg, miss_rad = distance_miss(data, robot, tools_m, q), distance_miss(data, robot, tools_m, as_rad)
        if miss_deg is not None and miss_deg > RADIAN_MISS[1] and miss_rad < RADIAN_MISS[0] * miss_deg:
            raise UnitsError(
                f"{path or data.source}: the rotary columns look like radians: read as radians the nominal machine "
                f"('{robot.name}') has the measured distances between rows to {miss_rad * 1e3:.3g} mm (median), read "
                f"as degrees, as the contract says, to {miss_deg * 1e3:.3g} mm. " + fix)
    return scales


def degrees_confirmed(scales: tuple[float, float] | None) -> bool:
    """Whether :func:`check_radians`' scales say the points fit the joints read as degrees."""
    return scales is not None and RADIAN_FIT[0] <= scales[0] <= RADIAN_FIT[1]


def check_units(data, robot, tools_m: torch.Tensor | None = None, path=None) -> tuple[list[str], tuple | None]:
    """The unit slips of a file of measured rows, checked the one way ``fit``, ``fleet``, ``sweep`` and ``update``
    do: joints that look like radians go to :func:`check_radians` (the points decide; the nominal points of
    radians read as degrees say nothing about the points' unit), the rest to :func:`check_point_scale`.
    Raises :class:`UnitsError` on a slip. -> (the columns that look like radians, :func:`check_radians`' scales),
    for the caller's note."""
    if metres := metre_columns(data.q, robot):
        raise UnitsError(metre_message(path or data.source, data.q, robot, metres))
    rad = radian_columns(data.q, robot)
    if rad:
        return rad, check_radians(data, robot, tools_m, path)
    check_point_scale(data, robot, tools_m, path)
    return [], None


def units_note(data, robot, rad: list[str], scales: tuple | None, override: str = OVERRIDE) -> str | None:
    """What :func:`check_units` let through but the user should hear: joints that look like radians read as
    degrees, because the points fit them as degrees (near-home poses) or cannot tell (then ``override`` is how
    the user says they really are degrees). None when nothing looked like radians."""
    if not rad:
        return None
    return radian_message(data.source, data.q, robot, rad) + (
        f"; but the measured points fit them read as degrees (distance ratio {scales[0]:.3g}): read as degrees "
        "(near-home poses?)" if degrees_confirmed(scales) else f"; set {override} if they really are degrees")


def check_point_scale(data, robot, tools_m: torch.Tensor | None = None, path=None) -> None:
    """Raise :class:`UnitsError` when the measured x, y, z spread ~1000x less (metres) or more than the nominal model's."""
    s, scales = _scales(data, robot, tools_m)
    if s is not None and SCALE_BOUNDS[0] <= s <= SCALE_BOUNDS[1]:
        for t, st in scales.items():  # one tool's points in metres (a merged export) hide in the median of all
            if not SCALE_BOUNDS[0] <= st <= SCALE_BOUNDS[1] and len(scales) > 1:
                others = ", ".join(f"tool {u}: {v:.3g}" for u, v in scales.items() if u != t)
                raise UnitsError(
                    f"{path or data.source}: columns x, y, z of the rows of tool {t}: the distances between its "
                    f"points are {st:.3g} times the nominal robot's ('{robot.name}'), the other tools' are {others}: "
                    f"tool {t}'s look like {scale_guess(st)}, and the contract is mm; convert them, or pass "
                    f"{OVERRIDE} (fit, fleet, sweep: data.units_checked=true) if they really are mm")
        return
    if s is None:
        return
    raise UnitsError(
        f"{path or data.source}: columns x, y, z: the distances between the rows' points are {s:.3g} times the "
        f"nominal robot's ('{robot.name}'), i.e. off by a factor ~{(1 / s if s < 1 else s):.3g}: they look like "
        f"{scale_guess(s)}, and the contract is mm; convert them, or pass {OVERRIDE} (fit, fleet, sweep: "
        f"data.units_checked=true) if they really are mm")


def scale_hint(data, robot, tools_m: torch.Tensor | None = None) -> str:
    """'' or a clause naming a suspect point scale (:data:`SUSPECT_SCALE`) and the unit it suggests, for a
    warning about a nominal residual beyond any calibration error."""
    s = point_scale(data, robot, tools_m)
    if s is None or SUSPECT_SCALE[0] <= s <= SUSPECT_SCALE[1]:
        return ""
    return (f"; the distances between the measured points are {s:.3g} times the nominal robot's: they look like "
            f"{scale_guess(s)} (the contract is mm)")


UNIT_RATIOS = {"metres": 1e-3, "centimetres": 0.1, "inches": 1 / 25.4, "micrometres": 1e3}
"""The measured / nominal distance ratio of points written in each unit instead of mm."""


def scale_guess(s: float) -> str:
    """The unit a measured / nominal distance ratio ``s`` suggests for points that should be mm: the nearest of
    :data:`UNIT_RATIOS` within a factor 4, else 'another unit'."""
    if not (s > 0 and math.isfinite(s)):
        return "another unit"
    name, ratio = min(UNIT_RATIOS.items(), key=lambda kv: abs(math.log(s / kv[1])))
    return name if abs(math.log(s / ratio)) < math.log(4.0) else "another unit"


__all__ = ["OVERRIDE", "UnitsError", "check_point_scale", "check_radians", "check_units", "degrees_confirmed",
           "metre_columns", "metre_message", "path_scale", "scale_hint", "point_scale", "radian_columns", "radian_message", "radian_scales", "scale_guess", "tool_scales",
           "units_note"]
