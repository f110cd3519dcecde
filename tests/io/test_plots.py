"""Plots: the curves behind Figure 12 are the model's error terms; every figure is written."""

import pytest
import torch

from torchcal.io.plots import (joint_error_curves, plot_compensation, plot_joint_errors, plot_residual_distribution,
                               plot_residuals)
from torchcal.analysis.stats import residual_stats
from torchcal.models.robot import RobotModel

PNG = b"\x89PNG\r\n\x1a\n"


def test_joint_error_curves_follow_the_chebyshev_terms(fanuc, tools_m):
    model = RobotModel(fanuc, tools_m, orders=1, backlash=True)
    je = model.joint_errors
    with torch.no_grad():
        je.coef[1, 0, 0] = 1e-3   # joint 2 eps_x: c0 + c1 * lambda
        je.coef[1, 0, 1] = 2e-3
        je.coef[4, 5, 1] = 1e-4   # joint 5 delta_z: c1 * lambda
        je.backlash[2, 0] = 5e-4  # joint 3 backlash: +/- 5e-4 rad on eps_z
    c = joint_error_curves(model, samples=11)
    theta, fwd, bwd = c["theta"], c["forward"], c["backward"]
    lo, hi = je.ranges[:, 0], je.ranges[:, 1]
    assert torch.allclose(theta[0], lo) and torch.allclose(theta[-1], hi)
    # lambda runs from -1 to 1 over the joint range: T0 = 1, T1 = lambda
    assert fwd[0, 1, 0].item() == pytest.approx(-1e-3, abs=1e-15)
    assert fwd[-1, 1, 0].item() == pytest.approx(3e-3, abs=1e-15)
    assert fwd[5, 1, 0].item() == pytest.approx(1e-3, abs=1e-15)  # the middle sample: lambda = 0
    assert fwd[-1, 4, 5].item() == pytest.approx(1e-4, abs=1e-15)
    assert torch.allclose(fwd[:, 2, 2] - bwd[:, 2, 2], torch.full((11,), 1e-3), atol=1e-15)
    same = torch.ones(6, 6, dtype=torch.bool)
    same[2, 2] = False
    assert torch.equal(fwd[:, same], bwd[:, same])  # only eps_z of joint 3 has backlash


def test_figures_are_written(tmp_path, fanuc, tools_m):
    model = RobotModel(fanuc, tools_m, orders=2, backlash=True)
    with torch.no_grad():
        model.joint_errors.coef.normal_(0.0, 1e-4, generator=torch.Generator().manual_seed(0))
    nominal = torch.linspace(1e-3, 5e-3, 30)
    modeled = torch.linspace(1e-5, 9e-5, 30)
    paths = [
        plot_joint_errors(model, tmp_path / "p" / "je.png", samples=21),
        plot_residuals(nominal, modeled, tmp_path / "res.png"),
        plot_compensation(nominal, modeled * 1.1, tmp_path / "comp.png", flagged=torch.arange(30) % 7 == 0),
        plot_residual_distribution(modeled, tmp_path / "dist.png", residual_stats(modeled).scaled(1e3)),
    ]
    for p in paths:
        assert p.read_bytes()[:8] == PNG and p.stat().st_size > 5000
    with pytest.raises(ValueError, match="differ in length"):
        plot_residuals(nominal, modeled[:3], tmp_path / "bad.png")
    assert not (tmp_path / "bad.png").exists()


def test_plot_worker_draws_the_same_files_in_another_process(tmp_path, fanuc, tools_m):
    """A PlotWorker draws in a second process what the plot_* functions draw here, byte for byte."""
    import subprocess
    import sys

    from torchcal.io import plots

    model = RobotModel(fanuc, tools_m, orders=1, backlash=True)
    with torch.no_grad():
        model.joint_errors.coef.normal_(0.0, 1e-4, generator=torch.Generator().manual_seed(1))
    nominal, modeled = torch.linspace(1e-3, 5e-3, 70), torch.linspace(1e-5, 9e-5, 70)
    stats = residual_stats(modeled).scaled(1e3)
    worker = plots.PlotWorker(processes=2)
    assert worker.concurrent and len({w.proc.pid for w in worker._procs} | {__import__("os").getpid()}) == 3
    worker.submit("je", "joint_errors", tmp_path / "w" / "je.png", plots.joint_errors_figure(model, samples=21))
    worker.submit("res", "pair", tmp_path / "w" / "res.png", plots.residuals_figure(nominal, modeled))
    worker.submit("dist", "distribution", tmp_path / "w" / "dist.png", plots.distribution_figure(modeled, stats))
    done = worker.finish()
    assert list(done) == ["je", "res", "dist"] and not worker._procs
    here = [plot_joint_errors(model, tmp_path / "h" / "je.png", samples=21), plot_residuals(nominal, modeled, tmp_path / "h" / "res.png"),
            plot_residual_distribution(modeled, tmp_path / "h" / "dist.png", stats)]
    for key, path in zip(done, here):
        assert done[key].read_bytes() == path.read_bytes(), key
    # the drawing half needs neither torch nor torchcal: the worker process never loads them
    code = ("import importlib.util, sys\n"
            f"spec = importlib.util.spec_from_file_location('w', {str(plots.__file__)!r})\n"
            "mod = importlib.util.module_from_spec(spec); spec.loader.exec_module(mod)\n"
            "import matplotlib.figure\n"
            "print(sorted(m for m in sys.modules if m.split('.')[0] in ('torch', 'torchcal')))\n")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120, check=True).stdout
    assert out.strip() == "[]"


def test_plot_worker_failures_are_raised_here(tmp_path):
    """A figure the worker cannot draw is drawn again in this process, which raises its error."""
    import numpy as np

    from torchcal.io import plots

    worker = plots.PlotWorker(processes=1)
    ok = plots.pair_figure(np.full(5, 2e-3), np.full(5, 1e-3), "t", "nominal", "modeled", "#1f77b4", "x")
    bad = dict(ok, after=np.ones(3))  # 5 bars above, 3 below: matplotlib refuses
    worker.submit("ok", "pair", tmp_path / "ok.png", ok)
    worker.submit("bad", "pair", tmp_path / "bad.png", bad)
    with pytest.raises(ValueError):
        worker.finish()
    assert (tmp_path / "ok.png").read_bytes()[:8] == PNG
    # a cancelled worker (a failed run) leaves no process behind and draws nothing more
    worker = plots.PlotWorker()
    procs = [w.proc for w in worker._procs]
    worker.cancel()
    assert procs and all(p.poll() is not None for p in procs) and not worker.concurrent


def test_plot_worker_submit_never_waits_for_the_worker(monkeypatch):
    """Figures larger than a pipe's buffer are handed over while the worker is busy (here: asleep)."""
    import time

    import numpy as np

    from torchcal.io import plots

    monkeypatch.setattr(plots, "_BOOT", "import time; time.sleep(30)")
    worker = plots.PlotWorker(processes=1)
    t0 = time.perf_counter()
    worker.submit("big", "distribution", "never.png", {"residuals": np.ones(500_000), "title": "t"})  # 4 MB
    assert time.perf_counter() - t0 < 3.0  # a blocking write would wait the 30 s
    proc = worker._procs[0].proc
    worker.cancel()
    assert proc.poll() is not None
