"""The fit pipeline behind ``torchcal fit`` and the experiments: config -> run directory.

Why one module: the stages of one fit in Paper II's order (5.5-5.6) and the config -> objects helpers they share; each stage is a function, :func:`run_fit` reads top to bottom.

A thin composition of library calls, in Paper II's order (5.5-5.6); each stage
is one function of this module, and :func:`run_fit` calls them in turn:

1. :func:`load_inputs`: the robot, config checks against it, the noise (the
   config's joint variances or the robot's ``repeatability:``), prior, solver
   options, the CSV data (identification, validation) and the truth;
2. :func:`align_inputs`: when the config leaves the tool vectors
   (``tools: {count: T}``) or the measurement frame (``measurement_frame:
   estimate``) to the data, estimate them on the nominal robot first
   (:mod:`torchcal.identify.alignment`); the model then starts from them;
3. :func:`write_preamble`: the run directory's config.yaml, versions.json,
   alignment.json and the first log lines;
4. :func:`choose_orders` (build): the Chebyshev orders, searched if
   ``model.order: auto`` (:func:`select_orders`: on the validation set if there
   is one, else by leave-one-pose-out residuals or K-fold CV by pose);
5. :func:`identify_model` (fit): :func:`torchcal.identify.fit`, then
   ``model.pt`` and ``fit.json`` at once, so that a later failure loses nothing;
6. :func:`check_data`: what the data cannot determine (never-measured tools,
   too few poses, one-sided backlash, parameters pinned beyond the model's own
   redundancy), as warnings;
7. :func:`evaluate_sets` (evaluate): nominal and modeled residuals (joint
   errors zero) on both sets: mean, max, Gamma 99 %, percent decrease (Table 6)
   -> ``metrics.json``, with a warning when the nominal residual is implausible;
8. :func:`check_compensation` (compensate-check), for simulated data with a
   ``data.truth``: compensate the validation commands, "run" them on the
   simulated robot and compare with where the nominal model sends the tool
   (Table 7, Figure 16);
9. plots (Figures 12-16), drawn by a second process (:class:`torchcal.io.plots.PlotWorker`)
   that gets each figure as soon as its data exist, while the stages above go on.

Every stage is a progress task (:mod:`torchcal.core.progress`): the CLI shows a bar on
a terminal and plain lines elsewhere, and run.log gets the lines
(:mod:`torchcal.io.progress_view`). Everything inside is SI; tables and files are mm and degrees.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass, field
from pathlib import Path

import torch
from collections.abc import Mapping

from ..core import threads, units
from ..analysis.stats import far_rows, far_rows_message, percent_decrease, point_residuals, residual_stats
from ..identify import FitResult, NoiseModel, Prior, fit
from ..identify.fit import frame_check
from .config import ConfigError, check_config, source_of
from ..kinematics.transforms import homogeneous, rpy_to_matrix
from ..io.csv import DataError, read_measurements, write_table
from ..io.rundir import make_run_dir, placed_note, run_log, save_model, write_json
from ..kinematics import load_robot
from ..core.measurements import Measurements
from ..models.robot import RobotModel
from .files import compensation_dof, compensation_kwargs  # the compensation check uses compensate's options
from .common import (  # shared with app.sensor; re-exported here under the old names
    write_run_report,
    worse_than_nominal,
    NOMINAL_IMPLAUSIBLE_MM,
    STAT_KEYS,
    RunResult,
    collect_warnings,
    Progress,
    stats_row,
    config_backlash,
    config_compliance,
    config_error_variable,
    config_noise,
    config_orders,
    config_prior,
    joint_variance_source,
    placement_text,
    solver_options,
    tools_text,
    write_preamble_files,
    changed_inputs,
    missing_directions_note,
)

log = logging.getLogger("torchcal")


# --------------------------------------------------------------- config -> objects
def config_tools(cfg) -> torch.Tensor | None:
    """Tool vectors (T, 3) in metres from the config's mm; None when the config only counts them ({count: T})."""
    if isinstance(cfg.tools, Mapping):
        return None
    return units.mm_to_m(torch.tensor([[float(v) for v in t] for t in cfg.tools], dtype=torch.float64))


def config_tool_count(cfg) -> int:
    """T: the number of tool configurations (listed vectors or tools.count)."""
    return int(cfg.tools["count"]) if isinstance(cfg.tools, Mapping) else len(cfg.tools)


def config_frame(cfg) -> tuple[str, torch.Tensor | None]:
    """measurement_frame resolved: ('base', identity), ('given', (4, 4) SI) or ('estimate', None).

    'auto' is 'base' when the tool vectors are listed and 'estimate' when they are only counted.
    A given frame {xyz_mm, rpy_deg} is the robot base in the measurement frame: p = Rot(rpy) p_base + xyz.
    """
    f = cfg.measurement_frame
    if isinstance(f, Mapping):
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
    from ..identify.alignment import AlignmentError, align

    try:
        res = align(robot, data, T, None if tools_m is None else tools_m.to(dev),
                    None if mode == "estimate" else frame.to(dev))
    except AlignmentError as exc:
        what = " and ".join(w for w, free in (("tool vectors", tools_m is None), ("measurement frame", mode == "estimate")) if free)
        raise ConfigError(f"{label}: cannot estimate the {what} from data.identification: {exc}") from None
    return res.tools, res.base_nominal, res


class ModelFactory:
    """make(orders[, backlash]) -> a fresh all-zero RobotModel on ``device`` (what :func:`select_orders` needs).

    ``backlash`` (attribute): the backlash orders used when none are passed; the
    order search sets it when it chooses them. error_variable: None keeps the
    robot's (its YAML's ``error_variable:``), else 'command' / 'joint' / per joint.
    """

    def __init__(self, robot, tools_m, backlash, device, base_nominal=None, compliance=False, error_variable=None,
                 backlash_on: str = "joint"):
        self.robot, self.backlash, self.device, self.compliance = robot, backlash, device, compliance
        self.tools_m = tools_m.detach().cpu()
        self.base_nominal = None if base_nominal is None else base_nominal.detach().cpu()
        self.extra = {} if error_variable is None else {"error_variable": error_variable}
        if backlash_on != "joint":
            self.extra["backlash_on"] = backlash_on

    def __call__(self, orders, backlash="default"):
        return RobotModel(self.robot, self.tools_m, orders=list(orders) if not isinstance(orders, int) else orders,
                          backlash=self.backlash if backlash == "default" else backlash, base_nominal=self.base_nominal,
                          compliance=self.compliance, **self.extra).to(self.device)


class MachineFactory:
    """make(orders) -> a fresh all-zero :class:`torchcal.models.machine.MachineModel` (Paper I) on ``device``.

    orders: an int (every table) or one order per INPUT axis j (the order of every f_ij(q_j)).
    """

    backlash = None  # the axis perturbation model has no direction term

    def __init__(self, robot, tools_m, device, base_nominal=None):
        self.robot, self.device = robot, device
        self.tools_m = tools_m.detach().cpu()
        self.base_nominal = None if base_nominal is None else base_nominal.detach().cpu()

    def __call__(self, orders, backlash="default"):
        from ..models.machine import MachineModel

        if not isinstance(orders, int):
            orders = [int(o) for o in orders]
            n = len(orders)
            orders = orders[0] if len(set(orders)) == 1 else torch.tensor(orders, dtype=torch.long).expand(n, n).clone()
        return MachineModel(self.robot, self.tools_m, orders=orders, base_nominal=self.base_nominal).to(self.device)


def model_factory(robot, tools_m: torch.Tensor, backlash, device, base_nominal: torch.Tensor | None = None,
                  compliance=False, error_variable=None, kind: str = "joint_dependent", backlash_on: str = "joint"):
    """make_model(orders) -> a fresh all-zero model on ``device``: a :class:`ModelFactory` (RobotModel, Paper II)
    or, for ``kind='axis_perturbation'``, a :class:`MachineFactory` (MachineModel, Paper I)."""
    if kind == "axis_perturbation":
        return MachineFactory(robot, tools_m, device, base_nominal)
    return ModelFactory(robot, tools_m, backlash, device, base_nominal, compliance, error_variable, backlash_on)


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


def table6(evaluations: dict[str, dict]) -> list[dict]:
    """Paper II Table 6 rows: per data set, nominal then modeled (mm), with percent decrease against nominal."""
    rows = []
    for set_name, ev in evaluations.items():
        rows.append(stats_row(set_name, "Nominal", ev["nominal_stats"], None))
        rows.append(stats_row(set_name, "Modeled", ev["modeled_stats"], ev["nominal_stats"]))
    return rows


def compensation_targets(model, q_nom: torch.Tensor, tool: torch.Tensor) -> torch.Tensor:
    """Where compensation must put each tool (B, 3) m, measurement frame: the nominal flange F_n(q_nom)
    seen through the nominal measurement frame, carrying the identified tool set's frame in its place
    (:mod:`torchcal.compensate.toolset`): each tool lands on the nominal robot's point for its nominal
    vector, up to the tool set's own non-rigid difference (a bent tool is not the robot's error, so
    compensation cannot and should not undo it)."""
    from ..compensate.toolset import compensation_goal

    with torch.no_grad():
        F = model.base.nominal @ compensation_goal(model, q_nom)
        p_t = model.tools()[tool]
        return (F[:, :3, :3] @ p_t[..., None])[..., 0] + F[:, :3, 3]


def compensation_check(model, truth, data: Measurements, noise: NoiseModel | None, seed: int, **options) -> dict:
    """Paper II 5.6 on a simulated robot: compensate ``data``'s commands, measure them on ``truth``.

    -> {'result': CompensationResult, 'nominal': (R,) m residual of the
    uncompensated measurements against the nominal prediction, 'compensated':
    (R,) m residual of the measurements at the compensated commands against
    :func:`compensation_targets`, 'measured': Measurements at the compensated commands}.
    """
    from ..compensate import compensate, row_tool_points
    from ..sim import simulate

    direction = data.direction if data.has_direction else None
    if (options.get("position_only") or options.get("free_tool_axis") is not None) and "tool_point" not in options:
        options = dict(options, tool_point=row_tool_points(model, data.tool))  # 3- / 5-DOF: the row's tool point
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




# ------------------------------------------------------------------- the stages
@dataclass
class FitInputs:
    """Stage 1 (:func:`load_inputs`): everything read and checked before anything is computed or written.

    robot; T: tool count; noise (SI) and noise_source (log line); prior; opts: solver keyword
    arguments; ident / val: Measurements on ``device`` (val None without a validation set); truth: the
    simulated truth or None; label: the config file (for messages); notes: warnings from reading.
    """

    robot: object
    T: int
    noise: NoiseModel
    noise_source: str
    prior: Prior | None
    opts: dict
    ident: Measurements
    val: Measurements | None
    truth: object | None
    device: torch.device
    label: str
    notes: list[str] = field(default_factory=list)


def first_poses(data: Measurements, count: int, label: str = "config") -> Measurements:
    """The rows of the first ``count`` poses of ``data`` in file order (``data.n_poses``); a ConfigError if it has fewer."""
    ids, slot = torch.unique(data.pose, return_inverse=True)
    first_row = torch.full((ids.numel(),), len(data), dtype=torch.long, device=data.pose.device)
    first_row = first_row.scatter_reduce(0, slot, torch.arange(len(data), device=data.pose.device), reduce="amin")
    ranked = ids[torch.argsort(first_row)]  # pose ids in order of first appearance
    if count > ranked.numel():
        raise ConfigError(f"{label}: key 'data.n_poses': {count} poses asked for, {data.source} has {ranked.numel()}")
    return data.poses_subset(ranked[:count])


def load_inputs(cfg) -> FitInputs:
    """Stage 1, load: robot, config checks against it, noise, prior, solver options, the CSV files, the truth.

    Reads every input first: a typo in the validation file should not cost a fit.
    Raises DataError / URDFError / ConfigError / TruthError naming the file and key.
    """
    label = cfg.config_file or "config"
    notes: list[str] = []  # warnings while reading (a URDF joint without <axis>, a European CSV), for the run log
    with collect_warnings(notes):
        robot = load_robot(cfg.robot)
    check_config(cfg, label, robot.joint_map.n)
    device = torch.device(cfg.device)
    torch.manual_seed(int(cfg.seed))
    T = config_tool_count(cfg)
    noise = config_noise(cfg, robot, label)
    try:
        ident, val = read_sets(cfg, robot, T, cfg.data.identification, cfg.data.validation, notes, device, label)
    except DataError as exc:
        script = Path(cfg.config_file).parent / "run.py" if cfg.config_file else None
        missing = [f for f in (cfg.data.identification, cfg.data.validation) if f and not Path(f).exists()]
        if missing and script is not None and script.is_file():  # an experiment's config: its script writes the data
            exc.args = (f"{exc}\n  this config's data are written by its experiment: run `python {script}` first",)
        raise
    if val is not None and not val.has_direction and config_backlash(cfg) is not None:
        # its residuals (and model.order: auto's choice, judged on them) leave the lost motion out: 0.19 mm where
        # the same rows with directions gave 0.045
        notes.append(missing_directions_note(f"validation set {cfg.data.validation}", robot.joint_map.n)
                     + ("; model.order: auto judges the orders on these residuals" if cfg.model.order == "auto" else ""))
    truth = None
    if cfg.data.truth:
        from ..io.truth import load_truth

        truth = load_truth(cfg.data.truth, robot).to(device)
    notes.extend(changed_inputs(cfg))
    return FitInputs(robot, T, noise, joint_variance_source(cfg, robot), config_prior(cfg), solver_options(cfg),
                     ident, val, truth, device, label, notes)


def read_sets(cfg, robot, T: int, identification, validation, notes: list[str], device, label: str = "config"):
    """The identification and (optional) validation files of a config -> (ident, val or None) on ``device``,
    with ``data.n_poses`` applied and the unit-slip checks (unless ``data.units_checked``); warnings go to
    ``notes``. Raises DataError naming the file, row and column."""
    with collect_warnings(notes):
        ident = read_measurements(identification, robot, T).to(device)
        val = read_measurements(validation, robot, T).to(device) if validation else None
    if cfg.data.n_poses is not None:
        ident = first_poses(ident, int(cfg.data.n_poses), source_of(cfg, "data.n_poses", label))
    if not cfg.data.units_checked:
        from ..io.unit_checks import check_units, units_note

        for d in (ident, val):
            if d is None:
                continue
            note = units_note(d, robot, *check_units(d, robot, config_tools(cfg)), "data.units_checked=true")
            if note:  # a slip the points confirm was refused above
                notes.append(note)
    return ident, val


def align_inputs(cfg, inp: FitInputs):
    """Stage 2, align: tools / measurement frame left to the data -> (tools_m, base_nominal, AlignmentResult or None).

    The rigid alignment is cheap and runs before anything is written (see :func:`config_alignment`).
    """
    return config_alignment(cfg, inp.robot, inp.ident, inp.label)


def write_preamble(run_dir: Path, cfg, inp: FitInputs, alignment, progress: Progress, files: dict) -> None:
    """Stage 3, start the run directory: config.yaml, versions.json, what was read (and how), alignment.json."""
    write_preamble_files(run_dir, cfg, inp.device, files)
    progress.info(f"run directory {run_dir}{placed_note(cfg.out, run_dir)}")
    ident, val = inp.ident, inp.val
    progress.info(f"robot '{inp.robot.name}' ({inp.robot.joint_map.n} joints), {inp.T} tools; identification "
                  f"{len(ident)} rows / {ident.n_poses} poses" + (f", validation {len(val)} rows" if val is not None else ""))
    progress.info(f"joint variances: {inp.noise_source}; tracker sigma {cfg.noise.sigma_m:g} mm (noise.sigma_m)")
    for note in inp.notes:
        progress.warn(note)
    if alignment is None:
        return
    a = alignment.summary()
    files["alignment"] = write_json(run_dir / "alignment.json", a)
    what = " and ".join(w for w, free in (("measurement frame", alignment.estimated_frame),
                                          ("tool vectors", alignment.estimated_tools)) if free)
    progress.info(f"alignment: estimated the {what} on the nominal robot ({a['start']} start, "
                  f"{alignment.iterations} iterations): residual rms {a['residual_mm']['rms']:.4f} mm, "
                  f"mean {a['residual_mm']['mean']:.4f} mm, max {a['residual_mm']['max']:.4f} mm")
    progress.info(f"alignment: {placement_text(a)}; tools {tools_text(a['tools_mm'])} mm")
    if not alignment.converged:
        progress.warn("the alignment refinement did not converge; see alignment.json")


def choose_orders(cfg, inp: FitInputs, make, run_dir: Path, progress: Progress, files: dict):
    """Stage 4, build: the Chebyshev orders per joint -> (orders, OrderSelection or None).

    ``model.order: auto`` searches them (validation set, else leave-one-pose-out or K-fold CV) and writes
    orders.json; otherwise the config's int or list.
    """
    order = cfg.model.order
    if not isinstance(order, str):
        orders = config_orders(cfg, inp.robot.joint_map.n)
        if make.backlash is True and cfg.prior.fleet is not None:
            # the prior describes the fleet's structure: a few poses' own choice could differ from it
            from .fleet_prior import fleet_backlash_orders

            make.backlash = fleet_backlash_orders(cfg.prior.fleet)
            progress.info(f"backlash orders {make.backlash}: the fleet's (prior.fleet)")
        elif make.backlash is True and inp.ident.has_direction:
            # backlash on without an order: its order follows the data (identifiable where directions do not
            # follow positions), never eps_z's order blindly
            from ..identify.backlash import default_backlash_orders

            make.backlash, r2 = default_backlash_orders(orders, inp.ident.q, inp.ident.direction,
                                                        inp.robot.joint_map.limits.to(inp.ident.q))
            progress.info(f"backlash orders {make.backlash}: direction explained by position R² "
                          + ", ".join(f"{x:.2f}" for x in r2) + " (below 0.1: the joint's order, at most 3; else 2)")
        return orders, None
    from ..identify.order import select_orders  # "auto": check_config allows no other string

    folds = int(cfg.model.folds)
    how = ("validation set" if inp.val is not None else
           "leave-one-pose-out residuals" if folds == 0 else f"{folds}-fold cross-validation")
    with progress.step(f"choosing Chebyshev orders by {how}") as p:
        selection = select_orders(make, inp.ident, inp.val, inp.noise, inp.prior, candidates=list(cfg.model.candidates),
                                  folds=folds, margin=float(cfg.model.margin), seed=int(cfg.seed), progress=p.update,
                                  joint_window=2,  # per-joint refinement near the uniform optimum: 3x fewer fits
                                  **inp.opts)
    orders = [int(o) for o in selection.orders]
    record = {"orders": orders, "criterion": selection.criterion, "score_mm": units.m_to_mm(selection.score),
              "table": [{**r, "score_mm": units.m_to_mm(r["score"])} for r in selection.table]}
    if make.backlash is True and inp.ident.has_direction:
        # backlash switched on without an order: its own order is chosen too, after the joints' (never tied to eps_z's)
        from ..identify.backlash import select_backlash_orders

        with progress.step("choosing the backlash orders") as p:
            bsel = select_backlash_orders(make, orders, inp.ident, inp.val, inp.noise, inp.prior, folds=folds,
                                          margin=float(cfg.model.margin), seed=int(cfg.seed), progress=p.update,
                                          warm=selection.fitted, **inp.opts)
        make.backlash = [int(b) for b in bsel.orders]
        record["backlash_orders"] = make.backlash
        record["backlash_table"] = [{**r, "score_mm": units.m_to_mm(r["score"])} for r in bsel.table]
        progress.info(f"backlash orders {make.backlash} ({bsel.criterion}; -1: off)")
    files["orders"] = write_json(run_dir / "orders.json", record)
    progress.info(f"orders {orders} ({selection.criterion})")
    return orders, selection


def identify_model(cfg, inp: FitInputs, model, orders, run_dir: Path, progress: Progress, files: dict) -> FitResult:
    """Stage 5, fit: identify ``model`` in place and write model.pt and fit.json at once (a later failure loses nothing)."""
    opts = inp.opts
    fleet = None
    if cfg.prior.fleet is not None:
        fleet = fleet_prior_for(cfg, model, progress)
        # the fleet's prior fixes what few poses cannot (its gauge pins included): no gauge fixing of our own,
        # which would pin those entries at the start instead
        opts = {**opts, "blocks": [*opts.get("blocks", []), fleet.block], "gauge": False}
    with progress.step(f"identifying the model (orders {orders}, {opts['method']})") as p:
        result = fit(model, inp.ident, inp.noise, inp.prior, callback=lambda it, cost: p.update(
            f"iteration {it}, cost {cost:.6g}"), **opts)
    tension = None if fleet is None else _prior_tension(inp, model, result, fleet, opts)
    files["model"] = save_model(run_dir, model, orders=orders, config_file=cfg.config_file)
    files["fit"] = write_json(run_dir / "fit.json", {**result.summary(), "pinned_names": list(result.pinned),
                                                      "orders": orders, "history": list(result.history),
                                                      "fleet_prior": None if fleet is None else
                                                      {**fleet.summary(cfg.prior.fleet),
                                                       "tension": None if tension is None else tension.summary()}})
    progress.info(f"fit: {result.message} after {result.nit} iterations, cost {result.fun:.6g}")
    if not result.success:
        progress.warn("the solver did not converge; see fit.json (raise solver.max_iter?)")
    if tension is not None:
        _say_prior_tension(tension, progress)
    return result


def _prior_tension(inp: FitInputs, model, result: FitResult, fleet, opts: dict):
    """How far the unit lies from the fleet prior against its data (:func:`torchcal.identify.fleet_prior.
    prior_tension`), or None where it cannot be judged (logged: a diagnostic must not cost the run)."""
    from ..analysis.identifiability import pin_entries
    from ..identify import CalibrationProblem
    from ..identify.fleet_prior import prior_tension

    try:
        problem = CalibrationProblem(model, inp.ident, inp.noise, inp.prior, opts.get("fixed", ()))
        pin_entries(problem, result.pinned)
        return prior_tension(fleet.block, problem, problem.layout.get().to(model.device), result.v)
    except Exception as exc:
        log.warning("fleet prior tension skipped: %s: %s", type(exc).__name__, exc)
        return None


def _say_prior_tension(t, progress: Progress) -> None:
    """The tension said, and warned about beyond :data:`~torchcal.identify.fleet_prior.TENSION_WARN`: a unit with a
    damaged gearbox and 30 poses fitted 0.034 mm on its poses, 0.17 mm off the robot, and said nothing."""
    from ..identify.fleet_prior import TENSION_WARN

    pos = sum(max(share, 0.0) for _, share in t.groups)  # a correlated prior's cross terms can be negative
    top = ", ".join(f"{g} {share / pos:.0%}" for g, share in t.groups[:2] if share > 0) if pos > 0 else "none"
    progress.info(f"distance from the fleet prior: d² {t.d2:.0f} against {t.expected:.0f} ± {t.sd:.0f} for a unit like "
                  f"the fleet's on these data ({t.ratio:.2f}x; most in {top})")
    if t.ratio > TENSION_WARN and t.d2 > t.expected + 4.0 * t.sd:  # few directions seen: d^2 alone scatters wide
        progress.warn(f"the unit lies {t.ratio:.1f}x farther from the fleet than the fleet's spread explains for these "
                      f"data (d² {t.d2:.0f} against {t.expected:.0f} ± {t.sd:.0f}; most in {top}): a damaged part or "
                      "another kind of unit, which the fleet's prior holds toward the fleet while its few poses fit "
                      "well (a helper's unit with a worn J3 gearbox, 30 poses: 0.17 mm off the robot, 0.02 mm with "
                      "250 poses alone); measure more poses and fit it without prior.fleet")


def compare_with_alone(inp, make, orders, evaluations: dict, progress) -> dict:
    """The unit fitted alone on the same data (no fleet prior: the config's prior and solver, its own gauge
    fixing, from zero), against its fit with the fleet's prior (``evaluations``: that fit's, from
    :func:`evaluate_sets`). -> {'alone': {set: {mean, max, gamma99}}, 'with_prior': likewise (mm),
    'alone_converged'}, for metrics.json; one line of it to ``progress``.

    The validation set says which models the robot better; the identification set, where there is no other,
    mixes accuracy with how closely each fit follows those few poses (said so)."""
    alone = make(orders)
    result = fit(alone, inp.ident, inp.noise, inp.prior, **inp.opts)
    sets = {"identification": inp.ident} | ({"validation": inp.val} if inp.val is not None else {})

    def stats(ev):
        return {k: float(getattr(ev, k)) for k in ("mean", "max", "gamma99")}

    out = {"alone": {name: stats(evaluate(alone, d)["modeled_stats"]) for name, d in sets.items()},
           "with_prior": {name.lower(): stats(ev["modeled_stats"]) for name, ev in evaluations.items()},
           "alone_converged": bool(result.success)}
    key = "validation" if inp.val is not None else "identification"
    a, w = out["alone"][key], out["with_prior"][key]
    progress.info(f"the same unit fitted alone (no fleet prior): {key} mean {a['mean']:.4f} mm, max {a['max']:.4f} mm; "
                  f"with the fleet's prior {w['mean']:.4f} mm, max {w['max']:.4f} mm"
                  + ("" if inp.val is not None else " (on the identification poses; give data.validation to "
                                                    "compare on poses neither fit saw)"))
    return out


def fleet_prior_for(cfg, model, progress: Progress):
    """``prior.fleet``: the fleet run's prior (:func:`torchcal.app.fleet_prior.prior_from_fleet_run`) for ``model``, whose
    parameters are set to the fleet's mean (the fit's start). Raises ConfigError when the model's structure is
    not the fleet's."""
    from ..identify.layout import ParameterLayout
    from .fleet_prior import prior_from_fleet_run

    fleet = prior_from_fleet_run(cfg.prior.fleet, cfg.prior.fleet_method, model.device, model.robot)
    layout = ParameterLayout(model)
    if layout.names() != fleet.names:
        mine, theirs = set(layout.names()), set(fleet.names)
        diff = sorted(mine ^ theirs)[:3]
        raise ConfigError(f"{source_of(cfg, 'prior.fleet', cfg.config_file or 'config')}: key 'prior.fleet': the fleet's units have another model "
                          f"structure ({len(theirs)} entries, this model {len(mine)}; e.g. {diff}): give model.order "
                          f"and model.backlash as in a unit's config.yaml there (units/<name>/config.yaml)")
    layout.set(fleet.mean.to(model.dtype))
    progress.info(f"prior: the fleet {cfg.prior.fleet} ({len(fleet.units)} units, {fleet.method} covariance; left out: "
                  f"{', '.join(fleet.left_out) or 'none'})")
    return fleet


def structural_pins(make, orders, inp: FitInputs, poses: int | None = None, seed: int = 0) -> list[str]:
    """Parameters the model itself leaves undetermined (redundant constants, Paper II (18)), whatever the data.

    The gauge fixing (:func:`torchcal.identify.fix_gauge`) on rich synthetic data: quasi-random
    commands over the controller range, both approach directions at random, every tool; its pinned
    names are what any data set pins. What a fit pins beyond them, its data cannot determine.
    """
    from ..identify import CalibrationProblem, fix_gauge

    model = make(orders)
    dev = inp.ident.q.device
    P = CalibrationProblem(model, inp.ident, inp.noise, inp.prior).layout.size
    poses = poses or max(64, P // max(inp.T, 1) + 32)
    # torch's own Sobol engine: which names are pinned does not depend on the points, and scipy.stats
    # (torchcal.sim's sampler) costs 1-3 s to import on every fit
    lim = inp.robot.joint_map.limits.to(dev)
    u = torch.quasirandom.SobolEngine(lim.shape[0], scramble=True, seed=seed).draw(poses, dtype=torch.float64).to(dev)
    q = lim[:, 0] + u * (lim[:, 1] - lim[:, 0])
    g = torch.Generator().manual_seed(seed)
    s = torch.where(torch.rand(poses, q.shape[1], generator=g, dtype=torch.float64) > 0.5, 1.0, -1.0).to(q)
    R = poses * inp.T
    tool = torch.arange(inp.T, device=dev).repeat(poses)
    qr, sr = q.repeat_interleave(inp.T, 0), s.repeat_interleave(inp.T, 0)
    with torch.no_grad():
        xyz = model.nominal_points(qr, tool)
    data = Measurements(qr, tool, xyz, sr, torch.arange(poses, device=dev).repeat_interleave(inp.T),
                        torch.arange(1, R + 1, device=dev), True, "synthetic gauge check")
    return fix_gauge(CalibrationProblem(model, data, inp.noise, inp.prior))


def _names_short(names: list[str], limit: int = 12) -> str:
    """'joint2.eps_x.c1, ...' with a count of the rest."""
    return ", ".join(names[:limit]) + (f" and {len(names) - limit} more" if len(names) > limit else "")


def check_data(cfg, inp: FitInputs, model, make, orders, result: FitResult, progress: Progress) -> tuple[dict, list[dict]]:
    """Stage 6, what the identification data cannot determine; each finding is a warning (console, run log, metrics).

    - tools of the config never measured in the identification file;
    - fewer equations (3 per row) than model parameters;
    - backlash on for a joint whose approach direction never changes in the data (or no dir columns);
    - parameters the fit had to pin beyond the model's own redundancy (:func:`structural_pins`):
      the data cannot determine them (e.g. every pose the same), they stay at their start values.
    - free parameter combinations the data barely determine (:func:`torchcal.analysis.identifiability`).
    - backlash on: how far direction and position are confounded, per joint and per backlash coefficient by
      name (:func:`torchcal.analysis.confounding.backlash_confounding`), warned when high.
    -> {'unobserved_tools', 'parameters', 'equations', 'undetermined': [names], 'one_sided_backlash': [joints],
    'barely_determined': [combinations], 'confounding': {...} (with backlash)}, and the rows of parameters.csv
    (:func:`parameter_uncertainty`; empty when the identifiability check could not be made).
    """
    ident, src = inp.ident, inp.ident.source or "data.identification"
    names = list(inp.robot.joint_map.names)
    out = {"unobserved_tools": [], "parameters": int(result.x.numel()) + len(result.pinned),
           "equations": 3 * len(ident), "undetermined": [], "one_sided_backlash": [], "barely_determined": []}
    seen = set(torch.unique(ident.tool).tolist())
    missing = [t for t in range(inp.T) if t not in seen]
    if missing:
        out["unobserved_tools"] = missing
        progress.warn(f"{src}: tool{'s' if len(missing) > 1 else ''} {missing} of the {inp.T} in 'tools' "
                      f"{'are' if len(missing) > 1 else 'is'} never measured: {'their' if len(missing) > 1 else 'its'} "
                      "vector cannot be identified (measure every tool, or remove it from 'tools')")
    P, E = out["parameters"], out["equations"]
    if E < P:
        per_pose = max(len(seen), 1) * 3
        progress.warn(f"{src}: too few poses for the model: {len(ident)} rows give {E} equations for {P} parameters; "
                      f"measure at least {-(-P // per_pose)} poses with {len(seen)} tool{'s' if len(seen) != 1 else ''}, "
                      "or lower model.order")
    je = getattr(model, "joint_errors", None)  # machines (axis perturbation model) have no backlash terms
    bl = [] if je is None else je.backlash_orders.cpu().tolist()
    on = [j for j, b in enumerate(bl) if b >= 0]
    if on and not ident.has_direction:
        out["one_sided_backlash"] = [names[j] for j in on]
        progress.warn(f"{src}: model.backlash is on but the file has no dir1..dir{len(names)} columns: the backlash terms "
                      "cannot be identified (set model.backlash=false, or give the approach directions)")
    elif on:
        d = ident.direction.cpu()
        one_sided = []
        for j in on:
            signs = set(torch.unique(d[:, j]).tolist()) - {0.0}
            if len(signs) < 2:
                sign = "+1" if signs == {1.0} else "-1" if signs == {-1.0} else "no direction"
                out["one_sided_backlash"].append(names[j])
                one_sided.append((j, f"'{names[j]}' (dir{j + 1}: {sign} only)"))
        if one_sided:
            fix = [-1 if j in {k for k, _ in one_sided} else b for j, b in enumerate(bl)]
            many = len(one_sided) > 1
            progress.warn(f"{src}: joint{'s' if many else ''} {', '.join(t for _, t in one_sided)} "
                          f"approach{'' if many else 'es'} from one side only: {'their' if many else 'its'} backlash "
                          f"cannot be identified; measure both approach directions, or turn it off there "
                          f"(model.backlash={fix})")
    if on and ident.has_direction:
        # backlash vs position in these data: how far the directions follow the positions (quasi-random poses
        # measured in sequence order), and how well each backlash coefficient is told from the position terms
        try:
            from ..analysis.confounding import backlash_confounding

            rep = backlash_confounding(ident, model=model, noise=inp.noise)
            out["confounding"] = rep.to_dict()
            found = rep.warnings()
            if found:
                progress.warn(f"{src}: backlash and position are confounded in these data ({len(found)} finding"
                              f"{'s' if len(found) > 1 else ''}; metrics.json 'data_checks.confounding'); compensated "
                              f"commands approached in other directions may be off by more than the validation "
                              f"residual says. {found[0]}")
                for w in found[1:]:
                    log.warning("%s: %s", src, w)
        except Exception as exc:  # a diagnostic must not cost the run
            log.warning("confounding check skipped: %s: %s", type(exc).__name__, exc)
    if result.pinned:
        try:
            structural = set(structural_pins(make, orders, inp, seed=int(cfg.seed)))
        except Exception as exc:  # a diagnostic must not cost the run; say that it could not be made
            log.warning("identifiability check skipped: %s: %s", type(exc).__name__, exc)
            structural = None
        if structural is not None:
            extra = [n for n in result.pinned if n not in structural]
            count = len(result.pinned) - len(structural)
            if count > 0 and extra:
                out["undetermined"] = extra
                backlash = [n for n in extra if ".backlash" in n or "backlash." in n]
                advice = ("Spread the poses over the joint ranges and measure every tool, or lower model.order")
                if backlash and not ident.has_direction:
                    # backlash needs both approach directions; a file without dir columns gives none
                    advice = (f"{len(backlash)} of them are backlash terms, which need approach directions: the "
                              f"file has no dir1..dir{ident.q.shape[1]} columns, so set model.backlash: false"
                              + ("; for the rest, spread the poses over the joint ranges and measure every tool, "
                                 "or lower model.order" if len(backlash) < len(extra) else ""))
                progress.warn(f"{src}: the data cannot determine {count} of the model's {P} parameters (beyond the "
                              f"{len(structural)} that no data can tell apart); they stay at their start values "
                              f"(fit.json 'pinned_names'): {_names_short(extra)}. {advice}")
    try:  # what is left free but barely determined: torchcal.analysis.identifiability at the solution
        from ..analysis.identifiability import identifiability

        ia = identifiability(model, ident, inp.noise, inp.prior, pinned=result.pinned, v=result.v)
        combos = ia.undetermined
        uncertainty = parameter_uncertainty(ia)
    except Exception as exc:  # a diagnostic must not cost the run
        log.warning("identifiability check skipped: %s: %s", type(exc).__name__, exc)
        combos, uncertainty = [], []
    if combos:
        out["barely_determined"] = [str(c) for c in combos]
        many = len(combos) > 1
        progress.warn(f"{src}: {len(combos)} combination{'s' if many else ''} of the free parameters "
                      f"{'are' if many else 'is'} barely determined by the data (relative singular value < "
                      f"{ia.rtol:g}, torchcal.analysis.identifiability); the fit holds {'them' if many else 'it'} "
                      f"near the prior, e.g. {combos[0]}")
    return out, uncertainty


def parameter_uncertainty(ia) -> list[dict]:
    """Each free parameter's value and Laplace standard deviation (:class:`torchcal.analysis.identifiability.
    Identifiability`, at the solution, joint errors marginalized, prior included), in mm / deg: the rows of
    ``parameters.csv``. Entries the gauge pinned are not free and have no row (fit.json lists them)."""
    scale = {"angle": units.rad_to_deg, "length": units.m_to_mm}
    rows = []
    for name, role, kind, x, s in zip(ia.names, ia.layout.roles(), ia.layout.kinds(), ia.x.tolist(), ia.std.tolist()):
        conv = scale.get(kind, float)
        rows.append({"name": name, "role": role, "unit": units.entry_unit(kind, name), "value": conv(x), "std": conv(s)})
    return rows


def evaluate_sets(inp: FitInputs, model, progress: Progress) -> tuple[dict, dict, list[dict]]:
    """Stage 7, evaluate: nominal and modeled residuals of every set -> (sets, evaluations, Table 6 rows).

    Warns when the nominal residual is beyond any plausible calibration error
    (:data:`NOMINAL_IMPLAUSIBLE_MM`): the percent decrease then measures a wrong description, not a calibration.
    """
    sets = {"Identification": inp.ident} | ({"Validation": inp.val} if inp.val is not None else {})
    evaluations = {name: evaluate(model, d) for name, d in sets.items()}
    for name, ev in evaluations.items():
        s = ev["modeled_stats"]
        progress.info(f"{name.lower()}: mean {ev['nominal_stats'].mean:.4f} -> {s.mean:.4f} mm "
                      f"({ev['decrease']['mean']:.2f} % decrease), max {s.max:.4f} mm, Gamma 99 % {s.gamma99:.4f} mm")
    for name, ev in evaluations.items():
        if far := far_rows_message(ev["modeled"], sets[name], f"{name.lower()} set ({sets[name].source})"):
            progress.warn(far)
    # far before the fit too: one row 210 mm off can pull a small set's whole fit with it, so that after the fit
    # no row stands out
    gross = far_rows(evaluations["Identification"]["nominal"])
    gross = gross if gross.numel() else far_rows(evaluations["Identification"]["modeled"])
    _check_noise(inp, model, sets, evaluations, progress)
    for name, ev in evaluations.items():
        nom, mod = ev["nominal_stats"].mean, ev["modeled_stats"].mean
        if worse_than_nominal(mod, nom):
            # a gross row (a line cut inside a number: 210 mm off) pulls the whole least-squares fit
            named = ", ".join(f"row {r}" for r in inp.ident.rows.cpu()[gross[:3].cpu()].tolist())
            more = ", ..." if gross.numel() > 3 else ""
            pulled = ("" if gross.numel() == 0 else f"; the identification rows far beyond the rest ({named}{more}) "
                      "pull the whole fit: mend or leave them out and fit again")
            progress.warn(f"the fitted model is worse than the nominal robot on the {name.lower()} set (mean {mod:.4f} "
                          f"against {nom:.4f} mm): do not deploy it; look for a unit slip, a wrong frame or tools, too "
                          f"few poses for the orders (model.order), or a solver that did not converge{pulled}")
    nominal = evaluations["Identification"]["nominal_stats"].mean
    if nominal > NOMINAL_IMPLAUSIBLE_MM:
        from ..io.unit_checks import scale_hint

        hint = scale_hint(inp.ident.to("cpu"), inp.robot, model.tools.nominal.detach().cpu())
        progress.warn(f"the nominal residual (identification mean {nominal:.1f} mm) is far beyond any plausible calibration "
                      f"error (> {NOMINAL_IMPLAUSIBLE_MM:g} mm){hint}: the robot description may not be the robot, and the "
                      f"percent decrease means little. Check the x, y, z units, the URDF of '{inp.robot.name}' (joint axes: a "
                      "joint without <axis> turns about x; origins), the joint map (offsets, coupling, units), the tool "
                      "vectors and the measurement frame (measurement_frame: estimate when the tracker is not at the robot "
                      "base)")
    return sets, evaluations, table6(evaluations)


def _check_noise(inp: FitInputs, model, sets: dict, evaluations: dict, progress: Progress) -> None:
    """Each set's residual against what the noise model explains (:mod:`torchcal.analysis.noise_check`): said, kept
    in the evaluations ('noise_ratio'), and warned about where the validation set (else the identification set)
    is beyond :data:`~torchcal.analysis.noise_check.NOISE_RATIO_WARN`: a fit 16x the tracker noise said nothing."""
    from ..analysis.noise_check import NOISE_RATIO_WARN, noise_ratio

    checks = {name: noise_ratio(model, sets[name], inp.noise, ev["modeled"]) for name, ev in evaluations.items()}
    for name, ev in evaluations.items():
        ev["noise_ratio"] = None if checks[name] is None else checks[name].ratio
    name = "Validation" if "Validation" in evaluations else "Identification"
    check = checks[name]
    if check is None:
        return
    said = ", ".join(f"{n.lower()} {c.ratio:.2f}" for n, c in checks.items())
    progress.info(f"residual / noise model (1 or below: the model holds the systematic errors): {said}")
    if check.ratio > NOISE_RATIO_WARN:
        rho = check.ratio
        causes = ["gravity sag (model.compliance)"] if getattr(model, "compliance", None) is None else []
        causes += ["too low a model.order (where the validation residual falls with a higher one)",
                   "thermal drift between sessions"]
        progress.warn(f"the {name.lower()} residual is {rho:.1f}x what the noise model explains (noise.sigma_m "
                      f"{units.m_to_mm(inp.noise.sigma_m):g} mm and the joints' repeatability, {inp.noise_source}): "
                      f"an error source the model lacks ({'; '.join(causes)}), or scatter beyond the config's, which "
                      f"noise.sigma_m {units.m_to_mm(check.sigma_m):.3g} mm would describe; until then the parameters' "
                      f"standard deviations (parameters.csv) assume the noise model and are about {rho:.0f}x too small")


def fit_metrics(orders, selection, result: FitResult, alignment, sets: dict, evaluations: dict, table) -> dict:
    """What metrics.json holds (mm, percent); Table 7 and the warnings are added by later stages."""
    return {
        "units": "mm, percent",
        "orders": orders,
        "order_selection": None if selection is None else selection.criterion,
        "fit": {"converged": bool(result.success), "iterations": int(result.nit), "cost": float(result.fun)},
        "alignment": None if alignment is None else alignment.summary(),
        "sets": {name.lower(): {"rows": len(sets[name]), "poses": sets[name].n_poses,
                                "nominal": vars(ev["nominal_stats"]), "modeled": vars(ev["modeled_stats"]),
                                "decrease_percent": ev["decrease"], "noise_ratio": ev.get("noise_ratio")}
                 for name, ev in evaluations.items()},
        "table6": table,
        "table7": None,
    }


TRUTH_MISS_FACTOR = 5.0
"""data.truth is another robot's when its points miss the validation rows by this many times the fitted model's
mean residual: the rows were measured on the truth, so it holds them to their noise, closer than any model."""


def _check_truth(source, inp: FitInputs, evaluations: dict, progress: Progress) -> None:
    """Warn when ``data.truth`` does not describe the validation rows: Table 7's 'Compensated' row is measured on
    the truth, and another seed's truth.json gave 1.32 mm there (0.053 mm with its own) without a word."""
    val = inp.val
    with torch.no_grad():
        miss = (inp.truth.points(val.q, val.tool, val.direction) - val.xyz).norm(dim=-1)
    miss_mm = float(units.m_to_mm(miss.mean()))
    model_mm = evaluations["Validation"]["modeled_stats"].mean
    if miss_mm > TRUTH_MISS_FACTOR * model_mm:
        progress.warn(f"data.truth ({source}) does not describe the validation rows: its points miss them "
                      f"by {miss_mm:.4f} mm (mean), the fitted model by {model_mm:.4f} mm; rows measured on it miss "
                      "by their noise alone. The compensated row of Table 7 measures on another robot: give the "
                      "truth.json written with these data")


def check_compensation(cfg, inp: FitInputs, model, evaluations: dict, metrics: dict, progress: Progress):
    """Stage 8, compensate-check (simulated data with a truth): Table 7 -> (rows, compensation_check dict).

    Adds 'table7' and 'compensation' to ``metrics``.
    """
    val = inp.val
    _check_truth(cfg.data.truth, inp, evaluations, progress)
    freedom, note = compensation_dof(model)  # what `torchcal compensate` does with this run by default
    if note is not None:
        progress.info(f"compensation check: {note}")
    with progress.step(f"compensating {len(val)} validation commands and measuring them on the simulated truth"):
        comp = compensation_check(model, inp.truth, val, inp.noise, int(cfg.seed) + 1, **freedom,
                                  **compensation_kwargs(cfg.compensation.tol_deg, cfg.compensation.max_iter))
    res = comp["result"]
    flagged = int((~res.converged | ~res.within_limits).sum())
    ns = evaluations["Validation"]["nominal_stats"]
    cs = residual_stats(comp["compensated"]).scaled(units.m_to_mm(1.0))
    rows = [stats_row("Validation", "Nominal", ns, None),
            stats_row("Validation", "Modeled", evaluations["Validation"]["modeled_stats"], ns),
            stats_row("Validation", "Compensated", cs, ns)]
    metrics["table7"] = rows
    ok = (res.converged & res.within_limits).cpu()
    metrics["compensation"] = {**res.summary(), "flagged": flagged, "compensated": vars(cs),
                               "dof": 3 if freedom.get("position_only") else 5 if freedom else 6,
                               # what a controller would run: flagged commands would be rejected
                               "compensated_unflagged": vars(residual_stats(comp["compensated"].cpu()[ok]).scaled(
                                   units.m_to_mm(1.0))) if ok.any() else None}
    progress.info(f"compensated: mean {ns.mean:.4f} -> {cs.mean:.4f} mm "
                  f"({percent_decrease(ns.mean, cs.mean):.2f} % decrease); {flagged} commands flagged "
                  "(not converged or outside the joint range)")
    return rows, comp


# ------------------------------------------------------------------- the run
@frame_check(quiet=True)  # the run says a far frame its own way (its nominal residual)
def run_fit(cfg, console=None) -> RunResult:
    """Run one calibration from a config (see :mod:`torchcal.app.config`) and write its run directory.

    console: a rich Console for progress (None: quiet, the run log still records
    everything). Raises DataError / URDFError / ConfigError for bad inputs,
    before anything is computed; see :mod:`torchcal.io.rundir` for the layout.
    A KeyboardInterrupt after the run directory exists carries it as ``exc.run_dir``
    (the CLI prints where the partial run is).

    Example:
        >>> from torchcal.app.config import load_config
        >>> result = run_fit(load_config("data/fanuc/fit.yaml", ["model.order=2"]))   # doctest: +SKIP
        >>> result.metrics["sets"]["validation"]["modeled"]["mean"]                  # doctest: +SKIP
        0.0123
    """
    from ..io.progress_view import showing

    # every stage is a progress task: a bar on a terminal, plain lines (and a heartbeat) elsewhere and in run.log
    with showing(console):
        if cfg.threads is None:  # each stage picks its threads by work size (torchcal.core.threads)
            return _run_fit(cfg, console)
        old = threads.get_override()
        threads.set_threads(int(cfg.threads))
        try:
            return _run_fit(cfg, console)
        finally:
            threads.set_threads(old)


def _run_fit(cfg, console=None) -> RunResult:
    """The stages in order: load, align, (run directory), build / select orders, fit, check data, evaluate,
    compensate-check, plots; each writes its files as soon as it has them. Sensor configs (Paper III) take
    :func:`torchcal.app.sensor.run_sensor_fit`."""
    if cfg.sensor.kind is not None:
        from .sensor import run_sensor_fit

        return run_sensor_fit(cfg, console)
    from ..io.plots import PlotWorker

    # the figures are drawn by a second process (numpy + matplotlib) while the stages below compute
    plotter = PlotWorker() if cfg.plots else None
    try:
        return _run_stages(cfg, console, plotter)
    finally:
        if plotter is not None:
            plotter.cancel()  # done already, or a failed / interrupted run


def _run_stages(cfg, console, plotter) -> RunResult:
    """:func:`_run_fit`'s stages; ``plotter``: a :class:`torchcal.io.plots.PlotWorker` that gets each figure
    as soon as its data exist, or None (plots: false)."""
    progress = Progress(console)
    with progress.step("reading the robot and the data", quiet=True):
        inp = load_inputs(cfg)
    with progress.step("estimating the tool vectors / measurement frame", quiet=True):
        tools_m, base_nominal, alignment = align_inputs(cfg, inp)
    run_dir = make_run_dir(cfg.out)
    files: dict[str, Path] = {}
    try:
        with run_log(run_dir):
            write_preamble(run_dir, cfg, inp, alignment, progress, files)
            make = model_factory(inp.robot, tools_m, config_backlash(cfg), inp.device, base_nominal,
                                 config_compliance(cfg), config_error_variable(cfg), cfg.model.kind,
                                 cfg.model.backlash_on)
            orders, selection = choose_orders(cfg, inp, make, run_dir, progress, files)
            constraint = None
            if cfg.constraint.c is None:
                model = make(orders)
                result = identify_model(cfg, inp, model, orders, run_dir, progress, files)
            else:
                from .constraint import identify_constrained

                model, result, constraint = identify_constrained(cfg, inp, make, orders, run_dir, progress, files)
            plot_folder = run_dir / "plots"
            if plotter is not None:
                _submit_plots(plotter, plot_folder, model=model)
            # the figures' data first (evaluation, compensation check), the diagnostics last: the plot worker
            # draws while this process checks the data, rather than alone at the end
            with progress.step("evaluating the residuals", quiet=True):
                sets, evaluations, table = evaluate_sets(inp, model, progress)
            if plotter is not None:
                _submit_plots(plotter, plot_folder, evaluations=evaluations)
            metrics = fit_metrics(orders, selection, result, alignment, sets, evaluations, table)
            if cfg.prior.fleet is not None:  # what the prior brought: the same data fitted without it
                with progress.step("fitting the unit alone, without the fleet's prior", quiet=True):
                    metrics["fleet_prior"] = compare_with_alone(inp, make, orders, evaluations, progress)
            metrics["data_checks"] = None
            metrics["constraint"] = constraint
            metrics["warnings"] = progress.warnings
            files["metrics"] = write_json(run_dir / "metrics.json", metrics)
            files["residuals"] = _write_residuals(run_dir / "residuals.csv", sets, evaluations)
            comp_table, comp = None, None
            if inp.truth is not None:
                comp_table, comp = check_compensation(cfg, inp, model, evaluations, metrics, progress)
                files["metrics"] = write_json(run_dir / "metrics.json", metrics)
                files["compensation"] = _write_compensation(run_dir / "compensation.csv", inp.val, comp, model)
                if plotter is not None:
                    _submit_plots(plotter, plot_folder, comp=comp)
            with progress.step("checking what the data determine", quiet=True):
                metrics["data_checks"], uncertainty = check_data(cfg, inp, model, make, orders, result, progress)
                if uncertainty:
                    import pandas as pd

                    files["parameters"] = write_table(run_dir / "parameters.csv", pd.DataFrame(uncertainty))
            metrics["warnings"] = progress.warnings
            files["metrics"] = write_json(run_dir / "metrics.json", metrics)
            if plotter is not None:
                with progress.step("plotting") as p:  # waits for the figures drawn meanwhile
                    files.update(plotter.finish(p.task))
            progress.info(f"done: {run_dir}")
        if cfg.report:  # after run_log: the run is complete (no PARTIAL marker) and its log whole
            with progress.step("writing the calibration report", quiet=True):
                write_run_report(run_dir, files, progress)
    except KeyboardInterrupt as exc:
        exc.run_dir = run_dir  # the CLI names the partial run directory
        raise
    return RunResult(run_dir, model, result, metrics, table, comp_table, orders, selection, files, progress.warnings)


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


def _write_compensation(path: Path, val: Measurements, comp: dict, model) -> Path:
    """Table 7's compensated row per validation row: the nominal command and the compensated one (deg / mm), its
    flags and reason, and both measured residuals (mm), so that every number of the row can be recomputed."""
    import pandas as pd

    from ..io.csv import joint_columns, joints_to_file

    res = comp["result"]
    robot = model.robot
    out = pd.DataFrame({"row": val.rows.cpu().numpy(), "pose": val.pose.cpu().numpy(), "tool": val.tool.cpu().numpy()})
    q_nom, q_comp = joints_to_file(val.q, robot), joints_to_file(res.q, robot)
    for i, c in enumerate(joint_columns(robot.joint_map.n)):
        out[c] = q_nom[:, i]
    if val.has_direction:
        for i in range(robot.joint_map.n):
            out[f"dir{i + 1}"] = val.direction[:, i].cpu().numpy().astype(int)
    for i, c in enumerate(joint_columns(robot.joint_map.n)):
        out[f"{c}_compensated"] = q_comp[:, i]
    out["converged"] = res.converged.cpu().numpy()
    out["within_limits"] = res.within_limits.cpu().numpy()
    out["reason"] = res.reasons(None, robot.joint_map.prismatic)
    out["nominal_mm"] = units.m_to_mm(comp["nominal"].detach().cpu().numpy())
    out["compensated_mm"] = units.m_to_mm(comp["compensated"].detach().cpu().numpy())
    return write_table(path, out)


def _submit_plots(plotter, folder: Path, model=None, evaluations: dict | None = None, comp: dict | None = None) -> None:
    """Hand the figures whose data exist to ``plotter`` (:class:`torchcal.io.plots.PlotWorker`): Figure 12 with the
    model, Figures 13-15 with the evaluations, Figure 16 with the compensation check."""
    from ..io import plots

    if isinstance(model, RobotModel):
        plotter.submit("plot_joint_errors", "joint_errors", folder / "joint_errors.png", plots.joint_errors_figure(model))
    if evaluations is not None:
        fig = {"Identification": 14, "Validation": 15}
        for name, ev in evaluations.items():
            plotter.submit(f"plot_residuals_{name.lower()}", "pair", folder / f"residuals_{name.lower()}.png",
                           plots.residuals_figure(ev["nominal"], ev["modeled"], f"Nominal and modeled residuals, "
                                                  f"{name.lower()} set (Paper II, Fig. {fig[name]})"))
        last = "Validation" if "Validation" in evaluations else "Identification"
        plotter.submit("plot_distribution", "distribution", folder / f"distribution_{last.lower()}.png",
                       plots.distribution_figure(evaluations[last]["modeled"], evaluations[last]["modeled_stats"],
                                                 f"Modeled residuals, {last.lower()} set (Paper II, Fig. 13)"))
    if comp is not None:
        plotter.submit("plot_compensation", "pair", folder / "compensation_validation.png", plots.compensation_figure(
            comp["nominal"], comp["compensated"], "Nominal and compensated residuals, validation set (Paper II, Fig. 16)",
            flagged=~(comp["result"].converged & comp["result"].within_limits)))


__all__ = [
    "NOMINAL_IMPLAUSIBLE_MM",
    "FitInputs",
    "RunResult",
    "align_inputs",
    "check_compensation",
    "check_data",
    "choose_orders",
    "compare_with_alone",
    "config_backlash",
    "config_error_variable",
    "evaluate_sets",
    "fit_metrics",
    "identify_model",
    "joint_variance_source",
    "load_inputs",
    "structural_pins",
    "write_preamble",
    "compensation_check",
    "compensation_targets",
    "config_alignment",
    "config_frame",
    "config_tool_count",
    "config_noise",
    "config_prior",
    "config_tools",
    "evaluate",
    "model_factory",
    "read_sets",
    "run_fit",
    "solver_options",
    "table6",
    "parameter_uncertainty",
    "write_run_report",
]
