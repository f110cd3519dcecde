"""What changed in each unit of a fleet since an earlier calibration of it: a crash, a gearbox swap, a season.

A plant re-measures its fleet after a crash, a gearbox swap or a season (issue #18). For every unit
calibrated both times, its earlier and its new fitted model are compared:

- at the tool (:func:`tool_change`): the distance between the points the two models predict at the unit's
  new commands, each with its own tool vectors, after the best rigid alignment of the two point sets (the
  tracker stands elsewhere in each campaign, and each fit places its measurement frame where it stood). This
  is what the robot does differently, whichever parameters carry it;
- per joint (:func:`joint_changes`): the change of the joint's transmission error (its modeled error about
  its own axis over its range, the mean over the range left out) and of its backlash.

Why not the joints' constant errors: of two parallel axes (a FANUC's J2 and J3), a mastering change of the
first, the matching shift of the link between them and the opposite mastering change of the second move no
point at first order, so two calibrations of one unchanged robot split its constant errors differently
(measured on simulated FANUCs: 0.02-0.3 deg from one measuring program to another, where the points agreed
to 0.08 mm). A changed mastering or a bent link shows at the tool, not at a joint.

Each change is judged against the fleet's own changes (:func:`changed_units`: the median and MAD over the
compared units, as :func:`~.fleet_outliers.parameter_outliers` judges the features themselves). What every
unit shares is the season, the targets' mounting and the calibrations' own scatter; a unit far beyond it at
the tool, or in a joint's transmission error, changed, and its joints whose changes lie far beyond the fleet's
say where. Joint 1's mastering is the
measurement frame's rotation about the base axis, which each campaign fits afresh: it needs a reference fixed
to the base and shows nowhere here.
"""

from __future__ import annotations

from dataclasses import dataclass

import torch

from ..core import units
from .alignment import kabsch
from .fleet_outliers import axis_errors, scores_from_values


def _axis_parts(model, samples: int) -> tuple[torch.Tensor, torch.Tensor]:
    """(S, n) the modeled error about (along) each joint's own axis over its range, direction-free part and
    backlash part (half the difference between the two approach directions)."""
    a_f, a_b = axis_errors(model, samples)
    return 0.5 * (a_f + a_b), 0.5 * (a_f - a_b)


def joint_changes(old_models, new_models, samples: int = 101) -> dict[str, torch.Tensor]:
    """Per unit and joint (M, n): 'transmission error change' (RMS over the joint's range of the change of its
    direction-free error about its own axis, its mean over the range left out (module docstring); rad, or m
    along a prismatic axis) and 'backlash change' (mean over the range of the backlash's change, absolute).

    old_models, new_models: M models each, unit by unit, of one structure (the same robot and orders).
    """
    if len(old_models) != len(new_models):
        raise ValueError(f"joint_changes: {len(old_models)} earlier models for {len(new_models)} new ones")
    ang, back = [], []
    with torch.no_grad():
        for old, new in zip(old_models, new_models):
            c_old, b_old = _axis_parts(old, samples)
            c_new, b_new = _axis_parts(new, samples)
            d = c_new - c_old.to(c_new)
            ang.append((d - d.mean(0)).pow(2).mean(0).sqrt())
            back.append((b_new - b_old.to(b_new)).abs().mean(0))
    return {"transmission error change": torch.stack(ang).cpu(), "backlash change": torch.stack(back).cpu()}


def tool_change(old, new, q: torch.Tensor, tool: torch.Tensor, direction: torch.Tensor | None = None) -> torch.Tensor:
    """(N,) distances (m) between the tool points of the earlier model ``old`` and the new model ``new`` at the
    commands q (N, n), tool indices tool (N,) and approach directions direction (N, n) or None, each model with
    its own tool vectors (a model's flange frame is only defined together with them), the earlier points carried
    onto the new ones by their best rigid motion (:func:`~.alignment.kabsch`: each campaign's own tracker frame).
    """
    if q.ndim != 2 or tool.shape != q.shape[:1]:
        raise ValueError(f"tool_change: q must be (N, n) and tool (N,), got {tuple(q.shape)} and {tuple(tool.shape)}")
    with torch.no_grad():
        dev, old_dev = new.tools().device, old.tools().device
        d = None if direction is None else direction.to(dev)
        p_new = new.points(q.to(dev), tool.to(dev), d)
        p_old = old.points(q.to(old_dev), tool.to(old_dev), None if d is None else d.to(old_dev)).to(dev)
        R, t = kabsch(p_old, p_new)
        return ((p_old @ R.T + t) - p_new).norm(dim=-1)


CHANGE_MIN_RATIO = 1.5
"""How many times the fleet's median change at the tool a changed unit's must be, beside its robust z
(:func:`changed_units`). Lower than the outlier test's 3x (:data:`~.fleet_outliers.OUTLIER_MIN_RATIO`): the
fleet's changes at the tool spread far less than its backlash does (100 simulated FANUCs, one season:
0.081-0.088 mm RMS, at most 1.04x their median; experiments/fleet/recheck.py)."""

SOLE_FEATURE = "transmission error change"
"""The joint change that names a unit changed with less than ``min_ratio`` x the fleet's change at the tool
(:func:`changed_units`), where the tool's change is beyond the fleet's scatter too; a backlash change only
says where. Two calibrations of one unchanged FANUC scatter in the wrist's backlash (joint 6: robust z up to
6.3, 4.1x the median over 87 healthy units) more than in a transmission error (z at most 4.1, 2.2x; one
healthy unit of 87 in another seed: joint 2, z 9, but nothing at the tool), which a gearbox swapped on the
wrist changes (joint 6: z 25, 9x) while the tool moves 1.1x the fleet's median change."""


@dataclass
class UnitChange:
    """A unit that changed since its earlier calibration far beyond the fleet's changes: at the tool by
    ``tool_rms_mm`` (RMS over its commands), ``ratio`` x the fleet's median change at robust z ``z``, and
    ``joints``: the joints whose transmission error or backlash changed far beyond the fleet's (each
    (joint, feature, change in deg or mm, its unit, ratio, z)); none where the change is a constant (a
    mastering, a bent link, a target)."""

    unit: int | str
    tool_rms_mm: float
    ratio: float
    z: float
    joints: list

    def __str__(self) -> str:
        who = self.unit if isinstance(self.unit, str) else f"unit {self.unit}"
        where = ("; " + ", ".join(f"{j} {f.replace(' change', '')} by {v:.3g} {u} (robust z {z:.0f})"
                                  for j, f, v, u, _, z in self.joints) if self.joints else
                 "; no joint's transmission error or backlash changed beyond the fleet's (a mastering, a link or a "
                 "target)")
        return (f"{who}: changed {self.tool_rms_mm:.3f} mm RMS at the tool, {self.ratio:.1f}x the fleet's median "
                f"change (robust z {self.z:.1f}){where}")


def changed_units(tool_rms: torch.Tensor, joint: dict[str, torch.Tensor], joints, prismatic,
                  threshold: float = 5.0, min_ratio: float = CHANGE_MIN_RATIO):
    """The units that changed far beyond the fleet: their change at the tool ``tool_rms`` (M,) (m, RMS of
    :func:`tool_change`) above ``threshold`` in robust z and at least ``min_ratio`` x the fleet's median; or
    above ``threshold`` in robust z alone where a joint's transmission error change (:data:`SOLE_FEATURE`) lies
    above ``threshold`` and 3x the fleet's (the outlier test's rule, :data:`~.fleet_outliers.OUTLIER_MIN_RATIO`):
    a gearbox swapped on the wrist moves the tool beyond the fleet's scatter but little. In each, the joints whose
    :func:`joint_changes` lie beyond the fleet's by that rule say where. A backlash change alone names no unit:
    two calibrations of one unchanged unit scatter most in the least determined terms (a wrist's backlash),
    which move no point.

    joint: {feature: (M, n)} as :func:`joint_changes` gives; joints: the n joint names; prismatic: (n,) bool, the
    joints whose findings are stated in mm (the others in deg). -> (tool scores, joint scores (:class:`FeatureScores`), the changed
    units (:class:`UnitChange`, largest z at the tool first)).
    """
    tool_sc = scores_from_values({"tool change": tool_rms[:, None]}, ["tool"])
    joint_sc = scores_from_values(joint, list(joints))
    value_units = units.joint_unit_names(prismatic)
    hit = tool_sc.flagged("tool change", threshold, min_ratio)[:, 0]
    if SOLE_FEATURE in joint_sc.value:  # confirmed at the tool: its points moved beyond the fleet's scatter
        hit = hit | (joint_sc.flagged(SOLE_FEATURE, threshold).any(1) & (tool_sc.z["tool change"][:, 0] > threshold))
    out = []
    for m in hit.nonzero()[:, 0].tolist():
        where = []
        for key in joint_sc.value:
            z, ratio = joint_sc.z[key][m], joint_sc.ratio[key][m]
            value = units.joints_from_si(joint_sc.value[key][m], prismatic)  # deg / mm
            for j in joint_sc.flagged(key, threshold)[m].nonzero()[:, 0].tolist():
                where.append((joint_sc.joints[j], key, float(value[j]), value_units[j], float(ratio[j]), float(z[j])))
        where.sort(key=lambda w: -w[5])
        out.append(UnitChange(m, units.m_to_mm(float(tool_rms[m])), float(tool_sc.ratio["tool change"][m, 0]),
                              float(tool_sc.z["tool change"][m, 0]), where))
    out.sort(key=lambda c: -c.z)
    return tool_sc, joint_sc, out


__all__ = ["CHANGE_MIN_RATIO", "SOLE_FEATURE", "UnitChange", "changed_units", "joint_changes", "tool_change"]
