"""``torchcal``: calibrate from CSV files, predict, compensate, simulate.

Thin on purpose: parse, call the library, write files. Every file and value
on this side is in mm and degrees (see :mod:`torchcal.io.csv`).

    torchcal simulate data/fanuc                 # simulated FANUC data + ready fit.yaml
    torchcal fit data/fanuc/fit.yaml model.order=4
    torchcal predict RUN_DIR commands.csv predicted.csv
    torchcal compensate RUN_DIR targets.csv compensated.csv

Bad inputs (data, robot, config, run directory) print one message naming the
file, row / key and column, and exit with status 2.
"""

from __future__ import annotations

import sys
from contextlib import contextmanager
from pathlib import Path
from typing import Annotated, Optional

import typer
from rich.console import Console
from rich.table import Table

app = typer.Typer(
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


def _user_error_types() -> tuple[type[BaseException], ...]:
    from .io.config import ConfigError
    from .io.csv import DataError
    from .io.rundir import RunDirError
    from .io.truth import TruthError
    from .kinematics import URDFError

    # unwritable or misnamed output paths are the user's to fix too; other OSErrors stay tracebacks (bugs)
    # NotImplementedError: a documented limitation, not a crash
    return (DataError, URDFError, ConfigError, RunDirError, TruthError, PermissionError, IsADirectoryError,
            NotADirectoryError, NotImplementedError)


@contextmanager
def _user_errors():
    """Turn bad-input exceptions into one message on stderr and exit status 2 (no traceback)."""
    try:
        yield
    except _user_error_types() as exc:
        # markup=False: messages quote file contents and lists, which must not be read as rich markup
        _console(stderr=True).print(f"error: {exc}", markup=False)
        raise typer.Exit(USER_ERROR) from None


def _device(name: str):
    """A usable torch device, or a ConfigError naming the option."""
    import torch

    from .io.config import ConfigError

    try:
        dev = torch.device(name)
    except (RuntimeError, ValueError) as exc:
        raise ConfigError(f"--device '{name}' is not a torch device ({exc})") from None
    if dev.type == "cuda" and not torch.cuda.is_available():
        raise ConfigError(f"--device '{name}': CUDA is not available here (use --device cpu)")
    return dev


def _version_callback(value: bool):
    if value:
        from importlib.metadata import version

        typer.echo(f"torchcal {version('torchcal')}")
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
    t = Table(title=title, caption="values in mm; % = percent decrease against the nominal residual")
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
    config: Annotated[Path, typer.Argument(help="YAML config (see torchcal.io.config; `torchcal simulate` writes one).")],
    overrides: Annotated[Optional[list[str]], typer.Argument(
        help="Dotted overrides, e.g. model.order=4 data.validation=val.csv solver.method=lbfgs.")] = None,
    quiet: Annotated[bool, typer.Option("--quiet", "-q", help="No progress output.")] = False,
    dry_run: Annotated[bool, typer.Option("--dry-run", help="Print the resolved config (overrides applied) and stop.")] = False,
):
    """Identify a model from a config and write a run directory (model, metrics, plots, log)."""
    with _user_errors():
        from .io.config import load_config, to_yaml
        from .pipeline import run_fit

        cfg = load_config(config, overrides or [])
        if dry_run:
            typer.echo(to_yaml(cfg), nl=False)
            return
        result = run_fit(cfg, console=None if quiet else _console(stderr=True))
    out = _console()
    out.print(results_table(result.table, "Residuals (Paper II, Table 6 layout)"))
    if result.compensation_table is not None:
        out.print(results_table(result.compensation_table, "Compensation on the simulated robot (Paper II, Table 7 layout)"))
        flagged = result.metrics["compensation"]["flagged"]
        if flagged:
            out.print(f"warning: {flagged} validation commands flagged (not converged or outside the joint range)", markup=False)
    if not result.fit.success:
        out.print(f"warning: the solver stopped without converging: {result.fit.message}", markup=False)
    # plain echo: a long path must stay on one line for scripts that read it
    typer.echo(f"run directory: {result.run_dir}")


# --------------------------------------------------------------------- predict
@app.command("predict")
def predict_cmd(
    run_dir: Annotated[Path, typer.Argument(help="Run directory written by `torchcal fit`.")],
    input: Annotated[Path, typer.Argument(help="CSV with tool, q1..qN [, dir1..dirN] (deg / mm); other columns are kept.")],
    output: Annotated[Path, typer.Argument(help="CSV to write: the same rows with x, y, z predicted (mm, measurement frame).")],
    device: Annotated[str, typer.Option(help="torch device.")] = "cpu",
):
    """Predict measured points x, y, z (mm) for joint commands with an identified model."""
    import torch

    from .io.csv import points_to_file, read_table, write_table
    from .io.rundir import load_model

    with _user_errors():
        model = load_model(run_dir, device=_device(device))
        data, df = read_table(input, model.robot, model.tools.count, require_xyz=False)
        data = data.to(model.device)
        with torch.no_grad():
            p = model.points(data.q, data.tool, data.direction if data.has_direction else None)
        mm = points_to_file(p)
        out = df.copy()
        for i, c in enumerate(("x", "y", "z")):
            out[c] = mm[:, i]  # replaces measured values if the file had them, else appends the column
        write_table(output, out)
    typer.echo(f"predicted {len(df)} rows -> {output}")


# ------------------------------------------------------------------ compensate
@app.command("compensate")
def compensate_cmd(
    run_dir: Annotated[Path, typer.Argument(help="Run directory written by `torchcal fit`.")],
    input: Annotated[Path, typer.Argument(help="CSV with nominal commands q1..qN [, dir1..dirN] (deg / mm); other columns are kept.")],
    output: Annotated[Path, typer.Argument(help="CSV to write: q1..qN compensated (deg / mm) plus converged, iterations, within_limits.")],
    tol_deg: Annotated[Optional[float], typer.Option(help="Newton tolerance on |dq| (deg); default: the run's compensation.tol_deg.")] = None,
    max_iter: Annotated[Optional[int], typer.Option(help="Newton iteration limit; default: the run's compensation.max_iter.")] = None,
    device: Annotated[str, typer.Option(help="torch device.")] = "cpu",
):
    """Compensated joint commands: where to send the robot so that it reaches the nominal flange pose (Paper II (46)-(52)).

    Rows that do not converge or leave the controller's joint range are
    flagged (converged / within_limits = false), never dropped.
    """
    from .io.csv import joint_columns, joints_to_file, read_table, write_table
    from .io.rundir import load_model

    with _user_errors():
        model = load_model(run_dir, device=_device(device))
        robot = model.robot
        data, df = read_table(input, robot, None, require_xyz=False, require_pose=False)
        data = data.to(model.device)
        options = _compensation_options(run_dir, tol_deg, max_iter)
        res = _compensate(model, data, options)
        within = res.within_limits
        q_file = joints_to_file(res.q, robot)
        out = df.copy()
        for i, c in enumerate(joint_columns(robot.joint_map.n)):
            out[c] = q_file[:, i]  # every row kept, in input order; failures are marked below
        out["converged"] = res.converged.cpu().numpy()
        out["iterations"] = res.iterations.cpu().numpy()
        out["within_limits"] = within.cpu().numpy()
        write_table(output, out)
    flagged = ~res.converged | ~within
    n_flag = int(flagged.sum())
    typer.echo(f"compensated {len(df)} commands -> {output}")
    if n_flag:
        _console(stderr=True).print(
            f"warning: {n_flag} of {len(df)} commands flagged ({int((~res.converged).sum())} did not converge, "
            f"{int((~within).sum())} outside the controller range); they are kept, marked in 'converged' / 'within_limits'",
            markup=False)
    else:
        typer.echo("0 commands flagged")


def _compensation_options(run_dir: Path, tol_deg: float | None, max_iter: int | None) -> dict:
    """Tolerance and iteration limit: the command line, else the run's config, else compensate()'s defaults."""
    from .io.rundir import load_run_config
    from .pipeline import compensation_kwargs

    try:
        comp = load_run_config(run_dir).get("compensation", None) or {}
    except Exception:  # a run folder without (or with an older) config.yaml still compensates
        comp = {}
    return compensation_kwargs(tol_deg if tol_deg is not None else comp.get("tol_deg"),
                               max_iter if max_iter is not None else comp.get("max_iter"))


def _compensate(model, data, options):
    from .compensate import compensate

    return compensate(model, data.q, data.direction if data.has_direction else None, **options)


# -------------------------------------------------------------------- simulate
def default_joint_variances(n: int) -> tuple[list[float], list[float]]:
    """Joint variances (deg²) for simulated data: Paper II Table 5 for 6 joints, else its median for every joint."""
    from .identify import PAPER2_JOINT_VAR_BWD, PAPER2_JOINT_VAR_FWD

    if n == len(PAPER2_JOINT_VAR_FWD):
        return list(PAPER2_JOINT_VAR_FWD), list(PAPER2_JOINT_VAR_BWD)
    med_f = sorted(PAPER2_JOINT_VAR_FWD)[len(PAPER2_JOINT_VAR_FWD) // 2]
    med_b = sorted(PAPER2_JOINT_VAR_BWD)[len(PAPER2_JOINT_VAR_BWD) // 2]
    return [med_f] * n, [med_b] * n


def simulate_dataset(out_dir, robot: str = "fanuc_lrmate200i", identification: int = 250, validation: int = 300,
                     validation_tool: int = 2, seed: int = 0, order: int = 6, force: bool = False) -> dict[str, Path]:
    """Write simulated measurements in the CSV contract plus truth.json and a ready-to-run fit.yaml.

    Paper II's protocol (5.2, 5.5): quasi-random commands over the controller
    range, each identification pose measured with all three tools of Table 4,
    disjoint validation commands measured with ``validation_tool``; tracker
    sigma 0.005 mm and Table 5 joint variances. The truth is Paper II's FANUC
    (:meth:`TruthRobot.fanuc_paper2`) for the bundled FANUC, else
    :meth:`TruthRobot.random`. -> name -> path of the files written.
    """
    import torch
    import yaml

    from . import units
    from .identify import NoiseModel
    from .io.config import ConfigError
    from .io.csv import write_measurements
    from .io.truth import save_truth
    from .kinematics import load_robot
    from .sim import TruthRobot, quasi_random_commands, simulate

    out_dir = Path(out_dir)
    names = {"identification": "identification.csv", "validation": "validation.csv", "truth": "truth.json", "config": "fit.yaml"}
    existing = [n for n in names.values() if (out_dir / n).exists()]
    if existing and not force:
        raise ConfigError(f"{out_dir}: already holds {existing}; choose another folder or pass --force to overwrite")
    if identification < 1 or validation < 0:
        raise ConfigError(f"--identification must be >= 1 and --validation >= 0 (got {identification}, {validation})")
    tools_mm = PAPER2_TOOLS_MM
    if not 0 <= validation_tool < len(tools_mm):
        raise ConfigError(f"--validation-tool {validation_tool}: tools are 0..{len(tools_mm) - 1} (Paper II Table 4)")
    rob = load_robot(robot)
    n = rob.joint_map.n
    tools_m = units.mm_to_m(torch.tensor(tools_mm, dtype=torch.float64))
    kind = "fanuc_paper2" if rob.name == "fanuc_lrmate200i" and n == 6 else "random"
    # fit.yaml and truth.json name a robot file absolutely: they are read from another folder
    robot_spec = str(Path(rob.source).resolve()) if Path(rob.source).suffix else (rob.source or rob.name)
    truth = TruthRobot.fanuc_paper2(rob, tools_m, seed) if kind == "fanuc_paper2" else TruthRobot.random(rob, tools_m, seed)
    var_f, var_b = default_joint_variances(n)
    sigma_mm = 0.005
    noise = NoiseModel.from_file_units(sigma_mm, var_f, var_b, rob.joint_map.prismatic)
    limits = rob.joint_map.limits
    # one scrambled sequence: validation continues where identification stopped, so the sets are disjoint
    q_id = quasi_random_commands(limits, identification, seed)
    ident = simulate(truth, q_id, list(range(len(tools_mm))), noise, seed)
    out_dir.mkdir(parents=True, exist_ok=True)
    paths = {"identification": write_measurements(out_dir / names["identification"], ident, rob)}
    if validation:
        q_val = quasi_random_commands(limits, validation, seed, skip=identification)
        val = simulate(truth, q_val, [validation_tool], noise, seed + 1)
        paths["validation"] = write_measurements(out_dir / names["validation"], val, rob)
    paths["truth"] = save_truth(out_dir / names["truth"], truth, kind, seed, noise, robot_spec=robot_spec)
    cfg = {
        "robot": robot_spec,
        "tools": tools_mm,
        "data": {"identification": names["identification"], "validation": names["validation"] if validation else None,
                 "truth": names["truth"] if validation else None},
        "model": {"order": order, "backlash": True},
        "noise": {"sigma_m": sigma_mm, "joint_var_fwd": var_f, "joint_var_bwd": var_b},
        "seed": seed,
        "out": "runs",
    }
    header = (f"# Simulated '{rob.name}' data written by `torchcal simulate` (truth: {kind}, seed {seed}).\n"
              f"# Run:  torchcal fit {out_dir / names['config']}  [key=value ...]\n"
              "# Units: mm, deg, deg^2. Relative paths resolve against this file's folder.\n"
              "# 'data.truth' enables the compensation check on the simulated robot (Paper II Table 7, Fig. 16).\n")
    (out_dir / names["config"]).write_text(header + yaml.safe_dump(cfg, sort_keys=False, default_flow_style=None), encoding="utf-8")
    paths["config"] = out_dir / names["config"]
    return paths


@app.command("simulate")
def simulate_cmd(
    out_dir: Annotated[Path, typer.Argument(help="Folder for identification.csv, validation.csv, truth.json and fit.yaml.")],
    robot: Annotated[str, typer.Option(help="Bundled robot name, joint-map YAML or URDF.")] = "fanuc_lrmate200i",
    identification: Annotated[int, typer.Option(help="Identification poses (each measured with all 3 tools).")] = 250,
    validation: Annotated[int, typer.Option(help="Validation poses (0: none).")] = 300,
    validation_tool: Annotated[int, typer.Option(help="Tool (0-based) the validation set is measured with.")] = 2,
    seed: Annotated[int, typer.Option(help="Seed of the truth robot, the commands and the noise.")] = 0,
    order: Annotated[int, typer.Option(help="model.order written into fit.yaml.")] = 6,
    force: Annotated[bool, typer.Option("--force", help="Overwrite files already in OUT_DIR.")] = False,
):
    """Simulated measurements of a robot with known errors (Paper II's protocol) and a ready-to-run fit.yaml."""
    with _user_errors():
        paths = simulate_dataset(out_dir, robot, identification, validation, validation_tool, seed, order, force)
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
):
    """Convert laser-tracker exports (whitespace / comma separated, one row per pose) into the measurement CSV.

    Approach directions follow the commanded pose order; 0 0 0 rows are failed
    readings (that reflector's row dropped, reported); base reflectors give
    the per-pose drift (checked against the threshold, or corrected).
    """
    from .io.csv import write_table
    from .io.tracker import import_tracker
    from .kinematics import load_robot

    with _user_errors():
        rob = load_robot(robot) if robot else None
        res = import_tracker(joints, list(target), list(base or []), rob, drift_threshold_mm, correct_drift, outlier_mm)
        write_table(output, res.table)
    out = _console()
    out.print(res.summary_table())
    for line in res.report:
        out.print(line, markup=False)
    typer.echo(f"wrote {len(res.table)} rows -> {output}")


def main(argv: list[str] | None = None) -> None:
    """Console entry point (``torchcal``)."""
    app(args=argv if argv is not None else sys.argv[1:], prog_name="torchcal")


if __name__ == "__main__":
    main()
