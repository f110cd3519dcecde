"""Run directories: everything one fit produced, reloadable, like a training run.

Layout written by :func:`torchcal.app.fit.run_fit`::

    <run>/
      config.yaml      the fully resolved config (absolute paths, every default)
      versions.json    python, platform, torchcal + dependency versions, git commit, device
      run.log          what happened, with timestamps (also when a step failed); long stages add a progress
                       line (stage, k/N, elapsed, ETA) at least every 5 s (torchcal.io.progress_view)
      model.pt         RobotModel.spec() + state_dict; reload with load_model(<run>)
      fit.json         FitResult.summary(), pinned (gauge-fixed) parameter names, cost history
      orders.json      order selection table (model.order: auto only)
      metrics.json     residual statistics in mm (Table 6 layout; Table 7 with a truth)
      residuals.csv    per-row nominal and modeled residuals (mm) of every data set
      plots/*.png      Figure 12 (joint_errors), 13 (distribution_*), 14-15 (residuals_*),
                       16 (compensation_validation, with a truth)

Where it goes (:func:`make_run_dir`): ``out`` itself when it does not exist or
is an empty folder; ``out-2``, ``out-3``, ... beside it when ``out`` already holds
a run; a fresh ``<out>/<YYYYmmdd-HHMMSS>`` when ``out`` is a folder of other
things (e.g. earlier runs). Re-running a config never overwrites an earlier run,
never nests inside one, and never fails for it.
"""

from __future__ import annotations

import json
import logging
import math
from contextlib import contextmanager
from datetime import datetime
from pathlib import Path

import torch

from ..core.exceptions import TorchcalError
from . import yamlio
from .provenance import collect_versions, file_sha256, git_commit, source_sha256

MODEL_FILE = "model.pt"
MODEL_FORMAT = "torchcal.RobotModel"
MODEL_FORMAT_VERSION = 1


class RunDirError(TorchcalError, ValueError):
    """A run directory that cannot be created or read; the message names the folder."""


PARTIAL_FILE = "PARTIAL"
"""Present in a run directory whose run failed or was interrupted (written when its log opens, removed at its end)."""

RUN_MARKERS = ("config.yaml", "run.log", "model.pt", "versions.json", "metrics.json")
"""Files that make a folder a run directory (what :func:`torchcal.app.fit.run_fit` writes first)."""


def is_run_dir(folder) -> bool:
    """Whether ``folder`` holds a run (any of :data:`RUN_MARKERS`)."""
    folder = Path(folder)
    return folder.is_dir() and any((folder / m).exists() for m in RUN_MARKERS)


def is_fleet_run(folder) -> bool:
    """Whether ``folder`` is what ``torchcal fleet`` writes (its summary.csv and units/): a fleet prior's source."""
    folder = Path(folder)
    return (folder / "summary.csv").is_file() and (folder / "units").is_dir()


def _fresh(path: Path) -> bool:
    """Create ``path`` as a new folder (or take it when it is an empty folder); False when it is taken."""
    try:
        path.mkdir(parents=True)
        return True
    except FileExistsError:
        return path.is_dir() and not any(path.iterdir())  # an empty folder holds no run


def make_run_dir(out) -> Path:
    """Create the run directory for ``out``; runs go side by side, never inside another run.

    - ``out`` absent or an empty folder: ``out`` itself;
    - ``out`` is itself a run directory (an earlier fit wrote there): the next
      free sibling ``out-2``, ``out-3``, ...;
    - ``out`` is a folder of other things (e.g. earlier runs): a fresh
      ``out/<YYYYmmdd-HHMMSS>`` inside it.

    Never reuses a folder, never writes into an earlier run.

    Example:
        >>> import tempfile, pathlib
        >>> tmp = pathlib.Path(tempfile.mkdtemp())
        >>> first = make_run_dir(tmp / "runs"); (first / "config.yaml").write_text("robot: x")
        8
        >>> make_run_dir(tmp / "runs").name
        'runs-2'
    """
    out = Path(out)
    try:
        return _make_run_dir(out)
    except OSError as exc:  # read-only or full filesystem, ...: one line naming the folder, not a traceback
        raise RunDirError(f"{out}: cannot create the run directory ({exc.strerror or exc})") from None


def placed_note(out, run_dir) -> str:
    """Why the run went to ``run_dir`` and not to the ``out`` asked for ('' when it is ``out``): a user who typed
    ``out=r1`` twice must not look for the second run in r1.

    Example:
        >>> placed_note("runs/r1", "runs/r1-2")
        ' (runs/r1 holds a run already, and a run is never overwritten)'
    """
    out, run_dir = Path(out), Path(run_dir)
    if run_dir == out:
        return ""
    if run_dir.parent == out:
        return f" (a new folder in {out}, which holds other things)"
    return f" ({out} holds a run already, and a run is never overwritten)"


def _make_run_dir(out: Path) -> Path:
    if out.exists() and not out.is_dir():
        raise RunDirError(f"{out}: exists and is not a folder; choose another 'out'")
    if not out.exists() or (not any(out.iterdir())):
        out.mkdir(parents=True, exist_ok=True)
        return out
    if is_run_dir(out):
        for k in range(2, 10000):
            run = out.with_name(f"{out.name}-{k}")
            if run.exists() and not run.is_dir():
                continue
            if _fresh(run):
                return run
        raise RunDirError(f"{out}: no free sibling folder {out.name}-2 ... {out.name}-9999; choose another 'out'")
    stamp = datetime.now().strftime("%Y%m%d-%H%M%S")
    for k in range(1, 1000):
        run = out / (stamp if k == 1 else f"{stamp}-{k}")
        try:
            run.mkdir()  # exist_ok=False: two runs started in the same second get different folders
            return run
        except FileExistsError:
            continue
    raise RunDirError(f"{out}: could not create a fresh run folder for {stamp}")


def _jsonable(obj):
    """Plain JSON values: tensors to lists, NaN / inf to null (strict JSON has neither), Paths to str."""
    if isinstance(obj, dict):
        return {str(k): _jsonable(v) for k, v in obj.items()}
    if isinstance(obj, (list, tuple)):
        return [_jsonable(v) for v in obj]
    if isinstance(obj, torch.Tensor):
        return _jsonable(obj.detach().cpu().tolist())
    if isinstance(obj, float):
        return obj if math.isfinite(obj) else None
    if isinstance(obj, Path):
        return str(obj)
    if hasattr(obj, "item") and callable(obj.item):  # numpy scalars
        return _jsonable(obj.item())
    return obj


def write_json(path, obj) -> Path:
    """Write ``obj`` as indented, strict JSON (NaN -> null)."""
    from .atomic import atomic_write_text

    return atomic_write_text(path, json.dumps(_jsonable(obj), indent=2, allow_nan=False) + "\n")


def read_json(path):
    return json.loads(Path(path).read_text(encoding="utf-8"))


PROVENANCE_SUFFIX = ".provenance.json"


def write_provenance(output, run_dir=None, **details) -> Path:
    """``<output>.provenance.json`` beside a deliverable (compensated commands, predictions, a planned pose list,
    a calibrated URDF): the file's own sha256, the run and model it came from, the options it was made with
    (``details``, as given) and the code and command that wrote it. A compensated file loaded on a controller
    named neither its run nor its options."""
    out = Path(output)
    run = Path(run_dir) if run_dir is not None else None
    model = run / MODEL_FILE if run is not None and run.is_dir() else run
    v = collect_versions()
    blob = {"file": out.name, "sha256": file_sha256(out),
            "run_dir": str(run.resolve()) if run is not None else None,
            "model_sha256": file_sha256(model) if model is not None and model.is_file() else None,
            "options": details,
            "written_by": {k: v.get(k) for k in ("torchcal", "git", "torchcal_source_sha256", "torch", "command", "host")},
            "created": v["created"]}
    return write_json(out.with_name(out.name + PROVENANCE_SUFFIX), blob)


# ----------------------------------------------------------------------- models
def save_model(run_dir, model, **meta) -> Path:
    """Write ``model.pt``: the model's spec (structure) and state dict (values, on CPU), plus ``meta``."""
    path = Path(run_dir) / MODEL_FILE
    state = {k: v.detach().cpu() for k, v in model.state_dict().items()}
    spec = dict(model.spec())
    robot = Path(str(spec["robot"]))
    if robot.suffix and robot.exists():
        # a robot file named relative to the working directory must reload from anywhere
        spec["robot"] = str(robot.resolve())
    from .atomic import atomic_path

    # atomic: a full disk used to leave a truncated model.pt that later loads fail on
    with atomic_path(path) as tmp, open(tmp, "wb") as fh:
        # through a file object: torch.save names the archive inside after a path it is given (the random
        # temporary here), so the same model gave different bytes run to run
        torch.save({"format": MODEL_FORMAT, "format_version": MODEL_FORMAT_VERSION, "spec": spec,
                    "state_dict": state, "meta": _jsonable(meta)}, fh)
    return path


# spec["kind"] -> "module:Class"; every class has spec() and from_spec(spec, robot=None). A spec without
# "kind" is a robot model (run directories written before machines and sensor rigs existed).
MODEL_KINDS = {
    "robot": "torchcal.models.robot:RobotModel",
    "machine": "torchcal.models.machine:MachineModel",
    "sensor_rig": "torchcal.models.sensor_rig:SensorRig",
}


def model_class(spec: dict, path="model.pt"):
    """The model class a saved spec names (its ``kind``, default 'robot')."""
    import importlib

    kind = spec.get("kind", "robot")
    target = MODEL_KINDS.get(kind)
    if target is None:
        raise RunDirError(f"{path}: unknown model kind '{kind}' (known: {', '.join(sorted(MODEL_KINDS))})")
    module, name = target.split(":")
    return getattr(importlib.import_module(module), name)


def require_finished(run_dir, what: str) -> None:
    """Refuse (:class:`RunDirError`) a run directory that still holds :data:`PARTIAL_FILE`: its model may be a
    failed solver's last iterate (a fit stopped by a bad number left one 8 mm off), not a calibration to deploy.
    ``what``: the command, for the message. A model file given directly is not checked."""
    path = Path(run_dir)
    if path.is_dir() and (path / PARTIAL_FILE).is_file():
        raise RunDirError(f"{path}: this run did not finish (it holds {PARTIAL_FILE}: failed or interrupted; its "
                          f"run.log, or its fleet's, says why), so {what} does not use its model; fit again, or "
                          f"delete {path / PARTIAL_FILE} if you have checked that the model is complete")


def run_model_notes(run_dir) -> list[str]:
    """What a command that uses a finished run's model must say first (read from its fit.json and metrics.json;
    [] for a model file given directly, or nothing to say): a fit that did not converge (its model is the solver's
    last iterate: predict, compensate and export-urdf used one 0.03 deg off the converged model without a word),
    and a fleet unit whose data could not determine its model (its terms are the prior's: a 5-pose unit was used
    0.46 mm off)."""
    path = Path(run_dir)
    if not path.is_dir():
        return []
    out = []
    try:
        fitted = read_json(path / "fit.json")
    except (OSError, ValueError):
        fitted = None
    if isinstance(fitted, dict) and fitted.get("converged") is False:
        why = str(fitted.get("message") or "").strip()
        out.append(f"{path}: this run's fit did not converge ({why + ', ' if why else ''}{fitted.get('iterations', '?')} "
                   "iterations): its model is the solver's last iterate, not a calibration; fit again (a larger "
                   "solver.max_iter, or see its run.log) before relying on these results")
    try:
        m = read_json(path / "metrics.json")
    except (OSError, ValueError):
        m = None
    if isinstance(m, dict) and m.get("determined") is False:
        why = m.get("findings") or "its data could not determine its model"
        out.append(f"{path}: this unit's model is not determined by its data ({why}): its error terms are mostly the "
                   "prior's, not the robot's; measure more poses and fit it again before relying on these rows")
    return out


def load_model(run_dir, device=None, robot=None):
    """Rebuild the identified :class:`torchcal.models.robot.RobotModel` of a run (a run folder or its model.pt).

    device: where to put it (default CPU); robot: a loaded Robot to use instead
    of the one named in the spec (e.g. when the run moved to another machine).

    Example:
        >>> model = load_model("data/fanuc/runs")                      # doctest: +SKIP
        >>> model.points(q, tool).shape                                # doctest: +SKIP
        torch.Size([100, 3])
    """
    path = Path(run_dir)
    if path.is_dir():
        path = path / MODEL_FILE
    if not path.is_file():
        if is_fleet_run(run_dir):  # each unit's model is in its own folder
            units = sorted(p.name for p in (Path(run_dir) / "units").iterdir() if p.is_dir())[:3]
            raise RunDirError(f"{path}: no model here: {run_dir} is a fleet run; give one unit's folder, e.g. "
                              f"{Path(run_dir) / 'units' / (units[0] if units else '<name>')}")
        raise RunDirError(f"{path}: no model here; give a run directory written by 'torchcal fit'")
    try:
        blob = torch.load(path, map_location="cpu", weights_only=True)
    except Exception as exc:  # a truncated or foreign file: say which file, not a pickle traceback
        raise RunDirError(f"{path}: not a readable torchcal model ({type(exc).__name__}: {exc})") from None
    if not isinstance(blob, dict) or blob.get("format") != MODEL_FORMAT:
        raise RunDirError(f"{path}: not a torchcal model file")
    if blob.get("format_version", 0) > MODEL_FORMAT_VERSION:
        raise RunDirError(f"{path}: written by a newer torchcal (format {blob['format_version']}); upgrade torchcal")
    model = model_class(blob["spec"], path).from_spec(blob["spec"], robot)
    try:
        model.load_state_dict(blob["state_dict"])
    except RuntimeError as exc:  # e.g. a subclass's own error module: its parameters have no place here
        extra = sorted(set(blob["state_dict"]) - set(model.state_dict()))
        raise RunDirError(f"{path}: the saved parameters do not fit a {type(model).__name__} ("
                          + (f"it has no {', '.join(extra[:4])}: saved from a subclass? Rebuild that class and load "
                             f"torch.load(path)['state_dict'] into it" if extra else str(exc).splitlines()[0])
                          + ")") from None
    return model.to(device) if device is not None else model


def first_readable_model(run_dirs, device=None):
    """The model of the first of ``run_dirs`` (e.g. a fleet run's ``units/<name>`` folders) that
    :func:`load_model` reads, or RunDirError naming the first one's reason where none is: one broken file
    does not hide a fleet's structure (every unit has it)."""
    why = []
    for run_dir in run_dirs:
        try:
            return load_model(run_dir, device)
        except Exception as exc:  # a truncated file, or a spec or state this torchcal cannot rebuild: the next one
            why.append(str(exc))
    raise RunDirError(f"no model is readable ({why[0] if why else 'none given'})")


def load_run_config(run_dir) -> dict:
    """The resolved config a run was made with, as plain containers (the typed, checked view of it is the
    application layer's: :func:`torchcal.app.config.run_config`)."""
    import yaml

    path = Path(run_dir) / "config.yaml"
    if not path.is_file():
        raise RunDirError(f"{path}: no config.yaml; is {run_dir} a run directory?")
    try:
        cfg = yamlio.safe_load(path.read_text(encoding="utf-8")) or {}
    except yaml.YAMLError as exc:
        raise RunDirError(f"{path}: not valid YAML: {exc}") from None
    if not isinstance(cfg, dict):
        raise RunDirError(f"{path}: not a run's config (a mapping of keys)")
    return cfg


# ---------------------------------------------------------------------- logging
def _mark(exc: BaseException, run_dir) -> None:
    """Name the partial run directory on the failure (the CLI prints it); an enclosing run (a sweep) names its own."""
    try:
        exc.run_dir = Path(run_dir)
    except (AttributeError, TypeError):  # an exception type without a __dict__: the PARTIAL file still says it
        pass


@contextmanager
def run_log(run_dir, name: str = "torchcal", filename: str = "run.log"):
    """Send the ``torchcal`` logger's INFO records to ``<run_dir>/run.log`` for the duration of the block.

    A failure inside the block is logged with its traceback before it propagates,
    so the log shows how far a run got; an interrupt (Ctrl-C) is logged as one line.
    While the block runs the folder holds :data:`PARTIAL_FILE`; it stays when the
    block fails (killed processes included), so an incomplete run is never taken
    for a finished one. The failure carries the folder as ``exc.run_dir``.
    """
    logger = logging.getLogger(name)
    marker = Path(run_dir) / PARTIAL_FILE
    marker.write_text("This run did not finish (failed or interrupted; see run.log). The files here are what it "
                      "had computed by then.\n", encoding="utf-8")
    handler = logging.FileHandler(Path(run_dir) / filename, encoding="utf-8")
    handler.setFormatter(logging.Formatter("%(asctime)s %(levelname)s %(message)s", "%Y-%m-%d %H:%M:%S"))
    old_level = logger.level
    logger.addHandler(handler)
    if logger.level == logging.NOTSET or logger.level > logging.INFO:
        logger.setLevel(logging.INFO)
    try:
        yield logger
        marker.unlink(missing_ok=True)
    except KeyboardInterrupt as exc:
        logger.error("interrupted (Ctrl-C); this run directory is incomplete")
        _mark(exc, run_dir)
        raise
    except BaseException as exc:
        logger.exception("run failed")
        _mark(exc, run_dir)
        raise
    finally:
        logger.removeHandler(handler)
        handler.close()
        logger.setLevel(old_level)


__all__ = [
    "MODEL_FILE",
    "PARTIAL_FILE",
    "RunDirError",
    "RUN_MARKERS",
    "collect_versions",
    "first_readable_model",
    "git_commit",
    "is_fleet_run",
    "is_run_dir",
    "load_model",
    "load_run_config",
    "make_run_dir",
    "read_json",
    "require_finished",
    "write_provenance",
    "file_sha256",
    "PROVENANCE_SUFFIX",
    "source_sha256",
    "run_model_notes",
    "run_log",
    "save_model",
    "write_json",
]
