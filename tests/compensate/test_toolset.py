"""The tool set's frame (torchcal.compensate.toolset): compensation that two equivalent models agree on."""

import math

import torch
from hypothesis import given, settings
from hypothesis import strategies as st

from tests.conftest import random_commands, randomize
from torchcal.compensate import compensate, row_tool_points
from torchcal.compensate.toolset import inverse, model_tool_set_frame, tool_set_frame
from torchcal.kinematics.transforms import homogeneous, rpy_to_matrix
from torchcal.models.robot import RobotModel


def _rigid(rpy, xyz):
    return homogeneous(rpy_to_matrix(torch.tensor(rpy, dtype=torch.float64)), torch.tensor(xyz, dtype=torch.float64))


@settings(max_examples=40, deadline=None)
@given(rpy=st.lists(st.floats(-0.05, 0.05), min_size=3, max_size=3),
       xyz=st.lists(st.floats(-0.02, 0.02), min_size=3, max_size=3),
       count=st.integers(3, 5), seed=st.integers(0, 10**6))
def test_a_rigid_motion_of_three_or_more_tools_is_recovered(rpy, xyz, count, seed):
    g = torch.Generator().manual_seed(seed)
    nominal = torch.rand(count, 3, generator=g, dtype=torch.float64) * 0.2 - 0.1
    G = _rigid(rpy, xyz)
    identified = nominal @ G[:3, :3].T + G[:3, 3]
    if float(torch.linalg.svdvals(nominal - nominal.mean(0))[1]) < 0.01:
        return  # nearly collinear draws: the rotation about their line is not determined well
    assert torch.allclose(tool_set_frame(nominal, identified), G, atol=1e-10)
    assert torch.allclose(inverse(G) @ G, torch.eye(4, dtype=torch.float64), atol=1e-14)


def test_one_tool_or_tools_that_coincide_give_the_mean_translation():
    one = torch.tensor([[0.0, 0.0, 0.1]], dtype=torch.float64)
    G = tool_set_frame(one, one + torch.tensor([1e-3, -2e-3, 0.0], dtype=torch.float64))
    assert torch.equal(G[:3, :3], torch.eye(3, dtype=torch.float64))
    assert torch.allclose(G[:3, 3], torch.tensor([1e-3, -2e-3, 0.0], dtype=torch.float64))
    same = one.expand(2, 3)
    G = tool_set_frame(same, same + torch.tensor([[1e-3, 0.0, 0.0], [3e-3, 0.0, 0.0]], dtype=torch.float64))
    assert torch.equal(G[:3, :3], torch.eye(3, dtype=torch.float64))
    assert torch.allclose(G[:3, 3], torch.tensor([2e-3, 0.0, 0.0], dtype=torch.float64))


@settings(max_examples=40, deadline=None)
@given(rpy=st.lists(st.floats(-0.05, 0.05), min_size=3, max_size=3),
       xyz=st.lists(st.floats(-0.02, 0.02), min_size=3, max_size=3),
       count=st.integers(2, 4), seed=st.integers(0, 10**6))
def test_tools_on_a_line_take_its_tilt_and_no_turn_about_it(rpy, xyz, count, seed):
    """Two reflectors (or any tools on one line) moved rigidly: G carries each nominal tool onto its identified
    one, and its rotation turns nothing about the line (its axis is orthogonal to it), the turn the points do not
    show. A translation-only G (the old reading) misses both tools by the tilt times their lever."""
    g = torch.Generator().manual_seed(seed)
    a = torch.randn(3, generator=g, dtype=torch.float64)
    a = a / a.norm()
    c = torch.rand(3, generator=g, dtype=torch.float64) * 0.2 - 0.1
    s = torch.linspace(-0.05, 0.06, count, dtype=torch.float64)
    nominal = c + s[:, None] * a
    M = _rigid(rpy, xyz)
    identified = nominal @ M[:3, :3].T + M[:3, 3]
    G = tool_set_frame(nominal, identified)
    assert torch.allclose(nominal @ G[:3, :3].T + G[:3, 3], identified, atol=1e-12)
    assert torch.allclose(G[:3, :3].T @ G[:3, :3], torch.eye(3, dtype=torch.float64), atol=1e-13)
    assert abs(float(torch.linalg.det(G[:3, :3])) - 1.0) < 1e-13
    axis = torch.stack([G[2, 1] - G[1, 2], G[0, 2] - G[2, 0], G[1, 0] - G[0, 1]])  # 2 sin(angle) times the axis
    assert abs(float(axis @ a)) < 1e-12


def _gauge_pair(fanuc, tools_m, d):
    """A model and its exact gauge twin: the last joint's error a pure translation, shifted by d (m) along the
    joint's own axis (a shift that commutes with the joint, Paper II (18)), the tool vectors shifted back. Every
    tool point is the same; the flange is d away."""
    model = randomize(RobotModel(fanuc, tools_m, orders=3, backlash=False), 7)
    with torch.no_grad():
        model.joint_errors.coef[5, :3] = 0.0  # E_6: translation only, so a constant shift commutes through it
    twin = randomize(RobotModel(fanuc, tools_m, orders=3, backlash=False), 7)
    twin.load_state_dict(model.state_dict())
    d = d * model.axes[5].to(torch.float64)
    with torch.no_grad():
        twin.joint_errors.coef[5, 3:, 0] += d
        twin.tools.delta -= d @ model.tip[:3, :3]  # the shift seen in the flange frame: R_tip^T d
    return model, twin


def test_two_models_that_predict_the_same_points_give_the_same_commands(fanuc, tools_m):
    """The flange of a point-data fit is fixed only up to the tool set's rigid motion: with tool_set (the default)
    compensation depends on the points alone; the bare flange ((46) as printed) follows the gauge."""
    model, twin = _gauge_pair(fanuc, tools_m, 0.013)  # 13 mm, as on the real IRB 120
    q = random_commands(fanuc, 300, 8)
    tool = torch.arange(300) % 3
    with torch.no_grad():
        assert torch.allclose(model.points(q, tool), twin.points(q, tool), atol=1e-12, rtol=0)
    a, b = compensate(model, q), compensate(twin, q)
    both = a.converged & b.converged
    assert int(both.sum()) > 250
    assert float((a.q[both] - b.q[both]).abs().max()) < 1e-9
    bare_a, bare_b = compensate(model, q, tool_set=False), compensate(twin, q, tool_set=False)
    both = bare_a.converged & bare_b.converged
    assert float((bare_a.q[both] - bare_b.q[both]).abs().max()) > math.radians(0.1)  # the gauge moved them


def test_a_rigidly_moved_tool_set_lands_on_the_nominal_robots_points(fanuc, tools_m):
    """Tools identified a rigid motion away from their nominal vectors (reflectors whose mount differs from the
    drawing): the compensated commands put every modeled tool point on the nominal robot's point for the nominal
    vector, whichever tool is measured (a known truth: the tool set has no non-rigid difference)."""
    model = randomize(RobotModel(fanuc, tools_m, orders=4, backlash=True), 11)
    G = _rigid([0.01, -0.02, 0.015], [0.002, -0.001, 0.004])
    with torch.no_grad():
        model.tools.delta.copy_(model.tools.nominal @ G[:3, :3].T + G[:3, 3] - model.tools.nominal)
    assert torch.allclose(model_tool_set_frame(model), G, atol=1e-12)
    q = random_commands(fanuc, 200, 12)
    s = torch.where(torch.rand(q.shape, generator=torch.Generator().manual_seed(13)) < 0.5, -1.0, 1.0).double()
    res = compensate(model, q, s)
    ok = res.converged
    assert ok.double().mean() > 0.9
    with torch.no_grad():
        for t in range(3):
            tool = torch.full((int(ok.sum()),), t)
            p = model.points(res.q[ok], tool, s[ok])
            nominal = model.base.nominal @ model.nominal_flange(q[ok])
            target = (nominal[:, :3, :3] @ model.tools.nominal[t]) + nominal[:, :3, 3]
            assert float((p - target).norm(dim=-1).max()) < 1e-9


def test_two_rigidly_moved_tools_land_on_the_nominal_robots_points_with_the_turn_free(fanuc, tools_m):
    """Two reflectors identified a rigid motion (tilt included) away from their nominal vectors: 5-DOF
    compensation about their line puts both modeled points on the nominal robot's points for the nominal
    vectors. With G a translation (before) they landed the tilt times the lever off (0.09 mm on a helper's
    2-reflector FANUC, whose 1- and 3-reflector runs landed 0.02 mm)."""
    two = tools_m[:2]
    model = randomize(RobotModel(fanuc, two, orders=4, backlash=True), 11)
    G = _rigid([0.01, -0.02, 0.015], [0.002, -0.001, 0.004])
    with torch.no_grad():
        model.tools.delta.copy_(model.tools.nominal @ G[:3, :3].T + G[:3, 3] - model.tools.nominal)
    axis = model.tools.nominal[1] - model.tools.nominal[0]
    q = random_commands(fanuc, 200, 12)
    s = torch.where(torch.rand(q.shape, generator=torch.Generator().manual_seed(13)) < 0.5, -1.0, 1.0).double()
    tool = torch.arange(200) % 2
    res = compensate(model, q, s, free_tool_axis=axis, tool_point=row_tool_points(model, tool))
    ok = res.converged
    assert ok.double().mean() > 0.9
    nominal = model.base.nominal @ model.nominal_flange(q[ok])
    with torch.no_grad():
        for t in range(2):
            p = model.points(res.q[ok], torch.full((int(ok.sum()),), t), s[ok])
            target = (nominal[:, :3, :3] @ model.tools.nominal[t]) + nominal[:, :3, 3]
            assert float((p - target).norm(dim=-1).max()) < 1e-9


def test_a_tool_the_data_never_measured_does_not_pull_the_frame(fanuc, tools_m):
    """Three tools configured, two measured: the third keeps its nominal vector (no data moved it), so G is judged
    on the two (with it, G would split the difference and miss the measured tools)."""
    model = RobotModel(fanuc, tools_m, orders=2, backlash=False)
    G = _rigid([0.01, -0.02, 0.015], [0.002, -0.001, 0.004])
    with torch.no_grad():
        moved = model.tools.nominal @ G[:3, :3].T + G[:3, 3] - model.tools.nominal
        moved[2] = 0.0
        model.tools.delta.copy_(moved)
    model.measured_tools = [0, 1]
    F = model_tool_set_frame(model)
    t = model.tools.nominal[:2]
    assert torch.allclose(t @ F[:3, :3].T + F[:3, 3], model.tools()[:2].detach(), atol=1e-12)
    model.measured_tools = None
    F = model_tool_set_frame(model)
    assert not torch.allclose(t @ F[:3, :3].T + F[:3, 3], model.tools()[:2].detach(), atol=1e-5)


def test_swapped_tool_labels_or_one_point_under_two_labels_are_refused():
    """The fit absorbs tool labels swapped in the data by swapping the identified vectors: G would then turn the
    flange 180 deg (two tools: NaN before; three: a silent half turn). Refused, naming the labels; as is a pair of
    identified tools that coincide (one point measured under two labels)."""
    import pytest

    from torchcal.core.exceptions import InputError

    two = torch.tensor([[0.0, 0.0, 0.1], [0.05, 0.0, 0.1]], dtype=torch.float64)
    with pytest.raises(InputError, match="turned by 180 deg"):
        tool_set_frame(two, two.flip(0))
    with pytest.raises(InputError, match="turned by 180 deg"):
        tool_set_frame(two, two.flip(0) + torch.tensor([1e-9, 0.0, 0.0], dtype=torch.float64))
    three = torch.tensor([[0.033, 0.058, 0.161], [0.057, -0.034, 0.161], [-0.034, -0.057, 0.161]],
                         dtype=torch.float64)
    with pytest.raises(InputError, match="labels are swapped"):
        tool_set_frame(three, three[[1, 0, 2]])
    with pytest.raises(InputError, match="coincide"):
        tool_set_frame(two, two[:1].expand(2, 3))
    G = _rigid([0.0, 0.0, 0.3], [0.0, 0.0, 0.0])  # 17 deg: a mount that differs from its drawing, accepted
    assert torch.allclose(tool_set_frame(three, three @ G[:3, :3].T), G, atol=1e-12)
