"""MachineModel: the XYZCB machine of Paper I (Figure 9, (34)-(38)), its measurement model (8)-(12)."""

import math

import numpy as np
import pytest
import torch

import torchcal
import torchcal.sim
from conftest import XYZCB_TOOLS, assert_point_jacobians_match_autograd
from torchcal.core import units
from torchcal.identify import NoiseModel, fit
from torchcal.io.rundir import load_model, save_model
from torchcal.models.machine import MachineModel
from torchcal.core.measurements import Measurements

TOOLS = XYZCB_TOOLS  # Paper I (32)



@pytest.fixture(autouse=True)
def _single_thread(one_thread):
    """Tiny tensors: torch's intra-op threads only contend on the shared 2-core machine."""


def perturbed(machine, seed, orders=3, scale=3e-5):
    model = MachineModel(machine, TOOLS, orders=orders)
    g = torch.Generator().manual_seed(seed)
    with torch.no_grad():
        K = model.axis_errors.coef.shape[-1]
        c = torch.randn(model.axis_errors.coef.shape, generator=g) / (1.0 + torch.arange(K)) ** 2 * scale
        model.axis_errors.coef.copy_(c * model.axis_errors.mask)
        model.base.twist.copy_(torch.randn(6, generator=g) * 1e-3)
        model.tools.delta[:, 2] = torch.randn(2, generator=g) * 1e-4
    return model


def xyzcb_reference(q, tool_len):
    """Trans(X, Y, Z) Rz(C) Ry(B) [0, 0, l] with plain numpy (independent of torchcal)."""
    X, Y, Z, C, B = q.T
    d = np.stack([np.cos(C) * np.sin(B), np.sin(C) * np.sin(B), np.cos(B)], 1)
    return np.stack([X, Y, Z], 1) + tool_len[:, None] * d


def test_bundled_machine_matches_table3(machine):
    assert machine.n == 5 and machine.joint_map.names == ["X", "Y", "Z", "C", "B"]
    assert machine.chain.prismatic.tolist() == [True, True, True, False, False]
    lim = units.joints_from_si(machine.joint_map.limits.T, machine.chain.prismatic).T
    table3 = torch.tensor([[83.2, 6081.1], [37.2, 2557.1], [7.4, 988.2], [-269.7, 269.9], [-109.5, 109.9]])
    assert torch.allclose(lim, table3, atol=1e-9)
    rep = machine.repeatability
    assert rep is not None and "Paper I" in rep.source
    assert torch.allclose(rep.var_fwd[:3], torch.full((3,), (0.003e-3) ** 2))


def test_nominal_kinematics_is_34_38(machine):
    model = MachineModel(machine, TOOLS)
    q = torchcal.sim.quasi_random_commands(machine.joint_map.limits, 20, 0)
    tool = torch.arange(20) % 2
    ref = xyzcb_reference(q.numpy(), TOOLS[tool, 2].numpy())
    assert np.allclose(model.nominal_points(q, tool).numpy(), ref, atol=1e-12)
    assert torch.allclose(model.points(q, tool), model.nominal_points(q, tool), atol=1e-15)


def test_points_are_nominal_kinematics_at_the_perturbed_command(machine):
    """(2), (12): F_AP(q) = F_nom(q + dq(q)), v added to the perturbed command, T_mf E_mf in front."""
    model = perturbed(machine, 1)
    with torch.no_grad():
        model.base.twist.zero_()
        model.tools.delta.zero_()
    q = torchcal.sim.quasi_random_commands(machine.joint_map.limits, 10, 1)
    v = torch.randn(10, 5, generator=torch.Generator().manual_seed(2)) * 1e-5
    tool = torch.ones(10, dtype=torch.long)
    with torch.no_grad():
        a = (q + model.axis_errors.delta(q) + v).numpy()
        got = model.points(q, tool, None, v).numpy()
    assert np.allclose(got, xyzcb_reference(a, np.full(10, 0.5009)), atol=1e-12)


def test_point_jacobians_match_autograd(machine):
    model = perturbed(machine, 3)
    q = torchcal.sim.quasi_random_commands(machine.joint_map.limits, 6, 3)
    tool = torch.tensor([0, 1, 0, 1, 1, 0])
    v = torch.randn(6, 5, generator=torch.Generator().manual_seed(4)) * 1e-5
    assert_point_jacobians_match_autograd(model, q, tool, None, v)


def test_tool_corrections_are_along_the_tool_axis_by_default(machine):
    groups = {g.name: g for g in MachineModel(machine, TOOLS).parameter_groups()}
    assert groups["tools.delta"].mask.tolist() == [[False, False, True]] * 2
    assert groups["axis_errors.coef"].role == "axis" and groups["base.twist"].role == "frame"
    assert bool(MachineModel(machine, TOOLS, tool_terms="xyz").parameter_groups()[-1].mask.all())


def test_save_load_round_trip(machine, tmp_path):
    model = perturbed(machine, 5, orders=[[2] * 5] * 3 + [[-1] * 5] * 2)
    save_model(tmp_path, model)
    back = load_model(tmp_path)
    assert isinstance(back, MachineModel) and back.spec()["kind"] == "machine"
    assert back.axis_errors.pairs == model.axis_errors.pairs
    q = torchcal.sim.quasi_random_commands(machine.joint_map.limits, 8, 5)
    tool = torch.arange(8) % 2
    assert torch.equal(back.points(q, tool), model.points(q, tool))


def test_fit_recovers_a_known_axis_perturbation_truth(machine, one_thread):
    truth = perturbed(machine, 7, orders=3)
    q = torchcal.sim.quasi_random_commands(machine.joint_map.limits, 80, 7)
    qq, tool = q.repeat(2, 1), torch.arange(2).repeat_interleave(80)
    noise = NoiseModel.from_robot(machine)
    g = torch.Generator().manual_seed(8)
    with torch.no_grad():
        p = truth.points(qq, tool) + torch.randn(160, 3, generator=g) * 1e-6
    data = Measurements(qq, tool, p, torch.zeros_like(qq), torch.arange(80).repeat(2), torch.arange(1, 161), False, "sim")
    model = MachineModel(machine, TOOLS, orders=3)
    res = fit(model, data, noise)
    assert res.success
    assert any(n.endswith(".c0") and n.startswith("axis.f_X") for n in res.pinned)  # redundant constants pinned
    qt = torchcal.sim.quasi_random_commands(machine.joint_map.limits, 200, 99)
    tt = torch.arange(200) % 2
    with torch.no_grad():
        err = (model.points(qt, tt) - truth.points(qt, tt)).norm(dim=1)
        nominal = (model.nominal_points(qt, tt) - truth.points(qt, tt)).norm(dim=1)
    assert float(nominal.mean()) > 1e-4
    assert float(err.max()) < 5e-6, float(err.max())
