"""The fit pipeline for 6-DOF measurements (Paper III): a config with ``sensor: {kind: sts | pose}``.

Stages, as for point targets (:mod:`torchcal.app.fit`), with the sensor's own:

1. load: robot, sensor CSVs (:func:`torchcal.io.sensor_csv.read_pose_measurements`:
   position + rotation per row, optional per-row standard deviations), noise;
2. frames: the tracker -> robot base frame and the flange -> sensor mount, each
   given in the config or estimated from the data (:func:`torchcal.identify.hand_eye.hand_eye`
   on the nominal robot: no guess needed);
3. instrument: the STS (position + yaw, roll, level; rows outside the sensor's
   ranges reported and left out, never silently used), a generic 6-DOF probe
   (position + rotation vector), or position only;
4. fit (:func:`torchcal.fit` on a :class:`~torchcal.models.sensor_rig.SensorRig`),
   model.pt at once;
5. evaluate: position (mm) and orientation (deg) residuals of every set, nominal
   (hand-eye frames, nominal robot) and modeled, joint errors zero.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass, field
from pathlib import Path

import torch
from collections.abc import Mapping

from ..core import units
from ..analysis.stats import percent_decrease, residual_stats
from ..identify import fit
from ..identify.hand_eye import hand_eye
from .common import write_run_report
from .config import ConfigError, source_of
from ..io.rundir import make_run_dir, placed_note, run_log, save_model, write_json
from ..kinematics import load_robot
from ..kinematics.transforms import homogeneous, rpy_to_matrix
from ..measure.pose import rotation_error
from ..core.measurements import Measurements
from ..identify.fit import frame_check

log = logging.getLogger("torchcal")


@dataclass
class SensorInputs:
    """Everything read before anything is computed: robot, sets, noise, prior, solver options, notes."""

    robot: object
    ident: Measurements
    val: Measurements | None
    noise: object
    noise_source: str
    prior: object
    opts: dict
    device: torch.device
    label: str
    notes: list[str] = field(default_factory=list)


def config_pose_frame(value) -> torch.Tensor | None:
    """{xyz_mm, rpy_deg} -> (4, 4) SI; 'estimate' / 'auto' -> None (from the data)."""
    if isinstance(value, Mapping):
        rpy = units.deg_to_rad(torch.tensor([float(v) for v in value["rpy_deg"]], dtype=torch.float64))
        xyz = units.mm_to_m(torch.tensor([float(v) for v in value["xyz_mm"]], dtype=torch.float64))
        return homogeneous(rpy_to_matrix(rpy), xyz)
    if value == "base":
        return torch.eye(4, dtype=torch.float64)
    return None


def up_vector(cfg) -> torch.Tensor:
    """The level's 'up' direction in the tracker frame: minus ``sensor.gravity`` (default gravity [0, 0, -1])."""
    g = cfg.sensor.gravity
    return torch.tensor([0.0, 0.0, 1.0], dtype=torch.float64) if g is None else -torch.tensor(
        [float(v) for v in g], dtype=torch.float64)


def read_sensor_set(path, robot, device) -> Measurements:
    from ..io.sensor_csv import read_pose_measurements

    return read_pose_measurements(path, robot).to(device)


def load_sensor_inputs(cfg) -> SensorInputs:
    """Stage 1: robot, config checks against it, noise, prior, solver options, the sensor CSVs."""
    from .config import check_config
    from .common import collect_warnings, config_noise, config_prior, joint_variance_source, solver_options

    label = cfg.config_file or "config"
    notes: list[str] = []
    with collect_warnings(notes):
        robot = load_robot(cfg.robot)
    check_config(cfg, label, robot.joint_map.n)
    device = torch.device(cfg.device)
    torch.manual_seed(int(cfg.seed))
    noise = config_noise(cfg, robot, label)
    with collect_warnings(notes):
        ident = read_sensor_set(cfg.data.identification, robot, device)
        val = read_sensor_set(cfg.data.validation, robot, device) if cfg.data.validation else None
    if not cfg.data.units_checked:  # a T-Mac export in metres was fitted "to 0.013 mm" before this check
        from ..io.unit_checks import check_units, units_note

        for d in (ident, val):
            if d is not None and (note := units_note(d, robot, *check_units(d, robot), "data.units_checked=true")):
                notes.append(note)
    from .common import changed_inputs

    notes.extend(changed_inputs(cfg))  # a re-run of a run's own config.yaml on edited files
    return SensorInputs(robot, ident, val, noise, joint_variance_source(cfg, robot), config_prior(cfg),
                        solver_options(cfg), device, label, notes)


def measured_poses(data: Measurements) -> torch.Tensor:
    """(R, 4, 4) measured sensor poses in the tracker frame."""
    T = torch.eye(4, dtype=data.xyz.dtype, device=data.xyz.device).repeat(len(data), 1, 1)
    T[:, :3, :3], T[:, :3, 3] = data.extra["rotation"].to(data.xyz), data.xyz
    return T


def initial_frames(cfg, robot, data: Measurements, seed: int = 0) -> tuple[torch.Tensor, torch.Tensor, dict]:
    """(X tracker <- base, M flange -> sensor, summary): each from the config, else from the data (hand-eye)."""
    from ..models.robot import RobotModel

    X = config_pose_frame(cfg.measurement_frame)
    M = config_pose_frame(cfg.sensor.mount)
    nominal = RobotModel(robot, torch.zeros(1, 3, dtype=torch.float64), orders=0).to(data.q.device)
    with torch.no_grad():
        F = nominal.nominal_flange(data.q)
    T = measured_poses(data)
    X, M = hand_eye(F, T, seed=seed, X=None if X is None else X.to(T), M=None if M is None else M.to(T))
    with torch.no_grad():
        P = X @ F @ M
    pos = (P[:, :3, 3] - T[:, :3, 3]).norm(dim=-1)
    summary = {"measurement_frame": "config" if config_pose_frame(cfg.measurement_frame) is not None else "estimated",
               "mount": "config" if config_pose_frame(cfg.sensor.mount) is not None else "estimated",
               "frame_xyz_mm": units.m_to_mm(X[:3, 3]).tolist(), "mount_xyz_mm": units.m_to_mm(M[:3, 3]).tolist(),
               "nominal_position_mean_mm": float(units.m_to_mm(pos.mean()))}
    return X, M, summary


def config_pose_std(cfg) -> torch.Tensor | None:
    """sensor.pose_std (mm, deg) -> (6,) m, rad, or None."""
    v = cfg.sensor.pose_std
    if v is None:
        return None
    v = [float(x) for x in v]
    return torch.tensor([units.mm_to_m(x) for x in v[:3]] + [units.deg_to_rad(x) for x in v[3:]], dtype=torch.float64)


def sensor_instrument(cfg, data: Measurements, noise, progress=None):
    """The instrument for ``data`` and the rows it uses -> (instrument, data, excluded file rows)."""
    from ..measure import PointTargets
    from ..measure.pose import PoseInstrument
    from ..measure.sts import STSInstrument
    from ..measure.tracker import TrackerNoise

    kind = cfg.sensor.kind
    if cfg.sensor.position_only:
        return PointTargets(data.xyz, cov=TrackerNoise.paper3().covariance(data.xyz)), data, []
    if kind == "pose":
        std = config_pose_std(cfg)
        if progress is not None:  # which weights the fit uses: noise.sigma_m is not one of them (a user read it was)
            from ..measure.pose import DEFAULT_POSE_STD

            src = ("sensor.pose_std" if std is not None else f"the file's sx..srz ({data.source})"
                   if "pose_std" in data.extra else "torchcal's default (sensor.pose_std to set them)")
            shown = std if std is not None else None if "pose_std" in data.extra else torch.as_tensor(DEFAULT_POSE_STD)
            progress.info(f"pose weights: {src}" + ("" if shown is None else (
                f": {', '.join(f'{units.m_to_mm(float(v)):g}' for v in shown[:3])} mm, "
                f"{', '.join(f'{units.rad_to_deg(float(v)):g}' for v in shown[3:])} deg"))
                + "; noise.sigma_m is not used by a pose sensor")
        return PoseInstrument.from_measurements(data, pose_std=None if std is None else std.to(data.xyz)), data, []
    sel = STSInstrument.from_measurements(data, TrackerNoise.paper3(), gravity=up_vector(cfg).to(data.xyz),
                                          invalid="exclude")
    if sel.excluded and progress is not None:
        progress.warn(f"{data.source}: {len(sel.excluded)} rows outside the sensor's ranges are left out: "
                      f"{sel.message[:400]}")
    return sel.instrument, sel.data, list(sel.excluded)


class SensorRigFactory:
    """make(orders) -> a fresh all-zero :class:`~torchcal.models.sensor_rig.SensorRig` with the initial frames.

    fine: None, or a :class:`~torchcal.error_models.fine.FineJointErrors` whose copy every rig gets.
    """

    def __init__(self, robot, backlash, device, X, M, up, compliance=False, error_variable=None, sts=True, fine=None,
                 backlash_on: str = "joint"):
        self.robot, self.backlash, self.device, self.backlash_on = robot, backlash, device, backlash_on
        self.X, self.M, self.up = X.detach().cpu(), M.detach().cpu(), up
        self.compliance, self.error_variable, self.sts, self.fine = compliance, error_variable, sts, fine

    def __call__(self, orders, backlash="default", fine: bool = True):
        import copy

        from ..models.sensor_rig import SensorRig
        from ..models.robot import RobotModel

        model = RobotModel(self.robot, torch.zeros(1, 3, dtype=torch.float64),
                           list(orders) if not isinstance(orders, int) else orders,
                           self.backlash if backlash == "default" else backlash, base_nominal=self.X,
                           compliance=self.compliance, error_variable=self.error_variable,
                           fine=copy.deepcopy(self.fine) if fine and self.fine is not None else None,
                           backlash_on=self.backlash_on)
        return SensorRig(model, self.M, self.up if self.sts else None).to(self.device)


def config_fine(cfg, robot, ident: Measurements):
    """model.fine -> (FineJointErrors over the identification data's joint range or None, smoothness block
    sigma (n,) rad or None, warm start)."""
    f = cfg.model.fine
    if f is None:
        return None, None, False
    from ..error_models.fine import DEFAULT_PRIOR, DEFAULT_SPACING, FineJointErrors

    spacing = units.deg_to_rad(float(f["spacing_deg"])) if "spacing_deg" in f else DEFAULT_SPACING
    prior = units.deg_to_rad(float(f["prior_deg"])) if "prior_deg" in f else DEFAULT_PRIOR
    fe = FineJointErrors.from_data(robot.joint_map.to_joint(ident.q).cpu(), spacing,
                                   joint_names=robot.chain.joint_names, prior_sigma=prior)
    sm = f.get("smoothness_deg")
    sigma = None
    if sm is not None:
        n = robot.joint_map.n
        vals = [float(v) for v in sm] if not isinstance(sm, (int, float)) else [float(sm)] * n
        if len(vals) != n:
            raise ConfigError(f"{source_of(cfg, 'model.fine.smoothness_deg', cfg.config_file or 'config')}: key 'model.fine.smoothness_deg': {len(vals)} values "
                              f"for {n} joints")
        sigma = units.deg_to_rad(torch.tensor(vals, dtype=torch.float64))
    return fe, sigma, bool(f.get("warm_start", True))


@torch.no_grad()
def pose_residuals(rig, data: Measurements, nominal: bool = False) -> tuple[torch.Tensor, torch.Tensor]:
    """(R,) position (m) and orientation (rad) errors of the rig's prediction, joint errors zero."""
    T = rig.nominal_sensor_pose(data.q) if nominal else rig.sensor_pose(
        data.q, None, data.direction if data.has_direction else None)
    M = measured_poses(data)
    return (T[:, :3, 3] - M[:, :3, 3]).norm(dim=-1), rotation_error(T[:, :3, :3], M[:, :3, :3]).norm(dim=-1)


def evaluate_pose_sets(rig, sets: dict[str, Measurements], progress) -> tuple[dict, list[dict]]:
    """-> ({set: {position_mm: {nominal, modeled, decrease_percent}, orientation_deg: {...}}}, Table 6 rows)."""
    from .common import stats_row

    out, table = {}, []
    for name, data in sets.items():
        pn, rn = pose_residuals(rig, data, nominal=True)
        pm, rm = pose_residuals(rig, data)
        ps = [residual_stats(units.m_to_mm(x.cpu())) for x in (pn, pm)]
        rs = [residual_stats(units.rad_to_deg(x.cpu())) for x in (rn, rm)]
        label = name.capitalize()
        table += [stats_row(label, "Nominal position", ps[0], None), stats_row(label, "Modeled position", ps[1], ps[0]),
                  stats_row(label, "Nominal angle (deg)", rs[0], None), stats_row(label, "Modeled angle (deg)", rs[1], rs[0])]
        out[name] = {"rows": len(data), "position_mm": {"nominal": vars(ps[0]), "modeled": vars(ps[1]),
                                                       "decrease_percent": percent_decrease(ps[0].mean, ps[1].mean)},
                     "orientation_deg": {"nominal": vars(rs[0]), "modeled": vars(rs[1]),
                                         "decrease_percent": percent_decrease(rs[0].mean, rs[1].mean)}}
        progress.info(f"{name}: position mean {ps[0].mean:.4f} -> {ps[1].mean:.4f} mm (Gamma 99 % {ps[1].gamma99:.4f}, max "
                      f"{ps[1].max:.4f}); orientation mean {rs[0].mean:.4f} -> {rs[1].mean:.5f} deg")
    return out, table


def warn_implausible_pose_fit(result, evaluations: dict, progress, position_only: bool = False) -> None:
    """The point runs' checks (:func:`torchcal.app.fit.evaluate_sets`) for a sensor run, whose fit said nothing:
    a T-Mac file imported with the wrong rotation order was fitted to 93 mm, "converged", warnings: [] (another
    order: 261 mm, the orientation 3.2 -> 12.5 deg, not converged, still nothing). position_only: the fit never
    saw the orientation, so its modeled orientation is no evidence either way (a real UR10 run halved the
    position error and was told not to deploy for its made-up orientation)."""
    from .common import NOMINAL_IMPLAUSIBLE_MM, worse_than_nominal

    if not result.success:
        progress.warn("the solver did not converge; see fit.json (raise solver.max_iter?)")
    for name, ev in evaluations.items():
        pos, ang = ev["position_mm"], ev["orientation_deg"]
        worse = [f"{what} mean {e['modeled']['mean']:.4f} against {e['nominal']['mean']:.4f} {unit}"
                 for what, e, unit in (("position", pos, "mm"), ("orientation", ang, "deg"))[:1 if position_only else 2]
                 if worse_than_nominal(e["modeled"]["mean"], e["nominal"]["mean"])]
        if worse:
            progress.warn(f"the fitted model is worse than the nominal robot on the {name} set ({'; '.join(worse)}): do "
                          "not deploy it; look for a unit slip, the rotation convention of the import "
                          "(import-tmac --convention), a wrong frame or mount, or a solver that did not converge")
    nominal, modeled = (evaluations["identification"]["position_mm"][k]["mean"] for k in ("nominal", "modeled"))
    if max(nominal, modeled) > NOMINAL_IMPLAUSIBLE_MM:
        progress.warn(f"the identification position residual ({nominal:.1f} mm nominal, {modeled:.1f} mm after the fit) is "
                      f"beyond any plausible calibration error (> {NOMINAL_IMPLAUSIBLE_MM:g} mm): the sensor's poses do "
                      "not describe this robot as configured; check the rotation convention of the import "
                      "(import-tmac --convention), the file's units (mm, deg), sensor.mount and the robot description")


def choose_sensor_orders(cfg, inp: SensorInputs, make, ident: Measurements, instrument, fixed, run_dir: Path,
                         progress, files: dict) -> list[int]:
    """``model.order: auto`` for a sensor run: the order search of point-target runs on the sensor's own residuals
    (leave-one-pose-out, or the validation set), then the backlash orders; writes orders.json."""
    from ..identify.backlash import select_backlash_orders
    from ..identify.order import select_orders

    val, val_instrument = inp.val, None
    if val is not None:
        val_instrument, val, _ = sensor_instrument(cfg, val, inp.noise)
    how = "validation set" if val is not None else "leave-one-pose-out residuals"
    opts = dict(inp.opts, instrument=instrument, fixed=fixed)
    with progress.step(f"choosing Chebyshev orders by {how} ({type(instrument).__name__})"):
        sel = select_orders(make, ident, val, inp.noise, inp.prior, candidates=list(cfg.model.candidates),
                            margin=float(cfg.model.margin), joint_window=2, validation_instrument=val_instrument, **opts)
    orders = [int(o) for o in sel.orders]
    record = {"orders": orders, "criterion": sel.criterion, "score": sel.score,
              "units": "whitened residual norm (position and angles on their noise scales)", "table": sel.table}
    if make.backlash is True and ident.has_direction:
        with progress.step("choosing the backlash orders"):
            bsel = select_backlash_orders(make, orders, ident, val, inp.noise, inp.prior, margin=float(cfg.model.margin),
                                          warm=sel.fitted, validation_instrument=val_instrument, **opts)
        make.backlash = [int(b) for b in bsel.orders]
        record.update(backlash_orders=make.backlash, backlash_table=bsel.table)
        progress.info(f"backlash orders {make.backlash} ({bsel.criterion}; -1: off)")
    files["orders"] = write_json(run_dir / "orders.json", record)
    progress.info(f"orders {orders} ({sel.criterion})")
    return orders


@frame_check(quiet=True)  # the run says a far frame its own way (its nominal residual)
def run_sensor_fit(cfg, console=None):
    """``torchcal fit`` for a sensor config: the stages of this module, written to a run directory."""
    from .common import (
        RunResult,
        Progress,
        config_backlash,
        config_compliance,
        config_error_variable,
        config_orders,
        write_preamble_files,
    )

    progress = Progress(console)
    with progress.step("reading the robot and the sensor data", quiet=True):
        inp = load_sensor_inputs(cfg)
    with progress.step("estimating the measurement frame and the sensor mount", quiet=True):
        X, M, frames = initial_frames(cfg, inp.robot, inp.ident, int(cfg.seed))
    run_dir = make_run_dir(cfg.out)
    files: dict[str, Path] = {}
    try:
        with run_log(run_dir):
            write_preamble_files(run_dir, cfg, inp.device, files)
            progress.info(f"run directory {run_dir}{placed_note(cfg.out, run_dir)}")
            progress.info(f"robot '{inp.robot.name}' ({inp.robot.joint_map.n} joints), sensor '{cfg.sensor.kind}'"
                          f"{' (position only)' if cfg.sensor.position_only else ''}; identification {len(inp.ident)} "
                          f"rows" + (f", validation {len(inp.val)} rows" if inp.val is not None else ""))
            progress.info(f"joint variances: {inp.noise_source}")
            for note in inp.notes:
                progress.warn(note)
            progress.info(f"frames: measurement frame {frames['measurement_frame']}, mount {frames['mount']}; "
                          f"nominal position residual {frames['nominal_position_mean_mm']:.3f} mm")
            files["frames"] = write_json(run_dir / "frames.json", frames)
            instrument, ident, excluded = sensor_instrument(cfg, inp.ident, inp.noise, progress)
            backlash = config_backlash(cfg)
            if backlash is not None and not (ident.has_direction and bool((ident.direction != 0).any())):
                progress.warn(f"{ident.source}: no approach directions (dir1..dir{inp.robot.joint_map.n}): the backlash "
                              "terms are left out (model.backlash=false)")
                backlash = None
            fine, smooth, warm = config_fine(cfg, inp.robot, ident)
            make = SensorRigFactory(inp.robot, backlash, inp.device, X, M, up_vector(cfg), config_compliance(cfg),
                                    config_error_variable(cfg), cfg.sensor.kind == "sts", fine, cfg.model.backlash_on)
            order = cfg.model.order
            fixed = () if cfg.sensor.kind == "sts" and not cfg.sensor.position_only else ("gravity",)
            if isinstance(order, str):
                orders = choose_sensor_orders(cfg, inp, make, ident, instrument, fixed, run_dir, progress, files)
            else:
                orders = config_orders(cfg, inp.robot.joint_map.n)
            rig = make(orders)
            blocks = []
            if fine is not None:
                from ..error_models.fine import SmoothnessPenalty

                if smooth is not None:
                    blocks.append(SmoothnessPenalty(rig.model.fine, smooth.to(inp.device)))
                if warm:  # the tables last: first the model without them, then everything from there
                    first = make(orders, fine=False)
                    with progress.step(f"identifying the model without the fine tables (orders {orders})") as p:
                        fit(first, ident, inp.noise, inp.prior, instrument=instrument, fixed=fixed,
                            callback=lambda it, cost: p.update(f"iteration {it}, cost {cost:.6g}"), **inp.opts)
                    rig.load_state_dict(first.state_dict(), strict=False)
            constraint = None
            if cfg.constraint.c is not None:  # Paper I's slope bound on the robot's modeled error at the sensor origin
                from .constraint import identify_constrained

                rig, result, constraint = identify_constrained(cfg, inp, make, orders, run_dir, progress, files, data=ident,
                                                               fit_options={"instrument": instrument, "fixed": fixed})
            else:
                with progress.step(f"identifying the model (orders {orders}{', fine tables' if fine is not None else ''}, "
                                   f"{inp.opts['method']}, {type(instrument).__name__})") as p:
                    result = fit(rig, ident, inp.noise, inp.prior, instrument=instrument, fixed=fixed, blocks=blocks,
                                 callback=lambda it, cost: p.update(f"iteration {it}, cost {cost:.6g}"), **inp.opts)
                files["model"] = save_model(run_dir, rig, orders=orders, config_file=cfg.config_file)
                files["fit"] = write_json(run_dir / "fit.json", {**result.summary(), "pinned_names": list(result.pinned),
                                                                  "orders": orders, "history": list(result.history)})
            progress.info(f"fit: {result.message} after {result.nit} iterations, cost {result.fun:.6g}")
            sets = {"identification": inp.ident} | ({"validation": inp.val} if inp.val is not None else {})
            with progress.step("evaluating the residuals", quiet=True):
                evaluations, table = evaluate_pose_sets(rig, sets, progress)
            warn_implausible_pose_fit(result, evaluations, progress, bool(cfg.sensor.position_only))
            metrics = {"units": "mm, deg, percent", "orders": orders, "sensor": cfg.sensor.kind,
                       "fit": {"converged": bool(result.success), "iterations": int(result.nit), "cost": float(result.fun)},
                       "frames": frames, "excluded_rows": excluded, "sets": evaluations, "table6": table, "warnings": progress.warnings}
            if constraint is not None:
                metrics["constraint"] = constraint
            files["metrics"] = write_json(run_dir / "metrics.json", metrics)
            progress.info(f"done: {run_dir}")
        if cfg.report:  # after run_log: the run is complete (no PARTIAL marker) and its log whole
            with progress.step("writing the calibration report", quiet=True):
                write_run_report(run_dir, files, progress)
    except KeyboardInterrupt as exc:
        exc.run_dir = run_dir
        raise
    return RunResult(run_dir, rig, result, metrics, table, None, orders, None, files, progress.warnings)


def predict_pose_file(run_dir, input, output, model) -> int:
    """``torchcal predict`` on a sensor run: the modeled x, y, z, r11..r33 for the commands of a sensor CSV."""
    from ..io.sensor_csv import read_pose_measurements, write_pose_measurements

    data = read_pose_measurements(input, model.robot, require_pose=False).to(model.device)
    with torch.no_grad():
        T = model.sensor_pose(data.q, None, data.direction if data.has_direction else None)
    write_pose_measurements(output, data, model.robot, modeled=T)
    return len(data)


__all__ = ["SensorInputs", "SensorRigFactory", "evaluate_pose_sets", "initial_frames", "load_sensor_inputs",
           "measured_poses", "pose_residuals", "predict_pose_file", "run_sensor_fit", "sensor_instrument"]
