"""The instrument-agnostic identification core: any residual dimension, autograd Jacobians, declared
parameter kinds, parameter-only blocks, frozen rows, the robot's own noise."""

import dataclasses
import logging

import pytest
import torch

from conftest import randomize
from test_fit import simulate
from torchcal.identify import CalibrationProblem, GaussianPrior, NoiseModel, Prior, fit, fix_gauge, parameter_groups
from torchcal.identify.gauge import gauge_priority
from torchcal.identify.lm import _schur_step
from torchcal.kinematics.robot import Robot
from torchcal.measure import Instrument, IsotropicWeight, PointTargets
from torchcal.models.robot import RobotModel

pytestmark = pytest.mark.usefixtures("one_thread")


class TwoPoints(Instrument):
    """d = 6: each row reports its own tool point and the next tool's (no closed-form Jacobians: autograd)."""

    dim = 6

    def __init__(self, y, sigma):
        self.observed = y
        self.weight = IsotropicWeight(sigma)

    def predict(self, model, q, tool, direction=None, v=None):
        nxt = (tool + 1) % model.tools.count
        return torch.cat([model.points(q, tool, direction, v), model.points(q, nxt, direction, v)], -1)

    def to(self, device):
        return self


class Range(Instrument):
    """d = 1: distance from a tracker at c to the tool point."""

    dim = 1

    def __init__(self, y, sigma, c):
        self.observed = y
        self.weight = IsotropicWeight(sigma)
        self.c = c

    def predict(self, model, q, tool, direction=None, v=None):
        return (model.points(q, tool, direction, v) - self.c).norm(dim=-1, keepdim=True)

    def to(self, device):
        return self


def _dense_step(f, A, C, w_v, v, lam, dx, mu, free):
    """The damped Gauss-Newton step on (b, v) with v of frozen rows removed, by one dense solve."""
    R, d, P = A.shape
    n = C.shape[-1]
    cols = [r for r in range(R) if free[r]]
    J = torch.zeros(R * d, P + len(cols) * n)
    J[:, :P] = A.reshape(R * d, P)
    for k, r in enumerate(cols):
        J[d * r : d * r + d, P + n * k : P + n * k + n] = C[r]
    W = torch.cat([lam, w_v[cols].reshape(-1)])
    H = J.T @ J + torch.diag(W)
    g = J.T @ f.reshape(-1) + W * torch.cat([dx, v[cols].reshape(-1)])
    step = torch.linalg.solve(H + mu * torch.diag(torch.diagonal(H)), -g)
    dv = torch.zeros(R, n)
    dv[cols] = step[P:].reshape(-1, n)
    return step[:P], dv


def _problem(fanuc, tools_m, orders=1, poses=8, seed=2, **kw):
    truth = randomize(RobotModel(fanuc, tools_m, orders=orders, backlash=True), seed)
    data = simulate(truth, fanuc, poses, seed + 1, NoiseModel.paper2())
    model = randomize(RobotModel(fanuc, tools_m, orders=orders, backlash=True), seed + 7, rot=1e-3, trans=1e-4)
    return truth, data, model


@pytest.mark.parametrize("compliance", [False, "functions"])
def test_autograd_jacobians_equal_the_closed_form(fanuc, tools_m, compliance):
    """torch.func (jacrev, vmapped over rows) and RobotModel.point_jacobians: the same A and C to 1e-10."""
    truth = randomize(RobotModel(fanuc, tools_m, orders=3, backlash=True, compliance=compliance), 1)
    data = simulate(truth, fanuc, 12, 2, NoiseModel.paper2())
    model = randomize(RobotModel(fanuc, tools_m, orders=3, backlash=True, compliance=compliance), 5)
    if compliance:
        with torch.no_grad():
            model.compliance.coef.copy_(1e-3 * torch.randn(model.compliance.coef.shape,
                                                           generator=torch.Generator().manual_seed(0)))
    prob = CalibrationProblem(model, data, NoiseModel.paper2(), Prior())
    x = prob.layout.get()
    v = 1e-5 * torch.randn(prob.data.q.shape, generator=torch.Generator().manual_seed(3))
    f1, A1, C1 = prob.linearize(x, v, jacobian="closed")
    f2, A2, C2 = prob.linearize(x, v, jacobian="autodiff")
    assert torch.allclose(f1, f2, rtol=0, atol=1e-12 * f1.abs().max())
    assert (A1 - A2).abs().max() <= 1e-10 * A1.abs().max()
    assert (C1 - C2).abs().max() <= 1e-10 * C1.abs().max()
    assert torch.allclose(prob.residual(x, v), f1, rtol=0, atol=1e-12 * f1.abs().max())


def test_covariance_whitening(fanuc, tools_m):
    """A per-row covariance sigma^2 I whitens like the isotropic sigma; a full one gives |f|^2 = r^T Sigma^-1 r."""
    _, data, model = _problem(fanuc, tools_m)
    R = len(data)
    iso = CalibrationProblem(model, data, NoiseModel.paper2(), Prior())
    x, v = iso.layout.get(), iso.v_zero()
    cov = torch.eye(3).expand(R, 3, 3) * 5e-6**2
    full = CalibrationProblem(model, data, NoiseModel.paper2(), Prior(), instrument=PointTargets(data.xyz, cov=cov))
    for a, b in zip(iso.linearize(x, v), full.linearize(x, v)):
        assert torch.allclose(a, b, rtol=1e-12, atol=0)
    g = torch.Generator().manual_seed(4)
    B = torch.randn(R, 3, 3, generator=g) * 1e-5
    cov = B @ B.transpose(1, 2) + torch.eye(3) * 1e-12
    full = CalibrationProblem(model, data, NoiseModel.paper2(), Prior(), instrument=PointTargets(data.xyz, cov=cov))
    f = full.residual(x, v)
    r = model.points(data.q, data.tool, data.direction) - data.xyz
    expected = (r[:, None, :] @ torch.linalg.solve(cov, r[..., None]))[:, 0, 0]
    assert torch.allclose((f * f).sum(1), expected, rtol=1e-9)


@pytest.mark.parametrize("d", [1, 6])
def test_schur_step_any_dimension(fanuc, tools_m, d):
    """Instruments with d = 1 (range) and d = 6 (two points): the eliminated step equals the dense one."""
    _, data, model = _problem(fanuc, tools_m)
    with torch.no_grad():
        if d == 6:
            y = TwoPoints(None, 1.0).predict(model, data.q, data.tool, data.direction) + 1e-5
            inst = TwoPoints(y, 5e-6)
        else:
            c = torch.tensor([2.0, -1.0, 0.5])
            inst = Range((data.xyz - c).norm(dim=1, keepdim=True), 5e-6, c)
    prob = CalibrationProblem(model, data, NoiseModel.paper2(), Prior(), instrument=inst)
    x = prob.layout.get()
    v = 1e-5 * torch.randn(prob.data.q.shape, generator=torch.Generator().manual_seed(3))
    f, A, C = prob.linearize(x, v)
    assert f.shape == (len(data), d) and A.shape[:2] == (len(data), d) and C.shape == (len(data), d, 6)
    free = torch.ones(len(data), dtype=torch.bool)
    db, dv, _ = _schur_step(f, A, C, prob.w_v, v, prob.prior_precision, x - prob.prior_mean, 1e-3)
    db_ref, dv_ref = _dense_step(f, A, C, prob.w_v, v, prob.prior_precision, x - prob.prior_mean, 1e-3, free)
    assert torch.allclose(db, db_ref, rtol=1e-7, atol=1e-12)
    assert torch.allclose(dv, dv_ref, rtol=1e-7, atol=1e-12)


@pytest.mark.parametrize("method", ["lm", "lbfgs"])
def test_six_dimensional_instrument_fits_like_points(fanuc, tools_m, method):
    """The same noise-free robot seen through a d = 6 instrument (autograd Jacobians) is recovered."""
    truth = randomize(RobotModel(fanuc, tools_m, orders=0), 12)
    data = simulate(truth, fanuc, 15, 13, None)
    with torch.no_grad():
        y = TwoPoints(None, 1.0).predict(truth, data.q, data.tool, data.direction)
    model = RobotModel(fanuc, tools_m, orders=0)
    opts = {"max_iter": 3000, "ftol": 1e-13} if method == "lbfgs" else {"ftol": 1e-14}
    res = fit(model, data, NoiseModel.paper2(), Prior(1.0, 1.0, 1.0, 1.0), method=method,
              instrument=TwoPoints(y, 5e-6), **opts)
    assert res.success, res.message
    test = simulate(truth, fanuc, 20, 14, None)
    with torch.no_grad():
        err = (model.points(test.q, test.tool) - test.xyz).norm(dim=1).max()
    assert err < (1e-8 if method == "lm" else 1e-6)


def test_declared_kinds_not_names_choose_the_prior(fanuc, tools_m):
    """A URDF joint named 'tool_roll' (or 'base_yaw') is a joint: joint prior, joint gauge priority."""
    names = ["base_yaw", "joint2", "joint3", "joint4", "joint5", "tool_roll"]
    robot = Robot(fanuc.name, dataclasses.replace(fanuc.chain, joint_names=names), fanuc.joint_map, fanuc.source,
                  fanuc.repeatability)
    model = RobotModel(robot, tools_m, orders=1, backlash=True)
    prob = CalibrationProblem(model, simulate(model, robot, 5, 1, None), NoiseModel.paper2(),
                              Prior(rotation=2e-2, translation=3e-3, frame_rotation=0.5, frame_translation=0.25))
    layout = prob.layout
    sigma = dict(zip(layout.names(), (1.0 / prob.prior_precision.sqrt()).tolist()))
    assert sigma["tool_roll.eps_x.c0"] == pytest.approx(2e-2)
    assert sigma["tool_roll.delta_z.c1"] == pytest.approx(3e-3)
    assert sigma["base_yaw.eps_z.c0"] == pytest.approx(2e-2)
    # backlash keeps its declaration (wide c0, tight variation terms) unless Prior.backlash is given
    from torchcal.error_models.joint import BACKLASH_SIGMA, BACKLASH_VARIATION_SIGMA

    assert sigma["tool_roll.backlash.c0"] == pytest.approx(BACKLASH_SIGMA)
    assert sigma["tool_roll.backlash.c1"] == pytest.approx(BACKLASH_VARIATION_SIGMA)
    prob_b = CalibrationProblem(model, simulate(model, robot, 5, 1, None), NoiseModel.paper2(), Prior(backlash=4e-3))
    sigma_b = dict(zip(prob_b.layout.names(), (1.0 / prob_b.prior_precision.sqrt()).tolist()))
    assert sigma_b["tool_roll.backlash.c1"] == pytest.approx(4e-3) and sigma_b["joint2.eps_x.c0"] == pytest.approx(1e-2)
    assert sigma["base.eps_x"] == pytest.approx(0.5) and sigma["base.delta_y"] == pytest.approx(0.25)
    assert sigma["tool2.dz"] == pytest.approx(0.25)
    rot = dict(zip(layout.names(), layout.is_rotation().tolist()))
    assert rot["tool_roll.eps_y.c1"] and not rot["tool_roll.delta_y.c1"] and not rot["tool0.dx"]
    roles = dict(zip(layout.names(), layout.roles()))
    assert roles["tool_roll.eps_x.c0"] == "joint" and roles["tool1.dy"] == "tool" and roles["base.eps_x"] == "frame"
    # gauge: tools and frame first, then every joint (tool_roll among them) in order
    order = [layout.names()[i] for i in gauge_priority(layout.roles()).tolist()]
    first_joint = next(i for i, nm in enumerate(order) if roles[nm] in ("joint", "backlash"))
    assert all(roles[nm] in ("frame", "tool") for nm in order[:first_joint])
    assert all(roles[nm] not in ("frame", "tool") for nm in order[first_joint:])
    # None keeps the module's declaration
    prec = Prior(None, None, None, None, compliance=None).precision(layout)
    assert torch.allclose(prec, 1.0 / layout.prior_sigma() ** 2)


def test_parameter_groups_cover_every_parameter(fanuc, tools_m):
    model = RobotModel(fanuc, tools_m, orders=2, backlash=True, compliance="functions")
    groups = parameter_groups(model)
    assert [g.name for g in groups] == [n for n, _ in model.named_parameters()]
    model.extra = torch.nn.Parameter(torch.zeros(2))
    with pytest.raises(ValueError, match="extra"):
        parameter_groups(model)


def test_gaussian_prior_block_equals_the_diagonal_prior(fanuc, tools_m):
    """A full-covariance block with the diagonal prior's variances gives the same fit (LM and the L-BFGS cost)."""
    _, data, _ = _problem(fanuc, tools_m, orders=1, poses=20, seed=30)
    m1 = RobotModel(fanuc, tools_m, orders=1, backlash=True)
    r1 = fit(m1, data, NoiseModel.paper2(), Prior(), ftol=1e-14)
    m2 = RobotModel(fanuc, tools_m, orders=1, backlash=True)
    layout = CalibrationProblem(m2, data, NoiseModel.paper2(), None).layout
    block = GaussianPrior.over(layout, torch.zeros(layout.size), torch.diag(Prior().sigma(layout) ** 2))
    r2 = fit(m2, data, NoiseModel.paper2(), None, blocks=[block], ftol=1e-14)
    assert r1.names == r2.names
    assert r2.fun == pytest.approx(r1.fun, rel=1e-9)
    assert (r1.x - r2.x).abs().max() <= 1e-5 * r1.x.abs().max(), float((r1.x - r2.x).abs().max() / r1.x.abs().max())
    # L-BFGS's objective (differentiable cost_from): same value and gradient as with the diagonal prior
    p_diag = CalibrationProblem(m2, data, NoiseModel.paper2(), Prior())
    p_blk = CalibrationProblem(m2, data, NoiseModel.paper2(), None, blocks=[block])
    xs = (p_diag.layout.get() * 1.1).requires_grad_(True)
    vs = 1e-6 * torch.ones_like(p_diag.v_zero())
    c_diag, c_blk = (p.cost_from(p.whitened_residual(xs, vs), xs, vs) for p in (p_diag, p_blk))
    assert float(c_blk.detach()) == pytest.approx(float(c_diag.detach()), rel=1e-12)
    g_diag, = torch.autograd.grad(c_diag, xs)
    g_blk, = torch.autograd.grad(c_blk, xs)
    assert torch.allclose(g_blk, g_diag, rtol=1e-9, atol=1e-9 * float(g_diag.abs().max()))
    # the block's residual is whitened by the full covariance: |r|^2 = dx^T Sigma^-1 dx
    g = torch.Generator().manual_seed(1)
    B = torch.randn(layout.size, layout.size, generator=g)
    cov = B @ B.T + torch.eye(layout.size)
    x = torch.randn(layout.size, generator=g)
    mean = torch.randn(layout.size, generator=g)
    r, J = GaussianPrior.over(layout, mean, cov).linearize(x, layout)
    assert float(r @ r) == pytest.approx(float((x - mean) @ torch.linalg.solve(cov, x - mean)), rel=1e-9)
    assert torch.allclose(J.T @ J, torch.linalg.inv(cov), rtol=1e-8, atol=1e-10)
    # and it follows the gauge: the pinned entries drop out (marginal)
    prob = CalibrationProblem(m2, data, NoiseModel.paper2(), None, blocks=[GaussianPrior.over(layout, mean, cov)])
    fix_gauge(prob)
    rr, JJ = prob.blocks[0].linearize(prob.layout.get(), prob.layout)
    assert JJ.shape == (prob.layout.size, prob.layout.size) and rr.shape == (prob.layout.size,)


def test_frozen_rows_keep_their_joint_errors(fanuc, tools_m):
    """fixed_rows: those rows' v stay at v0 (Schur step = dense step without their v); the rest are solved for."""
    _, data, model = _problem(fanuc, tools_m, poses=10, seed=40)
    R = len(data)
    fixed = torch.zeros(R, dtype=torch.bool)
    fixed[::3] = True
    v0 = 1e-5 * torch.randn(R, 6, generator=torch.Generator().manual_seed(2))
    prob = CalibrationProblem(model, data, NoiseModel.paper2(), Prior(), fixed_rows=fixed, v0=v0)
    x, v = prob.layout.get(), prob.v_zero()
    assert torch.equal(v, v0)
    f, A, C = prob.linearize(x, v)
    assert C[fixed].abs().max() == 0
    db, dv, _ = _schur_step(f, A, C, prob.w_v, v, prob.prior_precision, x - prob.prior_mean, 1e-3, v_free=prob.v_free)
    db_ref, dv_ref = _dense_step(f, A, C, prob.w_v, v, prob.prior_precision, x - prob.prior_mean, 1e-3, ~fixed)
    assert torch.allclose(db, db_ref, rtol=1e-7, atol=1e-12)
    assert torch.allclose(dv, dv_ref, rtol=1e-7, atol=1e-12) and dv[fixed].abs().max() == 0
    for method in ("lm", "lbfgs"):
        m = RobotModel(fanuc, tools_m, orders=1, backlash=True)
        res = fit(m, data, NoiseModel.paper2(), method=method, fixed_rows=fixed, v0=v0,
                  **({"max_iter": 2000} if method == "lbfgs" else {}))
        assert res.success, res.message
        assert torch.equal(res.v[fixed], v0[fixed])
        assert (res.v[~fixed] - v0[~fixed]).abs().max() > 1e-7


def test_noise_from_the_robot(fanuc, tools_m, caplog):
    nm = NoiseModel.from_robot(fanuc, sigma_m=7e-6)
    assert nm.sigma_m == 7e-6
    assert torch.allclose(nm.joint_var_fwd, fanuc.repeatability.var_fwd)
    assert torch.allclose(nm.joint_var_bwd, fanuc.repeatability.var_bwd)
    truth = randomize(RobotModel(fanuc, tools_m, orders=0), 3)
    data = simulate(truth, fanuc, 10, 4, None)
    with caplog.at_level(logging.INFO, logger="torchcal"):
        fit(RobotModel(fanuc, tools_m, orders=0), data, max_iter=2)
    assert fanuc.repeatability.source in caplog.text
    bare = Robot("bare_arm", fanuc.chain, fanuc.joint_map, "bare.urdf", None)
    with pytest.raises(ValueError, match="bare_arm"):
        fit(RobotModel(bare, tools_m, orders=0), data)


def test_fit_records_the_direction_coverage(fanuc, tools_m):
    truth = randomize(RobotModel(fanuc, tools_m, orders=0), 3)
    data = simulate(truth, fanuc, 10, 4, None)
    model = RobotModel(fanuc, tools_m, orders=0)
    fit(model, data, NoiseModel.paper2(), max_iter=2)
    assert model.coverage is not None
    assert int(model.coverage.counts.sum()) == len(data) * data.n_joints
