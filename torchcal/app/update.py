"""``torchcal update RUN_DIR NEW.csv --out NEW_RUN_DIR``: one online adaptive step on a run (Paper III (33)).

Loads a run's model, config and online state, adds the rows of NEW.csv with
:class:`torchcal.identify.online.OnlineCalibration` and writes a new run
directory that ``torchcal predict``, ``torchcal compensate`` and a further
``torchcal update`` accept::

    <new run>/
      config.yaml    the parent's config (noise, prior, solver, CSV contract), headed by a comment naming the parent
      versions.json  as for a fit
      run.log        what happened
      model.pt       the updated model (meta: parent, new data, strategy)
      online.pt      OnlineCalibration.state_dict(): the carried information (or the literal strategy's rows)
      fit.json       the update's solver summary, pinned entries, cost history
      update.json    lineage: parent, every ancestor, the new data file, rows so far, strategy, how the history was built
      metrics.json   residuals (mm) of the new rows and of the config's validation set, when readable; parent; update

Where the parent has no ``online.pt`` (a plain ``torchcal fit`` run), its
earlier rows are rebuilt: from the identification CSV its config names (their
joint errors solved at the fitted parameters, the fit's gauge from
``fit.json``), or, when that file is gone, from synthetic rows (stated in
run.log, update.json and metrics.json): quasi-random commands over the
controller range, as many poses and tools as the parent's metrics.json
reports, measured exactly by the parent model. That carries the right amount
of information about the right parameters, but not the parent's actual poses;
use it to keep a model moving, not for a result to publish.

Everything inside is SI; files are mm and degrees.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass, field
from pathlib import Path

import torch

from ..core import threads
from ..identify.online import STRATEGIES, OnlineCalibration, OnlineStep
from ..io.atomic import atomic_path, atomic_write_text
from .config import ConfigError, run_config, to_yaml
from ..io.rundir import (
    RunDirError,
    collect_versions,
    load_model,
    require_finished,
    make_run_dir,
    placed_note,
    read_json,
    run_log,
    save_model,
    write_json,
)
from ..core.measurements import Measurements
from ..identify.fit import frame_check
from .update_checks import check_new_data, held_backlash, rows_in_parent

log = logging.getLogger("torchcal")

ONLINE_FILE = "online.pt"
UPDATE_FILE = "update.json"
SYNTHETIC_SEED = 0


@dataclass
class UpdateResult:
    """What :func:`run_update` produced.

    run_dir: the new run directory; parent: the source run (absolute); model:
    the updated model; step: the :class:`OnlineStep`; metrics: what metrics.json
    holds (mm); table: Table 6 rows of the new rows and the validation set (mm,
    percent); history: how the parent's earlier rows entered ('online state',
    'identification data', 'synthetic'); files: name -> path; warnings.
    """

    run_dir: Path
    parent: Path
    model: object
    step: OnlineStep
    metrics: dict
    table: list[dict]
    history: str
    files: dict[str, Path] = field(default_factory=dict)
    warnings: list[str] = field(default_factory=list)


def is_sensor_run(cfg) -> bool:
    """Whether the run's config names a 6-DOF sensor (``sensor.kind``) rather than point targets."""
    return cfg.sensor.kind is not None


def read_update_data(cfg, model, path, noise=None, progress=None) -> tuple[Measurements, object | None]:
    """The rows of ``path`` in the run's CSV contract -> (Measurements SI, instrument or None).

    None stands for point targets on the rows' x, y, z (:class:`~torchcal.measure.PointTargets`
    with the run's tracker sigma): :func:`torchcal.io.csv.read_measurements`. A run whose config
    names a sensor (``sensor.kind``) reads the sensor contract and builds the instrument the fit
    used (:func:`torchcal.app.sensor.sensor_instrument`: STS rows outside the sensor's
    ranges are reported on ``progress`` and left out, as in the fit). This is the one place
    that knows which contract a run reads.
    """
    if is_sensor_run(cfg):
        from .sensor import read_sensor_set, sensor_instrument

        data = read_sensor_set(path, model.robot, model.device)
        instrument, data, _ = sensor_instrument(cfg, data, noise, progress)
        return data, instrument
    from ..io.csv import read_measurements

    return read_measurements(path, model.robot, int(model.tools.count)), None


def config_fixed(cfg) -> tuple[str, ...]:
    """Parameter groups the run's fit held fixed: a sensor rig's gravity unless the STS angles determine it."""
    if is_sensor_run(cfg) and (cfg.sensor.kind != "sts" or cfg.sensor.position_only):
        return ("gravity",)
    return ()


def _run_file(run_dir: Path, name: str) -> Path:
    return Path(run_dir) / name


def _noise_prior_options(cfg, model):
    from .fit import config_noise, config_prior, solver_options

    noise = config_noise(cfg, model.robot)
    opts = solver_options(cfg)
    method = opts.pop("method")
    return noise, config_prior(cfg), method, {**opts, "fixed": config_fixed(cfg)}


def _history_from_data(cfg, parent: Path, model, online: OnlineCalibration, notes: list[str], progress=None) -> str:
    """A plain fit run: its identification rows (or synthetic ones) as the first, already absorbed batch."""
    fit_json = _run_file(parent, "fit.json")
    pinned = read_json(fit_json).get("pinned_names") if fit_json.is_file() else None
    ident = cfg.data.identification
    if ident and Path(ident).is_file():
        from .common import DATA_HASH_FILE, file_sha256

        record = _run_file(parent, DATA_HASH_FILE)
        fitted = read_json(record).get("data.identification", {}) if record.is_file() else {}
        if fitted.get("sha256") and fitted["sha256"] != file_sha256(ident):
            # absorbing other rows than the fit used would count them twice or miss some
            raise RunDirError(f"{ident}: the parent run's identification file changed since the fit (sha256 recorded "
                              f"in {record} differs); restore the file the fit read, or refit with torchcal fit")
        data, instrument = read_update_data(cfg, model, ident, online.noise, progress)
        online.absorb(data, instrument, pinned=pinned)
        notes.append(f"parent has no {ONLINE_FILE}: its {len(data)} identification rows ({ident}) absorbed at the "
                     f"fitted parameters (joint errors solved per row)")
        return "identification data"
    if online.strategy == "literal" or is_sensor_run(cfg):
        need = "the literal strategy needs" if online.strategy == "literal" else "a sensor run's update needs"
        raise RunDirError(f"{parent}: no {ONLINE_FILE} and the identification data '{ident}' is not readable: "
                          f"{need} the earlier rows themselves"
                          + ("" if is_sensor_run(cfg) else "; use --strategy information"))
    data = synthetic_history(parent, model)
    online.absorb(data, None, v=torch.zeros_like(data.q), pinned=pinned)
    notes.append(f"parent has no {ONLINE_FILE} and its identification data '{ident}' is not readable: the earlier "
                 f"information is rebuilt from {len(data)} synthetic rows ({data.n_poses} quasi-random poses x "
                 f"{int(model.tools.count)} tools, measured exactly by the parent model); the poses are not the "
                 f"parent's, so the update is approximate")
    return "synthetic"


def synthetic_history(parent: Path, model) -> Measurements:
    """Stand-in rows for a parent whose data is gone: its pose and tool counts, quasi-random commands, exact points.

    The counts come from the parent's metrics.json (identification poses); the points are the
    model's own, so the rows sit at their optimum (residual and joint errors zero) and carry only
    information, no pull.
    """
    from ..sim.sampling import approach_directions, quasi_random_commands

    metrics = _run_file(parent, "metrics.json")
    try:
        poses = int(read_json(metrics)["sets"]["identification"]["poses"])
    except (OSError, KeyError, TypeError, ValueError):
        raise RunDirError(f"{parent}: no online state, no readable identification data and no identification pose "
                          f"count in {metrics}: nothing to rebuild the earlier information from") from None
    limits = model.command_limits
    q = quasi_random_commands(limits, poses, SYNTHETIC_SEED)
    s = approach_directions(q)
    T = int(model.tools.count)
    qq, ss = q.repeat(T, 1), s.repeat(T, 1)
    tool = torch.arange(T, device=q.device).repeat_interleave(poses)
    with torch.no_grad():
        xyz = model.points(qq, tool, ss)
    pose = torch.arange(poses, device=q.device).repeat(T)
    return Measurements(qq, tool, xyz, ss, pose, torch.arange(1, len(qq) + 1), True, f"{parent} (synthetic history)")


def load_online(parent: Path, cfg, model, strategy: str | None, notes: list[str], progress=None
                ) -> tuple[OnlineCalibration, str]:
    """The parent's online calibration: its state file, else rebuilt from its data (see the module)."""
    noise, prior, method, opts = _noise_prior_options(cfg, model)
    state_path = _run_file(parent, ONLINE_FILE)
    if state_path.is_file():
        try:
            state = torch.load(state_path, map_location="cpu", weights_only=True)
        except Exception as exc:  # a truncated or foreign file: say which file, not a pickle traceback
            raise RunDirError(f"{state_path}: not a readable online state ({type(exc).__name__}: {exc})") from None
        saved = state.get("strategy") if isinstance(state, dict) else None
        if strategy is not None and saved is not None and strategy != saved:
            raise ConfigError(f"--strategy {strategy}: the run {parent} continues the '{saved}' strategy ({state_path})")
        online = OnlineCalibration(model, noise, prior, strategy=saved or "information", method=method, **opts)
        try:
            online.load_state_dict(state, instrument=_stored_instrument(cfg, state, noise))
        except ValueError as exc:
            raise RunDirError(f"{state_path}: {exc}") from None
        return online, "online state"
    online = OnlineCalibration(model, noise, prior, strategy=strategy or "information", method=method, **opts)
    return online, _history_from_data(cfg, parent, model, online, notes, progress)


def _stored_instrument(cfg, state, noise):
    """The literal strategy's instrument for its stored rows where the state could not hold it (sensor runs)."""
    lit = state.get("literal") if isinstance(state, dict) else None
    if not lit or lit.get("instrument") is not None or not is_sensor_run(cfg):
        return None
    from ..identify.online import measurements_from_state
    from .sensor import sensor_instrument

    instrument, _, _ = sensor_instrument(cfg, measurements_from_state(lit["data"]), noise)
    return instrument


def _lineage(parent: Path) -> list[str]:
    path = _run_file(parent, UPDATE_FILE)
    earlier = read_json(path).get("lineage", []) if path.is_file() else []
    return list(earlier) + [str(parent)]


def _same_file(a, b) -> bool:
    """Whether two paths hold the same data: the same file, or byte-identical files (a copy)."""
    import filecmp

    try:
        return Path(a).resolve() == Path(b).resolve() or filecmp.cmp(a, b, shallow=False)
    except OSError:
        return False


def _evaluate(cfg, model, new: Measurements, progress, new_path=None) -> tuple[dict, list[dict]]:
    """Residual statistics of the new rows and of the config's validation set when readable (mm; sensors: and deg).
    A validation set that is the update's own data is not held out any more: said, and not reported as one."""
    sets = {"update": new}
    val = cfg.data.validation
    if val and new_path is not None and Path(val).is_file() and _same_file(val, new_path):
        progress.warn(f"the update's data are the config's validation set ({val}): the model has now been fitted "
                      "to them, so no held-out (validation) residual is reported; measure a new validation set")
    elif val and not Path(val).is_file():
        progress.warn(f"the config's validation set '{val}' is not readable: not evaluated")
    elif val:
        if is_sensor_run(cfg):
            from .sensor import read_sensor_set

            sets["validation"] = read_sensor_set(val, model.robot, model.device)
        else:
            from ..io.csv import read_measurements

            sets["validation"] = read_measurements(val, model.robot, int(model.tools.count)).to(model.device)
    if is_sensor_run(cfg):
        from .sensor import evaluate_pose_sets

        return evaluate_pose_sets(model, sets, progress)
    from .fit import evaluate, table6

    evaluations = {name.capitalize(): evaluate(model, d) for name, d in sets.items()}
    out = {name.lower(): {"rows": len(sets[name.lower()]), "poses": sets[name.lower()].n_poses,
                          "nominal": vars(ev["nominal_stats"]), "modeled": vars(ev["modeled_stats"]),
                          "decrease_percent": ev["decrease"]} for name, ev in evaluations.items()}
    for name, s in out.items():  # nominal robot -> the updated model, on each set (the file named)
        src = new_path if name == "update" else val
        progress.info(f"{name} ({Path(src).name if src else '?'}): mean nominal {s['nominal']['mean']:.4f} -> updated "
                      f"model {s['modeled']['mean']:.4f} mm, max {s['modeled']['max']:.4f} mm")
    return out, table6(evaluations)


@frame_check(quiet=True)  # the run says a far frame its own way (its nominal residual)
def run_update(run_dir, new_data, out, device=None, strategy: str | None = None, console=None,
               units_checked: bool = False) -> UpdateResult:
    """Add the rows of ``new_data`` (a CSV in the run's contract) to the run ``run_dir``; write the run ``out``.

    device: torch device (default the run config's); strategy: 'information' or
    'literal', for a parent without online state (otherwise it must match the
    parent's); console: a rich Console for progress. Raises RunDirError /
    DataError / ConfigError naming the folder, file or key, before anything is written.

    Example:
        >>> res = run_update("runs/fit", "batch2.csv", "runs/fit+batch2")      # doctest: +SKIP
        >>> res.step.rows, res.metrics["parent"]                                # doctest: +SKIP
        (825, '/abs/runs/fit')
    """
    if strategy is not None and strategy not in STRATEGIES:
        raise ConfigError(f"--strategy '{strategy}': choose from {', '.join(STRATEGIES)}")
    parent = Path(run_dir).resolve()
    if not parent.is_dir():
        raise RunDirError(f"{run_dir}: not a folder; give a run directory written by 'torchcal fit' or 'torchcal update'")
    cfg = run_config(parent)
    dev = torch.device(device) if device is not None else torch.device(cfg.device or "cpu")
    count = cfg.threads
    old_override = threads.get_override()
    if count:
        threads.set_threads(int(count))
    from ..io.progress_view import showing

    try:  # stages as progress tasks: a bar on a terminal, plain lines (and a heartbeat) elsewhere and in run.log
        with showing(console):
            return _run_update(parent, cfg, Path(new_data), Path(out), dev, strategy, console,
                               units_checked or bool(cfg.data.units_checked))
    finally:
        threads.set_threads(old_override)


def _run_update(parent: Path, cfg, new_path: Path, out: Path, dev, strategy, console,
                units_checked: bool = False) -> UpdateResult:
    from .fit import Progress

    progress = Progress(console)
    with progress.step(f"reading the run {parent} and {new_path}", quiet=True):
        require_finished(parent, "torchcal update")
        model = load_model(parent, device=dev)
        noise = _noise_prior_options(cfg, model)[0]
        new, instrument = read_update_data(cfg, model, new_path, noise, progress)  # a bad file fails before anything is written
        new = new.to(dev)
        if not units_checked:
            from ..io.unit_checks import check_units, units_note

            # the fit's unit-slip checks, named as such rather than as the 'misses by 600 mm' of another robot; a
            # sensor's positions are judged at the flange, as its fit judges them
            tools = model.tools().detach().cpu() if instrument is None else None
            note = units_note(new, model.robot, *check_units(new, model.robot, tools, new_path))
            if note:
                progress.warn(note)
        before, pred = check_new_data(model, new, new_path, is_sensor_run(cfg))
        from .common import moved_frame_note

        # an update would absorb a moved tracker into the robot's parameters
        note = moved_frame_note(pred, new.xyz.to(pred), "an update takes the parent's measurement frame: "
                                "measure from the parent's placement, or fit afresh (measurement_frame: estimate)")
        if note:
            progress.warn(f"{new_path}: {note}")
        repeated = rows_in_parent(cfg.data.identification, model, new, is_sensor_run(cfg))
        if repeated:
            shown = ", ".join(str(r) for r in repeated[:10]) + (" ..." if len(repeated) > 10 else "")
            progress.warn(f"{new_path}: {len(repeated)} row{'s' if len(repeated) > 1 else ''} ({shown}) repeat rows of "
                          f"the parent's identification file {cfg.data.identification} exactly: those measurements "
                          "would count twice; leave them out unless they really were measured again")
    notes: list[str] = []
    with progress.step("loading the parent's online state (or rebuilding it from its data)", quiet=True):
        online, history = load_online(parent, cfg, model, strategy, notes, progress)
    early = list(progress.warnings)  # said before the run log existed: repeated into it below
    run = make_run_dir(out)
    try:
        return _write_update(parent, cfg, new_path, run, new, instrument, online, history, notes, early, progress, dev,
                             before, placed_note(out, run))
    except KeyboardInterrupt as exc:
        exc.run_dir = run  # the CLI names the partial run directory
        raise


def _write_update(parent, cfg, new_path, run, new, instrument, online, history, notes, early, progress, dev,
                  before, placed=""):
    """Everything written into the new run directory, in order (config, versions, update, model, state, metrics)."""
    model = online.model
    files: dict[str, Path] = {}
    with run_log(run):
        for w in early:
            log.warning(w)
        files["config"] = run / "config.yaml"
        header = (f"# torchcal update: parent run {parent}\n# new data {new_path.resolve()}; the parent's config "
                  f"follows unchanged (its data.* name the parent's files)\n")
        atomic_write_text(files["config"], header + to_yaml(cfg))
        files["versions"] = write_json(run / "versions.json", {**collect_versions(dev), "run_dir": str(run)})
        from .common import DATA_HASH_FILE, file_sha256, input_hashes

        # the parent's inputs as they are now (update checked its identification file against the parent's record)
        # and the new rows, which a chained update reads as this run's
        hashes = {**input_hashes(cfg), "update.new": {"path": str(Path(new_path).resolve()), "sha256": file_sha256(new_path)}}
        files["data_hashes"] = write_json(run / DATA_HASH_FILE, hashes)
        progress.info(f"run directory {run}{placed}; parent {parent}")
        for note in notes:
            if history == "synthetic":
                progress.warn(note)
            else:
                progress.info(note)
        progress.info(f"earlier rows: {online.rows} in {online.batches} batch(es), from the parent's {history}; "
                      f"strategy '{online.strategy}'")
        # the parent's model on the new rows: how far the robot moved from its calibration
        progress.info(f"the parent's model on the new rows: mean {before.mean:.4f} mm, max {before.max:.4f} mm "
                      "(before the update)")
        parent_coverage = getattr(model, "coverage", None)  # the update replaces it with a widened one
        with progress.step(f"updating with {len(new)} rows of {new_path}"):
            step = online.update(new, instrument)
        progress.info(f"update: {step.result.message} after {step.result.nit} iterations, {step.seconds:.2f} s; "
                      f"{step.rows} rows so far")
        held = held_backlash(model, step.pinned, parent_coverage)
        if held:
            progress.warn(f"the backlash of {', '.join(held)} is held at the parent's value: the parent's data approached "
                          f"{'this joint' if len(held) == 1 else 'these joints'} from one direction only, so its fit "
                          "pinned it, and an update keeps the parent's pinned entries; with these rows both directions "
                          "are measured: fit all rows afresh (torchcal fit) to identify it")
        if not step.result.success:
            progress.warn("the solver did not converge; see fit.json")
        meta = {"parent": str(parent), "new_data": str(new_path.resolve()), "strategy": online.strategy}
        files["model"] = save_model(run, model, **meta)
        files["online"] = run / ONLINE_FILE
        with atomic_path(files["online"]) as tmp:
            torch.save(online.state_dict(), tmp)
        files["fit"] = write_json(run / "fit.json", {**step.result.summary(), "pinned_names": list(step.pinned),
                                                      "history": list(step.result.history)})
        lineage = _lineage(parent)
        update = {**meta, "lineage": lineage, "history": history, **step.summary()}
        files["update"] = write_json(run / UPDATE_FILE, update)
        with progress.step("evaluating the residuals", quiet=True):
            sets, table = _evaluate(cfg, model, new, progress, new_path)
        metrics = {"units": "mm, deg, percent" if is_sensor_run(cfg) else "mm, percent", "parent": str(parent),
                   "lineage": lineage, "history": history, "update": step.summary(), "sets": sets, "table6": table,
                   "parent_model_on_new_rows_mm": vars(before),
                   "warnings": progress.warnings}
        files["metrics"] = write_json(run / "metrics.json", metrics)
        progress.info(f"done: {run}")
    return UpdateResult(run, parent, model, step, metrics, table, history, files, progress.warnings)


__all__ = ["ONLINE_FILE", "UPDATE_FILE", "UpdateResult", "config_fixed", "is_sensor_run", "load_online",
           "read_update_data", "run_update", "synthetic_history"]
