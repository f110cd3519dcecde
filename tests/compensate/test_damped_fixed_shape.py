"""The damped least squares' fixed-shape loop (torchcal/compensate/damped_graph.py: finished rows frozen in place,
Cholesky solves; on a GPU replayed as CUDA graphs) against the eager loop that drops finished rows (LU solves),
run here on the CPU without graphs: the same verdicts and solutions to rounding, and rows that do not see each
other."""

from __future__ import annotations

import math

import pytest
import torch
from conftest import assert_reachable_alike, random_commands, randomize
from hypothesis import given, settings
from hypothesis import strategies as st

from torchcal.compensate.damped import damped_least_squares, spd_solve
from torchcal.compensate.kernel import FlangeKernel
from torchcal.models.robot import RobotModel


@settings(max_examples=40, deadline=None)
@given(st.integers(0, 10**6), st.integers(1, 7), st.floats(-6, 6))
def test_spd_solve_matches_lapack(seed, n, log_scale):
    g = torch.Generator().manual_seed(seed)
    J = torch.randn(9, n + 2, n, generator=g, dtype=torch.float64) * 10.0 ** log_scale
    A = J.transpose(1, 2) @ J + 1e-3 * 10.0 ** (2 * log_scale) * torch.eye(n, dtype=torch.float64)
    b = torch.randn(9, n, generator=g, dtype=torch.float64)
    x, ok = spd_solve(A, b)
    assert bool(ok.all())
    ref = torch.linalg.solve(A, b)
    assert torch.allclose(x, ref, rtol=1e-9, atol=1e-12 * float(ref.abs().max()))
    A[3] = -A[3]  # negative definite: refused, with a non-finite answer the caller discards
    x, ok = spd_solve(A, b)
    assert not bool(ok[3]) and bool(ok[torch.arange(9) != 3].all())
    assert not bool(torch.isfinite(x[3]).all())


@pytest.fixture(scope="module")
def problem(damped_problem):
    return damped_problem


def _both(model, q0, target, s, **kw):
    k = FlangeKernel(model, fused=False)
    return (damped_least_squares(model, q0, target, s, kernel=k, fixed_shape=True, **kw),
            damped_least_squares(model, q0, target, s, kernel=k, fixed_shape=False, **kw))


def test_reachable_targets_same_solutions(problem):
    model, q, s, T, _ = problem
    assert_reachable_alike(*_both(model, q, T, s), model, q)


@pytest.mark.parametrize("kind", ["unbounded", "bounded", "tikhonov"])
def test_flagged_rows_same_verdicts(problem, kind):
    """Out-of-reach rows end at a stationary point or at the box, as in the eager loop; trajectories over a flat
    cost may part after a rounding difference (Cholesky here, LU there): at most 1 % of the rows."""
    model, q, s, T, far = problem
    bounded = dict(q_ref=q, max_step=math.radians(5), max_correction=math.radians(5), stop_at_bound=True, max_iter=20)
    kw = {"unbounded": {}, "bounded": bounded, "tikhonov": dict(bounded, lam=1e-3, tol=1e-8)}[kind]
    a, b = _both(model, q, T if kind == "tikhonov" else far, s, **kw)
    same = (a.converged == b.converged) & (a.blocked == b.blocked) & (a.stationary == b.stationary)
    assert float(same.double().mean()) >= 0.99
    if kind != "tikhonov":
        flagged = same & ~a.converged
        assert int((a.stationary | a.blocked).sum()) > 100
        rel = (a.residual[flagged] - b.residual[flagged]).abs() / b.residual[flagged]
        assert float(rel.median()) < 1e-9
    it = (a.iterations - b.iterations)[same].abs()
    assert float((it <= 1).double().mean()) >= 0.99


def test_rows_do_not_see_each_other(problem):
    """A frozen row stays frozen and the others do not notice it: a row's answer is the same, bit for bit, whether
    its neighbours iterate on or are solved at once and frozen from the first iteration (a batch of the same size,
    so that every batched product takes the same code path)."""
    model, q, s, T, far = problem
    k = FlangeKernel(model, fused=False)
    pick = torch.zeros(q.shape[0], dtype=torch.bool)
    pick[torch.randperm(q.shape[0], generator=torch.Generator().manual_seed(3))[:57]] = True
    with torch.no_grad():
        at_start = model.flange(q, s, base=False)  # reached by the start itself
    for target in (T, far):
        full = damped_least_squares(model, q, target, s, kernel=k, fixed_shape=True)
        mixed = damped_least_squares(model, q, torch.where(pick[:, None, None], target, at_start), s, kernel=k,
                                     fixed_shape=True)
        assert bool(mixed.converged[~pick].all()) and int(mixed.iterations[~pick].max()) <= 2
        assert int(full.iterations[pick].min()) >= 2
        for f in ("q", "converged", "iterations", "pose_error", "step", "blocked", "stationary", "residual"):
            assert torch.equal(getattr(full, f)[pick], getattr(mixed, f)[pick]), f


def test_seven_axis_user_robot(iiwa, tools_m):
    """A 7-axis robot from a datasheet's DH (redundant: J^T J of rank 6, the damping makes the 7 x 7 solve
    definite): the fixed-shape loop reaches the targets the eager loop reaches, with the same verdicts."""
    model = randomize(RobotModel(iiwa, tools_m, orders=3, backlash=True), 2, rot=2e-3, trans=2e-4)
    q = random_commands(iiwa, 200, 4)
    s = torch.ones_like(q)
    with torch.no_grad():
        T = model.nominal_flange(q)
    a, b = _both(model, q, T, s)
    assert torch.equal(a.converged, b.converged) and float(a.converged.double().mean()) > 0.9
    assert float(a.residual[a.converged].max()) <= 1e-12
    # the redundant direction is free: the two loops may part along it by rounding, the poses they reach may not
    with torch.no_grad():
        Fa, Fb = model.flange(a.q, s, base=False), model.flange(b.q, s, base=False)
    assert float((Fa - Fb)[a.converged].abs().max()) < 1e-11


def test_failed_capture_falls_back_to_eager_iterations(problem, monkeypatch):
    """A CUDA graph capture that fails (another torch or CUDA than the one verified) warns and runs the same
    iterations eagerly: the answer is the graph-free loop's, bit for bit. torch.cuda is stood in for here (CPU),
    with a capture that refuses to start."""
    import contextlib

    from torchcal.compensate import damped_graph

    class Dummy:
        def __init__(self, *a, **k):
            pass

        def record(self, *a):
            pass

        def wait_stream(self, *a):
            pass

    @contextlib.contextmanager
    def refused(*a, **k):
        raise RuntimeError("operation not permitted when stream is capturing")
        yield

    model, q, s, T, far = problem
    k = FlangeKernel(model, fused=False)
    plain = damped_least_squares(model, q, far, s, kernel=k, fixed_shape=True)
    inner = damped_graph.solve_fixed_shape
    monkeypatch.setattr(damped_graph, "solve_fixed_shape", lambda *a, **kw: inner(*a, **{**kw, "graphs": True}))
    for name, value in (("Event", Dummy), ("Stream", Dummy), ("CUDAGraph", Dummy), ("graph", refused),
                        ("stream", lambda *a: contextlib.nullcontext()), ("current_stream", lambda *a: Dummy())):
        monkeypatch.setattr(torch.cuda, name, value)
    with pytest.warns(RuntimeWarning, match="could not be captured"):
        fell_back = damped_least_squares(model, q, far, s, kernel=k, fixed_shape=True)
    for f in ("q", "converged", "iterations", "pose_error", "step", "blocked", "stationary"):
        assert torch.equal(getattr(plain, f), getattr(fell_back, f)), f
