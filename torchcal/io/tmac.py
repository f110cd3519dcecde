"""Importer for UR10 + Leica T-Mac exports (the ipa-robot-accuracy data set, Landgraf et al., CASE 2021).

The export is one pose per row, ``;``-separated with decimal commas (CRLF or
LF line endings; NUL bytes ending a line are stripped):

- ``shoulder_pan_joint`` ... ``wrist_3_joint``: the six UR joint angles, rad;
- ``measurement_x/y/z``: T-Mac frame origin in the tracker frame, mm;
- ``measurement_rx/ry/rz``: T-Mac frame orientation in the tracker frame,
  Euler angles in degrees, **intrinsic XYZ** (scipy ``from_euler('XYZ')``,
  R = Rx(rx) Ry(ry) Rz(rz)), :data:`TMAC_EULER`. Checked on the data: the
  relative rotations between consecutive poses match the nominal UR10
  kinematics to 0.04° median with 'XYZ' (and its equal 'zyx'), 0.5° median and
  17° at worst with 'xyz'; after a hand-eye fit the implied flange-to-probe
  rotation is constant to 0.07° with 'XYZ' (see experiments/ur10_tmac);
- optional ``measurement_std_x/y/z`` (mm) and ``_rx/ry/rz`` (deg): per-axis
  scatter of the measurement, read as per-row standard deviations
  (``extra['pose_std']``, m and rad); ``measurement_temperature`` (°C) goes to
  ``extra['temperature']``. Other columns (Timestamp, Goal ...) are ignored.

:func:`read_tmac` returns :class:`~torchcal.core.measurements.Measurements` in SI
in the shape of the 6-DOF contract (``xyz``, ``extra['rotation']``);
:func:`convert_tmac` writes the sensor CSV contract of
:mod:`torchcal.io.sensor_csv` (``pose, q1..q6, x, y, z, r11..r33, sx..srz``,
mm / deg). Every unreadable cell is reported (file, 1-based data row, line,
column) in one :class:`~torchcal.io.csv.DataError`; no row is dropped here:
known bad rows are excluded by the caller, by their row numbers.
"""

from __future__ import annotations

import math
from pathlib import Path

import torch

from ..core import units
from ..core.measurements import Measurements
from .csv import DataError, Problem

TMAC_JOINTS = ("shoulder_pan_joint", "shoulder_lift_joint", "elbow_joint", "wrist_1_joint", "wrist_2_joint",
               "wrist_3_joint")
"""Joint columns of the export, rad, in chain order."""

TMAC_XYZ = ("measurement_x", "measurement_y", "measurement_z")
TMAC_ANGLES = ("measurement_rx", "measurement_ry", "measurement_rz")
TMAC_STD = ("measurement_std_x", "measurement_std_y", "measurement_std_z",
            "measurement_std_rx", "measurement_std_ry", "measurement_std_rz")
TMAC_TEMPERATURE = "measurement_temperature"

TMAC_EULER = "XYZ"
"""Euler convention of measurement_rx/ry/rz: intrinsic x-y-z (scipy naming, upper case = intrinsic)."""


def _lines(path: Path) -> list[str]:
    try:
        raw = path.read_bytes()
    except OSError as exc:
        raise DataError(path, [Problem(None, None, f"cannot read the file: {exc}")]) from None
    try:
        text = raw.decode("utf-8-sig")
    except UnicodeDecodeError as exc:
        raise DataError(path, [Problem(None, None, f"not UTF-8 text: {exc}")]) from None
    # CRLF or LF; the D series ends each line with a NUL byte
    return [ln.replace("\x00", "").rstrip("\r") for ln in text.split("\n")]


def _number(cell: str) -> float:
    s = cell.strip()
    if s.count(",") > 1 or ("," in s and "." in s):
        raise ValueError(s)
    return float(s.replace(",", "."))


def read_tmac_table(path) -> tuple[list[str], dict[str, torch.Tensor], torch.Tensor]:
    """Parse an export: header, {column: (R,) float64 in file units}, (R,) 1-based data row numbers.

    Only the columns this module uses are parsed (joints, measurement_*); all
    their bad cells are reported together. Empty trailing lines are skipped,
    an empty line inside the data is a problem.
    """
    path = Path(path)
    lines = _lines(path)
    while lines and not lines[-1].strip():
        lines.pop()
    if not lines:
        raise DataError(path, [Problem(None, None, "empty file")])
    header = [h.strip() for h in lines[0].split(";")]
    problems: list[Problem] = []
    missing = [c for c in TMAC_JOINTS + TMAC_XYZ + TMAC_ANGLES if c not in header]
    if missing:
        raise DataError(path, [Problem(None, c, "column missing (is this a ';'-separated T-Mac export?)") for c in missing])
    wanted = [c for c in TMAC_JOINTS + TMAC_XYZ + TMAC_ANGLES + TMAC_STD + (TMAC_TEMPERATURE,) if c in header]
    twice = [c for c in wanted if header.count(c) > 1]
    if twice:  # header.index would take the first silently (x = the first column's values on every row)
        raise DataError(path, [Problem(None, c, f"appears {header.count(c)} times in the header (fields "
                                                f"{', '.join(str(i + 1) for i, h in enumerate(header) if h == c)})")
                               for c in twice])
    idx = {c: header.index(c) for c in wanted}
    cols: dict[str, list[float]] = {c: [] for c in wanted}
    rows = []
    for r, line in enumerate(lines[1:], start=1):
        cells = line.split(";")
        if len(cells) != len(header):
            problems.append(Problem(r, None, f"{len(cells)} fields, the header has {len(header)}"))
            continue
        rows.append(r)
        for c in wanted:
            cell = cells[idx[c]]
            try:
                val = _number(cell)
            except ValueError:
                problems.append(Problem(r, c, f"not a number: {cell!r}"))
                val = math.nan
            else:
                if not math.isfinite(val):
                    problems.append(Problem(r, c, f"not a finite number: {cell!r}"))
            cols[c].append(val)
    if not rows and not problems:
        problems.append(Problem(None, None, "no data rows"))
    if problems:
        raise DataError(path, problems)
    return header, {c: torch.tensor(v, dtype=torch.float64) for c, v in cols.items()}, torch.tensor(rows)


def read_tmac(path, robot=None, convention: str = TMAC_EULER) -> Measurements:
    """A T-Mac export -> Measurements (SI): q (R, 6) rad, xyz (R, 3) m, extra['rotation'] (R, 3, 3),
    extra['pose_std'] (R, 6) m/rad where the file has the std columns, extra['temperature'] (R,) °C.

    robot: optional; when given, its joint count must be 6 and every joint
    inside its controller limits (else a DataError naming row and column).
    pose ids are the 1-based data rows.

    Example:
        >>> import tempfile, os
        >>> head = ";".join(TMAC_JOINTS + TMAC_XYZ + TMAC_ANGLES)
        >>> row = ";".join(["0,1"] * 6 + ["1000,5", "-2,25", "3"] + ["90", "0", "-90"])
        >>> f = os.path.join(tempfile.mkdtemp(), "m.csv")
        >>> _ = open(f, "w").write(head + "\\r\\n" + row + "\\r\\n")
        >>> m = read_tmac(f)
        >>> [round(v, 6) for v in m.xyz[0].tolist()], m.extra["rotation"].shape
        ([1.0005, -0.00225, 0.003], torch.Size([1, 3, 3]))
    """
    from ..measure.pose import rotation_from_euler

    path = Path(path)
    _, cols, rows = read_tmac_table(path)
    q = torch.stack([cols[c] for c in TMAC_JOINTS], 1)
    if robot is not None:
        if robot.n != q.shape[1]:
            raise DataError(path, [Problem(None, None, f"robot '{robot.name}' has {robot.n} joints, the file 6")])
        lim = robot.joint_map.limits
        out = (q < lim[:, 0] - 1e-9) | (q > lim[:, 1] + 1e-9)
        if out.any():
            probs = [Problem(int(rows[i]), TMAC_JOINTS[j], f"{float(q[i, j]):.6g} rad is outside the limits "
                             f"[{float(lim[j, 0]):.6g}, {float(lim[j, 1]):.6g}] rad of '{robot.name}'")
                     for i, j in out.nonzero().tolist()]
            raise DataError(path, probs)
    xyz = units.mm_to_m(torch.stack([cols[c] for c in TMAC_XYZ], 1))
    R = rotation_from_euler(torch.stack([cols[c] for c in TMAC_ANGLES], 1), convention)
    extra = {"rotation": R}
    if all(c in cols for c in TMAC_STD):
        std = torch.stack([cols[c] for c in TMAC_STD], 1)
        bad = (std <= 0).nonzero().tolist()
        if bad:
            raise DataError(path, [Problem(int(rows[i]), TMAC_STD[j], f"standard deviation {float(std[i, j]):.6g} "
                                           f"is not positive") for i, j in bad])
        extra["pose_std"] = torch.cat([units.mm_to_m(std[:, :3]), units.deg_to_rad(std[:, 3:])], 1)
    if TMAC_TEMPERATURE in cols:
        extra["temperature"] = cols[TMAC_TEMPERATURE]
    R_ = q.shape[0]
    return Measurements(q, torch.zeros(R_, dtype=torch.long), xyz, torch.zeros_like(q), rows.clone(), rows.clone(),
                        False, str(path), extra)


def read_trafo(path) -> torch.Tensor:
    """A ``Trafo_TM_F_*.txt`` file (4x4, whitespace-separated, translation in mm) -> (4, 4) transform in m."""
    path = Path(path)
    tokens = path.read_text().replace("\x00", "").split()
    try:
        vals = [float(t) for t in tokens]
    except ValueError as exc:
        raise DataError(path, [Problem(None, None, f"not a 4x4 matrix of numbers: {exc}")]) from None
    if len(vals) != 16:
        raise DataError(path, [Problem(None, None, f"expected 16 numbers (4x4), found {len(vals)}")])
    T = torch.tensor(vals, dtype=torch.float64).reshape(4, 4)
    T[:3, 3] = units.mm_to_m(T[:3, 3])
    return T


def repeated_rows(data: Measurements) -> list[tuple[int, int]]:
    """(row, earlier row) for every data row whose joints and measurement (position, rotation, scatter) equal an
    earlier row's bit for bit: a logger that wrote one sample twice, not a second measurement (two measurements
    of one pose differ in the tracker's last digits). Rows are the 1-based data rows (``data.rows``)."""
    import numpy as np

    parts = [data.q, data.xyz, data.extra["rotation"].reshape(len(data), 9)]
    if "pose_std" in data.extra:
        parts.append(data.extra["pose_std"])
    key = torch.cat(parts, 1).numpy()
    _, first, inverse = np.unique(key, axis=0, return_index=True, return_inverse=True)
    earliest = first[inverse.reshape(-1)]
    rows = data.rows.tolist()
    return [(rows[i], rows[int(j)]) for i, j in enumerate(earliest) if j != i]


STALE_MOTION = 1e-4
"""rad (m for a prismatic joint): the joint motion between two rows beyond which an unchanged measurement is a
stale reading (Series B's two move up to 2.4 rad; Series A's smallest real move between rows is 3.4e-4 rad)."""


def stale_rows(data: Measurements) -> list[tuple[int, int]]:
    """(row, previous row) for every data row whose measurement (position and rotation) equals the previous row's
    bit for bit while its joints differ: the tracker did not update (a stale reading), so the row puts the robot
    where it was not (the UR10's Series B, data rows 533 and 1064, SOURCE.md's known defect). A sample the logger
    wrote twice, joints included, is :func:`repeated_rows`' instead. Rows are the 1-based data rows."""
    if len(data) < 2:
        return []
    m = torch.cat([data.xyz, data.extra["rotation"].reshape(len(data), 9)], 1)
    # moved: more than an encoder's last digits (a robot standing still between two readings is no stale reading)
    same = (m[1:] == m[:-1]).all(1) & ((data.q[1:] - data.q[:-1]).abs().amax(1) > STALE_MOTION)
    rows = data.rows.tolist()
    return [(rows[i + 1], rows[i]) for i in same.nonzero()[:, 0].tolist()]


def _say(src, pairs: list[tuple[int, int]], what: str, why: str, warnings: list | None) -> None:
    """Rows ``pairs`` ((row, the row it repeats)) said, kept, with the --exclude that drops them: appended to
    ``warnings`` where a list is given, else a Python warning at the caller's caller."""
    if not pairs:
        return
    shown = ", ".join(f"{r} (= row {f})" for r, f in pairs[:10]) + (" ..." if len(pairs) > 10 else "")
    said = (f"{src}: {len(pairs)} data row{'s repeat' if len(pairs) > 1 else ' repeats'} {what}: {shown}; {why}. Kept; "
            "leave them out with " + " ".join(f"--exclude {r}" for r, _ in pairs[:10]))
    if warnings is None:
        import warnings as _warnings

        _warnings.warn(said, stacklevel=3)
    else:
        warnings.append(said)


def convert_tmac(src, dst, robot, convention: str = TMAC_EULER, exclude=(), warnings: list | None = None) -> Path:
    """Write a T-Mac export as the sensor CSV contract (:func:`torchcal.io.sensor_csv.write_pose_measurements`).

    exclude: 1-based data rows to leave out (e.g. the known bad rows of a series); each must exist,
    else a DataError naming it. The pose ids stay the source rows, so what was left out stays visible.
    Rows repeated bit for bit (:func:`repeated_rows`) and stale readings (:func:`stale_rows`) are kept and said:
    appended to ``warnings`` where a list is given, else a Python warning.
    """
    from .sensor_csv import rotation_fit, transposed_message, write_pose_measurements

    data = read_tmac(src, robot, convention)
    exclude = sorted({int(r) for r in exclude})
    if exclude:
        known = set(data.rows.tolist())
        missing = [r for r in exclude if r not in known]
        if missing:
            raise DataError(src, [Problem(None, None, f"rows {missing} to exclude are not data rows of the file "
                                                      f"(1..{len(data)})")])
        data = data.subset(~torch.isin(data.rows, torch.tensor(exclude)))
    _say(src, repeated_rows(data), "an earlier row bit for bit (joints and measurement)",
         "a logger's repeat counts one measurement twice in the fit", warnings)
    _say(src, stale_rows(data), "the previous row's measurement bit for bit while the joints moved",
         "a stale reading (the tracker did not update) puts the robot where it was not", warnings)
    msg = transposed_message(rotation_fit(data.q, data.extra["rotation"], robot), "measurement_rx/ry/rz")
    if msg:
        raise DataError(src, [Problem(None, "measurement_rx/ry/rz", msg + f"; is the Euler convention '{convention}' "
                                                                         f"the export's (--convention)?")])
    return write_pose_measurements(dst, data, robot)


__all__ = ["TMAC_EULER", "TMAC_JOINTS", "convert_tmac", "read_tmac", "read_tmac_table", "read_trafo", "repeated_rows",
           "STALE_MOTION", "stale_rows"]
