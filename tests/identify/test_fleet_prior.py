"""The fleet prior (issue #18): covariance estimators, the prior's posterior against closed forms, the greedy
Bayesian pose design against a brute-force reference (torchcal.identify.fleet_prior, torchcal.analysis.fleet_design)."""

from __future__ import annotations

from types import SimpleNamespace

import torchcal  # noqa: F401  first: OMP_WAIT_POLICY=PASSIVE

import numpy as np  # noqa: E402
import pytest  # noqa: E402
import torch  # noqa: E402

import torchcal.sim  # noqa: E402
from torchcal.analysis.fleet_design import (error_weight, greedy_design, known_group_gain, pose_jacobians,  # noqa: E402
                                            posterior_covariance, posterior_mean, predicted_mse)
from torchcal.analysis.identifiability import reduced_jacobian  # noqa: E402
from torchcal.identify import fit  # noqa: E402
from torchcal.identify.blocks import GaussianPrior  # noqa: E402
from torchcal.identify.fleet import fleet_prior  # noqa: E402
from torchcal.identify.fleet_prior import entry_groups, fleet_covariance, prior_from_parameters  # noqa: E402
from torchcal.identify.layout import ParameterLayout  # noqa: E402
from torchcal.identify.problem import CalibrationProblem, Prior  # noqa: E402

f64 = torch.float64


def spd(k, seed, scale=1.0):
    g = torch.Generator().manual_seed(seed)
    Q = torch.randn(k, k, generator=g, dtype=f64)
    return scale * (Q @ Q.T / k + 0.1 * torch.eye(k, dtype=f64))


# ------------------------------------------------------------------ linear-Gaussian closed forms
def test_posterior_mean_and_covariance_equal_the_information_form():
    g = torch.Generator().manual_seed(1)
    k, N, m = 7, 4, 3
    S0, mu = spd(k, 2), torch.randn(k, generator=g, dtype=f64)
    B, y = torch.randn(N, m, k, generator=g, dtype=f64), torch.randn(N, m, generator=g, dtype=f64)
    # independent reference (numpy, information form): (L0 + B^T B)^-1 (L0 mu + B^T y)
    Bn, L0 = B.reshape(-1, k).numpy(), np.linalg.inv(S0.numpy())
    P = np.linalg.inv(L0 + Bn.T @ Bn)
    ref = P @ (L0 @ mu.numpy() + Bn.T @ y.reshape(-1).numpy())
    np.testing.assert_allclose(posterior_mean(mu, S0, B, y).numpy(), ref, rtol=1e-10, atol=1e-12)
    np.testing.assert_allclose(posterior_covariance(S0, B).numpy(), P, rtol=1e-9, atol=1e-12)
    assert torch.equal(posterior_covariance(S0, B[:0]), S0)
    W = torch.randn(5, k, generator=g, dtype=f64)
    assert float(predicted_mse(posterior_covariance(S0, B), W)) == pytest.approx(np.trace(W.numpy() @ P @ W.numpy().T),
                                                                                 rel=1e-10)


def test_fit_with_the_fleet_prior_is_the_posterior_mode():
    """A real robot fit (torchcal.fit with the GaussianPrior block, no other prior, no gauge fixing) lands on the
    mode that an independent Gauss-Newton iteration of the closed-form linear-Gaussian posterior mean reaches."""
    robot = torchcal.load_robot("fanuc_lrmate200i")
    tools = torch.tensor([[0.033, 0.058, 0.161], [0.057, -0.034, 0.161]], dtype=f64)
    noise = torchcal.NoiseModel(5e-6, torch.zeros(6, dtype=f64), torch.zeros(6, dtype=f64))  # no joint errors
    truth = torchcal.TruthRobot.fanuc_paper2(robot, tools, 3)
    q = torchcal.sim.quasi_random_commands(robot.joint_map.limits, 12, 3)  # 72 residuals: fewer than parameters
    data = torchcal.simulate(truth, q, [0, 1], noise, 3)

    def make():
        return torchcal.RobotModel(robot, tools, orders=2)

    layout = ParameterLayout(make())
    P = layout.size
    assert P > 72
    # a synthetic "fleet" of 40 units around a mean of industrial size -> the prior over every entry
    g = torch.Generator().manual_seed(4)
    base = Prior().sigma(layout)
    X = 1e-2 * base * torch.randn(40, P, generator=g, dtype=f64) + 2e-2 * base * torch.randn(P, generator=g, dtype=f64)
    parts = prior_from_parameters(X, torch.ones(40, P, dtype=torch.bool), layout.names(), base)
    assert parts.names == layout.names() and bool(parts.free.all())
    model = make()
    ParameterLayout(model).set(parts.mean)
    fit(model, data, noise, prior=None, blocks=[GaussianPrior(parts.names, parts.mean, parts.cov)], gauge=False,
        ftol=1e-14, xtol=1e-14)
    x_fit = ParameterLayout(model).get()
    # reference: x <- posterior mean of the model linearized at x (y = A x0 - f0), repeated to convergence
    ref = make()
    prob = CalibrationProblem(ref, data, noise, None)
    x = parts.mean.clone()
    for _ in range(6):
        f, A, C = prob.linearize(x, prob.v_zero())
        At, ft = reduced_jacobian(A, C, prob.w_v, f)
        x = posterior_mean(parts.mean, parts.cov, At, (At @ x) - ft)
    scale = float((x - parts.mean).norm())
    assert float((x_fit - x).norm()) <= 1e-5 * scale


# ------------------------------------------------------------------ covariance estimators
def test_shrunk_method_is_the_previous_fleet_prior():
    """fleet_prior's default (method 'shrunk') is unchanged: the same mean, covariance and floor as before."""
    robot = torchcal.load_robot("fanuc_lrmate200i")
    model = torchcal.RobotModel(robot, torch.zeros(1, 3, dtype=f64), orders=1)
    layout = ParameterLayout(model)
    P = layout.size
    g = torch.Generator().manual_seed(0)
    base = Prior().sigma(layout)
    X = base * torch.randn(12, P, generator=g, dtype=f64) * torch.rand(P, generator=g, dtype=f64) * 1e-2
    keep = torch.ones(12, P, dtype=torch.bool)
    keep[:, :3] = False
    X[:, :3] = 0.0
    out = SimpleNamespace(batch=SimpleNamespace(x=X, keep=keep, names=layout.names()), layout=layout)
    block, mean = fleet_prior(out, exclude=[5])
    use = [m for m in range(12) if m != 5]
    Z = X[use][:, 3:]
    cov, _ = _shrunk_covariance(Z)  # the implementation before fleet_prior's methods (below, as it was)
    cov = cov + torch.diag(((base[3:] * 1e-3).pow(2) - cov.diagonal()).clamp(min=0.0))
    assert block.names == layout.names()[3:]
    torch.testing.assert_close(block.cov, cov, rtol=1e-12, atol=0.0)
    torch.testing.assert_close(mean[3:], Z.mean(0))
    assert bool((mean[:3] == 0).all())
    # pin_gauge: every entry covered, the pinned ones tight at zero and uncorrelated
    block, _ = fleet_prior(out, exclude=[5], pin_gauge=True)
    assert block.names == layout.names()
    torch.testing.assert_close(block.cov[3:, 3:], cov, rtol=1e-12, atol=0.0)
    torch.testing.assert_close(block.cov[:3, :3].diagonal(), (1e-6 * base[:3]).pow(2))
    assert bool((block.cov[:3, 3:] == 0).all()) and bool((block.mean[:3] == 0).all())


def test_ledoit_wolf_against_the_papers_formula():
    g = torch.Generator().manual_seed(5)
    M, k = 15, 9
    Z = torch.randn(M, k, generator=g, dtype=f64) @ torch.randn(k, k, generator=g, dtype=f64) * torch.logspace(-5, -2, k, dtype=f64)
    cov, info = fleet_covariance(Z, "ledoit-wolf")
    # reference (numpy, Ledoit & Wolf 2004 Lemma 3.2-3.4, a loop over samples) on the standardized data
    Zn = Z.numpy()
    Y = (Zn - Zn.mean(0)) / Zn.std(0, ddof=1)
    S = Y.T @ Y / M
    mu = np.trace(S) / k
    d2 = np.sum((S - mu * np.eye(k)) ** 2)
    b2 = sum(np.sum((np.outer(y, y) - S) ** 2) for y in Y) / M ** 2
    lam = min(b2, d2) / d2
    Cs = lam * mu * np.eye(k) + (1 - lam) * S
    Rs = Cs / np.sqrt(np.outer(np.diag(Cs), np.diag(Cs)))
    sd = Zn.std(0, ddof=1)
    assert info["weight"] == pytest.approx(lam, rel=1e-10)
    np.testing.assert_allclose(cov.numpy(), Rs * np.outer(sd, sd), rtol=1e-9, atol=0)


@pytest.mark.parametrize("method", ["shrunk", "ledoit-wolf", "factor"])
def test_estimators_keep_the_sample_variances_and_are_positive_definite_with_few_units(method):
    g = torch.Generator().manual_seed(6)
    M, k = 10, 30  # fewer units than parameters: the sample covariance is singular
    L = torch.randn(k, 3, generator=g, dtype=f64)
    Z = (torch.randn(M, 3, generator=g, dtype=f64) @ L.T + 0.1 * torch.randn(M, k, generator=g, dtype=f64)) * 1e-3
    cov, info = fleet_covariance(Z, method)
    torch.testing.assert_close(cov.diagonal(), Z.var(0), rtol=1e-9, atol=0.0)
    assert float(torch.linalg.eigvalsh(cov).min()) > 0
    if method == "factor":
        assert 1 <= info["rank"] <= M - 1
        # rank M - 1 with no floor reproduces the sample covariance
        full, _ = fleet_covariance(Z, "factor", rank=M - 1)
        assert float(torch.linalg.eigvalsh(full).min()) > 0
    with pytest.raises(ValueError, match="singular"):
        fleet_covariance(Z, "sample")


def test_block_method_is_ledoit_wolf_per_group_and_zero_across():
    g = torch.Generator().manual_seed(15)
    M, k = 12, 10
    Z = torch.randn(M, k, generator=g, dtype=f64) @ torch.randn(k, k, generator=g, dtype=f64)
    groups = [torch.tensor([0, 2, 4, 6]), torch.tensor([1, 3, 5]), torch.tensor([7, 8, 9])]
    cov, info = fleet_covariance(Z, "block", groups=groups)
    for gi in groups:
        ref, _ = fleet_covariance(Z[:, gi], "ledoit-wolf")
        torch.testing.assert_close(cov[gi][:, gi], ref, rtol=1e-12, atol=0.0)
    assert float(cov[0, 1]) == 0.0 and float(cov[3, 9]) == 0.0 and len(info["weights"]) == 3
    with pytest.raises(ValueError, match="partition"):
        fleet_covariance(Z, "block", groups=groups[:2])
    assert [t.tolist() for t in entry_groups(["joint1.a", "base.x", "joint1.b", "tool0.dx"])] == [[0, 2], [1], [3]]


def test_sample_method_with_many_units():
    g = torch.Generator().manual_seed(7)
    Z = torch.randn(50, 4, generator=g, dtype=f64)
    cov, _ = fleet_covariance(Z, "sample")
    np.testing.assert_allclose(cov.numpy(), np.cov(Z.numpy().T), rtol=1e-12)


# ------------------------------------------------------------------ greedy Bayesian design
def brute_force_step(B, L0, chosen, W, criterion):
    """Every unchosen candidate's criterion with the information form (numpy inverses, no Woodbury)."""
    Bn, info = B.numpy(), L0.copy()
    for c in chosen:
        info += Bn[c].T @ Bn[c]
    vals = {}
    for c in range(Bn.shape[0]):
        if c in chosen:
            continue
        Ic = info + Bn[c].T @ Bn[c]
        vals[c] = np.trace(W @ np.linalg.inv(Ic) @ W.T) if criterion == "A" else np.linalg.slogdet(Ic)[1]
    return vals


@pytest.mark.parametrize("criterion", ["A", "D"])
def test_greedy_design_against_brute_force(criterion):
    g = torch.Generator().manual_seed(8)
    N, m, k, count = 30, 3, 8, 6
    B = torch.randn(N, m, k, generator=g, dtype=f64) * torch.rand(N, 1, 1, generator=g, dtype=f64)
    S0 = spd(k, 9, scale=0.5)
    W = torch.randn(4, k, generator=g, dtype=f64)
    pick, obj = greedy_design(B, S0, count, W, criterion)
    assert pick.shape == (count,) and len(set(pick.tolist())) == count
    L0, Wn = np.linalg.inv(S0.numpy()), W.numpy()
    base = np.linalg.slogdet(L0)[1]
    if criterion == "A":
        assert float(obj[0]) == pytest.approx(np.trace(Wn @ S0.numpy() @ Wn.T), rel=1e-10)
        assert bool((obj[1:] <= obj[:-1]).all())  # never increases
    else:
        assert float(obj[0]) == 0.0 and bool((obj[1:] >= obj[:-1]).all())
    for i in range(count):
        vals = brute_force_step(B, L0, pick[:i].tolist(), Wn, criterion)
        best = min(vals, key=vals.get) if criterion == "A" else max(vals, key=vals.get)
        assert int(pick[i]) == best
        expect = vals[best] if criterion == "A" else vals[best] - base
        assert float(obj[i + 1]) == pytest.approx(expect, rel=1e-8, abs=1e-12)


def test_greedy_design_start_and_plain_a_optimality():
    g = torch.Generator().manual_seed(10)
    N, m, k = 20, 2, 5
    B = torch.randn(N, m, k, generator=g, dtype=f64)
    S0 = spd(k, 11)
    start = torch.tensor([3, 7])
    pick, obj = greedy_design(B, S0, 4, None, "A", start=start)
    assert not set(pick.tolist()) & {3, 7}
    assert float(obj[0]) == pytest.approx(float(posterior_covariance(S0, B[start]).trace()), rel=1e-10)
    assert float(obj[-1]) == pytest.approx(float(posterior_covariance(S0, B[torch.cat([start, pick])]).trace()), rel=1e-8)
    with pytest.raises(ValueError):
        greedy_design(B, S0, N + 1)


def test_pose_jacobians_group_rows_and_marginalize_joint_errors():
    g = torch.Generator().manual_seed(12)
    R, d, k, n = 6, 3, 4, 2
    A, C = torch.randn(R, d, k, generator=g, dtype=f64), torch.randn(R, d, n, generator=g, dtype=f64)
    w_v = torch.rand(R, n, generator=g, dtype=f64) + 0.5
    rows = torch.tensor([[0, 3], [1, 4], [2, 5]])  # tool-major rows: pose p has rows p and p + 3
    B = pose_jacobians(A, C, w_v, rows)
    assert B.shape == (3, 2 * d, k)
    for p in range(3):
        # the Schur complement of the pose's rows' normal matrix, [A C] with the v prior, numpy
        H = np.zeros((k, k))
        for r in rows[p].tolist():
            a, c = A[r].numpy(), C[r].numpy()
            Hvv = c.T @ c + np.diag(w_v[r].numpy())
            H += a.T @ a - a.T @ c @ np.linalg.solve(Hvv, c.T @ a)
        np.testing.assert_allclose((B[p].T @ B[p]).numpy(), H, rtol=1e-10, atol=1e-12)


def test_error_weight_and_group_gain():
    g = torch.Generator().manual_seed(13)
    k = 6
    G = torch.randn(30, k, generator=g, dtype=f64)
    W = error_weight(G)
    cov = spd(k, 14)
    assert float(predicted_mse(cov, W)) == pytest.approx(float((G @ cov @ G.T).trace()) / 10, rel=1e-10)
    gain = known_group_gain(cov, W, {"a": [0, 1], "all": list(range(k)), "none": []})
    assert gain["all"] == pytest.approx(float(predicted_mse(cov, W)), rel=1e-10)  # knowing everything: no error left
    assert gain["none"] == 0.0
    # reference: the conditional covariance with group a known, explicitly
    c = cov.numpy()
    cond = c - c[:, :2] @ np.linalg.solve(c[:2, :2], c[:2, :])
    Wn = W.numpy()
    assert gain["a"] == pytest.approx(np.trace(Wn @ c @ Wn.T) - np.trace(Wn @ cond @ Wn.T), rel=1e-9)


def _shrunk_covariance(Z: torch.Tensor) -> tuple[torch.Tensor, float]:
    """Covariance (k, k) of the rows of Z (M, k), shrunk towards its diagonal (Schaefer and Strimmer 2005,
    target D: the optimal weight on the diagonal from the sampling variance of the correlations) -> (cov, weight).
    With fewer units than parameters the sample covariance is singular; the shrunk one is not."""
    M = Z.shape[0]
    Zc = Z - Z.mean(0)
    sd = Zc.pow(2).sum(0).div(M - 1).sqrt().clamp(min=1e-300)
    Y = Zc / sd
    W = Y[:, :, None] * Y[:, None, :]  # (M, k, k)
    Wm = W.mean(0)
    R = Wm * M / (M - 1)
    var_r = (W - Wm).pow(2).sum(0) * M / (M - 1) ** 3
    off = ~torch.eye(Z.shape[1], dtype=torch.bool, device=Z.device)
    lam = float((var_r[off].sum() / R[off].pow(2).sum().clamp(min=1e-300)).clamp(0.0, 1.0))
    Rs = (1.0 - lam) * R
    Rs.diagonal().fill_(1.0)
    return Rs * sd[:, None] * sd[None, :], lam


def _tension_units(fanuc, tools_m, spread, count, seed, damage=None):
    """Units drawn from a known Gaussian fleet N(mu, S) (S diagonal: ``spread`` x the default prior's sigmas),
    each measured on 30 poses with the noise model's own scatter and fitted under that prior: prior_tension of
    each (damage: (entry name, sigmas) added to every unit's draw). spread: 1 is 1 mrad / 0.1 mm."""
    from conftest import random_commands

    from torchcal.identify import CalibrationProblem, NoiseModel
    from torchcal.identify.blocks import GaussianPrior
    from torchcal.identify.fleet_prior import prior_tension
    from torchcal.identify.layout import ParameterLayout
    from torchcal.models.robot import RobotModel

    make = lambda: RobotModel(fanuc, tools_m, orders=1, backlash=False)  # noqa: E731
    layout = ParameterLayout(make())
    angle = torch.tensor([k == "angle" for k in layout.kinds()])
    sigma = torch.where(angle, 1e-3, 1e-4).to(torch.float64) * spread  # rad, m: a fleet's spread of errors
    g = torch.Generator().manual_seed(seed)
    mu = sigma * torch.randn(sigma.shape, generator=g, dtype=torch.float64)
    block = GaussianPrior(layout.names(), mu, torch.diag(sigma ** 2))
    noise = NoiseModel.from_robot(fanuc, 5e-6)
    out = []
    for k in range(count):
        truth = make()
        x = mu + sigma * torch.randn(sigma.shape, generator=g, dtype=torch.float64)
        if damage is not None:
            i = layout.names().index(damage[0])
            x[i] += damage[1] * sigma[i]
        ParameterLayout(truth).set(x)
        q = random_commands(fanuc, 30, seed).repeat_interleave(3, 0)  # one program: one expectation
        tool = torch.arange(90) % 3
        v = torch.randn(q.shape, generator=g, dtype=torch.float64) * noise.joint_variance(torch.zeros_like(q)).sqrt()
        with torch.no_grad():
            xyz = truth.points(q, tool, None, v) + 5e-6 * torch.randn(90, 3, generator=g, dtype=torch.float64)
        data = torchcal.Measurements.from_tensors(q, tool, xyz)
        model = make()
        ParameterLayout(model).set(mu.clone())
        res = fit(model, data, noise, None, blocks=[block], gauge=False)
        assert res.success
        problem = CalibrationProblem(model, data, noise, None)
        out.append(prior_tension(block, problem, problem.layout.get(), res.v))
    return out


def test_prior_tension_is_its_expectation_for_a_unit_like_the_fleet(fanuc, tools_m):
    """Units drawn from the prior itself: d^2 averages its expectation k - tr(S^-1 S_post) (the linear Gaussian
    result; the robot is near-linear at this size); the expectation lies between 0 and the k entries and grows
    with the data's information over the fleet's spread. A unit whose joint 3 transmission error grows over its range 12
    sigmas beyond the fleet's (a damaged gearbox) lies far beyond it, with that joint named first."""
    from torchcal.identify.fleet_prior import TENSION_WARN

    units = _tension_units(fanuc, tools_m, 1.0, 16, 1)
    d2 = torch.tensor([t.d2 for t in units])
    E, sd = units[0].expected, units[0].sd  # one program for all: the same expectation
    assert all(abs(t.expected - E) < 0.02 * E for t in units)  # linearized at each unit's own solution
    assert abs(float(d2.mean()) - E) < 3.0 * sd / 16 ** 0.5, (float(d2.mean()), E, sd)  # the mean of 16 draws
    assert 0.5 * sd < float(d2.std()) < 1.6 * sd, (float(d2.std()), sd)  # and their scatter
    k = 6 * 6 * 2 + 6 + 9
    assert all(0.0 < t.expected < k and t.sd > 0.0 for t in units)
    tight = _tension_units(fanuc, tools_m, 0.1, 2, 1)  # a fleet 10x tighter: the data see fewer directions
    assert max(t.expected for t in tight) < min(t.expected for t in units)
    (bad,) = _tension_units(fanuc, tools_m, 1.0, 1, 2, damage=("joint3.eps_z.c1", 12.0))
    assert bad.ratio > TENSION_WARN and bad.groups[0][0] == "joint3", (bad.ratio, bad.groups[:3])
