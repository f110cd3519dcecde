"""torchcal.identify.fleet_change: a unit's change between two calibrations, at the tool and per joint."""

from __future__ import annotations

import copy

import torch
from hypothesis import given, settings, strategies as st

import torchcal
import torchcal.sim
from torchcal.core import units as U
from torchcal.identify.fleet_change import changed_units, joint_changes, tool_change

TOOLS = torch.tensor([[0.033, 0.058, 0.161], [0.057, -0.034, 0.161]], dtype=torch.float64)
ROBOT = torchcal.load_robot("fanuc_lrmate200i")


def _model(seed=0):
    """A model with random errors of industrial size (its coefficients drawn, not fitted)."""
    m = torchcal.RobotModel(ROBOT, TOOLS, orders=4, backlash=2)
    g = torch.Generator().manual_seed(seed)
    with torch.no_grad():
        for p in m.parameters():
            p.copy_(1e-4 * torch.randn(p.shape, generator=g, dtype=p.dtype))
    return m


def _commands(count=60, seed=3):
    q = torchcal.sim.quasi_random_commands(ROBOT.joint_map.limits, count, seed)
    tool = torch.arange(count) % 2
    d = torch.where(torch.rand(q.shape, generator=torch.Generator().manual_seed(seed), dtype=torch.float64) > 0.5,
                    1.0, -1.0)
    return q, tool, d


@settings(max_examples=15, deadline=None)
@given(rot=st.lists(st.floats(-0.02, 0.02), min_size=3, max_size=3),
       trans=st.lists(st.floats(-0.01, 0.01), min_size=3, max_size=3))
def test_tool_change_ignores_where_the_tracker_stood(rot, trans):
    """The same robot seen from another tracker frame (the base twist moved, radians and metres) has not changed."""
    a = _model()
    b = copy.deepcopy(a)
    with torch.no_grad():
        b.base.twist += torch.tensor(rot + trans, dtype=torch.float64)
    q, tool, d = _commands()
    assert float(tool_change(a, b, q, tool, d).max()) < 1e-9


def test_tool_change_is_symmetric_and_sees_a_mastering_change():
    """A mastering change of joint 2 moves the tool (unlike a frame), by the same amount seen either way."""
    a = _model()
    b = copy.deepcopy(a)
    with torch.no_grad():
        b.joint_errors.coef[1, 2, 0] += 0.03 * U.DEG  # joint 2's constant error about its own axis
    q, tool, d = _commands()
    ab, ba = tool_change(a, b, q, tool, d), tool_change(b, a, q, tool, d)
    assert torch.allclose(ab, ba, atol=1e-9)
    # J2 turns the arm ~0.6 m from its axis: 0.03 deg moves the tool ~0.3 mm, of which a rigid motion undoes part
    assert 0.05e-3 < float(ab.pow(2).mean().sqrt()) < 0.5e-3


def test_joint_changes_measure_a_transmission_error_and_a_backlash_change():
    """A linear term added to joint 3's error about its axis is its transmission error change: c T_1 over the
    range, RMS c sqrt(mean(lambda^2)) with the mean left out; a constant (a mastering) is none; a constant backlash
    change is itself."""
    a = _model(1)
    b = copy.deepcopy(a)
    c, k0, bl = 0.02 * U.DEG, 0.05 * U.DEG, 0.004 * U.DEG
    with torch.no_grad():
        b.joint_errors.coef[2, 2, 1] += c
        b.joint_errors.coef[3, 2, 0] += k0  # joint 4: a constant only
        b.joint_errors.backlash[4, 0] += bl  # joint 5
    out = joint_changes([a], [b], samples=101)
    lam = torch.linspace(-1.0, 1.0, 101, dtype=torch.float64)
    expect = c * float((lam - lam.mean()).pow(2).mean().sqrt())
    te, back = out["transmission error change"][0], out["backlash change"][0]
    assert abs(float(te[2]) - expect) < 1e-12
    assert float(te[3]) < 1e-12 and float(te[[0, 1, 4, 5]].max()) < 1e-12
    assert abs(float(back[4]) - bl) < 1e-12 and float(back[[0, 1, 2, 3, 5]].max()) < 1e-12


def test_changed_units_by_the_tool_or_a_transmission_error_seen_there():
    """A unit is changed by its change at the tool (z and 1.5x the median), or by a joint's transmission error
    change where the tool moved beyond the fleet's scatter too (z alone); the joints say where. A joint's change
    with nothing at the tool, and a backlash change alone, change no unit."""
    g = torch.Generator().manual_seed(0)
    M, n = 12, 6
    tool = 1e-4 * (1 + 0.02 * torch.randn(M, generator=g, dtype=torch.float64))
    te = 1e-5 * (1 + 0.1 * torch.rand(M, n, generator=g, dtype=torch.float64))
    back = 1e-6 * (1 + 0.1 * torch.rand(M, n, generator=g, dtype=torch.float64))
    tool[3] *= 5.0
    te[3, 2] *= 40.0  # unit 3: joint 3's transmission error, seen at the tool
    tool[5] *= 1.3  # unit 5: outlying at the tool (z), but only 1.3x the median: not enough to matter
    back[7, 5] *= 40.0  # unit 7: joint 6's backlash alone, nothing at the tool
    te[9, 5] *= 10.0  # unit 9: joint 6's transmission error (a wrist's gearbox), the tool moved 1.2x
    tool[9] *= 1.2
    te[10, 1] *= 10.0  # unit 10: joint 2's transmission error, nothing at the tool: the fits' own scatter
    names = [f"joint{j + 1}" for j in range(n)]
    revolute = torch.zeros(n, dtype=torch.bool)
    _, _, found = changed_units(tool, {"transmission error change": te, "backlash change": back}, names, revolute)
    assert [c.unit for c in found] == [3, 9]  # largest z at the tool first
    assert [(j, f) for j, f, *_ in found[0].joints] == [("joint3", "transmission error change")]
    assert [(j, f) for j, f, *_ in found[1].joints] == [("joint6", "transmission error change")]
    assert found[0].joints[0][2] == float(te[3, 2]) / U.DEG  # stated in degrees
    _, _, none = changed_units(tool[:3].clone().fill_(1e-4), {"transmission error change": te[:3]}, names, revolute)
    assert none == []


def test_a_users_7_axis_robot_is_compared_the_same_way(iiwa):
    """A robot we do not bundle (a 7-axis arm from a datasheet's DH table, conftest.iiwa): another tracker frame
    changes nothing; a transmission error change of joint 7 is measured at joint 7 and moves the tool."""
    tools = torch.tensor([[0.05, 0.0, 0.1], [-0.05, 0.0, 0.1]], dtype=torch.float64)
    a = torchcal.RobotModel(iiwa, tools, orders=3, backlash=True)
    g = torch.Generator().manual_seed(2)
    with torch.no_grad():
        for p in a.parameters():
            p.copy_(1e-4 * torch.randn(p.shape, generator=g, dtype=p.dtype))
    moved, changed = copy.deepcopy(a), copy.deepcopy(a)
    with torch.no_grad():
        moved.base.twist += torch.tensor([0.01, -0.02, 0.005, 0.003, 0.002, -0.004], dtype=torch.float64)
        changed.joint_errors.coef[6, 2, 2] += 0.05 * U.DEG  # joint 7, about its axis, T_2
    q = torchcal.sim.quasi_random_commands(iiwa.joint_map.limits * 0.9, 50, 1)
    tool = torch.arange(50) % 2
    assert float(tool_change(a, moved, q, tool).max()) < 1e-9
    assert float(tool_change(a, changed, q, tool).max()) > 1e-5  # 0.05 deg at 0.05-0.1 m from the axis
    te = joint_changes([a, a], [moved, changed])["transmission error change"]
    assert float(te[0].max()) < 1e-12 and int(te[1].argmax()) == 6 and float(te[1, :6].max()) < 1e-12
