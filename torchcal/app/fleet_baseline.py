"""``fleet.baseline``: a ``torchcal fleet`` run compared unit by unit with an earlier run of the same units.

A plant re-measures its fleet after a crash, a gearbox swap or a season. With ``fleet.baseline`` naming the
earlier run's directory, every unit fitted in both runs (by name) is compared
(:mod:`torchcal.identify.fleet_change`): its change at the tool (RMS and max over its new commands, mm), and
the joints whose transmission error or backlash changed. The units that changed far beyond the fleet's own
changes are named in the log, ``summary.csv`` (``changed``, ``change``), ``fleet.json`` (``changes``),
``changes.csv`` (every compared unit's changes, the fleet's medians and z-scores) and the fleet report.
"""

from __future__ import annotations

import logging
from pathlib import Path

import torch

from ..core import units
from ..core.exceptions import ConfigError
from .config import source_of
from ..io.atomic import atomic_path
from .fleet_summary import read_summary

log = logging.getLogger("torchcal")

KEY = "fleet.baseline"


def baseline_units(cfg, label: str) -> tuple[Path, list[str]] | None:
    """(the baseline run directory, its fitted units' names) of ``cfg.fleet.baseline``, or None where none is
    set; ConfigError naming the key where it is not a ``torchcal fleet`` run directory with fitted units."""
    if not cfg.fleet.baseline:
        return None
    run = Path(cfg.fleet.baseline)
    summary = run / "summary.csv"
    if not (run / "fleet.json").is_file() or not summary.is_file():
        raise ConfigError(f"{source_of(cfg, KEY, label)}: key '{KEY}': {run} is not a `torchcal fleet` run directory (it needs its "
                          "fleet.json and summary.csv)")
    from ..io.rundir import require_finished

    require_finished(run, f"the comparison with a baseline ({source_of(cfg, KEY, label)}: key '{KEY}')")
    table = read_summary(run)
    if "unit" not in table or "status" not in table:
        raise ConfigError(f"{source_of(cfg, KEY, label)}: key '{KEY}': {summary} lacks the columns 'unit' and 'status'")
    names = [str(u) for u in table.loc[table["status"].eq("fitted"), "unit"]]
    if not names:
        raise ConfigError(f"{source_of(cfg, KEY, label)}: key '{KEY}': {run} has no fitted unit to compare with")
    return run, names


def baseline_model(run: Path, names: list[str], label: str):
    """The first readable unit model of the baseline ``run`` (its structure and backlash orders are the fleet's;
    a broken one is said per unit after the solve); ConfigError naming the key where none is readable."""
    from ..io.rundir import RunDirError, first_readable_model

    try:
        return first_readable_model((run / "units" / name for name in names), torch.device("cpu"))
    except RunDirError as exc:
        raise ConfigError(f"{label}: key '{KEY}': {run}: {exc}") from None


def check_structure(run: Path, theirs, model, label: str) -> None:
    """Refuse (ConfigError naming the key) a baseline whose units (``theirs``, :func:`baseline_model`) are another
    robot type or model structure than ``model`` (the fleet's, as it will be fitted): checked before the solve, so
    that nothing fitted is lost."""
    from ..identify.layout import ParameterLayout

    if theirs.robot.name != model.robot.name:
        raise ConfigError(f"{label}: key '{KEY}': the units of {run} are a {theirs.robot.name}, this fleet a "
                          f"{model.robot.name}")
    if ParameterLayout(theirs).names() != ParameterLayout(model).names():
        raise ConfigError(f"{label}: key '{KEY}': the units of {run} have another model structure (orders, backlash or "
                          "tool count) than this fleet's: compare like with like (the same model.order, model.backlash "
                          "and tools)")
    a = theirs.tools.nominal.detach().cpu()
    b = model.tools.nominal.detach().cpu().to(a)
    if a.shape != b.shape or float((a - b).abs().max()) > 1e-6:  # 0.001 mm
        from .common import tools_text

        theirs_mm, ours_mm = (tools_text(units.m_to_mm(t).tolist()) for t in (a, b))
        raise ConfigError(f"{label}: key '{KEY}': the units of {run} were measured with other tool vectors "
                          f"({theirs_mm} mm) than this fleet's tools ({ours_mm} mm): every unit's points would differ by the targets' "
                          "move, not by a change of the robot. The re-check compares campaigns with the same tools")


def compare_with_baseline(run: Path, names: list[str], fitted: list, idents: dict, rows: dict, run_dir: Path,
                          threshold: float, robot, device, warn) -> list:
    """Every unit of ``fitted`` ([(unit dict, model)]) that the baseline ``run`` also fitted, compared with its
    earlier model at its new identification commands (``idents`` {name: Measurements}); ``rows`` {name: row}
    gain ``change_rms_mm``, ``change_max_mm``, ``changed`` and ``change``; ``changes.csv`` is written. ->
    the changed units (:class:`~torchcal.identify.fleet_change.UnitChange`, named)."""
    from ..identify.fleet_change import changed_units, joint_changes, tool_change
    from ..identify.layout import ParameterLayout
    from ..io.rundir import load_model

    earlier = set(names)
    now = {u["name"] for u, _ in fitted}
    gone = [n for n in names if n not in now]
    if gone:
        warn(f"{KEY}: {len(gone)} unit(s) of {run} not fitted in this run: {', '.join(gone)}")
    pairs, old, same = [], [], []
    for u, m in fitted:
        name = u["name"]
        if name not in earlier:
            rows[name]["change"] = f"not in {KEY} (new since {run.name}, or not fitted there)"
            continue
        if _same_file(run / "units" / name, idents[name].source):
            # no new measurement: its change is zero by construction, and zeros in the fleet's changes made the
            # scatter vanish (a re-measured healthy unit scored z 1e10)
            rows[name]["change"] = f"not re-measured: its identification file is the one {run.name} fitted"
            same.append(name)
            continue
        try:  # a unit whose earlier model cannot be read (or is of another structure) is said, the rest compared
            o = load_model(run / "units" / name, device)
            if ParameterLayout(o).names() != ParameterLayout(m).names():
                raise ConfigError(f"{run / 'units' / name}: another model structure than this fleet's")
        except Exception as exc:
            rows[name]["change"] = f"not compared: {exc}"
            warn(f"{KEY}: unit {name} not compared: {exc}")
            continue
        pairs.append((name, m))
        old.append(o)
    if same:
        warn(f"{KEY}: {len(same)} unit(s) hold the identification file {run.name} fitted, byte for byte: not "
             f"re-measured, so neither compared nor part of the fleet's changes: {', '.join(same)}")
    if not pairs:
        warn(f"{KEY}: no unit of this run could be compared with {run}")
        return []
    dist = [tool_change(o, m, idents[n].q, idents[n].tool, idents[n].direction if idents[n].has_direction else None)
            for o, (n, m) in zip(old, pairs)]
    rms = torch.stack([d.pow(2).mean().sqrt() for d in dist]).cpu()
    for (n, _), d, r in zip(pairs, dist, rms.tolist()):
        rows[n].update(change_rms_mm=units.m_to_mm(r), change_max_mm=units.m_to_mm(float(d.max())), changed=False)
    joints = joint_changes(old, [m for _, m in pairs])
    joint_names = list(pairs[0][1].joint_errors.joint_names)
    prismatic = robot.joint_map.prismatic.cpu()
    if len(pairs) < 3:
        warn(f"{KEY}: {len(pairs)} unit(s) compared with {run.name}; at least 3 are needed to judge a change against "
             "the fleet's: the changes are reported, none judged")
        _write_changes(run_dir, [n for n, _ in pairs], rms, joints, joint_names, prismatic, None, None, threshold)
        return []
    tool_sc, joint_sc, found = changed_units(rms, joints, joint_names, prismatic, threshold)
    _write_changes(run_dir, [n for n, _ in pairs], rms, joints, joint_names, prismatic, tool_sc, joint_sc, threshold)
    median = units.m_to_mm(float(tool_sc.median["tool change"][0]))
    log.info(f"{KEY}: {len(pairs)} unit(s) compared with {run}; the fleet's median change at the tool "
             f"{median:.4f} mm RMS; {len(found)} changed")
    for c in found:
        c.unit = pairs[c.unit][0]
        rows[c.unit].update(changed=True, change=str(c).split(": ", 1)[1])
        log.warning("changed: %s", c)
    return found


def _same_file(unit_dir: Path, path) -> bool:
    """Whether the identification file at ``path`` hashes as the one the baseline's unit ``unit_dir`` was fitted on
    (its data_hashes.json); False where either is unknown."""
    from .common import file_sha256, fitted_hash

    then = fitted_hash(unit_dir)
    return then is not None and Path(path).is_file() and then == file_sha256(path)


def _write_changes(run_dir: Path, names, rms, joints: dict, joint_names, prismatic, tool_sc, joint_sc,
                   threshold: float) -> None:
    """changes.csv: per compared unit its change at the tool (mm, RMS) and per joint and feature its change (deg,
    mm for a prismatic joint); where judged, the fleet's median, the ratio, the robust z, the level above which
    a change lies beyond the fleet's (``flag_level``) and whether it does (``beyond``)."""
    import pandas as pd

    from ..identify.fleet_change import CHANGE_MIN_RATIO

    value_units = units.joint_unit_names(prismatic)
    file_units = {key: units.joints_from_si(value, prismatic) for key, value in joints.items()}  # (M, n) deg / mm
    if joint_sc is not None:
        medians = {key: units.joints_from_si(joint_sc.median[key], prismatic) for key in joints}
        levels = {key: units.joints_from_si(joint_sc.flag_level(key, threshold), prismatic) for key in joints}
    out = []
    for m, name in enumerate(names):
        row = {"unit": name, "joint": "tool", "feature": "tool change", "change": units.m_to_mm(float(rms[m])),
               "value_unit": "mm"}
        if tool_sc is not None:
            key = "tool change"
            row.update(fleet_median=units.m_to_mm(float(tool_sc.median[key][0])),
                       ratio=float(tool_sc.ratio[key][m, 0]), robust_z=float(tool_sc.z[key][m, 0]),
                       flag_level=units.m_to_mm(float(tool_sc.flag_level(key, threshold, CHANGE_MIN_RATIO)[0])),
                       beyond=bool(tool_sc.flagged(key, threshold, CHANGE_MIN_RATIO)[m, 0]))
        out.append(row)
        for key in joints:
            for j, joint in enumerate(joint_names):
                row = {"unit": name, "joint": joint, "feature": key, "change": float(file_units[key][m, j]),
                       "value_unit": value_units[j]}
                if joint_sc is not None:
                    row.update(fleet_median=float(medians[key][j]), ratio=float(joint_sc.ratio[key][m, j]),
                               robust_z=float(joint_sc.z[key][m, j]), flag_level=float(levels[key][j]),
                               beyond=bool(joint_sc.flagged(key, threshold)[m, j]))
                out.append(row)
    with atomic_path(run_dir / "changes.csv") as tmp:
        pd.DataFrame(out).to_csv(tmp, index=False, float_format="%.9g")


__all__ = ["KEY", "baseline_model", "baseline_units", "check_structure", "compare_with_baseline"]
