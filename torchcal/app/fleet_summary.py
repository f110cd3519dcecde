"""What a ``torchcal fleet`` run writes about the fleet as a whole: ``summary.csv`` / ``fleet.json`` (a row per
unit) and ``features.csv`` (the fleet's distribution behind every outlier finding)."""

from __future__ import annotations

from pathlib import Path

from ..core import units
from ..io.atomic import atomic_path


def write_features(run_dir: Path, names: list[str], scores, robot, threshold: float) -> None:
    """features.csv: per scored unit, joint and feature (transmission error, backlash) its value in deg (mm for a
    prismatic joint), the fleet median, its ratio to it, its robust z, the level above which it is flagged, and
    whether it is: the fleet's distribution behind every finding, for the report and the engineer."""
    import pandas as pd

    prismatic = robot.joint_map.prismatic.cpu()
    unit_names = units.joint_unit_names(prismatic)
    rows = []
    for key in scores.value:
        value = units.joints_from_si(scores.value[key], prismatic)
        median = units.joints_from_si(scores.median[key][None], prismatic)[0]
        level = units.joints_from_si(scores.flag_level(key, threshold)[None], prismatic)[0]
        z, ratio, flagged = scores.z[key], scores.ratio[key], scores.flagged(key, threshold)
        for m, name in enumerate(names):
            for j, joint in enumerate(scores.joints):
                rows.append({"unit": name, "joint": joint, "feature": key, "value": float(value[m, j]),
                             "value_unit": unit_names[j], "fleet_median": float(median[j]),
                             "ratio": float(ratio[m, j]), "robust_z": float(z[m, j]),
                             "flag_level": float(level[j]), "flagged": bool(flagged[m, j])})
    with atomic_path(run_dir / "features.csv") as tmp:
        pd.DataFrame(rows).to_csv(tmp, index=False, float_format="%.9g")


def write_summary(run_dir: Path, result, cfg) -> None:
    """summary.csv (one row per unit, the reason last) and fleet.json (the run's settings, every row, the findings
    and changes) of a fleet ``result`` (:class:`torchcal.app.fleet.FleetRunResult`)."""
    import pandas as pd

    from ..identify.fleet import OUTLIER_MIN_RATIO
    from ..identify.fleet_change import CHANGE_MIN_RATIO
    from ..io.rundir import write_json

    df = pd.DataFrame(result.rows)
    # one column order whatever unit comes first (a failed first unit put 'reason' third): the reason last
    df = df[[c for c in df.columns if c != "reason"] + (["reason"] if "reason" in df.columns else [])]
    with atomic_path(run_dir / "summary.csv") as tmp:
        df.to_csv(tmp, index=False, float_format="%.6g")
    write_json(run_dir / "fleet.json", {"time_s": result.time, "solve_time_s": result.solve_time,
                                        "engine": cfg.fleet.engine, "cell": int(cfg.fleet.cell),
                                        "model_backlash": cfg.model.backlash,  # as resolved for the whole fleet
                                        "threshold": float(cfg.fleet.threshold), "min_ratio": OUTLIER_MIN_RATIO,
                                        "units": result.rows, "findings": [str(f) for f in result.findings],
                                        "baseline": cfg.fleet.baseline, "reuse": cfg.fleet.reuse, "change_min_ratio": CHANGE_MIN_RATIO,
                                        "changes": [str(c) for c in result.changes]})


def read_summary(run_dir):
    """A fleet run's summary.csv as a DataFrame, unit names as written (a plant's serial '0001' read as the number 1
    matched no unit folder: fleet.reuse then took nothing, silently)."""
    import pandas as pd

    return pd.read_csv(Path(run_dir) / "summary.csv", dtype={"unit": str}, keep_default_na=False, na_values=[""])


__all__ = ["read_summary", "write_features", "write_summary"]
