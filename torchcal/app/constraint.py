"""The fit pipeline's constraint stage: Paper I's slope bound (31) from a config's ``constraint:`` section.

``constraint.c``:

- null: the unconstrained MLE (:func:`torchcal.fit`);
- a number (mm per half axis range): :func:`torchcal.identify.constrained.fit_constrained`;
- auto: BORDER in a two-axis space, the constraint sweep on the sub-identification
  set, the knee, and a refit on all data with it
  (:func:`torchcal.identify.constrained.auto_constraint`, Paper I 3.4, Figure 14).

The same stage serves machine tools (axis perturbation model) and robots
(Paper II's model: the slope of the modeled tool-point error per joint).
Everything it decides goes to ``constraint.json`` and the run log.
"""

from __future__ import annotations

import logging
import math
from pathlib import Path

import torch

from ..core import units
from ..identify import FitResult
from ..identify.constrained import ConstraintError, auto_constraint, fit_constrained
from ..identify.slope import slope_model
from .config import ConfigError, source_of
from ..io.rundir import save_model, write_json

log = logging.getLogger("torchcal")

XYZCB_BORDER_AXES = ("B", "Z")
"""Paper I's BORDER space for the XYZCB machine (Figures 2, 3, 11)."""


def border_axes(cfg, robot, data) -> tuple[int, int]:
    """The two axis indices BORDER works in: ``constraint.border_axes`` by name, else B and Z where the
    machine has them (Paper I), else the two joints whose identification data span least of their range."""
    names = list(robot.joint_map.names)
    given = cfg.constraint.border_axes
    if given is not None:
        missing = [a for a in given if a not in names]
        if missing:
            raise ConfigError(f"{source_of(cfg, 'constraint.border_axes', cfg.config_file or 'config')}: key 'constraint.border_axes': {missing} "
                              f"{'is not an axis' if len(missing) == 1 else 'are not axes'} of '{robot.name}' "
                              f"(axes: {', '.join(names)})")
        return names.index(given[0]), names.index(given[1])
    if all(a in names for a in XYZCB_BORDER_AXES):
        return names.index(XYZCB_BORDER_AXES[0]), names.index(XYZCB_BORDER_AXES[1])
    lim = robot.joint_map.limits.to(data.q)
    span = (data.q.amax(0) - data.q.amin(0)) / (lim[:, 1] - lim[:, 0])
    a, b = sorted(torch.argsort(span)[:2].tolist())
    return a, b


def _solver_options(inp) -> dict:
    opts = dict(inp.opts)
    opts.pop("callback", None)
    return opts


def identify_constrained(cfg, inp, make, orders, run_dir: Path, progress, files: dict, data=None,
                         fit_options: dict | None = None):
    """Stage 5 with ``constraint.c`` set: -> (model, FitResult of the final inner fit, summary dict).

    data: the identification rows (default ``inp.ident``); fit_options: more keyword arguments of
    :func:`~torchcal.identify.constrained.fit_constrained` (a sensor run's ``instrument`` and ``fixed``:
    the bound is then on its robot model's error at the sensor origin).
    Writes model.pt, fit.json and constraint.json at once. A c whose constrained fit fails keeps the
    partial model (written, with the failure in constraint.json) and raises the ConstraintError.
    """
    c_cfg = cfg.constraint
    opts = {**_solver_options(inp), **(fit_options or {})}
    data = inp.ident if data is None else data
    base_make = make

    def make(o):  # noqa: F811 (the factory with the slope's reference set)
        m = base_make(o)
        if c_cfg.reference != "nominal":
            inner = slope_model(m)[0]
            if not hasattr(inner, "joint_errors"):
                raise ConfigError(f"{source_of(cfg, 'constraint.reference', cfg.config_file or 'config')}: key 'constraint.reference': 'constant' is for robot "
                                  "models (model.kind: joint_dependent)")
            inner.slope_reference = c_cfg.reference
        return m

    common = dict(points=int(c_cfg.points), check_points=int(c_cfg.check_points), tol=float(c_cfg.tol),
                  seed=int(cfg.seed), **opts)
    summary: dict = {"units": "mm per half axis range", "c": None}
    if c_cfg.c == "auto":
        axes = border_axes(cfg, inp.robot, data)
        names = [inp.robot.joint_map.names[a] for a in axes]
        c_values = None if c_cfg.sweep is None else [units.mm_to_m(float(v)) for v in c_cfg.sweep]
        try:
            with progress.step(f"choosing c: BORDER in ({', '.join(names)}) space, k = {c_cfg.border_k}, "
                               f"{c_cfg.border_n} poses; constraint sweep"):
                auto = auto_constraint(lambda: make(orders), data, border_axes=axes, border_k=int(c_cfg.border_k),
                                       border_n=int(c_cfg.border_n), c_values=c_values,
                                       tol_mm=float(c_cfg.knee_tol_mm), noise=inp.noise, prior=inp.prior, **common)
        except KeyboardInterrupt as exc:  # the bounds fitted by then are minutes of work: written down, not lost
            part = getattr(exc, "sweep", None)
            if part is not None:
                summary.update(mode="auto", interrupted=True, border_axes=names, sweep=part.table(),
                               knee_tol_mm=float(c_cfg.knee_tol_mm))
                files["constraint"] = write_json(run_dir / "constraint.json", summary)
                progress.warn(f"interrupted: the constraint sweep's {len(part.c)} bound(s) fitted by then are in "
                              f"{files['constraint']}; constraint.c=VALUE fits one bound without the sweep")
            raise
        model, res = auto.model, auto.result
        summary.update(mode="auto", border_axes=names, boundary_rows=int(auto.boundary_index.sum()),
                       sweep=auto.sweep.table(), knee_tol_mm=float(c_cfg.knee_tol_mm))
        c = auto.c
        progress.info("constraint sweep (sub-identification mean, boundary max, mm):")
        for row in auto.sweep.table():
            progress.info("  " + ", ".join(f"{k} {v:.4f}" if isinstance(v, float) else f"{k} {v}" for k, v in row.items()))
        progress.info(f"knee: c = {'inf' if math.isinf(c) else f'{units.m_to_mm(c):.4f} mm'} "
                      f"(tolerance {c_cfg.knee_tol_mm} mm)")
    else:
        c = units.mm_to_m(float(c_cfg.c))
        model = make(orders)
        summary["mode"] = "given"
        with progress.step(f"identifying with the slope bound c = {c_cfg.c} mm (constrained Levenberg-Marquardt)"):
            try:
                res = fit_constrained(model, data, c, inp.noise, inp.prior, **common)
            except ConstraintError as exc:
                summary.update(error=str(exc), result=None if exc.result is None else exc.result.summary())
                files["model"] = save_model(run_dir, model, orders=orders, config_file=cfg.config_file, constraint=summary)
                files["constraint"] = write_json(run_dir / "constraint.json", summary)
                raise
    summary["c"] = None if c is None or math.isinf(c) else units.m_to_mm(c)
    summary["result"] = res.summary() if hasattr(res, "summary") else None
    fit_result: FitResult = res.fit if getattr(res, "fit", None) is not None else res
    files["model"] = save_model(run_dir, model, orders=orders, config_file=cfg.config_file, constraint=summary)
    files["fit"] = write_json(run_dir / "fit.json", {**fit_result.summary(), "pinned_names": list(fit_result.pinned),
                                                      "orders": orders, "history": list(fit_result.history)})
    files["constraint"] = write_json(run_dir / "constraint.json", summary)
    if summary["result"] is not None:
        r = summary["result"]
        progress.info(f"slope bound: largest |h̄| {r['max_slope_mm']:.4f} mm at the {r['points']} penalty points, "
                      f"{r['max_slope_check_mm']:.4f} mm at {r['check_points']} fresh points (c = {summary['c']} mm)")
        if not r["converged"]:
            progress.warn(f"the constrained fit did not meet the bound: {r['message']}")
    return model, fit_result, summary
