"""``torchcal``: calibrate from CSV files, predict, compensate, simulate.

Why one module: one typer command per CLI command, each only parsing, checking the overwrite policy and printing (the work is in :mod:`torchcal.app`); a newcomer finds every command's options in one file.

Thin on purpose: parse, call the library, write files. Every file and value
on this side is in mm and degrees (see :mod:`torchcal.io.csv`).

    torchcal simulate data/fanuc                 # simulated FANUC data + ready fit.yaml
    torchcal fit data/fanuc/fit.yaml model.order=4
    torchcal predict RUN_DIR commands.csv predicted.csv
    torchcal compensate RUN_DIR targets.csv compensated.csv
    torchcal update RUN_DIR new.csv --out NEW_RUN_DIR    # add measurements (Paper III (33))
    torchcal export-urdf RUN_DIR calibrated.urdf         # the best constant model as a URDF, compared

Bad inputs (data, robot, config, run directory) print one message naming the
file, row / key and column, and exit with status 2. Ctrl-C prints one line
("interrupted", and for a fit where the partial run directory is) and exits
with status 130. Output files are written atomically (:mod:`torchcal.io.atomic`);
an existing one is replaced only with ``--force``, an input never.

Long stages report their progress on stderr (:mod:`torchcal.io.progress_view`):
a bar per task on a terminal; elsewhere (CI, nohup, a log file) plain lines
``stage: k/N, elapsed 12.3 s, ETA 40 s [note]`` at least every 5 s while a stage
runs; the same lines go to a run's ``run.log``.
"""

from __future__ import annotations

import gc
import sys
from contextlib import contextmanager
from pathlib import Path
from typing import Annotated, Optional

try:
    import typer
    from rich.console import Console
    from rich.table import Table
    from typer.core import TyperGroup
except KeyboardInterrupt:  # Ctrl-C while the console script starts: one line, not an import traceback
    sys.stderr.write("\ninterrupted\n")
    raise SystemExit(130) from None

from .core.exceptions import TorchcalError

INTERRUPTED = 130
"""Exit status after Ctrl-C (128 + SIGINT), as shells report it."""


def _partial_note(run_dir) -> str:
    """Where a failed or interrupted run left its files (the folder holds a PARTIAL file saying so)."""
    return f"; the partial run directory is {run_dir} (marked by its PARTIAL file)" if run_dir is not None else ""


def _interrupted(exc: BaseException) -> None:
    """One line on stderr for Ctrl-C; imports nothing (the interrupt may have hit an import half done)."""
    run_dir = getattr(exc, "run_dir", None)
    where = _partial_note(run_dir)
    try:
        sys.stderr.write(f"\ninterrupted{where}\n")
        sys.stderr.flush()
    except Exception:  # a closed stderr must not turn Ctrl-C into a traceback
        pass


class _Group(TyperGroup):
    """The command group: Ctrl-C anywhere in a command is one line and exit status 130, not a traceback."""

    def invoke(self, ctx):
        try:
            return super().invoke(ctx)
        except KeyboardInterrupt as exc:
            _interrupted(exc)
            raise typer.Exit(INTERRUPTED) from None


app = typer.Typer(
    cls=_Group,
    name="torchcal",
    help="Volumetric error calibration of industrial robots (Paper II's method): fit, predict, compensate, simulate.",
    no_args_is_help=True,
    add_completion=False,
    pretty_exceptions_enable=False,
    rich_markup_mode=None,
)

USER_ERROR = 2
"""Exit status for bad inputs (like a usage error): data, robot, config, run directory."""

PAPER2_TOOLS_MM = [[33.06, 57.73, 161.22], [57.26, -33.86, 161.22], [-33.96, -57.23, 161.22]]
"""Paper II Table 4: the three measurement tool vectors, mm, flange frame."""


def _console(stderr: bool = False) -> Console:
    c = Console(stderr=stderr, highlight=False, log_path=False)
    # piped output gets rich's 80 columns, too narrow for Table 6; a log file is not a terminal either
    return c if c.is_terminal else Console(stderr=stderr, highlight=False, log_path=False, width=120)


@contextmanager
def _progress(console=None, stage: str | None = None):
    """Show the progress of the command's long stages (:mod:`torchcal.io.progress_view`) for the block.

    console: where (None: only the ``torchcal`` logger, i.e. a run's run.log): a bar
    per task on a terminal, plain lines with a heartbeat every 5 s elsewhere.
    stage: a task of that name around the whole block, so that the heartbeat covers
    it even where the library reports nothing finer. Stops before the block's
    exception (Ctrl-C included) propagates: nothing is printed after it.
    """
    from .io.progress_view import ProgressView
    from .core.progress import task

    _imports_done()
    with ProgressView(console):
        if stage is None:
            yield
        else:
            with task(stage):
                yield


def _user_error_types() -> tuple[type[BaseException], ...]:
    """TorchcalError (every bad input: data, robot, config, run directory, truth file) and a few builtins.

    Imports nothing: it runs while an exception propagates, possibly out of an
    import half done.
    """
    # unwritable or misnamed output paths are the user's to fix too; other OSErrors stay tracebacks (bugs)
    # NotImplementedError: a documented limitation, not a crash
    return (TorchcalError, PermissionError, IsADirectoryError, NotADirectoryError, FileExistsError, NotImplementedError)


def _storage_error(exc: BaseException) -> bool:
    """A read-only file system, a full disk or quota: the user's storage, not a bug (no traceback)."""
    import errno

    return isinstance(exc, OSError) and exc.errno in (errno.EROFS, errno.ENOSPC, errno.EDQUOT, errno.EACCES)


@contextmanager
def _user_errors():
    """Turn bad-input exceptions into one message on stderr and exit status 2 (no traceback).

    Only ``Exception``s are looked at: KeyboardInterrupt passes through untouched to
    the command group (one line, status 130).
    """
    try:
        yield
    except Exception as exc:
        if not isinstance(exc, _user_error_types()) and not _storage_error(exc):
            raise
        # markup=False: messages quote file contents and lists, which must not be read as rich markup;
        # soft_wrap: one line however long the paths in it (scripts grep it)
        _console(stderr=True).print(f"error: {exc}{_partial_note(getattr(exc, 'run_dir', None))}", markup=False,
                                    soft_wrap=True)
        raise typer.Exit(USER_ERROR) from None


def _warn(lines) -> None:
    """Each line a ``warning:`` on stderr, one line however long (scripts grep it)."""
    for w in lines:
        _console(stderr=True).print(f"warning: {w}", markup=False, soft_wrap=True)


def _warn_repeated(items, command: str) -> None:
    """A key given twice among the overrides (the last one is used), or one that ``command`` does not read: said
    on stderr before the run starts."""
    from .app.config import repeated_overrides, unused_overrides

    _warn([*repeated_overrides(items or []), *unused_overrides(items or [], command)])


def _device(name: str):
    """A usable torch device, or a ConfigError naming the option."""
    import torch

    from .app.config import ConfigError

    try:
        dev = torch.device(name)
    except (RuntimeError, ValueError) as exc:
        raise ConfigError(f"--device '{name}' is not a torch device ({exc})") from None
    if dev.type == "cuda" and not torch.cuda.is_available():
        raise ConfigError(f"--device '{name}': CUDA is not available here (use --device cpu)")
    return dev


FORCE_HELP = "Overwrite the output if it exists (it is never the input)."


def _check_output(output: Path, force: bool, *inputs) -> None:
    """The overwrite policy, before any work: never over an input, over an existing output only with --force."""
    from .io.atomic import check_output

    check_output(output, force, [p for p in inputs if p is not None])


def _run_files(run_dir: Path) -> list[Path]:
    """What a command reads from a run directory (or a model.pt given directly): an output must not replace it."""
    return [run_dir, run_dir / "model.pt", run_dir / "config.yaml"]


def _robot_file(robot: str | None) -> Path | None:
    """The robot option when it names a file (a bundled name is not one)."""
    return Path(robot) if robot and Path(robot).suffix else None


def _positive_option(value, option: str, unit: str):
    """None, or a positive finite number; else a ConfigError naming the option and the value in its unit."""
    import math

    from .app.config import ConfigError

    if value is not None and not (math.isfinite(value) and value > 0):
        raise ConfigError(f"{option} {value:g}: must be a positive number of {unit}")
    return value


def _version_callback(value: bool):
    if value:
        from . import __version__  # package metadata, or a fallback in a source tree never installed

        typer.echo(f"torchcal {__version__}")
        raise typer.Exit()


@app.callback()
def _root(
    version: Annotated[Optional[bool], typer.Option("--version", callback=_version_callback, is_eager=True,
                                                    help="Print the version and exit.")] = None,
):
    """Volumetric error calibration of industrial robots."""


# ------------------------------------------------------------------------- fit
def _pct(x) -> str:
    return "N/A" if x is None or x != x else f"{x:.2f} %"


def _mm(x) -> str:
    return "N/A" if x is None or x != x else f"{x:.4f}"


def results_table(rows: list[dict], title: str) -> Table:
    """A rich table in Paper II's Table 6 / 7 layout: value (mm) and percent decrease per statistic."""
    t = Table(title=title, caption="values in mm (angles in deg); % = percent decrease against the nominal residual")
    t.add_column("Set", no_wrap=True)
    t.add_column("Residual", no_wrap=True)
    for name in ("Mean", "Maximum", "Gamma 99 %"):
        t.add_column(name, justify="right", no_wrap=True)
        t.add_column("%", justify="right", no_wrap=True)
    for r in rows:
        t.add_row(r["set"], r["residual"], _mm(r["mean"]), _pct(r["mean_decrease"]), _mm(r["max"]),
                  _pct(r["max_decrease"]), _mm(r["gamma99"]), _pct(r["gamma99_decrease"]))
    return t


@app.command("fit")
def fit_cmd(
    config: Annotated[Path, typer.Argument(help="YAML config (see torchcal.app.config; `torchcal simulate` writes one).")],
    overrides: Annotated[Optional[list[str]], typer.Argument(
        help="Dotted overrides, e.g. model.order=4 data.validation=val.csv solver.method=lbfgs.")] = None,
    quiet: Annotated[bool, typer.Option("--quiet", "-q", help="No progress output.")] = False,
    dry_run: Annotated[bool, typer.Option("--dry-run", help="Print the resolved config (overrides applied) and stop.")] = False,
    units_checked: Annotated[bool, typer.Option("--units-checked", help="Skip the unit-slip checks (joints that look like radians"
                                                                    ", points that look like metres): the file really is deg / mm.")] = False,
):
    """Identify a model from a config and write a run directory (model, metrics, plots, log)."""
    with _user_errors():
        from .app.config import load_config, to_yaml
        from .app.fit import run_fit

        _warn_repeated(overrides, "fit")
        cfg = load_config(config, [*(overrides or []), *(["data.units_checked=true"] if units_checked else [])])
        if dry_run:
            typer.echo(to_yaml(cfg), nl=False)
            return
        console = None if quiet else _console(stderr=True)
        with _progress(console):
            result = run_fit(cfg, console=console)
    out = _console()
    out.print(results_table(result.table, "Residuals (Paper II, Table 6 layout)"))
    if result.compensation_table is not None:
        out.print(results_table(result.compensation_table, "Compensation on the simulated robot (Paper II, Table 7 layout)"))
        flagged = result.metrics["compensation"]["flagged"]
        if flagged:
            out.print(f"warning: {flagged} validation commands flagged (not converged or outside the joint range)", markup=False)
    if not result.fit.success:
        out.print(f"warning: the solver stopped without converging: {result.fit.message}", markup=False)
    for w in getattr(result, "warnings", []):  # data that cannot determine the model, implausible nominal residual, ...
        if not w.startswith("the solver did not converge"):
            out.print(f"warning: {w}", markup=False)
    # plain echo: a long path must stay on one line for scripts that read it
    typer.echo(f"run directory: {result.run_dir}")


# ----------------------------------------------------------------------- sweep
@app.command("sweep")
def sweep_cmd(
    config: Annotated[Path, typer.Argument(help="YAML config: the base every cell starts from.")],
    grid: Annotated[list[str], typer.Argument(
        help="Grid axes key=a,b,c or key=lo:hi (integers, inclusive), and plain key=value overrides; "
             "e.g. model.order=1:10 data.n_poses=150,250,350 (Paper II, Figure 11); sweep.engine=ray "
             "[sweep.address=HOST:PORT] fits the independent groups of cells on Ray.")],
    out: Annotated[Optional[Path], typer.Option("--out", help="Run directory (default: 'sweeps' beside the config's out).")] = None,
    quiet: Annotated[bool, typer.Option("--quiet", "-q", help="No progress output.")] = False,
):
    """Fit a grid of configs into one run directory: results table, models and the Figure 11 plot."""
    with _user_errors():
        from .app.sweep import parse_grid, run_sweep

        _warn_repeated(parse_grid(grid)[0], "sweep")
        console = None if quiet else _console(stderr=True)
        with _progress(console):
            result = run_sweep(config, grid, out=out, console=console)
    _warn(result.warnings)
    t = Table(title=f"Sweep: {len(result.rows)} cells ({result.time:.1f} s)")
    cols = [*result.keys, "status", "converged", "iterations", "identification_mean_mm", "validation_mean_mm",
            "validation_max_mm"]
    cols = [c for c in cols if any(c in r for r in result.rows)]
    for c in cols:
        # grid keys as given (data.n_poses), the result columns in words
        t.add_column(c if c in result.keys else c.replace("_mm", " (mm)").replace("_", " "), justify="right")
    for r in result.rows:
        t.add_row(*[f"{r[c]:.4f}" if isinstance(r.get(c), float) else str(r.get(c, "")) for c in cols])
    _console().print(t)
    for r in result.rows:
        if r["status"] != "fitted":
            _console().print(f"warning: cell {r['cell']} not fitted: {r['reason']}", markup=False)
    typer.echo(f"run directory: {result.run_dir}")


# ----------------------------------------------------------------------- fleet
FLEET_TABLE_ROWS = 30
"""Above this many units, `torchcal fleet`'s console table lists only the units that need a look."""


@app.command("fleet")
def fleet_cmd(
    config: Annotated[Path, typer.Argument(help="YAML config of one robot type whose data.identification is a folder "
                                                "with one CSV per unit (data.validation: a folder of the same names).")],
    overrides: Annotated[Optional[list[str]], typer.Argument(
        help="Dotted overrides, e.g. fleet.engine=ray fleet.cell=25 model.order=4 "
             "fleet.baseline=fleets (an earlier run: a config's first goes to 'fleets' beside it, the next to "
             "'fleets-2'); fleet.reuse=fleets (fit only the units that run did not, or whose data changed).")] = None,
    out: Annotated[Optional[Path], typer.Option("--out", help="Run directory (default: 'fleets' beside the config's out).")] = None,
    quiet: Annotated[bool, typer.Option("--quiet", "-q", help="No progress output.")] = False,
):
    """Fit every unit of a fleet in batched solves: a run directory per unit, a summary, outliers flagged; with
    fleet.baseline=RUN each unit compared with its calibration in that earlier run (what changed since)."""
    with _user_errors():
        from .app.fleet import run_fleet

        _warn_repeated(overrides, "fleet")
        console = None if quiet else _console(stderr=True)
        with _progress(console):
            result = run_fleet(config, overrides or [], out=out, console=console)
    rows = result.rows
    if len(rows) > FLEET_TABLE_ROWS:  # a plant's fleet: the units that need a look; every unit is in the files
        rows = [r for r in rows if r.get("status") != "fitted" or r.get("flagged") or not r.get("converged", True)
                or r.get("determined") is False or r.get("changed")]
    caption = None if rows is result.rows else (
        f"{len(rows)} of {len(result.rows)} units shown: failed, flagged, changed, not converged or undetermined; every "
        "unit in summary.csv and the fleet report")
    if any(isinstance(r.get("outlier_score"), float) for r in result.rows):  # a large score alone is no finding
        from .app.fleet import OUTLIER_MIN_RATIO

        caption = ((caption + "\n") if caption else "") + (
            "outlier score: the unit's largest robust z over its joints' features; a joint is flagged where its z "
            f"exceeds fleet.threshold and its feature is at least {OUTLIER_MIN_RATIO:g}x the fleet's median "
            "(features.csv)")
    t = Table(title=f"Fleet: {len(result.rows)} units ({result.time:.1f} s, solve {result.solve_time:.1f} s)",
              caption=caption)
    cols = ["unit", "status", "converged", "identification_mean_mm", "validation_mean_mm", "validation_max_mm",
            "outlier_score", "findings", "change_rms_mm", "change", "reason"]
    cols = [c for c in cols if any(r.get(c) not in (None, "") for r in result.rows)]
    for c in cols:
        t.add_column(c.replace("_mm", " (mm)").replace("_", " "), justify="left" if c in ("unit", "findings", "change", "reason") else "right")
    for r in rows:
        t.add_row(*[f"{r[c]:.4f}" if isinstance(r.get(c), float) else str(r.get(c, "")) for c in cols])
    _console().print(t)
    for w in result.warnings:
        _console().print(f"warning: {w}", markup=False)
    if result.reused:
        _console().print(f"fleet.reuse: {result.reused} unit(s) taken as the earlier run fitted them, "
                         f"{sum(r['status'] == 'fitted' for r in result.rows) - result.reused} fitted now "
                         "(summary.csv: reused_from)", markup=False)
    failed = [r["unit"] for r in result.rows if r["status"] == "failed"]
    if failed:
        _console().print(f"warning: {len(failed)} unit(s) not fitted: {', '.join(failed)} (summary.csv: reason); once "
                         f"their files are mended, fleet.reuse={result.run_dir} fits only them", markup=False)
    typer.echo(f"run directory: {result.run_dir}{result.placed}")
    if (result.run_dir / "report.html").is_file():
        typer.echo(f"fleet report: {result.run_dir / 'report.html'}")
    if not any(r["status"] == "fitted" and not r.get("implausible") for r in result.rows):
        # written, but nothing to deploy: a script must not read the run as a fleet calibrated
        implausible = sum(bool(r.get("implausible")) for r in result.rows)
        typer.echo(f"error: no usable unit: {len(failed)} not fitted (summary.csv 'reason'), {implausible} fitted but "
                   "not describing its robot (summary.csv 'findings'); nothing to deploy", err=True)
        raise typer.Exit(1)


# --------------------------------------------------------------------- predict
@app.command("predict")
def predict_cmd(
    run_dir: Annotated[Path, typer.Argument(help="Run directory written by `torchcal fit`.")],
    input: Annotated[Path, typer.Argument(help="CSV with tool, q1..qN [, dir1..dirN] (deg / mm); other columns are kept.")],
    output: Annotated[Path, typer.Argument(help="CSV to write: the same rows with x, y, z predicted (mm, measurement frame).")],
    device: Annotated[str, typer.Option(help="torch device.")] = "cpu",
    force: Annotated[bool, typer.Option("--force", help=FORCE_HELP)] = False,
    units_checked: Annotated[bool, typer.Option("--units-checked", help="Skip the unit-slip checks (joints that look like radians"
                                                                    ", points that look like metres): the file really is deg / mm.")] = False,
):
    """Predict measured points x, y, z (mm) for joint commands with an identified model."""
    with _user_errors():
        from .app.files import predict_file

        _check_output(output, force, input, *_run_files(run_dir))
        with _progress(_console(stderr=True)):
            res = predict_file(run_dir, input, output, _device(device), units_checked)
    typer.echo(f"predicted {res.rows} rows -> {output}")
    _warn(res.warnings)


# ---------------------------------------------------------------------- verify
@app.command("verify")
def verify_cmd(
    run_dir: Annotated[Path, typer.Argument(help="Run directory written by `torchcal fit` or `torchcal update`.")],
    data: Annotated[Path, typer.Argument(help="CSV of new measurements in the run's contract (mm, deg): a verification set.")],
    out: Annotated[Optional[Path], typer.Option("--out", help="Per-row CSV to write: row, pose, tool, x/y/z_model, nominal_mm, "
                                                              "modeled_mm [, nominal_deg, modeled_deg] [, outside_data].")] = None,
    new_frame: Annotated[bool, typer.Option("--new-frame", help="The tracker was moved: re-estimate the measurement frame "
                                                                "(a rigid motion of the predictions, nothing else refitted).")] = False,
    device: Annotated[str, typer.Option(help="torch device.")] = "cpu",
    force: Annotated[bool, typer.Option("--force", help=FORCE_HELP)] = False,
    units_checked: Annotated[bool, typer.Option("--units-checked", help="Skip the unit-slip checks (joints that look like radians"
                                                                    ", points that look like metres): the file really is deg / mm.")] = False,
):
    """Judge a run's model on new measurements (a verification set, another day, a new tracker placement): nothing is refitted."""
    with _user_errors():
        from .app.verify import verify_file

        if out is not None:
            _check_output(out, force, data, *_run_files(run_dir))
        with _progress(_console(stderr=True)):
            res = verify_file(run_dir, data, out, _device(device), new_frame, units_checked)
    _console().print(results_table(res.table, f"Verification on {data.name} (Paper II, Table 6 layout)"))
    if res.frame is not None:
        typer.echo(f"measurement frame re-estimated: moved {res.frame['moved_mm']:.3f} mm at the robot base, turned "
                   f"{res.frame['turned_deg']:.4f} deg")
    _warn(res.warnings)
    if res.output is not None:
        typer.echo(f"wrote {res.output}")


# ---------------------------------------------------------------------- update
@app.command("update")
def update_cmd(
    run_dir: Annotated[Path, typer.Argument(help="Run directory written by `torchcal fit` or `torchcal update`.")],
    new_data: Annotated[Path, typer.Argument(help="CSV of new measurements in the run's contract (mm, deg).")],
    out: Annotated[Path, typer.Option("--out", help="New run directory (the parent is never modified).")],
    strategy: Annotated[Optional[str], typer.Option(
        help="information (default: earlier rows' joint errors marginalized) or literal (Paper III (33) as printed); "
             "only for a parent written by `torchcal fit`, an updated run keeps its own.")] = None,
    device: Annotated[str, typer.Option(help="torch device.")] = "cpu",
    quiet: Annotated[bool, typer.Option("--quiet", "-q", help="No progress output.")] = False,
    units_checked: Annotated[bool, typer.Option("--units-checked", help="Skip the unit-slip checks (joints that look like radians"
                                                                    ", points that look like metres): the file really is deg / mm.")] = False,
):
    """Online adaptive identification (Paper III (33)): add new measurements to a run without refitting the old ones."""
    with _user_errors():
        from .app.update import run_update

        console = None if quiet else _console(stderr=True)
        with _progress(console):
            res = run_update(run_dir, new_data, out, _device(device), strategy, console=console,
                             units_checked=units_checked)
    if res.table:
        _console().print(results_table(res.table, "Residuals after the update (Paper II, Table 6 layout)"))
    for w in res.warnings:
        _console().print(f"warning: {w}", markup=False)
    typer.echo(f"{res.step.rows} rows in {res.step.batch + 1} batches ({res.step.strategy}); parent {res.parent}")
    typer.echo(f"run directory: {res.run_dir}")


# ------------------------------------------------------------------ compensate
@app.command("compensate")
def compensate_cmd(
    run_dir: Annotated[Path, typer.Argument(help="Run directory written by `torchcal fit`.")],
    input: Annotated[Path, typer.Argument(help="CSV with nominal commands q1..qN [, dir1..dirN] (deg / mm), or Cartesian targets "
                                               "x, y, z (mm) + rx, ry, rz (deg, URDF roll-pitch-yaw) or qw, qx, qy, qz in the "
                                               "robot base frame with q1..qN the controller's seeds [, tool]; other columns are kept.")],
    output: Annotated[Path, typer.Argument(help="CSV to write: q1..qN compensated (deg / mm) plus converged, iterations, within_limits, "
                                                "max_dq (largest |q_new - q_nom|, deg / mm) [, direction_outside], reason (empty, or why the row is flagged).")],
    tol_deg: Annotated[Optional[float], typer.Option(help="Newton tolerance on |dq| (deg); default: the run's compensation.tol_deg.")] = None,
    max_iter: Annotated[Optional[int], typer.Option(help="Newton iteration limit; default: the run's compensation.max_iter.")] = None,
    max_correction_deg: Annotated[Optional[float], typer.Option(
        help="Largest correction |q_new - q_nom| of any joint (deg, mm for prismatic joints); rows that need more are "
             "flagged, not converged. Default 30 (an outer guard: a solution on another branch of the arm, i.e. "
             "other configuration flags, is refused whatever its size).")] = None,
    free_tool_axis: Annotated[bool, typer.Option("--free-tool-axis", help="5-DOF compensation for axisymmetric tools "
                                                 "(drill, spindle, torch, reflector): the rotation about the tool axis "
                                                 "is left free.")] = False,
    tool_axis: Annotated[str, typer.Option(help="The tool axis X,Y,Z in the flange frame (with --free-tool-axis).")] = "0,0,1",
    dof: Annotated[str, typer.Option(help="What the commands restore: 6 (the flange pose), 3 (the tool point's position "
                                          "only), 5 (with --free-tool-axis), or auto: what the run's tools observe (one "
                                          "tool: 3, two or tools on one line: 5 about their line, else 6).")] = "auto",
    device: Annotated[str, typer.Option(help="torch device.")] = "cpu",
    force: Annotated[bool, typer.Option("--force", help=FORCE_HELP)] = False,
    units_checked: Annotated[bool, typer.Option("--units-checked", help="Skip the unit-slip checks (joints that look like radians"
                                                                    ", points that look like metres): the file really is deg / mm.")] = False,
):
    """Compensated joint commands: where to send the robot so that it reaches the nominal flange pose (Paper II (46)-(52)).

    A run fitted from one measured point per pose (one tool) has no observed
    flange orientation: by default its commands restore the tool point's
    position only, with the smallest joint motion (--dof auto; a note says so).

    A file of Cartesian targets (a robot program's poses) gets the calibrated
    joint commands and, in x_cmd .. rz_cmd, the corrected target to send to a
    controller that keeps its nominal inverse kinematics (a program filter);
    q1..qN there are the seeds that pick the controller's branch, and 'reason'
    says why a row is flagged (out of reach, joint limit, correction bound).

    Rows that do not converge or leave the controller's joint range are
    flagged (converged / within_limits = false), never dropped. A row whose
    exact solution lies more than --max-correction-deg from its nominal
    command, or on another branch of the arm, is not converged: it keeps a
    bounded best-effort command, and 'reason' says which. direction_outside (when the run's model records the
    identification data's coverage and the file has dir1..dirN) marks rows
    whose approach directions the identification never saw.
    """
    with _user_errors():
        from .app.files import compensate_file

        # the library reads these in radians: a bad value is named here, in the unit the user typed
        _positive_option(max_correction_deg, "--max-correction-deg", "degrees (mm for prismatic joints)")
        _positive_option(tol_deg, "--tol-deg", "degrees")
        if max_iter is not None and max_iter < 1:
            _positive_option(float(max_iter), "--max-iter", "iterations")
        _check_output(output, force, input, *_run_files(run_dir))
        with _progress(_console(stderr=True)):
            out = compensate_file(run_dir, input, output, _device(device), tol_deg, max_iter, max_correction_deg,
                                  units_checked, _tool_axis(tool_axis) if free_tool_axis else None, dof)
    typer.echo(f"compensated {out.rows} {'Cartesian targets' if out.targets else 'commands'} -> {output}")
    _warn(out.warnings)
    if out.flagged:
        _console(stderr=True).print(
            f"warning: {out.flagged} of {out.rows} commands flagged ({out.not_converged} did not converge or are out "
            "of reach, "
            f"{out.outside_limits} outside the controller range); they are kept, marked in 'converged' / 'within_limits'",
            markup=False)
    else:
        typer.echo("0 commands flagged")
    if out.direction_outside:
        _console(stderr=True).print(
            f"warning: {out.direction_outside} of {out.rows} commands approach a joint from a direction the "
            f"identification data did not cover there (column 'direction_outside')", markup=False)


# -------------------------------------------------------------------- simulate
@app.command("simulate")
def simulate_cmd(
    out_dir: Annotated[Path, typer.Argument(help="Folder for identification.csv, validation.csv, truth.json and fit.yaml.")],
    robot: Annotated[str, typer.Option(help="Bundled robot name, joint-map YAML or URDF.")] = "fanuc_lrmate200i",
    identification: Annotated[int, typer.Option(help="Identification poses (each measured with all 3 tools).")] = 250,
    validation: Annotated[int, typer.Option(help="Validation poses (0: none).")] = 300,
    validation_tool: Annotated[int, typer.Option(help="Tool (0-based) the validation set is measured with.")] = 2,
    seed: Annotated[int, typer.Option(help="Seed of the truth robot, the commands and the noise.", min=0, max=2**63 - 1)] = 0,
    order: Annotated[int, typer.Option(help="model.order written into fit.yaml.")] = 6,
    force: Annotated[bool, typer.Option("--force", help="Overwrite files already in OUT_DIR.")] = False,
    error_variable: Annotated[str, typer.Option(help="What the simulated gear errors follow: command (Paper II (24)) or joint.")] = "command",
    pose_order: Annotated[str, typer.Option(help="Visit the quasi-random poses shuffled or in the sequence's own order (the paper's).")] = "shuffled",
    backlash_on: Annotated[str, typer.Option(help="Where the simulated gears' backlash acts: joint (Paper II (13)) or command "
                                                  "(the controller joint's, carried by the joint map: a parallelogram's J2 "
                                                  "backlash turns θ3 too).")] = "joint",
):
    """Simulated measurements of a robot with known errors (Paper II's protocol) and a ready-to-run fit.yaml."""
    with _user_errors():
        from .app.simulate import simulate_dataset

        with _progress(_console(stderr=True), f"simulating {identification} + {validation} poses -> {out_dir}"):
            paths = simulate_dataset(out_dir, robot, identification, validation, validation_tool, seed, order, force,
                                     error_variable=error_variable, pose_order=pose_order, backlash_on=backlash_on)
    for name, p in paths.items():
        typer.echo(f"{name}: {p}")
    typer.echo(f"next: torchcal fit {paths['config']}")


# --------------------------------------------------------------- import-tracker
@app.command("import-tracker")
def import_tracker_cmd(
    output: Annotated[Path, typer.Argument(help="Measurement CSV to write (pose, tool, q1..qN, dir1..dirN, x, y, z; mm, deg).")],
    joints: Annotated[Path, typer.Option("--joints", help="Commanded joints, one row per pose, N columns (deg / mm).")],
    target: Annotated[list[Path], typer.Option("--target", help="Tool reflector file (x y z mm per pose); repeat, tool i = i-th file (0-based).")],
    base: Annotated[Optional[list[Path]], typer.Option("--base", help="Base reflector file (x y z mm per pose), for drift; repeat.")] = None,
    robot: Annotated[Optional[str], typer.Option(help="Bundled robot name, joint-map YAML or URDF: joint count and controller limits are checked.")] = None,
    drift_threshold_mm: Annotated[float, typer.Option(help="Largest per-pose base drift (mm) accepted without --correct-drift.")] = 0.1,
    correct_drift: Annotated[bool, typer.Option("--correct-drift", help="Map each pose's target points through its rigid base-drift correction.")] = False,
    outlier_mm: Annotated[float, typer.Option(help="A single base reading this far (mm) off its median is a wrong-target outlier.")] = 1.0,
    force: Annotated[bool, typer.Option("--force", help=FORCE_HELP)] = False,
):
    """Convert laser-tracker exports (whitespace / comma separated, one row per pose) into the measurement CSV.

    Approach directions follow the commanded pose order; 0 0 0 rows are failed
    readings (that reflector's row dropped, reported); base reflectors give
    the per-pose drift (checked against the threshold, or corrected).
    """
    with _user_errors(), _progress(_console(stderr=True), f"importing the tracker exports -> {output}"):
        from .app.commands import import_tracker_file

        _check_output(output, force, joints, *target, *(base or []), _robot_file(robot))
        res = import_tracker_file(output, joints, target, base, robot, drift_threshold_mm, correct_drift, outlier_mm)
    out = _console()
    out.print(res.summary_table())
    for line in res.report:
        out.print(line, markup=False)
    typer.echo(f"wrote {len(res.table)} rows -> {output}")


# ---------------------------------------------------------------- export-tables
@app.command("export-tables")
def export_tables_cmd(
    run_dir: Annotated[Path, typer.Argument(help="Run directory of a machine fit (model.kind: axis_perturbation).")],
    out: Annotated[Path, typer.Argument(help="File (csv, siemens-cec) or folder (linuxcnc, linuxcnc-volumetric, all) to write.")],
    format: Annotated[str, typer.Option("--format", help="csv | siemens-cec | linuxcnc (same-axis joint tables) | linuxcnc-volumetric (all 25 tables, a HAL component) | all")] = "csv",
    points: Annotated[Optional[int], typer.Option(help="Grid points per table (equally spaced over the input axis's range).")] = None,
    max_points: Annotated[int, typer.Option(help="Siemens MD18342 $MN_MM_CEC_MAX_POINTS of the controller.")] = 2000,
    force: Annotated[bool, typer.Option("--force", help="Overwrite the files already there.")] = False,
):
    """Compensation tables -f_ij of a machine model for a controller (Paper I): q̂_i = q_i + Σ_j T_ij(q_j)."""
    import warnings

    with _user_errors(), warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        from .app.commands import export_tables, run_notes

        _check_table_outputs(run_dir, out, format, force)
        with _progress(_console(stderr=True), f"exporting the compensation tables of {run_dir} ({format})"):
            written = export_tables(run_dir, out, format, points, max_points)
    for note in run_notes(run_dir):
        typer.echo(f"warning: {note}", err=True)
    seen = set()
    for w in caught:  # the end-slope warnings, once each (every writer checks them)
        if str(w.message) not in seen:
            seen.add(str(w.message))
            typer.echo(f"warning: {w.message}", err=True)
    for line in _written_lines(written):
        typer.echo(line)


def _written_lines(written, prefix: str = "") -> list[str]:
    """'wrote PATH' lines for what a writer returned: a path, {name: path}, or {format: either}."""
    if isinstance(written, dict):
        return [line for k, v in written.items() for line in _written_lines(v, f"{prefix}{k}: ")]
    if isinstance(written, (list, tuple)):
        return [line for v in written for line in _written_lines(v, prefix)]
    return [f"wrote {prefix}{written}"]


def _check_table_outputs(run_dir: Path, out: Path, fmt: str, force: bool) -> None:
    """export-tables' overwrite policy: a file format checks its file; the folder formats, the files they put there."""
    from .app.commands import table_output_names
    from .io.atomic import OutputExistsError

    names = table_output_names(fmt)
    if names is None:
        if fmt in ("csv", "siemens-cec"):  # an unknown format is the library's message
            _check_output(out, force, *_run_files(run_dir))
        return
    if out.exists() and not out.is_dir():
        raise OutputExistsError(f"{out}: already exists and is a file; --format {fmt} writes a folder, give a folder name")
    existing = sorted(str(p.relative_to(out)) for pattern in names for p in out.glob(pattern))
    if existing and not force:
        shown = ", ".join(existing[:5]) + (f" and {len(existing) - 5} more" if len(existing) > 5 else "")
        raise OutputExistsError(f"{out}: already holds {shown}; pass --force to overwrite them or choose another folder")


# ------------------------------------------------------------------ export-urdf
@app.command("export-urdf")
def export_urdf_cmd(
    run_dir: Annotated[Path, typer.Argument(help="Run directory of a robot fit, written by `torchcal fit` or `torchcal update`.")],
    output: Annotated[Path, typer.Argument(help="URDF to write (.urdf); a robot given by a joint-map YAML gets that YAML next to "
                                                "it (same stem, .yaml; a bare URDF robot has none).")],
    base: Annotated[str, typer.Option("--base", help="joint: fold the base correction into the first joint's origin; link: a new root link with a fixed joint carrying it.")] = "joint",
    measurement_frame: Annotated[bool, typer.Option("--measurement-frame", help="Also fold in the measurement frame: the URDF's root is the tracker frame.")] = False,
    constants: Annotated[str, typer.Option("--constants", help="fit: constants fitted to the full model at the identification data's poses (best); c0: the order-0 coefficients as identified (exact only for an order-0 model).")] = "fit",
    force: Annotated[bool, typer.Option("--force", help=FORCE_HELP)] = False,
):
    """A calibrated URDF: the constant part of a robot model in the joint origins, compared on the run's data (mm)."""
    with _user_errors():
        from .app.commands import export_urdf, run_notes
        from .app.config import ConfigError

        if base not in ("joint", "link"):
            raise ConfigError(f"--base '{base}': choose joint or link")
        if constants not in ("fit", "c0"):
            raise ConfigError(f"--constants '{constants}': choose fit or c0")
        _check_output(output, force, *_run_files(run_dir))
        with _progress(_console(stderr=True), f"exporting the calibrated URDF of {run_dir}"):
            res, which = export_urdf(run_dir, output, base, measurement_frame, constants, force)
        for note in run_notes(run_dir):
            typer.echo(f"warning: {note}", err=True)
    exp = res.export
    typer.echo(f"wrote {exp.urdf}")
    if exp.joint_map is not None:
        typer.echo(f"wrote {exp.joint_map}")
    how = "fitted to the full model" if constants == "fit" else "order-0 coefficients (c0)"
    typer.echo(f"constants: {how}; vs the full model at {exp.commands} commands ({exp.region}): "
               f"RMS {exp.misfit_rms_mm:.4f} mm, max {exp.misfit_max_mm:.4f} mm")
    if res.comparison is None:
        typer.echo("warning: the run's config names no readable identification or validation file: not compared",
                   err=True)
        return
    c, rms = res.comparison, res.rms_mm
    typer.echo(f"compared on the {which} data: {res.data} ({c.nominal.count} points)")
    t = Table(title="Residuals (mm)", caption="|p - xyz|, joint errors v at zero; every row with the run's identified "
                                              "tool vectors (the URDF holds no tools)")
    t.add_column("Model", no_wrap=True)
    for name in ("Mean", "RMS", "Max"):
        t.add_column(name, justify="right", no_wrap=True)
    for label, key, stats in (("Nominal", "nominal", c.nominal), ("URDF alone", "urdf", c.urdf),
                              ("Full model", "full", c.full)):
        t.add_row(label, _mm(stats.mean), _mm(rms[key]), _mm(stats.max))
    _console().print(t)
    if res.urdf_worse_than_nominal:
        hint = ("; export with --constants fit (the default)" if constants == "c0" else
                "; the full model is worse than the nominal robot there too: do not deploy this run"
                if c.full.mean > c.nominal.mean else
                ": the joint-dependent errors dominate (no constant holds them), use the full model (torchcal "
                "predict / compensate)")
        typer.echo(f"warning: the URDF alone is worse than the nominal robot on the {which} data (mean "
                   f"{c.urdf.mean:.4f} mm against {c.nominal.mean:.4f} mm, RMS {rms['urdf']:.4f} against "
                   f"{rms['nominal']:.4f} mm){hint}", err=True)


# ------------------------------------------------------------------ import-tmac
# ---------------------------------------------------------------------- report
@app.command("report")
def report_cmd(
    run_dir: Annotated[Path, typer.Argument(help="Run directory written by `torchcal fit` or `torchcal update`; a `torchcal fleet` run gets the fleet report.")],
    out: Annotated[Optional[Path], typer.Option("--out", help="HTML file to write (default: RUN_DIR/report.html).")] = None,
    force: Annotated[bool, typer.Option("--force", help=FORCE_HELP)] = False,
):
    """The calibration report: one self-contained HTML page (plots embedded, opens offline, prints to PDF)."""
    with _user_errors():
        from .app.commands import write_report

        target = out if out is not None else run_dir / "report.html"
        if out is not None:  # the default file is the run's own report: rewriting it is what the command is for
            _check_output(target, force, *_run_files(run_dir))
        with _progress(_console(stderr=True), f"writing the report of {run_dir}"):
            path = write_report(run_dir, out)
    typer.echo(f"wrote {path}")


@app.command("import-tmac")
def import_tmac_cmd(
    source: Annotated[Path, typer.Argument(help="T-Mac export (';'-separated, decimal commas: joints in rad, measurement_x/y/z mm, measurement_rx/ry/rz deg).")],
    output: Annotated[Path, typer.Argument(help="Sensor CSV to write (pose, q1..q6, x, y, z, r11..r33, sx..srz; mm, deg).")],
    robot: Annotated[str, typer.Option(help="Bundled robot name, joint-map YAML or URDF (joint count and limits are checked).")] = "ur10",
    convention: Annotated[str, typer.Option(help="Euler convention of measurement_rx/ry/rz (scipy naming; XYZ = intrinsic).")] = "XYZ",
    exclude: Annotated[Optional[list[int]], typer.Option("--exclude", help="1-based data row to leave out (repeat).")] = None,
    force: Annotated[bool, typer.Option("--force", help=FORCE_HELP)] = False,
):
    """Convert a UR10 + Leica T-Mac export (ipa-robot-accuracy format) into the sensor CSV contract."""
    with _user_errors(), _progress(_console(stderr=True), f"converting {source}"):
        from .app.commands import import_tmac_file

        _check_output(output, force, source, _robot_file(robot))
        path, said = import_tmac_file(source, output, robot, convention, exclude or ())
    if exclude:
        typer.echo(f"left out data rows {sorted(set(exclude))}")
    typer.echo(f"wrote {path}")
    _warn(said)


# ------------------------------------------------------------------ plan-poses
def _three_numbers(text: str, option: str, what: str) -> list[float]:
    """'X,Y,Z' (or ';'-separated) -> three finite numbers; a ConfigError naming the option and what it wants."""
    from .app.config import ConfigError

    try:
        v = [float(x) for x in text.replace(";", ",").split(",")]
    except ValueError:
        v = []
    if len(v) != 3 or not all(x == x and abs(x) != float("inf") for x in v):
        raise ConfigError(f"{option} '{text}': expected {what}")
    return v


def _tool_axis(text: str) -> list[float]:
    """'X,Y,Z' -> a nonzero direction [x, y, z] (flange frame); a ConfigError naming --tool-axis otherwise."""
    what = "a nonzero direction X,Y,Z in the flange frame"
    v = _three_numbers(text, "--tool-axis", what)
    if not any(v):
        from .app.config import ConfigError

        raise ConfigError(f"--tool-axis '{text}': expected {what}")
    return v


def _parse_xyz_mm(text: str | None, option: str):
    """'X,Y,Z' in mm -> [x, y, z] (mm), or None; a ConfigError naming the option otherwise."""
    return None if text is None else _three_numbers(text, option, "three numbers X,Y,Z in mm (robot base frame)")


@app.command("plan-poses")
def plan_poses_cmd(
    robot: Annotated[str, typer.Argument(help="Bundled robot name, joint-map YAML or URDF.")],
    count: Annotated[int, typer.Argument(help="Number of poses to plan.")],
    output: Annotated[Path, typer.Argument(help="CSV to write: pose, q1..qN (deg / mm), in visiting order.")],
    seed: Annotated[int, typer.Option(help="Seed of the Sobol scrambling and the visiting order.", min=0, max=2**63 - 1)] = 0,
    tracker: Annotated[Optional[str], typer.Option(help="Tracker position X,Y,Z in mm (robot base frame): keep only poses whose flange z axis points within --max-incidence-deg of it.")] = None,
    max_incidence_deg: Annotated[float, typer.Option(help="Largest angle between the flange z axis and the line to the tracker.")] = 60.0,
    min_height_mm: Annotated[float, typer.Option(help="Lowest flange z (mm) in the robot base frame.")] = 0.0,
    min_distance_mm: Annotated[float, typer.Option(help="Radius (mm) of the keep-out sphere around the base origin.")] = 200.0,
    order: Annotated[str, typer.Option(help="Visiting order: decorrelate (backlash-friendly), shuffle, or sequence (Sobol order; confounds backlash).")] = "decorrelate",
    fleet: Annotated[Optional[Path], typer.Option(help="A fleet's run directory (torchcal fleet): design the poses for a new unit fitted with that fleet's prior (prior.fleet), the COUNT of --candidates that lower its predicted model error most.")] = None,
    candidates: Annotated[int, typer.Option(help="With --fleet: reachable candidate poses to design from.")] = 2000,
    force: Annotated[bool, typer.Option("--force", help=FORCE_HELP)] = False,
):
    """Quasi-random, reachable measurement poses in an order that decorrelates approach direction from position.

    Prints, per joint, the correlation and R² (cubic Chebyshev basis) between
    the approach direction and the position in the planned order, next to the
    Sobol sequence's own order (see torchcal.analysis.planning).
    """
    with _user_errors():
        from .app.commands import plan_poses_file

        tracker_mm = _parse_xyz_mm(tracker, "--tracker")
        _check_output(output, force, _robot_file(robot))
        with _progress(_console(stderr=True)):
            plan, rob = plan_poses_file(robot, count, output, seed, tracker_mm, min_distance_mm, min_height_mm,
                                        max_incidence_deg, order, fleet, candidates)
    st = plan.stats
    table = Table(title=f"approach direction vs position, {len(plan)} poses, order={order}")
    for col in ("joint", "corr", "R²", "one-sided bins", "corr (Sobol order)", "R² (Sobol order)"):
        table.add_column(col, justify="left" if col == "joint" else "right")
    names = list(rob.joint_map.names) if hasattr(rob.joint_map, "names") else [f"J{j + 1}" for j in range(rob.joint_map.n)]
    for j, name in enumerate(names):
        table.add_row(name, f"{st['corr'][j]:+.3f}", f"{st['r2'][j]:.3f}", f"{st['one_sided_bins'][j]}/{st['bins']}",
                      f"{st['sequence']['corr'][j]:+.3f}", f"{st['sequence']['r2'][j]:.3f}")
    out = _console()
    out.print(table)
    rej = st["rejected"]
    seen = "" if tracker_mm is None else f", {rej['not_visible']} not visible from the tracker"
    out.print(f"drew {st['drawn']} candidates; rejected {rej['below_plane']} below the floor plane, "
              f"{rej['near_base']} near the base{seen}", markup=False)
    design = st.get("design")
    if design is not None:
        out.print(f"designed for the prior of {design['fleet']}: predicted RMS model error {design['predicted_rms_mm']:.4f} mm "
                  f"({design['candidates']} candidates; the first {len(plan)} of a plain plan: "
                  f"{design['plain_predicted_rms_mm']:.4f} mm; the prior alone: {design['prior_rms_mm']:.4f} mm)",
                  markup=False)
    typer.echo(f"wrote {len(plan)} poses -> {output}")


# --------------------------------------------------------------------- compile
@app.command("compile")
def compile_cmd(
    only: Annotated[Optional[str], typer.Option(help="Kernel families, comma-separated: targets, fleet, damped, flange (default: all).")] = None,
    jobs: Annotated[Optional[int], typer.Option(help="Processes side by side (default: the CPUs this process may use).")] = None,
    force: Annotated[bool, typer.Option("--force", help="Run the families already in numba's cache too (they only load).")] = False,
):
    """Build torchcal's compiled kernels into numba's cache now, not in the first run that needs them.

    Once per install (and after a numba or CPU change): about 3 min on 2
    cores for all four families, side by side (one after another, inside the
    first compensation and the first fleet, ~3 min 50 s). Prints each family:
    compiled, or already in the cache.
    """
    from .app.config import ConfigError

    with _user_errors():
        from .app.compile import ORDER, compile_kernels

        families = None if only is None else [f.strip() for f in only.split(",") if f.strip()]
        bad = [f for f in families or [] if f not in ORDER]
        if bad:
            raise ConfigError(f"--only {only}: unknown kernel families {', '.join(bad)} (known: {', '.join(ORDER)})")
        if jobs is not None and jobs < 1:
            raise ConfigError(f"--jobs {jobs}: must be at least 1")
        err = _console(stderr=True)

        def done(c):
            err.print(f"{c.family}: {'failed' if c.error else 'compiled' if c.missing else 'loaded'} in {c.seconds:.1f} s",
                      markup=False)

        try:
            results = compile_kernels(families, jobs, force, progress=done)
        except RuntimeError as exc:  # no numba in use: nothing to build, and nothing is wrong
            typer.echo(f"nothing to compile: {str(exc).split(': ', 1)[1]}")
            return
    t = Table(title="numba's cache: torchcal's compiled kernels")
    for col in ("family", "status", "seconds"):
        t.add_column(col, justify="right" if col == "seconds" else "left")
    for c in results:
        kernels = f"{len(c.missing)} kernel{'s' if len(c.missing) > 1 else ''}"
        status = f"failed: {c.error}" if c.error else f"compiled ({kernels})" if c.missing else "in the cache already"
        t.add_row(c.family, status, f"{c.seconds:.1f}" if c.seconds else "")
    _console().print(t)
    failed = [c.family for c in results if c.error]
    if failed:
        _console(stderr=True).print(f"error: {', '.join(failed)} not compiled (see the table)", markup=False)
        raise typer.Exit(1)


_gc_held = False
"""True while :func:`main` holds the garbage collector off for the command's imports (see :func:`_imports_done`)."""


def _imports_done() -> None:
    """The command's imports are in: keep their objects out of every later collection, and collect again.

    :func:`main` runs the imports with the collector off: torch, pandas, scipy and
    friends allocate about a million objects that live as long as the process, and
    every full collection walked them all (measured: ~1 s of the CPU time of a FANUC
    ``torchcal fit``, 0.2 s with them frozen). Acts only under :func:`main` (the
    console script), never when the app runs inside another program (tests).
    """
    global _gc_held
    if _gc_held:
        _gc_held = False
        gc.freeze()
        gc.enable()


def main(argv: list[str] | None = None) -> None:
    """Console entry point (``torchcal``); Ctrl-C outside a command (while parsing) is one line and status 130 too."""
    global _gc_held
    if gc.isenabled():
        gc.disable()  # until the command's imports are in: _imports_done
        _gc_held = True
    try:
        app(args=argv if argv is not None else sys.argv[1:], prog_name="torchcal")
    except KeyboardInterrupt as exc:
        _interrupted(exc)
        sys.exit(INTERRUPTED)
    finally:
        if _gc_held:
            _gc_held = False
            gc.enable()


if __name__ == "__main__":
    main()
