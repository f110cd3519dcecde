"""Which units of a fleet are not the fleet's robot as described, though their fits absorbed it.

A unit's model has a base frame, tool corrections and joint terms enough to absorb a robot that is not the one
described (a longer sister arm, tool labels swapped in the file, a tracker left elsewhere): its residual after
the fit looks like the others'. The nominal robot's residual does not. Such a unit is flagged, scored for no
outlier and left out of the fleet prior (:func:`implausible_units`), so that its parameters, which say nothing
about its gearboxes, neither raise false findings nor widen the prior.
"""

from __future__ import annotations

import torch

from ..core import units


NOMINAL_FLEET_RATIO = 2.0
"""How many times the fleet's median nominal residual a unit's must be (beside robust z > fleet.threshold) to be
suspected of being another robot (judged then against the fleet's joint features): a sister arm 10 mm longer lay
37x above a helper's fleet (0.50 mm median), one 12 mm longer 2.6x above a simulated one (4.8 mm), each fitted,
unflagged and in the fleet prior. Healthy units stay within 1.7x of the median at robust z 2.9 or less (two
100-FANUC fleets of the simulated type, 4.3-4.4 mm median; the helper's 23 units)."""


def implausible_units(fitted: list, rows: dict, robot, frames: dict, warn, threshold: float) -> tuple[dict, dict]:
    """The fitted units that may not be this robot as described -> ({unit: why}, {unit: (short, why)}).

    The first: the identification residual of the nominal robot (as ``torchcal fit`` warns) or of the fitted
    model beyond any plausible calibration error (:data:`torchcal.app.common.NOMINAL_IMPLAUSIBLE_MM`): the robot
    description, the tools (labels swapped) or the measurement frame are not this unit's, and the model's
    parameters, which absorb that, say nothing about its gearboxes (warned here). The second, suspects: the
    nominal residual far above the fleet's (:data:`NOMINAL_FLEET_RATIO`), which a badly damaged gearbox also
    gives; the caller judges them against the fleet's joint features (:func:`~torchcal.identify.fleet_outliers.
    judge_against`) and calls "another robot" only the ones no joint explains."""
    from ..identify.fleet_outliers import scores_from_values
    from .common import NOMINAL_IMPLAUSIBLE_MM

    hint = ("" if frames else "; measurement_frame: estimate when the tracker was not at the robot base")
    check = (f"check the robot description of '{robot.name}', the tool vectors and labels, the measurement frame and "
             f"the file's units (deg, mm){hint}")
    out, suspects = {}, {}
    nominal = {u["name"]: rows[u["name"]]["identification_nominal_mean_mm"] for u, _ in fitted}
    for u, _ in fitted:
        name = u["name"]
        mean, nom = rows[name]["identification_mean_mm"], nominal[name]
        if mean > NOMINAL_IMPLAUSIBLE_MM:
            out[name] = (f"identification residual mean {mean:.1f} mm after the fit, beyond any plausible calibration "
                         f"error (> {NOMINAL_IMPLAUSIBLE_MM:g} mm): {check}")
        elif nom > NOMINAL_IMPLAUSIBLE_MM:
            out[name] = (f"the nominal robot misses its identification points by {nom:.1f} mm (mean), beyond any "
                         f"plausible calibration error (> {NOMINAL_IMPLAUSIBLE_MM:g} mm), which the fit absorbed "
                         f"({mean:.3f} mm after it): {check}")
    for name, why in out.items():
        warn(f"unit {name}: {why}; not scored for outliers, left out of the fleet prior")
    rest = [name for name in nominal if name not in out]
    if len(rest) >= 3:  # judged against the units the absolute bound let through, as the features are
        sc = scores_from_values({"nominal": torch.tensor([[nominal[name]] for name in rest], dtype=torch.float64)},
                                ["nominal"])
        med = float(sc.median["nominal"][0])
        for k, name in enumerate(rest):
            nom = nominal[name]
            if float(sc.ratio["nominal"][k, 0]) > NOMINAL_FLEET_RATIO and float(sc.z["nominal"][k, 0]) > threshold:
                short = f"nominal residual {nom:.2f} mm, {nom / med:.1f}x the fleet's median"
                suspects[name] = (short, (
                    f"the nominal robot misses its identification points by {nom:.2f} mm (mean), {nom / med:.1f}x the "
                    f"fleet's median {med:.2f} mm, which the fit absorbed ({rows[name]['identification_mean_mm']:.3f} "
                    f"mm after it) and no joint's features explain: another robot than the fleet's? {check}"))
    return out, suspects


def nominal_means(fitted: list, idents: dict) -> dict[str, float]:
    """Each fitted unit's nominal residual mean (mm) on its identification rows: the nominal robot's points of
    every unit in one pass, since the chain and the nominal tools are the fleet's and a unit carries only its own
    measurement frame (a pass per unit cost 6 ms, 0.6 s of a 100-unit fleet's 7 s)."""
    if not fitted:
        return {}
    m0 = fitted[0][1]
    data = [idents[u["name"]] for u, _ in fitted]
    q = torch.cat([d.q for d in data]).to(m0.device, m0.dtype)
    tool = torch.cat([d.tool for d in data]).to(m0.device)
    out, start = {}, 0
    with torch.no_grad():
        F = m0.nominal_flange(q)
        p = (F[:, :3, :3] @ m0.tools.nominal[tool][..., None])[..., 0] + F[:, :3, 3]  # the robot base frame
        for (u, model), d in zip(fitted, data):
            B = model.base.nominal.to(p)
            mine = p[start:start + len(d)] @ B[:3, :3].T + B[:3, 3]
            out[u["name"]] = float(units.m_to_mm((mine - d.xyz.to(p)).norm(dim=1).mean()))
            start += len(d)
    return out


__all__ = ["NOMINAL_FLEET_RATIO", "implausible_units", "nominal_means"]
