"""Figures of a calibration run (matplotlib, Agg backend: files only, no display needed).

- :func:`plot_joint_errors`: Paper II Figure 12, the six terms of every E_i over its joint's range;
- :func:`plot_residuals`: Figures 14-15, nominal vs modeled residual per measured row;
- :func:`plot_compensation`: Figure 16, nominal vs compensated residual per command;
- :func:`plot_residual_distribution`: Figure 13, residual histogram with mean, max and Gamma 99 %.

Every function takes plain tensors / arrays in SI (m, rad) and writes a PNG;
units on the axes are mm and degrees.
"""

from __future__ import annotations

from pathlib import Path

import matplotlib

matplotlib.use("Agg")  # headless: runs on servers and in tests; must precede pyplot
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402
from matplotlib.patches import Patch  # noqa: E402
from matplotlib.ticker import MaxNLocator  # noqa: E402
import torch  # noqa: E402

from .. import units  # noqa: E402

ROT_LABELS = (r"$\varepsilon_X$", r"$\varepsilon_Y$", r"$\varepsilon_Z$")
TRANS_LABELS = (r"$\delta_X$", r"$\delta_Y$", r"$\delta_Z$")
NOMINAL_COLOR, MODELED_COLOR, COMPENSATED_COLOR, FLAGGED_COLOR = "#b0b0b0", "#1f77b4", "#2ca02c", "#d62728"


def _np(x) -> np.ndarray:
    if isinstance(x, torch.Tensor):
        return x.detach().to("cpu", torch.float64).numpy()
    return np.asarray(x, dtype=np.float64)


def _save(fig, path) -> Path:
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=120)
    plt.close(fig)
    return path


@torch.no_grad()
def joint_error_curves(model, samples: int = 201) -> dict:
    """The six error terms of every E_i sampled over its error variable's range (the data of Figure 12).

    -> dict with 'theta' (samples, n) error variables (rad / m): the joint
    command q_i or the URDF θ_i, per ``model.error_variable``), 'forward' and
    'backward' (samples, n, 6) error terms (rad, m) for approach direction +1 /
    -1 (identical without backlash), 'prismatic' (n,) bool.
    """
    je = model.joint_errors
    lo, hi = je.ranges[:, 0], je.ranges[:, 1]
    t = torch.linspace(0.0, 1.0, samples, dtype=lo.dtype, device=lo.device)[:, None]
    theta = lo + t * (hi - lo)  # (samples, n): every joint swept at once, one batched call
    ones = torch.ones_like(theta)
    return {
        "theta": theta,
        "forward": je.twists(theta, ones),
        "backward": je.twists(theta, -ones),
        "prismatic": model.prismatic.cpu(),
    }


def plot_joint_errors(model, path, samples: int = 201, title: str | None = None) -> Path:
    """Figure 12: rotational (deg) and translational (mm) error terms of each joint over its range.

    One row per joint, rotations left and translations right; with backlash the
    eps_Z term is drawn for both approach directions (backward dashed).
    """
    c = joint_error_curves(model, samples)
    theta, fwd, bwd = _np(c["theta"]), _np(c["forward"]), _np(c["backward"])
    prismatic = c["prismatic"].numpy()
    names = model.joint_errors.joint_names
    n = theta.shape[1]
    has_backlash = bool(np.abs(fwd - bwd).max() > 0) if fwd.size else False
    fig, axes = plt.subplots(n, 2, figsize=(11, 2.1 * n + 0.8), squeeze=False, sharex="row")
    for i in range(n):
        x = units.m_to_mm(theta[:, i]) if prismatic[i] else units.rad_to_deg(theta[:, i])
        xunit = "mm" if prismatic[i] else "deg"
        ax_r, ax_t = axes[i]
        for k in range(3):
            line, = ax_r.plot(x, units.rad_to_deg(fwd[:, i, k]), label=ROT_LABELS[k])
            if has_backlash and k == 2:
                ax_r.plot(x, units.rad_to_deg(bwd[:, i, k]), ls="--", color=line.get_color(), label=ROT_LABELS[k] + " (backward)")
            ax_t.plot(x, units.m_to_mm(fwd[:, i, 3 + k]), label=TRANS_LABELS[k])
        ax_r.set_ylabel(f"{names[i]}\nrotation (deg)")
        ax_t.set_ylabel("translation (mm)")
        for ax in (ax_r, ax_t):
            ax.grid(alpha=0.3)
            ax.axhline(0.0, color="k", lw=0.5)
        if i == 0:
            ax_r.legend(fontsize=7, ncol=4, loc="upper left")
            ax_t.legend(fontsize=7, ncol=3, loc="upper left")
        var = getattr(model, "error_variable", ["joint"] * n)[i]
        xlabel = f"command {names[i]} ({xunit})" if var == "command" else f"joint variable ({xunit})"
        ax_r.set_xlabel(xlabel, fontsize=8)
        ax_t.set_xlabel(xlabel, fontsize=8)
    fig.suptitle(title or "Joint-dependent error terms of each E_i (Paper II, Fig. 12)")
    fig.tight_layout()
    return _save(fig, path)


def _bar(ax, heights, color, label=None):
    """Bars 1..N; above 60 bars one filled step patch (the same picture, edge to edge) instead of N
    rectangles, which cost matplotlib ~3 ms each: a fit's plots took 7 s."""
    x = np.arange(1, heights.size + 1)
    if heights.size <= 60:
        return ax.bar(x, heights, width=0.8, color=color, label=label)
    return ax.stairs(heights, np.arange(0.5, heights.size + 1), fill=True, color=color, label=label, baseline=0.0)


def _bars(ax, before, after, before_label, after_label, after_color):
    _bar(ax, before, NOMINAL_COLOR, f"{before_label} (mean {before.mean():.3f} mm)")
    _bar(ax, after, after_color, f"{after_label} (mean {after.mean():.3f} mm)")
    ax.set_xlim(0.5, before.size + 0.5)
    ax.xaxis.set_major_locator(MaxNLocator(integer=True))
    ax.set_ylabel("residual (mm)")
    ax.legend(fontsize=8, loc="upper right")
    ax.grid(axis="y", alpha=0.3)


def _pair_plot(before, after, path, title, before_label, after_label, after_color, xlabel, flagged=None) -> Path:
    b, a = units.m_to_mm(_np(before)), units.m_to_mm(_np(after))
    if b.shape != a.shape:
        raise ValueError(f"{before_label} and {after_label} residuals differ in length ({b.size} vs {a.size})")
    fig, (top, bottom) = plt.subplots(2, 1, figsize=(11, 6.5), height_ratios=[3, 2])
    _bars(top, b, a, before_label, after_label, after_color)
    top.set_title(title)
    # the modeled residuals are ~30x smaller than the nominal ones: show them on their own scale too
    flag = np.zeros(a.size, dtype=bool) if flagged is None else _np(flagged).astype(bool).reshape(-1)
    _bar(bottom, np.where(flag, 0.0, a), after_color)
    if flag.any():
        _bar(bottom, np.where(flag, a, 0.0), FLAGGED_COLOR)
    bottom.axhline(a.mean(), color="k", lw=0.8, ls="--", label=f"mean {a.mean():.4f} mm")
    bottom.axhline(a.max(), color="r", lw=0.8, ls=":", label=f"max {a.max():.4f} mm")
    bottom.set_xlim(0.5, a.size + 0.5)
    bottom.xaxis.set_major_locator(MaxNLocator(integer=True))
    bottom.set_ylabel(f"{after_label} (mm)")
    bottom.set_xlabel(xlabel)
    handles, _ = bottom.get_legend_handles_labels()
    if flag.any():
        handles.append(Patch(color=FLAGGED_COLOR, label=f"flagged ({int(flag.sum())}: not converged / outside limits)"))
    bottom.legend(handles=handles, fontsize=8, loc="upper right")
    bottom.grid(axis="y", alpha=0.3)
    fig.tight_layout()
    return _save(fig, path)


def plot_residuals(nominal, modeled, path, title: str = "Nominal and modeled residuals") -> Path:
    """Figures 14-15: nominal vs modeled residual (R,) m for each measured row (pose x tool), as bars in mm."""
    return _pair_plot(nominal, modeled, path, title, "nominal", "modeled", MODELED_COLOR, "measurement (pose x tool, file order)")


def plot_compensation(nominal, compensated, path, title: str = "Nominal and compensated residuals", flagged=None) -> Path:
    """Figure 16: residual (R,) m of each command run uncompensated vs compensated, as bars in mm.

    flagged: optional (R,) bool, commands the compensation flagged (drawn red in the lower panel).
    """
    return _pair_plot(nominal, compensated, path, title, "nominal", "compensated", COMPENSATED_COLOR,
                      "command (file order)", flagged)


def plot_residual_distribution(residuals, path, stats=None, title: str = "Residual distribution") -> Path:
    """Figure 13: histogram of residuals (R,) m with mean, maximum and Gamma 99 % (``stats`` in mm, optional)."""
    r = units.m_to_mm(_np(residuals))
    fig, ax = plt.subplots(figsize=(7, 4))
    ax.hist(r, bins=max(10, min(60, r.size // 5)), density=True, color=MODELED_COLOR, alpha=0.6, label="residuals")
    if stats is not None:
        if np.isfinite(stats.gamma99) and r.size > 1 and (r > 0).all():
            from scipy import stats as sps

            a, _, scale = sps.gamma.fit(r / r.mean(), floc=0)
            xs = np.linspace(0, max(r.max(), stats.gamma99) * 1.1, 300)
            ax.plot(xs, sps.gamma.pdf(xs / r.mean(), a, scale=scale) / r.mean(), "k-", lw=1, label="fitted Gamma")
            ax.axvline(stats.gamma99, color="r", ls="-.", label=f"Gamma 99 % {stats.gamma99:.4f} mm")
        ax.axvline(stats.mean, color="k", ls="--", label=f"mean {stats.mean:.4f} mm")
        ax.axvline(stats.max, color="r", ls=":", label=f"max {stats.max:.4f} mm")
    ax.set_xlabel("residual (mm)")
    ax.set_ylabel("density")
    ax.set_title(title)
    ax.legend(fontsize=8)
    fig.tight_layout()
    return _save(fig, path)


__all__ = [
    "joint_error_curves",
    "plot_compensation",
    "plot_joint_errors",
    "plot_residual_distribution",
    "plot_residuals",
]
