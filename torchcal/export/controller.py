"""Compensation tables (Paper I (2)-(3)) in controller formats: CSV, Siemens 840D CEC, LinuxCNC.

Why one module: the compensation tables in every controller format (CSV, Siemens 840D CEC, LinuxCNC joint tables) and the one dispatcher ``export-tables`` uses.

Every writer takes :class:`~torchcal.compensate.tables.CompensationTable` s
(SI) and writes millimetres and degrees (each value in its own axis's unit:
the grid in the INPUT axis's, the correction in the OUTPUT axis's). The
correction is always the amount to ADD to the output axis's command.

Formats
-------
CSV (:func:`write_tables_csv`, :func:`read_tables_csv`): one row per grid
point, header ``output_axis,input_axis,input,correction`` (axis names, input
in mm/deg, correction in mm/deg to add). The reader validates every cell and
rebuilds the tables in SI, so the tables can be applied from file
(:func:`torchcal.compensate.tables.apply_tables`).

Siemens SINUMERIK 840D "sag / angularity error compensation" (CEC, cross
error compensation; Function Manual Extended Functions K3, "Interpolatory
compensation"), :func:`write_siemens_cec`: a part program setting, per table
t, ``$AN_CEC[t,N]`` (value of interpolation point N), ``$AN_CEC_INPUT_AXIS[t]``
(base axis), ``$AN_CEC_OUTPUT_AXIS[t]`` (compensation axis), ``$AN_CEC_STEP``,
``$AN_CEC_MIN``, ``$AN_CEC_MAX`` (with (MAX - MIN) / STEP + 1 = the number of
points), ``$AN_CEC_DIRECTION`` (0: both directions), ``$AN_CEC_MULT_BY_TABLE``
(0: none) and ``$AN_CEC_IS_MODULO``. The number of points per table must not
exceed ``MD18342 $MN_MM_CEC_MAX_POINTS[t]`` (the ``max_points`` argument);
the activation (``MD32710 $MA_CEC_ENABLE`` per output axis,
``SD41300 $SN_CEC_TABLE_ENABLE[t]``, NEWCONF / reset) is written in the file's
comments. ``$AN_CEC_IS_MODULO[t] = 1`` (the table repeats cyclically, its
last value followed by its first) is right only for a table over one turn of
a modulo (rollover) rotary axis: name such axes in ``modulo_axes``; their
tables must span exactly 360 deg and start and end on the same value. Paper
I's C axis runs from -269.7 to 269.9 deg (Table 3), a rotary axis with
limits, so its tables are written absolute (IS_MODULO = 0) by default.

LinuxCNC joint compensation (:func:`write_linuxcnc_comp`), only for the
same-axis tables T_ii (a joint's correction as a function of its own
position): ``[JOINT_n] COMP_FILE = ...`` with ``COMP_FILE_TYPE = 1``, lines
``nominal forward_trim reverse_trim``. Sign convention, as LinuxCNC defines
it: the motion controller drives the motor to ``pos_cmd + trim``
(``motor_pos_cmd = pos_cmd + backlash_filt`` in ``src/emc/motion/control.c``,
the trim interpolated from the table), and a type-0 file's actual positions
are turned into trims as ``trim = nominal - actual``
(``usrmotLoadComp`` in ``src/emc/motion/usrmotintf.cc``); so the trim is the
correction to ADD, our table value, written for both directions (the model
has no backlash). The table holds at most 256 strictly increasing entries
(``EMCMOT_COMP_SIZE`` in ``src/emc/motion/motion.h``); beyond its ends the
controller holds the end trims. The loader stops at the first line that is
not three numbers, so the file carries no comments; :func:`write_linuxcnc_comp`
writes the INI lines to a separate ``linuxcnc_comp.ini`` snippet. See the
LinuxCNC INI documentation, section [JOINT_<num>], COMP_FILE and
COMP_FILE_TYPE (https://linuxcnc.org/docs/html/config/ini-config.html).
The cross-axis tables are refused there, by name (a :class:`TableNotWrittenWarning`
and the returned mapping's ``refused``): ``--format linuxcnc-volumetric``
(:mod:`torchcal.export.linuxcnc_hal`) writes a HAL component that applies all
tables, same-axis and cross-axis, instead of the joint files.

Bad input raises :mod:`torchcal.compensate.tables` errors (all TorchcalError
and ValueError): a table larger than the controller allows or not equally
spaced -> :class:`TableSizeError`, after the tables that were fine have been
written (``.ok``: their paths or names, ``.failed``: {table: reason}). Every
writer warns (:class:`TableSlopeWarning`) where a table's end slope is large.
"""

from __future__ import annotations

from datetime import UTC, datetime
from pathlib import Path

import numpy as np
import pandas as pd
import torch

from ..core import units
from ..compensate.tables import (
    CompensationTable,
    TableAxisError,
    TableSizeError,
    warn_end_slopes,
)
from ..io.atomic import atomic_write_text
from ..io.csv import DataError, Problem, parse_numbers, read_raw_table, write_table
from .linuxcnc_hal import FORMAT as LINUXCNC_VOLUMETRIC
from .linuxcnc_hal import TableNotWrittenWarning, write_linuxcnc_volumetric

CSV_COLUMNS = ("output_axis", "input_axis", "input", "correction")

SIEMENS_MAX_POINTS = 2000
"""Default ``MD18342 $MN_MM_CEC_MAX_POINTS``: pass the value configured on the controller."""

SIEMENS_MAX_TABLES = 62
"""Tables the 840D sl can hold: index 0 .. 2 x (max. NC axes = 31) - 1."""

LINUXCNC_MAX_POINTS = 256
"""``EMCMOT_COMP_SIZE``: entries of a LinuxCNC joint compensation table."""

VALUE_FORMAT = "%.9g"

CEC_DECIMALS = 8
"""Decimal places of a value in the 840D file: fixed point, no exponent (the NC language writes exponents as
``EX``, not C's ``e``, and takes at most 8 decimal places: SINUMERIK 840D sl programming manual 12/2019, R
parameters); 1e-8 mm or deg, far below any correction."""


def _fmt(x: float) -> str:
    return VALUE_FORMAT % x


def _cec(x: float) -> str:
    """A value as the 840D reads it: fixed point, at most :data:`CEC_DECIMALS` decimals, trailing zeros dropped."""
    out = f"{x:.{CEC_DECIMALS}f}".rstrip("0").rstrip(".")
    return "0" if out in ("-0", "") else out


def _unit(prismatic: bool) -> str:
    return "mm" if prismatic else "deg"


# ------------------------------------------------------------------------------ CSV
def tables_frame(tables) -> pd.DataFrame:
    """The CSV table (file units) of ``tables``: columns :data:`CSV_COLUMNS`, one row per grid point."""
    parts = []
    for t in tables:
        x, c = t.file_units()
        parts.append(pd.DataFrame({"output_axis": t.output_name, "input_axis": t.input_name,
                                   "input": x.numpy(), "correction": c.numpy()}))
    return pd.concat(parts, ignore_index=True) if parts else pd.DataFrame(columns=list(CSV_COLUMNS))


def write_tables_csv(path, tables, warn_slopes: bool = True) -> Path:
    """Write tables as CSV (mm/deg; see the module docstring); returns the path.

    Example:
        >>> import pathlib, tempfile
        >>> from torchcal.compensate.tables import CompensationTable
        >>> t = CompensationTable(2, 4, "Z", "B", [-1.0, 1.0], [1e-5, -1e-5], True, False)
        >>> p = write_tables_csv(pathlib.Path(tempfile.mkdtemp()) / "t.csv", [t])
        >>> print(p.read_text().strip())
        output_axis,input_axis,input,correction
        Z,B,-57.2957795131,0.01
        Z,B,57.2957795131,-0.01
    """
    if warn_slopes:
        warn_end_slopes(tables)
    return write_table(path, tables_frame(tables))


def read_tables_csv(path, axis_names, prismatic) -> list[CompensationTable]:
    """Read a tables CSV back into SI :class:`CompensationTable` s (one per (output, input) pair, file order).

    axis_names: the machine's axis names in order (e.g. ``["X", "Y", "Z", "C", "B"]``);
    prismatic: (n,) bool, for the units (mm -> m, deg -> rad). Rows of one
    table need not be contiguous; within a table the input must be strictly
    increasing. Raises :class:`~torchcal.io.csv.DataError` listing every
    problem with file, row and column (missing columns, unknown axis names,
    non-numbers, a table's input not increasing, a table of one point).
    """
    path = Path(path)
    names = list(axis_names)
    pris = [bool(p) for p in torch.as_tensor(prismatic, dtype=torch.bool).tolist()]
    if len(pris) != len(names):
        raise ValueError(f"read_tables_csv: {len(names)} axis names but {len(pris)} prismatic flags")
    df = read_raw_table(path)
    problems: list[Problem] = []
    missing = [c for c in CSV_COLUMNS if c not in df.columns]
    if missing:
        raise DataError(path, [Problem(None, c, "required column is missing (header must be "
                                                 + ",".join(CSV_COLUMNS) + ")") for c in missing])
    lines = df.attrs.get("lines")
    for col in ("output_axis", "input_axis"):
        for r, v in enumerate(df[col].tolist()):
            if v not in names:
                problems.append(Problem(r + 1, col, f"{v!r} is not one of the machine's axes {names}",
                                        lines[r] if lines else None))
    x = parse_numbers(df, "input", problems)
    c = parse_numbers(df, "correction", problems)
    if problems:
        raise DataError(path, problems)
    key = list(zip(df["output_axis"].tolist(), df["input_axis"].tolist()))
    order: list[tuple[str, str]] = []
    for k in key:
        if k not in order:
            order.append(k)
    tables = []
    for out_name, in_name in order:
        rows = np.array([r for r, k in enumerate(key) if k == (out_name, in_name)])
        name = f"{out_name}({in_name})"
        if rows.size < 2:
            problems.append(Problem(int(rows[0]) + 1, "input", f"table {name} has only one point; a table needs two"))
            continue
        xi = x[rows]
        dec = np.flatnonzero(np.diff(xi) <= 0)
        if dec.size:
            r = int(rows[dec[0] + 1])
            problems.append(Problem(r + 1, "input", f"table {name}: input {xi[dec[0] + 1]:.9g} does not increase "
                                                    f"(previous point {xi[dec[0]]:.9g})", lines[r] if lines else None))
            continue
        i, j = names.index(out_name), names.index(in_name)
        grid = units.mm_to_m(xi) if pris[j] else units.deg_to_rad(xi)
        corr = units.mm_to_m(c[rows]) if pris[i] else units.deg_to_rad(c[rows])
        tables.append(CompensationTable(i, j, out_name, in_name, torch.from_numpy(grid.copy()),
                                        torch.from_numpy(corr.copy()), pris[i], pris[j]))
    if problems:
        raise DataError(path, problems)
    return tables


# ----------------------------------------------------------------------- Siemens 840D
def siemens_cec_program(tables, machine_axes=None, max_points: int = SIEMENS_MAX_POINTS, modulo_axes=(),
                        first_index: int = 0, channel: int = 1) -> tuple[str, list[str], dict[str, str]]:
    """The 840D CEC part program text for the tables that fit; returns (text, written table names, failed {name: reason}).

    machine_axes: {axis name: 840D machine axis name}, default ``AX<n>`` with n
    the 1-based axis index; max_points: ``MD18342 $MN_MM_CEC_MAX_POINTS``;
    modulo_axes: names of modulo (rollover) rotary axes; first_index: table
    index t of the first table.
    """
    failed: dict[str, str] = {}
    body: list[str] = []
    written: list[str] = []
    enable_axes: list[str] = []
    t_index = first_index
    for t in tables:
        if t.size > max_points:
            failed[t.name] = (f"{t.size} points, more than MD18342 $MN_MM_CEC_MAX_POINTS = {max_points} allows; "
                              f"rebuild it with points_per_table <= {max_points} or raise MD18342")
            continue
        if not t.equally_spaced():
            failed[t.name] = "grid not equally spaced; $AN_CEC_STEP needs equal spacing"
            continue
        if t_index >= SIEMENS_MAX_TABLES:
            failed[t.name] = f"table index {t_index} beyond the {SIEMENS_MAX_TABLES} CEC tables of the 840D sl"
            continue
        x, c = t.file_units()
        modulo = t.input_name in modulo_axes
        if modulo:
            span = float(x[-1] - x[0])
            if abs(span - 360.0) > 1e-6 or abs(float(c[-1] - c[0])) > 1e-9:
                failed[t.name] = (f"input axis {t.input_name} is modulo but the table spans {span:.6g} deg "
                                  f"(a modulo table spans one turn, 360 deg, and ends on its first value)")
                continue
        if machine_axes is not None and (t.input_name not in machine_axes or t.output_name not in machine_axes):
            failed[t.name] = f"no 840D axis name for {t.input_name if t.input_name not in machine_axes else t.output_name}"
            continue
        ax_in = machine_axes[t.input_name] if machine_axes else f"AX{t.input_axis + 1}"
        ax_out = machine_axes[t.output_name] if machine_axes else f"AX{t.output_axis + 1}"
        step = (float(x[-1]) - float(x[0])) / (t.size - 1)
        body.append(f"; table {t_index}: {t.name}, correction of {t.output_name} ({_unit(t.output_prismatic)}) "
                    f"over {t.input_name} ({_unit(t.input_prismatic)}), {t.size} points")
        body += [f"$AN_CEC[{t_index},{k}]={_cec(v)}" for k, v in enumerate(c.tolist())]
        body += [
            f"$AN_CEC_INPUT_AXIS[{t_index}]=({ax_in})",
            f"$AN_CEC_OUTPUT_AXIS[{t_index}]=({ax_out})",
            f"$AN_CEC_STEP[{t_index}]={_cec(step)}",
            f"$AN_CEC_MIN[{t_index}]={_cec(float(x[0]))}",
            f"$AN_CEC_MAX[{t_index}]={_cec(float(x[0]) + step * (t.size - 1))}",
            f"$AN_CEC_DIRECTION[{t_index}]=0",
            f"$AN_CEC_MULT_BY_TABLE[{t_index}]=0",
            f"$AN_CEC_IS_MODULO[{t_index}]={1 if modulo else 0}",
            "",
        ]
        if ax_out not in enable_axes:
            enable_axes.append(ax_out)
        written.append(t.name)
        t_index += 1
    n_written = len(written)
    head = [
        "%_N_NC_CEC_INI",
        f"; torchcal compensation tables (Paper I axis perturbation model), {datetime.now(UTC):%Y-%m-%d %H:%M} UTC",
        "; values: correction ADDED to the output (compensation) axis, mm or deg; positions of the input (base) axis, mm or deg",
        f"; {n_written} table(s), index {first_index}..{first_index + n_written - 1}",
        "; activation (not done by this program):",
        (f";   MD18342 $MN_MM_CEC_MAX_POINTS[t] >= the points of table t (here at most "
         f"{max((t.size for t in tables if t.name in written), default=0)}; this file was checked against {max_points})"),
        f";   MD32710 $MA_CEC_ENABLE[<axis>] = 1 for every compensation axis: {', '.join(enable_axes) or '-'}",
        f";   SD41300 $SN_CEC_TABLE_ENABLE[t] = 1 for t = {first_index}..{first_index + n_written - 1}",
        ";   then NEWCONF (or an NCK reset); the tables act once the axes are referenced",
        "; beyond $AN_CEC_MIN / $AN_CEC_MAX the controller holds the first / last value",
        f"CHANDATA({channel})",
        "",
    ]
    return "\n".join(head + body + ["M17", ""]), written, failed


def write_siemens_cec(path, tables, machine_axes=None, max_points: int = SIEMENS_MAX_POINTS, modulo_axes=(),
                      first_index: int = 0, warn_slopes: bool = True) -> Path:
    """Write the tables as a Siemens 840D CEC part program (``%_N_NC_CEC_INI``); returns the path.

    See :func:`siemens_cec_program` for the arguments and the module docstring
    for the format. Tables that do not fit (more points than ``max_points``,
    not equally spaced, a modulo table not spanning one turn) are left out of
    the file, which is still written with the others; then
    :class:`TableSizeError` is raised naming them (``.ok``: the written
    tables' names, ``.failed``: reasons).
    """
    if warn_slopes:
        warn_end_slopes(tables)
    text, written, failed = siemens_cec_program(tables, machine_axes, max_points, modulo_axes, first_index)
    path = atomic_write_text(path, text)
    if failed:
        raise TableSizeError(f"{path}: {len(failed)} table(s) not written ({len(written)} written): "
                             + "; ".join(f"{k}: {v}" for k, v in failed.items()), ok=written, failed=failed)
    return path


# -------------------------------------------------------------------------- LinuxCNC
class WrittenTables(dict):
    """{name: path} of what a writer wrote, plus ``refused``: {table name: why it is not in the output}."""

    def __init__(self, written=(), refused=None):
        super().__init__(written)
        self.refused: dict[str, str] = dict(refused or {})


def write_linuxcnc_comp(folder, tables, max_points: int = LINUXCNC_MAX_POINTS, joint_numbers=None,
                        warn_slopes: bool = True) -> WrittenTables:
    """Write LinuxCNC joint compensation files (COMP_FILE_TYPE = 1) for the same-axis tables T_ii.

    folder: output folder; one file ``<axis>.comp`` per table with i == j
    (a cross-axis table has no LinuxCNC joint equivalent: it is refused by name in
    one :class:`TableNotWrittenWarning`, in the INI snippet's comments and in the
    result's ``refused``; ``--format linuxcnc-volumetric`` applies it), lines ``nominal trim trim`` in the
    joint's unit (mm / deg), trim = correction to ADD (module docstring).
    joint_numbers: {axis name: LinuxCNC joint number}, default the 0-based axis
    index. Also writes ``linuxcnc_comp.ini`` with the ``[JOINT_n] COMP_FILE``
    and ``COMP_FILE_TYPE`` lines. Returns {axis name: path} (a :class:`WrittenTables`).

    Tables with more than max_points (256) entries are not written and raise
    :class:`TableSizeError` after the others are (``.ok``: {axis: path}).
    """
    if warn_slopes:
        warn_end_slopes(tables)
    folder = Path(folder)
    folder.mkdir(parents=True, exist_ok=True)
    written: dict[str, Path] = {}
    failed: dict[str, str] = {}
    refused = {t.name: f"cross-axis: not written, applied by the volumetric component (--format {LINUXCNC_VOLUMETRIC})"
               for t in tables if t.output_axis != t.input_axis}
    ini = ["# LinuxCNC joint compensation written by torchcal (Paper I axis perturbation tables).",
           "# Add these lines to the [JOINT_n] sections of the machine's INI file. Values: joint units (mm / deg),",
           "# 'nominal forward_trim reverse_trim', trim = correction ADDED to the joint command (COMP_FILE_TYPE = 1).",
           "# Beyond the first / last nominal position LinuxCNC holds the end trim."]
    if refused:
        ini.append(f"# {len(refused)} cross-axis table(s) NOT written (a joint's COMP_FILE follows its own position only); "
                   f"--format {LINUXCNC_VOLUMETRIC} applies them:")
        ini += [f"#   {name}: not written" for name in refused]
        import warnings

        warnings.warn(f"linuxcnc: {len(refused)} cross-axis table(s) not written, LinuxCNC joint compensation follows a "
                      f"joint's own position only: {', '.join(refused)}; --format {LINUXCNC_VOLUMETRIC} writes a HAL "
                      f"component that applies all {len(tables)} tables", TableNotWrittenWarning, stacklevel=2)
    for t in tables:
        if t.output_axis != t.input_axis:
            continue
        if t.size > max_points:
            failed[t.name] = f"{t.size} points, LinuxCNC holds at most {max_points} (EMCMOT_COMP_SIZE)"
            continue
        x, c = t.file_units()
        lines = [f"{_fmt(a)} {_fmt(b)} {_fmt(b)}" for a, b in zip(x.tolist(), c.tolist())]
        if any(float(b) <= float(a) for a, b in zip(x.tolist(), x.tolist()[1:])):
            failed[t.name] = "nominal positions not strictly increasing in file precision"
            continue
        p = folder / f"{t.input_name}.comp"
        atomic_write_text(p, "\n".join(lines) + "\n")
        written[t.input_name] = p
        jn = joint_numbers[t.input_name] if joint_numbers else t.input_axis
        ini += ["", f"[JOINT_{jn}]", f"COMP_FILE = {p.name}", "COMP_FILE_TYPE = 1"]
    atomic_write_text(folder / "linuxcnc_comp.ini", "\n".join(ini) + "\n")
    written = WrittenTables(written, {**refused, **failed})
    if failed:
        raise TableSizeError(f"{folder}: {len(failed)} LinuxCNC table(s) not written ({len(written)} written): "
                             + "; ".join(f"{k}: {v}" for k, v in failed.items()), ok=written, failed=failed)
    return written


def read_linuxcnc_comp(path, axis: int, name: str, prismatic: bool) -> CompensationTable:
    """Read a COMP_FILE_TYPE = 1 file back (forward trims) as the SI same-axis table of ``axis``.

    Reads like LinuxCNC: triplets until the first line that is not three numbers.
    """
    rows = []
    for line in Path(path).read_text().splitlines():
        parts = line.split()
        try:
            if len(parts) != 3:
                break
            rows.append([float(v) for v in parts])
        except ValueError:
            break
    if len(rows) < 2:
        raise DataError(path, [Problem(None, None, "fewer than two 'nominal forward reverse' lines")])
    a = np.asarray(rows)
    conv = units.mm_to_m if prismatic else units.deg_to_rad
    return CompensationTable(axis, axis, name, name, torch.from_numpy(conv(a[:, 0])),
                             torch.from_numpy(conv(a[:, 1])), prismatic, prismatic)


def export_tables(folder, tables, siemens_max_points: int = SIEMENS_MAX_POINTS, machine_axes=None,
                  modulo_axes=(), slope_limit_mm: float = 0.4) -> dict:
    """Every format into ``folder``: tables.csv, cec_tables.mpf (840D), linuxcnc/ (same-axis tables),
    linuxcnc_volumetric/ (the HAL component applying all tables).

    Returns {'csv': path, 'siemens': path, 'linuxcnc': {axis: path}, 'linuxcnc-volumetric': {file: path}}. Formats
    that fail partly still write what fits; the first error is raised after
    all were attempted (``.ok`` holds this dict).
    """
    import warnings

    from ..compensate.tables import TableSlopeWarning

    folder = Path(folder)
    warn_end_slopes(tables, slope_limit_mm)
    out: dict = {"csv": write_tables_csv(folder / "tables.csv", tables, warn_slopes=False)}
    errors = []
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", TableSlopeWarning)   # warned once above
        try:
            out["siemens"] = write_siemens_cec(folder / "cec_tables.mpf", tables, machine_axes, siemens_max_points,
                                               modulo_axes, warn_slopes=False)
        except TableSizeError as e:
            out["siemens"] = folder / "cec_tables.mpf"
            errors.append(e)
        try:
            out["linuxcnc"] = write_linuxcnc_comp(folder / "linuxcnc", tables, warn_slopes=False)
        except TableSizeError as e:
            out["linuxcnc"] = e.ok
            errors.append(e)
        out[LINUXCNC_VOLUMETRIC] = write_linuxcnc_volumetric(folder / "linuxcnc_volumetric", tables, warn_slopes=False)
    if errors:
        failed = {k: v for e in errors for k, v in e.failed.items()}
        raise TableSizeError("; ".join(str(e) for e in errors), ok=out, failed=failed)
    return out


FORMATS = ("csv", "siemens-cec", "linuxcnc", LINUXCNC_VOLUMETRIC, "all")


def export_run_tables(run_dir, out, fmt: str = "csv", points: int | None = None, siemens_max_points: int = SIEMENS_MAX_POINTS,
                      pairs=None):
    """``torchcal export-tables``: the compensation tables of a machine run directory in one controller format.

    run_dir: written by ``torchcal fit`` with ``model.kind: axis_perturbation``; out: a file (csv,
    siemens-cec) or a folder (linuxcnc, linuxcnc-volumetric, all); points: grid points per table (default: the tables'
    default, at most ``siemens_max_points`` for siemens-cec); pairs: (output, input) axis names or
    indices (default every table of the model). -> what was written (path, or {axis: path}, or a dict).
    Raises RunDirError for a run without an axis perturbation model, TableError subclasses as the writers do.
    """
    from ..compensate.tables import DEFAULT_POINTS, TableError, compensation_tables
    from ..io.rundir import RunDirError, load_model

    if fmt not in FORMATS:
        raise TableError(f"unknown table format {fmt!r}; choose from {', '.join(FORMATS)}")
    from ..core.contract import require

    model = load_model(run_dir)
    try:  # the model contract: only an axis perturbation model has tables
        require(model, "export tables", f"torchcal export-tables {run_dir}")
    except TypeError as exc:
        raise RunDirError(str(exc)) from None
    k = int(points) if points is not None else DEFAULT_POINTS
    if fmt in ("siemens-cec", "all"):
        if points is not None and k > int(siemens_max_points):
            # an explicit request is never cut down behind the user's back
            raise TableSizeError(f"--points {k} is more than the Siemens 840D table holds (--max-points "
                                 f"{int(siemens_max_points)}, MD18342 $MN_MM_CEC_MAX_POINTS); give --points <= "
                                 f"{int(siemens_max_points)} or raise --max-points to the controller's MD18342")
        k = min(k, int(siemens_max_points))
    tables = compensation_tables(model, k, pairs)
    modulo = ()
    limit = run_slope_limit_mm(run_dir)
    if fmt != "all":
        warn_end_slopes(tables, limit)
    if fmt == "csv":
        return write_tables_csv(out, tables, warn_slopes=False)
    if fmt == "siemens-cec":
        return write_siemens_cec(out, tables, max_points=siemens_max_points, modulo_axes=modulo, warn_slopes=False)
    if fmt == "linuxcnc":
        return write_linuxcnc_comp(out, tables, warn_slopes=False)
    if fmt == LINUXCNC_VOLUMETRIC:
        return write_linuxcnc_volumetric(out, tables, warn_slopes=False)
    return export_tables(out, tables, siemens_max_points, slope_limit_mm=limit)


def run_slope_limit_mm(run_dir, default_mm: float = 0.4) -> float:
    """The end-slope limit the tables of a run are judged against: the slope constraint c the run's fit chose
    or was given (``constraint.json``, mm; 5 % above it, the fit's own check tolerance), else Paper I's
    0.4 mm."""
    import json
    import math

    path = Path(run_dir) / "constraint.json"
    try:
        c = json.loads(path.read_text(encoding="utf-8")).get("c")
    except (OSError, ValueError):
        return default_mm
    return float(c) * 1.05 if isinstance(c, (int, float)) and math.isfinite(c) and c > 0 else default_mm


__all__ = [
    "CSV_COLUMNS",
    "FORMATS",
    "export_run_tables",
    "LINUXCNC_MAX_POINTS",
    "SIEMENS_MAX_POINTS",
    "TableAxisError",
    "TableNotWrittenWarning",
    "WrittenTables",
    "export_tables",
    "read_linuxcnc_comp",
    "read_tables_csv",
    "siemens_cec_program",
    "tables_frame",
    "write_linuxcnc_comp",
    "write_linuxcnc_volumetric",
    "write_siemens_cec",
    "write_tables_csv",
]
