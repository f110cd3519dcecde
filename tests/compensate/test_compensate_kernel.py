"""The compensation kernel reproduces RobotModel's flange, Jacobians and pose error; the damped residual Jacobian is exact."""

import pytest
import torch

from conftest import PRISMATIC_URDF, random_commands, randomize
from torchcal.compensate import fused
from torchcal.compensate.damped import pose_residual, residual_jacobian
from torchcal.compensate.kernel import FlangeKernel, pose_error_soa
from torchcal.kinematics import load_robot
from torchcal.kinematics.transforms import pose_error
from torchcal.models.robot import RobotModel

# both evaluations of the flange: the torch ops (any device) and the numba-compiled CPU kernel
BACKENDS = [False, pytest.param(True, marks=pytest.mark.skipif(not fused.HAVE_NUMBA, reason="numba unavailable (not installed, or TORCHCAL_NO_NUMBA set)"))]


def soa(q):
    return q.T.contiguous()


@pytest.fixture(scope="module", params=["command", "joint", ["command", "joint", "joint", "command", "joint", "command"]],
                ids=["command", "joint", "mixed"])
def model(fanuc, tools_m, request):
    # errors far larger than a real robot's so that every term shows; the FANUC's θ3 = q2 + q3 makes
    # the error variable matter (command: J3's series follows q3; joint: it follows q2 + q3)
    return randomize(RobotModel(fanuc, tools_m, orders=6, backlash=True, error_variable=request.param), 11,
                     rot=2e-2, trans=5e-3)


@pytest.mark.parametrize("use_fused", BACKENDS)
@pytest.mark.parametrize("general_axes", [False, True])
@pytest.mark.parametrize("with_direction", [False, True])
def test_kernel_matches_model(model, fanuc, general_axes, with_direction, use_fused):
    q = random_commands(fanuc, 1200, 3)  # more than one chunk of the fused kernel's threads
    s = torch.sign(torch.randn(1200, 6, generator=torch.Generator().manual_seed(4))) if with_direction else None
    sT = None if s is None else soa(s)
    k = FlangeKernel(model, general_axes=general_axes, fused=use_fused)
    assert (k.fused is not None) == use_fused
    with torch.no_grad():
        F = model.flange(q, s, base=False)
        F0, J0 = model.flange_jacobian(q, s)
        Fn = model.nominal_flange(q)
    R, p = k.flange(soa(q), sT)
    assert torch.allclose(R.permute(2, 0, 1), F[:, :3, :3], atol=2e-15, rtol=0)
    assert torch.allclose(p.T, F[:, :3, 3], atol=2e-15, rtol=0)
    R, p, J = k.flange_jacobian(soa(q), sT)
    assert torch.allclose(R.permute(2, 0, 1), F0[:, :3, :3], atol=2e-15, rtol=0)
    assert torch.allclose(J.permute(2, 0, 1), J0, atol=1e-14, rtol=0)
    Rn, pn = k.nominal_flange(soa(q))
    assert torch.allclose(Rn.permute(2, 0, 1), Fn[:, :3, :3], atol=2e-15, rtol=0)
    assert torch.allclose(pn.T, Fn[:, :3, 3], atol=2e-15, rtol=0)


@pytest.mark.parametrize("use_fused", BACKENDS)
def test_nominal_jacobian_is_the_zero_model_jacobian(fanuc, tools_m, use_fused):
    zero = RobotModel(fanuc, tools_m, orders=6, backlash=True)
    q = random_commands(fanuc, 100, 5)
    with torch.no_grad():
        F0, J0 = zero.flange_jacobian(q)
    R, p, J = FlangeKernel(zero, fused=use_fused).nominal_flange_jacobian(soa(q))
    assert torch.allclose(J.permute(2, 0, 1), J0, atol=1e-15, rtol=0)
    assert torch.allclose(p.T, F0[:, :3, 3], atol=2e-15, rtol=0)


@pytest.mark.parametrize("use_fused", BACKENDS)
def test_kernel_matches_model_with_a_prismatic_joint(tmp_path, use_fused):
    """Travel along a prismatic axis after E_i, non-z revolute axes, backlash about (along) each joint's own axis,
    and the Jacobian's linear columns."""
    path = tmp_path / "rpr.urdf"
    path.write_text(PRISMATIC_URDF)
    robot = load_robot(path)
    model = randomize(RobotModel(robot, torch.tensor([[0.0, 0.0, 0.05]], dtype=torch.float64), orders=4, backlash=True),
                      3, rot=2e-2, trans=5e-3)
    q = random_commands(robot, 300, 9)
    s = torch.sign(torch.randn(300, 3, generator=torch.Generator().manual_seed(1)))
    k = FlangeKernel(model, fused=use_fused)
    with torch.no_grad():
        F0, J0 = model.flange_jacobian(q, s)
        F = model.flange(q, s, base=False)
        Fn = model.nominal_flange(q)
    R, p = k.flange(soa(q), soa(s))
    assert torch.allclose(R.permute(2, 0, 1), F[:, :3, :3], atol=2e-15, rtol=0)
    assert torch.allclose(p.T, F[:, :3, 3], atol=2e-15, rtol=0)
    R, p, J = k.flange_jacobian(soa(q), soa(s))
    assert torch.allclose(J.permute(2, 0, 1), J0, atol=1e-14, rtol=0)
    Rn, pn, _ = k.nominal_flange_jacobian(soa(q))
    assert torch.allclose(pn.T, Fn[:, :3, 3], atol=2e-15, rtol=0)


@pytest.mark.skipif(not fused.HAVE_NUMBA, reason="numba unavailable (not installed, or TORCHCAL_NO_NUMBA set)")
def test_fused_kernel_is_refused_where_it_does_not_apply(fanuc, tools_m):
    model = RobotModel(fanuc, tools_m, orders=2).to(torch.float32)
    assert FlangeKernel(model).fused is None  # automatic choice: torch ops for float32
    with pytest.raises(ValueError, match="float64"):
        FlangeKernel(model, fused=True)


def test_pose_error_soa_matches_pose_error(model, fanuc):
    q = random_commands(fanuc, 100, 6)
    k = FlangeKernel(model)
    Ra, pa = k.flange(soa(q))
    Rn, pn = k.nominal_flange(soa(q + 0.05))
    with torch.no_grad():
        ref = pose_error(model.flange(q, base=False), model.nominal_flange(q + 0.05))
    assert torch.allclose(pose_error_soa(Ra, pa, Rn, pn).T, ref, atol=1e-15, rtol=0)


def test_residual_jacobian_matches_finite_differences(model, fanuc):
    """The damped path's Jacobian of de (47)-(48) away from the solution (Ω far from I)."""
    q = random_commands(fanuc, 8, 7)
    s = torch.sign(torch.randn(8, 6, generator=torch.Generator().manual_seed(8)))
    k = FlangeKernel(model)
    target = model.nominal_flange(q + 0.1).detach()
    Rn, pn = target[:, :3, :3], target[:, :3, 3]

    def de_at(x):
        R, p = k.flange(soa(x), soa(s))
        return pose_residual(R.permute(2, 0, 1), p.T, Rn, pn)

    R, p, J = k.flange_jacobian(soa(q), soa(s))
    de, OR = pose_residual(R.permute(2, 0, 1), p.T, Rn, pn)
    length = 0.7
    Jr = residual_jacobian(de, OR, J.permute(2, 0, 1), length)
    h = 1e-6
    w = torch.tensor([1.0, 1.0, 1.0, length, length, length])
    for j in range(6):
        e = torch.zeros(6)
        e[j] = h
        fd = (de_at(q + e)[0] - de_at(q - e)[0]) / (2 * h) * w
        assert torch.allclose(Jr[:, :, j], fd, atol=1e-8, rtol=0), j


def test_blocked_evaluation_equals_one_pass(fanuc, tools_m):
    """The CPU block loop in flange() is bookkeeping only: every block gives the one-pass numbers."""
    model = randomize(RobotModel(fanuc, tools_m, orders=6, backlash=True), 5)
    q = random_commands(fanuc, 50, 6)
    s = torch.sign(torch.randn(50, 6, generator=torch.Generator().manual_seed(7)))
    R1, p1 = FlangeKernel(model, block=None, fused=False).flange(soa(q), soa(s))
    R2, p2 = FlangeKernel(model, block=7, fused=False).flange(soa(q), soa(s))
    assert torch.allclose(R1, R2, atol=1e-15, rtol=0) and torch.allclose(p1, p2, atol=1e-15, rtol=0)
