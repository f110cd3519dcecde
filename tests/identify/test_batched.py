"""The model batch dimension of identification: fit_batch against separate fits, per-model rows and noise."""

from __future__ import annotations

import pytest
import torch

from conftest import random_commands, randomize
from torchcal.identify import NoiseModel, Prior, fit
from torchcal.identify.batched import fit_batch
from torchcal.identify.structure_batch import fit_structures
from torchcal.identify.problem import row_errors
from torchcal.core.measurements import Measurements
from torchcal.models.robot import RobotModel


def _data(truth, robot, poses, seed, noise):
    q = random_commands(robot, poses, seed)
    s = torch.sign(torch.diff(torch.cat([torch.zeros(1, 6), q]), dim=0))
    qq, ss = q.repeat(3, 1), s.repeat(3, 1)
    tool = torch.arange(3).repeat_interleave(poses)
    g = torch.Generator().manual_seed(seed)
    with torch.no_grad():
        v = torch.randn(qq.shape, generator=g) * noise.joint_variance(ss).sqrt()
        p = truth.points(qq, tool, ss, v) + torch.randn(qq.shape[0], 3, generator=g) * noise.sigma_m
    return Measurements(qq, tool, p, ss, torch.arange(poses).repeat(3), torch.arange(1, len(qq) + 1), True, "sim")


@pytest.fixture(scope="module")
def setup(fanuc, tools_m):
    noise = NoiseModel.paper2()
    truth = randomize(RobotModel(fanuc, tools_m, orders=2, backlash=1), 41)
    data = _data(truth, fanuc, 50, 42, noise)
    val = _data(truth, fanuc, 20, 43, noise)
    return noise, data, val, lambda o, b=1: RobotModel(fanuc, tools_m, orders=o, backlash=b)


def test_batched_fits_equal_separate_fits(setup):
    """Each model of the batch follows the single-model solver's path: same cost, same iterations, same model."""
    noise, data, val, make = setup
    models = [make(o) for o in (0, 1, 2)]
    out = fit_batch(make(2), models, data, noise, Prior())
    for o, m, r in zip((0, 1, 2), models, out.results):
        alone = make(o)
        ra = fit(alone, data, noise, Prior())
        assert r.success and ra.success
        assert r.nit == ra.nit
        assert r.fun == pytest.approx(ra.fun, rel=1e-9)
        assert torch.allclose(row_errors(m, val), row_errors(alone, val), rtol=1e-6, atol=1e-12)
    # models converge on their own: the small one needed fewer iterations than the batch ran
    assert min(r.nit for r in out.results) < out.iterations


def test_rows_and_noise_per_model(setup):
    """A model fitting the first 30 poses with its own tracker sigma equals that fit on that subset alone."""
    noise, data, val, make = setup
    loose = NoiseModel(noise.sigma_m * 3, noise.joint_var_fwd, noise.joint_var_bwd)
    first = data.pose < 30
    models = [make(1), make(1)]
    out = fit_batch(make(1), models, data, [noise, loose], Prior(), rows=torch.stack([torch.ones_like(first), first]))
    alone = make(1)
    ra = fit(alone, data.subset(first), loose, Prior())
    assert out.results[1].fun == pytest.approx(ra.fun, rel=1e-9)
    assert torch.allclose(row_errors(models[1], val), row_errors(alone, val), rtol=1e-6, atol=1e-12)
    assert out.results[0].fun != pytest.approx(ra.fun, rel=1e-3)


def test_superset_may_be_one_of_the_models(setup):
    """Results are written without reading the superset back, so passing a model as its own superset is safe."""
    noise, data, val, make = setup
    models = [make(2), make(2)]
    with torch.no_grad():
        models[1].joint_errors.coef.normal_(0, 1e-4)  # another start
    fit_batch(models[0], models, data, noise, Prior())
    alone = make(2)
    fit(alone, data, noise, Prior())
    for m in models:
        assert torch.allclose(row_errors(m, val), row_errors(alone, val), rtol=1e-4, atol=1e-9)


def test_fit_structures_lands_at_the_separate_fits(setup):
    noise, data, val, make = setup
    models, out = fit_structures(lambda o: make(o), [0, 1, 2], data, noise, Prior())
    for o, m in zip((0, 1, 2), models):
        alone = make(o)
        fit(alone, data, noise, Prior())
        a, b = row_errors(m, val).mean(), row_errors(alone, val).mean()
        assert abs(float(a / b) - 1) < 5e-3


@pytest.mark.parametrize("seed", [0, 1])
def test_schur_steps_solve_the_full_damped_normal_equations(seed):
    """The batched step (joint errors eliminated per row in Woodbury form, both forms of M A) equals the solve
    of each model's whole damped system in parameters and joint errors, formed and solved densely."""
    from torchcal.identify.schur import inv3_sym, schur_steps
    from torchcal.kinematics.transforms import rowwise_matmul

    g = torch.Generator().manual_seed(seed)
    m, R, d, P, n = 3, 20, 3, 12, 6
    rnd = lambda *s: torch.randn(*s, generator=g, dtype=torch.float64)
    f, A, C, V, dx = rnd(m, R, d), rnd(m, R, d, P), rnd(m, R, d, n), rnd(m, R, n), rnd(m, P)
    w_v = torch.rand(m, R, n, generator=g, dtype=torch.float64) + 0.1
    lam = torch.rand(P, generator=g, dtype=torch.float64)
    mu = torch.rand(m, generator=g, dtype=torch.float64)
    keep = torch.rand(m, P, generator=g) > 0.25
    A = A * keep[:, None, None, :]
    db, dv, lin = schur_steps(f, A, C, w_v, V, lam, dx, mu, keep)
    assert torch.allclose(rowwise_matmul(inv3_sym(torch.eye(3, dtype=torch.float64) + C @ C.transpose(-1, -2)), A),
                          torch.linalg.inv(torch.eye(3, dtype=torch.float64) + C @ C.transpose(-1, -2)) @ A, atol=1e-12)
    for k in range(m):
        kf = keep[k].double()
        J = torch.cat([A[k].reshape(R * d, P), torch.block_diag(*C[k])], 1)
        H = J.T @ J
        H[:P, :P] += torch.diag(lam * kf)
        H[P:, P:] += torch.diag(w_v[k].reshape(-1))
        grad = J.T @ f[k].reshape(-1)
        grad[:P] += lam * kf * dx[k]
        grad[P:] += (w_v[k] * V[k]).reshape(-1)
        H = H + mu[k] * torch.diag(torch.diagonal(H))  # Marquardt's scaling
        H[:P, :P] += torch.diag(1.0 - kf)  # an entry the model lacks: unit diagonal, no gradient, no step
        step = -torch.linalg.solve(H, grad * torch.cat([kf, torch.ones(R * n, dtype=torch.float64)]))
        assert torch.allclose(db[k], step[:P], atol=1e-10)
        assert torch.allclose(dv[k].reshape(-1), step[P:], atol=1e-10)
        assert torch.allclose(lin[k].reshape(-1), f[k].reshape(-1) + J @ step, atol=1e-10)
