import math

import pytest
import torch

from conftest import random_commands, randomize
from torchcal.identify import CalibrationProblem, NoiseModel, Prior, fit, fix_gauge
from torchcal.identify.lm import _schur_step
from torchcal.core.measurements import Measurements
from torchcal.models.robot import RobotModel


def simulate(truth, robot, poses, seed, noise: NoiseModel | None, tools=(0, 1, 2)):
    q = random_commands(robot, poses, seed)
    s = torch.sign(torch.diff(torch.cat([torch.zeros(1, 6), q]), dim=0))
    T = len(tools)
    qq, ss = q.repeat(T, 1), s.repeat(T, 1)
    tool = torch.tensor(tools).repeat_interleave(poses)
    g = torch.Generator().manual_seed(seed + 1000)
    v = None
    with torch.no_grad():
        if noise is not None:
            v = torch.randn(qq.shape, generator=g) * noise.joint_variance(ss).sqrt()
        p = truth.points(qq, tool, ss, v)
        if noise is not None:
            p = p + torch.randn(p.shape, generator=g) * noise.sigma_m
    return Measurements(qq, tool, p, ss, torch.arange(poses).repeat(T), torch.arange(1, len(qq) + 1), True, "sim")


def test_noise_model_units_and_directions():
    nm = NoiseModel.from_file_units(0.005, [1.0, 4.0], [9.0, 16.0])
    assert nm.sigma_m == pytest.approx(5e-6)
    var = nm.joint_variance(torch.tensor([[1.0, -1.0], [0.0, 0.0]]))
    d2 = (math.pi / 180) ** 2
    assert torch.allclose(var, torch.tensor([[1.0, 16.0], [5.0, 10.0]]) * d2)


def test_schur_step_equals_dense_joint_solve(fanuc, tools_m):
    """Eliminating each row's joint errors must give exactly the dense Gauss-Newton step."""
    truth = randomize(RobotModel(fanuc, tools_m, orders=1, backlash=True), 1)
    data = simulate(truth, fanuc, 8, 2, NoiseModel.paper2())
    model = RobotModel(fanuc, tools_m, orders=1, backlash=True)
    prob = CalibrationProblem(model, data, NoiseModel.paper2(), Prior())
    x = prob.layout.get()
    v = 1e-5 * torch.randn(prob.data.q.shape, generator=torch.Generator().manual_seed(3))
    f, A, C = prob.linearize(x, v)
    mu = 1e-3
    db, dv, _ = _schur_step(f, A, C, prob.w_v, v, prob.prior_precision, x - prob.prior_mean, mu)
    R, _, P = A.shape
    n = C.shape[-1]
    J = torch.zeros(R * 3, P + R * n)
    J[:, :P] = A.reshape(R * 3, P)
    for r in range(R):
        J[3 * r : 3 * r + 3, P + n * r : P + n * r + n] = C[r]
    W = torch.cat([prob.prior_precision, prob.w_v.reshape(-1)])
    H = J.T @ J + torch.diag(W)
    g = J.T @ f.reshape(-1) + W * torch.cat([x - prob.prior_mean, v.reshape(-1)])
    step = torch.linalg.solve(H + mu * torch.diag(torch.diagonal(H)), -g)
    assert torch.allclose(step[:P], db, rtol=1e-7, atol=1e-12)
    assert torch.allclose(step[P:], dv.reshape(-1), rtol=1e-7, atol=1e-12)


def test_gauge_pins_exactly_the_redundant_constants(fanuc, tools_m):
    """Constant model of a 6R arm seen through 3 tool points: 4 per joint + 6 base + 9 tool - 6 = 33 identifiable."""
    truth = randomize(RobotModel(fanuc, tools_m, orders=0), 4)
    data = simulate(truth, fanuc, 40, 5, None)
    model = RobotModel(fanuc, tools_m, orders=0)
    prob = CalibrationProblem(model, data, NoiseModel.paper2(), Prior())
    assert prob.layout.size == 51
    pinned = fix_gauge(prob)
    assert prob.layout.size == 33 and len(pinned) == 18
    assert all(n.endswith(".c0") for n in pinned)


def test_lm_recovers_known_truth_from_noise_free_data(fanuc, tools_m):
    truth = randomize(RobotModel(fanuc, tools_m, orders=2, backlash=True), 6)
    data = simulate(truth, fanuc, 80, 7, None)
    # Pinning a redundant constant re-expresses the others only to second order
    # (exp(a) exp(b) != exp(a + b)); give the truth the pinned gauge so that it is
    # exactly expressible, then recovery must be exact.
    pinned = fit(RobotModel(fanuc, tools_m, orders=2, backlash=True), data, NoiseModel.paper2(), max_iter=1).pinned
    names = truth.joint_errors.parameter_names()[0]
    with torch.no_grad():
        flat = truth.joint_errors.coef.view(-1)
        for name in pinned:
            if name in names:
                flat[names.index(name)] = 0.0
        for i, t in enumerate(("eps_x", "eps_y", "eps_z", "delta_x", "delta_y", "delta_z")):
            if f"base.{t}" in pinned:
                truth.base.twist[i] = 0.0
    data = simulate(truth, fanuc, 80, 7, None)
    model = RobotModel(fanuc, tools_m, orders=2, backlash=True)
    res = fit(model, data, NoiseModel.paper2(), Prior(1.0, 1.0, 1.0, 1.0, backlash=1.0), ftol=1e-14)
    assert res.success
    test = simulate(truth, fanuc, 50, 8, None)
    err = (model.points(test.q, test.tool, test.direction) - test.xyz).norm(dim=1).max()
    assert err < 1e-9  # metres: exact recovery of what the model can express


def test_lm_fits_noisy_data_to_the_noise_floor(fanuc, tools_m):
    noise = NoiseModel.paper2()
    truth = randomize(RobotModel(fanuc, tools_m, orders=2, backlash=True), 9)
    data = simulate(truth, fanuc, 120, 10, noise)
    model = RobotModel(fanuc, tools_m, orders=2, backlash=True)
    res = fit(model, data, noise)
    assert res.success and res.nit < 40
    test = simulate(truth, fanuc, 100, 11, None)
    with torch.no_grad():
        err = (model.points(test.q, test.tool, test.direction) - test.xyz).norm(dim=1).mean()
        nominal = (model.nominal_points(test.q, test.tool) - test.xyz).norm(dim=1).mean()
    assert err < 0.02e-3 and nominal > 50 * err


def test_lbfgs_agrees_with_lm_on_a_small_problem(fanuc, tools_m):
    noise = NoiseModel.paper2()
    truth = randomize(RobotModel(fanuc, tools_m, orders=0), 12)
    data = simulate(truth, fanuc, 15, 13, noise)
    m1 = RobotModel(fanuc, tools_m, orders=0)
    r1 = fit(m1, data, noise, method="lm")
    m2 = RobotModel(fanuc, tools_m, orders=0)
    r2 = fit(m2, data, noise, method="lbfgs", max_iter=5000, ftol=1e-12)
    assert r1.success, r1.message
    assert r2.success, r2.message  # converged by its own criterion, not stopped at max_iter
    assert r2.nit < 5000
    assert r2.fun <= r1.fun * 1.01 + 1.0
    test = simulate(truth, fanuc, 20, 14, None)
    with torch.no_grad():
        diff = (m1.points(test.q, test.tool) - m2.points(test.q, test.tool)).norm(dim=1).max()
    assert diff < 2e-5


@pytest.mark.parametrize("folds, criterion", [(3, "cv-3"), (0, "loo")])
def test_order_selection_finds_the_joint_that_needs_terms(fanuc, tools_m, folds, criterion):
    from torchcal.identify import select_orders

    noise = NoiseModel.paper2()
    truth = randomize(RobotModel(fanuc, tools_m, orders=3), 15)
    with torch.no_grad():
        # constant errors everywhere; joint 2 alone carries joint-dependent errors up to order 3
        truth.joint_errors.coef[:, :, 1:] = 0.0
        truth.joint_errors.coef[1, :3, 1:4] = 3e-4
    data = simulate(truth, fanuc, 60, 16, noise)
    sel = select_orders(lambda o: RobotModel(fanuc, tools_m, orders=o), data, None, noise,
                        candidates=[0, 3], folds=folds, seed=0)
    assert sel.orders[1] == 3
    assert sum(sel.orders) == 3  # every other joint stays constant
    assert sel.criterion == criterion


def test_order_selection_window_limits_the_per_joint_search(fanuc, tools_m):
    """joint_window: stage 2 only tries orders near each joint's current one; the result is still the best tried."""
    from torchcal.identify import select_orders

    noise = NoiseModel.paper2()
    truth = randomize(RobotModel(fanuc, tools_m, orders=1), 17)
    data = simulate(truth, fanuc, 40, 18, noise)
    val = simulate(truth, fanuc, 30, 19, noise)
    sel = select_orders(lambda o: RobotModel(fanuc, tools_m, orders=o), data, val, noise,
                        candidates=[0, 1, 2, 3], joint_window=1, max_passes=1, margin=0.0)
    uniform = [r for r in sel.table if r["stage"] == "uniform"]
    assert len(uniform) == 4
    # stage 1 ends where the best uniform order of the last linearization stays put
    stage1 = [i for i, r in enumerate(sel.table) if r["stage"].startswith("uniform")]
    last = sel.table[stage1[-1]]["epoch"]
    best = min((r for r in sel.table[:stage1[-1] + 1] if r["epoch"] == last), key=lambda r: r["score"])
    # replay the search: every per-joint trial moves one joint by at most the window from the best orders so
    # far; a re-centred linearization re-scores the incumbent ("recentred") and later trials compare with that
    cur, cur_score = list(best["orders"]), best["score"]
    for r in sel.table[stage1[-1] + 1:]:
        if r["stage"] == "recentred":
            assert r["orders"] == cur
            cur_score = r["score"]
            continue
        j = int(r["stage"][len("joint"):]) - 1
        assert [o for i, o in enumerate(r["orders"]) if i != j] == [o for i, o in enumerate(cur) if i != j]
        assert abs(r["orders"][j] - cur[j]) == 1
        if r["score"] < cur_score:
            cur, cur_score = list(r["orders"]), r["score"]
    assert cur == sel.orders
    assert sel.score == cur_score


def test_prior_follows_the_layout_when_a_whole_group_is_pinned(fanuc, tools_m):
    """set_layout must drop the prior entries of a group the new layout no longer has at all."""
    from torchcal.identify.problem import CalibrationProblem

    model = RobotModel(fanuc, tools_m, orders=1, backlash=True)
    data = simulate(model, fanuc, 10, 20, None)
    prob = CalibrationProblem(model, data, NoiseModel.paper2(), Prior())
    names = prob.layout.names()
    first = prob.layout.entries[0][0]
    k = int(prob.layout.entries[0][2].sum())
    drop = torch.zeros(prob.layout.size, dtype=torch.bool)
    drop[:k] = True  # pin every entry of the first group
    drop[k + 1] = True  # and one more
    before = dict(zip(names, prob.prior_precision.tolist()))
    new = prob.layout.without(drop)
    prob.set_layout(new)
    assert first not in [e[0] for e in new.entries]
    assert prob.prior_precision.numel() == new.size
    assert prob.prior_precision.tolist() == [before[n] for n in new.names()]


def test_leave_one_pose_out_matches_refits(fanuc, tools_m):
    """loo_residuals (one linearization, Woodbury) against the model actually refitted without each pose."""
    from torchcal.identify.order import _row_errors, loo_residuals

    noise = NoiseModel.paper2()
    truth = randomize(RobotModel(fanuc, tools_m, orders=2), 21)
    data = simulate(truth, fanuc, 40, 22, noise)
    model = RobotModel(fanuc, tools_m, orders=1)  # too simple on purpose: held-out errors well above the training ones
    r = fit(model, data, noise, ftol=1e-14)
    loo = loo_residuals(model, data, noise, Prior(), r.v)
    train = _row_errors(model, data)
    for pose in (0, 17, 39):
        held = data.pose == pose
        refit = RobotModel(fanuc, tools_m, orders=1)
        refit.load_state_dict(model.state_dict())
        fit(refit, data.subset(~held), noise, ftol=1e-14)
        exact = _row_errors(refit, data.subset(held))
        assert torch.allclose(loo[held], exact, rtol=2e-3, atol=2e-8), (pose, loo[held], exact)
        assert (exact - train[held]).abs().max() > 20 * (loo[held] - exact).abs().max()  # the shift is resolved


def test_paired_improvement_averages_rows_per_pose():
    from torchcal.identify.order import paired_improvement

    pose = torch.tensor([0, 0, 1, 1, 2, 2, 3, 3])
    a = torch.tensor([1.0, 3.0, 2.0, 2.0, 5.0, 1.0, 0.0, 4.0])
    b = a - torch.tensor([1.0, 1.0, 0.0, 2.0, 3.0, 3.0, 0.5, 1.5])  # per-pose mean differences 1, 1, 3, 1
    gain, se = paired_improvement(a, b, pose)
    d = torch.tensor([1.0, 1.0, 3.0, 1.0])
    assert gain == pytest.approx(1.5)
    assert se == pytest.approx(float(d.std()) / 2.0)
    gain, se = paired_improvement(a, a + 0.25, pose)
    assert gain == pytest.approx(-0.25) and se == pytest.approx(0.0, abs=1e-12)
