"""The hot paths on CUDA (runs only where a CUDA device exists): each against the same computation on the CPU.

float64 throughout; compensation also in float32, where the accuracy allows it (stated below).
"""

from __future__ import annotations

import pytest
import torch

from torchcal.compensate.toolset import compensation_goal
import torchcal
import torchcal.sim
from torchcal.compensate import compensate
from torchcal.identify import fit
from torchcal.identify.fleet import fit_fleet

pytestmark = pytest.mark.skipif(not torch.cuda.is_available(), reason="needs CUDA")

TOOLS = torch.tensor([[0.033, 0.058, 0.161], [0.057, -0.034, 0.161], [-0.034, -0.057, 0.161]], dtype=torch.float64)


@pytest.fixture(scope="module")
def setup():
    robot = torchcal.load_robot("fanuc_lrmate200i")
    noise = torchcal.NoiseModel.from_robot(robot)
    q = torchcal.sim.quasi_random_commands(robot.joint_map.limits, 80, 0)
    truths = [torchcal.TruthRobot.fanuc_paper2(robot, TOOLS, s) for s in range(3)]
    units = [torchcal.simulate(t, q, [0, 1, 2], noise, s) for s, t in enumerate(truths)]
    return robot, noise, units


def _model(robot, device="cpu"):
    return torchcal.RobotModel(robot, TOOLS, orders=3, backlash=True).to(device)


def test_fit_on_cuda_matches_cpu(setup):
    robot, noise, units = setup
    cpu, gpu = _model(robot), _model(robot, "cuda")
    rc = fit(cpu, units[0], noise)
    rg = fit(gpu, units[0].to("cuda"), noise)
    assert rg.success and rc.success
    assert rg.fun == pytest.approx(rc.fun, rel=1e-8)
    d = units[0]
    with torch.no_grad():  # prediction on the GPU against the CPU model's
        pg = gpu.points(d.q.cuda(), d.tool.cuda(), d.direction.cuda()).cpu()
        pc = cpu.points(d.q, d.tool, d.direction)
    assert float((pg - pc).norm(dim=1).max()) < 1e-9  # m


def test_fleet_on_cuda_matches_cpu(setup):
    robot, noise, units = setup
    # at the single fit's stopping point: the GPU's exact steps and the CPU's factored ones stop alike
    c = fit_fleet(lambda: _model(robot), units, noise, ftol=1e-8)
    g = fit_fleet(lambda: _model(robot, "cuda"), [u.to("cuda") for u in units], noise, ftol=1e-8)
    for rc, rg in zip(c.results, g.results):
        assert rg.success and rg.fun == pytest.approx(rc.fun, rel=1e-8)


def test_compensation_on_cuda_float64_and_float32(setup):
    """float64 on the GPU equals the CPU to 1e-11 rad; float32 commands reach the target to about a micrometre
    (judged in float64), far below a tracker's 5 µm: float32 is good enough for compensation."""
    robot, noise, units = setup
    m = _model(robot)
    fit(m, units[0], noise)
    q = torchcal.sim.quasi_random_commands(robot.joint_map.limits, 500, 5)
    s = torch.ones_like(q)
    cpu = compensate(m, q, s)
    gm = _model(robot, "cuda")
    gm.load_state_dict(m.state_dict())
    gpu = compensate(gm, q.cuda(), s.cuda())
    ok = cpu.converged & gpu.converged.cpu()
    assert ok.float().mean() > 0.9
    assert torch.allclose(gpu.q.cpu()[ok], cpu.q[ok], atol=1e-11, rtol=0)
    g32 = _model(robot, "cuda")
    g32.load_state_dict(m.state_dict())
    g32 = g32.to(torch.float32)
    r32 = compensate(g32, q.cuda().float(), s.cuda().float())
    ok32 = r32.converged.cpu()
    assert ok32.float().mean() > 0.85
    with torch.no_grad():  # the float32 commands, judged in float64, reach the target to a micrometre
        reach = (m.flange(r32.q.double().cpu(), s, base=False)[:, :3, 3] - compensation_goal(m, q)[:, :3, 3]).norm(dim=1)
    assert float(reach[ok32].max()) < 2e-6


def test_slope_constraint_on_cuda_matches_cpu():
    """Paper I's constrained fit (the slope penalty's QP steps) on CUDA lands where the CPU's lands."""
    from torchcal.identify.constrained import fit_constrained
    from torchcal.models.machine import MachineModel

    robot = torchcal.load_robot("five_axis_xyzcb")
    tools = torch.tensor([[0.0, 0.0, 0.4029], [0.0, 0.0, 0.5009]], dtype=torch.float64)
    truth = MachineModel(robot, tools, orders=2)
    with torch.no_grad():
        truth.axis_errors.coef[2, 4, 2].fill_(2e-4)
    q = torchcal.sim.quasi_random_commands(robot.joint_map.limits, 40, 0).repeat(2, 1)
    tool = torch.arange(2).repeat_interleave(40)
    data = torchcal.Measurements.from_tensors(q, tool, truth.points(q, tool).detach())
    out = []
    for dev in ("cpu", "cuda"):
        m = MachineModel(robot, tools, orders=2).to(dev)
        out.append(fit_constrained(m, data.to(dev), c=2e-4, points=64))
    assert out[0].success and out[1].success
    assert out[1].max_slope_check == pytest.approx(out[0].max_slope_check, rel=1e-6)
    assert torch.allclose(out[1].x.cpu(), out[0].x, rtol=1e-6, atol=1e-12)


def test_cartesian_targets_on_cuda_match_cpu(setup):
    """compensate_targets (nominal IK from the seed, then compensation) on the GPU lands where the CPU lands."""
    from torchcal.compensate.targets import compensate_targets
    from torchcal.kinematics.transforms import homogeneous

    robot, noise, units = setup
    m = _model(robot)
    fit(m, units[0], noise)
    q = torchcal.sim.quasi_random_commands(robot.joint_map.limits, 300, 6)
    tool = torch.arange(300) % 3
    with torch.no_grad():
        F = m.nominal_flange(q)
        t = m.tools.nominal[tool]
        T = homogeneous(F[:, :3, :3], F[:, :3, 3] + (F[:, :3, :3] @ t[..., None])[..., 0])
    cpu = compensate_targets(m, T, q, tool)
    g = _model(robot, "cuda")
    g.load_state_dict(m.state_dict())
    gpu = compensate_targets(g, T.cuda(), q.cuda(), tool.cuda())
    ok = cpu.converged & gpu.converged.cpu()
    assert ok.float().mean() > 0.9
    assert torch.allclose(gpu.q.cpu()[ok], cpu.q[ok], atol=1e-10, rtol=0)
    assert torch.allclose(gpu.command_target.cpu()[ok], cpu.command_target[ok], atol=1e-10, rtol=0)


@pytest.mark.filterwarnings("error:.*could not be captured:RuntimeWarning")  # the graphs must capture here
def test_damped_graphs_match_the_eager_loop(setup, monkeypatch):
    """The damped least squares replayed as CUDA graphs (damped_graph.py: rows frozen in place, Cholesky solves)
    against the eager loop on the same GPU (rows dropped, cuSOLVER's LU) and against the CPU: reachable targets
    to rounding, out-of-reach ones with the same verdicts; and compensate() with graphs off and on."""
    import math

    from torchcal.compensate.damped import damped_least_squares

    robot, noise, units = setup
    m = _model(robot)
    fit(m, units[0], noise)
    g = _model(robot, "cuda")
    g.load_state_dict(m.state_dict())
    q = torchcal.sim.quasi_random_commands(robot.joint_map.limits, 400, 9).cuda()
    s = torch.ones_like(q)
    with torch.no_grad():
        T = g.nominal_flange(q)
    far = T.clone()
    far[:, :3, 3] *= 1.3  # out of reach
    bounded = dict(q_ref=q, max_step=math.radians(5), max_correction=math.radians(5), stop_at_bound=True, max_iter=20)
    for target, kw in ((T, {}), (far, {}), (far, bounded)):
        a = damped_least_squares(g, q, target, s, **kw)  # graphs
        b = damped_least_squares(g, q, target, s, fixed_shape=False, **kw)
        c = damped_least_squares(m, q.cpu(), target.cpu(), s.cpu(), **{k: v.cpu() if torch.is_tensor(v) else v
                                                                        for k, v in kw.items()})
        for other in (b, c):
            same = (a.converged.cpu() == other.converged.cpu()) & (a.stationary.cpu() == other.stationary.cpu())
            assert float(same.double().mean()) >= 0.99
        if target is T:
            ok = a.converged.cpu() & c.converged
            assert float(ok.double().mean()) > 0.9
            assert torch.allclose(a.q.cpu()[ok], c.q[ok], rtol=0, atol=1e-10)
    # a batch with many rows on the damped path: commands near the wrist singularity (q5 = 0)
    qs = q.clone()
    qs[:, 4] = 1e-3 * torch.linspace(-1, 1, q.shape[0], device=q.device, dtype=q.dtype)
    on = compensate(g, qs, s)
    monkeypatch.setenv("TORCHCAL_CUDA_GRAPHS", "0")
    off = compensate(g, qs, s)
    assert int(on.damped.sum()) > 50
    assert float((on.status == off.status).double().mean()) >= 0.99
    ok = on.converged & off.converged
    assert torch.allclose(on.q[ok], off.q[ok], rtol=0, atol=1e-9)


def test_position_only_compensation_on_cuda_matches_cpu(setup):
    """3-DOF (one reflector per pose): the same commands on the GPU as on the CPU, and the tool point reached."""
    robot, _, _ = setup
    tool = TOOLS[:1]
    cpu = torchcal.RobotModel(robot, tool, orders=3, backlash=False)
    with torch.no_grad():
        g = torch.Generator().manual_seed(5)
        cpu.joint_errors.coef.copy_(torch.randn(cpu.joint_errors.coef.shape, generator=g, dtype=torch.float64) * 1e-4
                                    * cpu.joint_errors.mask)
    gpu = torchcal.RobotModel(robot, tool, orders=3, backlash=False).to("cuda")
    gpu.load_state_dict(cpu.state_dict())
    q = torchcal.sim.quasi_random_commands(robot.joint_map.limits, 2000, 3)
    c = cpu.tools()[0].detach()
    rc = compensate(cpu, q, position_only=True, tool_point=c)
    rg = compensate(gpu, q.cuda(), position_only=True, tool_point=c.cuda())
    both = rc.converged & rg.converged.cpu()
    assert int(both.sum()) > 1900
    assert float((rg.q.cpu()[both] - rc.q[both]).abs().max()) < 1e-9
