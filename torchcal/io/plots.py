"""Figures of a calibration run (matplotlib's Agg renderer: files only, no display needed).

Why one module: every figure of a run directory and the worker process that draws them; the worker boots once and imports matplotlib once, and the figure functions (data in, figure out) are what it runs.

- :func:`plot_joint_errors`: Paper II Figure 12, the six terms of every E_i over its joint's range;
- :func:`plot_residuals`: Figures 14-15, nominal vs modeled residual per measured row;
- :func:`plot_compensation`: Figure 16, nominal vs compensated residual per command;
- :func:`plot_residual_distribution`: Figure 13, residual histogram with mean, max and Gamma 99 %.

Every function takes plain tensors / arrays in SI (m, rad) and writes a PNG;
units on the axes are mm and degrees.

Each figure is made in two halves: ``*_figure`` turns the inputs into the
numbers drawn (mm, degrees; torch, :mod:`torchcal.core.units` and scipy live here)
and ``draw_*`` draws them with numpy and matplotlib alone. So a
:class:`PlotWorker` (a second Python process that never imports torch) can draw
while the caller goes on: the pipeline starts one with the run, hands it each
figure as soon as its data exist, and collects the files at the end. Figures
use matplotlib's object API (no pyplot state) and fixed margins (a
``tight_layout`` pass cost as much as drawing the figure once more).
"""

from __future__ import annotations

import os
import pickle
import queue
import subprocess
import sys
import threading
from pathlib import Path

import numpy as np

ROT_LABELS = (r"$\varepsilon_X$", r"$\varepsilon_Y$", r"$\varepsilon_Z$")
TRANS_LABELS = (r"$\delta_X$", r"$\delta_Y$", r"$\delta_Z$")
NOMINAL_COLOR, MODELED_COLOR, COMPENSATED_COLOR, FLAGGED_COLOR = "#b0b0b0", "#1f77b4", "#2ca02c", "#d62728"
DPI = 120


def _np(x) -> np.ndarray:
    if hasattr(x, "detach"):  # a torch tensor (torch is not imported in a PlotWorker)
        import torch

        return x.detach().to("cpu", torch.float64).numpy()
    return np.asarray(x, dtype=np.float64)


def _figure(figsize):
    """A matplotlib Figure that is not registered with pyplot (nothing to close, safe outside the main thread)."""
    from matplotlib.figure import Figure

    return Figure(figsize=figsize)


def _margins(fig, left: float, right: float, bottom: float, top: float, wspace: float = 0.0, hspace: float = 0.0,
             ncols: int = 1, nrows: int = 1) -> None:
    """subplots_adjust from margins and gaps in inches (what tight_layout would find, without drawing twice)."""
    w, h = fig.get_size_inches()
    aw = (w - left - right - wspace * (ncols - 1)) / ncols  # one axes' width, inches
    ah = (h - top - bottom - hspace * (nrows - 1)) / nrows
    fig.subplots_adjust(left=left / w, right=1 - right / w, bottom=bottom / h, top=1 - top / h,
                        wspace=wspace / aw if ncols > 1 else 0.2, hspace=hspace / ah if nrows > 1 else 0.2)


def _save(fig, path) -> Path:
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    # atomic like torchcal.io.atomic.atomic_path, written out here: a PlotWorker loads this file without the package
    tmp = path.with_name(f".{path.stem}.{os.getpid()}.tmp{path.suffix}")
    try:
        fig.savefig(tmp, dpi=DPI)
        os.replace(tmp, path)
    except BaseException:
        try:
            tmp.unlink(missing_ok=True)
        except OSError:
            pass
        raise
    return path


# ------------------------------------------------------------------ Figure 12
def joint_error_curves(model, samples: int = 201) -> dict:
    """The six error terms of every E_i sampled over its error variable's range (the data of Figure 12).

    -> dict with 'theta' (samples, n) error variables (rad / m): the joint
    command q_i or the URDF θ_i, per ``model.error_variable``), 'forward' and
    'backward' (samples, n, 6) error terms (rad, m) for approach direction +1 /
    -1 (identical without backlash), 'prismatic' (n,) bool.
    """
    import torch

    with torch.no_grad():
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


def joint_errors_figure(model, samples: int = 201, title: str | None = None) -> dict:
    """What :func:`draw_joint_errors` draws (mm, degrees): keyword arguments, numpy and str only."""
    from ..core import units

    c = joint_error_curves(model, samples)
    theta, fwd, bwd = _np(c["theta"]), _np(c["forward"]), _np(c["backward"])
    prismatic = c["prismatic"].numpy()
    n = theta.shape[1]
    names = list(model.joint_errors.joint_names)
    has_backlash = bool(np.abs(fwd - bwd).max() > 0) if fwd.size else False
    x = np.stack([units.m_to_mm(theta[:, i]) if prismatic[i] else units.rad_to_deg(theta[:, i]) for i in range(n)], 1) \
        if n else theta
    variables = getattr(model, "error_variable", ["joint"] * n)
    xlabels = []
    for i in range(n):
        xunit = "mm" if prismatic[i] else "deg"
        xlabels.append(f"command {names[i]} ({xunit})" if variables[i] == "command" else f"joint variable ({xunit})")
    return {
        "x": x,
        "rotation": units.rad_to_deg(fwd[:, :, :3]),
        "rotation_backward": units.rad_to_deg(bwd[:, :, 2]) if has_backlash else None,
        "translation": units.m_to_mm(fwd[:, :, 3:]),
        "names": names,
        "xlabels": xlabels,
        "title": title or "Joint-dependent error terms of each E_i (Paper II, Fig. 12)",
    }


def draw_joint_errors(path, x, rotation, rotation_backward, translation, names, xlabels, title) -> Path:
    """Figure 12 from :func:`joint_errors_figure`'s numbers: x (S, n) deg / mm; rotation (S, n, 3) deg,
    rotation_backward (S, n) deg of eps_Z for approach direction -1 or None; translation (S, n, 3) mm."""
    n = x.shape[1]
    fig = _figure((11, 2.1 * n + 0.8))
    # both panels of a row plot over the same x, so their x limits agree without sharex (whose linked axes
    # cost a quarter of the drawing time; the picture is byte for byte the same)
    axes = fig.subplots(n, 2, squeeze=False)
    for i in range(n):
        ax_r, ax_t = axes[i]
        for k in range(3):
            line, = ax_r.plot(x[:, i], rotation[:, i, k], label=ROT_LABELS[k])
            if rotation_backward is not None and k == 2:
                ax_r.plot(x[:, i], rotation_backward[:, i], ls="--", color=line.get_color(),
                          label=ROT_LABELS[k] + " (backward)")
            ax_t.plot(x[:, i], translation[:, i, k], label=TRANS_LABELS[k])
        ax_r.set_ylabel(f"{names[i]}\nrotation (deg)")
        ax_t.set_ylabel("translation (mm)")
        for ax in (ax_r, ax_t):
            ax.grid(alpha=0.3)
            ax.axhline(0.0, color="k", lw=0.5)
            ax.set_xlabel(xlabels[i], fontsize=8)
        if i == 0:
            ax_r.legend(fontsize=7, ncol=4, loc="upper left")
            ax_t.legend(fontsize=7, ncol=3, loc="upper left")
    fig.suptitle(title)
    _margins(fig, left=1.05, right=0.15, bottom=0.45, top=0.55, wspace=1.0, hspace=0.6, ncols=2, nrows=n)
    return _save(fig, path)


def plot_joint_errors(model, path, samples: int = 201, title: str | None = None) -> Path:
    """Figure 12: rotational (deg) and translational (mm) error terms of each joint over its range.

    One row per joint, rotations left and translations right; with backlash the
    eps_Z term is drawn for both approach directions (backward dashed).
    """
    return draw_joint_errors(path, **joint_errors_figure(model, samples, title))


# --------------------------------------------------------------- Figures 14-16
def _bar(ax, heights, color, label=None):
    """Bars 1..N; above 60 bars one filled step patch (the same picture, edge to edge) instead of N
    rectangles, which cost matplotlib ~3 ms each: a fit's plots took 7 s."""
    x = np.arange(1, heights.size + 1)
    if heights.size <= 60:
        return ax.bar(x, heights, width=0.8, color=color, label=label)
    from matplotlib.patches import StepPatch

    # what ax.stairs(fill=True, baseline=0) adds, without add_patch's data-limit walk over the patch's N
    # Bezier segments in Python (0.2 s a figure): the limits are the edges and the heights' range
    edges = np.arange(0.5, heights.size + 1)
    patch = StepPatch(heights, edges, baseline=0.0, fill=True, linewidth=0, facecolor=color, label=label)
    ax.add_artist(patch)
    patch.sticky_edges.y.append(0.0)
    ax.update_datalim([(edges[0], min(0.0, float(heights.min()))), (edges[-1], max(0.0, float(heights.max())))])
    ax.autoscale_view()
    return patch


def _bars(ax, before, after, before_label, after_label, after_color):
    from matplotlib.ticker import MaxNLocator

    _bar(ax, before, NOMINAL_COLOR, f"{before_label} (mean {before.mean():.3f} mm)")
    _bar(ax, after, after_color, f"{after_label} (mean {after.mean():.3f} mm)")
    ax.set_xlim(0.5, before.size + 0.5)
    ax.xaxis.set_major_locator(MaxNLocator(integer=True))
    ax.set_ylabel("residual (mm)")
    ax.legend(fontsize=8, loc="upper right")
    ax.grid(axis="y", alpha=0.3)


def pair_figure(before, after, title, before_label, after_label, after_color, xlabel, flagged=None) -> dict:
    """What :func:`draw_pair` draws: residuals (R,) m -> mm, flags (R,) bool."""
    from ..core import units

    b, a = units.m_to_mm(_np(before)), units.m_to_mm(_np(after))
    if b.shape != a.shape:
        raise ValueError(f"{before_label} and {after_label} residuals differ in length ({b.size} vs {a.size})")
    flag = np.zeros(a.size, dtype=bool) if flagged is None else _np(flagged).astype(bool).reshape(-1)
    return {"before": b, "after": a, "title": title, "before_label": before_label, "after_label": after_label,
            "after_color": after_color, "xlabel": xlabel, "flag": flag}


def draw_pair(path, before, after, title, before_label, after_label, after_color, xlabel, flag) -> Path:
    """Figures 14-16 from :func:`pair_figure`'s numbers (mm): both residuals above, the second alone below."""
    from matplotlib.patches import Patch
    from matplotlib.ticker import MaxNLocator

    b, a = before, after
    fig = _figure((11, 6.5))
    top, bottom = fig.subplots(2, 1, height_ratios=[3, 2])
    _bars(top, b, a, before_label, after_label, after_color)
    top.set_title(title)
    # the modeled residuals are ~30x smaller than the nominal ones: show them on their own scale too
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
    _margins(fig, left=0.85, right=0.2, bottom=0.55, top=0.4, hspace=0.45, nrows=2)
    return _save(fig, path)


def residuals_figure(nominal, modeled, title: str = "Nominal and modeled residuals") -> dict:
    return pair_figure(nominal, modeled, title, "nominal", "modeled", MODELED_COLOR, "measurement (pose x tool, file order)")


def compensation_figure(nominal, compensated, title: str = "Nominal and compensated residuals", flagged=None) -> dict:
    return pair_figure(nominal, compensated, title, "nominal", "compensated", COMPENSATED_COLOR, "command (file order)",
                       flagged)


def plot_residuals(nominal, modeled, path, title: str = "Nominal and modeled residuals") -> Path:
    """Figures 14-15: nominal vs modeled residual (R,) m for each measured row (pose x tool), as bars in mm."""
    return draw_pair(path, **residuals_figure(nominal, modeled, title))


def plot_compensation(nominal, compensated, path, title: str = "Nominal and compensated residuals", flagged=None) -> Path:
    """Figure 16: residual (R,) m of each command run uncompensated vs compensated, as bars in mm.

    flagged: optional (R,) bool, commands the compensation flagged (drawn red in the lower panel).
    """
    return draw_pair(path, **compensation_figure(nominal, compensated, title, flagged))


# ------------------------------------------------------------------ Figure 13
def distribution_figure(residuals, stats=None, title: str = "Residual distribution") -> dict:
    """What :func:`draw_distribution` draws: residuals in mm, the statistics and the fitted Gamma density."""
    from ..core import units

    r = units.m_to_mm(_np(residuals))
    out = {"residuals": r, "title": title, "mean": None, "max": None, "gamma99": None, "gamma_curve": None}
    if stats is not None:
        out.update(mean=float(stats.mean), max=float(stats.max))
        if np.isfinite(stats.gamma99) and r.size > 1 and (r > 0).all():
            from ..core.gamma_fit import gamma_mle, gamma_pdf

            fitted = gamma_mle(r)
            xs = np.linspace(0, max(r.max(), stats.gamma99) * 1.1, 300)
            curve = None if fitted is None else (xs, gamma_pdf(xs, *fitted))
            out.update(gamma99=float(stats.gamma99), gamma_curve=curve)
    return out


def draw_distribution(path, residuals, title, mean=None, max=None, gamma99=None, gamma_curve=None) -> Path:
    """Figure 13 from :func:`distribution_figure`'s numbers (mm)."""
    r = residuals
    fig = _figure((7, 4))
    ax = fig.subplots()
    ax.hist(r, bins=int(np.clip(r.size // 5, 10, 60)), density=True, color=MODELED_COLOR, alpha=0.6, label="residuals")
    if gamma_curve is not None:
        ax.plot(gamma_curve[0], gamma_curve[1], "k-", lw=1, label="fitted Gamma")
        ax.axvline(gamma99, color="r", ls="-.", label=f"Gamma 99 % {gamma99:.4f} mm")
    if mean is not None:
        ax.axvline(mean, color="k", ls="--", label=f"mean {mean:.4f} mm")
        ax.axvline(max, color="r", ls=":", label=f"max {max:.4f} mm")
    ax.set_xlabel("residual (mm)")
    ax.set_ylabel("density")
    ax.set_title(title)
    ax.legend(fontsize=8)
    _margins(fig, left=0.75, right=0.2, bottom=0.55, top=0.4)
    return _save(fig, path)


def plot_residual_distribution(residuals, path, stats=None, title: str = "Residual distribution") -> Path:
    """Figure 13: histogram of residuals (R,) m with mean, maximum and Gamma 99 % (``stats`` in mm, optional)."""
    return draw_distribution(path, **distribution_figure(residuals, stats, title))


# --------------------------------------------------------------- the worker
DRAW = {"joint_errors": "draw_joint_errors", "pair": "draw_pair", "distribution": "draw_distribution"}
"""Figure kind -> drawing function (numpy and matplotlib only) a :class:`PlotWorker` runs."""

_BOOT = (
    "import gc, importlib.util, sys\n"
    "gc.disable()\n"  # until the imports are in (_serve)
    "spec = importlib.util.spec_from_file_location('_torchcal_plot_worker', sys.argv[1])\n"
    "mod = importlib.util.module_from_spec(spec)\n"
    "spec.loader.exec_module(mod)\n"
    "mod._serve()\n"
)


COST = {"joint_errors": 3.0, "pair": 1.0, "distribution": 0.6}
"""Rough drawing time of each figure kind (a pair of residual panels = 1): how a PlotWorker spreads them."""


class _Process:
    """One drawing process of a :class:`PlotWorker`, fed by a thread (a figure's data can exceed the pipe's
    buffer while the process still imports or draws: submit() must not wait for it)."""

    def __init__(self):
        env = {**os.environ, "MPLBACKEND": "Agg", "OMP_NUM_THREADS": "1", "OPENBLAS_NUM_THREADS": "1",
               "MKL_NUM_THREADS": "1"}
        self.proc = subprocess.Popen([sys.executable, "-c", _BOOT, str(Path(__file__).resolve())],
                                     stdin=subprocess.PIPE, stdout=subprocess.PIPE, stderr=subprocess.DEVNULL, env=env)
        self.feed: queue.SimpleQueue = queue.SimpleQueue()
        self.load = 0.0  # the COST of the figures handed to it
        self.feeder = threading.Thread(target=_feed, args=(self.proc.stdin, self.feed), name="torchcal-plot-feeder",
                                       daemon=True)
        self.feeder.start()

    def results(self):
        """(status, key, path or message) per figure, until the process has drawn everything and ended."""
        while True:
            try:
                yield pickle.load(self.proc.stdout)
            except EOFError:
                return

    def kill(self) -> None:
        proc = self.proc
        if proc.poll() is None:
            proc.kill()
        self.feed.put(None)
        self.feeder.join(timeout=10)  # its write fails at once on the dead pipe
        for stream in (proc.stdin, proc.stdout):
            try:
                stream.close()
            except (OSError, ValueError):
                pass
        try:
            proc.wait(timeout=10)
        except subprocess.TimeoutExpired:
            pass


class PlotWorker:
    """Draws figures in other Python processes (numpy and matplotlib only, never torch) while the caller goes on.

    ``submit(key, kind, path, data)`` hands over a figure (``data``: what
    ``*_figure`` returned) and returns at once; :meth:`finish` waits and returns
    key -> path. processes: how many drawing processes (default one: measured on
    2 CPUs, a second one's imports slowed the caller more than its drawing saved);
    each figure goes to the one with the least drawing handed to it so far
    (:data:`COST`). A figure the workers
    could not draw (one failed to start, died, or the drawing raised) is drawn in
    this process by :meth:`finish`, so that its error, if any, is raised here as it
    would be without a worker. :meth:`cancel` ends the processes (a failed or
    interrupted run). Without a usable interpreter everything is drawn at
    :meth:`finish`.
    """

    def __init__(self, start: bool = True, processes: int = 1):
        self._procs: list[_Process] = []
        self._jobs: list[tuple[str, str, str, dict]] = []
        if start and sys.executable:
            try:
                for _ in range(max(int(processes), 1)):
                    self._procs.append(_Process())
            except OSError:
                pass

    @property
    def concurrent(self) -> bool:
        return bool(self._procs)

    def submit(self, key: str, kind: str, path, data: dict) -> None:
        job = (key, kind, str(path), data)
        self._jobs.append(job)
        if self._procs:
            worker = min(self._procs, key=lambda w: w.load)
            worker.load += COST.get(kind, 1.0)
            worker.feed.put(pickle.dumps(job, protocol=pickle.HIGHEST_PROTOCOL))

    def finish(self, task=None, timeout: float = 300.0) -> dict[str, Path]:
        """Wait for every submitted figure -> key -> path. task: a progress Task advanced once per figure."""
        if task is not None:
            task.set_total(len(self._jobs))
        done: dict[str, Path] = {}
        try:
            for worker in self._procs:
                worker.feed.put(None)  # the feeder closes stdin after the last figure: the process ends when done
            for worker in self._procs:
                for status, key, value in worker.results():
                    if status == "ok":
                        done[key] = Path(value)
                        if task is not None:
                            task.advance(note=key)
                worker.proc.wait(timeout=timeout)
        except (OSError, ValueError, pickle.UnpicklingError, subprocess.TimeoutExpired):
            pass
        finally:
            self.cancel()
        for key, kind, path, data in self._jobs:  # not drawn by a worker: here (raises what drawing raises)
            if key not in done:
                done[key] = globals()[DRAW[kind]](path, **data)
                if task is not None:
                    task.advance(note=key)
        return {key: done[key] for key, _, _, _ in self._jobs}

    def cancel(self) -> None:
        """End the drawing processes now (idempotent)."""
        procs, self._procs = self._procs, []
        for worker in procs:
            worker.kill()


def _feed(stdin, jobs: queue.SimpleQueue) -> None:
    """The feeder thread: write each pickled job to the worker until None, then close its stdin."""
    while True:
        blob = jobs.get()
        if blob is None:
            break
        try:
            stdin.write(blob)
            stdin.flush()
        except (OSError, ValueError):  # the worker is gone: finish() draws the rest here
            break
    try:
        stdin.close()
    except (OSError, ValueError):
        pass


def _serve() -> None:
    """The worker's loop (run by :data:`_BOOT` in the second process): draw every job read from stdin."""
    import signal

    signal.signal(signal.SIGINT, signal.SIG_IGN)  # Ctrl-C is the parent's to handle: it ends this process
    inp, out = sys.stdin.buffer, sys.stdout.buffer
    sys.stdout = sys.stderr  # stdout carries the results: nothing else may write to it
    import gc

    import matplotlib.backends.backend_agg  # noqa: F401  (the imports while the parent still computes)
    import matplotlib.figure  # noqa: F401

    gc.freeze()  # the modules' objects live as long as the process: out of every collection
    gc.enable()
    try:  # the first text, mathtext and PNG of a process load fonts and parsers: now, while the parent computes
        import io

        fig = _figure((1, 1))
        fig.subplots().set_title(ROT_LABELS[0])
        fig.savefig(io.BytesIO(), format="png", dpi=20)
    except Exception:
        pass

    while True:
        try:
            key, kind, path, data = pickle.load(inp)
        except EOFError:
            break
        try:
            result = ("ok", key, str(globals()[DRAW[kind]](path, **data)))
        except Exception as exc:  # drawn again by the parent, which raises it
            result = ("error", key, f"{type(exc).__name__}: {exc}")
        pickle.dump(result, out, protocol=pickle.HIGHEST_PROTOCOL)
        out.flush()


__all__ = [
    "PlotWorker",
    "compensation_figure",
    "distribution_figure",
    "draw_distribution",
    "draw_joint_errors",
    "draw_pair",
    "joint_error_curves",
    "joint_errors_figure",
    "pair_figure",
    "plot_compensation",
    "plot_joint_errors",
    "plot_residual_distribution",
    "plot_residuals",
    "residuals_figure",
]
