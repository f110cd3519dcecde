"""What ``torchcal update`` checks of the new rows against the parent run, before and after the update.

Each returns what it found (statistics, joints, rows) for :mod:`torchcal.app.update` to say or refuse; a file
that cannot be used raises :class:`~torchcal.io.csv.DataError` naming it.
"""

from __future__ import annotations

from pathlib import Path

import torch

from ..analysis.stats import residual_stats
from ..core import units
from ..core.measurements import Measurements


def check_new_data(model, new: Measurements, new_path: Path, sensor: bool):
    """Refuse rows the update cannot use as the parent's robot: no approach directions for a backlash model,
    or points the calibrated model misses by more than any calibration error (another robot, frame or unit).
    -> the parent model's residual statistics (mm) on the new rows (a sensor run's: of the sensor positions) and its
    predictions of them (R, 3) m."""
    from ..io.csv import DataError, Problem

    je = getattr(getattr(model, "model", model), "joint_errors", None)  # a sensor rig's: its robot model's
    if je is not None and not new.has_direction:
        on = [j for j, b in enumerate(je.backlash_orders.cpu().tolist()) if b >= 0]
        if on:
            names = list(model.robot.joint_map.names)
            n = model.robot.joint_map.n
            raise DataError(new_path, [Problem(None, f"dir1..dir{n}", (
                f"missing on rows 1..{len(new)}: the run's model has backlash terms on {', '.join(names[j] for j in on)}, "
                f"which need each row's approach directions (+1 / -1 per joint)"))])
    from ..analysis.stats import point_residuals
    from .fit import NOMINAL_IMPLAUSIBLE_MM

    what = "sensor positions" if sensor else "points"
    with torch.no_grad():  # a sensor rig's points are its sensor origin's, the part of a 6-DOF row a moved tracker shows in
        pred = model.points(new.q, new.tool, new.direction if new.has_direction else None)
    modeled_m = (new.xyz.to(pred) - pred).norm(dim=-1)
    stats = residual_stats(modeled_m).scaled(units.m_to_mm(1.0))
    modeled = stats.mean
    if modeled > NOMINAL_IMPLAUSIBLE_MM:
        nominal_said = "" if sensor else \
            f" (nominal {units.m_to_mm(float(point_residuals(model, new, nominal=True).mean())):.1f} mm)"
        raise DataError(new_path, [Problem(None, "x, y, z", (
            f"the run's model misses these {what} by {modeled:.1f} mm on average{nominal_said}, far beyond "
            f"any calibration error (> {NOMINAL_IMPLAUSIBLE_MM:g} mm): data of another robot, tool set, measurement "
            f"frame or unit? An update only refines the parent's robot; fit such data with torchcal fit"))])
    miss = units.m_to_mm(modeled_m.detach().cpu())
    gross = (miss > NOMINAL_IMPLAUSIBLE_MM).nonzero()[:, 0].tolist()
    if gross:  # one bad row would be absorbed into the model (a 50 mm row took a 0.2 mm model to 1.1 mm)
        rows = new.rows.cpu().tolist()
        raise DataError(new_path, [Problem(int(rows[i]), "x, y, z", (
            f"the run's model misses this point by {float(miss[i]):.1f} mm (the file's median {float(miss.median()):.3f} "
            f"mm), beyond any calibration error (> {NOMINAL_IMPLAUSIBLE_MM:g} mm): a gross measurement (another "
            "reflector, a beam break)? Remove the row; an update would absorb it")) for i in gross])
    return stats, pred


def held_backlash(model, pinned, parent_coverage) -> list[str]:
    """Joints (their command names) whose constant backlash c0 is ``pinned`` (the gauge holds it), whose parent
    data (``parent_coverage``, the model's DirectionCoverage before the update) approached them from one
    direction only, and whose rows now (``model.coverage``, which the update widened) come from both: what an
    update cannot learn, since it keeps the gauge of the fit it started from."""
    after = getattr(model, "coverage", None)
    je = getattr(getattr(model, "model", model), "joint_errors", None)  # a sensor rig's: its robot model's
    if after is None or parent_coverage is None or je is None or not pinned:
        return []
    held = {n.split(".backlash.")[0].rsplit(".", 1)[-1] for n in pinned if n.endswith(".backlash.c0")}
    before, now = parent_coverage.counts.sum(1), after.counts.sum(1)  # (n, 3): rows per direction -1, 0, +1
    names = list(model.robot.joint_map.names)

    def both(c, i):
        return int(c[i, 0]) > 0 and int(c[i, 2]) > 0

    return [names[i] for i, j in enumerate(je.joint_names)
            if j in held and i < len(names) and not both(before, i) and both(now, i)]


def rows_in_parent(ident, model, new: Measurements, sensor: bool) -> list[int]:
    """Rows (1-based, as in the new file) whose commands and measured point equal a row of the parent's identification
    file bit for bit: the same measurement given twice. [] where that file is not readable (nothing to compare)."""
    if sensor or not ident or not Path(ident).is_file():
        return []
    from ..io.csv import read_measurements

    try:
        old = read_measurements(ident, model.robot, int(model.tools.count))
    except Exception:  # the parent's file is checked (and named) elsewhere; here it only might show repeats
        return []
    seen = {r.tobytes() for r in torch.cat([old.q, old.xyz], 1).cpu().numpy()}
    key = torch.cat([new.q, new.xyz], 1).cpu().numpy()
    rows = new.rows.cpu().tolist()
    return [int(rows[i]) for i, r in enumerate(key) if r.tobytes() in seen]


__all__ = ["check_new_data", "held_backlash", "rows_in_parent"]
