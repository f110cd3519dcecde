"""The CSV data contract: one row per measured point, millimetres and degrees.

Why one module: the whole CSV data contract (columns, units, reading with file/row/column errors, writing, Cartesian targets); split, one contract's rules would spread over files.

Columns (a header line is required; order is free; names are case-sensitive):

=============  ==============================================================
``pose``       int; rows of one pose measured with different tools share it
``tool``       int; 0-based index into the config's tool list
``q1..qN``     commanded joints in the controller's convention (deg, mm if
               the joint is prismatic), N = the robot's joint count
``dir1..dirN`` optional; approach direction of each joint, +1 or -1
``x, y, z``    measured point in the measurement frame, mm
anything else  carried through untouched (kept as text, written back as is)
=============  ==============================================================

Reading validates everything and raises one :class:`DataError` listing every
problem (up to :data:`MAX_LISTED`, then a count) with the file, the 1-based
data row and its line in the file (the header is line 1), and the column.
Rows are never dropped. Units are converted with :mod:`torchcal.core.units` only.
"""

from __future__ import annotations

import csv as _csv
import io
import logging
import re
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import pandas as pd
import torch

from ..core import units
from ..core.exceptions import TorchcalError
from ..core.measurements import Measurements

MAX_LISTED = 20
"""How many problems a :class:`DataError` message lists before summarising the rest as a count."""

LIMIT_TOL = 1e-6
"""Tolerance on the controller joint range, in file units (deg / mm): absorbs rounding in written files."""

FLOAT_FORMAT = "%.12g"
"""How floats are written: 12 significant digits (1e-9 mm at a metre, far below any tracker's noise)."""

XYZ = ("x", "y", "z")


@dataclass(frozen=True)
class Problem:
    """One defect of an input file. row: 1-based data row (None: the whole file); column: name or None."""

    row: int | None
    column: str | None
    message: str
    line: int | None = None
    """Line in the file where the row starts (header = line 1); default row + 1."""

    def __str__(self) -> str:
        where = []
        if self.row is not None:
            # blank lines are kept as rows, so data row r is line r + 1 unless a quoted field spans lines
            where.append(f"row {self.row} (line {self.line if self.line is not None else self.row + 1})")
        if self.column is not None:
            where.append(f"column '{self.column}'")
        return (", ".join(where) + ": " if where else "") + self.message


class DataError(TorchcalError, ValueError):
    """An input data file that cannot be used; lists every problem with file, row, line and column.

    path: the file; problems: list of :class:`Problem` (all of them, not only the listed ones).
    """

    def __init__(self, path, problems: list[Problem]):
        self.path = str(path)
        self.problems = list(problems)
        super().__init__(self._format())

    def _format(self) -> str:
        n = len(self.problems)
        head = f"{self.path}: {n} problem{'s' if n != 1 else ''} in the data"
        if any(p.row is not None for p in self.problems):
            # 'line' counts every line of the file; only a file with a header has row and line one apart
            head += " (row = 1-based data row, line = line in the file)"
        lines = [head + ":"]
        ordered = sorted(self.problems, key=lambda p: (-1 if p.row is None else p.row))
        lines += [f"  - {p}" for p in ordered[:MAX_LISTED]]
        if n > MAX_LISTED:
            lines.append(f"  ... and {n - MAX_LISTED} more problems")
        return "\n".join(lines)


# ---------------------------------------------------------------------------- reading
def joint_columns(n: int) -> list[str]:
    """['q1', ..., 'qN']."""
    return [f"q{i + 1}" for i in range(n)]


def direction_columns(n: int) -> list[str]:
    """['dir1', ..., 'dirN']."""
    return [f"dir{i + 1}" for i in range(n)]


log = logging.getLogger("torchcal.io.csv")

CONTRACT_COLUMN = re.compile(r"^(pose|tool|x|y|z|q\d+|dir\d+)$")
"""Names of the columns the contract interprets (the ones a decimal comma is read in)."""

_PADDING = re.compile(r"[^\S\r\n]")
"""Whitespace that str.strip would take from a cell (anything str.isspace but the line breaks pandas consumes)."""
_DECIMAL_COMMA = re.compile(r"^[+-]?\d*,\d+(?:[eE][+-]?\d+)?$")


def _is_number(text: str) -> bool:
    try:
        float(text.replace(",", "."))
        return True
    except ValueError:
        return False


def _delimiter(path: Path) -> str:
    """',' (the contract), ';' for a European spreadsheet export (``;`` separators, decimal commas), or a tab.

    Judged on the header line: a header split by ';' (or a tab) into more fields
    than by ',' (the contract's header has neither) is a ';'- (tab-) separated file.
    """
    try:
        with path.open(newline="", encoding="utf-8-sig") as fh:
            first = fh.readline()
    except (OSError, UnicodeDecodeError):
        return ","  # _scan reports it
    return _header_delimiter(first)


def _header_delimiter(first: str) -> str:
    """:func:`_delimiter` of a file whose header line is ``first``."""
    counts = {",": first.count(","), ";": first.count(";"), "\t": first.count("\t")}
    best = max(counts, key=lambda k: counts[k])
    return best if counts[best] > counts[","] else ","


def missing_file_message(path) -> str:
    """Why ``path`` cannot be read as a file: a folder given where a file is expected is not 'not found'."""
    path = Path(path)
    return "is a directory, not a file; give the data file inside it" if path.is_dir() else "file not found"


class LineNumbers(tuple):
    """The file line each row of a table starts on (``df.attrs['lines']``). pandas deep-copies a frame's attrs
    on every column access; a list of Python ints cost a call per row there (37 % of reading a 750-row file).
    A tuple never changes, so its copy is itself."""

    def __deepcopy__(self, memo):
        return self


def _scan(path: Path, delimiter: str = ",") -> tuple[list[str], list[int], list[int], bool]:
    """Header names, first file line and field count of every record (csv module: knows quoted newlines), and
    whether any cell may need stripping: the file holds whitespace other than line breaks, or quotes (a quoted
    cell may hold a line break)."""
    if not path.is_file():
        raise DataError(path, [Problem(None, None, missing_file_message(path))])
    try:
        with path.open(newline="", encoding="utf-8-sig") as fh:
            text = fh.read()
            padded = '"' in text or _PADDING.search(text) is not None
            reader = _csv.reader(io.StringIO(text, newline=""), delimiter=delimiter)
            header = next(reader, None)
            starts, widths, prev = [], [], reader.line_num
            for rec in reader:
                starts.append(prev + 1)
                widths.append(len(rec) if any(f.strip() for f in rec) else 0)  # whitespace-only: blank
                prev = reader.line_num
    except UnicodeDecodeError as exc:
        raise DataError(path, [Problem(None, None, f"not a UTF-8 text file ({exc.reason} at byte {exc.start})")]) from None
    except _csv.Error as exc:
        raise DataError(path, [Problem(None, None, f"not a well-formed CSV: {exc}")]) from None
    if not header or all(not h.strip() for h in header):
        raise DataError(path, [Problem(None, None, "no header line; the first line must name the columns")])
    return [h.strip() for h in header], starts, widths, padded


def _whitespace_hint(path: Path, header: str) -> str:
    """What else a whitespace-separated file needs: its rows' decimal commas (e.g. '1,5') are what made them
    look like several ','-separated fields, so changing the separators alone would not read them."""
    if len(header.split()) < 2:
        return ""
    try:
        with path.open(encoding="utf-8-sig") as fh:
            fh.readline()
            sample = [fh.readline() for _ in range(20)]
    except (OSError, UnicodeDecodeError):
        return ""
    tokens = [t for line in sample for t in line.split()]
    commas = [t for t in tokens if _DECIMAL_COMMA.match(t)]
    hint = " (this file separates them with whitespace)"
    if commas:
        hint += (f", and its numbers use decimal commas (e.g. {commas[0]!r}): write '.' as the decimal mark, or "
                 "';' between fields, which is read as a European spreadsheet export")
    return hint


def _blank_rows(df: pd.DataFrame) -> np.ndarray:
    """(R,) bool: the rows whose every cell is empty text. On the cells as one object array (pandas' own
    comparison of a frame of strings took 4x as long)."""
    return (df.to_numpy(dtype=object) == "").all(1)


def read_raw_table(path: Path) -> pd.DataFrame:
    """Every cell as stripped text ('' where empty), one row per record, blank lines kept as rows.

    ``df.attrs['lines']`` holds the file line each row starts on. Structural
    problems (header, field counts) are all reported before pandas reads.

    A European spreadsheet export (``;`` between fields, ``,`` as the decimal
    mark) is recognised from its header and read as such, with a warning on
    the ``torchcal`` logger and the note in ``df.attrs['notes']``: decimal
    commas are read in the contract's columns (pose, tool, q*, dir*, x, y, z);
    other columns are carried through as written.
    """
    sep = _delimiter(path)
    names, starts, widths, padded = _scan(path, sep)
    problems = []
    seen: dict[str, int] = {}
    for i, name in enumerate(names):
        if not name:
            problems.append(Problem(None, None, f"header field {i + 1} is empty"))
        elif name in seen:
            problems.append(Problem(None, name, f"appears twice in the header (fields {seen[name] + 1} and {i + 1})"))
        else:
            seen[name] = i
    for r, (line, w) in enumerate(zip(starts, widths)):
        if w and w != len(names):
            problems.append(Problem(r + 1, None, f"has {w} fields, the header has {len(names)}", line))
    if names and all(_is_number(n) for n in names if n):
        # the first line holds numbers: no header at all (the column names are not optional)
        problems = [Problem(None, None, f"the first line holds numbers ({', '.join(names[:4])}"
                                        f"{', ...' if len(names) > 4 else ''}), not column names: the file has no "
                                        "header line; the contract needs one first (e.g. pose,tool,q1..qN,x,y,z)")]
    elif sep == "," and len(names) == 1 and (len(names[0].split()) > 1 or any(w > 1 for w in widths)):
        # e.g. a space-separated file: say so once instead of "column missing" for every column, or one line per row
        problems = [Problem(None, None, f"the header has one field ({names[0][:60]!r}) and the rows up to "
                                        f"{max(widths, default=0)}: the contract separates fields with ','"
                                        + _whitespace_hint(path, names[0]))] + problems[:3]
    if problems:
        raise DataError(path, problems)
    try:
        df = pd.read_csv(path, dtype=str, keep_default_na=False, skip_blank_lines=False, encoding="utf-8-sig",
                         skipinitialspace=True, sep=sep)
    except pd.errors.ParserError as exc:
        raise DataError(path, [Problem(None, None, f"not a well-formed CSV: {exc}".strip())]) from None
    if len(df) != len(starts):  # the two readers disagree: trust neither with line numbers
        starts = [None] * len(df)
    df.columns = names
    df = df.fillna("")
    if padded:  # stripping is a Python call per cell, a third of reading a clean file, which has nothing to strip
        for c in df.columns:
            df[c] = df[c].astype(str).str.strip()
    # trailing blank lines are an editor artefact, not rows; blank lines in between are reported
    blank = _blank_rows(df)
    end = len(df)
    while end > 0 and blank[end - 1]:
        end -= 1
    df = df.iloc[:end].reset_index(drop=True)
    if len(df) == 0:
        raise DataError(path, [Problem(None, None, "no data rows after the header")])
    df.attrs["lines"] = LineNumbers(starts[:end])
    df.attrs["notes"] = []
    if sep == "\t":
        # spreadsheets and instrument software often export tabs; the values are the same, only the separator differs
        note = f"{path}: read as tab-separated; the contract is ',' between fields"
        df.attrs["notes"].append(note)
        log.warning(note)
    if sep == ";":
        converted = []
        for c in df.columns:
            if CONTRACT_COLUMN.match(c):
                comma = df[c].str.match(_DECIMAL_COMMA)
                if comma.any():
                    df.loc[comma, c] = df.loc[comma, c].str.replace(",", ".", regex=False)
                    converted.append(c)
        note = (f"{path}: read as a European spreadsheet export (';' between fields"
                + (f", decimal commas in {', '.join(converted)})" if converted else ")")
                + "; the contract is ',' between fields and '.' as the decimal mark")
        df.attrs["notes"].append(note)
        log.warning(note)
    return df


def parse_numbers(df: pd.DataFrame, column: str, problems: list[Problem]) -> np.ndarray:
    """Column as float64 (R,); every empty, non-numeric or non-finite cell becomes a Problem (value NaN).

    Rows flagged in ``df.attrs['blank']`` (blank lines, reported once each) are not reported again.
    """
    text = df[column]
    # on the cells as one object array: the same values and rejections as on the Series of strings (pandas
    # signs a '-0' cell by the column's other cells in either form), in half the time (a 750-row file: 17 columns)
    values = np.asarray(pd.to_numeric(text.to_numpy(dtype=object), errors="coerce"), dtype=np.float64)
    bad = ~np.isfinite(values)
    blank = df.attrs.get("blank")
    if blank is not None and len(blank) == len(bad):
        bad &= ~blank
    for r in np.flatnonzero(bad):
        t = text.iloc[r]
        msg = "empty; a number is required" if t == "" else f"{t!r} is not a finite number"
        problems.append(Problem(int(r) + 1, column, msg))
    return values


MARK_BOUND = 100.0
"""A command beyond this many times its joint's largest limit is refused even where commands past the range are
only marked (predict, compensate): no joint turns or travels that far."""

MAX_EXACT_ID = 2**53
"""The largest pose / tool id read exactly (ids are read as float64 first)."""


def _integers(df: pd.DataFrame, column: str, problems: list[Problem]) -> tuple[np.ndarray, np.ndarray]:
    """Column as int64 (R,) and (R,) bool valid; non-integer values become Problems (value 0, invalid)."""
    values = parse_numbers(df, column, problems)
    ok = np.isfinite(values)
    frac = ok & (values != np.round(values))
    for r in np.flatnonzero(frac):
        problems.append(Problem(int(r) + 1, column, f"{df[column].iloc[r]!r} is not an integer"))
    # read through float64: beyond 2**53 two ids can merge (ns timestamps), beyond int64 one became -2**63
    huge = ok & ~frac & (np.abs(values) > MAX_EXACT_ID)
    for r in np.flatnonzero(huge):
        problems.append(Problem(int(r) + 1, column, f"{df[column].iloc[r]!r} is beyond the exact integers "
                                                    f"(|id| <= {MAX_EXACT_ID}); number the rows with smaller ids"))
    ok &= ~frac & ~huge
    return np.where(ok, values, 0.0).astype(np.int64), ok


def _file_limits(robot) -> np.ndarray:
    """(n, 2) the controller range of every joint in file units (deg / mm)."""
    prismatic = robot.joint_map.prismatic.cpu()
    return units.joints_from_si(robot.joint_map.limits.cpu().T, prismatic).T.numpy()


POSE_COMMAND_TOLERANCE = 1e-3
"""deg (mm): how far a row's joint command may lie from its pose's first row's before the file is warned about
(rows of one pose are one robot position measured with several tools; encoders repeat far closer)."""


def _pose_consistency(q: np.ndarray, direction: np.ndarray, pose: np.ndarray, tool: np.ndarray, source) -> None:
    """Warn (the run's log and warnings) where rows of one pose differ in their joint commands or approach
    directions: a pose number used twice, or rows pasted from another session. Their measurements are fitted
    as they are, and a far-off row reads as a robot error, so the file and the rows are named."""
    if len(pose) < 2:
        return
    _, first_of, inverse = np.unique(pose, return_index=True, return_inverse=True)
    ref = first_of[inverse]
    dq = np.abs(q - q[ref])
    bad_dir = (direction != direction[ref]).any(axis=1)
    bad = (dq.max(axis=1) > POSE_COMMAND_TOLERANCE) | bad_dir
    if not bad.any():
        return
    rows = np.flatnonzero(bad)
    r = int(rows[np.argmax(dq[rows].max(axis=1))])
    j = int(np.argmax(dq[r]))
    what = (f"q{j + 1} {q[r, j]:.6g} against {q[ref[r], j]:.6g}" if dq[r, j] > POSE_COMMAND_TOLERANCE
            else "the approach directions")
    log.warning(f"{source}: {len(rows)} row(s) differ from their pose's first row, which one robot position "
                f"measured with several tools shares: e.g. row {r + 1} (pose {pose[r]}, tool {tool[r]}) against "
                f"row {ref[r] + 1}, {what}; a pose number used twice? The rows are fitted as they are")


def _to_measurements(q, tool, xyz, direction, pose, has_direction: bool, source: str, extra: dict,
                     prismatic) -> Measurements:
    """Checked columns in file units (numpy: q, direction (R, n), tool, pose (R,) int64, xyz (R, 3) mm) -> SI
    :class:`Measurements`, rows numbered from 1."""
    _pose_consistency(q, direction, pose, tool, source)
    return Measurements(
        q=units.joints_to_si(torch.from_numpy(q), prismatic),
        tool=torch.from_numpy(tool),
        xyz=units.mm_to_m(torch.from_numpy(xyz)),
        direction=torch.from_numpy(direction),
        pose=torch.from_numpy(pose),
        rows=torch.arange(1, len(q) + 1),
        has_direction=has_direction,
        source=source,
        extra=extra,
    )


def parse_table(
    df: pd.DataFrame,
    path,
    robot,
    n_tools: int | None,
    require_xyz: bool = True,
    require_pose: bool | None = None,
    outside_limits: str = "refuse",
) -> Measurements:
    """Validate a raw text table (as read by :func:`read_table`) and convert it to SI :class:`Measurements`.

    n_tools: number of configured tools (the 'tool' column is required and
    checked against it), or None when tools do not matter (compensation): then
    a 'tool' column is carried through as an extra column and every tool is 0.
    require_xyz: measured data ('x, y, z' required and finite); otherwise xyz
    is read when all three columns are there (empty cells allowed, NaN) and is
    NaN where absent. require_pose: default = require_xyz; without a 'pose'
    column every row is its own pose. Duplicate (pose, tool) rows are an error
    in measured data only. outside_limits: 'refuse' (a joint beyond the
    controller range is a problem of its row and column) or 'mark' (read, and
    the rows listed in ``extra['outside_limits']``, (R,) bool: what a model
    predicts there is an extrapolation, but e.g. compensate's own flagged rows
    must not make its output unreadable).
    """
    path = str(path)
    n = robot.joint_map.n
    prismatic = robot.joint_map.prismatic.cpu()
    unit = units.joint_unit_names(prismatic)
    require_pose = require_xyz if require_pose is None else require_pose
    problems: list[Problem] = []
    cols = set(df.columns)
    R = len(df)
    blank = _blank_rows(df)
    for r in np.flatnonzero(blank):
        problems.append(Problem(int(r) + 1, None, "blank line between data rows; remove it (rows are never skipped)"))
    df = df.copy()
    df.attrs["blank"] = blank

    qcols, dcols = joint_columns(n), direction_columns(n)
    required = qcols + (["tool"] if n_tools is not None else []) + (["pose"] if require_pose else [])
    required += list(XYZ) if require_xyz else []
    found = ", ".join(df.columns)
    # a header in another case (Q1, X, DIR1): one line naming those columns, not 'missing' for each one, and never
    # a direction column silently taken for an extra one
    misnamed = [str(c) for c in df.columns
                if not CONTRACT_COLUMN.match(str(c)) and CONTRACT_COLUMN.match(str(c).strip().lower())]
    if misnamed:
        problems.append(Problem(None, None, "the contract's column names are lower case (pose, tool, q1.., dir1.., x, "
                                            f"y, z); this file names {', '.join(misnamed)}: rename them"))
    renamed = {c.strip().lower() for c in misnamed}
    for c in required:
        if c not in cols and c not in renamed:
            problems.append(Problem(None, c, f"missing (the robot '{robot.name}' has {n} joints; columns found: {found})"))
    for prefix in ("q", "dir"):
        extra_joint = f"{prefix}{n + 1}"
        if extra_joint in cols:
            problems.append(Problem(None, extra_joint, f"robot '{robot.name}' has only {n} joints; is this file for another robot?"))
    present_dirs = [c for c in dcols if c in cols]
    if present_dirs and len(present_dirs) != n:
        missing = [c for c in dcols if c not in cols]
        problems.append(Problem(None, None, f"direction columns must be all of dir1..dir{n} or none; missing {missing}"))
    has_xyz = all(c in cols for c in XYZ)
    if not require_xyz and any(c in cols for c in XYZ) and not has_xyz:
        problems.append(Problem(None, None, f"give all of x, y, z or none; found only {[c for c in XYZ if c in cols]}"))

    # joints: numbers inside the controller range
    q = np.zeros((R, n))
    limits = _file_limits(robot)
    beyond = np.zeros(R, dtype=bool)
    refused = np.zeros(R, dtype=bool)
    for i, c in enumerate(qcols):
        if c not in cols:
            continue
        q[:, i] = parse_numbers(df, c, problems)
        lo, hi = limits[i]
        outside = np.isfinite(q[:, i]) & ((q[:, i] < lo - LIMIT_TOL) | (q[:, i] > hi + LIMIT_TOL))
        if outside_limits == "mark":
            # marked, not refused: a command a little past the range; one beyond any joint (1e300) predicted NaN
            absurd = outside & (np.abs(q[:, i]) > MARK_BOUND * max(abs(lo), abs(hi), 1.0))
            for r in np.flatnonzero(absurd):
                problems.append(Problem(int(r) + 1, c, f"{q[r, i]:.6g} {unit[i]} is far beyond any command of "
                                                        f"'{robot.name}' (range [{lo:.6g}, {hi:.6g}] {unit[i]})"))
            beyond |= outside & ~absurd
            continue
        refused |= outside
        for r in np.flatnonzero(outside):
            problems.append(Problem(int(r) + 1, c, f"{q[r, i]:.6g} {unit[i]} is outside the controller range "
                                                    f"[{lo:.6g}, {hi:.6g}] {unit[i]} of '{robot.name}'"))
    if R >= 10 and refused.mean() > 0.5:  # not a few stray rows: the whole file (1 539 cells listed one by one)
        problems.append(Problem(None, None, f"{int(refused.sum())} of {R} rows command a joint outside the controller "
                                            f"range of '{robot.name}': is this file for another robot?"))

    # approach directions: exactly +1 or -1
    has_direction = len(present_dirs) == n
    direction = np.zeros((R, n))
    if has_direction:
        for i, c in enumerate(dcols):
            d = parse_numbers(df, c, problems)
            wrong = np.isfinite(d) & (np.abs(d) != 1.0)
            for r in np.flatnonzero(wrong):
                problems.append(Problem(int(r) + 1, c, f"{df[c].iloc[r]!r} is not an approach direction (+1 or -1)"))
            direction[:, i] = np.where(np.isfinite(d) & ~wrong, d, 0.0)

    tool = np.zeros(R, dtype=np.int64)
    valid_key = np.ones(R, dtype=bool)  # rows whose (pose, tool) can take part in the duplicate check
    if n_tools is not None and "tool" in cols:
        tool, ok = _integers(df, "tool", problems)
        unknown = ok & ((tool < 0) | (tool >= n_tools))
        valid_key &= ok & ~unknown
        for r in np.flatnonzero(unknown):
            problems.append(Problem(int(r) + 1, "tool", f"tool {tool[r]} is not configured; tools are 0..{n_tools - 1} "
                                                        f"({n_tools} in the config's tool list)"))
        tool = np.where(unknown, 0, tool)

    pose = np.arange(R, dtype=np.int64)  # no pose column: every row its own pose, like Measurements.from_tensors
    if "pose" in cols:
        pose, ok = _integers(df, "pose", problems)
        valid_key &= ok

    xyz = np.full((R, 3), np.nan)
    if has_xyz:
        for i, c in enumerate(XYZ):
            if require_xyz:
                xyz[:, i] = parse_numbers(df, c, problems)
            else:
                # predicting: empty cells are allowed (nothing measured), text is still an error
                filled = df[c] != ""
                sub = df.loc[filled, [c]].reset_index(drop=True)
                sub_problems: list[Problem] = []
                vals = parse_numbers(sub, c, sub_problems)
                rows = np.flatnonzero(filled.to_numpy())
                problems += [Problem(int(rows[p.row - 1]) + 1, p.column, p.message) for p in sub_problems]
                xyz[rows, i] = vals

    far = np.abs(xyz) > XYZ_BOUND_MM
    for r, i in zip(*np.nonzero(far)):  # finite, but no tracker measures there: a lost-beam code or a unit slip
        problems.append(Problem(int(r) + 1, XYZ[i], f"{xyz[r, i]:g} mm is beyond any tracker's range "
                                f"(|value| > {XYZ_BOUND_MM:g} mm): a lost-beam or error code? remove the row"))
    if require_xyz and "pose" in cols and (n_tools is None or "tool" in cols):
        # a bad pose or tool is already reported; it must not also pair up as a false duplicate
        key = pd.DataFrame({"pose": pose, "tool": tool, "row": np.arange(R)})[valid_key]
        dup = np.zeros(R, dtype=bool)
        dup[key["row"].to_numpy()[key.duplicated(["pose", "tool"], keep="first").to_numpy()]] = True
        if dup.any():
            first = np.zeros(R, dtype=np.int64)
            first[key["row"].to_numpy()] = key.groupby(["pose", "tool"])["row"].transform("min").to_numpy()
            for r in np.flatnonzero(dup):
                problems.append(Problem(int(r) + 1, "pose, tool", f"duplicate of row {first[r] + 1} "
                                                                  f"(pose {pose[r]}, tool {tool[r]}); each pose is measured once per tool"))

    if problems:
        lines = df.attrs.get("lines")
        if lines is not None and len(lines) == R:
            problems = [p if p.row is None else Problem(p.row, p.column, p.message, lines[p.row - 1]) for p in problems]
        raise DataError(path, problems)

    interpreted = set(qcols) | ({"tool"} if n_tools is not None else set()) | {"pose"}
    interpreted |= set(dcols) if has_direction else set()
    interpreted |= set(XYZ) if has_xyz else set()
    extra = {c: df[c].to_numpy(dtype=object) for c in df.columns if c not in interpreted}
    if outside_limits == "mark":
        extra["outside_limits"] = torch.from_numpy(beyond)
    return _to_measurements(q, tool, xyz, direction, pose, has_direction, path, extra, prismatic)


def read_table(path, robot, n_tools: int | None, require_xyz: bool = True, require_pose: bool | None = None,
               outside_limits: str = "refuse") -> tuple[Measurements, pd.DataFrame]:
    """Read and validate a CSV; returns SI :class:`Measurements` and the raw text table (for carrying columns through).

    See :func:`parse_table` for the arguments. Raises :class:`DataError`.
    """
    path = Path(path)
    df = read_raw_table(path)
    return parse_table(df, path, robot, n_tools, require_xyz, require_pose, outside_limits), df


_ODD_BREAKS = re.compile("[\r\x0b\x0c\x1c\x1d\x1e\x85\u2028\u2029]")
"""Line breaks other than '\\n' (str.splitlines would split on them; the csv module reads them otherwise)."""


XYZ_BOUND_MM = 1.0e6
"""|x|, |y|, |z| beyond 1 km (mm) are no measured point: laser trackers reach tens of metres."""


def _read_clean(path: Path, robot, n_tools: int) -> Measurements | None:
    """A measurement file that the checked path (:func:`read_table`) would read without a single problem, read
    by pandas' C float parser (2-3 ms a 750-row file against ~25 ms for the checked path, which carries every
    cell as text to name a bad one by row and column) -> the same :class:`Measurements`; None wherever
    anything is unusual (another separator, quotes, padding, other line breaks, a blank or short line, a
    missing or doubled column, a cell that is not a finite number, a value the checks would refuse): the
    checked path then reads the file and says what it finds. ``torchcal fleet`` reads a file per unit, and
    100 units' files took longer than their batched solve."""
    n = robot.joint_map.n
    try:
        text = path.read_text(encoding="utf-8-sig")  # universal newlines: CRLF files read as the csv module reads them
    except (OSError, UnicodeDecodeError):
        return None
    if _header_delimiter(text.split("\n", 1)[0]) != ",":
        return None
    if '"' in text or _PADDING.search(text) is not None or _ODD_BREAKS.search(text) is not None:
        return None
    lines = text.split("\n")
    if lines and lines[-1] == "":
        lines.pop()
    if len(lines) < 2:
        return None
    names = lines[0].split(",")
    width = len(names) - 1
    if any(not line or line.count(",") != width for line in lines[1:]):
        return None
    qcols, dcols = joint_columns(n), direction_columns(n)
    cols = set(names)
    has_direction = all(c in cols for c in dcols)
    if (len(cols) != len(names) or "" in cols or not {*qcols, "tool", "pose", *XYZ} <= cols
            or (any(c in cols for c in dcols) and not has_direction) or f"q{n + 1}" in cols or f"dir{n + 1}" in cols
            or any(not CONTRACT_COLUMN.match(c) and CONTRACT_COLUMN.match(c.lower()) for c in names)):
        return None
    numeric = qcols + (dcols if has_direction else []) + ["tool", "pose", *XYZ]
    try:
        df = pd.read_csv(io.StringIO(text), dtype={c: (np.float64 if c in numeric else str) for c in names},
                         keep_default_na=False, na_filter=False, skip_blank_lines=False)
    except (ValueError, pd.errors.ParserError):
        return None
    if len(df) != len(lines) - 1:
        return None
    num = {c: df[c].to_numpy(dtype=np.float64) for c in numeric}
    # a '-0' cell: pandas' text path signs it by the column's other cells, the C parser does not
    if not all(np.isfinite(v).all() and not (np.signbit(v) & (v == 0)).any() for v in num.values()):
        return None
    prismatic = robot.joint_map.prismatic.cpu()
    limits = _file_limits(robot)
    q = np.stack([num[c] for c in qcols], 1)
    if ((q < limits[:, 0] - LIMIT_TOL) | (q > limits[:, 1] + LIMIT_TOL)).any():
        return None
    direction = np.stack([num[c] for c in dcols], 1) if has_direction else np.zeros_like(q)
    if has_direction and (np.abs(direction) != 1.0).any():
        return None
    tool, pose = num["tool"], num["pose"]
    if ((tool != np.round(tool)).any() or (pose != np.round(pose)).any() or (tool < 0).any() or (tool >= n_tools).any()
            or (np.abs(pose) > MAX_EXACT_ID).any()):  # the careful path names such an id
        return None
    tool, pose = tool.astype(np.int64), pose.astype(np.int64)
    if pd.DataFrame({"pose": pose, "tool": tool}).duplicated().any():
        return None
    xyz = np.stack([num[c] for c in XYZ], 1)
    if (np.abs(xyz) > XYZ_BOUND_MM).any():
        return None
    extra = {c: df[c].to_numpy(dtype=object) for c in names if c not in numeric}
    return _to_measurements(q, tool, xyz, np.ascontiguousarray(direction), pose, has_direction, str(path), extra,
                            prismatic)


def read_measurements(path, robot, n_tools: int | None, require_xyz: bool = True) -> Measurements:
    """Read a measurement CSV (mm, deg) into SI :class:`Measurements` (m, rad); columns beyond the contract go to ``extra``.

    robot: a :class:`torchcal.kinematics.Robot` (joint count, units, controller
    range); n_tools: number of tools in the config. Raises :class:`DataError`
    listing every problem.

    Example:
        >>> import pathlib, tempfile
        >>> from torchcal.kinematics import load_robot
        >>> path = pathlib.Path(tempfile.mkdtemp()) / "m.csv"
        >>> _ = path.write_text("pose,tool,q1,q2,q3,q4,q5,q6,x,y,z\\n0,0,90,0,0,0,0,0,500,0,300\\n")
        >>> data = read_measurements(path, load_robot("fanuc_lrmate200i"), n_tools=1)
        >>> round(data.q[0, 0].item(), 6), data.xyz[0].tolist()     # SI inside: rad, m
        (1.570796, [0.5, 0.0, 0.3])
    """
    if require_xyz and n_tools is not None:  # a clean file by pandas' C parser; anything else is checked cell by cell
        clean = _read_clean(Path(path), robot, int(n_tools))
        if clean is not None:
            return clean
    return read_table(path, robot, n_tools, require_xyz)[0]


TARGET_RPY = ("rx", "ry", "rz")
TARGET_QUAT = ("qw", "qx", "qy", "qz")
"""Orientation columns of a Cartesian target file: URDF roll-pitch-yaw in degrees (fixed axes X, then Y, then
Z: R = Rz(rz) Ry(ry) Rx(rx)), or a unit quaternion (w, x, y, z)."""


def target_kind(df: pd.DataFrame) -> str | None:
    """'rpy' or 'quaternion' when the table holds Cartesian targets (x, y, z and an orientation), else None."""
    cols = set(df.columns)
    if not set(XYZ) <= cols:
        return None
    if set(TARGET_RPY) <= cols:
        return "rpy"
    if set(TARGET_QUAT) <= cols:
        return "quaternion"
    return None


def read_targets(df: pd.DataFrame, path) -> tuple[str, torch.Tensor, torch.Tensor]:
    """Cartesian target columns of a raw table (see :func:`target_kind`), SI -> (kind, positions (R, 3) m,
    orientations: (R, 3) roll-pitch-yaw rad, or (R, 4) unit quaternions w, x, y, z).

    Raises :class:`DataError` listing every empty or non-numeric cell and every quaternion that is not of
    unit length (within 1e-6), by row and column. :func:`torchcal.compensate.targets.target_poses` turns
    them into poses.
    """
    kind = target_kind(df)
    if kind is None:
        raise DataError(path, [Problem(None, None, "no Cartesian target columns: x, y, z (mm) and rx, ry, rz "
                                                   "(deg) or qw, qx, qy, qz")])
    problems: list[Problem] = []
    if set(TARGET_RPY) <= set(df.columns) and set(TARGET_QUAT) <= set(df.columns):
        problems.append(Problem(None, "qw", "both rx, ry, rz and qw, qx, qy, qz are given: keep one orientation "
                                            "(which one the controller meant cannot be told)"))
    p = np.stack([parse_numbers(df, c, problems) for c in XYZ], 1)
    names = TARGET_RPY if kind == "rpy" else TARGET_QUAT
    o = np.stack([parse_numbers(df, c, problems) for c in names], 1)
    if kind == "quaternion":
        norm = np.linalg.norm(o, axis=1)
        for r in np.flatnonzero(np.isfinite(norm) & (np.abs(norm - 1.0) > 1e-6)):
            problems.append(Problem(int(r) + 1, "qw", f"the quaternion has length {norm[r]:.6g}, not 1"))
    if problems:
        raise DataError(path, problems)
    orientation = torch.from_numpy(o)
    return kind, units.mm_to_m(torch.from_numpy(p)), units.deg_to_rad(orientation) if kind == "rpy" else orientation


# ---------------------------------------------------------------------------- writing
def joints_to_file(q: torch.Tensor, robot) -> np.ndarray:
    """Controller commands (R, n) SI -> (R, n) float64 numpy in file units (deg / mm)."""
    return units.joints_from_si(q.detach().to("cpu", torch.float64), robot.joint_map.prismatic.cpu()).numpy()


def points_to_file(xyz: torch.Tensor) -> np.ndarray:
    """Points (R, 3) m -> (R, 3) float64 numpy in mm."""
    return units.m_to_mm(xyz.detach().to("cpu", torch.float64)).numpy()


def measurements_frame(data: Measurements, robot) -> pd.DataFrame:
    """The contract's table (file units) for ``data``: pose, tool, q, [dir], x, y, z, then 1-D extra columns."""
    n = data.n_joints
    if n != robot.joint_map.n:
        raise ValueError(f"measurements have {n} joints, robot '{robot.name}' has {robot.joint_map.n}")
    cols: dict[str, np.ndarray] = {
        "pose": data.pose.cpu().numpy().astype(np.int64),
        "tool": data.tool.cpu().numpy().astype(np.int64),
    }
    q = joints_to_file(data.q, robot)
    for i, c in enumerate(joint_columns(n)):
        cols[c] = q[:, i]
    if data.has_direction:
        d = data.direction.cpu().numpy().astype(np.int64)
        for i, c in enumerate(direction_columns(n)):
            cols[c] = d[:, i]
    xyz = points_to_file(data.xyz)
    for i, c in enumerate(XYZ):
        cols[c] = xyz[:, i]
    for name, v in data.extra.items():
        arr = v.detach().cpu().numpy() if isinstance(v, torch.Tensor) else np.asarray(v)
        # only per-row scalars are columns; other extras (e.g. (R, n) tensors from a simulator) are not
        if arr.ndim == 1 and arr.shape[0] == len(data) and name not in cols:
            cols[name] = arr
    return pd.DataFrame(cols)


def write_table(path, df: pd.DataFrame) -> Path:
    """Write a table as CSV (floats with :data:`FLOAT_FORMAT`, NaN as an empty cell); creates the folder.

    Atomic (:func:`torchcal.io.atomic.atomic_path`): an interrupted write leaves the earlier file whole.
    """
    from .atomic import atomic_path

    path = Path(path)
    with atomic_path(path) as tmp:
        df.to_csv(tmp, index=False, float_format=FLOAT_FORMAT, na_rep="", lineterminator="\n")
    return path


def write_measurements(path, data: Measurements, robot) -> Path:
    """Write SI :class:`Measurements` in the CSV contract (mm, deg); NaN points become empty x, y, z cells."""
    return write_table(path, measurements_frame(data, robot))


__all__ = [
    "DataError",
    "Problem",
    "direction_columns",
    "joint_columns",
    "measurements_frame",
    "parse_table",
    "read_measurements",
    "read_table",
    "write_measurements",
    "write_table",
]
