"""Laser-tracker exports -> the measurement CSV contract (:mod:`torchcal.io.csv`).

A tracker session is a set of plain text files with one row per pose, in the
order the robot visited the poses:

- the commanded joints: N columns, degrees (mm for prismatic joints);
- one file per target reflector on the tool: x y z in mm, tracker frame;
- optionally one file per reflector fixed on the robot base, re-measured at
  every pose: x y z in mm, used to watch (and optionally undo) drift of the
  tracker against the robot.

Fields are separated by whitespace and/or commas; ``#`` starts a comment line;
blank lines at the end are ignored, blank lines between rows are an error
(rows are never skipped). A row ``0 0 0`` is a failed reading.

:func:`import_tracker` applies the rules below and returns a
:class:`TrackerImport` holding the contract table, a per-reflector summary and
a report; it never prints. Bad input raises :class:`~torchcal.io.csv.DataError`
naming the file, the row (and line) and the column.

1. Approach directions ``dir1..dirN`` come from the commanded pose order
   (:func:`torchcal.sim.approach_directions`) over *all* poses, before any
   row is dropped.
2. A failed target reading drops that reflector's row at that pose only.
3. Base reflectors: each one's median position over the session is its
   reference. A single reading farther than ``outlier_mm`` from its median
   whose distances to the other base reflectors also disagree with the median
   distances (a rigid drift keeps those distances) is a wrong-target reading:
   reported and left out of the drift estimate. Per pose, a rigid
   registration (Kabsch) of the remaining base readings onto their medians
   gives the drift correction (translation only with fewer than three
   readings); the drift of a pose is the largest displacement this correction
   applies to the pose's base readings and target points.
4. Drift above ``drift_threshold_mm`` is an error naming the pose and the base
   files, unless ``correct_drift``: then every target point is mapped through
   its pose's correction into the base reflectors' median frame.
"""

from __future__ import annotations

import logging
import re
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import pandas as pd
import torch

from ..core import units
from .csv import LIMIT_TOL, XYZ, DataError, Problem, direction_columns, joint_columns, missing_file_message

OUTLIER_MM = 1.0
"""Default distance (mm) from its median beyond which a single base reading is a wrong-target outlier."""

DRIFT_THRESHOLD_MM = 0.1
"""Default largest tolerated per-pose drift (mm) without ``--correct-drift``."""

_SPLIT = re.compile(r"[,\s]+")


@dataclass
class RowFile:
    """A headerless numeric text file: values (R, C) float64, the file line of each row, its path."""

    path: str
    values: np.ndarray
    lines: list[int]
    commented: list[tuple[int, int]] = field(default_factory=list)
    """Lines commented out between data rows: (data rows before it, file line). Rows are paired across files by
    position, so a reading left out of one file only shifts every later pose onto the next one's row."""

    @property
    def rows(self) -> int:
        return self.values.shape[0]


def read_rows(path, columns: list[str]) -> RowFile:
    """Read a whitespace/comma separated file with ``len(columns)`` numbers per row.

    columns: names used in messages (e.g. ['x', 'y', 'z']). Raises
    :class:`DataError` listing every bad row / column (1-based row, file line).
    """
    path = Path(path)
    if not path.is_file():
        raise DataError(path, [Problem(None, None, missing_file_message(path))])
    try:
        text = path.read_text(encoding="utf-8-sig")
    except UnicodeDecodeError as exc:
        raise DataError(path, [Problem(None, None, f"not a UTF-8 text file ({exc.reason} at byte {exc.start})")]) from None
    records: list[tuple[int, str]] = []
    commented: list[tuple[int, int]] = []
    for ln, raw in enumerate(text.splitlines(), start=1):
        s = raw.strip()
        if s.startswith("#"):
            if any(r for _, r in records):  # after the first data row: a reading left out, not a header comment
                commented.append((len(records), ln))
            continue
        records.append((ln, s))
    while records and not records[-1][1]:
        records.pop()
    problems: list[Problem] = []
    C = len(columns)
    values = np.full((len(records), C), np.nan)
    lines = []
    # a European spreadsheet export: ';' between fields, ',' as the decimal mark (as read_table reads it)
    european = any(";" in s for _, s in records)
    if european:
        logging.getLogger("torchcal").warning("%s: fields separated by ';': read with ',' as the decimal mark", path)
    for r, (ln, s) in enumerate(records):
        row = r + 1
        lines.append(ln)
        if not s:
            problems.append(Problem(row, None, "blank line between data rows; remove it (rows are never skipped)", ln))
            continue
        fields = ([f.strip().replace(",", ".") for f in s.strip("; \t").split(";")] if european else
                  [f for f in _SPLIT.split(s.strip(", \t")) if f != ""])
        if len(fields) != C:
            problems.append(Problem(row, None, f"has {len(fields)} fields, expected {C} ({', '.join(columns)})", ln))
            continue
        for c, f in enumerate(fields):
            try:
                v = float(f)
            except ValueError:
                v = float("nan")
            if not np.isfinite(v):
                problems.append(Problem(row, f"{c + 1} ({columns[c]})", f"{f!r} is not a finite number", ln))
            values[r, c] = v
    if not records:
        problems.append(Problem(None, None, "no data rows"))
    if problems:
        raise DataError(path, problems)
    # a comment after the last data row says nothing about pairing
    return RowFile(str(path), values, lines, [(k, ln) for k, ln in commented if k < len(records)])


def check_same_comments(files: list[RowFile]) -> None:
    """Refuse files whose readings were commented out at different places: their rows are paired by position, so
    pose k's joints met pose k + 1's point from there on (a 249-row import, rc 0, 5 poses mispaired)."""
    where = [{k for k, _ in f.commented} for f in files]
    if all(w == where[0] for w in where):
        return
    problems = [Problem(None, None, f"{f.path} line {ln} is commented out after data row {k}, where "
                                    f"{', '.join(o.path for o, wo in zip(files, where) if k not in wo)} leave(s) no reading out")
                for f in files for k, ln in f.commented if any(k not in wo for wo in where)]
    problems.append(Problem(None, None, "rows are paired across the joints and reflector files by position: comment "
                                        "out the same reading in every file (a missed reading can stay as 0 0 0)"))
    raise DataError(files[0].path, problems)


@dataclass
class ReflectorSummary:
    """What happened to one reflector file. kind: 'target' (tool given) or 'base'."""

    name: str
    kind: str
    path: str
    rows: int
    failed: list[int] = field(default_factory=list)
    """1-based rows read as 0 0 0 (dropped for a target, ignored for a base reflector)."""
    outliers: list[tuple[int, float]] = field(default_factory=list)
    """Base only: (row, distance from the median in mm) of wrong-target readings left out of the drift estimate."""
    tool: int | None = None

    @property
    def kept(self) -> int:
        return self.rows - len(self.failed) - len(self.outliers)


@dataclass
class TrackerImport:
    """Result of :func:`import_tracker`.

    table: the contract table (pose, tool, q1..qN, dir1..dirN, x, y, z; file
    units, pose = 1-based row in the input files), one row per kept target
    reading, tool-major. reflectors: per-file summary. drift_mm: (P,) per-pose
    drift (NaN where no base reading is usable; empty without base files).
    corrections: (P, 4, 4) per-pose rigid correction (mm) onto the base
    medians, or None. report: human-readable lines (what was dropped, flagged
    and corrected), for the CLI to print.
    """

    table: pd.DataFrame
    reflectors: list[ReflectorSummary]
    poses: int
    drift_mm: np.ndarray
    corrections: np.ndarray | None
    corrected: bool
    report: list[str]

    @property
    def dropped(self) -> dict[str, list[int]]:
        """Target file -> 1-based rows dropped (failed readings)."""
        return {s.path: list(s.failed) for s in self.reflectors if s.kind == "target"}

    def summary_table(self):
        """A rich Table: per reflector, rows, kept, failed and outliers (with the first few row numbers)."""
        from rich.table import Table

        def rows_text(rows: list[int], limit: int = 8) -> str:
            s = ", ".join(str(r) for r in rows[:limit])
            return s + (f", ... (+{len(rows) - limit})" if len(rows) > limit else "")

        t = Table(title=f"Tracker import: {self.poses} poses",
                  caption="failed = 0 0 0 readings; outliers = base readings on a wrong target (not used for drift)")
        for name, just in (("Reflector", "left"), ("Use", "left"), ("File", "left"), ("Rows", "right"),
                           ("Kept", "right"), ("Failed", "right"), ("Outliers", "right"), ("Rows dropped / flagged", "left")):
            t.add_column(name, justify=just)
        for s in self.reflectors:
            use = f"tool {s.tool}" if s.kind == "target" else "base (drift)"
            flagged = rows_text(sorted(s.failed + [r for r, _ in s.outliers]))
            t.add_row(s.name, use, Path(s.path).name, str(s.rows), str(s.kept), str(len(s.failed)),
                      str(len(s.outliers)) if s.kind == "base" else "-", flagged or "-")
        return t


# ---------------------------------------------------------------------------- rigid registration
def rigid_to_reference(x: np.ndarray, ref: np.ndarray, w: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Per-pose rigid transform of the weighted points onto their references.

    x: (P, K, 3) readings, ref: (K, 3) reference positions, w: (P, K) bool.
    -> R (P, 3, 3), b (P, 3) with R x + b ~ ref (Kabsch with >= 3 points,
    translation only with 1-2, identity with none), count (P,) points used.
    """
    import torch

    from ..identify.alignment import kabsch

    wf = w.astype(np.float64)[..., None]
    cnt = w.sum(1)
    safe = np.maximum(cnt, 1)[:, None]
    xs = np.where(w[..., None], x, 0.0)
    cx = (xs * wf).sum(1) / safe
    cm = (ref[None] * wf).sum(1) / safe
    # poses with no usable point get unit weights only to keep kabsch finite; their R is replaced below
    wk = np.where((cnt > 0)[:, None], w, True).astype(np.float64)
    R, _ = kabsch(torch.from_numpy(xs), torch.from_numpy(np.broadcast_to(ref, xs.shape).copy()), torch.from_numpy(wk))
    R = np.where((cnt >= 3)[:, None, None], R.numpy(), np.eye(3))
    b = cm - np.einsum("pij,pj->pi", R, cx)
    b = np.where((cnt > 0)[:, None], b, 0.0)
    return R, b, cnt


def _masked_median(x: np.ndarray, w: np.ndarray) -> np.ndarray:
    """x (P, K, 3), w (P, K) bool -> (K, 3) median over the poses where w (NaN for a column with none)."""
    return np.nanmedian(np.where(w[..., None], x, np.nan), axis=0)


# ---------------------------------------------------------------------------- import
def import_tracker(
    joints,
    targets: list,
    bases: list | None = None,
    robot=None,
    drift_threshold_mm: float = DRIFT_THRESHOLD_MM,
    correct_drift: bool = False,
    outlier_mm: float = OUTLIER_MM,
) -> TrackerImport:
    """Read a tracker session (see the module docstring) into the CSV contract.

    joints: path of the commanded joints (P, N); targets: paths, tool i = the
    i-th file; bases: paths of base reflectors (none: no drift handling);
    robot: a :class:`~torchcal.kinematics.Robot` (joint count and controller
    limits checked) or None (N from the file, limits not checked).
    Raises :class:`DataError` naming file, row and column.
    """
    bases = list(bases or [])
    targets = list(targets)
    if not targets:
        raise DataError(str(joints), [Problem(None, None, "no target reflector files given (--target)")])
    if drift_threshold_mm is not None and not drift_threshold_mm > 0:
        raise DataError(str(joints), [Problem(None, None, f"drift threshold must be > 0 mm, got {drift_threshold_mm}")])
    report: list[str] = []

    # joints: count, numbers, limits
    if robot is not None:
        n = robot.joint_map.n
        jnames = list(robot.joint_map.names)
    else:
        n = _count_fields(joints)
        jnames = [f"q{i + 1}" for i in range(n)]
    jf = read_rows(joints, jnames)
    q = jf.values
    P = jf.rows
    if robot is not None:
        prismatic = robot.joint_map.prismatic.cpu()
        unit = units.joint_unit_names(prismatic)
        lim = units.joints_from_si(robot.joint_map.limits.cpu().T, prismatic).T.numpy()
        outside = (q < lim[:, 0] - LIMIT_TOL) | (q > lim[:, 1] + LIMIT_TOL)
        if outside.any():
            raise DataError(jf.path, [
                Problem(int(r) + 1, f"{c + 1} ({jnames[c]})",
                        f"{q[r, c]:.6g} {unit[c]} is outside the controller range [{lim[c, 0]:.6g}, {lim[c, 1]:.6g}] "
                        f"{unit[c]} of '{robot.name}'", jf.lines[r])
                for r, c in zip(*np.nonzero(outside))])
        from .unit_checks import radian_columns, radian_message

        q_si = units.joints_to_si(torch.from_numpy(q), prismatic)
        rad = radian_columns(q_si, robot)
        if rad:
            # a warning, not a refusal: the CSV written here is read again (fit warns, predict / compensate refuse)
            report.append("warning: " + radian_message(jf.path, q_si, robot, rad).replace(f"{jf.path}: columns ", f"{jf.path}: joint columns "))
    else:
        report.append("no robot given: joint limits not checked")

    # 1. directions over every commanded pose, before anything is dropped
    direction = _approach_directions(q)

    # reflector files: same length as the joints, zero rows = failed
    def read_points(paths):
        out = []
        for p in paths:
            f = read_rows(p, list(XYZ))
            check_same_comments([jf, f])  # before the row counts: a reading left out of one file changes its count
            if f.rows != P:
                first = min(f.rows, P) + 1
                what = f"rows {first}..{max(f.rows, P)} are missing here" if f.rows < P else f"rows {first}..{f.rows} have no pose"
                raise DataError(f.path, [Problem(None, None, f"the file has {f.rows} rows, the joints file {jf.path} has {P} "
                                                             f"({what}); every file needs one row per pose")])
            zero = (f.values == 0).all(1)
            if zero.all():
                raise DataError(f.path, [Problem(None, "1-3 (x, y, z)", f"the reflector never read: all {P} rows are 0 0 0")])
            out.append((f, zero))
        return out

    tgt = read_points(targets)
    bse = read_points(bases)
    summaries = [ReflectorSummary(f"T{i + 1}", "target", f.path, P, [int(r) + 1 for r in np.flatnonzero(z)], tool=i)
                 for i, (f, z) in enumerate(tgt)]
    bsum = [ReflectorSummary(f"B{i + 1}", "base", f.path, P, [int(r) + 1 for r in np.flatnonzero(z)])
            for i, (f, z) in enumerate(bse)]
    for s in summaries + bsum:
        if s.failed:
            what = "dropped (that reflector only)" if s.kind == "target" else "not used for drift"
            report.append(f"{s.path}: {len(s.failed)} failed reading(s) (0 0 0) {what}, rows {_rows(s.failed)}")

    X = np.stack([f.values for f, _ in tgt], 1)  # (P, T, 3) mm
    valid_t = ~np.stack([z for _, z in tgt], 1)
    _check_target_scales(tgt, X, valid_t, q, robot, jf.path, report)
    drift = np.zeros(0)
    corrections = None
    if bse:
        B = np.stack([f.values for f, _ in bse], 1)  # (P, K, 3)
        blines = bse[0][0].lines  # file line of each row in the first base file (named first in messages)
        ok = ~np.stack([z for _, z in bse], 1)
        out = _base_outliers(B, ok, outlier_mm)
        for k, s in enumerate(bsum):
            med = _masked_median(B, ok)[k]
            s.outliers = [(int(r) + 1, float(np.linalg.norm(B[r, k] - med))) for r in np.flatnonzero(out[:, k])]
            if s.outliers:
                report.append(f"{s.path}: {len(s.outliers)} wrong-target reading(s) (> {outlier_mm:g} mm off the median, "
                              f"not a rigid drift) left out of the drift estimate: "
                              + ", ".join(f"row {r} ({d:.1f} mm)" for r, d in s.outliers))
        use = ok & ~out
        ref = _masked_median(B, use)
        R, b, cnt = rigid_to_reference(B, np.nan_to_num(ref), use)
        T = np.tile(np.eye(4), (P, 1, 1))
        T[:, :3, :3], T[:, :3, 3] = R, b
        corrections = T
        # drift = largest displacement the correction applies to the pose's used base readings and valid targets
        pts = np.concatenate([B, X], 1)
        w = np.concatenate([use, valid_t], 1)
        moved = np.linalg.norm(np.einsum("pij,pkj->pki", R, pts) + b[:, None] - pts, axis=2)
        drift = np.where(w, moved, 0.0).max(1)
        drift = np.where(cnt > 0, drift, np.nan)
        few = np.flatnonzero((cnt > 0) & (cnt < 3))
        none = np.flatnonzero(cnt == 0)
        fin = drift[np.isfinite(drift)]
        worst = int(np.nanargmax(drift)) if fin.size else -1
        report.append(f"base drift over {fin.size} poses: max {fin.max():.4f} mm (pose {worst + 1}), "
                      f"median {np.median(fin):.4f} mm" if fin.size else "base drift: no usable base reading")
        if len(few):
            report.append(f"{len(few)} pose(s) with only 1-2 usable base readings: translation-only drift estimate, "
                          f"poses {_rows([int(p) + 1 for p in few])}")
        if len(none):
            msg = f"no usable base reading at pose(s) {_rows([int(p) + 1 for p in none])}"
            if correct_drift:
                raise DataError(", ".join(s.path for s in bsum), [Problem(int(p) + 1, None, "no usable base reading: cannot "
                                                                          "correct the drift of this pose", blines[p]) for p in none])
            report.append(msg + ": drift not checked there")
        if correct_drift:
            X = np.einsum("pij,ptj->pti", R, X) + b[:, None]
            report.append("drift corrected: every target point mapped through its pose's rigid correction onto the "
                          "base reflectors' median frame")
        elif drift_threshold_mm is not None:
            over = np.flatnonzero(np.nan_to_num(drift, nan=0.0) > drift_threshold_mm)
            if len(over):
                raise DataError(", ".join(s.path for s in bsum), [
                    Problem(int(p) + 1, None, f"pose {p + 1}: base drift {drift[p]:.4f} mm exceeds the threshold "
                                              f"{drift_threshold_mm:g} mm (pass --correct-drift to correct it, or raise "
                                              f"--drift-threshold-mm)", blines[p]) for p in over])
    else:
        report.append("no base reflector files: drift neither checked nor corrected")

    # contract table: tool-major, failed readings dropped
    tool_idx, pose_idx = np.nonzero(valid_t.T)
    cols: dict[str, np.ndarray] = {"pose": pose_idx.astype(np.int64) + 1, "tool": tool_idx.astype(np.int64)}
    for i, c in enumerate(joint_columns(n)):
        cols[c] = q[pose_idx, i]
    for i, c in enumerate(direction_columns(n)):
        cols[c] = direction[pose_idx, i].astype(np.int64)
    for i, c in enumerate(XYZ):
        cols[c] = X[pose_idx, tool_idx, i]
    table = pd.DataFrame(cols)
    dropped = int((~valid_t).sum())
    report.append(f"{len(table)} measurement rows written ({P} poses x {len(tgt)} targets, {dropped} failed readings dropped)")
    return TrackerImport(table, summaries + bsum, P, drift, corrections, bool(correct_drift and bse), report)


def _check_target_scales(tgt, X: np.ndarray, valid: np.ndarray, q: np.ndarray, robot, joints_path, report) -> None:
    """Every reflector rides on the flange, so the distances between consecutive poses' points are alike in every
    target file: a file whose distances are ~1000x shorter than the others' is in metres (DataError naming it). With
    a robot, each file's are also compared with the nominal flange's (a warning in the report: the fit refuses,
    and offers its override). X: (P, T, 3) mm; valid: (P, T); q: (P, n) commands as read (deg / mm)."""
    from .unit_checks import SCALE_BOUNDS, MIN_ROWS, path_scale, scale_guess

    medians = []
    for k in range(X.shape[1]):
        rows = np.flatnonzero(valid[:, k])
        d = np.linalg.norm(np.diff(X[rows, k], axis=0), axis=1)
        medians.append(float(np.median(d)) if d.size >= MIN_ROWS // 2 else np.nan)
    odd = []
    for k, ((f, _), m) in enumerate(zip(tgt, medians)):
        others = [x for i, x in enumerate(medians) if i != k and np.isfinite(x)]
        ref = float(np.median(others)) if others else np.nan
        r = m / ref if ref > 0 else np.nan
        if np.isfinite(r) and not SCALE_BOUNDS[0] <= r <= SCALE_BOUNDS[1]:
            odd.append((r, f, m, ref))
    if odd:  # of two files 1000x apart both look odd to the other: metres (the shorter) are the likelier slip
        r, f, m, ref = min(odd, key=lambda o: o[0])
        raise DataError(f.path, [Problem(None, "1-3 (x, y, z)", (
            f"the distances between consecutive poses' points (median {m:.4g}) are {r:.3g} times the other "
            f"target file{'s' if len(tgt) > 2 else ''}' (median {ref:.4g}), though every reflector rides on the "
            f"flange: this file looks like {scale_guess(r)}, and the contract is mm"))])
    if robot is None:
        return
    q_si = units.joints_to_si(torch.from_numpy(q), robot.joint_map.prismatic.cpu())
    for k, (f, _) in enumerate(tgt):
        xyz = units.mm_to_m(torch.from_numpy(np.where(valid[:, k, None], X[:, k], np.nan)))
        s = path_scale(xyz, q_si, robot)
        if s is not None and not SCALE_BOUNDS[0] <= s <= SCALE_BOUNDS[1]:
            report.append(f"warning: {f.path}: the distances between consecutive poses' points are {s:.3g} times the "
                          f"nominal '{robot.name}' flange's at {joints_path}'s commands: they look like "
                          f"{scale_guess(s)}, and the contract is mm (the fit will refuse them)")


def _approach_directions(q: np.ndarray) -> np.ndarray:
    from ..sim.sampling import approach_directions

    return approach_directions(torch.from_numpy(q)).numpy()


def _base_outliers(B: np.ndarray, ok: np.ndarray, outlier_mm: float) -> np.ndarray:
    """(P, K) bool: readings far from their median whose distances to every other usable base reading disagree too."""
    med = _masked_median(B, ok)
    far = ok & (np.linalg.norm(B - med[None], axis=2) > outlier_mm)
    dist = np.linalg.norm(B[:, :, None] - B[:, None, :], axis=3)  # (P, K, K)
    ref = np.linalg.norm(med[:, None] - med[None, :], axis=2)  # (K, K)
    pair = ok[:, :, None] & ok[:, None, :] & ~np.eye(B.shape[1], dtype=bool)[None]
    disagree = np.abs(dist - ref[None]) > outlier_mm
    # all pairs with the other usable readings disagree (vacuously true when it is the only reading)
    return far & np.where(pair, disagree, True).all(2)


def _count_fields(path) -> int:
    """Fields on the first data row of a file (for the joint count without a robot)."""
    path = Path(path)
    if not path.is_file():
        raise DataError(path, [Problem(None, None, missing_file_message(path))])
    for line in path.read_text(encoding="utf-8-sig").splitlines():
        s = line.strip()
        if s and not s.startswith("#"):
            return len([f for f in _SPLIT.split(s.strip(", \t")) if f != ""])
    raise DataError(path, [Problem(None, None, "no data rows")])


def _rows(rows: list[int], limit: int = 30) -> str:
    s = ", ".join(str(r) for r in rows[:limit])
    return s + (f", ... ({len(rows) - limit} more)" if len(rows) > limit else "")


__all__ = ["DRIFT_THRESHOLD_MM", "OUTLIER_MM", "ReflectorSummary", "TrackerImport", "import_tracker", "read_rows",
           "rigid_to_reference"]
