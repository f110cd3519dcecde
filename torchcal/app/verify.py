"""``torchcal verify``: a finished run's model judged on new measurements, nothing refitted.

The check a calibration engineer makes after a fit: a verification set measured later (another day, after a
crash), or from another tracker placement. With ``new_frame`` (the tracker moved) the measurement frame is
re-estimated as the least-squares rigid motion of the predictions onto the measured points (Kabsch, the exact
optimum of the positions' squared distances); the model's joint errors, tools and everything else are held, and
the nominal prediction gets its own best frame, so both rows are judged alike. Point runs give position
residuals; sensor runs (6-DOF poses) the sensor origin's position and the orientation angle.

Nothing is written into the run directory.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import torch

from ..analysis.stats import percent_decrease, residual_stats
from ..core import units
from ..core.progress import task as progress_task
from ..kinematics.transforms import kabsch
from ..measure.pose import rotation_error
from .common import moved_frame_note, stats_row


@dataclass
class VerifyResult:
    """rows: measured rows judged; table: Table 6 layout rows (Verification: nominal, modeled; sensors: and the
    angle); stats: {'position_mm': {nominal, modeled, decrease_percent}[, 'orientation_deg': ...]}; frame: with
    new_frame {'moved_mm', 'turned_deg'} of the modeled prediction's registration at the robot base, else None;
    output: the per-row CSV or None; warnings: said to the user."""

    rows: int
    table: list[dict]
    stats: dict
    frame: dict | None
    output: Path | None
    warnings: list[str] = field(default_factory=list)


def _predictions(model, data, sensor: bool):
    """-> (modeled, nominal) positions (R, 3) and rotations (R, 3, 3) or None, measurement frame, SI."""
    direction = data.direction if data.has_direction else None
    with torch.no_grad():
        if sensor:
            Tm, Tn = model.sensor_pose(data.q, None, direction), model.nominal_sensor_pose(data.q)
            return (Tm[:, :3, 3], Tm[:, :3, :3]), (Tn[:, :3, 3], Tn[:, :3, :3])
        return (model.points(data.q, data.tool, direction), None), (model.nominal_points(data.q, data.tool), None)


def verify_file(run_dir, data_path, output=None, device=None, new_frame: bool = False,
                units_checked: bool = False) -> VerifyResult:
    """``torchcal verify``: residuals of the run's model (and of the nominal robot) on the rows of ``data_path``, a
    CSV in the run's contract (mm, deg); with ``new_frame`` each prediction is first carried by its own best rigid
    motion onto the measurements (a new tracker placement). output: a per-row CSV (row, pose, tool, the predicted
    x, y, z in mm after any registration, nominal_mm / modeled_mm and, for sensors, nominal_deg / modeled_deg).
    Raises RunDirError / DataError / ConfigError naming the folder, file or key."""
    from ..io.csv import write_table
    from ..io.rundir import load_model, require_finished, run_model_notes
    from .config import run_config

    run_dir, data_path = Path(run_dir), Path(data_path)
    require_finished(run_dir, "torchcal verify")
    with progress_task(f"loading the run {run_dir}"):
        model = load_model(run_dir, device=device)
    sensor = hasattr(model, "sensor_pose")  # a 6-DOF sensor rig (Paper III) reads the sensor contract
    if not units_checked and (run_dir / "config.yaml").is_file():
        units_checked = bool(run_config(run_dir).data.units_checked)
    said: list[str] = run_model_notes(run_dir)
    with progress_task(f"reading {data_path}"):
        if sensor:
            from .sensor import read_sensor_set

            data = read_sensor_set(data_path, model.robot, model.device)
        else:
            from ..io.csv import read_measurements

            data = read_measurements(data_path, model.robot, int(model.tools.count)).to(model.device)
    if not units_checked:  # a sensor's positions at the flange, as its fit and update judge them
        from ..io.unit_checks import check_units, units_note

        tools = None if sensor else model.tools().detach().cpu()
        note = units_note(data, model.robot, *check_units(data, model.robot, tools, data_path))
        if note:
            said.append(note)
    inner = getattr(model, "model", model)  # a sensor rig's robot model
    je = getattr(inner, "joint_errors", None)
    if je is not None and je.has_backlash and not data.has_direction:  # the modeled residual was 2x, unsaid
        from .common import missing_directions_note

        said.append(missing_directions_note(data_path, model.robot.joint_map.n))
    outside = inner.outside_data(data.q) if hasattr(inner, "outside_data") else None
    if outside is not None and bool(outside.any()):
        said.append(f"{int(outside.any(-1).sum())} of {len(data)} rows command a joint beyond the identification "
                    "data's range: there the model extrapolates (column outside_data)")
    (pm, Rm), (pn, Rn) = _predictions(model, data, sensor)
    xyz = data.xyz.to(pm)
    frame = None
    if new_frame:
        Ym, tm = kabsch(pm, xyz)
        Yn, tn = kabsch(pn, xyz)
        o = inner.base()[:3, 3].detach().to(pm)  # the robot base in the run's measurement frame
        frame = {"moved_mm": float(units.m_to_mm((Ym @ o + tm - o).norm())),
                 "turned_deg": float(units.rad_to_deg(rotation_error(Ym, torch.eye(3).to(Ym)).norm()))}
        pm, pn = pm @ Ym.T + tm, pn @ Yn.T + tn
        if sensor:
            Rm, Rn = Ym @ Rm, Yn @ Rn
    res_m, res_n = (xyz - pm).norm(dim=-1), (xyz - pn).norm(dim=-1)
    if not new_frame and (note := moved_frame_note(pm, xyz, "--new-frame takes the measurement frame from these rows")):
        said.append(note)
    from ..analysis.stats import far_rows_message

    if far := far_rows_message(res_m, data, f"{data_path}: the run's model", fitted=False):  # it showed only as the max
        said.append(far)
    ps = [residual_stats(units.m_to_mm(x.cpu())) for x in (res_n, res_m)]
    table = [stats_row("Verification", "Nominal", ps[0], None), stats_row("Verification", "Modeled", ps[1], ps[0])]
    stats = {"position_mm": {"nominal": vars(ps[0]), "modeled": vars(ps[1]),
                             "decrease_percent": percent_decrease(ps[0].mean, ps[1].mean)}}
    ang = None
    if sensor:
        Rmeas = data.extra["rotation"].to(Rm)
        ang = [rotation_error(R, Rmeas).norm(dim=-1) for R in (Rn, Rm)]  # the fit's orientation residual
        rs = [residual_stats(units.rad_to_deg(a.cpu())) for a in ang]
        table += [stats_row("Verification", "Nominal angle (deg)", rs[0], None),
                  stats_row("Verification", "Modeled angle (deg)", rs[1], rs[0])]
        stats["orientation_deg"] = {"nominal": vars(rs[0]), "modeled": vars(rs[1]),
                                    "decrease_percent": percent_decrease(rs[0].mean, rs[1].mean)}
    if output is not None:
        import pandas as pd

        mm = units.m_to_mm(pm.detach().cpu().numpy())
        out = pd.DataFrame({"row": data.rows.cpu().numpy(), "pose": data.pose.cpu().numpy(),
                            "tool": data.tool.cpu().numpy(), "x_model": mm[:, 0], "y_model": mm[:, 1],
                            "z_model": mm[:, 2], "nominal_mm": units.m_to_mm(res_n.cpu().numpy()),
                            "modeled_mm": units.m_to_mm(res_m.cpu().numpy())})
        if ang is not None:
            out["nominal_deg"] = units.rad_to_deg(ang[0].cpu().numpy())
            out["modeled_deg"] = units.rad_to_deg(ang[1].cpu().numpy())
        if outside is not None:
            out["outside_data"] = np.asarray(outside.any(-1).cpu().numpy())
        output = write_table(Path(output), out)
    return VerifyResult(len(data), table, stats, frame, output, said)


__all__ = ["VerifyResult", "verify_file"]
