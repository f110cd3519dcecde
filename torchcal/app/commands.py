"""The CLI's file commands beyond fit / predict / compensate: tracker and T-Mac imports, pose planning, controller
tables, the calibration report.

Each takes paths and the user's options (mm, deg), calls the library, writes its files (atomically, through the
library's writers) and returns what a front end shows. The CLI (:mod:`torchcal.cli`) parses, checks the
overwrite policy and prints; it calls nothing below this layer (an import contract checks it), so a second
front end (a notebook, a service) gets the same commands.
"""

from __future__ import annotations

from pathlib import Path

from ..core import units


def import_tracker_file(output, joints, targets, bases, robot: str | None, drift_threshold_mm: float,
                        correct_drift: bool, outlier_mm: float):
    """``torchcal import-tracker``: tracker exports -> the measurement CSV ``output``.

    -> :class:`torchcal.io.tracker.TrackerImport` (``table``, ``report`` lines, ``summary_table()``).
    """
    from ..io.csv import write_table
    from ..io.tracker import import_tracker
    from ..kinematics import load_robot

    rob = load_robot(robot) if robot else None
    res = import_tracker(joints, list(targets), list(bases or []), rob, drift_threshold_mm, correct_drift, outlier_mm)
    write_table(output, res.table)
    return res


def import_tmac_file(source, output, robot: str, convention: str, exclude=()) -> tuple[Path, list[str]]:
    """``torchcal import-tmac``: a UR10 + Leica T-Mac export -> the sensor CSV ``output``; -> (its path, warnings:
    rows repeated bit for bit, kept)."""
    from ..io.tmac import convert_tmac
    from ..kinematics import load_robot

    said: list[str] = []
    return convert_tmac(source, output, load_robot(robot), convention, exclude or (), warnings=said), said


def plan_poses_file(robot: str, count: int, output, seed: int = 0, tracker_mm=None, min_distance_mm: float = 200.0,
                    min_height_mm: float = 0.0, max_incidence_deg: float = 60.0, order: str = "decorrelate",
                    fleet=None, candidates: int = 2000):
    """``torchcal plan-poses``: ``count`` measurement poses -> ``output`` (pose, q1..qN in deg / mm).

    tracker_mm: the tracker's position [x, y, z] in the robot base frame (mm) or None. The count is checked
    before the robot loads (a huge count used to die in numpy's allocator). fleet: a ``torchcal fleet`` run
    directory: the poses are designed for a unit that will be fitted with that fleet's prior (``prior.fleet``):
    ``count`` of ``candidates`` reachable poses, picked to lower the predicted model error most
    (:func:`torchcal.analysis.fleet_design.design_poses`); the plan's stats then carry 'design': the predicted
    RMS model error (mm) of the designed poses and of the first ``count`` plain ones. -> (plan, robot): the
    :class:`torchcal.analysis.planning.PosePlan` (its ``stats``) and the loaded robot (joint names).
    """
    from ..analysis.planning import MAX_POSES, PlanningError, ordered_plan, plan_poses
    from ..kinematics import load_robot

    if not 1 <= count <= MAX_POSES:
        raise PlanningError(f"COUNT {count}: plan between 1 and {MAX_POSES} poses")
    if fleet is not None and not count < candidates <= MAX_POSES:
        raise PlanningError(f"--candidates {candidates}: give more candidates than poses ({count}) to design from")
    import math

    for flag, value, ok in (("--min-distance-mm", min_distance_mm, math.isfinite(min_distance_mm) and min_distance_mm >= 0),
                            ("--min-height-mm", min_height_mm, math.isfinite(min_height_mm)),
                            ("--max-incidence-deg", max_incidence_deg, 0 < max_incidence_deg <= 180)):
        if not ok:  # NaN passes every comparison's negation: a NaN incidence bound switched visibility off
            raise PlanningError(f"{flag} {value}: give "
                                + ("a distance >= 0 (mm)" if flag == "--min-distance-mm" else "a finite height (mm)"
                                   if flag == "--min-height-mm" else "an angle in (0, 180] degrees"))
    rob = load_robot(robot)
    tracker = None if tracker_mm is None else [units.mm_to_m(float(v)) for v in tracker_mm]
    kw = dict(seed=seed, tracker=tracker, min_tool_distance=units.mm_to_m(min_distance_mm),
              min_height=units.mm_to_m(min_height_mm), max_incidence_deg=max_incidence_deg)
    if fleet is None:
        plan = _in_option_words(plan_poses, rob, count, order=order, **kw)
    else:
        pool = _in_option_words(plan_poses, rob, candidates, order="sequence", **kw)  # reachable, visible; Sobol
        design = _fleet_design(fleet, rob, seed)
        picked, rms = design(pool.q, count)
        plain = design(pool.q[:count], count)[1]  # the plan without the design
        plan = ordered_plan(pool.q[picked], pool.flange[picked], pool.limits, order, seed, None, 8,
                            {"drawn": pool.stats["drawn"], "rejected": pool.stats["rejected"],
                             "design": {"fleet": str(fleet), "candidates": candidates,
                                        "predicted_rms_mm": units.m_to_mm(float(rms[-1])),
                                        "plain_predicted_rms_mm": units.m_to_mm(float(plain[-1])),
                                        "prior_rms_mm": units.m_to_mm(float(rms[0]))}})
    plan.to_csv(output, rob)
    from ..io.rundir import write_provenance

    # the plan is drawn from a seed: what it took to draw it again
    write_provenance(output, None, command="plan-poses", robot=str(robot), count=count, seed=seed, order=order,
                     tracker_mm=None if tracker_mm is None else [float(v) for v in tracker_mm],
                     min_distance_mm=min_distance_mm, min_height_mm=min_height_mm, max_incidence_deg=max_incidence_deg,
                     fleet=None if fleet is None else str(fleet), candidates=candidates if fleet is not None else None)
    return plan, rob


_OPTION_WORDS = (("plan_poses: ", "plan-poses: "), ("order must", "--order must"),
                 ("relax min_height / min_tool_distance / max_incidence_deg",
                  "relax --min-height-mm / --min-distance-mm / --max-incidence-deg"))


def _in_option_words(fn, *args, **kwargs):
    """``fn(*args, **kwargs)`` with a PlanningError's argument names put in the command's option names."""
    from ..analysis.planning import PlanningError

    try:
        return fn(*args, **kwargs)
    except PlanningError as exc:
        msg = str(exc)
        for lib, cli in _OPTION_WORDS:
            msg = msg.replace(lib, cli)
        raise PlanningError(msg) from None


def _fleet_design(fleet, rob, seed: int):
    """The fleet run ``fleet``'s prior, read once, as a design function: (q (N, n) candidate commands, count) ->
    (picked (count,), predicted RMS model error (m) before and after each pick); given exactly ``count``
    candidates, the predicted error of those."""
    import torch

    from ..analysis.fleet_design import design_poses
    from ..identify.problem import NoiseModel
    from .fleet_prior import prior_from_fleet_run

    from ..io.rundir import is_fleet_run
    from .config import ConfigError

    if not is_fleet_run(fleet):
        raise ConfigError(f"--fleet {fleet}: not a `torchcal fleet` run directory (it needs the summary.csv and "
                          "units/ that `torchcal fleet` writes; a `torchcal fit` run has neither)")
    fp = prior_from_fleet_run(fleet, robot=rob)
    model, free = fp.unit_model, fp.free
    cov = fp.block.cov.to(fp.mean)[free][:, free]
    lim = rob.joint_map.limits.to(fp.mean)
    u = torch.quasirandom.SobolEngine(lim.shape[0], scramble=True, seed=int(seed) + 1).draw(200, dtype=fp.mean.dtype)
    val = lim[:, 0] + u * (lim[:, 1] - lim[:, 0])
    noise = NoiseModel.from_robot(model.robot)
    return lambda q, count: design_poses(model, fp.mean, cov, free, q.to(fp.mean), count, noise, val, seed)


def table_output_names(fmt: str) -> list[str] | None:
    """The files (glob patterns, relative to the output folder) a folder format of ``export-tables`` writes;
    None for the file formats (csv, siemens-cec), whose output is the path itself."""
    from ..export.linuxcnc_hal import FILES as VOL_FILES, FORMAT as VOL

    if fmt == "linuxcnc":
        return ["*.comp", "linuxcnc_comp.ini"]
    if fmt == VOL:
        return list(VOL_FILES)
    if fmt == "all":
        return ["tables.csv", "cec_tables.mpf", "linuxcnc/*.comp", "linuxcnc/linuxcnc_comp.ini",
                *[f"linuxcnc_volumetric/{f}" for f in VOL_FILES]]
    return None


def export_tables(run_dir, out, fmt: str = "csv", points: int | None = None, max_points: int = 2000):
    """``torchcal export-tables``: a machine run's compensation tables in a controller format; -> what was
    written (a path, or {name: path}); refusals and end-slope notes come as warnings."""
    from ..export.controller import export_run_tables
    from ..io.rundir import require_finished

    require_finished(run_dir, "torchcal export-tables")
    return export_run_tables(run_dir, out, fmt, points, max_points)


def export_urdf(run_dir, out, base: str = "joint", measurement_frame: bool = False, constants: str = "fit",
                force: bool = False):
    """``torchcal export-urdf``: a robot run's calibrated URDF (:func:`torchcal.export.urdf.export_run_urdf`),
    compared on the run's validation data, else its identification data (the first its config names that
    exists). -> (:class:`~torchcal.export.urdf.RunUrdfExport`, 'validation', 'identification' or None)."""
    from ..export.urdf import export_run_urdf
    from ..io.rundir import require_finished
    from .config import run_config

    require_finished(run_dir, "torchcal export-urdf")
    cfg = run_config(run_dir)
    data, which = None, None
    for key in ("validation", "identification"):
        path = getattr(cfg.data, key)
        if path and Path(path).is_file():
            data, which = Path(path), key
            break
    ident = cfg.data.identification
    fit_data = Path(ident) if ident and Path(ident).is_file() else None  # the constants fitted where the model is known
    res = export_run_urdf(run_dir, out, base, measurement_frame, constants, data, force, fit_data)
    from ..io.rundir import write_provenance

    write_provenance(out, run_dir, command="export-urdf", base=base, measurement_frame=measurement_frame,
                     constants=constants, joint_map=None if res.export.joint_map is None else str(res.export.joint_map))
    return res, which


def run_notes(run_dir) -> list[str]:
    """What a command using the run's model must say (:func:`torchcal.io.rundir.run_model_notes`): a fit that did
    not converge, a fleet unit its data did not determine."""
    from ..io.rundir import run_model_notes

    return run_model_notes(run_dir)


def write_report(run_dir, out=None) -> Path:
    """``torchcal report``: the run directory's self-contained ``report.html`` (:mod:`torchcal.report`)."""
    from ..report import write_report as _write

    return _write(run_dir, out)


__all__ = ["export_tables", "export_urdf", "import_tmac_file", "import_tracker_file", "plan_poses_file", "run_notes",
           "table_output_names", "write_report"]
