"""Which units of a fleet lie far from the others: a damaged gearbox, a bad measurement.

Each unit's fitted model is reduced to two features per joint (:func:`joint_features`: the transmission error's
RMS over the range, the backlash); each feature is standardized by the fleet's median and MAD
(:func:`feature_scores`), and :func:`parameter_outliers` flags the units' joints that lie far above the fleet.
``torchcal fleet`` writes the scores to features.csv for the fleet report.
"""

from __future__ import annotations

from dataclasses import dataclass

import torch


@dataclass
class Outlier:
    """A flagged unit (its index in the fleet, or its name): which joint and feature lie far from the fleet."""

    unit: int | str
    joint: str
    feature: str
    ratio: float
    z: float

    def __str__(self) -> str:
        who = self.unit if isinstance(self.unit, str) else f"unit {self.unit}"
        return f"{who}: {self.joint} {self.feature} {self.ratio:.1f}x the fleet median (robust z {self.z:.1f})"


def axis_errors(model, samples: int = 101) -> tuple[torch.Tensor, torch.Tensor]:
    """(S, n) twice: each joint's modeled error about (along, if prismatic) its own axis at ``samples`` points
    evenly over its range, approached from the + side and from the - side (rad or m)."""
    je = model.joint_errors
    with torch.no_grad():
        lo, hi = je.ranges[:, 0], je.ranges[:, 1]
        t = torch.linspace(0.0, 1.0, samples, dtype=lo.dtype, device=lo.device)[:, None]
        u = lo + t * (hi - lo)
        ones = torch.ones_like(u)
        prismatic = model.prismatic.to(u.device)[None, :]
        axes = model.axes.to(u)

        def along(tw):  # (S, n, 6) twists -> (S, n): the turn about, or the move along, each joint's own axis
            return torch.where(prismatic, (tw[..., 3:] * axes).sum(-1), (tw[..., :3] * axes).sum(-1))

        coupling = getattr(model, "backlash_coupling", lambda: None)()
        if coupling is None:  # backlash in E_i about (along) each joint's own axis (Paper II (13))
            return along(je.twists(u, ones)), along(je.twists(u, -ones))
        # backlash_on: command moves the joint variables through the coupling: each command's own lost motion
        axis = along(je.twists(u, None))
        b = je.backlash_values(u, ones) if je.has_backlash else torch.zeros_like(axis)
        return axis + b, axis - b


def joint_features(model, samples: int = 101) -> dict[str, torch.Tensor]:
    """Per joint (n,): 'transmission error' (RMS over the joint's range of its modeled error about its own axis, the
    transmission error, rad or m) and 'backlash' (mean half difference between the two approach directions)."""
    axis, axis_b = axis_errors(model, samples)
    ang = (axis - axis.mean(0)).pow(2).mean(0).sqrt()
    back = (0.5 * (axis - axis_b)).abs().mean(0)
    return {"transmission error": ang, "backlash": back}


OUTLIER_MIN_RATIO = 3.0
"""How many times the fleet median a flagged unit's feature must be, beside its robust z (:func:`parameter_outliers`)."""


@dataclass
class FeatureScores:
    """The fleet's joint features and how far each unit lies from the fleet: per feature name (M, n) tensors
    ``value`` (rad or m, as :func:`joint_features` gives them), ``z`` (the modified z-score) and ``ratio`` (to
    the fleet median), and per feature (n,) ``median`` and ``mad``; ``joints`` the joints' names."""

    joints: list
    value: dict
    z: dict
    ratio: dict
    median: dict
    mad: dict

    def flagged(self, key: str, threshold: float, min_ratio: float = OUTLIER_MIN_RATIO) -> torch.Tensor:
        """(M, n) bool: the units' joints that lie far from the fleet (z > threshold, at least min_ratio x the median)."""
        return (self.z[key] > threshold) & (self.ratio[key] >= min_ratio)

    def flag_level(self, key: str, threshold: float, min_ratio: float = OUTLIER_MIN_RATIO) -> torch.Tensor:
        """(n,) the value above which a unit's joint is flagged: z > threshold and at least min_ratio x the median."""
        return torch.maximum(self.median[key] + threshold * self.mad[key] / 0.6745, min_ratio * self.median[key])


def feature_scores(models) -> FeatureScores:
    """:func:`joint_features` of every model, each feature standardized by the fleet's median and MAD."""
    feats = [joint_features(m) for m in models]
    return scores_from_values({key: torch.stack([f[key] for f in feats]) for key in feats[0]},
                              list(models[0].joint_errors.joint_names))


MAD_FLOOR = 0.01
"""The least spread (a fraction of the fleet median) a feature's MAD is taken to have."""


def scores_from_values(values: dict, joints: list, against: FeatureScores | None = None) -> FeatureScores:
    """Per feature name (M, n) values of M units, each standardized by the units' median and MAD (per column), or
    by those of ``against`` (another fleet's scores, which these units then do not move)."""
    out = FeatureScores(list(joints), {}, {}, {}, {}, {})
    for key, F in values.items():
        F = F.detach().cpu().clamp(min=1e-15)  # (M, n)
        if against is not None:
            med, mad = against.median[key], against.mad[key]
        else:
            med = F.median(0).values
            # a spread of at least 1 % of the median: units with equal values (a file given twice, a fleet of
            # three) have no MAD, and a z-score divided by nothing says 1e12 where a ratio says 1.2
            mad = torch.maximum((F - med).abs().median(0).values, MAD_FLOOR * med.abs()).clamp(min=1e-15)
        out.value[key], out.median[key], out.mad[key] = F, med, mad
        out.z[key] = 0.6745 * (F - med) / mad
        out.ratio[key] = F / med
    return out


def parameter_outliers(fit, threshold: float = 5.0, min_ratio: float = OUTLIER_MIN_RATIO,
                       scores: FeatureScores | None = None) -> tuple[torch.Tensor, list[Outlier]]:
    """Units whose joints lie far from the fleet's: a damaged gearbox, a bad measurement.

    For every joint, two features of each unit's fitted model
    (:func:`joint_features`: the transmission error's RMS over the range,
    the backlash); each feature is standardized by the fleet's median and
    MAD (robust to the outliers themselves; the modified z-score
    of Iglewicz and Hoaglin, whose 3.5 flags a healthy fleet's tails here:
    measured, healthy units reach 3.5, damaged ones 7-14). A unit's joint is
    flagged where its z exceeds ``threshold`` (5) and its feature is at least ``min_ratio`` times the fleet
    median: outlying and large enough to matter (a healthy fleet's backlash
    spans 4x from unit to unit; a worn gear adds several times the type's
    clearance). One-sided, since damage and bad measurements add error (a
    unit whose joint is better than the fleet's is not a finding).
    fit: a :class:`~torchcal.identify.fleet.FleetFit` (anything with ``models``); scores: :func:`feature_scores` of
    ``fit.models`` where already computed.
    -> (score (M,): the largest z of each unit, the findings, largest first).
    """
    sc = feature_scores(fit.models) if scores is None else scores
    M = next(iter(sc.value.values())).shape[0]
    score = torch.zeros(M, dtype=torch.float64)
    found: list[Outlier] = []
    for key in sc.value:
        z, ratio = sc.z[key], sc.ratio[key]
        score = torch.maximum(score, z.max(1).values)
        for m, j in sc.flagged(key, threshold, min_ratio).nonzero().tolist():
            found.append(Outlier(m, sc.joints[j], key, float(ratio[m, j]), float(z[m, j])))
    found.sort(key=lambda o: -o.z)
    return score, found


def judge_against(scores: FeatureScores, model, threshold: float = 5.0,
                  min_ratio: float = OUTLIER_MIN_RATIO) -> tuple[float, list[Outlier]]:
    """One more unit's :func:`joint_features` judged against a fleet's ``scores`` (its median and MAD, which the
    unit does not move): -> (its largest robust z, its flagged joints as :class:`Outlier` with unit -1).

    For a unit held out of the fleet's own scoring (its nominal residual says it may be another robot): a damaged
    gearbox also raises the nominal residual, and is then named at its joint rather than called another robot."""
    mine = scores_from_values({k: v[None] for k, v in joint_features(model).items()}, scores.joints, scores)
    score, found = float("-inf"), []
    for key in mine.value:
        z, ratio = mine.z[key][0], mine.ratio[key][0]
        score = max(score, float(z.max()))
        for j in mine.flagged(key, threshold, min_ratio)[0].nonzero()[:, 0].tolist():
            found.append(Outlier(-1, scores.joints[j], key, float(ratio[j]), float(z[j])))
    found.sort(key=lambda o: -o.z)
    return score, found


__all__ = ["FeatureScores", "MAD_FLOOR", "OUTLIER_MIN_RATIO", "Outlier", "axis_errors", "feature_scores", "joint_features",
           "judge_against", "parameter_outliers", "scores_from_values"]
