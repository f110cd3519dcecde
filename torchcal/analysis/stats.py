"""Residual statistics of a model on measured data: mean, maximum, Gamma 99 % (Paper II, 5.5, Fig. 13).

A model is judged by the distance between what it predicts for a command and
what the tracker measured, *without* the per-row joint positioning errors v
that identification fits: with those free, even a constant model reproduces
every measured point almost exactly. Because the largest residual of a finite
validation set need not be the largest over the workspace, Paper II also
reports the 99th percentile of a Gamma distribution fitted to the residual
norms (Figure 13, Tables 6, 7, 12).
"""

from __future__ import annotations

import math
from dataclasses import asdict, dataclass

import numpy as np
import torch

from ..core import units
from ..core.measurements import Measurements

GAMMA_QUANTILE = 0.99
"""Quantile of the fitted Gamma distribution reported as 'Gamma 99 %'."""


def check_xyz(data: Measurements) -> None:
    bad = ~torch.isfinite(data.xyz).all(-1)
    if bad.any():
        rows = data.rows[bad.nonzero()[:, 0].cpu()][:5].tolist()
        raise ValueError(
            f"{data.source or 'measurements'}: rows {rows} (and {int(bad.sum()) - len(rows)} more) have no measured "
            "xyz (NaN/inf); residuals need measured points"
        )


def point_residuals(model, data: Measurements, nominal: bool = False, compiled: bool = False) -> torch.Tensor:
    """Distance between predicted and measured points, (R,) metres.

    model: anything with ``points(q, tool, direction=None)`` (a
    :class:`torchcal.models.robot.RobotModel`, a :class:`torchcal.analysis.cpa.CPAModel`, ...)
    and, for ``nominal=True``, ``nominal_points(q, tool)``.
    data: measurements with xyz (R, 3) in the measurement frame, metres.
    compiled: a RobotModel's points by compensation's compiled flange kernel where it applies (numba, the CPU,
    float64, no gravity compliance or fine tables; the same points to ~1e-15 m, a 750-row set 3.6x faster); it
    imports numba, which a caller that already uses it (a fleet) pays nothing for.
    -> |p_model(q, tool, s) - xyz| per row, with the joint positioning errors
    v left at zero (the honest judge of a model, see the module docstring).
    Approach directions are passed only when the data records them.
    """
    check_xyz(data)
    with torch.no_grad():
        p = None
        if nominal:
            p = model.nominal_points(data.q, data.tool)
        elif compiled:
            p = _compiled_points(model, data)
        if p is None:
            p = model.points(data.q, data.tool, data.direction if data.has_direction else None)
        return torch.linalg.norm(p - data.xyz.to(p), dim=-1).detach()


def _compiled_points(model, data: Measurements) -> torch.Tensor | None:
    """model.points (R, 3) at zero joint errors by :class:`~torchcal.compensate.kernel.FlangeKernel`'s compiled
    flange (E_base F_a, the robot's nominal base frame) where it applies, else None."""
    from ..compensate.kernel import FlangeKernel
    from ..models.robot import RobotModel

    if not isinstance(model, RobotModel) or data.q.device.type != "cpu" or data.q.dtype != torch.float64:
        return None  # (a GPU fleet's units: no kernel to build)
    k = FlangeKernel(model)
    if k.fused is None:  # no numba, not the CPU or float64, or a flange that depends on the whole configuration
        return None
    R, p = k.flange(data.q.T, data.direction.T if data.has_direction else None)  # (3, 3, R), (3, R)
    t = model.tools()[data.tool]  # (R, 3)
    pf = (R * t.T[None]).sum(1) + p
    N = model.base.nominal
    return (N[:3, :3] @ pf + N[:3, 3:4]).T


@dataclass
class ResidualStats:
    """Summary of residual norms; every value in the unit of the residuals given.

    mean, max: of the residuals; gamma99: 99th percentile of a Gamma
    distribution fitted to them (NaN when it cannot be fitted: fewer than two
    residuals, or a zero residual); count: number of residuals.
    """

    mean: float
    max: float
    gamma99: float
    count: int

    def scaled(self, factor: float) -> "ResidualStats":
        """The same statistics in another unit (e.g. ``units.m_to_mm(1.0)`` for mm)."""
        return ResidualStats(self.mean * factor, self.max * factor, self.gamma99 * factor, self.count)


def gamma99(residuals, quantile: float = GAMMA_QUANTILE) -> float:
    """``quantile`` of a Gamma distribution fitted (MLE, location fixed at 0) to residual norms.

    residuals: (R,) positive values (tensor or array). -> float in their unit;
    NaN for fewer than two residuals or any zero residual (the Gamma
    likelihood is zero there, so no fit exists).
    """
    from ..core.gamma_fit import gamma_mle, gamma_ppf

    x = _as_numpy(residuals)
    if x.size < 2 or (x <= 0).any():
        return float("nan")
    fitted = gamma_mle(x)
    if fitted is None:  # (numerically) identical residuals: a degenerate Gamma, all its quantiles at the value
        return float(np.mean(x))
    return gamma_ppf(quantile, *fitted)


def _as_numpy(residuals) -> np.ndarray:
    if isinstance(residuals, torch.Tensor):
        x = residuals.detach().to("cpu", torch.float64).numpy()
    else:
        x = np.asarray(residuals, dtype=np.float64)
    x = x.reshape(-1)
    if not np.isfinite(x).all():
        i = int(np.flatnonzero(~np.isfinite(x))[0])
        raise ValueError(f"residual {i} is not finite ({x[i]})")
    if (x < 0).any():
        i = int(np.flatnonzero(x < 0)[0])
        raise ValueError(f"residual {i} is negative ({x[i]}); residuals are distances")
    return x


def residual_stats(residuals) -> ResidualStats:
    """Mean, max and Gamma 99 % of residual norms (R,), in their unit (Paper II, Fig. 13)."""
    x = _as_numpy(residuals)
    if x.size == 0:
        raise ValueError("no residuals to summarise")
    return ResidualStats(float(x.mean()), float(x.max()), gamma99(x), int(x.size))


def grouped_stats(residuals, groups) -> dict[int, ResidualStats]:
    """Statistics per group label (e.g. per swept joint, Tables 10-11).

    residuals: (R,); groups: (R,) integer labels. -> {label: ResidualStats}, labels sorted.
    """
    x = _as_numpy(residuals)
    g = groups.detach().cpu().numpy() if isinstance(groups, torch.Tensor) else np.asarray(groups)
    g = g.reshape(-1)
    if g.shape != x.shape:
        raise ValueError(f"groups has {g.size} labels for {x.size} residuals")
    return {int(k): residual_stats(x[g == k]) for k in np.unique(g)}


FAR_ROW_FACTOR = 10.0
"""A row whose residual after the fit is this many times the set's median residual or more lies far beyond the
rest: for Gaussian tracker noise (the residual's norm ~ Maxwell, median 1.54 sigma) that is beyond 15 sigma,
so a gross error (a reflector off its nest, a beam break, a pose number used twice), not noise."""


def far_rows(residuals: torch.Tensor, factor: float = FAR_ROW_FACTOR) -> torch.Tensor:
    """Positions (K,) of the rows whose residual (R,) is ``factor`` x the median residual or more, largest first.

    Example:
        >>> far_rows(torch.tensor([1.0, 1.2, 0.9, 30.0, 1.1])).tolist()
        [3]
    """
    r = residuals.detach().cpu()
    if r.numel() < 5:  # a median of a few rows says nothing
        return torch.zeros(0, dtype=torch.long)
    idx = (r >= factor * r.median()).nonzero()[:, 0]
    return idx[r[idx].argsort(descending=True)]


def far_rows_message(residuals: torch.Tensor, data: Measurements, what: str, fitted: bool = True) -> str | None:
    """One warning naming ``what`` (the set and its file) and its far rows by their file row, or None.
    fitted: the residuals are a fit's (else a finished model's on new rows, ``torchcal verify``)."""
    idx = far_rows(residuals)
    if idx.numel() == 0:
        return None
    mm = units.m_to_mm(residuals.detach().cpu())
    rows = data.rows.cpu()[idx].tolist()
    shown = ", ".join(f"row {r} ({v:.3f} mm)" for r, v in zip(rows[:5], mm[idx][:5].tolist()))
    return (f"{what}: {idx.numel()} row(s) lie far beyond the rest{' after the fit' if fitted else ''} (>= "
            f"{FAR_ROW_FACTOR:g}x the median residual {float(mm.median()):.4f} mm): {shown}"
            f"{', ...' if idx.numel() > 5 else ''}; a gross measurement error (a reflector off its nest, a beam break), "
            "a pose number used twice, or an error the model lacks there"
            + (" (does a higher model.order fit them)? They are fitted as they are" if fitted else
               "? They are counted in the statistics as they are"))


def percent_decrease(before: float, after: float) -> float:
    """100 (before - after) / before: how much of ``before`` a model removed (Tables 6, 7)."""
    before, after = float(before), float(after)
    if before == 0.0 or not math.isfinite(before):
        return float("nan")
    return 100.0 * (before - after) / before


def stats_table(rows: dict[str, ResidualStats], reference: str | None = None) -> list[dict]:
    """Rows of a Table 6/7/12-style summary, ready for rich or pandas.

    rows: label -> ResidualStats (all in one unit); reference: label of the
    row the percent decreases are taken against (e.g. 'Nominal'), or None.
    -> one dict per row: label, mean, max, gamma99, count and, with a
    reference, mean_decrease / max_decrease / gamma99_decrease in percent
    (None on the reference row itself, the paper's 'N/A').
    """
    if reference is not None and reference not in rows:
        raise KeyError(f"reference row '{reference}' not among {list(rows)}")
    ref = rows.get(reference) if reference is not None else None
    out = []
    for label, s in rows.items():
        row = {"label": label, **asdict(s)}
        if ref is not None:
            for key in ("mean", "max", "gamma99"):
                row[f"{key}_decrease"] = None if label == reference else percent_decrease(getattr(ref, key), getattr(s, key))
        out.append(row)
    return out
