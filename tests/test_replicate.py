"""torchcal.core.replicate.replicate against copy.deepcopy: the same model, independent tensors and hooks."""

from __future__ import annotations

import copy

import torch

import torchcal
import torchcal.sim
from torchcal.core.replicate import replicate


def _tensors(m):
    return list(m.state_dict(keep_vars=True).items())


def test_a_robot_model_replica_is_its_deepcopy_with_its_own_tensors():
    robot = torchcal.load_robot("fanuc_lrmate200i")
    tools = torch.tensor([[0.033, 0.058, 0.161], [0.057, -0.034, 0.161]], dtype=torch.float64)
    m = torchcal.RobotModel(robot, tools, orders=3, backlash=True)
    with torch.no_grad():
        for p in m.parameters():
            p.normal_(0, 1e-4)
    r, d = replicate(m), copy.deepcopy(m)
    assert [n for n, _ in r.named_parameters()] == [n for n, _ in m.named_parameters()]
    for (n, a), (_, b), (_, c) in zip(_tensors(r), _tensors(d), _tensors(m)):
        assert torch.equal(a, b) and type(a) is type(b), n
        assert a.data_ptr() != c.data_ptr(), n  # its own storage
        assert a.requires_grad == c.requires_grad, n
    q = torchcal.sim.quasi_random_commands(robot.joint_map.limits, 5, 0)
    assert torch.equal(r.flange(q), m.flange(q))
    with torch.no_grad():
        r.joint_errors.coef.add_(1.0)
        r.joint_errors.mask.zero_()
    assert not torch.equal(r.flange(q), m.flange(q))
    assert torch.equal(m.flange(q), d.flange(q))  # the original untouched
    assert bool(m.joint_errors.mask.any())
    r.joint_errors.joint_names.append("extra")
    assert "extra" not in m.joint_errors.joint_names
    r.register_forward_hook(lambda *a: None)
    assert len(m._forward_hooks) == 0
    assert r.robot is m.robot  # shared, as the factory shares it


def test_any_module_with_buffers():
    torch.manual_seed(0)
    m = torch.nn.Sequential(torch.nn.Linear(3, 4), torch.nn.BatchNorm1d(4), torch.nn.Linear(4, 2)).double()
    m(torch.randn(8, 3, dtype=torch.float64))  # running statistics (buffers) away from their start
    m.eval()
    r = replicate(m)
    x = torch.randn(5, 3, dtype=torch.float64)
    assert torch.equal(r(x), m(x))
    r.train()
    r(torch.randn(8, 3, dtype=torch.float64))  # updates r's running statistics only
    assert not m.training
    assert torch.equal(m(x), copy.deepcopy(m)(x))
    assert not torch.equal(r[1].running_mean, m[1].running_mean)
