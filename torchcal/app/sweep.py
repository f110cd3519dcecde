"""``torchcal sweep CONFIG key=a,b,c key2=lo:hi``: a grid of configs fitted into one run directory.

Figure 11 of Paper II is such a grid (``model.order=1:10 data.n_poses=150,250,350``:
30 models). Cells that differ only in what the batched solver stacks along its
model axis (Chebyshev and backlash orders, the first N poses of one file, the
noise settings) are fitted together by :func:`torchcal.identify.batched.fit_batch`
with their own convergence: one batched solve per structure, each model from
zero as its own fit would start (warm starts from a smaller structure were
measured: no fewer iterations, the late ones creep along near-redundant
directions whatever the start). Each cell then lands where a separate
``torchcal fit`` lands (the fits stop at a relative
cost change of :data:`SWEEP_FTOL`: validation means within 0.07 % of fully
converged fits on Figure 11's 30 cells). Any other
difference (a model kind, a constraint, automatic orders, a sensor run) runs
the cell as a ``torchcal fit`` of its own inside the sweep's folder.

The independent groups (one per model structure of the stacked cells, one per
cell fitted alone) run on ``sweep.engine``: ``local`` (this process) or
``ray`` (:mod:`torchcal.app.engines`, as ``torchcal fleet``'s cells), with the
same results either way. A group that fails is reported in ``results.csv``
(``status`` failed, ``reason``) and the others finish.

The run directory holds ``config.yaml`` (the base config), ``sweep.json`` (the
grid), ``versions.json``, ``run.log``, ``results.csv`` / ``results.json`` (one
row per cell: its grid values, convergence, identification and validation
residuals in mm), ``cells/NN/model.pt`` and ``plots/sweep.png``.
"""

from __future__ import annotations

import itertools
import json
import logging
import math
import time
from dataclasses import dataclass, field
from pathlib import Path

import torch

from ..core import units
from ..core.exceptions import TorchcalError
from ..io.atomic import atomic_path, atomic_write_text
from .common import failed_row
from .config import ConfigError, load_config, source_of, to_yaml
from .engines import Interrupted, check_engine, interrupted, run_cells
from ..identify.fit import frame_check

log = logging.getLogger("torchcal")

SWEEP_FTOL = 1e-4
"""Relative cost reduction at which a sweep's fits stop (unless the config sets ``solver.ftol`` above the
default): the last ~15 iterations of a fit from zero creep along near-redundant directions (~1 chi^2 unit
each) that move no prediction that matters. Measured on Figure 11 (simulated FANUC, 30 cells): every cell's
validation mean within 0.07 % of the fully converged fit's (1e-3: 1.1 %)."""

STACKED_KEYS = ("model.order", "model.backlash", "data.n_poses", "noise.sigma_m", "noise.joint_var_fwd",
                "noise.joint_var_bwd", "out")
"""Config keys along which cells are stacked into one batched solve; cells differing elsewhere are separate groups."""


@dataclass
class SweepResult:
    """What :func:`run_sweep` did: the run directory, the grid keys and one dict per cell (``rows``)."""

    run_dir: Path
    keys: list[str]
    rows: list[dict] = field(default_factory=list)
    time: float = 0.0
    warnings: list[str] = field(default_factory=list)
    """What the data files' checks said (joints read as degrees although they look like radians, ...)."""


def parse_grid(specs: list[str]) -> tuple[list[str], list[tuple[str, list[str]]]]:
    """Split ``key=value`` items into plain overrides and grid axes.

    ``key=a,b,c`` is an axis of those values, ``key=lo:hi`` (or ``lo:hi:step``)
    the integers lo..hi inclusive; anything else a plain override for every
    cell. A list value in brackets (``model.order=[6,6,4,4,4,4]``) is one
    value. -> (overrides, [(key, values)]).

    Example:
        >>> parse_grid(["model.order=1:3", "data.n_poses=150,250", "seed=2"])
        (['seed=2'], [('model.order', ['1', '2', '3']), ('data.n_poses', ['150', '250'])])
    """
    plain, axes = [], []
    for item in specs:
        if "=" not in item:
            raise ConfigError(f"sweep item '{item}': expected key=value, key=a,b,c or key=lo:hi")
        key, value = item.split("=", 1)
        key, value = key.strip(), value.strip()
        if value.startswith("[") or value.startswith("{"):
            plain.append(f"{key}={value}")
        elif "," in value:
            axes.append((key, [v.strip() for v in value.split(",") if v.strip()]))
        elif value.count(":") in (1, 2) and all(_is_int(p) for p in value.split(":")):
            parts = [int(p) for p in value.split(":")]
            lo, hi, step = parts[0], parts[1], parts[2] if len(parts) == 3 else 1
            if step <= 0 or hi < lo:
                raise ConfigError(f"sweep item '{item}': a range lo:hi[:step] needs lo <= hi and step > 0")
            axes.append((key, [str(v) for v in range(lo, hi + 1, step)]))
        else:
            plain.append(f"{key}={value}")
    if len({k for k, _ in axes}) != len(axes):
        raise ConfigError("sweep: a key is given twice as a grid axis")
    both = sorted({k for k, _ in axes} & {p.partition("=")[0].strip() for p in plain})
    if both:
        raise ConfigError(f"sweep: key '{both[0]}' is given both as a grid axis and as one value; give one of them")
    engine_axes = [k for k, _ in axes if k.startswith("sweep.")]
    if engine_axes:
        raise ConfigError(f"sweep item '{engine_axes[0]}=...': where the sweep runs is one value for the whole grid, "
                          "not a grid axis")
    return plain, axes


def _is_int(s: str) -> bool:
    try:
        int(s)
        return True
    except ValueError:
        return False


def _stackable(cfg) -> bool:
    """Whether a cell can join a batched solve (joint-dependent robot model, fixed orders, plain LM fit on the
    given tools and frame, the config's own prior): anything else is a ``torchcal fit`` of its own, which does
    what the cell's config says (a fleet prior, an alignment, a constraint)."""
    from .fit import config_frame, config_tools

    return (cfg.model.kind == "joint_dependent" and not isinstance(cfg.model.order, str) and cfg.constraint.c is None
            and cfg.sensor.kind is None and cfg.solver.method == "lm" and cfg.model.fine is None
            and cfg.prior.fleet is None and config_tools(cfg) is not None and config_frame(cfg)[0] != "estimate")


def _group_key(cfg) -> str:
    """The config with the stacked keys removed: cells with equal keys share one batched solve."""
    from .config import to_dict

    c = to_dict(cfg)
    c.pop("overrides", None)  # provenance: each cell's own grid values, which the keys below already hold
    for key in STACKED_KEYS:
        node = c
        *path, last = key.split(".")
        for p in path:
            node = node.get(p, {})
        node.pop(last, None)
    return json.dumps(c, sort_keys=True, default=str)


@frame_check(quiet=True)  # the run says a far frame its own way (its nominal residual)
def run_sweep(config, specs: list[str], out=None, console=None) -> SweepResult:
    """Fit every cell of the grid ``specs`` over ``config`` into one run directory (see the module docstring).

    config: a YAML config; specs: ``key=a,b,c`` / ``key=lo:hi`` axes and plain
    ``key=value`` overrides; out: the run directory (default: ``sweeps`` next to
    the config's ``out``). Each cell's config is checked before anything is
    fitted. -> :class:`SweepResult`.
    """
    from ..io.rundir import collect_versions, make_run_dir, placed_note, run_log, write_json
    from ..core.progress import task

    t0 = time.perf_counter()
    plain, axes = parse_grid(list(specs))
    if not axes:
        odd = [p for p in plain if ":" in p.partition("=")[2] and not p.partition("=")[2].lstrip().startswith(("[", "{"))]
        empty = [p for p in plain if not p.partition("=")[2].strip()]
        hint = (f"; '{odd[0]}' is no range: lo:hi[:step] takes integers" if odd else
                f"; '{empty[0]}' gives no values" if empty else "")
        raise ConfigError(f"sweep: give at least one grid axis (key=a,b,c or key=lo:hi){hint}")
    keys = [k for k, _ in axes]
    cells = [dict(zip(keys, values)) for values in itertools.product(*[v for _, v in axes])]
    cfgs = [load_config(config, plain + [f"{k}={v}" for k, v in cell.items()]) for cell in cells]
    base = load_config(config, plain)
    check_engine(base.sweep.engine, f"{source_of(base, 'sweep.engine', base.config_file or 'config')}: key 'sweep.engine'")
    notes = check_data(cfgs)
    requested = Path(out) if out is not None else Path(base.out).with_name("sweeps")
    run_dir = make_run_dir(requested)
    atomic_write_text(run_dir / "config.yaml", to_yaml(base))
    write_json(run_dir / "sweep.json", {"config": str(config), "overrides": plain, "axes": {k: v for k, v in axes},
                                        "cells": len(cells)})
    write_json(run_dir / "versions.json", {**collect_versions(torch.device(base.device)), "run_dir": str(run_dir)})
    from .common import DATA_HASH_FILE, input_hashes

    write_json(run_dir / DATA_HASH_FILE, input_hashes(base))  # the cells read the base's files (grids over data.*: the base's)
    result = SweepResult(run_dir, keys, warnings=notes)
    # the independent groups an engine runs: one per model structure of the stacked cells (each its own batched
    # solve; backlash: true may still split a group by what each cell's data choose), one per cell fitted alone
    groups: dict[str, list[int]] = {}
    for i, cfg in enumerate(cfgs):
        key = (_group_key(cfg) + json.dumps([cfg.model.order, cfg.model.backlash], default=str)
               if _stackable(cfg) else f"cell {i}")
        groups.setdefault(key, []).append(i)
    rows: list[dict | None] = [None] * len(cells)
    members_of = list(groups.values())
    jobs = [("stacked" if _stackable(cfgs[m[0]]) else "alone", [cfgs[i] for i in m], str(run_dir), m,
             cfgs[m[0]].threads) for m in members_of]
    engine = base.sweep.engine
    with run_log(run_dir):
        log.info(f"sweep of {len(cells)} cells over {', '.join(keys)}: {len(groups)} independent group(s), engine "
                 f"{engine}; {run_dir}{placed_note(requested, run_dir)}")
        for note in notes:
            log.warning(note)
        with task("sweep: cell groups", total=len(groups)) as bar:
            def done(g, got):
                members = members_of[g]
                if isinstance(got, Exception):  # this group's cells are reported; the others go on
                    log.warning(f"cells {members} failed ({engine}): {type(got).__name__}: {got}")
                    got = [failed_row(got)] * len(members)
                for i, row in zip(members, got):
                    rows[i] = row
                    if engine != "local" and row["status"] == "fitted":  # a worker's log stays on the worker
                        log.info(f"cell {i}: {_row_line(row)}")
                bar.advance(note=f"{sum(r is not None for r in rows)} of {len(cells)} cells")

            outs = run_cells(sweep_group, jobs, engine, base.sweep.address,
                             where=f"{source_of(base, 'sweep.engine', base.config_file or 'config')}: key 'sweep.engine'", on_done=done)
            for g, got in enumerate(outs):
                if isinstance(got, Interrupted):
                    done(g, got)
        result.rows = [{"cell": i, **cells[i], **rows[i]} for i in range(len(cells))]
        result.time = time.perf_counter() - t0
        _write_results(run_dir, result)
        failed = [r["cell"] for r in result.rows if r["status"] != "fitted"]
        if failed:
            log.warning(f"{len(failed)} of {len(cells)} cells failed ({', '.join(map(str, failed))}): results.csv "
                        "says why")
        if interrupted(outs):  # the cells fitted by then are written; the run ends as interrupted (PARTIAL stays)
            raise KeyboardInterrupt
        if len(failed) == len(cells):  # as `torchcal fleet`: nothing fitted is a failed run (exit 2), its table kept
            first = result.rows[0]
            raise ConfigError(f"sweep: no cell could be fitted; cell {first['cell']}: {first['reason']}\n(results.csv "
                              f"in {run_dir} has every cell's reason)")
        log.info(f"sweep done in {result.time:.1f} s: {run_dir / 'results.csv'}")
    return result


def check_data(cfgs) -> list[str]:
    """Read and unit-check each distinct set of data files of the grid once, before the run directory exists.
    When every set fails (a file in radians or metres, one that cannot be read), that is one error up front
    (exit 2, nothing written) rather than the same failure in every cell; a grid over data files where only
    some fail goes on, and those cells fail alone (as a fleet's broken unit). ``data.n_poses`` is left to the
    cells likewise. -> the checks' notes (joints read as degrees, ...), each once."""
    from dataclasses import replace

    from ..kinematics import load_robot
    from .fit import config_tool_count, read_sets

    seen, notes, errors = set(), [], []
    for cfg in cfgs:
        key = (cfg.robot, cfg.data.identification, cfg.data.validation, str(cfg.tools), cfg.data.units_checked)
        if key in seen:
            continue
        seen.add(key)
        whole = replace(cfg, data=replace(cfg.data, n_poses=None))
        found: list[str] = []
        try:
            read_sets(whole, load_robot(cfg.robot), config_tool_count(cfg), cfg.data.identification,
                      cfg.data.validation, found, torch.device("cpu"), cfg.config_file or "config")
        except TorchcalError as exc:
            errors.append(exc)
        notes += [n for n in found if n not in notes]
    if errors and len(errors) == len(seen):
        raise errors[0]
    return notes


def sweep_group(kind: str, cfgs: list, run_dir: str, cells: list[int], n_threads: int | None) -> list[dict]:
    """One independent group of a sweep's cells, what an engine runs: ``kind`` 'stacked' (one batched solve,
    :func:`_fit_stacked`) or 'alone' (one cell, its own ``torchcal fit``). cfgs: each cell's resolved
    :class:`~torchcal.app.config.FitConfig` (frozen and picklable: Ray carries it as it is); run_dir: the
    sweep's run directory, where the cells write ``cells/NN`` (on a Ray cluster it must be on storage this node
    reaches); n_threads: the config's ``threads`` (None: chosen by work size, the same choice on any engine of
    one machine). -> one row per cell (status 'fitted', convergence, residuals in mm)."""
    import socket

    from ..core import threads
    from ..io.rundir import RunDirError

    root = Path(run_dir)
    if not root.is_dir():
        raise RunDirError(f"{root}: the sweep's run directory is not visible on {socket.gethostname()}, where this "
                          "cell runs: with sweep.engine=ray on a cluster, put the run directory (--out) and the data "
                          "on storage every node reaches")
    old = threads.get_override()
    if n_threads is not None:
        threads.set_threads(n_threads)
    try:
        if kind == "stacked":
            return _fit_stacked(cfgs, root, cells)
        return [_fit_alone(cfgs[0], root, cells[0], None)]
    finally:
        threads.set_threads(old)


def _row_line(row: dict) -> str:
    if "validation_mean_mm" in row:
        return f"validation {row['validation_mean_mm']:.4f} mm ({row['iterations']} iterations)"
    return f"identification {row.get('identification_mean_mm', float('nan')):.4f} mm ({row['iterations']} iterations)"


def _fit_stacked(cfgs: list, run_dir: Path, cells: list[int]) -> list[dict]:
    """One batched solve for cells that differ only in orders, the number of poses and the noise."""
    from ..analysis.stats import point_residuals, residual_stats
    from ..identify.backlash import default_backlash_orders
    from ..identify.batched import fit_batch
    from ..io.rundir import save_model
    from .common import config_orders
    from .fit import align_inputs, config_backlash, config_noise, first_poses, load_inputs, model_factory

    from .config import updated

    cfg0 = updated(cfgs[0], {"data.n_poses": None})  # the file's every pose; each cell takes its first N
    inp = load_inputs(cfg0)
    tools_m, base_nominal, alignment = align_inputs(cfg0, inp)
    if alignment is not None:
        raise ConfigError(f"{inp.label}: the sweep stacks cells on the given tools and frame; run the alignment "
                          "once with `torchcal fit` and give its tools and measurement frame in the config")
    n = inp.robot.joint_map.n
    models, rows, noises, structures = {}, {}, {}, {}
    out: list[dict | None] = [None] * len(cfgs)
    for i, cfg in enumerate(cfgs):
        try:
            data = inp.ident if cfg.data.n_poses is None else first_poses(inp.ident, int(cfg.data.n_poses),
                                                                               source_of(cfg, "data.n_poses", inp.label))
        except ConfigError as exc:  # this cell's own value (more poses than the file has): the others go on
            out[i] = failed_row(exc)
            log.warning(f"cell {cells[i]} failed: {exc}")
            continue
        orders = config_orders(cfg, n)
        make = model_factory(inp.robot, tools_m, config_backlash(cfg), inp.device, base_nominal, _compliance(cfg),
                             None if cfg.model.error_variable is None else cfg.model.error_variable, cfg.model.kind,
                             cfg.model.backlash_on)
        if make.backlash is True and data.has_direction:  # as torchcal fit: the backlash order follows the data
            make.backlash, _ = default_backlash_orders(orders, data.q, data.direction, inp.robot.joint_map.limits.to(data.q))
        models[i] = make(orders)
        structures[i] = (orders, make.backlash)
        rows[i] = torch.isin(inp.ident.pose, data.pose.unique())
        noises[i] = config_noise(cfg, inp.robot, inp.label)
    # one batched solve per structure: every model of it at its own size (a superset of mixed orders would
    # compute the small ones at the largest size); each from zero, as its own fit would start
    levels: dict[str, list[int]] = {}
    for i, st in structures.items():
        levels.setdefault(json.dumps(st), []).append(i)
    opts = {k: v for k, v in inp.opts.items() if k in ("ftol", "max_iter")}
    opts["ftol"] = max(float(opts.get("ftol", 0.0)), SWEEP_FTOL)
    for part in levels.values():
        batch = fit_batch(models[part[0]], [models[i] for i in part], inp.ident, [noises[i] for i in part], inp.prior,
                          rows=torch.stack([rows[i] for i in part]), **opts)
        for i, r in zip(part, batch.results):
            model = models[i]
            model.record_data_span(inp.ident.q[rows[i]])  # its own first N poses: what extrapolation is judged by
            data = inp.ident.subset(rows[i])
            ident = residual_stats(point_residuals(model, data).cpu()).scaled(units.m_to_mm(1.0))
            row = {"status": "fitted", "converged": bool(r.success), "iterations": int(r.nit), "cost": float(r.fun),
                   "identification_mean_mm": ident.mean, "identification_max_mm": ident.max, "poses": data.n_poses,
                   "orders": structures[i][0], "backlash_orders": structures[i][1]}
            if inp.val is not None:
                val = residual_stats(point_residuals(model, inp.val).cpu()).scaled(units.m_to_mm(1.0))
                row.update(validation_mean_mm=val.mean, validation_max_mm=val.max, validation_gamma99_mm=val.gamma99)
            cell_dir = run_dir / "cells" / f"{cells[i]:02d}"
            cell_dir.mkdir(parents=True, exist_ok=True)
            atomic_write_text(cell_dir / "config.yaml", to_yaml(cfgs[i]))
            save_model(cell_dir, model, orders=structures[i][0], config_file=cfgs[i].config_file, fit=r.summary())
            out[i] = row
            log.info(f"cell {cells[i]}: orders {structures[i][0]}, {data.n_poses} poses: "
                     + (f"validation {row['validation_mean_mm']:.4f} mm" if "validation_mean_mm" in row else
                        f"identification {ident.mean:.4f} mm") + f" ({r.message}, {r.nit} iterations)")
    return out


def _compliance(cfg):
    from .fit import config_compliance

    return config_compliance(cfg)


def _fit_alone(cfg, run_dir: Path, cell: int, console) -> dict:
    """A cell the batched solve cannot take: a `torchcal fit` of its own under cells/NN."""
    from .fit import run_fit

    from .config import updated

    cfg = updated(cfg, {"out": str(run_dir / "cells" / f"{cell:02d}")})
    res = run_fit(cfg, console=None)
    sets = res.metrics.get("sets", {})
    row = {"status": "fitted", "converged": bool(res.fit.success), "iterations": int(res.fit.nit),
           "cost": float(res.fit.fun), "orders": res.metrics.get("orders")}
    ident = sets.get("identification", {}).get("modeled")
    if ident:
        row.update(identification_mean_mm=ident["mean"], identification_max_mm=ident["max"])
    val = sets.get("validation", {}).get("modeled")
    if val:
        row.update(validation_mean_mm=val["mean"], validation_max_mm=val["max"], validation_gamma99_mm=val.get("gamma99"))
    return row


def _write_results(run_dir: Path, result: SweepResult) -> None:
    import pandas as pd

    from ..io.rundir import write_json

    df = pd.DataFrame([{k: (json.dumps(v) if isinstance(v, (list, tuple)) else v) for k, v in r.items()}
                       for r in result.rows])
    with atomic_path(run_dir / "results.csv") as tmp:
        df.to_csv(tmp, index=False, float_format="%.6g")
    write_json(run_dir / "results.json", {"keys": result.keys, "time_s": result.time, "cells": result.rows})
    try:
        plot_sweep(result, run_dir / "plots" / "sweep.png")
    except Exception as exc:  # a plot must never cost the results
        log.warning(f"sweep plot not written: {exc}")


def plot_sweep(result: SweepResult, path: Path) -> Path:
    """Figure 11's layout: the held-out (else identification) mean residual against the first grid key,
    one line per combination of the other keys."""
    from ..io import plots  # noqa: F401  (selects matplotlib's file-only backend)
    import matplotlib.pyplot as plt

    rows = result.rows
    metric = "validation_mean_mm" if all("validation_mean_mm" in r for r in rows) else "identification_mean_mm"
    x_key, others = result.keys[0], result.keys[1:]
    fig, ax = plt.subplots(figsize=(7.5, 4.5))
    lines: dict[tuple, list] = {}
    for r in rows:
        lines.setdefault(tuple(r[k] for k in others), []).append(r)
    numeric = all(_is_number(r[x_key]) for r in rows)
    for label, rs in lines.items():
        rs = sorted(rs, key=lambda r: float(r[x_key]) if numeric else str(r[x_key]))
        xs = [float(r[x_key]) if numeric else str(r[x_key]) for r in rs]
        ax.plot(xs, [r.get(metric, math.nan) for r in rs], marker="o",
                label=", ".join(f"{k} {v}" for k, v in zip(others, label)) or None)
    ax.set_xlabel(x_key)
    ax.set_ylabel(("validation" if metric.startswith("validation") else "identification") + " mean residual (mm)")
    ax.set_title("Sweep (Paper II, Figure 11 layout)")
    ax.grid(alpha=0.3)
    if others:
        ax.legend(fontsize=8)
    fig.tight_layout()
    with atomic_path(path) as tmp:
        fig.savefig(tmp, dpi=110)
    plt.close(fig)
    return path


def _is_number(v) -> bool:
    try:
        float(v)
        return True
    except (TypeError, ValueError):
        return False
