"""What both fit pipelines share (:mod:`torchcal.app.fit`, point targets; :mod:`torchcal.app.sensor`,
Paper III's sensor runs): config -> objects (noise, prior, solver options, model options), the run result,
the run directory's preamble files, Table 6 rows, progress and warning collection.

Moved here unchanged from :mod:`torchcal.app.fit` (which re-exports every name) so that neither pipeline
imports the other's internals: ``pipeline`` -> ``pipeline_sensor`` -> ``pipeline_common`` (the layers of
``[tool.importlinter]`` in pyproject.toml).
"""

from __future__ import annotations

import logging
import time
from contextlib import contextmanager
from dataclasses import dataclass, field
from pathlib import Path
from typing import Mapping

import torch


from ..core import units
from ..analysis.stats import ResidualStats, percent_decrease
from ..identify import FitResult, NoiseModel, Prior
from ..io.atomic import atomic_write_text
from .config import ConfigError, to_yaml
from ..io.rundir import collect_versions, file_sha256, read_json, write_json
from ..models.robot import RobotModel
from ..core.progress import task as progress_task

log = logging.getLogger("torchcal")

STAT_KEYS = ("mean", "max", "gamma99")

def worse_than_nominal(modeled: float, nominal: float) -> bool:
    """Whether a fitted model's mean residual is worse than the nominal robot's, beyond rounding (point and sensor
    runs alike: a calibration that makes the robot worse is no calibration, whatever the solver said)."""
    return modeled > 1.001 * nominal + 1e-6


NOMINAL_IMPLAUSIBLE_MM = 20.0
"""A mean nominal residual above this (mm) is beyond any plausible calibration error: the pipeline warns
that the robot description (URDF, joint map, tools, frame) may not describe the measured robot (point runs,
sensor runs and each unit of a fleet)."""


@dataclass
class RunResult:
    """What a fit run produced.

    run_dir: the run directory; model: the identified model (on the config's
    device); fit: the solver's result; metrics: what metrics.json holds (mm);
    table: Table 6 rows (mm, percent); compensation_table: Table 7 rows or
    None; orders: Chebyshev order per joint; selection: the order search
    (model.order: auto) or None; files: name -> path of everything written;
    warnings: see below.
    """

    run_dir: Path
    model: RobotModel
    fit: FitResult
    metrics: dict
    table: list[dict]
    compensation_table: list[dict] | None
    orders: list[int]
    selection: object | None = None
    files: dict[str, Path] = field(default_factory=dict)
    warnings: list[str] = field(default_factory=list)
    """What the run warned about (also in run.log and metrics.json): data that cannot determine the model,
    an implausible nominal residual, a CSV read as a European export, ..."""


# --------------------------------------------------------------- config -> objects
def joint_variance_source(cfg, robot) -> str:
    """Where the joint variances of :func:`config_noise` come from, for the run log ("joint variances: <source>")."""
    if cfg.noise.joint_var_fwd is not None:
        where = cfg.config_file or "the config"
        return f"noise.joint_var_fwd / joint_var_bwd of {where}"
    if robot.repeatability is not None:
        return f"robot '{robot.name}' repeatability ({robot.repeatability.source})"
    return "none"


def config_noise(cfg, robot, label: str | None = None) -> NoiseModel:
    """NoiseModel (SI) from noise.sigma_m (mm) and the joint variances (deg², mm² for prismatic joints).

    The joint variances are the config's ``noise.joint_var_fwd`` / ``joint_var_bwd`` when given,
    else the robot's own ``repeatability:`` (its YAML); with neither, a ConfigError naming the keys.
    The tracker sigma is the config's (default 0.005 mm): a property of the tracker, not of the robot.

    Example:
        >>> from torchcal.app.config import make_config
        >>> from torchcal.kinematics import load_robot
        >>> cfg = make_config({"robot": "fanuc_lrmate200i", "tools": [[0, 0, 100]], "data": {"identification": "x.csv"}})
        >>> noise = config_noise(cfg, load_robot("fanuc_lrmate200i"))   # the robot's Table 5 variances
        >>> round(noise.sigma_m * 1e6, 3), noise.joint_var_fwd.shape
        (5.0, torch.Size([6]))
    """
    label = label or cfg.config_file or "config"
    sigma = float(cfg.noise.sigma_m)
    if cfg.noise.joint_var_fwd is not None and cfg.noise.joint_var_bwd is not None:
        return NoiseModel.from_file_units(sigma, list(cfg.noise.joint_var_fwd), list(cfg.noise.joint_var_bwd),
                                          robot.joint_map.prismatic.cpu())
    if robot.repeatability is None:
        raise ConfigError(
            f"{label}: keys 'noise.joint_var_fwd' and 'noise.joint_var_bwd' are not set and robot '{robot.name}' "
            f"({robot.source or robot.name}) has no 'repeatability:' (joint variances, deg²): give one variance per "
            f"joint ({robot.joint_map.n}) in the config, e.g. noise.joint_var_fwd=[...] noise.joint_var_bwd=[...], "
            "or a 'repeatability: {joint_var_fwd, joint_var_bwd, source}' in the robot's YAML")
    return NoiseModel.from_robot(robot, sigma_m=units.mm_to_m(sigma))


def config_prior(cfg) -> Prior | None:
    """Prior (SI) from prior.* (deg, mm), or None when prior.enabled is false."""
    p = cfg.prior
    if not p.enabled:
        return None
    backlash = p.backlash_deg
    compliance = p.compliance_deg
    extra = {} if compliance is None else {"compliance": units.deg_to_rad(compliance)}
    return Prior(rotation=units.deg_to_rad(p.rotation_deg), translation=units.mm_to_m(p.translation_mm),
                 frame_rotation=units.deg_to_rad(p.frame_rotation_deg), frame_translation=units.mm_to_m(p.frame_translation_mm),
                 backlash=None if backlash is None else units.deg_to_rad(backlash), **extra)


def config_orders(cfg, n: int) -> list[int]:
    """model.order as n per-joint Chebyshev orders (one int for every joint, or the list); not for 'auto', which
    the order search resolves."""
    order = cfg.model.order
    return [int(order)] * n if isinstance(order, int) else [int(o) for o in order]


def config_backlash(cfg):
    """model.backlash as RobotModel takes it: None (off), True, an int order or a per-joint list."""
    b = cfg.model.backlash
    if isinstance(b, bool):
        return True if b else None
    return list(b) if not isinstance(b, int) else int(b)


def missing_directions_note(source, n: int) -> str:
    """Why a file without approach directions misleads a backlash model: every joint's direction is taken as 0."""
    return (f"{source}: no dir1..dir{n} columns: the model's backlash terms are left out (direction 0 for every "
            f"joint), so each row is off by the lost motion; give each row's approach directions (+1 / -1)")


def solver_options(cfg) -> dict:
    """Keyword arguments for :func:`torchcal.identify.fit` from solver.*."""
    opts = {"method": cfg.solver.method, "ftol": float(cfg.solver.ftol)}
    if cfg.solver.max_iter is not None:
        opts["max_iter"] = int(cfg.solver.max_iter)
    return opts


def config_compliance(cfg):
    """model.compliance as RobotModel takes it: False, True, 'auto', 'gravity', 'functions' or a plain dict."""
    c = cfg.model.compliance
    return dict(c) if isinstance(c, Mapping) else c


def config_error_variable(cfg):
    """model.error_variable as RobotModel takes it: None (the robot's), 'command', 'joint' or a per-joint list."""
    ev = cfg.model.error_variable
    return None if ev is None else (str(ev) if isinstance(ev, str) else [str(e) for e in ev])


def stats_row(set_name: str, label: str, s: ResidualStats, ref: ResidualStats | None) -> dict:
    row = {"set": set_name, "residual": label, "count": s.count}
    for k in STAT_KEYS:
        row[k] = getattr(s, k)
        row[f"{k}_decrease"] = None if ref is None else percent_decrease(getattr(ref, k), getattr(s, k))
    return row


# ------------------------------------------------------------------ reporting
class Progress:
    """Log lines to the run log and, when a rich console is given, to the console too; stages as progress tasks.

    Every :meth:`step` is a :func:`torchcal.core.progress.task`: the installed
    :class:`torchcal.io.progress_view.ProgressView` shows it (a bar on a terminal,
    plain lines with a heartbeat elsewhere and in run.log), together with the
    library's own tasks inside it. warnings: every :meth:`warn` text, in order
    (they also go to ``metrics.json`` and the CLI's summary).
    """

    QUIET_STEP_S = 2.0
    """A quiet step says 'done in' only when it took at least this long."""

    def __init__(self, console=None):
        self.console = console
        self.task = None  # the innermost running step's progress.Task
        self.warnings: list[str] = []

    def _show(self, text: str, markup: bool = True) -> None:
        if self.console is None:
            return
        from ..io.progress_view import current_view

        view = current_view()
        if view is not None and view.console is self.console:
            view.message(text, markup=markup)  # never in the middle of a progress line
        else:
            self.console.log(text, markup=markup)

    def info(self, text: str) -> None:
        log.info(text)
        self._show(text)

    def warn(self, text: str) -> None:
        self.warnings.append(text)
        log.warning(text)
        self._show(f"warning: {text}", markup=False)

    def update(self, text: str) -> None:
        """A note on the running step (its bar, its next progress line)."""
        log.debug(text)
        if self.task is not None:
            self.task.set_note(text)

    @contextmanager
    def step(self, text: str, total: int | None = None, quiet: bool = False):
        """A stage: logged when it starts and with its duration when it ends, a progress task in between.

        total: items, when the stage advances ``self.task`` itself; quiet: no start line, and the
        'done in' line only when it took :data:`QUIET_STEP_S` or longer (short bookkeeping stages).
        """
        if not quiet:
            log.info(text)
        t0 = time.perf_counter()
        with progress_task(text, total) as t:
            outer, self.task = self.task, t
            try:
                yield self
            finally:
                self.task = outer
        dt = time.perf_counter() - t0
        if not quiet or dt >= self.QUIET_STEP_S:
            self.info(f"{text} done in {dt:.1f} s")


@contextmanager
def collect_warnings(into: list[str], name: str = "torchcal"):
    """Keep the WARNING records of the ``torchcal`` logger emitted in the block (e.g. a CSV read as a
    European export) in ``into``, to be replayed into the run log once it exists."""

    class _Keep(logging.Handler):
        def emit(self, record):
            into.append(record.getMessage())

    logger = logging.getLogger(name)
    handler = _Keep(logging.WARNING)
    logger.addHandler(handler)
    try:
        yield into
    finally:
        logger.removeHandler(handler)


DATA_HASH_FILE = "data_hashes.json"
"""In a fit's run directory: {config key: {path, sha256}} of the data files the fit read (``torchcal update``
re-reads the identification file and refuses one that changed since)."""




def fitted_hash(run_dir) -> str | None:
    """The sha256 of the identification file a run (or a fleet unit's folder) was fitted on, from its
    :data:`DATA_HASH_FILE`; None where it is not recorded or cannot be read."""
    try:
        return (read_json(Path(run_dir) / DATA_HASH_FILE).get("data.identification") or {}).get("sha256")
    except (OSError, ValueError, AttributeError):
        return None


def write_preamble_files(run_dir: Path, cfg, device, files: dict) -> None:
    """config.yaml (the resolved config), versions.json and data_hashes.json: what every run directory starts with."""
    files["config"] = run_dir / "config.yaml"
    atomic_write_text(files["config"], to_yaml(cfg))
    # the folder written (config.yaml's 'out' is the one asked for: a second run there went to runs-2)
    files["versions"] = write_json(run_dir / "versions.json", {**collect_versions(device), "run_dir": str(run_dir)})
    files["data_hashes"] = write_json(run_dir / DATA_HASH_FILE, input_hashes(cfg))


def _input_files(cfg) -> dict[str, str]:
    """The files a run reads, by config key: its data, the truth its compensation check measures on (Table 7's
    'Compensated' row is the truth's), and the robot when given as a file."""
    out = {f"data.{key}": getattr(cfg.data, key) for key in ("identification", "validation", "truth")}
    out["robot"] = cfg.robot
    return {k: str(p) for k, p in out.items() if p and Path(str(p)).is_file()}


def input_hashes(cfg) -> dict:
    """{key: {'path', 'sha256'}} of every input file of ``cfg`` (:func:`_input_files`): data_hashes.json."""
    return {key: {"path": p, "sha256": file_sha256(p)} for key, p in _input_files(cfg).items()}


def changed_inputs(cfg) -> list[str]:
    """Warnings for a config that is a run directory's own config.yaml (a re-run): each input whose file differs
    from what that run recorded in its data_hashes.json. The re-run fitted an edited file without a word, and
    its parameters moved by as much as the edit."""
    if not cfg.config_file:
        return []
    recorded_file = Path(cfg.config_file).parent / DATA_HASH_FILE
    if not recorded_file.is_file():
        return []
    try:
        recorded = read_json(recorded_file)
    except (OSError, ValueError):
        return []
    out = []
    for key, p in _input_files(cfg).items():
        was = recorded.get(key) if isinstance(recorded, dict) else None
        if not (isinstance(was, dict) and was.get("sha256")):
            continue
        now = file_sha256(p)
        if was["sha256"] != now:
            out.append(f"{key} ({p}) has changed since the run {recorded_file.parent} recorded it (sha256 "
                       f"{was['sha256'][:12]}..., now {now[:12]}...): this re-run does not reproduce it; "
                       "restore the file to reproduce the run, or give the new file its own config")
    return out



def write_run_report(run_dir: Path, files: dict, progress: Progress) -> None:
    """report.html (:func:`torchcal.report.write_report`) of a finished run; a report that cannot be written is a
    warning, never the loss of the run it describes."""
    from ..report import write_report

    try:
        files["report"] = write_report(run_dir)
    except Exception as exc:  # noqa: BLE001 - the run's files are complete; say why the report is missing
        progress.warn(f"{run_dir}: report.html not written ({type(exc).__name__}: {exc}); "
                      f"run `torchcal report {run_dir}` to retry")


def placement_text(summary: dict) -> str:
    """'robot base at xyz x, y, z mm, rpy r, p, y deg' from an alignment's summary (alignment.json)."""
    return ("robot base at xyz " + ", ".join(f"{v:.3f}" for v in summary["frame"]["xyz_mm"]) + " mm, rpy "
            + ", ".join(f"{v:.4f}" for v in summary["frame"]["rpy_deg"]) + " deg")


def tools_text(tools_mm) -> str:
    """'[x, y, z]; [x, y, z]' of tool vectors in mm ((T, 3) nested lists)."""
    return "; ".join("[" + ", ".join(f"{v:.3f}" for v in t) + "]" for t in tools_mm)


def moved_frame_note(pred: torch.Tensor, measured: torch.Tensor, advice: str) -> str | None:
    """Where one rigid motion of the predictions (N, 3) m explains most of their miss of ``measured`` (N, 3) m (the
    mean falls more than 3x and by more than 0.1 mm): a note saying so, ending in ``advice`` (a moved tracker reads
    as a worse robot); else None."""
    from ..kinematics.transforms import kabsch

    if pred.shape[0] < 3:
        return None
    before = float((measured - pred).norm(dim=-1).mean())
    Y, t = kabsch(pred, measured)
    after = float((measured - (pred @ Y.T + t)).norm(dim=-1).mean())
    if before <= max(3.0 * after, units.mm_to_m(0.1)):
        return None
    return (f"the model's residual falls from {units.m_to_mm(before):.3f} to {units.m_to_mm(after):.3f} mm (mean) "
            f"once its predictions are moved by one rigid motion: did the tracker stand elsewhere? {advice}")


def failed_row(exc: BaseException | str, **keys) -> dict:
    """A results row of a unit or cell that could not be fitted: ``keys`` (its name) with status 'failed' and the
    reason, an exception as 'Type: message' (what fleet and sweep tables and their summaries read)."""
    why = exc if isinstance(exc, str) else f"{type(exc).__name__}: {exc}"
    return {**keys, "status": "failed", "reason": why}


__all__ = [
    "failed_row",
    "moved_frame_note",
    "write_run_report",
    "STAT_KEYS",
    "RunResult",
    "config_backlash",
    "missing_directions_note",
    "config_compliance",
    "config_error_variable",
    "config_noise",
    "config_orders",
    "config_prior",
    "joint_variance_source",
    "placement_text",
    "solver_options",
    "tools_text",
    "write_preamble_files",
    "changed_inputs",
    "input_hashes",
]
