"""``torchcal fleet CONFIG``: every unit of one robot type fitted in batched solves; a run directory per unit.

The config is a ``torchcal fit`` config whose ``data.identification`` is a
folder with one CSV per unit (the unit is named by the file's stem) and whose
optional ``data.validation`` is a folder holding files of the same names.
Units are fitted ``fleet.cell`` at a time in one batched solve each
(:func:`torchcal.identify.fleet.fit_fleet`: every unit its own data, damping
and convergence). ``fleet.engine: ray`` sends the cells to Ray (a local Ray
started for the run, or the cluster at ``fleet.address``); every engine forms
the same cells from the same data, so a Ray run computes what the local run
computes. A unit whose file cannot be read is reported (``summary.csv``,
status ``failed``, with the reason) and the others go on, as is a unit whose
file lacks the approach directions the others have (or alone has them); a cell
that fails on a worker is reported the same way for its units.

The run directory holds ``config.yaml``, ``versions.json``, ``run.log``,
``summary.csv`` / ``fleet.json`` (per unit: status, rows, convergence,
identification / validation mean and max in mm, ``determined``: whether the
data hold as many equations as the model has parameters, the outlier score and
what was flagged) and ``units/<name>/`` with the unit's own ``config.yaml`` (a
``torchcal fit`` of it refits that unit alone), ``model.pt`` (usable by
``torchcal predict`` / ``compensate``) and ``metrics.json``. With ``fleet.baseline`` (an earlier run of the
same units) each unit is also compared with its earlier calibration (:mod:`.fleet_baseline`).
"""

from __future__ import annotations

import logging
import time
from dataclasses import dataclass, field
from collections.abc import Mapping
from pathlib import Path

import torch

from ..core import units
from ..core.progress import task
from ..io.atomic import atomic_write_text
from .common import config_backlash, config_orders, failed_row, write_preamble_files
from .config import ConfigError, SolverConfig, check_config, load_config, source_of, to_yaml, updated
from .engines import check_engine, interrupted
from .fleet_baseline import KEY, baseline_model, baseline_units, check_structure, compare_with_baseline
from .fleet_files import identical_files, ignored_files, unit_files, validation_gaps
from .fleet_frames import align_units, in_base
from .fleet_nominal import implausible_units, nominal_means
from .fleet_reuse import reuse_run, reused_units
from .fleet_summary import write_features, write_summary
from ..identify.fleet_outliers import OUTLIER_MIN_RATIO  # noqa: F401  the CLI's caption states the rule

log = logging.getLogger("torchcal")


@dataclass
class FleetRunResult:
    """What :func:`run_fleet` did: the run directory, one dict per unit (``rows``), the findings, the time, and the
    warnings about the data (a unit without validation, too few poses, an unmeasured tool)."""

    run_dir: Path
    rows: list[dict] = field(default_factory=list)
    findings: list = field(default_factory=list)
    time: float = 0.0
    solve_time: float = 0.0
    warnings: list[str] = field(default_factory=list)  # what the data leave open, also in run.log
    changes: list = field(default_factory=list)  # fleet.baseline: the units that changed since it
    reused: int = 0  # fleet.reuse: units taken as the earlier run fitted them
    placed: str = ""  # why the run directory is not the 'out' asked for ('' when it is)


def _check_fleet_config(cfg) -> None:
    label = cfg.config_file or "config"
    if isinstance(cfg.model.order, str):
        raise ConfigError(f"{source_of(cfg, 'model.order', label)}: key 'model.order': a fleet fits one structure for every unit; give the order "
                          "(choose it with `torchcal fit` on one unit, model.order: auto)")
    for key, bad in (("constraint.c", cfg.constraint.c is not None), ("sensor.kind", cfg.sensor.kind is not None),
                     ("model.kind", cfg.model.kind != "joint_dependent"), ("data.truth", bool(cfg.data.truth))):
        if bad:
            raise ConfigError(f"{label}: key '{key}': not supported by `torchcal fleet` (robots of Paper II, "
                              "unconstrained LM fits)")
    if cfg.tools is None or isinstance(cfg.tools, Mapping):
        raise ConfigError(f"{source_of(cfg, 'tools', label)}: key 'tools': a fleet needs the tool vectors listed (mm)")
    if cfg.prior.fleet is not None:
        raise ConfigError(f"{source_of(cfg, 'prior.fleet', label)}: key 'prior.fleet': a fleet's units are fitted under the config's own prior; a "
                          "fleet prior is for a new unit with few poses (`torchcal fit UNIT.yaml prior.fleet=RUN`)")
    check_engine(cfg.fleet.engine, f"{source_of(cfg, 'fleet.engine', label)}: key 'fleet.engine'")
    if cfg.solver.method != "lm":
        raise ConfigError(f"{source_of(cfg, 'solver.method', label)}: key 'solver.method': a fleet's batched solve is Levenberg-Marquardt (lm), got "
                          f"{cfg.solver.method!r}")


def _factory(cfg, robot, device, backlash):
    """The fleet's model factory (pipeline.model_factory from the config) with the given backlash orders."""
    from .fit import config_frame, config_tools, model_factory
    from .common import config_compliance, config_error_variable

    _, base = config_frame(cfg)
    return model_factory(robot, config_tools(cfg), backlash, device, base, config_compliance(cfg),
                         config_error_variable(cfg), cfg.model.kind, cfg.model.backlash_on)


def _solve_threads(cfg) -> int:
    """CPU threads of every cell's solve and of the evaluation: the config's, else this process's usable CPUs
    (one count for every engine: the count sets how the solve splits its units into streams, and another
    split sums in another order)."""
    from ..core import threads

    return int(cfg.threads) if cfg.threads is not None else threads.usable_cpus()


def fit_cell(cfg, cell: list[tuple[str, object]], n_threads: int) -> list[dict]:
    """One cell's batched solve: what an engine runs. cfg: the fleet's resolved
    :class:`~torchcal.app.config.FitConfig` (frozen and picklable: Ray carries it as it is, as a sweep's);
    cell: (name, :class:`Measurements`) per unit; n_threads: the CPU threads of the solve, the same wherever it
    runs (the driver's choice: a different count sums in another order, and a Ray worker starts with one). ->
    per unit {'name', 'state' (the model's state dict on the CPU), 'fit' (FitResult.summary()), 'orders',
    'backlash'}: plain data, so that any transport carries it."""
    from ..identify.fleet import fit_fleet
    from ..kinematics import load_robot
    from .fit import config_noise, config_prior
    from .common import solver_options
    from ..core import threads

    robot = load_robot(cfg.robot)
    device = torch.device(cfg.device)
    make = _factory(cfg, robot, device, config_backlash(cfg))
    orders = config_orders(cfg, robot.joint_map.n)
    data = [d.to(device) for _, d in cell]  # model.backlash: true is resolved already (run_fleet, for every cell)
    noise = config_noise(cfg, robot, cfg.config_file or "config")
    prior = config_prior(cfg)
    opts = {k: v for k, v in solver_options(cfg).items() if k == "max_iter"}
    opts["ftol"] = float(cfg.fleet.ftol)  # solver.ftol is a single fit's (run_fleet says so where it is set)
    old = threads.get_override()
    threads.set_threads(int(n_threads))
    try:
        out = fit_fleet(lambda: make(orders), data, noise, prior, **opts)
    finally:
        threads.set_threads(old)
    return [{"name": name, "state": {k: v.detach().cpu() for k, v in m.state_dict().items()}, "span": m.data_span,
             "fit": r.summary(), "orders": orders, "backlash": make.backlash}
            for (name, _), m, r in zip(cell, out.models, out.results)]


def _run_cells(cfg, cells: list[list]) -> list:
    """Every cell through the configured engine -> per cell its list of unit dicts, or the exception it raised."""
    from .engines import run_cells

    n_threads = _solve_threads(cfg)

    def done(i, got):
        if isinstance(got, Exception):  # reported per unit in summary.csv; the others go on
            log.warning("cell of %s failed (%s): %s: %s", [n for n, _ in cells[i]], cfg.fleet.engine,
                        type(got).__name__, got)

    return run_cells(fit_cell, [(cfg, cell, n_threads) for cell in cells], cfg.fleet.engine,
                     cfg.fleet.address, where=f"{source_of(cfg, 'fleet.engine', cfg.config_file or 'config')}: key 'fleet.engine'", on_done=done)


def run_fleet(config, overrides: list[str] | None = None, out=None, console=None) -> FleetRunResult:
    """Fit every unit of the fleet ``config`` (see the module docstring) into one run directory."""
    from ..identify.fleet import FleetFit, feature_scores, parameter_outliers
    from ..identify.fleet_outliers import judge_against
    from ..io.rundir import collect_versions, make_run_dir, placed_note, run_log, save_model, write_json
    from ..kinematics import load_robot
    from .fit import config_tool_count, read_sets

    t0 = time.perf_counter()
    cfg = load_config(config, list(overrides or []))  # checked: every key's value; the robot's joints below
    label = cfg.config_file or "config"
    _check_fleet_config(cfg)
    files = unit_files(cfg)
    baseline = baseline_units(cfg, label)  # (run, its fitted units) or None; a bad folder fails before any work
    earlier = reuse_run(cfg, label)  # fleet.reuse: likewise
    robot = load_robot(cfg.robot)
    check_config(cfg, label, robot.joint_map.n)
    T = config_tool_count(cfg)
    device = torch.device(cfg.device)
    target = Path(out) if out is not None else Path(cfg.out).with_name("fleets")
    for key in ("identification", "validation"):  # a run inside a data folder would be read as units next time
        folder = getattr(cfg.data, key)
        if folder and Path(folder).resolve() in (target.resolve(), *target.resolve().parents):
            raise ConfigError(f"{label}: the run directory {target} lies inside data.{key} ({folder}): choose an "
                              "'out' beside the data")
    written = cfg  # as given (model.backlash: true stays true: a later fleet.reuse compares with it)
    theirs = baseline_model(*baseline, source_of(cfg, "fleet.baseline", label)) if baseline is not None else None
    if theirs is not None and config_backlash(cfg) is True:  # like with like: the baseline's backlash orders
        cfg = updated(cfg, {"model.backlash": [int(b) for b in theirs.joint_errors.backlash_orders.tolist()]})
    if theirs is not None:  # before the run directory: a refused baseline leaves no empty run behind
        check_structure(baseline[0], theirs, _factory(cfg, robot, torch.device("cpu"), config_backlash(cfg))(
            config_orders(cfg, robot.joint_map.n)), source_of(cfg, "fleet.baseline", label))
    run_dir = make_run_dir(target)
    atomic_write_text(run_dir / "config.yaml", to_yaml(written))
    write_json(run_dir / "versions.json", collect_versions(device))
    result = FleetRunResult(run_dir, placed=placed_note(target, run_dir))

    def warn(msg: str) -> None:
        log.warning(msg)
        result.warnings.append(msg)

    with run_log(run_dir):
        log.info(f"fleet of {len(files)} units from {cfg.data.identification}; engine {cfg.fleet.engine}; {run_dir}{result.placed}")
        if float(cfg.solver.ftol) != SolverConfig.ftol:
            warn(f"solver.ftol ({cfg.solver.ftol:g}) is a single fit's; the fleet's units stop at fleet.ftol "
                 f"({float(cfg.fleet.ftol):g}): set that one")
        no_val, orphans = validation_gaps(cfg, files)
        ignored = ignored_files(cfg)
        if ignored:
            warn(f"not read (not .csv / .tsv files): {', '.join(ignored)}")
        for same in identical_files(files):  # one unit's file copied under two names: two "units", no spread
            warn(f"units {', '.join(same)} have byte-identical identification files: one unit measured once?")
        if no_val:
            warn(f"data.validation: no file in {cfg.data.validation} for {len(no_val)} unit(s): {', '.join(no_val)} "
                 "(their validation columns stay empty)")
        if orphans:
            warn(f"data.validation: {', '.join(p.name for p in orphans)} name{'s' if len(orphans) == 1 else ''} no "
                 "unit's identification file: not used")
        loaded, rows, val_errors = [], {}, {}
        with task("reading the units' files", total=len(files)) as bar:
            for name, fi, fv in files:
                notes: list[str] = []
                try:
                    try:
                        ident, val = read_sets(cfg, robot, T, fi, fv, notes, torch.device("cpu"), label)
                    except Exception as exc:
                        if fv is None:
                            raise
                        # a broken validation file costs the unit its held-out check, not its fit
                        notes = []
                        ident, val = read_sets(cfg, robot, T, fi, None, notes, torch.device("cpu"), label)
                        notes.append(f"validation file not used: {type(exc).__name__}: {exc}")
                        val_errors[name] = f"{type(exc).__name__}: {exc}"
                except Exception as exc:  # a broken file is this unit's failure, not the fleet's
                    rows[name] = failed_row(exc, unit=name)
                    log.warning("unit %s: not fitted: %s", name, exc)
                else:
                    for note in notes:
                        warn(f"unit {name}: {note}")
                    loaded.append((name, ident, val))
                bar.advance(note=name)
        frames, alignments = {}, {}  # measurement_frame: estimate: each unit's own (_align_units)
        if loaded:
            loaded = _same_format(loaded, rows, robot)
            loaded, frames, alignments = align_units(cfg, robot, loaded, rows, label)
        if not loaded:  # every unit failed before its fit: one error, the first unit's reason, summary.csv written
            result.rows = [rows[name] for name, _, _ in files]
            write_summary(run_dir, result, cfg)
            first = result.rows[0]
            raise ConfigError(f"{label}: no unit could be fitted; {first['unit']}: {first['reason']}\n(summary.csv in "
                              f"{run_dir} has every unit's reason)")
        if cfg is not written and written.model.backlash is True:
            log.info("backlash orders %s (model.backlash: true), the baseline's (%s)", cfg.model.backlash, KEY)
        cfg = _fleet_backlash(cfg, robot, loaded, warn)
        thin = _data_checks(cfg, robot, T, loaded, warn)  # {unit: why}: fewer equations than parameters
        size = int(cfg.fleet.cell)
        reused = {} if earlier is None else reused_units(earlier, files, loaded, _factory(
            cfg, robot, torch.device("cpu"), config_backlash(cfg))(config_orders(cfg, robot.joint_map.n)).spec(), warn)
        to_fit, result.reused = [u for u in loaded if u[0] not in reused], len(reused)
        # with measurement_frame: estimate each unit is solved in its own robot base frame (its points moved by
        # its alignment), its model then given that alignment as the nominal measurement frame
        cells = [[(n, in_base(i, frames.get(n))) for n, i, _ in to_fit[c:c + size]] for c in range(0, len(to_fit), size)]
        ts = time.perf_counter()
        with task(f"fitting {len(to_fit)} unit{'' if len(to_fit) == 1 else 's'} in {len(cells)} batched solve(s) "
                  f"({cfg.fleet.engine})", total=None):
            outs = (_run_cells(cfg, cells) if cells else []) + [list(reused.values())]
        cells.append([(n, None) for n in reused])
        result.solve_time = time.perf_counter() - ts
        vals = {n: v for n, _, v in loaded}
        idents = {n: i for n, i, _ in loaded}
        fitted = []
        for cell, got in zip(cells, outs):
            if isinstance(got, Exception):
                for name, _ in cell:
                    rows[name] = failed_row(got, unit=name)
                continue
            for u in got:
                model = _factory(cfg, robot, device, u["backlash"])(u["orders"])
                model.load_state_dict(u["state"])
                model.data_span = u.get("span")  # its data's range: not a parameter, so not in the state
                model.measured_tools = sorted({int(t) for t in idents[u["name"]].tool.tolist()})  # compensation's dof
                if u["name"] in frames:
                    with torch.no_grad():
                        model.base.nominal.copy_(frames[u["name"]].to(model.base.nominal))
                fitted.append((u, model))
        place = {name: k for k, (name, _, _) in enumerate(files)}  # the files' order, reused units among the rest
        fitted.sort(key=lambda um: place[um[0]["name"]])
        from ..core import threads

        with threads.limit_threads(_solve_threads(cfg)):  # the same sums whatever the engine left in this process
            for u, model in fitted:
                _evaluate(u, model, idents, vals, rows, device, warn)
                if u["name"] in val_errors:  # summary.csv and fleet.json say why its validation columns are empty
                    rows[u["name"]]["validation_error"] = val_errors[u["name"]]
                if u["name"] in reused:
                    rows[u["name"]]["reused_from"] = str(earlier)
            for name, mean in nominal_means(fitted, idents).items():
                rows[name]["identification_nominal_mean_mm"] = mean
        implausible, suspects = implausible_units(fitted, rows, robot, frames, warn, float(cfg.fleet.threshold))
        # a unit whose data cannot determine its parameters holds the prior's values: no evidence of damage, and no
        # part of the fleet's spread
        for u, _ in fitted:
            name = u["name"]
            rows[name]["determined"] = name not in thin
            if name in thin:
                rows[name].update(outlier_score=float("nan"), flagged=False, findings=f"not scored: {thin[name]}")
        scored = [(u, m) for u, m in fitted if u["name"] not in thin and u["name"] not in implausible
                  and u["name"] not in suspects]
        if len(scored) >= 3:
            fake = FleetFit([m for _, m in scored], None)
            scores = feature_scores(fake.models)
            score, findings = parameter_outliers(fake, float(cfg.fleet.threshold), scores=scores)
            write_features(run_dir, [u["name"] for u, _ in scored], scores, robot, float(cfg.fleet.threshold))
            for f in findings:  # the unit by its name, not its place among the scored units
                f.unit = scored[f.unit][0]["name"]
            result.findings = findings
            for k, (u, _) in enumerate(scored):
                mine = [str(f) for f in findings if f.unit == u["name"]]
                rows[u["name"]].update(outlier_score=float(score[k]), flagged=bool(mine), findings="; ".join(
                    s.split(": ", 1)[1] for s in mine))
            for f in findings:
                log.warning("flagged: %s", f)
            for u, model in fitted:  # held out of the fleet's scoring: a damaged joint, or another robot
                name = u["name"]
                if name not in suspects or name in thin:
                    continue
                top, mine = judge_against(scores, model, float(cfg.fleet.threshold))
                if mine:
                    for f in mine:
                        f.unit = name
                        log.warning("flagged: %s", f)
                    result.findings.extend(mine)
                    rows[name].update(outlier_score=top, flagged=True, findings="; ".join(
                        str(f).split(": ", 1)[1] for f in mine) + f"; {suspects.pop(name)[0]}")
        elif fitted:
            warn(f"outliers: {len(scored)} unit(s) with data enough to judge, at least 3 are needed; none scored")
        for name, (_, why) in suspects.items():  # no joint explains the miss: another robot than the fleet's
            implausible[name] = why
            warn(f"unit {name}: {why}; not scored for outliers, left out of the fleet prior")
        for name, why in implausible.items():  # flagged: a look is needed, and the fleet prior leaves it out
            rows[name].update(outlier_score=float("nan"), flagged=True, findings=why, implausible=True)
        if baseline is not None and fitted:
            try:
                result.changes = compare_with_baseline(*baseline, fitted, idents, rows, run_dir,
                                                       float(cfg.fleet.threshold), robot, device, warn)
            except Exception as exc:  # the fits are done: a comparison that fails is said, and they are written
                warn(f"{KEY}: the comparison with {baseline[0]} failed: {type(exc).__name__}: {exc}")
        by_name = {name: (str(fi), None if fv is None else str(fv)) for name, fi, fv in files}
        for u, model in fitted:
            name = u["name"]
            d = run_dir / "units" / name
            d.mkdir(parents=True, exist_ok=True)
            ident, val = by_name[name]
            ucfg = updated(cfg, {"data.identification": ident, "data.validation": val, "out": str(d)})
            write_preamble_files(d, ucfg, device, {})  # config, versions, data hashes: `torchcal update` checks them
            save_model(d, model, orders=u["orders"], config_file=str(d / "config.yaml"), fit=u["fit"])
            write_json(d / "metrics.json", {"units": "mm", "unit": name, **{k2: v for k2, v in rows[name].items()
                                                                            if k2 != "unit"}})
            if name in alignments:
                write_json(d / "alignment.json", alignments[name])
        result.rows = [rows[name] for name, _, _ in files]
        result.time = time.perf_counter() - t0
        write_summary(run_dir, result, cfg)
        if interrupted(outs):  # the units fitted by then are written; the run ends as interrupted (PARTIAL stays)
            log.warning(f"interrupted: {sum(r['status'] == 'fitted' for r in result.rows)} unit(s) fitted and written "
                        "before Ctrl-C; summary.csv names the others")
            raise KeyboardInterrupt
        failed = [r["unit"] for r in result.rows if r["status"] == "failed"]
        log.info(f"fleet done in {result.time:.1f} s (solve {result.solve_time:.1f} s): {len(fitted)} fitted, "
                 f"{len(failed)} failed{' ' + str(failed) if failed else ''}, "
                 f"{sum(bool(r.get('flagged')) for r in result.rows)} flagged; {run_dir / 'summary.csv'}")
    if cfg.report:  # after run_log: the log is whole
        from ..report import write_report

        try:
            write_report(run_dir)
        except Exception as exc:  # the fits are on disk: a report that fails is said, not the run's failure
            log.warning("fleet report not written: %s: %s", type(exc).__name__, exc)
            result.warnings.append(f"fleet report not written: {type(exc).__name__}: {exc}")
    return result


def _same_format(loaded: list, rows: dict, robot) -> list:
    """The units whose files share the fleet's format: with approach directions (dir columns) or without, as
    most units are (with them on a tie). A fleet fits one model structure in one solve, and backlash follows the
    directions; each other unit gets a failure row saying why, and the rest are fitted."""
    have = [u for u in loaded if u[1].has_direction]
    lack = [u for u in loaded if not u[1].has_direction]
    if not have or not lack:
        return loaded
    keep, odd = (have, lack) if len(have) >= len(lack) else (lack, have)
    n = robot.joint_map.n
    cols = f"dir1..dir{n} columns"
    for name, ident, _ in odd:
        why = (f"{ident.source or name}: no approach directions ({cols}), while {len(keep)} of the fleet's "
               f"{len(loaded)} readable units have them" if keep is have else
               f"{ident.source or name}: approach directions ({cols}), while {len(keep)} of the fleet's "
               f"{len(loaded)} readable units have none")
        why += ("; a fleet fits one model structure (backlash follows the directions): give every unit the same "
                "columns, or fit this unit alone with `torchcal fit`")
        rows[name] = failed_row(why, unit=name)
        log.warning("unit %s: not fitted: %s", name, why)
    return keep


def _fleet_backlash(cfg, robot, loaded: list, warn):
    """cfg with ``model.backlash: true`` resolved once for the whole fleet: the orders
    :func:`~torchcal.identify.backlash.default_backlash_orders` chooses on every unit's identification rows
    together. Each cell deciding on its own first unit would give units of one fleet different structures
    (and the outlier test and the fleet prior compare like with like); the resolved list goes into the run's and
    every unit's config, so a unit refitted alone keeps the fleet's structure."""
    from ..identify.backlash import default_backlash_orders

    b = config_backlash(cfg)  # None (off), True, an order or one per joint (-1: off)
    on = b is True or any(x >= 0 for x in ([b] if isinstance(b, int) else b or []))
    if on and not loaded[0][1].has_direction:  # as torchcal fit warns it
        warn(f"model.backlash is on but the units' files have no dir1..dir{robot.joint_map.n} columns: the backlash "
             "terms cannot be identified (set model.backlash=false, or give the approach directions)")
    if b is not True or not loaded[0][1].has_direction:
        return cfg
    orders = config_orders(cfg, robot.joint_map.n)
    q = torch.cat([d.q for _, d, _ in loaded])
    direction = torch.cat([d.direction for _, d, _ in loaded])
    chosen, _ = default_backlash_orders(orders, q, direction, robot.joint_map.limits.to(q))
    log.info("backlash orders %s (model.backlash: true), chosen once on the %d units' %d identification rows",
             chosen, len(loaded), q.shape[0])
    return updated(cfg, {"model.backlash": chosen})


def _data_checks(cfg, robot, T: int, loaded: list, warn) -> dict:
    """What each unit's identification data cannot determine, told to ``warn`` as ``torchcal fit`` warns it. -> {unit
    name: why} for the units with fewer equations (3 per row) than the model's parameters, or without a tool the
    fleet's other units measured: they are fitted (the prior holds what the data leave open) but neither judged for
    outliers nor part of the fleet prior."""
    from ..identify.layout import ParameterLayout

    orders = config_orders(cfg, robot.joint_map.n)
    P = ParameterLayout(_factory(cfg, robot, torch.device("cpu"), config_backlash(cfg))(orders)).size
    out = {}
    fleet_tools = set(torch.unique(torch.cat([i.tool for _, i, _ in loaded])).tolist())
    for name, ident, _ in loaded:
        E = 3 * len(ident)
        seen = set(torch.unique(ident.tool).tolist())
        missing = [t for t in range(T) if t not in seen]
        if missing:
            many = len(missing) > 1
            warn(f"unit {name}: tool{'s' if many else ''} {missing} never measured: {'their' if many else 'its'} "
                 "vector is the prior's")
        if gap := [t for t in missing if t in fleet_tools]:  # its wrist is seen through fewer points than the
            # others': its features differ for that alone (a J6 'outlier' 14x the median), so it is not judged
            out[name] = f"tool{'s' if len(gap) > 1 else ''} {gap} never measured, unlike the fleet's other units"
        if E < P:
            per_pose = 3 * max(len(seen), 1)
            few = (f"too few poses: {len(ident)} row{'s give' if len(ident) != 1 else ' gives'} {E} equations "
                   f"for {P} parameters")
            out[name] = f"{few}; {out[name]}" if name in out else few
            warn(f"unit {name}: {few}; its parameters are mostly the prior's (measure at least "
                 f"{-(-P // per_pose)} poses with {len(seen)} tool{'s' if len(seen) != 1 else ''}): fitted, not "
                 "judged for outliers, left out of the fleet prior")
    return out


def _evaluate(u: dict, model, idents: dict, vals: dict, rows: dict, device, warn) -> None:
    """A fitted unit's row: identification (and validation) residual statistics in mm; rows far beyond the rest
    are warned about (:func:`~torchcal.analysis.stats.far_rows`)."""
    from ..analysis.stats import far_rows_message, point_residuals, residual_stats

    name = u["name"]
    ident = idents[name].to(device)
    # by the compiled flange where it applies: the fleet has numba loaded already, and torch's batched 3 x 3
    # products made this 11 ms a unit
    res = point_residuals(model, ident, compiled=True).cpu()
    if far := far_rows_message(res, ident, f"unit {name}: identification ({ident.source})"):
        warn(far)
    s = residual_stats(res).scaled(units.m_to_mm(1.0))
    row = {"unit": name, "status": "fitted", "rows": len(ident), "converged": bool(u["fit"]["converged"]),
           "iterations": int(u["fit"]["iterations"]), "identification_mean_mm": s.mean,
           "identification_max_mm": s.max}
    if vals[name] is not None:
        val = point_residuals(model, vals[name].to(device), compiled=True)
        v = residual_stats(val.cpu()).scaled(units.m_to_mm(1.0))
        row.update(validation_mean_mm=v.mean, validation_max_mm=v.max, validation_gamma99_mm=v.gamma99)
    rows[name] = row


__all__ = ["FleetRunResult", "OUTLIER_MIN_RATIO", "fit_cell", "run_fleet", "unit_files"]
