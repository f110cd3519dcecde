"""Plots: the curves behind Figure 12 are the model's error terms; every figure is written."""

import pytest
import torch

from torchcal.io.plots import (joint_error_curves, plot_compensation, plot_joint_errors, plot_residual_distribution,
                               plot_residuals)
from torchcal.analysis.stats import residual_stats
from torchcal.model import RobotModel

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
