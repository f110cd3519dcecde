"""A fit must not depend on torch's default dtype (a Ray worker, a notebook and the test suite differ there)."""

from __future__ import annotations

import torch

import torchcal
import torchcal.sim
from torchcal.identify import fit


def test_fit_is_the_same_under_either_default_dtype():
    robot = torchcal.load_robot("fanuc_lrmate200i")
    tools = torch.tensor([[0.033, 0.058, 0.161], [0.057, -0.034, 0.161]], dtype=torch.float64)
    noise = torchcal.NoiseModel.from_robot(robot)
    q = torchcal.sim.quasi_random_commands(robot.joint_map.limits, 40, 0)
    data = torchcal.simulate(torchcal.TruthRobot.fanuc_paper2(robot, tools, 0), q, [0, 1], noise, 0)
    old = torch.get_default_dtype()
    out = []
    try:
        for dt in (torch.float32, torch.float64):
            torch.set_default_dtype(dt)
            m = torchcal.RobotModel(robot, tools, orders=2, backlash=True)
            r = fit(m, data, noise)
            out.append((r.fun, {k: v.clone() for k, v in m.state_dict().items()}))
    finally:
        torch.set_default_dtype(old)
    assert out[0][0] == out[1][0]
    for k in out[0][1]:
        assert torch.equal(out[0][1][k], out[1][1][k]), k


def test_a_float32_model_is_refused_naming_the_model():
    """fit on a float32 model: said of the model (the commands' dtype message named a q the user never passed)."""
    import pytest

    from torchcal.core.exceptions import InputError

    robot = torchcal.load_robot("fanuc_lrmate200i")
    tools = torch.tensor([[0.033, 0.058, 0.161]], dtype=torch.float64)
    noise = torchcal.NoiseModel.from_robot(robot)
    q = torchcal.sim.quasi_random_commands(robot.joint_map.limits, 20, 0)
    data = torchcal.simulate(torchcal.TruthRobot.fanuc_paper2(robot, tools, 0), q, [0], noise, 0)
    m = torchcal.RobotModel(robot, tools, orders=1).to(torch.float32)
    with pytest.raises(InputError, match=r"fit: the model is torch.float32; identification runs in float64"):
        fit(m, data, noise)
    assert fit(m.to(torch.float64), data, noise).success
