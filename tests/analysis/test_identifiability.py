"""Identifiability and Laplace uncertainty: dense cross-checks, null directions, Monte Carlo."""

import matplotlib

matplotlib.use("Agg")

import pytest
import torch
from torch.func import functional_call

from conftest import random_commands, randomize
from torchcal.analysis.identifiability import (
    identifiability,
    joint_sweeps,
    plot_position_std,
    position_std_sweeps,
    reduced_jacobian,
)
from torchcal.identify import CalibrationProblem, NoiseModel, Prior
from torchcal.core.measurements import Measurements
from torchcal.models.robot import RobotModel


def simulate(truth, q, seed, noise, tools=(0, 1, 2)):
    """Measurements of ``truth`` at commands q (N, n) with every tool, with joint + tracker noise."""
    N = q.shape[0]
    s = torch.sign(torch.diff(torch.cat([torch.zeros(1, q.shape[1]), q]), dim=0))
    T = len(tools)
    qq, ss = q.repeat(T, 1), s.repeat(T, 1)
    tool = torch.tensor(tools).repeat_interleave(N)
    g = torch.Generator().manual_seed(seed)
    with torch.no_grad():
        v = torch.randn(qq.shape, generator=g) * noise.joint_variance(ss).sqrt()
        p = truth.points(qq, tool, ss, v) + torch.randn(qq.shape[0], 3, generator=g) * noise.sigma_m
    return Measurements(qq, tool, p, ss, torch.arange(N).repeat(T), torch.arange(1, len(qq) + 1), True, "sim")


@pytest.fixture(scope="module")
def small(fanuc, tools_m):
    model = randomize(RobotModel(fanuc, tools_m, orders=1, backlash=1), 4)
    data = simulate(model, random_commands(fanuc, 14, 5), 6, NoiseModel.paper2())
    return model, data


def dense_marginal_covariance(model, data, noise, prior, layout, v):
    """(J^T J + W)^-1 over (x, v) by autograd + dense inversion, then the x block (marginal)."""
    full = CalibrationProblem(model, data, noise, prior)
    where = {name: i for i, name in enumerate(full.layout.names())}
    prior_precision = full.prior_precision[[where[name] for name in layout.names()]]
    x0 = layout.get()
    R, n = data.q.shape
    P = x0.numel()

    def residual(z):
        x, vv = z[:P], z[P:].reshape(R, n)
        p = functional_call(model, layout.as_dict(x), (data.q, data.tool, data.direction, vv))
        return ((p - data.xyz) / noise.sigma_m).reshape(-1)

    J = torch.autograd.functional.jacobian(residual, torch.cat([x0, v.reshape(-1)]), vectorize=True)
    W = torch.cat([prior_precision, noise.joint_variance(data.direction).reshape(-1).reciprocal()])
    H = J.T @ J + torch.diag(W)
    return torch.linalg.inv(H)[:P, :P], J[:, :P], J[:, P:]


def test_covariance_equals_dense_marginal_inverse(small):
    model, data = small
    noise, prior = NoiseModel.paper2(), Prior()
    v = 1e-5 * torch.randn(data.q.shape, generator=torch.Generator().manual_seed(7))
    before = {k: p.detach().clone() for k, p in model.named_parameters()}
    res = identifiability(model, data, noise, prior, v=v)
    for k, p in model.named_parameters():  # the analysis leaves the model as it found it
        assert torch.equal(p, before[k])
    assert res.pinned and not set(res.pinned) & set(res.names)
    cov, _, _ = dense_marginal_covariance(model, data, noise, prior, res.layout, v)
    scale = torch.diagonal(cov).sqrt()
    rel = (res.covariance - cov) / (scale[:, None] * scale[None, :])
    assert rel.abs().max() < 1e-6
    assert torch.allclose(res.std, scale, rtol=1e-6)


def test_reduced_jacobian_gram_is_lm_schur_complement(small):
    model, data = small
    prob = CalibrationProblem(model, data, NoiseModel.paper2(), Prior())
    f, A, C = prob.linearize(prob.layout.get(), prob.v_zero())
    R, _, P = A.shape
    At = reduced_jacobian(A, C, prob.w_v).reshape(-1, P)
    # lm.py's Schur complement, written out densely: H_bb - H_bv H_vv^-1 H_vb with a block-diagonal H_vv
    Af = A.reshape(-1, P)
    Cd = torch.block_diag(*C)  # (3R, nR)
    Hvv = Cd.T @ Cd + torch.diag(prob.w_v.reshape(-1))
    S = Af.T @ Af - Af.T @ Cd @ torch.linalg.solve(Hvv, Cd.T @ Af)
    assert torch.allclose(At.T @ At, S, rtol=1e-9, atol=1e-9 * S.abs().max())


def test_redundant_pair_is_reported_and_really_undetermined(fanuc, tools_m, small):
    """Without gauge fixing, base eps_z and joint 1's constant eps_z (same axis) are one combination."""
    model, data = small
    res = identifiability(model, data, NoiseModel.paper2(), Prior(), gauge=False)
    assert res.pinned == []
    names = {"base.eps_z", "joint1.eps_z.c0"}
    hits = [c for c in res.undetermined if names <= set(c.names())]
    assert hits
    # the pure pair (base eps_z = -joint 1's constant eps_z) lies (nearly: the other errors tilt it by
    # ~1e-3) in the span of the reported undetermined directions
    U = torch.stack([c.direction for c in res.undetermined], 1)
    pair = torch.zeros(len(res.names))
    pair[res.names.index("base.eps_z")], pair[res.names.index("joint1.eps_z.c0")] = 1.0, -1.0
    resid = pair - U @ torch.linalg.lstsq(U, pair[:, None]).solution[:, 0]
    assert resid.norm() < 0.02 * pair.norm()
    # independent check: moving the parameters along a reported combination leaves every predicted
    # point unchanged (to first order: central differences), moving one of its members alone does not
    q = random_commands(fanuc, 20, 11)
    tool = torch.arange(20) % 3
    layout, x = res.layout, res.x

    def points(dx):
        return functional_call(model, layout.as_dict(x + dx), (q, tool)).detach()

    d = 1e-5
    single = torch.zeros(len(res.names))
    single[res.names.index("base.eps_z")] = 1.0
    one = (points(d * single) - points(-d * single)).norm(dim=1).max()
    assert one > 1e-6
    exact = [c for c in hits if c.singular_value < 1e-12]  # the others are near-redundant (s ~ 1e-7)
    assert exact
    for c in exact:
        moved = (points(d * c.direction) - points(-d * c.direction)).norm(dim=1).max()
        assert moved < 1e-5 * one
    # with the gauge pinned, fewer combinations are left undetermined, and none names a pinned entry; the gauge
    # is judged at zero joint errors, where the families are exactly redundant, so it pins at least every
    # combination that is exactly undetermined at this (randomized) model
    pinned = identifiability(model, data, NoiseModel.paper2(), Prior())
    assert len(pinned.pinned) >= len(exact)
    assert len(pinned.undetermined) <= max(0, len(res.undetermined) - len(pinned.pinned) + 1)
    assert not set(pinned.pinned) & {n for c in pinned.undetermined for n in c.names()}


def test_singular_values_and_correlations_are_consistent(small):
    model, data = small
    res = identifiability(model, data, NoiseModel.paper2(), Prior(), gauge=False)
    # Weyl: the prior rows add Λ to S, so every eigenvalue s^2 moves up by between min Λ and max Λ
    lam = CalibrationProblem(model, data, NoiseModel.paper2(), Prior()).prior_precision
    gap = res.singular_values_prior**2 - res.singular_values**2
    assert (gap >= lam.min() * (1 - 1e-6) - 1e-9 * res.singular_values[0] ** 2).all()
    assert (gap <= lam.max() * (1 + 1e-6) + 1e-9 * res.singular_values[0] ** 2).all()
    assert (res.relative_singular_values[res.rank :] < res.rtol).all()
    assert {(p.first, p.second) for p in res.correlated} >= {("joint1.eps_x.c0", "base.eps_x")} or any(
        {p.first, p.second} == {"joint1.eps_x.c0", "base.eps_x"} for p in res.correlated
    )
    for p in res.correlated:
        i, j = res.names.index(p.first), res.names.index(p.second)
        c = res.covariance[i, j] / (res.covariance[i, i] * res.covariance[j, j]).sqrt()
        assert abs(float(c)) > 0.95 and float(c) == pytest.approx(p.correlation, rel=1e-9)
    table = res.table()
    assert len(table) == len(res.names) and {r["unit"] for r in table} == {"deg", "mm"}
    s = res.summary()
    assert s["parameters"] == len(res.names) and s["undetermined"]


def _mc_points(res, model, q, tool, S, scale, seed):
    """Tool points (S, B, 3) for S parameter draws x + scale * N(0, covariance), all draws at once."""
    lam, V = torch.linalg.eigh(res.covariance)
    z = torch.randn(S, lam.numel(), generator=torch.Generator().manual_seed(seed))
    xs = res.x + scale * (z * lam.clamp(min=0).sqrt()) @ V.T
    params, i = {}, 0  # (S, *shape) parameter tensors, free entries from the draws
    for name, p, m in res.layout.entries:
        k = int(m.sum())
        full = p.detach().expand((S,) + p.shape).clone()
        full[:, m] = xs[:, i : i + k]
        params[name] = full
        i += k
    return torch.vmap(lambda d: functional_call(model, d, (q, tool)))(params)


def test_point_std_matches_monte_carlo(fanuc, tools_m):
    model = randomize(RobotModel(fanuc, tools_m, orders=2, backlash=True), 8)
    noise = NoiseModel.paper2()
    data = simulate(model, random_commands(fanuc, 30, 9), 10, noise)
    q = random_commands(fanuc, 12, 12)
    tool = torch.arange(12) % 3
    # a prior tight enough that the Gaussian posterior stays in the model's linear regime
    res = identifiability(model, data, noise, Prior(1e-3, 1e-4, 1e-2, 1e-3))
    std = res.point_std(q, tool)
    p = _mc_points(res, model, q, tool, 3000, 1.0, 13)
    d = p - p.mean(0)
    mc = d.pow(2).sum(-1).mean(0).sqrt()
    assert ((mc / std) - 1).abs().max() < 0.1
    mc_cov = torch.einsum("sbi,sbj->bij", d, d) / p.shape[0]
    cov = res.point_covariance(q, tool)
    assert torch.allclose(torch.diagonal(mc_cov, dim1=1, dim2=2), torch.diagonal(cov, dim1=1, dim2=2), rtol=0.15)
    # default prior: the near-redundant combinations keep ~prior-wide (1e-2 rad) posteriors whose
    # second-order effect the linear propagation leaves out; scaled-down draws still match it
    res = identifiability(model, data, noise, Prior())
    std = res.point_std(q, tool)
    mc = (_mc_points(res, model, q, tool, 3000, 0.05, 14) / 0.05).var(0).sum(-1).sqrt()
    assert ((mc / std) - 1).abs().max() < 0.1


def test_std_grows_where_a_joint_range_has_no_data(fanuc, tools_m):
    model = randomize(RobotModel(fanuc, tools_m, orders=2, backlash=True), 14)
    noise = NoiseModel.paper2()
    q = random_commands(fanuc, 40, 15)
    full = simulate(model, q, 16, noise)
    lo, hi = fanuc.joint_map.limits[0]
    q_half = q.clone()
    q_half[:, 0] = lo + (q[:, 0] - lo) * 0.5  # joint 1 only in the lower half of its range
    half = simulate(model, q_half, 16, noise)
    r_full = identifiability(model, full, noise, Prior())
    r_half = identifiability(model, half, noise, Prior())
    test_q = random_commands(fanuc, 30, 17)
    test_q[:, 0] = lo + (hi - lo) * (0.8 + 0.2 * torch.rand(30, generator=torch.Generator().manual_seed(18)))
    tool = torch.zeros(30, dtype=torch.long)
    s_full, s_half = r_full.point_std(test_q, tool), r_half.point_std(test_q, tool)
    assert (s_half > 2.0 * s_full).all()
    # along a sweep of joint 1, the half-range model's std rises towards the unmeasured end
    home = fanuc.joint_map.limits.mean(1)
    qs, sw = position_std_sweeps(r_half, home, steps=21)
    assert torch.equal(qs, joint_sweeps(fanuc.joint_map.limits, home, 21))
    assert sw[0, -1] > 3 * sw[0, 5]
    assert torch.allclose(sw[0], r_half.point_std(qs[0], torch.zeros(21, dtype=torch.long)))


def test_plot_position_std_writes_png(tmp_path, small):
    model, data = small
    res = identifiability(model, data, NoiseModel.paper2(), Prior())
    fig = plot_position_std(res, tmp_path / "std.png", data=data, random_poses=200, steps=11)
    assert (tmp_path / "std.png").stat().st_size > 10_000
    assert len(fig.axes) == 6
    import matplotlib.pyplot as plt

    plt.close(fig)


def test_repeatability_adds_joint_noise(small, fanuc):
    model, data = small
    res = identifiability(model, data, NoiseModel.paper2(), Prior())
    q = random_commands(fanuc, 5, 19)
    tool = torch.zeros(5, dtype=torch.long)
    d = torch.ones(5, 6)
    c0, c1 = res.point_covariance(q, tool, d), res.point_covariance(q, tool, d, repeatability=True)
    _, J = model.point_jacobians(q, tool, d)
    expected = J["v"] @ torch.diag(NoiseModel.paper2().joint_var_fwd) @ J["v"].transpose(1, 2)
    assert torch.allclose(c1 - c0, expected, rtol=1e-9, atol=1e-24)
