"""compensate(): round trip (46), independent reference, identity, singular and unreachable poses, batching, backlash, device."""

import math

import numpy as np
import pytest
import torch

from conftest import random_commands, randomize
from torchcal.compensate.toolset import compensation_goal
from torchcal.compensate import compensate, damped_least_squares, nominal_sigma_min
from torchcal.kinematics.fk import chain_frames
from torchcal.kinematics.transforms import pose_error
from torchcal.models.robot import RobotModel


def actual_error(model, res, q_nom, s):
    """(46) checked with RobotModel itself, not with the kernel the solver runs on."""
    with torch.no_grad():
        return pose_error(model.flange(res.q, s, base=False), compensation_goal(model, q_nom))


def directions(count, seed):
    return torch.sign(torch.randn(count, 6, generator=torch.Generator().manual_seed(seed)))


@pytest.fixture(scope="module")
def model(fanuc, tools_m):
    """The solver's tests: the tools at their nominal vectors, so the frame compensated is the flange itself ((46)
    as printed; the identified tool set's frame has its own tests, test_toolset.py)."""
    m = randomize(RobotModel(fanuc, tools_m, orders=6, backlash=True), 21)
    with torch.no_grad():
        m.tools.delta.zero_()
    return m


def test_round_trip(model, fanuc):
    q = random_commands(fanuc, 250, 22)
    s = directions(250, 23)
    res = compensate(model, q, s)
    de = actual_error(model, res, q, s)
    c = res.converged
    assert c.double().mean() > 0.8
    # Every row stays within the default bound of 30 deg of its nominal command, flagged or not
    bound = math.radians(30.0)
    assert torch.equal(res.correction, (res.q - q).abs().amax(-1))
    assert (res.correction <= bound * (1 + 1e-12)).all()
    # The flagged rows either sit at the edge of reach (elbow nearly stretched, theta3 = q2 + q3 near
    # 75.5 deg, where the modeled arm falls short of the nominal pose: scipy confirms below), or their
    # exact solution, found without the bound, lies further than the bound from q_nom or on another branch.
    free = compensate(model, q, s, max_step=None, max_correction=None, null_damping=0.0, branch=False)
    elbow = torch.rad2deg(q[:, 1] + q[:, 2])
    unreachable = ~free.converged
    assert ((elbow[unreachable] - 75.5).abs() < 10.0).all()
    from torchcal.compensate import branch_changed, FlangeKernel
    other = branch_changed(FlangeKernel(model), q, free.q)
    assert (unreachable | (free.correction > bound) | other)[~c].all()
    assert (res.status[unreachable & ~c] == 3).all()  # OUT_OF_REACH: the reason says so
    tight = compensate(model, q, s, max_correction=math.radians(5.0))
    assert (~tight.converged & ~unreachable).any()  # a tight bound does flag rows the unbounded solver swings
    assert (free.correction[~c & ~unreachable] > bound).all()
    # where both converge they found the same commands: the bound changes which rows pass, not the answer
    both = c & free.converged
    assert torch.allclose(res.q[both], free.q[both], atol=1e-10, rtol=0)
    assert de[c, :3].norm(dim=-1).max() <= 1e-12
    assert de[c, 3:].norm(dim=-1).max() <= 1e-12
    assert torch.allclose(res.pose_error, de, atol=1e-14, rtol=0)  # reported = recomputed
    assert (res.step[c] < 1e-10).all()  # (51)
    # the compensated commands differ from the nominal ones by about the model error, not by zero
    assert (res.q - q)[c].norm(dim=-1).median() > 1e-3
    # rows that are not converged are honest about it: finite, and their error is not small
    assert torch.isfinite(res.q).all()
    assert (res.residual[~c] > 1e-9).all()
    from scipy.optimize import least_squares

    target = model.nominal_flange(q).detach()
    for i in (~c & unreachable).nonzero()[:2, 0].tolist():
        def f(x, i=i):
            with torch.no_grad():
                return pose_error(model.flange(torch.from_numpy(x)[None], s[i : i + 1], base=False), target[i : i + 1])[0].numpy()

        for x0 in (q[i].numpy(), res.q[i].numpy()):
            ref = least_squares(f, x0, method="lm", xtol=1e-15, ftol=1e-15, gtol=1e-15)
            assert np.linalg.norm(ref.fun) > 1e-6  # truly out of reach, not a solver failure
            assert float(res.residual[i]) <= np.linalg.norm(ref.fun) * (1 + 1e-6)


def test_plain_paper_iteration_reaches_the_same_commands(model, fanuc):
    """Broyden and Jacobian refreshes change the path, not the fixed point of (47)-(50)."""
    q = random_commands(fanuc, 100, 24)
    s = directions(100, 25)
    fast = compensate(model, q, s)
    plain = compensate(model, q, s, broyden=False, refresh=0)
    both = fast.converged & plain.converged & ~fast.damped & ~plain.damped
    assert both.double().mean() > 0.7
    assert torch.allclose(fast.q[both], plain.q[both], atol=1e-10, rtol=0)


def test_agrees_with_scipy_least_squares(model, fanuc):
    from scipy.optimize import least_squares

    q = random_commands(fanuc, 40, 26)
    s = directions(40, 27)
    sig = nominal_sigma_min(model, q)
    q, s = q[sig > 0.05][:4], s[sig > 0.05][:4]  # well-conditioned poses: one nearby solution
    res = compensate(model, q, s)
    assert res.converged.all()
    target = model.nominal_flange(q).detach()
    for i in range(q.shape[0]):
        def f(x, i=i):
            with torch.no_grad():
                return pose_error(model.flange(torch.from_numpy(x)[None], s[i : i + 1], base=False), target[i : i + 1])[0].numpy()

        ref = least_squares(f, q[i].numpy(), method="lm", xtol=1e-15, ftol=1e-15, gtol=1e-15)
        assert np.linalg.norm(ref.fun) < 1e-12
        assert np.abs(res.q[i].numpy() - ref.x).max() < 1e-9


def test_zero_model_leaves_commands_unchanged(fanuc, tools_m):
    zero = RobotModel(fanuc, tools_m, orders=6, backlash=True)
    q = random_commands(fanuc, 100, 28)
    res = compensate(zero, q, directions(100, 29))
    assert res.converged.all()
    assert torch.equal(res.q, q)  # converged at q^0: no update made
    assert (res.iterations == 0).all()
    assert res.pose_error.abs().max() < 1e-15


def test_wrist_singularity(model, fanuc):
    """q5 = 0: J(q_nom) is singular, the fixed-Jacobian iteration cannot start; no NaN, honest flags."""
    q = random_commands(fanuc, 12, 30)
    q[:6, 4] = 0.0
    q[6:, 4] = 1e-7
    s = directions(12, 31)
    res = compensate(model, q, s, sigma=True)
    assert torch.isfinite(res.q).all() and torch.isfinite(res.pose_error).all()
    assert (res.sigma_min < 1e-5).all()
    assert res.damped.all()
    de = actual_error(model, res, q, s)
    assert torch.allclose(res.pose_error, de, atol=1e-14, rtol=0)
    c = res.converged
    assert (de[c].norm(dim=-1) <= 1e-12).all()
    assert (res.residual[~c] > 1e-12).all()


def stretched_poses(fanuc, count, seed):
    """Poses with the elbow fully stretched: the wrist centre as far from the shoulder as the arm reaches."""
    g = torch.Generator().manual_seed(seed)
    q = random_commands(fanuc, count, seed)
    q[:, 1] = torch.deg2rad(torch.rand(count, generator=g) * 40.0)
    # theta3 = q2 + q3 is the elbow angle; find the stretched one on a grid
    grid = torch.deg2rad(torch.linspace(0.0, 130.0, 1301))
    qq = torch.zeros(grid.numel(), 6)
    qq[:, 2] = grid
    c = fanuc.chain
    _, jp, _ = chain_frames(c.origins, c.axes, c.prismatic, fanuc.joint_map.to_joint(qq), None, c.tip)
    reach = (jp[:, 4] - jp[:, 1]).norm(dim=-1)
    q[:, 2] = grid[reach.argmax()] - q[:, 1]
    return q, float(reach.max())


def test_unreachable_target_is_flagged_with_best_solution(fanuc, tools_m):
    q, reach = stretched_poses(fanuc, 6, 32)
    assert 0.54 < reach < 0.56
    short = RobotModel(fanuc, tools_m, orders=2)
    with torch.no_grad():
        short.joint_errors.coef[2, 3, 0] = -0.1  # upper arm 100 mm shorter: the target is 100 mm out of reach
    res = compensate(short, q)
    assert not res.converged.any()
    assert torch.isfinite(res.q).all()
    de = actual_error(short, res, q, None)
    assert torch.allclose(res.pose_error, de, atol=1e-14, rtol=0)
    assert (de[:, :3].norm(dim=-1) > 0.09).all()
    # the best damped solution: no worse than the start, and a local optimum of the weighted error
    r0 = pose_error(short.flange(q, base=False), short.nominal_flange(q)).detach()
    assert (res.residual < r0[:, :3].norm(dim=-1)).all()
    from scipy.optimize import least_squares

    target = short.nominal_flange(q).detach()
    for i in range(2):
        def f(x, i=i):
            with torch.no_grad():
                return pose_error(short.flange(torch.from_numpy(x)[None], base=False), target[i : i + 1])[0].numpy()

        ref = least_squares(f, res.q[i].numpy(), method="lm", xtol=1e-15, ftol=1e-15, gtol=1e-15)
        assert float(res.residual[i]) <= np.linalg.norm(ref.fun) * (1 + 1e-6)


def test_batching_does_not_change_results(model, fanuc):
    """Rows are solved independently: chunking or solving one row at a time gives the same answer.

    Not bit for bit: BLAS kernels round differently for different batch widths
    (~1e-16), which moves a converged solution by far less than tol, and the
    stopping point at the least-squares optimum of an unreachable target by up
    to ~1e-8 rad next to a singularity, where that optimum lies in a valley
    that is flat to 1e-12 of its cost (the residual itself agrees to 1e-9).
    """
    q = random_commands(fanuc, 48, 33)
    q[:3, 4] = 1e-6  # a few rows through the damped path as well
    s = directions(48, 34)
    full = compensate(model, q, s)
    assert full.damped.any() and (~full.converged).any()
    c = full.converged
    runs = [(slice(None), compensate(model, q, s, chunk_size=7))]
    runs += [(slice(i, i + 1), compensate(model, q[i : i + 1], s[i : i + 1])) for i in [0, 1, 2, 5, 17, 31, 40]]
    runs += [(slice(i, i + 1), compensate(model, q[i : i + 1], s[i : i + 1])) for i in (~c).nonzero()[:2, 0].tolist()]
    for rows, other in runs:
        ref_c = full.converged[rows]
        assert torch.equal(other.converged, ref_c)
        assert torch.equal(other.damped, full.damped[rows])
        assert torch.allclose(other.q[ref_c], full.q[rows][ref_c], atol=1e-13, rtol=0)
        assert torch.allclose(other.q[~ref_c], full.q[rows][~ref_c], atol=1e-7, rtol=0)
        assert torch.allclose(other.residual[~ref_c], full.residual[rows][~ref_c], rtol=1e-9, atol=0)


def test_direction_selects_the_backlash_side(fanuc, tools_m):
    m = RobotModel(fanuc, tools_m, orders=2, backlash=True)
    with torch.no_grad():
        m.joint_errors.backlash[:, 0] = 2e-3  # 2 mrad of backlash on every joint
    q = random_commands(fanuc, 50, 35)
    s = directions(50, 36)
    plus, minus = compensate(m, q, s), compensate(m, q, -s)
    assert plus.converged.all() and minus.converged.all()
    assert (actual_error(m, plus, q, s).norm(dim=-1) <= 1e-12).all()
    assert (actual_error(m, minus, q, -s).norm(dim=-1) <= 1e-12).all()
    # pure backlash on eps_z turns each joint by s_i b_i: the command turns back by about that much
    d = plus.q - q
    assert torch.allclose(d[:, [0, 3, 4, 5]], -2e-3 * s[:, [0, 3, 4, 5]], atol=1e-6)
    assert (plus.q - minus.q).abs().max() > 3e-3
    no_dir = compensate(m, q)
    assert torch.allclose(no_dir.q, q, atol=1e-15)  # without directions there is no backlash term


def test_within_limits_flag(model, fanuc):
    lim = fanuc.joint_map.limits
    q = random_commands(fanuc, 20, 37)
    q[:10, 0] = lim[0, 1]  # on the upper limit of J1: the correction may push it out
    res = compensate(model, q, directions(20, 38))
    inside = ((res.q >= lim[:, 0]) & (res.q <= lim[:, 1])).all(-1)
    assert torch.equal(res.within_limits, inside)


def test_bad_input_names_pose_and_joint(model):
    q = torch.zeros(3, 6)
    q[1, 4] = math.nan
    with pytest.raises(ValueError, match="pose 1, joint 5"):
        compensate(model, q)
    with pytest.raises(ValueError, match=r"\(B, 6\)"):
        compensate(model, torch.zeros(3, 5))
    s = torch.ones(3, 6)
    s[2, 0] = 0.5
    with pytest.raises(ValueError, match="pose 2, joint 1"):
        compensate(model, torch.zeros(3, 6), s)


def test_damped_path_alone_solves_from_far(model, fanuc):
    """Levenberg-Marquardt on its own, started 0.3 rad away, reaches the same commands."""
    q = random_commands(fanuc, 10, 39)
    s = directions(10, 40)
    sig = nominal_sigma_min(model, q)
    q, s = q[sig > 0.05], s[sig > 0.05]
    ref = compensate(model, q, s)
    g = torch.Generator().manual_seed(41)
    start = q + 0.3 * (torch.rand(q.shape, generator=g) - 0.5)
    out = damped_least_squares(model, start, model.nominal_flange(q).detach(), s)
    assert out.converged.all()
    assert torch.allclose(out.q, ref.q, atol=1e-10, rtol=0)


@pytest.mark.skipif(not torch.cuda.is_available(), reason="CUDA not available")
def test_cuda_matches_cpu(model, fanuc):
    q = random_commands(fanuc, 300, 42)
    s = directions(300, 43)
    cpu = compensate(model, q, s)
    m = RobotModel.from_spec(model.spec())
    m.load_state_dict(model.state_dict())
    m = m.to("cuda")
    gpu = compensate(m, q.cuda(), s.cuda())
    assert gpu.q.device.type == "cuda"
    assert torch.equal(gpu.converged.cpu(), cpu.converged)
    c = cpu.converged
    assert torch.allclose(gpu.q.cpu()[c], cpu.q[c], atol=1e-11, rtol=0)


def test_compensation_of_a_model_with_gravity_compliance(fanuc, tools_m):
    """The deflection Δθ(q) moves with the command: (46) holds with it, checked on RobotModel itself."""
    m = randomize(RobotModel(fanuc, tools_m, orders=3, backlash=True, compliance=True), 31)
    with torch.no_grad():
        m.compliance.coef.copy_(torch.randn(m.compliance.coef.shape, generator=torch.Generator().manual_seed(32)) * 2e-3)
    q = random_commands(fanuc, 200, 33)
    s = directions(200, 34)
    res = compensate(m, q, s)
    c = res.converged
    assert c.double().mean() > 0.85
    de = actual_error(m, res, q, s)
    assert de[c].norm(dim=-1).max() <= 1e-12
    # the same model without compliance compensates differently: the deflection is not ignored
    rigid = RobotModel(fanuc, tools_m, orders=3, backlash=True)
    rigid.load_state_dict({k: v for k, v in m.state_dict().items() if not k.startswith("compliance.")})
    other = compensate(rigid, q, s)
    both = c & other.converged
    assert (res.q - other.q)[both].norm(dim=-1).median() > 1e-4


def test_small_batches_on_the_torch_ops_agree_with_the_compiled_kernel(monkeypatch):
    """Under FUSED_MIN_POSES poses compensate skips the numba kernel (its first call costs ~0.5 s per process):
    the same commands either way."""
    import torchcal
    from torchcal.compensate import fused, newton

    if not fused.HAVE_NUMBA:
        pytest.skip("numba not available")
    robot = torchcal.load_robot("fanuc_lrmate200i")
    model = torchcal.RobotModel(robot, torch.zeros(1, 3, dtype=torch.float64), orders=3, backlash=True)
    g = torch.Generator().manual_seed(0)
    with torch.no_grad():
        model.joint_errors.coef.normal_(0.0, 2e-4, generator=g)
    lim = robot.joint_map.limits
    q = lim[:, 0] + 0.1 + torch.rand(300, 6, generator=g, dtype=torch.float64) * (lim[:, 1] - lim[:, 0] - 0.2)
    s = torch.where(torch.rand(300, 6, generator=g) < 0.5, -1.0, 1.0).to(q)
    assert q.shape[0] < newton.FUSED_MIN_POSES
    small = torchcal.compensate(model, q, s)
    monkeypatch.setattr(newton, "FUSED_MIN_POSES", 0)
    compiled = torchcal.compensate(model, q, s)
    assert torch.equal(small.converged, compiled.converged)
    ok = small.converged
    assert (small.q[ok] - compiled.q[ok]).abs().max() < 1e-9


def test_a_model_without_joint_errors_is_refused_by_name():
    """A machine-tool model has no Newton compensation here: a TypeError naming it and the tables, not an
    AttributeError from deep inside."""
    import torchcal
    from torchcal.models.machine import MachineModel

    model = MachineModel(torchcal.load_robot("five_axis_xyzcb"), torch.tensor([[0.0, 0.0, 0.4]], dtype=torch.float64),
                         orders=2)
    with pytest.raises(TypeError, match="MachineModel.*export-tables"):
        torchcal.compensate(model, torch.zeros(3, model.n, dtype=torch.float64))


def test_mismatched_dtype_and_degrees_are_refused_by_name(fanuc, tools_m):
    """A float32 model given float64 commands ended 'out of reach' on 98 % of rows, silently, and commands in
    degrees failed every row with no hint: both are refused naming what to do. Radians within a wide range pass."""
    from torchcal.compensate.targets import compensate_targets
    from torchcal.core.exceptions import InputError

    model = RobotModel(fanuc, tools_m, orders=2)
    randomize(model, 1)
    q = random_commands(fanuc, 20, 3)
    with pytest.raises(InputError, match=r"q_nom is torch.float64, the model torch.float32.*q_nom.to"):
        compensate(model.to(torch.float32), q)
    model = model.to(torch.float64)
    with pytest.raises(InputError, match=r"q_nom reaches .* rad on joint \d.*degrees\? The Python API takes radians"):
        compensate(model, torch.rad2deg(q))
    with pytest.raises(InputError, match=r"compensate_targets: seed reaches .*degrees"):
        compensate_targets(model, torch.eye(4, dtype=torch.float64).repeat(20, 1, 1), torch.rad2deg(q))
    assert compensate(model, q).converged.all()  # the same commands in radians
