"""The compiled damped least squares (torchcal/compensate/fused_damped.py) against the batched torch solver it
replaces on the CPU, and its pieces against torch: the residual and its Jacobian, the linear solve."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch
from conftest import assert_reachable_alike
from hypothesis import given, settings
from hypothesis import strategies as st

from torchcal.compensate import fused
from torchcal.compensate.damped import damped_least_squares, pose_residual, residual_jacobian
from torchcal.compensate.kernel import FlangeKernel
from torchcal.compensate.newton import nominal_sigma_min

pytestmark = pytest.mark.skipif(not fused.HAVE_NUMBA, reason="the compiled pass needs numba")


def _solve_both(model, q0, target, s, **kw):
    a = damped_least_squares(model, q0, target, s, kernel=FlangeKernel(model, fused=True), **kw)
    b = damped_least_squares(model, q0, target, s, kernel=FlangeKernel(model, fused=False), **kw)
    return a, b


@pytest.fixture(scope="module")
def problem(damped_problem):
    return damped_problem


def test_reachable_targets_same_solutions(problem):
    model, q, s, T, _ = problem
    assert_reachable_alike(*_solve_both(model, q, T, s), model, q)


@pytest.mark.parametrize("bounded", [False, True])
def test_unreachable_and_bounded_rows_same_verdicts(problem, bounded):
    """Rows out of reach end at a stationary point (or, bounded, at the box): the same verdict as the torch
    solver for (nearly) every row, at the same residual. Trajectories that wander over a flat cost can part after
    a rounding difference (LAPACK's LU there, Gaussian elimination here): at most 1 % of the rows."""
    model, q, s, _, far = problem
    kw = dict(q_ref=q, max_step=math.radians(5), max_correction=math.radians(5), stop_at_bound=True, max_iter=20) \
        if bounded else {}
    a, b = _solve_both(model, q, far, s, **kw)
    same = (a.converged == b.converged) & (a.blocked == b.blocked) & (a.stationary == b.stationary)
    assert float(same.double().mean()) >= 0.99
    flagged = same & ~a.converged
    assert int(flagged.sum()) > 100
    assert int((a.stationary | a.blocked).sum()) > 100
    rel = (a.residual[flagged] - b.residual[flagged]).abs() / b.residual[flagged]
    assert float(rel.median()) < 1e-9


def test_tikhonov_and_bounds_follow_the_torch_solver(problem):
    """The first, damped pass of compensate (lam > 0, loose tolerance): the same iterates."""
    model, q, s, T, _ = problem
    kw = dict(q_ref=q, lam=1e-3, max_step=math.radians(5), max_correction=math.radians(5), stop_at_bound=True,
              tol=1e-8, max_iter=20)
    a, b = _solve_both(model, q, T, s, **kw)
    same = (a.converged == b.converged) & (a.blocked == b.blocked) & (a.stationary == b.stationary)
    assert float(same.double().mean()) >= 0.99
    clear = same & (nominal_sigma_min(model, q) > 0.02)
    assert float((a.q[clear] - b.q[clear]).abs().median()) < 1e-12


@settings(max_examples=30, deadline=None)
@given(st.integers(0, 10**6), st.booleans())
def test_residual_rows_match_torch(seed, near):
    from torchcal.compensate.fused_damped import residual_rows
    from torchcal.kinematics.transforms import so3_exp

    g = torch.Generator().manual_seed(seed)
    f64 = torch.float64
    w = torch.randn(2, 3, generator=g, dtype=f64) * (0.3 if near else 2.0)
    R = so3_exp(w)
    p = torch.randn(2, 3, generator=g, dtype=f64)
    J = torch.randn(1, 6, 6, generator=g, dtype=f64)
    length = float(torch.rand(1, generator=g, dtype=f64)) + 0.1
    de_t, OR = pose_residual(R[:1], p[:1], R[1:], p[1:])
    Jr_t = residual_jacobian(de_t, OR, J, length)
    r, Jr, de = np.empty(6), np.empty((6, 6)), np.empty(6)
    tr = residual_rows(R[0].numpy()[..., None], p[0].numpy()[:, None], R[1].numpy()[..., None],
                       p[1].numpy()[:, None], 0, J[0].numpy()[..., None], length, r, Jr, de)
    np.testing.assert_allclose(de, de_t[0].numpy(), rtol=0, atol=1e-14)
    np.testing.assert_allclose(r[3:], length * de_t[0, 3:].numpy(), rtol=0, atol=1e-14)
    np.testing.assert_allclose(Jr, Jr_t[0].numpy(), rtol=0, atol=1e-12)
    assert tr == pytest.approx(float(OR[0].trace()), abs=1e-14)


@settings(max_examples=40, deadline=None)
@given(st.integers(0, 10**6), st.floats(-6, 6))
def test_solve_lu_matches_torch(seed, log_scale):
    from torchcal.compensate.fused_damped import solve_lu

    g = torch.Generator().manual_seed(seed)
    A = torch.randn(6, 6, generator=g, dtype=torch.float64) * 10.0 ** log_scale
    x = torch.randn(6, generator=g, dtype=torch.float64)
    out = x.numpy().copy()
    assert solve_lu(A.numpy(), out, np.empty((6, 7)))
    ref = torch.linalg.solve(A, x).numpy()
    An = A.numpy()
    # a backward-stable solve: its residual is rounding-sized (whatever the conditioning), and it is LAPACK's answer
    # where the system is well conditioned
    assert np.abs(An @ out - x.numpy()).max() <= 1e-12 * (np.abs(An).max() * np.abs(out).max() + 1.0)
    if np.linalg.cond(An) < 1e6:
        np.testing.assert_allclose(out, ref, rtol=1e-8, atol=1e-12 * np.abs(ref).max())
    S = A.clone()
    S[3] = 0.0  # singular: refused, as torch.linalg.solve_ex's info != 0
    assert not solve_lu(S.numpy(), x.numpy().copy(), np.empty((6, 7)))
