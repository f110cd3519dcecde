"""Paper I's constrained identification: the QP step, the slope-bounded fit, the sweep and the knee."""

import math

import numpy as np
import pytest
import torch

import torchcal
from conftest import XYZCB_TOOLS
import torchcal.sim
from torchcal.core.exceptions import TorchcalError
from torchcal.identify import NoiseModel, fit
from torchcal.identify.constrained import (ConstraintError, SlopePenalty, SweepResult, constraint_sweep,
                                           fit_constrained, pick_knee, solve_qp)
from torchcal.identify.layout import ParameterLayout
from torchcal.identify.slope import slope_norms, slope_points
from torchcal.models.machine import MachineModel
from torchcal.core.measurements import Measurements

TOOLS = XYZCB_TOOLS  # Paper I (32)



@pytest.fixture(autouse=True)
def _single_thread(one_thread):
    """Tiny tensors: torch's intra-op threads only contend on the shared 2-core machine."""


@pytest.fixture(scope="module")
def dataset(machine):
    """A known AP truth (order 3; a Z error steep in B, as Paper I's Figure 12), 60 commands x 2 tools."""
    truth = MachineModel(machine, TOOLS, orders=3)
    g = torch.Generator().manual_seed(0)
    with torch.no_grad():
        c = torch.randn(truth.axis_errors.coef.shape, generator=g) * 2e-5
        c[2, 4, 3] = 1e-4
        truth.axis_errors.coef.copy_(c)
        truth.base.twist.copy_(torch.randn(6, generator=g) * 1e-4)
    q = torchcal.sim.quasi_random_commands(machine.joint_map.limits, 60, 0)
    qq, tool = q.repeat(2, 1), torch.arange(2).repeat_interleave(60)
    with torch.no_grad():
        p = truth.points(qq, tool) + torch.randn(120, 3, generator=g) * 5e-6
    return truth, Measurements(qq, tool, p, torch.zeros_like(qq), torch.arange(60).repeat(2), torch.arange(1, 121), False, "sim")


def test_solve_qp_meets_the_kkt_conditions():
    g = torch.Generator().manual_seed(1)
    P, k = 6, 12
    L = torch.randn(P, P, generator=g)
    S = L @ L.T + torch.eye(P)
    rhs = torch.randn(P, generator=g) * 5
    G = torch.randn(k, P, generator=g)
    h = torch.rand(k, generator=g)
    db = solve_qp(S, rhs, G, h)
    assert float((G @ db - h).max()) <= 1e-10
    # KKT: S db - rhs = -G^T mu, mu >= 0 on the active rows only (non-negative least squares for mu)
    active = (G @ db - h).abs() < 1e-9
    from scipy.optimize import nnls

    mu, res = nnls(G[active].T.numpy(), -(S @ db - rhs).numpy())
    assert res < 1e-8 and int(active.sum()) > 0
    unconstrained = torch.linalg.solve(S, rhs)
    assert float((G @ unconstrained - h).max()) > 0  # the bound matters
    assert solve_qp(S, rhs, torch.cat([G[:1], -G[:1]]), torch.tensor([-1.0, -1.0])) is None  # infeasible


def test_constrained_fit_meets_the_bound_everywhere(machine, dataset, one_thread):
    truth, data = dataset
    noise = NoiseModel.from_robot(machine)
    free = MachineModel(machine, TOOLS, orders=3)
    r0 = fit_constrained(free, data, math.inf, noise, points=64)
    c = 0.5 * r0.max_slope_check
    model = MachineModel(machine, TOOLS, orders=3)
    res = fit_constrained(model, data, c, noise, points=64)
    assert res.success and res.c == c
    assert res.max_slope <= c * (1 + 1e-2) and res.max_slope_check <= c * (1 + 5e-2)
    fresh = slope_points(machine.joint_map.limits, 256, seed=12345)
    assert float(slope_norms(model, fresh).detach().max()) <= c * 1.05  # where nothing was measured too, C included
    assert res.fit.fun >= r0.fit.fun - 1e-6  # a bound cannot fit the data better
    assert res.penalty_points.shape[1] == 5 and isinstance(res.summary()["max_slope_mm"], float)


def test_penalty_block_jacobian(machine, dataset, one_thread):
    truth, data = dataset
    pts = slope_points(machine.joint_map.limits, 32, 3)
    c = 0.5 * float(slope_norms(truth, pts).detach().max())
    pen = SlopePenalty(truth, pts, c, weight=1.0 / c)
    layout = ParameterLayout(truth)
    x = layout.get()
    r, J = pen.linearize(x, layout)
    assert r.numel() > 0 and bool((r > 0).all())
    d = torch.randn(x.numel(), generator=torch.Generator().manual_seed(2)) * 1e-8
    r_plus, _ = pen.linearize(x + d, layout)
    r_minus, _ = pen.linearize(x - d, layout)
    assert r_plus.shape == r.shape == r_minus.shape
    assert torch.allclose((r_plus - r_minus) / 2, J @ d, rtol=1e-6, atol=1e-12)
    assert torch.equal(pen.linearize(x, layout)[1], J)  # cached on x


@pytest.mark.slow
def test_augmented_lagrangian_penalty_solver(machine, dataset, one_thread):
    truth, data = dataset
    pts = slope_points(machine.joint_map.limits, 32, 3)
    c = 0.5 * float(slope_norms(truth, pts).detach().max())
    model = MachineModel(machine, TOOLS, orders=3)
    res = fit_constrained(model, data, c, NoiseModel.from_robot(machine), points=32, solver="penalty", max_outer=12,
                          ftol=1e-6)
    assert res.success and res.max_slope <= c * 1.01


def test_infeasible_and_invalid_bounds(machine, dataset):
    truth, data = dataset
    noise = NoiseModel.from_robot(machine)
    with pytest.raises(ValueError):
        fit_constrained(MachineModel(machine, TOOLS, orders=1), data, -1.0, noise)
    model = MachineModel(machine, TOOLS, orders=3)
    model.load_state_dict(truth.state_dict())
    with pytest.raises(ConstraintError, match="infeasible") as err:  # the tables that carry the slope are held fixed
        fit_constrained(model, data, 1e-6, noise, points=16, fixed=("axis_errors",))
    assert isinstance(err.value, TorchcalError) and err.value.result is not None and not err.value.result.success
    assert err.value.result.max_slope > 1e-6


@pytest.mark.slow
def test_constraint_sweep_and_knee(machine, dataset, one_thread):
    truth, data = dataset
    boundary = torch.isin(data.pose, torch.argsort(data.q[:60, 2])[:6])  # 6 lowest-Z poses, both tools
    sweep = constraint_sweep(lambda: MachineModel(machine, TOOLS, orders=3), data, boundary, [4e-4, 1e-4],
                             NoiseModel.from_robot(machine), points=32)
    assert sweep.c.tolist()[0] == math.inf and sweep.c.tolist()[1:] == [4e-4, 1e-4]
    assert all(sweep.success)
    assert bool((sweep.max_slope[1:] <= sweep.c[1:] * 1.05).all())
    assert bool((sweep.sub_mean[1:] >= sweep.sub_mean[0] - 1e-9).all())
    assert len(sweep.table()) == 3 and sweep.table()[1]["c_mm"] == pytest.approx(0.4)
    assert pick_knee(sweep, tol_mm=1e3) == pytest.approx(1e-4)  # nothing rises by a metre
    assert pick_knee(sweep, tol_mm=0.0, mean_tol_mm=0.0) in sweep.c.tolist()


def test_pick_knee_reads_figure_14():
    inf = math.inf
    c = torch.tensor([inf, 1.6e-3, 0.8e-3, 0.4e-3, 0.2e-3, 0.1e-3])
    noise = torch.tensor([0.0, 3e-6, -4e-6, 2e-6, 0.0, 0.0])
    flat_then_rise = torch.tensor([0.45e-3, 0.45e-3, 0.45e-3, 0.45e-3, 0.60e-3, 0.9e-3]) + noise
    sub_mean = torch.tensor([38e-6, 38e-6, 38.5e-6, 39e-6, 45e-6, 60e-6])
    s = SweepResult(c, sub_mean, sub_mean, sub_mean, flat_then_rise, c, [True] * 6, [0.0] * 6)
    assert pick_knee(s, tol_mm=0.01) == pytest.approx(0.4e-3)
    rising_mean = SweepResult(c, torch.tensor([38e-6, 38e-6, 60e-6, 70e-6, 80e-6, 90e-6]), sub_mean, sub_mean,
                              flat_then_rise, c, [True] * 6, [0.0] * 6)
    assert pick_knee(rising_mean, tol_mm=0.01) == pytest.approx(1.6e-3)
    failed = SweepResult(c, sub_mean, sub_mean, sub_mean, flat_then_rise, c, [True, True, True, False, True, True], [0.0] * 6)
    assert pick_knee(failed, tol_mm=0.01) == pytest.approx(0.8e-3)


@pytest.mark.slow
def test_robot_constrained_fit(fanuc, tools_m, one_thread):
    """Item 7: the same bound on a robot's modeled flange-point error over its whole joint range."""
    truth = torchcal.TruthRobot.fanuc_paper2(fanuc, tools_m, 0)
    q = torchcal.sim.quasi_random_commands(fanuc.joint_map.limits, 30, 0)
    data = torchcal.simulate(truth, q, [0, 1, 2], torchcal.NoiseModel.from_robot(fanuc), 0)
    model = torchcal.RobotModel(fanuc, tools_m, orders=1)
    pts = slope_points(fanuc.joint_map.limits, 16, 0, face_count=2, corners=False)
    r0 = fit_constrained(model, data, math.inf, points=pts)
    c = 0.7 * r0.max_slope
    res = fit_constrained(model, data, c, points=pts, check_points=slope_points(fanuc.joint_map.limits, 16, 9, face_count=2,
                                                                             corners=False), tools=[0])
    assert res.success and res.max_slope <= c * 1.01


def test_solve_qp_working_set_equals_one_nnls_over_every_constraint():
    """The working-set QP (constraint generation, warm starts) is exact: the same step as Lawson & Hanson's LDP
    over all k constraints at once, with many near-duplicate rows (neighbouring slope points) among them."""
    from torchcal.identify.constrained import _ldp_nnls

    g = torch.Generator().manual_seed(3)
    P, k = 12, 600
    L = torch.randn(P, P, generator=g, dtype=torch.float64)
    S = L @ L.T + torch.eye(P, dtype=torch.float64)
    rhs = torch.randn(P, generator=g, dtype=torch.float64) * 10
    base = torch.randn(40, P, generator=g, dtype=torch.float64)
    G = base.repeat(15, 1) + 1e-3 * torch.randn(k, P, generator=g, dtype=torch.float64)  # clusters of near-twins
    h = torch.rand(k, generator=g, dtype=torch.float64)
    Lc = torch.linalg.cholesky(S)
    db0 = torch.cholesky_solve(rhs[:, None], Lc)[:, 0]
    z, _ = _ldp_nnls(-torch.linalg.solve_triangular(Lc, G.T, upper=False).T, G @ db0 - h)
    ref = db0 + torch.linalg.solve_triangular(Lc.T, z[:, None], upper=True)[:, 0]
    db, active = solve_qp(S, rhs, G, h, chunk=4, return_active=True)
    assert float((G @ db - h).max()) <= 1e-10
    assert torch.allclose(db, ref, rtol=1e-9, atol=1e-12)
    assert 0 < int(active.sum()) <= P and float((G[active] @ db - h[active]).abs().max()) < 1e-9  # active: on the bound
    warm = solve_qp(S * 1.01, rhs, G, h, start=active)  # a nearby QP from the last active set
    cold = solve_qp(S * 1.01, rhs, G, h)
    assert torch.allclose(warm, cold, rtol=1e-9, atol=1e-12)
    assert not torch.allclose(warm, db, rtol=1e-6)


def test_sqp_stops_on_its_own_tolerance_with_a_least_squares_ftol(machine, dataset, one_thread, monkeypatch):
    """The pipeline passes the LM's ftol (1e-8): the constrained solver stops at SQP_FTOL_FLOOR instead of going
    on over changes of V the l1 merit cannot resolve, and loses nothing by it (the longer run trades V against
    round-off violations of the bound: measured 1.5e-5 V higher)."""
    import torchcal.identify.constrained as constrained

    truth, data = dataset
    noise = NoiseModel.from_robot(machine)
    free = MachineModel(machine, TOOLS, orders=3)
    c = 0.5 * fit_constrained(free, data, math.inf, noise, points=64).max_slope_check
    floored = fit_constrained(MachineModel(machine, TOOLS, orders=3), data, c, noise, points=64, ftol=1e-8)
    monkeypatch.setattr(constrained, "SQP_FTOL_FLOOR", 0.0)
    exact = fit_constrained(MachineModel(machine, TOOLS, orders=3), data, c, noise, points=64, ftol=1e-8)
    assert floored.success and exact.success
    assert floored.fit.nit < exact.fit.nit
    assert floored.fit.fun <= exact.fit.fun * (1 + 1e-6)


def test_sweep_is_warm_started_and_reports_progress(machine, dataset, one_thread):
    """Each c of the sweep starts from the previous c's model: the same fit (residuals, cost) as a cold fit from
    the zero model with the same penalty points; the sweep advances one progress task per c."""
    from torchcal.core import progress

    truth, data = dataset
    noise = NoiseModel.from_robot(machine)
    boundary = torch.isin(data.pose, torch.argsort(data.q[:60, 2])[:6])

    class Keep(progress.Reporter):
        def __init__(self):
            self.seen = []

        def update(self, task):
            self.seen.append((task.name, task.completed, task.total, task.parent.name if task.parent else None))

    keep = Keep()
    with progress.reporting(keep):
        sweep = constraint_sweep(lambda: MachineModel(machine, TOOLS, orders=3), data, boundary, [8e-4, 4e-4], noise,
                                 points=32)
    rows = [s for s in keep.seen if s[0] == "constraint sweep"]
    assert [r[1] for r in rows] == [1, 2, 3] and rows[-1][2] == 3
    inner = [s for s in keep.seen if s[0].startswith("constrained fit")]
    assert inner and all(s[3] == "constraint sweep" for s in inner)  # the fits' iterations, nested in the sweep
    sub = data.subset(~boundary)
    cold = MachineModel(machine, TOOLS, orders=3)
    res = fit_constrained(cold, sub, 4e-4, noise, points=32, seed=2000)
    assert res.success
    from torchcal.identify.problem import row_errors

    assert float(row_errors(cold, sub).mean()) == pytest.approx(float(sweep.sub_mean[-1]), rel=1e-2)  # 0.1 um
    assert float(sweep.max_slope[-1]) <= 4e-4 * 1.05
