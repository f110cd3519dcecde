
import pytest
import torch

from conftest import assert_point_jacobians_match_autograd, random_commands, randomize
from torchcal.kinematics.transforms import pose_error, twist_to_transform
from torchcal.models.robot import RobotModel


def test_zero_model_is_nominal(fanuc, tools_m):
    m = RobotModel(fanuc, tools_m, orders=6, backlash=True)
    q = random_commands(fanuc, 50, 0)
    tool = torch.arange(50) % 3
    s = torch.sign(torch.randn(50, 6, generator=torch.Generator().manual_seed(0)))
    assert torch.allclose(m.points(q, tool, s), m.nominal_points(q, tool), atol=1e-16)
    assert torch.allclose(m.flange(q, s, base=False), m.nominal_flange(q), atol=1e-16)


def test_pure_base_error_moves_all_points_rigidly(fanuc, tools_m):
    m = RobotModel(fanuc, tools_m, orders=0)
    e = torch.tensor([1e-3, -2e-3, 3e-3, 1e-4, 2e-4, -3e-4])
    with torch.no_grad():
        m.base.twist.copy_(e)
    q = random_commands(fanuc, 20, 1)
    tool = torch.arange(20) % 3
    p = m.nominal_points(q, tool)
    T = twist_to_transform(e)
    assert torch.allclose(m.points(q, tool), p @ T[:3, :3].T + T[:3, 3], atol=1e-15)


def test_spec_round_trip(fanuc, tools_m):
    m = randomize(RobotModel(fanuc, tools_m, orders=[2, 3, 4, 1, 0, 2], backlash=True), 3)
    m2 = RobotModel.from_spec(m.spec())
    m2.load_state_dict(m.state_dict())
    q = random_commands(fanuc, 10, 4)
    tool = torch.arange(10) % 3
    s = torch.ones(10, 6)
    assert torch.equal(m.points(q, tool, s), m2.points(q, tool, s))


@pytest.mark.parametrize("error_variable", ["command", "joint"])
def test_point_jacobians_match_autograd(fanuc, tools_m, error_variable):
    m = randomize(RobotModel(fanuc, tools_m, orders=3, backlash=True, error_variable=error_variable), 5, rot=1e-2, trans=1e-3)
    B = 6
    q = random_commands(fanuc, B, 6)
    tool = torch.arange(B) % 3
    s = torch.sign(torch.randn(B, 6, generator=torch.Generator().manual_seed(7)))
    v = 1e-3 * torch.randn(B, 6, generator=torch.Generator().manual_seed(8))
    assert_point_jacobians_match_autograd(m, q, tool, s, v)


@pytest.mark.parametrize("error_variable", ["command", "joint"])
def test_flange_jacobian_matches_finite_differences(fanuc, tools_m, error_variable):
    m = randomize(RobotModel(fanuc, tools_m, orders=4, backlash=True, error_variable=error_variable), 9, rot=1e-2, trans=1e-3)
    q = random_commands(fanuc, 8, 10)
    s = torch.ones(8, 6)
    F, J = m.flange_jacobian(q, s)
    h = 1e-6
    for j in range(6):
        dq = torch.zeros_like(q)
        dq[:, j] = h
        num = (pose_error(F, m.flange(q + dq, s, base=False)) - pose_error(F, m.flange(q - dq, s, base=False))) / (2 * h)
        assert torch.allclose(num, J[:, :, j], atol=1e-8), j


def test_so3_right_jacobian_definition():
    from torchcal.models.jacobian import so3_right_jacobian
    from torchcal.kinematics.transforms import so3_exp, so3_log

    w = torch.tensor([0.4, -0.3, 0.2])
    dw = torch.tensor([1e-7, -2e-7, 3e-7])
    lhs = so3_log(so3_exp(w).T @ so3_exp(w + dw))
    assert torch.allclose(lhs, so3_right_jacobian(w) @ dw, atol=1e-13)


def test_command_errors_of_j3_follow_q3_not_theta3(fanuc, tools_m):
    """Paper II (23)-(24): E_3 is a series of the command q3; on the FANUC θ3 = q2 + q3 (Table 2)."""
    cmd = randomize(RobotModel(fanuc, tools_m, orders=4, error_variable="command"), 21, rot=1e-2, trans=1e-3)
    jnt = RobotModel(fanuc, tools_m, orders=4, error_variable="joint")
    with torch.no_grad():  # same coefficients; the ranges (a buffer) stay each model's own
        for (_, a), (_, b) in zip(jnt.named_parameters(), cmd.named_parameters()):
            a.copy_(b)
    q = random_commands(fanuc, 30, 22)
    q2 = q.clone()
    q2[:, 1] += 0.3  # move J2 only: θ3 moves with it, q3 does not
    u, u2 = cmd.error_variables(q), cmd.error_variables(q2)
    assert torch.equal(u[:, 2], u2[:, 2])  # the command series of J3 does not see J2
    e, e2 = cmd.joint_errors.twists(u), cmd.joint_errors.twists(u2)
    assert torch.equal(e[:, 2], e2[:, 2])
    ej, ej2 = jnt.joint_errors.twists(jnt.error_variables(q)), jnt.joint_errors.twists(jnt.error_variables(q2))
    assert (ej[:, 2] - ej2[:, 2]).abs().max() > 1e-5  # on θ3 it does
    # identity-coupled joints are the same either way: command range and θ range map to the same λ
    for i in (0, 3, 4, 5):
        assert torch.allclose(e[:, i], ej[:, i], atol=1e-15)
    assert (cmd.points(q, torch.zeros(30, dtype=torch.long)) - jnt.points(q, torch.zeros(30, dtype=torch.long))).abs().max() > 1e-5


def test_spec_without_error_variable_loads_as_joint(fanuc, tools_m):
    """Run directories written before the error variable existed evaluated every series on θ."""
    m = randomize(RobotModel(fanuc, tools_m, orders=2, error_variable="joint"), 3)
    spec = m.spec()
    assert spec["error_variable"] == ["joint"] * 6
    del spec["error_variable"]
    old = RobotModel.from_spec(spec)
    assert old.error_variable == ["joint"] * 6
    old.load_state_dict(m.state_dict())
    q = random_commands(fanuc, 10, 4)
    tool = torch.arange(10) % 3
    assert torch.equal(old.points(q, tool), m.points(q, tool))
    assert RobotModel.from_spec(RobotModel(fanuc, tools_m, orders=1).spec()).error_variable == ["command"] * 6


def test_unknown_error_variable_names_the_joint(fanuc, tools_m):
    with pytest.raises(ValueError, match="J3.*'gear'"):
        RobotModel(fanuc, tools_m, orders=1, error_variable=["command", "command", "gear", "command", "command", "command"])


@pytest.mark.parametrize("error_variable", ["command", "joint"])
def test_point_jacobians_equal_row_vmapped_autograd(fanuc, tools_m, error_variable):
    """point_jacobians against torch.func.jacrev vmapped over rows (the identification core's autograd path)."""
    from torch.func import functional_call

    from torchcal.measure import row_jacobians

    m = randomize(RobotModel(fanuc, tools_m, orders=3, backlash=True, error_variable=error_variable,
                             compliance="functions"), 11)
    with torch.no_grad():
        m.compliance.coef.copy_(1e-3 * torch.randn(m.compliance.coef.shape, generator=torch.Generator().manual_seed(1)))
    B = 9
    q = random_commands(fanuc, B, 12)
    tool = torch.arange(B) % 3
    s = torch.sign(torch.randn(B, 6, generator=torch.Generator().manual_seed(13)))
    v = 1e-4 * torch.randn(B, 6, generator=torch.Generator().manual_seed(14))
    params = {k: t.detach() for k, t in m.named_parameters()}
    p, Jp, Jv = row_jacobians(lambda pr, vr, qr, tr, sr: functional_call(m, pr, (qr, tr, sr, vr)), params, v, q, tool, s)
    p_ref, J = m.point_jacobians(q, tool, s, v)
    assert torch.allclose(p, p_ref, rtol=0, atol=1e-15)
    for name, ref in J.items():
        got = Jv if name == "v" else Jp[name]
        assert (got - ref).abs().max() <= 1e-10 * ref.abs().max().clamp(min=1e-300), name
