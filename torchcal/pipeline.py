"""The fit pipeline behind ``torchcal fit`` and the experiments: config -> run directory.

A thin composition of library calls, in Paper II's order (5.5-5.6):

1. load the robot, tools (mm -> m) and the CSV data (identification, validation);
   when the config leaves the tool vectors (``tools: {count: T}``) or the
   measurement frame (``measurement_frame: estimate``) to the data, estimate
   them on the nominal robot first (:mod:`torchcal.identify.alignment`) ->
   ``alignment.json``; the model then starts from them (base_nominal, tools);
2. choose the Chebyshev orders if ``model.order: auto`` (:func:`select_orders`:
   on the validation set if there is one, else by leave-one-pose-out residuals or K-fold CV by pose);
3. identify the model (:func:`torchcal.identify.fit`) and write ``model.pt`` and
   ``fit.json`` at once, so that a later failure loses nothing computed;
4. evaluate nominal and modeled residuals (joint errors zero) on both sets:
   mean, max, Gamma 99 %, percent decrease (Table 6) -> ``metrics.json``;
5. for simulated data with a ``data.truth``: compensate the validation
   commands, "run" them on the simulated robot and compare with where the
   nominal model sends the tool (Table 7, Figure 16);
6. plots (Figures 12-16).

Everything inside is SI; tables and files are mm and degrees.
"""

from __future__ import annotations

import logging
import time
from contextlib import contextmanager, nullcontext
from dataclasses import dataclass, field
from pathlib import Path

import torch
from omegaconf import DictConfig

from . import units
from .analysis.stats import ResidualStats, percent_decrease, point_residuals, residual_stats
from .identify import FitResult, NoiseModel, Prior, fit
from .io.config import ConfigError, check_config, to_yaml
from .kinematics.transforms import homogeneous, rpy_to_matrix
from .io.csv import read_measurements, write_table
from .io.rundir import collect_versions, make_run_dir, run_log, save_model, write_json
from .kinematics import load_robot
from .measurements import Measurements
from .model import RobotModel

log = logging.getLogger("torchcal")

STAT_KEYS = ("mean", "max", "gamma99")


@dataclass
class RunResult:
    """What a fit run produced.

    run_dir: the run directory; model: the identified model (on the config's
    device); fit: the solver's result; metrics: what metrics.json holds (mm);
    table: Table 6 rows (mm, percent); compensation_table: Table 7 rows or
    None; orders: Chebyshev order per joint; selection: the order search
    (model.order: auto) or None; files: name -> path of everything written.
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


# --------------------------------------------------------------- config -> objects
def config_tools(cfg) -> torch.Tensor | None:
    """Tool vectors (T, 3) in metres from the config's mm; None when the config only counts them ({count: T})."""
    if isinstance(cfg.tools, (dict, DictConfig)):
        return None
    return units.mm_to_m(torch.tensor([[float(v) for v in t] for t in cfg.tools], dtype=torch.float64))


def config_tool_count(cfg) -> int:
    """T: the number of tool configurations (listed vectors or tools.count)."""
    return int(cfg.tools["count"]) if isinstance(cfg.tools, (dict, DictConfig)) else len(cfg.tools)


def config_frame(cfg) -> tuple[str, torch.Tensor | None]:
    """measurement_frame resolved: ('base', identity), ('given', (4, 4) SI) or ('estimate', None).

    'auto' is 'base' when the tool vectors are listed and 'estimate' when they are only counted.
    A given frame {xyz_mm, rpy_deg} is the robot base in the measurement frame: p = Rot(rpy) p_base + xyz.
    """
    f = cfg.measurement_frame
    if isinstance(f, (dict, DictConfig)):
        rpy = units.deg_to_rad(torch.tensor([float(v) for v in f["rpy_deg"]], dtype=torch.float64))
        xyz = units.mm_to_m(torch.tensor([float(v) for v in f["xyz_mm"]], dtype=torch.float64))
        return "given", homogeneous(rpy_to_matrix(rpy), xyz)
    if f == "auto":
        f = "estimate" if config_tools(cfg) is None else "base"
    return (f, torch.eye(4, dtype=torch.float64)) if f == "base" else (f, None)


def config_alignment(cfg, robot, data: Measurements, label: str = "config"):
    """Run :func:`torchcal.identify.alignment.align` when the config leaves tools or frame to the data.

    -> (tools_m (T, 3), base_nominal (4, 4), AlignmentResult or None); SI, on the data's device.
    Raises ConfigError (naming the config and the data file) when the data cannot determine them.
    """
    tools_m, T = config_tools(cfg), config_tool_count(cfg)
    mode, frame = config_frame(cfg)
    dev = data.xyz.device
    if tools_m is not None and mode != "estimate":
        return tools_m.to(dev), frame.to(dev), None
    from .identify.alignment import AlignmentError, align

    try:
        res = align(robot, data, T, None if tools_m is None else tools_m.to(dev),
                    None if mode == "estimate" else frame.to(dev))
    except AlignmentError as exc:
        what = " and ".join(w for w, free in (("tool vectors", tools_m is None), ("measurement frame", mode == "estimate")) if free)
        raise ConfigError(f"{label}: cannot estimate the {what} from data.identification: {exc}") from None
    return res.tools, res.base_nominal, res


def config_noise(cfg, robot) -> NoiseModel:
    """NoiseModel (SI) from noise.sigma_m (mm) and the joint variances (deg², mm² for prismatic joints)."""
    return NoiseModel.from_file_units(cfg.noise.sigma_m, list(cfg.noise.joint_var_fwd), list(cfg.noise.joint_var_bwd),
                                      robot.joint_map.prismatic.cpu())


def config_prior(cfg) -> Prior | None:
    """Prior (SI) from prior.* (deg, mm), or None when prior.enabled is false."""
    p = cfg.prior
    if not p.enabled:
        return None
    return Prior(rotation=units.deg_to_rad(p.rotation_deg), translation=units.mm_to_m(p.translation_mm),
                 frame_rotation=units.deg_to_rad(p.frame_rotation_deg), frame_translation=units.mm_to_m(p.frame_translation_mm))


def config_backlash(cfg):
    """model.backlash as RobotModel takes it: None (off), True, an int order or a per-joint list."""
    b = cfg.model.backlash
    if isinstance(b, bool):
        return True if b else None
    return list(b) if not isinstance(b, int) else int(b)


def solver_options(cfg) -> dict:
    """Keyword arguments for :func:`torchcal.identify.fit` from solver.*."""
    opts = {"method": cfg.solver.method, "ftol": float(cfg.solver.ftol)}
    if cfg.solver.max_iter is not None:
        opts["max_iter"] = int(cfg.solver.max_iter)
    return opts


def model_factory(robot, tools_m: torch.Tensor, backlash, device, base_nominal: torch.Tensor | None = None,
                  compliance=False):
    """make_model(orders) -> a fresh all-zero RobotModel on ``device`` (what :func:`select_orders` needs)."""
    base_nominal = None if base_nominal is None else base_nominal.detach().cpu()
    tools_m = tools_m.detach().cpu()

    def make(orders):
        return RobotModel(robot, tools_m, orders=list(orders) if not isinstance(orders, int) else orders,
                          backlash=backlash, base_nominal=base_nominal, compliance=compliance).to(device)

    return make


# ------------------------------------------------------------------ evaluation
def evaluate(model, data: Measurements) -> dict:
    """Nominal and modeled residuals of ``data`` (joint errors zero).

    -> {'nominal': (R,) m, 'modeled': (R,) m, 'nominal_stats' / 'modeled_stats':
    ResidualStats in mm, 'decrease': {mean, max, gamma99: percent}}.
    """
    nominal = point_residuals(model, data, nominal=True)
    modeled = point_residuals(model, data)
    mm = units.m_to_mm(1.0)
    ns, ms = residual_stats(nominal).scaled(mm), residual_stats(modeled).scaled(mm)
    return {
        "nominal": nominal, "modeled": modeled, "nominal_stats": ns, "modeled_stats": ms,
        "decrease": {k: percent_decrease(getattr(ns, k), getattr(ms, k)) for k in STAT_KEYS},
    }


def _row(set_name: str, label: str, s: ResidualStats, ref: ResidualStats | None) -> dict:
    row = {"set": set_name, "residual": label, "count": s.count}
    for k in STAT_KEYS:
        row[k] = getattr(s, k)
        row[f"{k}_decrease"] = None if ref is None else percent_decrease(getattr(ref, k), getattr(s, k))
    return row


def table6(evaluations: dict[str, dict]) -> list[dict]:
    """Paper II Table 6 rows: per data set, nominal then modeled (mm), with percent decrease against nominal."""
    rows = []
    for set_name, ev in evaluations.items():
        rows.append(_row(set_name, "Nominal", ev["nominal_stats"], None))
        rows.append(_row(set_name, "Modeled", ev["modeled_stats"], ev["nominal_stats"]))
    return rows


def compensation_targets(model, q_nom: torch.Tensor, tool: torch.Tensor) -> torch.Tensor:
    """Where compensation must put each tool (B, 3) m, measurement frame: the nominal flange F_n(q_nom)
    seen through the nominal measurement frame, carrying the identified tool vector (the tool is not
    part of the robot, so compensation cannot and should not undo its error)."""
    with torch.no_grad():
        F = model.base.nominal @ model.nominal_flange(q_nom)
        p_t = model.tools()[tool]
        return (F[:, :3, :3] @ p_t[..., None])[..., 0] + F[:, :3, 3]


def compensation_check(model, truth, data: Measurements, noise: NoiseModel | None, seed: int, **options) -> dict:
    """Paper II 5.6 on a simulated robot: compensate ``data``'s commands, measure them on ``truth``.

    -> {'result': CompensationResult, 'nominal': (R,) m residual of the
    uncompensated measurements against the nominal prediction, 'compensated':
    (R,) m residual of the measurements at the compensated commands against
    :func:`compensation_targets`, 'measured': Measurements at the compensated commands}.
    """
    from .compensate import compensate
    from .sim import simulate

    direction = data.direction if data.has_direction else None
    res = compensate(model, data.q, direction, **options)
    q_comp = res.q.detach()
    xyz = torch.empty_like(data.xyz)
    # simulate() measures every command with every listed tool, so run each tool's rows on their own
    for t in torch.unique(data.tool).tolist():
        idx = (data.tool == t).nonzero()[:, 0]
        sim_dir = data.direction[idx] if data.has_direction else None
        m = simulate(truth, q_comp[idx].to(truth.origins.device), [t], noise, seed + 7919 * (t + 1), directions=sim_dir)
        xyz[idx] = m.xyz.to(xyz)
    target = compensation_targets(model, data.q, data.tool)
    compensated = torch.linalg.norm(xyz - target, dim=-1)
    nominal = point_residuals(model, data, nominal=True)
    return {"result": res, "nominal": nominal, "compensated": compensated,
            "measured": Measurements(q_comp, data.tool, xyz, data.direction, data.pose, data.rows, data.has_direction,
                                     "compensated commands on the simulated truth")}


# ------------------------------------------------------------------ reporting
class _Progress:
    """Log lines to the run log and, when a rich console is given, a live status line on it."""

    def __init__(self, console=None):
        self.console = console
        self._status = None

    def info(self, text: str) -> None:
        log.info(text)
        if self.console is not None:
            self.console.log(text)

    def update(self, text: str) -> None:
        log.debug(text)
        if self._status is not None:
            self._status.update(text)

    @contextmanager
    def step(self, text: str):
        log.info(text)
        t0 = time.perf_counter()
        cm = self.console.status(text) if self.console is not None else nullcontext()
        with cm as status:
            self._status = status
            try:
                yield self
            finally:
                self._status = None
        self.info(f"{text} done in {time.perf_counter() - t0:.1f} s")


# ------------------------------------------------------------------- the run
def run_fit(cfg, console=None) -> RunResult:
    """Run one calibration from a config (see :mod:`torchcal.io.config`) and write its run directory.

    console: a rich Console for progress (None: quiet, the run log still records
    everything). Raises DataError / URDFError / ConfigError for bad inputs,
    before anything is computed; see :mod:`torchcal.io.rundir` for the layout.
    """
    if cfg.threads is None:
        return _run_fit(cfg, console)
    old = torch.get_num_threads()
    torch.set_num_threads(int(cfg.threads))
    try:
        return _run_fit(cfg, console)
    finally:
        torch.set_num_threads(old)


def _run_fit(cfg, console=None) -> RunResult:
    label = cfg.config_file or "config"
    robot = load_robot(cfg.robot)
    check_config(cfg, label, robot.joint_map.n)
    device = torch.device(cfg.device)
    torch.manual_seed(int(cfg.seed))
    T = config_tool_count(cfg)
    noise = config_noise(cfg, robot)
    prior = config_prior(cfg)
    opts = solver_options(cfg)

    # read every input first: a typo in the validation file should not cost a fit
    ident = read_measurements(cfg.data.identification, robot, T).to(device)
    val = read_measurements(cfg.data.validation, robot, T).to(device) if cfg.data.validation else None
    truth = None
    if cfg.data.truth:
        from .io.truth import load_truth

        truth = load_truth(cfg.data.truth, robot).to(device)
        if val is None:
            raise ConfigError(f"{label}: key 'data.truth': the compensation check runs on the validation set; set data.validation")

    # tools / measurement frame left to the data: the rigid alignment (cheap) before anything is written
    tools_m, base_nominal, alignment = config_alignment(cfg, robot, ident, label)

    run_dir = make_run_dir(cfg.out)
    files: dict[str, Path] = {}
    progress = _Progress(console)
    with run_log(run_dir):
        files["config"] = run_dir / "config.yaml"
        files["config"].write_text(to_yaml(cfg), encoding="utf-8")
        files["versions"] = write_json(run_dir / "versions.json", collect_versions(device))
        progress.info(f"run directory {run_dir}")
        progress.info(f"robot '{robot.name}' ({robot.joint_map.n} joints), {T} tools; identification "
                      f"{len(ident)} rows / {ident.n_poses} poses" + (f", validation {len(val)} rows" if val is not None else ""))
        if alignment is not None:
            files["alignment"] = write_json(run_dir / "alignment.json", alignment.summary())
            a = alignment.summary()
            what = " and ".join(w for w, free in (("measurement frame", alignment.estimated_frame),
                                                  ("tool vectors", alignment.estimated_tools)) if free)
            progress.info(f"alignment: estimated the {what} on the nominal robot ({a['start']} start, "
                          f"{alignment.iterations} iterations): residual rms {a['residual_mm']['rms']:.4f} mm, "
                          f"mean {a['residual_mm']['mean']:.4f} mm, max {a['residual_mm']['max']:.4f} mm")
            progress.info("alignment: robot base at xyz " + ", ".join(f"{v:.3f}" for v in a["frame"]["xyz_mm"])
                          + " mm, rpy " + ", ".join(f"{v:.4f}" for v in a["frame"]["rpy_deg"]) + " deg; tools "
                          + "; ".join("[" + ", ".join(f"{v:.3f}" for v in t) + "]" for t in a["tools_mm"]) + " mm")
            if not alignment.converged:
                log.warning("the alignment refinement did not converge; see alignment.json")
        make = model_factory(robot, tools_m, config_backlash(cfg), device, base_nominal, cfg.model.compliance)

        selection = None
        order = cfg.model.order
        if isinstance(order, str):  # "auto" (check_config allows no other string)
            from .identify.order import select_orders

            folds = int(cfg.model.folds)
            how = ("validation set" if val is not None else
                   "leave-one-pose-out residuals" if folds == 0 else f"{folds}-fold cross-validation")
            with progress.step(f"choosing Chebyshev orders by {how}") as p:
                selection = select_orders(make, ident, val, noise, prior, candidates=list(cfg.model.candidates),
                                          folds=folds, margin=float(cfg.model.margin), seed=int(cfg.seed), progress=p.update,
                                          joint_window=2,  # per-joint refinement near the uniform optimum: 3x fewer fits
                                          **opts)
            orders = [int(o) for o in selection.orders]
            files["orders"] = write_json(run_dir / "orders.json", {
                "orders": orders, "criterion": selection.criterion, "score_mm": units.m_to_mm(selection.score),
                "table": [{**r, "score_mm": units.m_to_mm(r["score"])} for r in selection.table]})
            progress.info(f"orders {orders} ({selection.criterion})")
        else:
            orders = [int(order)] * robot.joint_map.n if isinstance(order, int) else [int(o) for o in order]

        model = make(orders)
        with progress.step(f"identifying the model (orders {orders}, {opts['method']})") as p:
            result = fit(model, ident, noise, prior, callback=lambda it, cost: p.update(
                f"identifying ({opts['method']}): iteration {it}, cost {cost:.6g}"), **opts)
        # the model first: whatever fails later, the fit is kept
        files["model"] = save_model(run_dir, model, orders=orders, config_file=cfg.config_file)
        files["fit"] = write_json(run_dir / "fit.json", {**result.summary(), "pinned_names": list(result.pinned),
                                                          "orders": orders, "history": list(result.history)})
        progress.info(f"fit: {result.message} after {result.nit} iterations, cost {result.fun:.6g}")
        if not result.success:
            log.warning("the solver did not converge; see fit.json (raise solver.max_iter?)")

        sets = {"Identification": ident} | ({"Validation": val} if val is not None else {})
        evaluations = {name: evaluate(model, d) for name, d in sets.items()}
        table = table6(evaluations)
        metrics = {
            "units": "mm, percent",
            "orders": orders,
            "order_selection": None if selection is None else selection.criterion,
            "fit": {"converged": bool(result.success), "iterations": int(result.nit), "cost": float(result.fun)},
            "alignment": None if alignment is None else alignment.summary(),
            "sets": {name.lower(): {"rows": len(sets[name]), "poses": sets[name].n_poses,
                                    "nominal": vars(ev["nominal_stats"]), "modeled": vars(ev["modeled_stats"]),
                                    "decrease_percent": ev["decrease"]} for name, ev in evaluations.items()},
            "table6": table,
            "table7": None,
        }
        files["metrics"] = write_json(run_dir / "metrics.json", metrics)
        files["residuals"] = _write_residuals(run_dir / "residuals.csv", sets, evaluations)
        for name, ev in evaluations.items():
            s = ev["modeled_stats"]
            progress.info(f"{name.lower()}: mean {ev['nominal_stats'].mean:.4f} -> {s.mean:.4f} mm "
                          f"({ev['decrease']['mean']:.2f} % decrease), max {s.max:.4f} mm, Gamma 99 % {s.gamma99:.4f} mm")

        comp_table, comp = None, None
        if truth is not None:
            with progress.step(f"compensating {len(val)} validation commands and measuring them on the simulated truth"):
                comp = compensation_check(model, truth, val, noise, int(cfg.seed) + 1,
                                          **compensation_kwargs(cfg.compensation.tol_deg, cfg.compensation.max_iter))
            res = comp["result"]
            flagged = int((~res.converged | ~res.within_limits).sum())
            ns = evaluations["Validation"]["nominal_stats"]
            cs = residual_stats(comp["compensated"]).scaled(units.m_to_mm(1.0))
            comp_table = [_row("Validation", "Nominal", ns, None),
                          _row("Validation", "Modeled", evaluations["Validation"]["modeled_stats"], ns),
                          _row("Validation", "Compensated", cs, ns)]
            metrics["table7"] = comp_table
            ok = (res.converged & res.within_limits).cpu()
            metrics["compensation"] = {**res.summary(), "flagged": flagged, "compensated": vars(cs),
                                       # what a controller would run: flagged commands would be rejected
                                       "compensated_unflagged": vars(residual_stats(comp["compensated"].cpu()[ok]).scaled(
                                           units.m_to_mm(1.0))) if ok.any() else None}
            files["metrics"] = write_json(run_dir / "metrics.json", metrics)
            progress.info(f"compensated: mean {ns.mean:.4f} -> {cs.mean:.4f} mm "
                          f"({percent_decrease(ns.mean, cs.mean):.2f} % decrease); {flagged} commands flagged "
                          "(not converged or outside the joint range)")

        if cfg.plots:
            with progress.step("plotting"):
                files.update(_plots(run_dir / "plots", model, evaluations, comp))
        progress.info(f"done: {run_dir}")
    return RunResult(run_dir, model, result, metrics, table, comp_table, orders, selection, files)


def compensation_kwargs(tol_deg: float | None = None, max_iter: int | None = None) -> dict:
    """Keyword arguments for :func:`torchcal.compensate.compensate`: tolerance deg -> rad; None keeps its defaults.

    The tolerance is a joint-space step norm; like the paper's (51) it is one
    number for all joints (read as mm for prismatic ones, converted the same way).
    """
    out = {}
    if tol_deg is not None:
        out["tol"] = units.deg_to_rad(float(tol_deg))
    if max_iter is not None:
        out["max_iter"] = int(max_iter)
    return out


def _write_residuals(path: Path, sets: dict, evaluations: dict) -> Path:
    """Per-row residuals (mm) of every set, for plotting elsewhere."""
    import pandas as pd

    frames = []
    for name, d in sets.items():
        ev = evaluations[name]
        frames.append(pd.DataFrame({
            "set": name.lower(), "row": d.rows.cpu().numpy(), "pose": d.pose.cpu().numpy(), "tool": d.tool.cpu().numpy(),
            "nominal_mm": units.m_to_mm(ev["nominal"].cpu().numpy()), "modeled_mm": units.m_to_mm(ev["modeled"].cpu().numpy()),
        }))
    return write_table(path, pd.concat(frames, ignore_index=True))


def _plots(folder: Path, model, evaluations: dict, comp: dict | None) -> dict[str, Path]:
    from .io import plots

    out = {"plot_joint_errors": plots.plot_joint_errors(model, folder / "joint_errors.png")}
    fig = {"Identification": 14, "Validation": 15}
    for name, ev in evaluations.items():
        out[f"plot_residuals_{name.lower()}"] = plots.plot_residuals(
            ev["nominal"], ev["modeled"], folder / f"residuals_{name.lower()}.png",
            f"Nominal and modeled residuals, {name.lower()} set (Paper II, Fig. {fig[name]})")
    last = "Validation" if "Validation" in evaluations else "Identification"
    out["plot_distribution"] = plots.plot_residual_distribution(
        evaluations[last]["modeled"], folder / f"distribution_{last.lower()}.png", evaluations[last]["modeled_stats"],
        f"Modeled residuals, {last.lower()} set (Paper II, Fig. 13)")
    if comp is not None:
        out["plot_compensation"] = plots.plot_compensation(
            comp["nominal"], comp["compensated"], folder / "compensation_validation.png",
            "Nominal and compensated residuals, validation set (Paper II, Fig. 16)",
            flagged=~(comp["result"].converged & comp["result"].within_limits))
    return out


__all__ = [
    "RunResult",
    "compensation_check",
    "compensation_kwargs",
    "compensation_targets",
    "config_alignment",
    "config_frame",
    "config_tool_count",
    "config_noise",
    "config_prior",
    "config_tools",
    "evaluate",
    "model_factory",
    "run_fit",
    "solver_options",
    "table6",
]
