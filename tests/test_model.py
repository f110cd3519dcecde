
import torch

from conftest import assert_point_jacobians_match_autograd, random_commands, randomize
from torchcal.kinematics.transforms import pose_error, twist_to_transform
from torchcal.model import RobotModel


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


def test_point_jacobians_match_autograd(fanuc, tools_m):
    m = randomize(RobotModel(fanuc, tools_m, orders=3, backlash=True), 5, rot=1e-2, trans=1e-3)
    B = 6
    q = random_commands(fanuc, B, 6)
    tool = torch.arange(B) % 3
    s = torch.sign(torch.randn(B, 6, generator=torch.Generator().manual_seed(7)))
    v = 1e-3 * torch.randn(B, 6, generator=torch.Generator().manual_seed(8))
    assert_point_jacobians_match_autograd(m, q, tool, s, v)


def test_flange_jacobian_matches_finite_differences(fanuc, tools_m):
    m = randomize(RobotModel(fanuc, tools_m, orders=4, backlash=True), 9, rot=1e-2, trans=1e-3)
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
    from torchcal.jacobian import so3_right_jacobian
    from torchcal.kinematics.transforms import so3_exp, so3_log

    w = torch.tensor([0.4, -0.3, 0.2])
    dw = torch.tensor([1e-7, -2e-7, 3e-7])
    lhs = so3_log(so3_exp(w).T @ so3_exp(w + dw))
    assert torch.allclose(lhs, so3_right_jacobian(w) @ dw, atol=1e-13)
