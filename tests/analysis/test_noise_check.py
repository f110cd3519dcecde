"""noise_ratio: a fit's residual against what its noise model explains (torchcal.analysis.noise_check)."""

from __future__ import annotations

import math

import torch
from conftest import random_commands, randomize

import torchcal
from torchcal.analysis.noise_check import NOISE_RATIO_WARN, noise_ratio
from torchcal.analysis.stats import point_residuals
from torchcal.models.robot import RobotModel


def _draw(model, q, tool, s, noise, seed):
    """Points of ``model`` with the noise model's own scatter drawn (tracker per axis, joint errors on the
    command by direction): rows for which the ratio must be 1."""
    g = torch.Generator().manual_seed(seed)
    v = torch.randn(q.shape, generator=g, dtype=torch.float64) * noise.joint_variance(s).sqrt()
    with torch.no_grad():
        p = model.points(q, tool, s, v)
    return p + noise.sigma_m * torch.randn(p.shape, generator=g, dtype=torch.float64)


def test_the_ratio_is_one_under_the_noise_model_and_large_with_an_unmodelled_error(fanuc, tools_m):
    """Drawn from the noise model itself (sigma_m and the joints' repeatability, Monte Carlo) the ratio of
    mean squares is 1 within its sampling error; a sag the model lacks (0.3 mm cos q2, against Paper II's joint
    repeatability of up to 0.07 mm at the tools) puts it above the warning threshold."""
    model = randomize(RobotModel(fanuc, tools_m, orders=2, backlash=True), 3)
    noise = torchcal.NoiseModel.from_robot(fanuc, 5e-6)
    R = 6000
    q = random_commands(fanuc, R, 4)
    tool = torch.arange(R) % 3
    s = torch.where(torch.rand(q.shape, generator=torch.Generator().manual_seed(5)) < 0.5, -1.0, 1.0).double()
    data = torchcal.Measurements.from_tensors(q, tool, _draw(model, q, tool, s, noise, 6), direction=s)
    check = noise_ratio(model, data, noise, point_residuals(model, data))
    assert abs(check.ratio - 1.0) < 0.05, check
    assert abs(check.sigma_m / noise.sigma_m - 1.0) < 0.5, check  # the tracker's part: a small share of the rows'
    sag = torch.zeros(R, 3, dtype=torch.float64)
    sag[:, 2] = 3e-4 * torch.cos(q[:, 1])
    bent = torchcal.Measurements.from_tensors(q, tool, data.xyz + sag, direction=s)
    bent_check = noise_ratio(model, bent, noise, point_residuals(model, bent))
    assert bent_check.ratio > NOISE_RATIO_WARN
    # the sigma that would describe it, given as such, brings the ratio to 1
    fitted = torchcal.NoiseModel(bent_check.sigma_m, noise.joint_var_fwd, noise.joint_var_bwd)
    assert abs(noise_ratio(model, bent, fitted, point_residuals(model, bent)).ratio - 1.0) < 1e-9
    # a noise model that admits the scatter: the same rows explained (tracker sigma 0.3 mm per axis)
    wide = torchcal.NoiseModel(3e-4, noise.joint_var_fwd, noise.joint_var_bwd)
    assert noise_ratio(model, bent, wide, point_residuals(model, bent)).ratio < 1.0


def test_no_ratio_where_the_closed_form_declines(fanuc, tools_m):
    from test_model_extension import ShiftedFlange

    model = ShiftedFlange(fanuc, tools_m, orders=1)
    q = random_commands(fanuc, 5, 1)
    tool = torch.zeros(5, dtype=torch.long)
    data = torchcal.Measurements.from_tensors(q, tool, torch.zeros(5, 3, dtype=torch.float64))
    assert noise_ratio(model, data, torchcal.NoiseModel.from_robot(fanuc), torch.ones(5, dtype=torch.float64)) is None
    assert math.isfinite(noise_ratio(RobotModel(fanuc, tools_m, orders=1), data,
                                     torchcal.NoiseModel.from_robot(fanuc), torch.ones(5, dtype=torch.float64)).ratio)
