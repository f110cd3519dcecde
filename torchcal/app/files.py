"""The file commands on a fitted run: ``torchcal predict`` and ``torchcal compensate`` (CSV in, CSV out).

Both load a run directory's model, ask the model contract (:mod:`torchcal.core.contract`) whether it can do
what is asked (a machine-tool or sensor run cannot compensate joint commands: one clear message), read the
CSV contract (mm, deg), refuse joints that look like radians, and write every input row back, in order, with
the answer and a reason for each flagged row. Writing goes through :func:`torchcal.io.csv.write_table`
(atomic, one overwrite policy).
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import torch

from ..core import units
from ..core.measurements import Measurements
from ..core.progress import task as progress_task
from ..io.csv import write_table
from .targets_input import (has_flags, ignored_flags_note, refuse_radian_orientations, refuse_targets_without_orientation,
                            seeds_from_flags)


def _refuse_radians(path, data: Measurements, model, units_checked: bool) -> None:
    """Commands that look like radians would be driven as degrees (a rail in metres as mm): refuse unless the user
    says they are degrees, the file's measured points fit degrees, or the run was itself identified on such
    commands (near-home)."""
    if units_checked:
        return
    from ..io.unit_checks import (OVERRIDE, RADIAN_BOUND, UnitsError, check_radians, degrees_confirmed,
                                  metre_columns, metre_message, radian_columns, radian_message)

    robot = model.robot
    if metres := metre_columns(data.q, robot):  # a rail in metres would be driven a thousandth of the way
        raise UnitsError(metre_message(path, data.q, robot, metres))
    rad = radian_columns(data.q, robot)
    if not rad:
        return
    if degrees_confirmed(check_radians(data, robot, model.tools().detach().cpu(), path)):  # radians: refused there
        return
    span = getattr(model, "data_span", None)
    if span is not None:  # the run's own commands (error variables: the same unit) stayed this close to home
        deg = units.joints_from_si(span.abs().amax(1)[None], robot.joint_map.prismatic.cpu())[0]
        cols = [int(c[1:]) - 1 for c in rad]
        if bool((deg[cols] <= RADIAN_BOUND).all()):
            return
    raise UnitsError(radian_message(path, data.q, robot, rad) + f"; pass {OVERRIDE} if they really are degrees")


@dataclass
class PredictFile:
    """What :func:`predict_file` wrote: rows, and how many command a joint beyond the identification data."""

    rows: int
    outside_data: int | None = None
    """Rows (of the file as read) with a joint beyond the identification data's range, the model's error series
    extrapolated there (column 'outside_data'); None for runs that recorded no range."""
    warnings: list[str] = field(default_factory=list)
    """What the input leaves out (no approach directions for a backlash model) and the rows beyond the data's
    range, said by the CLI."""


def _outside_data_column(model, q: torch.Tensor):
    """(B,) bool numpy per row, or None: any joint commanded beyond the identification data's range."""
    out = model.outside_data(q) if hasattr(model, "outside_data") else None
    return None if out is None else out.any(-1).cpu().numpy()


def _mark_outside_data(table, outside, input, said: list[str]) -> int | None:
    """The 'outside_data' column (``outside``: per row of ``table``, or None where the run recorded no range)
    added to ``table``, and its count said in ``said`` when any. -> that count (None: no range)."""
    if outside is None:
        return None
    table["outside_data"] = outside
    count = int(outside.sum())
    if count:
        said.append(f"{input}: {count} of {len(table)} rows put a joint beyond the identification data's range "
                    "(column 'outside_data'; for compensate, at the compensated command): the model extrapolates "
                    "its error terms there; measure such poses to calibrate them")
    return count


def predict_file(run_dir, input, output, device=None, units_checked: bool = False) -> PredictFile:
    """``torchcal predict``: the points x, y, z (mm, measurement frame) an identified model predicts for
    the commands of a CSV (tool, q1..qN [, dir1..dirN]); other columns are kept, measured x, y, z replaced.
    A file without a 'tool' column (``torchcal plan-poses`` writes commands only) gets every tool of the
    run for every row, tool by tool, with the 'tool' column added.

    Column 'outside_data' (when the run recorded its data's range): the row commands a joint beyond it.
    -> :class:`PredictFile`. Raises RunDirError / DataError naming the folder or file.
    """
    from ..io.csv import points_to_file, read_table
    from ..io.rundir import RunDirError, load_model, require_finished, run_model_notes

    require_finished(run_dir, "torchcal predict")
    with progress_task(f"loading the run {run_dir}"):
        model = load_model(run_dir, device=device)
    from ..core.contract import PredictsPoints, implements, require

    if not implements(model, PredictsPoints) and hasattr(model, "sensor_pose"):
        from .sensor import predict_pose_file  # a sensor run (Paper III): modeled x, y, z, r11..r33

        with progress_task(f"predicting the sensor poses of {input}"):
            done = PredictFile(predict_pose_file(run_dir, input, output, model))
        _provenance(output, run_dir, input, "predict sensor poses")
        return done
    try:
        require(model, "predict points", f"torchcal predict {run_dir}")
    except TypeError as exc:
        raise RunDirError(str(exc)) from None
    import pandas as pd

    from ..io.csv import parse_table

    T = model.tools.count
    with progress_task(f"reading {input}"):
        # commands beyond the controller range are predicted and marked (compensate keeps its flagged rows, so its
        # own output must stay readable), not refused
        data, df = read_table(input, model.robot, None, require_xyz=False, outside_limits="mark")
        per_tool = "tool" not in df.columns
        if not per_tool:  # the rows name their tools: checked against the run's
            data = parse_table(df, input, model.robot, T, require_xyz=False, outside_limits="mark")
    _refuse_radians(input, data, model, units_checked)
    beyond = data.extra.pop("outside_limits").numpy()
    data = data.to(model.device)
    # a file of commands only (e.g. from `torchcal plan-poses`): every row for every tool of the run, tool-major
    tools = range(T) if per_tool else [None]
    said = run_model_notes(run_dir) + _input_warnings(model, input, df, data, targets=False)
    outside = _outside_data_column(model, data.q)
    parts = []
    with torch.no_grad(), progress_task(f"predicting {len(df) * len(tools)} rows"):
        for t in tools:
            tool = data.tool if t is None else torch.full_like(data.tool, t)
            mm = points_to_file(model.points(data.q, tool, data.direction if data.has_direction else None))
            out = df.copy()
            if t is not None:
                out.insert(1 if "pose" in out.columns else 0, "tool", t)
            for i, c in enumerate(("x", "y", "z")):
                out[c] = mm[:, i]  # replaces measured values if the file had them, else appends the column
            parts.append(out)
    out = parts[0] if len(parts) == 1 else pd.concat(parts, ignore_index=True)
    if per_tool and T > 1:
        said.append(f"{input}: no 'tool' column: each of its {len(df)} rows is predicted for every one of the run's {T} "
                    f"tools ({len(out)} rows, tool by tool, column 'tool' added)")
    measured = [c for c in ("x", "y", "z") if c in df.columns]
    if measured:
        said.append(f"{input}: its columns {', '.join(measured)} are replaced by the predictions in {output} (the "
                    "input file is unchanged; `torchcal verify` compares a model with measured points)")
    # every tool's part holds the same commands: one judgement, repeated per part
    count = _mark_outside_data(out, None if outside is None else np.tile(outside, len(tools)), input, said)
    if beyond.any():
        out["within_limits"] = ~np.tile(beyond, len(tools))
        rows = np.flatnonzero(beyond)
        said.append(f"{input}: {rows.size} of {len(df)} rows command a joint outside the controller range (rows "
                    f"{', '.join(str(r + 1) for r in rows[:5])}{', ...' if rows.size > 5 else ''}): predicted there "
                    "all the same (the model extrapolates) and marked within_limits=False")
    write_table(output, out)
    _provenance(output, run_dir, input, "predict")
    return PredictFile(len(out), count, said)


@dataclass
class CompensationFile:
    """What :func:`compensate_file` wrote: row count and how many rows are flagged, and why."""

    rows: int
    not_converged: int
    outside_limits: int
    flagged: int
    direction_outside: int
    result: Any = field(default=None, repr=False)
    warnings: list[str] = field(default_factory=list)
    """What the input leaves out (no approach directions for a backlash model, targets without a tool), said
    by the CLI; the rows are still compensated."""
    targets: bool = False
    """The rows were Cartesian targets (not joint commands)."""


def _input_warnings(model, input, df, data, targets: bool) -> list[str]:
    """The two silent defaults of a compensation input, said: without dir1..dirN a backlash model is evaluated
    without its backlash terms (the commands are then off by the lost motion: on a user's robot 5x the error
    with directions), and targets without a 'tool' column are all for tool 0, not the flange."""
    out = []
    je = getattr(model, "joint_errors", None)
    if je is not None and je.has_backlash and not data.has_direction:
        from .common import missing_directions_note

        out.append(missing_directions_note(input, model.robot.joint_map.n))
    if targets and "tool" not in df.columns:
        tools = units.m_to_mm(model.tools().detach().cpu())
        t0 = ", ".join(f"{float(v):.3f}" for v in tools[0])
        out.append(f"{input}: no 'tool' column: every target is for tool 0 ({t0} mm in the flange frame, the run's "
                   f"identified tool 0), not the flange; add a 'tool' column (0..{model.tools.count - 1}) to choose")
    return out


def _provenance(output, run_dir, input, what: str, **options) -> None:
    """output's provenance sidecar (:func:`torchcal.io.rundir.write_provenance`): the run, its model and the
    input file by sha256, the options as given (None: the run's config or the default)."""
    from ..io.rundir import file_sha256, write_provenance

    axis = options.get("free_tool_axis")
    if axis is not None:
        options["free_tool_axis"] = [float(v) for v in axis]
    write_provenance(output, run_dir, command=what, input={"path": str(Path(input).resolve()),
                                                          "sha256": file_sha256(input)}, **options)


def _set_max_dq(out, dq_file, robot) -> None:
    """Column max_dq: each row's largest |q_new - q_nom| in file units; on a chain with both kinds of joint (an
    arm on a rail) max_dq is the revolute joints' (deg) and max_dq_mm the prismatic ones' (mm): one column took
    the larger of a mm and a deg number."""
    d = abs(np.asarray(dq_file, dtype=float))
    prismatic = robot.joint_map.prismatic.cpu().numpy().astype(bool)
    if prismatic.any() and not prismatic.all():
        out["max_dq"] = d[:, ~prismatic].max(axis=1)
        out["max_dq_mm"] = d[:, prismatic].max(axis=1)
    else:
        out["max_dq"] = d.max(axis=1)


def run_compensation_options(run_dir, tol_deg: float | None = None, max_iter: int | None = None,
                             max_correction_deg: float | None = None, prismatic=None) -> dict:
    """Keyword arguments for compensate(): the given values, else the run's config, else compensate()'s defaults.

    max_correction_deg: the correction bound, deg for revolute joints and the same number in mm for prismatic
    ones (``prismatic``: (n,) bool), as an (n,) SI tensor; the step bound is the smaller of it and
    compensate()'s default step (a 30 deg bound must not allow 30 deg Newton steps).
    """
    from ..io.rundir import load_run_config

    try:
        comp = load_run_config(run_dir).get("compensation", None) or {}
    except Exception:  # a run folder without (or with an older) config.yaml still compensates
        comp = {}
    out = compensation_kwargs(tol_deg if tol_deg is not None else comp.get("tol_deg"),
                              max_iter if max_iter is not None else comp.get("max_iter"))
    if max_correction_deg is not None:
        if prismatic is None:
            bound = units.deg_to_rad(float(max_correction_deg))
        else:
            bound = units.joint_scale(torch.as_tensor(prismatic).cpu()) * float(max_correction_deg)
        from ..compensate.bounds import DEFAULT_BOUND, DEFAULT_STEP_DEG, per_joint_bound

        if prismatic is None:
            step = min(bound, units.deg_to_rad(DEFAULT_STEP_DEG))
        else:
            step = torch.minimum(bound, per_joint_bound(DEFAULT_BOUND, bound.numel(), bound.dtype, "cpu", "max_step",
                                                        prismatic))
        out.update(max_correction=bound, max_step=step)
    return out


DOF_CHOICES = ("auto", "6", "5", "3")
"""``torchcal compensate --dof``: what of the tool's pose the commands restore (auto: what the run's tools observe)."""


def compensation_dof(model, dof: str = "auto", free_tool_axis=None) -> tuple[dict, str | None]:
    """The freedom of compensation for a run's model -> (compensate()'s free_tool_axis / position_only keywords,
    a note for the user where 'auto' chose less than the whole pose, else None).

    dof: 'auto' (:func:`torchcal.compensate.observed_dof`: one tool -> 3, two or collinear tools -> 5 about
    their line, else 6), '6', '5' (needs free_tool_axis, the axis (3,) in the flange frame) or '3';
    free_tool_axis given with 'auto' means '5' about it (``--free-tool-axis``)."""
    from ..compensate import observed_dof
    from .config import ConfigError

    dof = str(dof)
    if dof not in DOF_CHOICES:
        raise ConfigError(f"--dof '{dof}': expected one of {', '.join(DOF_CHOICES)}")
    if free_tool_axis is not None:
        if dof not in ("auto", "5"):
            raise ConfigError(f"--free-tool-axis is 5-DOF compensation; it cannot be given with --dof {dof}")
        return {"free_tool_axis": torch.as_tensor(free_tool_axis, dtype=model.dtype, device=model.device)}, None
    if dof == "5":
        raise ConfigError("--dof 5 needs the free axis: give --free-tool-axis [--tool-axis X,Y,Z]")
    if dof == "6":
        return {}, None
    if dof == "3":
        return {"position_only": True}, (None if model.tools.count == 1 else (
            f"--dof 3: each row's identified tool point is the one put on its programmed position (the row's tool "
            f"column; tool 0 where the file has none) of the run's {model.tools.count} tools"))
    seen, axis = observed_dof(model)
    if seen == 6:
        return {}, None
    T = model.tools.count
    measured = getattr(model, "measured_tools", None)
    if measured is not None and len(measured) < T:  # the others' vectors are their nominal ones: no evidence
        which = (f"the run's data measured only tool{'s' if len(measured) > 1 else ''} "
                 f"{', '.join(str(t) for t in measured)} of its {T}")
        T = len(measured)
    else:
        which = "the run's model has one tool" if T == 1 else f"the run's {T} tools sit at one point"
    if seen == 3:
        return {"position_only": True}, (
            which +
            ": its data measured one point per pose and do not fix the flange's orientation, so each command puts "
            "the row's tool point on its programmed position only (3-DOF, the smallest joint motion); --dof 6 "
            "compensates the whole flange pose")
    return {"free_tool_axis": axis.to(model.device, model.dtype)}, (
        f"the run's {T} tools lie on one line: the turn about it is not observed, so the commands leave it free "
        "(5-DOF about the tools' line); --dof 6 compensates the whole flange pose")


def compensate_file(run_dir, input, output, device=None, tol_deg: float | None = None, max_iter: int | None = None,
                    max_correction_deg: float | None = None, units_checked: bool = False,
                    free_tool_axis=None, dof: str = "auto") -> CompensationFile:
    """``torchcal compensate``: compensated commands for every row of a CSV (q1..qN [, dir1..dirN], deg / mm).

    free_tool_axis: None, or the tool axis (3,) in the flange frame whose rotation is left free
    (axisymmetric tools: 5-DOF compensation); the point on the axis is the identified tool of each row's
    'tool' column, else the flange origin. dof: :func:`compensation_dof` ('auto': 3-DOF for a run with one
    tool, 5-DOF for tools on one line, the point being each row's tool, else tool 0).

    Writes q1..qN compensated plus converged, iterations, within_limits,
    max_dq (largest |q_new - q_nom|, deg / mm; with both kinds of joint: revolute, deg, and max_dq_mm)
    [, direction_outside]; every
    input row is kept, in order, other columns too. Raises RunDirError /
    DataError naming the folder or file.
    """
    from ..compensate import compensate, row_tool_points
    from ..io.csv import joint_columns, joints_to_file, write_table
    from ..io.rundir import load_model

    from ..core.contract import require
    from ..io.rundir import RunDirError, require_finished, run_model_notes

    require_finished(run_dir, "torchcal compensate")
    with progress_task(f"loading the run {run_dir}"):
        model = load_model(run_dir, device=device)
    try:  # the model contract: machine tools and sensor rigs have no joint-error Newton solve
        require(model, "compensate commands", f"torchcal compensate {run_dir}")
    except TypeError as exc:
        raise RunDirError(str(exc)) from None
    freedom, dof_note = compensation_dof(model, dof, free_tool_axis)
    robot = model.robot
    from ..io.csv import parse_table, read_raw_table, target_kind

    with progress_task(f"reading {input}"):
        df = read_raw_table(Path(input))
        refuse_targets_without_orientation(Path(input), df)
        flags_note = ignored_flags_note(df, robot, input) if target_kind(df) is not None else None  # before seeding
        unseeded = None
        if target_kind(df) is not None and has_flags(df, robot):  # the controller's branch by configuration flags
            df, unseeded = seeds_from_flags(model, Path(input), df)
        data = parse_table(df, Path(input), robot, None, False, False)
    _refuse_radians(input, data, model, units_checked)
    targets = target_kind(df) is not None
    if targets and not units_checked:  # target x, y, z in metres: ~1000x too close together
        from ..io.unit_checks import check_point_scale

        check_point_scale(data, robot, model.tools().detach().cpu(), path=input)
        if unseeded is None and not freedom.get("position_only"):  # seeds from the file: they tell the unit
            refuse_radian_orientations(model, Path(input), df, data.q)

    said = run_model_notes(run_dir) + _input_warnings(model, input, df, data, targets=targets)
    if flags_note is not None:
        said.append(flags_note)
    if dof_note is not None:
        said.insert(0, dof_note)
    if targets:  # Cartesian targets: q1..qN are the controller's seeds (its branch)
        done = _compensate_targets_file(model, run_dir, input, output, data, df, tol_deg, max_iter, max_correction_deg,
                                        freedom, unseeded)
        done.warnings[:0] = said
        _provenance(output, run_dir, input, "compensate targets", tol_deg=tol_deg, max_iter=max_iter,
                    max_correction_deg=max_correction_deg, dof=dof, free_tool_axis=free_tool_axis)
        return done
    data = data.to(model.device)
    opts = run_compensation_options(run_dir, tol_deg, max_iter, max_correction_deg, robot.joint_map.prismatic)
    opts.update(freedom)
    if freedom:
        # each row's identified tool point is the one compensated (on the free axis); without a tool column the
        # free axis passes through the flange origin, the position-only point is tool 0
        if "tool" in df.columns or free_tool_axis is None:
            opts["tool_point"] = row_tool_points(model, _with_run_tools(model, input, df, data).tool)
    with progress_task(f"compensating {len(df)} commands"):
        res = compensate(model, data.q, data.direction if data.has_direction else None, **opts)
    q_file = joints_to_file(res.q, robot)
    out = df.copy()
    for i, c in enumerate(joint_columns(robot.joint_map.n)):
        out[c] = q_file[:, i]  # every row kept, in input order; failures are marked below
    out["converged"] = res.converged.cpu().numpy()
    out["iterations"] = res.iterations.cpu().numpy()
    out["within_limits"] = res.within_limits.cpu().numpy()
    # largest correction in file units (deg / mm): a flagged or large one is visible per row
    _set_max_dq(out, q_file - joints_to_file(data.q, robot), robot)
    if res.direction_outside is not None:
        out["direction_outside"] = res.direction_outside.cpu().numpy()
    # judged where the model is evaluated: the compensated command
    _mark_outside_data(out, _outside_data_column(model, res.q), input, said)
    out["reason"] = res.reasons(opts.get("max_correction"), robot.joint_map.prismatic)
    write_table(output, out)
    _provenance(output, run_dir, input, "compensate commands", tol_deg=tol_deg, max_iter=max_iter,
                max_correction_deg=max_correction_deg, dof=dof, free_tool_axis=free_tool_axis)
    nc, ol = int((~res.converged).sum()), int((~res.within_limits).sum())
    return CompensationFile(len(df), nc, ol, int((~res.converged | ~res.within_limits).sum()),
                            0 if res.direction_outside is None else int(res.direction_outside.sum()), res, said)


def _with_run_tools(model, input, df, data):
    """The rows read again with their 'tool' column checked against the run's tools (a file without one keeps
    ``data``: tool 0 on every row)."""
    if "tool" not in df.columns:
        return data
    from ..io.csv import parse_table

    return parse_table(df, input, model.robot, model.tools.count, require_xyz=False, require_pose=False)


def _compensate_targets_file(model, run_dir, input, output, data, df, tol_deg, max_iter,
                             max_correction_deg, freedom=None, unseeded=None) -> CompensationFile:
    """``torchcal compensate`` on Cartesian targets (x, y, z mm; rx, ry, rz deg or qw, qx, qy, qz; robot base
    frame; q1..qN the seeds on the controller's branch; tool optional, default 0): writes q1..qN calibrated,
    x_cmd .. rz_cmd the corrected target for a controller that runs nominal IK with its nominal tool data,
    converged, within_limits, max_dq (against the nominal IK's commands) [, direction_outside] and reason (empty
    when converged)."""
    from ..compensate.targets import compensate_targets, pose_rpy, target_poses
    from ..io.csv import joint_columns, joints_to_file, read_targets

    robot = model.robot
    data = _with_run_tools(model, input, df, data)
    _, pos, ori = read_targets(df, input)
    T = target_poses(pos, ori).to(model.device)
    data = data.to(model.device)
    with progress_task(f"compensating {len(df)} Cartesian targets"):
        res = compensate_targets(model, T, data.q, data.tool, data.direction if data.has_direction else None,
                                 **(freedom or {}), **run_compensation_options(run_dir, tol_deg, max_iter,
                                                                               max_correction_deg,
                                                                               robot.joint_map.prismatic))
    q_file = joints_to_file(res.q, robot)
    out = df.copy()
    for i, c in enumerate(joint_columns(robot.joint_map.n)):
        out[c] = q_file[:, i]
    cmd = pose_rpy(res.command_target).cpu()
    for i, c in enumerate(("x_cmd", "y_cmd", "z_cmd")):
        out[c] = units.m_to_mm(cmd[:, i]).numpy()
    for i, c in enumerate(("rx_cmd", "ry_cmd", "rz_cmd")):
        out[c] = units.rad_to_deg(cmd[:, 3 + i]).numpy()
    comp = res.compensation
    converged = res.converged.cpu()
    if unseeded is not None and bool(unseeded.any()):  # no command with the flags: nothing to send for the row
        converged = converged & ~unseeded
        rows = unseeded.nonzero()[:, 0].tolist()
        for i in rows:
            res.reason[i] = "configuration flags: no nominal IK solution with these flags was found"
        cols = list(joint_columns(robot.joint_map.n)) + ["x_cmd", "y_cmd", "z_cmd", "rx_cmd", "ry_cmd", "rz_cmd"]
        out.loc[out.index[rows], cols] = np.nan  # no command on some other branch
    out["converged"] = converged.numpy()
    out["within_limits"] = comp.within_limits.cpu().numpy()
    _set_max_dq(out, q_file - joints_to_file(res.q_nominal, robot), robot)
    within = comp.within_limits.cpu()
    if unseeded is not None and bool(unseeded.any()):  # no command: nothing to measure against the limits
        out["within_limits"] = out["within_limits"].astype(object)
        moved = ["max_dq"] + (["max_dq_mm"] if "max_dq_mm" in out.columns else [])
        out.loc[out.index[unseeded.numpy()], ["within_limits", *moved]] = [None] + [np.nan] * len(moved)
        within = within | unseeded  # counted as not converged, not as outside the range
    outside_dirs = None if comp.direction_outside is None else comp.direction_outside.cpu().clone()
    if outside_dirs is not None:  # the console counts it: the rows must say which
        out["direction_outside"] = outside_dirs.numpy()
        if unseeded is not None and bool(unseeded.any()):  # no command: no approach to judge
            outside_dirs &= ~unseeded
            out["direction_outside"] = out["direction_outside"].astype(object)
            out.loc[out.index[unseeded.numpy()], "direction_outside"] = None
    said: list[str] = []
    _mark_outside_data(out, _outside_data_column(model, res.q), input, said)
    out["reason"] = res.reason
    write_table(output, out)
    flagged = int((~converged).sum())
    # a target the nominal IK cannot reach (or with no seed for its flags) is a row that did not converge too
    return CompensationFile(len(df), int((~converged & within).sum()), int((~within).sum()), flagged,
                            0 if outside_dirs is None else int(outside_dirs.sum()), comp, said, targets=True)


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


__all__ = ["CompensationFile", "compensate_file", "compensation_kwargs", "predict_file", "run_compensation_options"]
