"""``fleet.reuse``: a ``torchcal fleet`` run that takes the units an earlier run fitted, and fits only the others.

A plant's fleet of 100 robots finishes with two units failed (a file cut
short, a unit with another controller's columns) or is interrupted half way.
After the files are mended, refitting the 98 good units would repeat minutes of
work for the same numbers. With ``fleet.reuse`` naming the earlier run, a unit
is taken as that run fitted it (its model, its solver summary) when

- the earlier run's ``summary.csv`` says ``fitted``;
- its identification file hashes as it did then
  (``units/<name>/data_hashes.json``): a mended or re-measured unit is fitted
  again (the validation file shapes no fit: each run evaluates the one it has);
- every setting that shapes a fit is the same (the config with its data folders,
  run directory, engine, cell size, outlier threshold, baseline, threads and
  device set aside), and its model has the orders and backlash orders this run
  resolves.

Everything after the solve runs on every unit as in a fresh run: residuals,
the outlier scores (on the whole fleet: a reused unit can still be the one
flagged), the baseline comparison, the unit folders, the summary (column
``reused_from``). An interrupted earlier run may be reused: the units it wrote
were finished.
"""

from __future__ import annotations

import logging
from pathlib import Path

from ..core.exceptions import ConfigError
from .config import source_of, to_dict
from .fleet_summary import read_summary

log = logging.getLogger("torchcal")

KEY = "fleet.reuse"

IGNORED_KEYS = ("out", "report", "plots", "threads", "device", "data.identification", "data.validation",
                "data.units_checked", "data.truth", "solver.ftol", "fleet.engine", "fleet.address", "fleet.cell",
                "fleet.threshold", "fleet.baseline", KEY, "config_file", "overrides")
"""Settings that do not change a unit's fit (or name where its data lie: the data themselves are compared by hash)."""


def _flat(d: dict, prefix: str = "") -> dict:
    out = {}
    for k, v in d.items():
        key = f"{prefix}{k}"
        if isinstance(v, dict):
            out.update(_flat(v, key + "."))
        else:
            out[key] = v
    return out


IGNORED_SECTIONS = ("compensation.", "sweep.")
"""Config sections that act after a fit (the compensation check) or outside a fleet (a sweep's engine)."""


def _differing_keys(earlier: dict, now: dict) -> list[str]:
    a, b = _flat(earlier), _flat(now)
    return sorted(k for k in set(a) | set(b) if k not in IGNORED_KEYS and not k.startswith(IGNORED_SECTIONS)
                  and a.get(k) != b.get(k))


def reuse_run(cfg, label: str) -> Path | None:
    """The earlier fleet run of ``cfg.fleet.reuse`` (None where none is set); ConfigError naming the key where it
    is not a ``torchcal fleet`` run directory, or where a setting that shapes the fits differs from this run's."""
    if not cfg.fleet.reuse:
        return None
    from ..io.rundir import RunDirError, is_fleet_run, load_run_config

    run = Path(cfg.fleet.reuse)
    where = f"{source_of(cfg, KEY, label)}: key '{KEY}'"
    if not run.exists():
        raise ConfigError(f"{where}: {run} does not exist")
    if not (run / "units").is_dir() and (run / "PARTIAL").exists() and (run / "config.yaml").is_file():
        raise ConfigError(f"{where}: {run} fitted no unit (interrupted before its first batched solve): there is "
                          "nothing to take; drop the key")
    if not is_fleet_run(run):
        raise ConfigError(f"{where}: {run} is not a `torchcal fleet` run directory (it needs its summary.csv and units/)")
    try:
        differ = _differing_keys(load_run_config(run), to_dict(cfg))
    except RunDirError as exc:
        raise ConfigError(f"{where}: {exc}") from None
    if differ:
        raise ConfigError(f"{where}: {run} was fitted with other settings ({', '.join(differ)}): its units would not "
                          "be what this run fits; drop the key to fit every unit")
    return run


STRUCTURE_KEYS = ("orders", "backlash", "backlash_on", "error_variable", "tools", "compliance", "fine")
"""Model spec keys a reused unit's model must share with this run's (not its base frame: a unit's own where the
measurement frame is estimated)."""


def reused_units(run: Path, files: list, loaded: list, spec: dict, warn) -> dict[str, dict]:
    """The units of ``loaded`` (name, identification, validation) to take from the earlier ``run`` as it fitted
    them -> {name: the unit dict :func:`torchcal.app.fleet.fit_cell` returns}. files: (name, identification path,
    validation path or None) per unit; spec: the spec of this run's model (its orders and backlash orders
    resolved). A unit that cannot be taken is fitted, and why is logged (or warned, where its data changed)."""
    from ..io.rundir import MODEL_FILE
    from .common import DATA_HASH_FILE, file_sha256, fitted_hash

    table = read_summary(run)
    fitted = set(str(u) for u in table.loc[table["status"].eq("fitted"), "unit"]) if "status" in table else set()
    paths = {name: (fi, fv) for name, fi, fv in files}
    out, changed, unknown = {}, [], []
    for name, _, _ in loaded:
        unit = run / "units" / name
        if name not in fitted:
            continue  # failed, interrupted before it, or new: this run fits it
        if not (unit / MODEL_FILE).is_file():
            unknown.append(f"{name} (no {MODEL_FILE})")
            continue
        then = fitted_hash(unit)
        if then is None:
            unknown.append(f"{name} (no {DATA_HASH_FILE}: its data cannot be compared)")
            continue
        # the identification file alone: the validation file shapes no fit (this run evaluates the one it has)
        if then != file_sha256(paths[name][0]):
            changed.append(name)
            continue
        try:
            unit_dict, theirs = _unit_dict(unit / MODEL_FILE, name)
        except Exception as exc:  # a damaged earlier file costs only the reuse
            warn(f"{KEY}: unit {name}: its model in {run} cannot be read ({type(exc).__name__}: "
                 f"{str(exc).splitlines()[0][:200]}); fitted again")
            continue
        if differ := [k for k in STRUCTURE_KEYS if theirs.get(k) != spec.get(k)]:
            warn(f"{KEY}: unit {name}: its model in {run} differs in {', '.join(differ)}; fitted again")
            continue
        out[name] = unit_dict
    if changed:
        warn(f"{KEY}: {len(changed)} unit(s) whose data changed since {run} are fitted again: {', '.join(changed)}")
    if unknown:
        warn(f"{KEY}: {len(unknown)} unit(s) fitted in {run} cannot be taken from it, fitted again: {', '.join(unknown)}")
    gone = sorted(fitted - {name for name, _, _ in files})
    if gone:  # a unit the earlier run fitted whose file is no longer among the data: not silently forgotten
        warn(f"{KEY}: {len(gone)} unit(s) fitted in {run} have no identification file in this run's data: "
             f"{', '.join(gone)} (not in this run)")
    log.info(f"{KEY}: {len(out)} unit(s) taken as {run} fitted them; {len(loaded) - len(out)} to fit")
    return out


def _unit_dict(path: Path, name: str) -> tuple[dict, dict]:
    """An earlier unit's model file -> (the unit dict of :func:`torchcal.app.fleet.fit_cell`, its model's spec)."""
    import torch

    blob = torch.load(path, map_location="cpu", weights_only=True)
    meta, spec = blob["meta"], blob["spec"]
    span = spec.get("data_span")
    b = spec.get("backlash")
    return {"name": name, "state": blob["state_dict"], "fit": meta["fit"], "orders": list(spec["orders"]),
            "span": None if span is None else torch.tensor(span, dtype=torch.float64),
            "backlash": None if b is None or max(b) < 0 else list(b)}, spec


__all__ = ["IGNORED_KEYS", "IGNORED_SECTIONS", "KEY", "STRUCTURE_KEYS", "reuse_run", "reused_units"]
