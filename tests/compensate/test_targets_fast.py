"""The compiled targets pass (torchcal.compensate.fused_targets) against the batched general path, and its
pieces against torch: the same commands where both converge off singular surfaces, the rows it hands on still
solved and explained, its inverse and det sign, its pose error."""

from __future__ import annotations

import numpy as np
import pytest
import torch
from conftest import random_commands, randomize
from hypothesis import given, settings
from hypothesis import strategies as st

from torchcal.compensate.toolset import compensation_goal, inverse, model_tool_set_frame, tool_poses
from torchcal.compensate import fused
from torchcal.compensate import targets as TG
from torchcal.compensate.kernel import pose_error_soa
from torchcal.compensate.newton import nominal_sigma_min
from torchcal.kinematics.transforms import homogeneous, pose_error
from torchcal.models.robot import RobotModel

pytestmark = pytest.mark.skipif(not fused.HAVE_NUMBA, reason="the compiled pass needs numba")


def _g_inv(model):
    """The inverse of the model's tool-set frame (None: identity), as compensate() passes it to its solver."""
    G = model_tool_set_frame(model)
    return None if G is None else inverse(G)


def _tool_pose(F, t):
    return homogeneous(F[:, :3, :3], F[:, :3, 3] + (F[:, :3, :3] @ t[..., None])[..., 0])


def _problem(fanuc, tools_m, B=300, seed=21):
    model = randomize(RobotModel(fanuc, tools_m, orders=4, backlash=True), seed, rot=3e-3, trans=3e-4)
    with torch.no_grad():
        model.tools.delta.copy_(torch.tensor([[2e-4, -1e-4, 3e-4], [0.0, 1e-4, -2e-4], [-1e-4, 0.0, 2e-4]],
                                             dtype=torch.float64))
    q = random_commands(fanuc, B, seed + 1)
    tool = torch.arange(B) % 3
    g = torch.Generator().manual_seed(seed + 2)
    s = torch.where(torch.rand(B, 6, generator=g) < 0.5, -1.0, 1.0).double()
    with torch.no_grad():
        T = _tool_pose(model.nominal_flange(q), model.tools.nominal[tool])
    return model, q, tool, s, T


def test_compiled_pass_equals_the_general_path(fanuc, tools_m, monkeypatch):
    model, q, tool, s, T = _problem(fanuc, tools_m)
    seed = q + 0.01 * torch.randn(q.shape, generator=torch.Generator().manual_seed(3), dtype=torch.float64)
    used = {}
    real = TG._fast_pass

    def spy(*a, **k):
        out = real(*a, **k)
        used["status"] = None if out is None else out["status"].clone()
        return out

    monkeypatch.setattr(TG, "_fast_pass", spy)
    fast = TG.compensate_targets(model, T, seed, tool, s)
    assert used["status"] is not None and int((used["status"] == 0).sum()) > 250  # most rows took the pass
    monkeypatch.setattr(TG, "FAST_MIN_TARGETS", 10**9)
    ref = TG.compensate_targets(model, T, seed, tool, s)
    clear = fast.converged & ref.converged & (nominal_sigma_min(model, q) > 0.02)
    assert int(clear.sum()) > 200  # (random commands within the range: ~20 % leave it or lie near a surface)
    assert float((fast.q[clear] - ref.q[clear]).abs().max()) < 1e-9
    assert float((fast.q_nominal[clear] - ref.q_nominal[clear]).abs().max()) < 1e-9
    assert float(pose_error(fast.command_target[clear], ref.command_target[clear]).abs().max()) < 1e-9
    assert torch.equal(fast.converged, fast.compensation.converged & fast.compensation.within_limits)
    # the calibrated commands put the identified tool on the target, the tool set's frame (.toolset) in the
    # target's orientation (independent of either solver)
    with torch.no_grad():
        reach = tool_poses(model, fast.q, tool, s)
    assert float(pose_error(reach[fast.converged], T[fast.converged]).norm(dim=-1).max()) < 1e-9
    assert all((r == "") == bool(c) for r, c in zip(fast.reason, fast.converged.tolist()))
    c = fast.compensation
    assert float(c.residual[fast.converged].max()) < 1e-12
    assert torch.allclose(c.correction, (fast.q - fast.q_nominal).abs().amax(-1))


def test_rows_the_pass_hands_on_are_solved_and_explained(fanuc, tools_m, monkeypatch):
    """Seeds beyond the pass's trust region, a target out of reach, a tight bound: the general path gets them."""
    from torchcal.compensate.fused_targets import DONE, IK_FAILED, IK_TRUST

    model, q, tool, s, T = _problem(fanuc, tools_m, B=120, seed=5)
    seed = q.clone()
    seed[:10, 0] += 2.5 * IK_TRUST  # far seeds: the first Newton step leaves the trust region
    T = T.clone()
    T[10:12, :3, 3] += 3.0  # out of reach
    seen = []
    real = TG._fast_pass

    def spy(*a, **k):
        seen.append(real(*a, **k))
        return seen[-1]

    monkeypatch.setattr(TG, "_fast_pass", spy)
    res = TG.compensate_targets(model, T, seed, tool, s, max_correction=0.2)
    status = seen[0]["status"]
    assert bool((status[:10] == IK_FAILED).all()) and bool((status[10:12] != DONE).all())
    assert bool((status[12:] == DONE).any())
    # the far seeds: the general path's damped IK still reaches the target from them
    with torch.no_grad():
        reach = tool_poses(model, res.q, tool, s)
    err = pose_error(reach, T).norm(dim=-1)
    far_ok = res.converged[:10]
    assert int(far_ok.sum()) >= 5 and float(err[:10][far_ok].max()) < 1e-9
    assert not bool(res.converged[10:12].any()) and all(r.startswith("out of reach") for r in res.reason[10:12])
    # a bound every correction exceeds: nothing converges in the pass, every row says why
    res2 = TG.compensate_targets(model, T[12:], seed[12:], tool[12:], s[12:], max_correction=1e-6)
    assert not bool((seen[1]["status"] == DONE).any())
    assert not bool(res2.converged.any()) and all(r != "" for r in res2.reason)


@settings(max_examples=40, deadline=None)
@given(st.integers(0, 2**31 - 1), st.floats(-3.0, 3.0))
def test_invert_column_matches_torch(seed, log_scale):
    from torchcal.compensate.fused_targets import det_sign_column, invert_column

    g = torch.Generator().manual_seed(seed)
    J = torch.randn(6, 6, 3, generator=g, dtype=torch.float64) * 10.0 ** log_scale
    A, P = np.empty((6, 12)), np.empty((6, 6))
    for b in range(3):
        sign = invert_column(J.numpy(), b, A, P)
        Jb = J[:, :, b]
        assert sign == float(torch.sign(torch.linalg.det(Jb))) == det_sign_column(J.numpy(), b, A)
        assert np.allclose(P @ Jb.numpy(), np.eye(6), atol=1e-8)
    J[:, 2, 0] = 0.0  # a zero column: singular
    assert invert_column(J.numpy(), 0, A, P) == 0.0 == det_sign_column(J.numpy(), 0, A)


def test_pose_error_matches_the_torch_kernel():
    from torchcal.compensate.fused_targets import pose_error as pose_error_nb
    from torchcal.kinematics.transforms import axis_angle_to_matrix

    g = torch.Generator().manual_seed(4)
    B = 5
    ax = torch.nn.functional.normalize(torch.randn(2, B, 3, generator=g, dtype=torch.float64), dim=-1)
    R = axis_angle_to_matrix(ax, torch.rand(2, B, generator=g, dtype=torch.float64) * 3)  # (2, B, 3, 3)
    p = torch.randn(2, B, 3, generator=g, dtype=torch.float64)
    Ra, Rn = R[0].permute(1, 2, 0).contiguous(), R[1].permute(1, 2, 0).contiguous()
    pa, pn = p[0].T.contiguous(), p[1].T.contiguous()
    ref = pose_error_soa(Ra, pa, Rn, pn)
    de = np.empty(6)
    for b in range(B):
        pose_error_nb(Ra.numpy(), pa.numpy(), b, R[1].contiguous().numpy(), pn.numpy(), b, de)  # the goal pose-first
        assert np.allclose(de, ref[:, b].numpy(), atol=1e-14)


def test_compensate_compiled_pass_equals_the_batched_solver(fanuc, tools_m):
    """compensate() on the CPU takes the compiled pass (1 100 poses >= FUSED_MIN_POSES); its batched solver
    (_solve, torch ops over the pose axis) is the reference: same commands where both converge, same flags."""
    from torchcal.compensate import newton

    model = randomize(RobotModel(fanuc, tools_m, orders=4, backlash=True), 31, rot=3e-3, trans=3e-4)
    q = random_commands(fanuc, 1100, 32)
    s = torch.where(torch.rand(q.shape, generator=torch.Generator().manual_seed(33)) < 0.5, -1.0, 1.0).double()
    assert q.shape[0] >= newton.FUSED_MIN_POSES
    res = newton.compensate(model, q, s)
    ref = newton._solve(model, q, s, 1e-10, 30, 1e-5, None, 50, 0.5, 1.0, 1e-12, False, True, 2, True,
                        newton.DEFAULT_BOUND, newton.DEFAULT_BOUND, 1e-3, True, None, None, target=None, g_inv=_g_inv(model))
    both = res.converged & ref.converged
    assert int(both.sum()) > 900 and int((res.converged != ref.converged).sum()) <= 5
    assert float((res.q[both] - ref.q[both]).abs().max()) < 1e-9
    assert torch.equal(res.within_limits, ((res.q >= model.command_limits[:, 0]) & (res.q <= model.command_limits[:, 1])).all(-1))
    with torch.no_grad():  # (46) met: the modeled flange at q is the nominal flange at q_nom
        err = pose_error(model.flange(res.q, s, base=False), compensation_goal(model, q))
    assert float(err[res.converged].norm(dim=-1).max()) < 1e-11
    assert torch.allclose(res.correction, (res.q - q).abs().amax(-1))


def test_damped_ik_from_far_starts_never_calls_a_half_turn_converged(fanuc, tools_m):
    """The residual's rotation part ½ vee(Ω - Ω^T) = sin(angle) axis vanishes at a half turn: Levenberg-Marquardt
    from starts spread over the joint range settles there for most of them. Converged must mean the flange is on
    the goal (checked by forward kinematics, not by the residual)."""
    from torchcal.compensate import damped_least_squares

    model = RobotModel(fanuc, tools_m, orders=0)
    goal = model.nominal_flange(torch.tensor([[0.5, -0.45, 0.87, -2.33, 1.19, -0.29]], dtype=torch.float64)).detach()
    lim = model.command_limits
    starts = lim[:, 0] + torch.quasirandom.SobolEngine(6, scramble=True, seed=0).draw(64).double() * (lim[:, 1] - lim[:, 0])
    res = damped_least_squares(model, starts, goal.expand(64, 4, 4).contiguous(), None, max_iter=100)
    with torch.no_grad():
        err = (model.nominal_flange(res.q) - goal).abs().amax((-1, -2))
    assert bool(res.converged.any())
    assert float(err[res.converged].max()) < 1e-9


def test_compiled_pass_keeps_large_corrections_on_the_branch(fanuc, tools_m):
    """Large wrist errors (corrections beyond the 10 deg path threshold next to the wrist singularity): no row the
    compiled pass returns converged changes a configuration flag at its end or on its straight path (flags
    computed geometrically, torchcal.compensate.flags), and it agrees with the batched solver where both converge."""
    from torchcal.compensate import newton
    from torchcal.compensate.flags import configuration_flags

    model = randomize(RobotModel(fanuc, tools_m, orders=2, backlash=False), 41, rot=3e-3, trans=3e-4)
    with torch.no_grad():  # a 6 deg offset on joints 4 and 6, 3 deg on joint 5: near q5 = 0 the corrections grow
        model.joint_errors.coef[3, 2, 0] += 0.1
        model.joint_errors.coef[4, 2, 0] += 0.05
        model.joint_errors.coef[5, 2, 0] += 0.1
    q = random_commands(fanuc, 1500, 42)
    q[:700, 4] = torch.empty(700).uniform_(-0.35, 0.35, generator=torch.Generator().manual_seed(43))
    res = newton.compensate(model, q)
    big = res.converged & (res.correction > newton.PATH_ABOVE) & ~res.damped  # taken by the compiled pass
    assert int(big.sum()) > 20
    f0 = configuration_flags(model, q)
    # (a nominal command on a singular surface has no branch to keep: the solvers do not test those rows)
    ok = res.converged & (f0 != 0).all(-1) & (newton.nominal_sigma_min(model, q) > 1e-2)
    for t in torch.linspace(0.125, 1.0, 8, dtype=torch.float64):
        ft = configuration_flags(model, q + t * (res.q - q))
        assert torch.equal(ft[ok], f0[ok])
    ref = newton._solve(model, q, None, 1e-10, 30, 1e-5, None, 50, 0.5, 1.0, 1e-12, False, True, 2, True,
                        newton.DEFAULT_BOUND, newton.DEFAULT_BOUND, 1e-3, True, None, None, target=None, g_inv=_g_inv(model))
    both = res.converged & ref.converged
    assert int((res.converged != ref.converged).sum()) <= 0.02 * q.shape[0]
    assert float((res.q[both] - ref.q[both]).abs().max()) < 1e-8
