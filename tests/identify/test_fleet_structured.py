"""The fleet's factored Jacobian and normal matrix against the dense ones (torchcal.identify.structured)."""

from __future__ import annotations

from functools import partial

import pytest
import torch
from hypothesis import given, settings
from hypothesis import strategies as hst

import torchcal
import torchcal.sim
from torchcal.identify import fleet_kernel
from torchcal.identify.schur import schur_steps
from torchcal.identify.fleet import FleetProblem
from torchcal.identify.structured import (RobotStructure, contract, dense_jacobian, factored_linearization,
                                          factored_residual, gram_parts, pair_basis, pose_groups, slots_of,
                                          structured_steps)
from torchcal.sim.fleet import fleet_truths

TOOLS = torch.tensor([[0.033, 0.058, 0.161], [0.057, -0.034, 0.161], [-0.034, -0.057, 0.161]], dtype=torch.float64)


@pytest.fixture(scope="module")
def problems():
    robot = torchcal.load_robot("fanuc_lrmate200i")
    noise = torchcal.NoiseModel.from_robot(robot)
    fleet = fleet_truths(robot, TOOLS, 3, 0, [1])
    lim = robot.joint_map.limits
    # the units' own programs (different commands and pose counts): padding and pose slots differ per unit
    units = [torchcal.simulate(t, torchcal.sim.quasi_random_commands(lim, 24 + 5 * k, k), [0, 1, 2], noise, 10 + k)
             for k, t in enumerate(fleet.truths)]

    def make():
        return torchcal.RobotModel(robot, TOOLS, orders=3, backlash=2)

    dense = FleetProblem(make, units, noise, structured=False)
    fact = FleetProblem(make, units, noise)
    g = torch.Generator().manual_seed(3)
    X = fact.start() + 1e-4 * torch.randn(fact.M, fact.layout.size, generator=g, dtype=torch.float64) * fact.keep
    return dense, fact, X, g


def _rel(a, b):
    return float((a - b).abs().max() / b.abs().max())


@pytest.mark.parametrize("compiled", [False, True])
def test_factored_jacobian_is_the_dense_one(problems, compiled, monkeypatch):
    """E x Phi reassembled column by column is RobotModel.point_jacobians' A (whitened, masked rows), to rounding;
    the residual and the joint-error Jacobian too, in the torch form and in the compiled one."""
    dense, fact, X, g = problems
    if compiled and not fleet_kernel.available("cpu"):
        pytest.skip("numba not importable")
    assert fact.structure is not None
    V = 1e-4 * torch.randn(fact.M, fact.R, fact.n, generator=g, dtype=torch.float64)
    w = torch.arange(fact.M)
    f, A, C = dense.linearize(X, V, w)
    st = fact.stack
    fn = fleet_kernel.factored_linearization_fused if compiled else factored_linearization
    raw, Jv, E, Phi = fn(fact.superset, fact.structure, fact._params(X), st["q"], st["tool"], st["direction"], V,
                         st["xyz"])
    s = fact.scale[:, :, None] / fact.instrument.weight.sigma
    assert _rel(raw * s, f) < 1e-10
    # a trial point's residual alone: the kernel's Jacobian-free pass, or the torch form's forward half (a GPU's
    # geodesic acceleration), the same bits
    alone = (partial(fn, jac=False) if compiled else factored_residual)(
        fact.superset, fact.structure, fact._params(X), st["q"], st["tool"], st["direction"], V, st["xyz"])
    assert torch.equal(alone, raw)
    if not compiled:  # and FleetProblem.residual where no kernel serves the device
        monkeypatch.setattr(fleet_kernel, "available", lambda device: False)
        assert torch.equal(fact.residual(X, V, w), raw * s)
    assert _rel(Jv * s[..., None], C) < 1e-10
    Ad = dense_jacobian(E * s[..., None], Phi, fact.structure) * fact.keep[:, None, None, :]
    assert _rel(Ad, A) < 1e-10


def _dense_normal(dense, f, A, C, w_v):
    """sum_r A_r^T (I - C_r H_vv,r^-1 C_r^T) A_r: the Schur complement of the joint errors, densely."""
    m, R, d, P = A.shape
    H = C.transpose(-1, -2) @ C + torch.diag_embed(w_v)
    M = torch.eye(d, dtype=A.dtype) - C @ torch.linalg.solve(H, C.transpose(-1, -2))
    Af = A.reshape(m, R * d, P)
    return Af.transpose(1, 2) @ (M @ A).reshape(m, R * d, P)


@pytest.mark.parametrize("products", ["numpy", "torch"])
def test_khatri_rao_normal_matrix_is_the_dense_one(problems, products, monkeypatch, request):
    """At v = 0 (the rows of a pose share their basis values) the per-pose Gram matrices contracted with the
    Chebyshev basis give the dense J^T M J to 1e-10 relative, by the torch route and the compiled one, with the
    products through numpy's BLAS and torch's (torchcal.core.blas: whichever this machine would not choose too),
    for units of their own programs and of one."""
    from torchcal.core import blas

    monkeypatch.setenv(blas.ENV, products)
    blas.numpy_blas.cache_clear()
    request.addfinalizer(blas.numpy_blas.cache_clear)  # the machine's own choice for the tests after
    dense, fact, X, _ = problems
    V = torch.zeros(fact.M, fact.R, fact.n, dtype=torch.float64)
    w = torch.arange(fact.M)
    f, A, C = dense.linearize(X, V, w)
    ref = _dense_normal(dense, f, A, C, dense.w_v)
    ff, Cf, E, Phi, Phi_p = fact.linearize(X, V, w)
    H = Cf.transpose(-1, -2) @ Cf + torch.diag_embed(fact.w_v)
    M = torch.eye(3, dtype=E.dtype) - Cf @ torch.linalg.solve(H, Cf.transpose(-1, -2))
    kf = fact.keep.to(E)
    paths = [gram_parts]
    if fleet_kernel.available("cpu"):
        paths.append(lambda E, ME, slots, st: fleet_kernel.gram_fused(fleet_kernel.pose_last(E, slots),
                                                                      fleet_kernel.pose_last(ME, slots), st.n, st.A))
    for parts in paths:
        S = contract(parts(E, M @ E, fact.slots, fact.structure), Phi_p, fact.structure) * kf[:, :, None] * kf[:, None, :]
        assert _rel(S, ref) < 1e-10
        assert torch.equal(S, S.transpose(1, 2))
        # units measured with one program share the pair products of their basis values: unit 0 alone
        S0 = contract(parts(E[:1], (M @ E)[:1], fact.slots[:1], fact.structure), Phi_p[:1], fact.structure,
                      pp=pair_basis(Phi_p[0], fact.n)) * kf[:1, :, None] * kf[:1, None, :]
        assert _rel(S0, ref[:1]) < 1e-10
        # each unit's own pair products handed in, as FleetProblem's step does
        S1 = contract(parts(E, M @ E, fact.slots, fact.structure), Phi_p, fact.structure,
                      pp=pair_basis(Phi_p, fact.n)) * kf[:, :, None] * kf[:, None, :]
        assert _rel(S1, ref) < 1e-10


def test_structured_steps_are_the_dense_steps(problems):
    """With joint errors (rows of a pose no longer share basis values), the preconditioned iterations on the
    exact product give the dense Levenberg-Marquardt step."""
    dense, fact, X, g = problems
    # padding rows (units with fewer rows) keep v = 0, as in a solve
    V = 2e-5 * torch.randn(fact.M, fact.R, fact.n, generator=g, dtype=torch.float64) * fact.rows[..., None]
    w = torch.arange(fact.M)
    f, A, C = dense.linearize(X, V, w)
    lin = fact.linearize(X, V, w)
    for mu0 in (1e-8, 1e-2):
        mu = torch.full((fact.M,), mu0, dtype=torch.float64)
        a = schur_steps(f, A, C, dense.w_v, V, dense.lam, X - dense.mean, mu, dense.keep)
        args = (lin, fact.structure, fact.slots, fact.w_v, V, fact.lam, X - fact.mean, mu, fact.keep)
        for (refine, tol), bound in (((30, 1e-14), 1e-8), ((3, 1e-7), 1e-4)):  # to convergence; the default
            for x, y in zip(a, structured_steps(*args, refine=refine, tol=tol)):
                assert _rel(y, x) < bound


def test_dense_normal_steps_are_the_dense_steps(problems):
    """The GPU's form (factored linearization expanded to A, one product for the normal matrix) takes the
    step the dense linearization takes, and a solve in it ends where the dense solve ends."""
    from torchcal.identify.batched import solve_batched

    dense, fact, X, g = problems
    dn = FleetProblem(lambda: torchcal.RobotModel(dense.superset.robot, TOOLS, orders=3, backlash=2), dense.units,
                      dense.problem.noise, dense_normal=True)
    assert dn.dense_normal and dn.structure is not None
    V = 2e-5 * torch.randn(dn.M, dn.R, dn.n, generator=g, dtype=torch.float64) * dn.rows[..., None]
    w = torch.arange(dn.M)
    f, A, C = dense.linearize(X, V, w)
    mu = torch.full((dn.M,), 1e-3, dtype=torch.float64)
    a = schur_steps(f, A, C, dense.w_v, V, dense.lam, X - dense.mean, mu, dense.keep)
    b = dn.step(dn.linearize(X, V, w), V, X - dn.mean, mu, w)
    for x, y in zip(a, b):
        assert _rel(y, x) < 1e-9
    ra, rb = solve_batched(dense, chunk=2), solve_batched(dn, chunk=2)
    assert [r.nit for r in ra.results] == [r.nit for r in rb.results]
    assert _rel(rb.x, ra.x) < 1e-8
    # every unit's model holds its solution (the fleet's vectorized write), and start() reads it back
    assert _rel(dn.start(), rb.x * dn.keep) < 1e-15


def test_unsupported_models_take_the_dense_path():
    robot = torchcal.load_robot("fanuc_lrmate200i")
    model = torchcal.RobotModel(robot, TOOLS, orders=1, compliance=True)
    from torchcal.identify.layout import ParameterLayout
    from torchcal.measure import PointTargets

    assert not RobotStructure.supports(model, PointTargets(torch.zeros(2, 3, dtype=torch.float64), sigma=1e-5),
                                       ParameterLayout(model))


def test_compiled_rows_are_the_torch_rows(problems):
    """The compiled per-row half of the step (each row's elimination, the per-pose Gram matrices formed in the same
    pass and contracted, the gradient and diagonal from per-block sums, the exact products) against the batched
    torch form, with joint errors (the rows of a pose differ) and units of different pose counts (padding)."""
    from torchcal.identify.structured import _RowsFused, _RowsTorch

    dense, fact, X, g = problems
    if not fleet_kernel.available("cpu"):
        pytest.skip("numba not importable")
    V = 2e-5 * torch.randn(fact.M, fact.R, fact.n, generator=g, dtype=torch.float64) * fact.rows[..., None]
    lin = fact.linearize(X, V, torch.arange(fact.M))
    mu = torch.tensor([1e-8, 1e-3, 1e-1], dtype=torch.float64)
    st = fact.structure
    a = _RowsFused(lin, fact.slots, fact.w_v, V, mu, st)
    b = _RowsTorch(lin, fact.slots, fact.w_v, V, mu, st)
    assert _rel(a.S, b.S) < 1e-10 and torch.equal(a.S, a.S.transpose(1, 2))
    assert _rel(a.gx, b.gx) < 1e-10 and _rel(a.diag_x, b.diag_x) < 1e-10
    dbx = torch.randn(fact.M, st.size, generator=g, dtype=torch.float64)
    assert _rel(a.product(dbx), b.product(dbx)) < 1e-10
    r = torch.randn(fact.M, fact.R, 3, generator=g, dtype=torch.float64)  # another residual (geodesic acceleration)
    assert _rel(a.gradient(r), b.gradient(r)) < 1e-10
    for x, y in zip(a.finish(dbx), b.finish(dbx)):
        assert _rel(x, y) < 1e-10
    # units measured with one program: the shared pair products and basis values take the other contraction
    robot = fact.superset.robot
    same = FleetProblem(lambda: torchcal.RobotModel(robot, TOOLS, orders=3, backlash=2), [fact.units[0]] * 2,
                        torchcal.NoiseModel.from_robot(robot))
    assert same.pp is not None
    V = V[:2, :same.R] * same.rows[..., None]
    lin = same.linearize(X[:2], V, torch.arange(2))
    a = _RowsFused(lin, same.slots, same.w_v, V, mu[:2], st, same.pp)
    b = _RowsTorch(lin, same.slots, same.w_v, V, mu[:2], st)
    assert _rel(a.S, b.S) < 1e-10 and torch.equal(a.S, a.S.transpose(1, 2))


@pytest.mark.parametrize("compiled", [False, True])
def test_a_one_program_fleet_shares_its_first_linearization_and_normal_matrix(problems, compiled, monkeypatch):
    """Units that ran one program (same commands, tools, directions; their own truths and noise) and stand at one
    point share the linearization but for their residuals, and one normal matrix serves all their steps: the
    shared linearization and steps equal each unit's own (to rounding), in the torch form and the compiled one.
    Units of different programs, or one program at different points, are not shared."""
    from torchcal.identify import structured

    dense, fact, X, g = problems
    if compiled and not fleet_kernel.available("cpu"):
        pytest.skip("numba not importable")
    if not compiled:
        monkeypatch.setattr(fleet_kernel, "available", lambda device: False)
    assert not fact.one_program  # the fixture's units have their own programs
    robot = fact.superset.robot
    noise = torchcal.NoiseModel.from_robot(robot)
    fleet = fleet_truths(robot, TOOLS, 3, 1, [2])
    q = torchcal.sim.quasi_random_commands(robot.joint_map.limits, 20, 4)
    dirs = torch.where(torch.rand(q.shape, generator=g, dtype=torch.float64) > 0.5, 1.0, -1.0)
    units = [torchcal.simulate(t, q, [0, 1, 2], noise, 30 + k, directions=dirs) for k, t in enumerate(fleet.truths)]
    same = FleetProblem(lambda: torchcal.RobotModel(robot, TOOLS, orders=3, backlash=2), units, noise)
    assert same.one_program
    M, w = same.M, torch.arange(same.M)
    X0 = same.start().expand(M, -1).clone()
    V = torch.zeros(M, same.R, same.n, dtype=torch.float64)
    assert same._common(X0, V) and not same._common(X0 + 1e-6 * torch.rand(X0.shape, generator=g), V)
    shared_lin = same.linearize(X0, V, w)
    own = same._factored(X0, V, w, same.stack["q"], same.stack["tool"], same.stack["xyz"])
    assert _rel(shared_lin[0], own[0]) < 1e-12 and float(shared_lin[0].std(0).max()) > 0  # residuals differ
    for a, b in zip(shared_lin[1:], own[1:]):
        assert torch.equal(a, b)
    # the GPU's form (the dense normal matrix from the expanded Jacobian) shares the linearization alike
    dn = FleetProblem(lambda: torchcal.RobotModel(robot, TOOLS, orders=3, backlash=2), units, noise, dense_normal=True)
    assert dn.one_program
    for a, b in zip(dn.linearize(X0, V, w), own[:4]):
        assert _rel(a, b) < 1e-12
    mu = torch.full((M,), 1e-3, dtype=torch.float64)
    args = (same.structure, same.slots, same.w_v, V, same.lam, X0 - same.mean, mu, same.keep)
    own_steps = structured.structured_steps(list(own), *args, pp=same.pp)
    shared_steps = structured.structured_steps([t.contiguous() for t in shared_lin], *args, pp=same.pp, shared=True)
    for a, b in zip(shared_steps, own_steps):
        assert _rel(a, b) < 1e-9
    assert float(own_steps[0].std(0).max()) > 0  # the units' steps differ: their right-hand sides were used
    # FleetProblem.step takes the shared path at the common point only
    calls = []
    real = structured.structured_steps
    monkeypatch.setattr("torchcal.identify.fleet.structured_steps",
                        lambda *a, **k: calls.append(k["shared"]) or real(*a, **k))
    same.step([t.contiguous() for t in shared_lin], V, X0 - same.mean, mu, w)
    same.step(list(own), V, X0 - same.mean, mu * torch.tensor([1.0, 2.0, 1.0], dtype=torch.float64), w)
    assert calls == [True, False]


@pytest.mark.parametrize("P", [1, 2, 3, 5, 7, 64, 65])
def test_compiled_cholesky_is_torch_cholesky(P):
    """fleet_kernel.cholesky_rows / cholesky_solve_rows against torch.linalg.cholesky_ex / cholesky_solve on a batch of
    positive definite matrices of every size modulo 4 (the kernel takes two rows and four columns per pass), and the
    failing pivot of matrices that are not positive definite (on either row of a pass, and on a last row without a
    second) reported as torch reports it (its index + 1, 0 for the others)."""
    if not fleet_kernel.available("cpu"):
        pytest.skip("numba not importable")
    g = torch.Generator().manual_seed(P)
    A = torch.randn(4, P + 3, P, generator=g, dtype=torch.float64)
    S = A.transpose(1, 2) @ A + 1e-3 * torch.eye(P, dtype=torch.float64)
    S[2] = S[2] - 2.0 * S[2][P // 2, P // 2] * torch.outer(torch.eye(P, dtype=torch.float64)[P // 2],
                                                             torch.eye(P, dtype=torch.float64)[P // 2])
    S[3, P - 1, P - 1] = float("nan")
    L, info = torch.empty_like(S), torch.empty(4, dtype=torch.int64)
    fleet_kernel.cholesky_rows(S.numpy(), L.numpy(), info.numpy())
    L_ref, info_ref = torch.linalg.cholesky_ex(S)
    assert info.tolist() == info_ref.tolist() and info[0] == 0 and info[2] == P // 2 + 1 and info[3] == P
    assert _rel(L[:2], L_ref[:2]) < 1e-12 and torch.equal(L[:2], L[:2].tril())
    b = torch.randn(2, P, generator=g, dtype=torch.float64)
    x = torch.empty_like(b)
    fleet_kernel.cholesky_solve_rows(L[:2].contiguous().numpy(), b.numpy(), x.numpy())
    assert _rel(S[:2] @ x[..., None], b[..., None]) < 1e-9
    assert _rel(x, torch.cholesky_solve(b[..., None], L_ref[:2])[..., 0]) < 1e-10


def test_a_users_7_axis_robot_fleet_lands_where_each_unit_alone_lands(iiwa):
    """A fleet of a robot we do not bundle (a 7-axis arm from a datasheet's DH table, conftest.iiwa) takes the
    factored and compiled path like the bundled ones, and every unit lands on its own fit's optimum. The
    truths are random error models of a higher order than the fitted one (their residual is not the noise)."""
    from conftest import randomize
    from torchcal.core.measurements import Measurements
    from torchcal.identify.fleet import fit_fleet

    tools = torch.tensor([[0.03, 0.05, 0.1], [0.05, -0.03, 0.1]], dtype=torch.float64)
    noise = torchcal.NoiseModel.from_file_units(0.02, [1e-4] * 7, [1e-4] * 7)
    q = torchcal.sim.quasi_random_commands(iiwa.joint_map.limits * 0.9, 60, 0)
    g = torch.Generator().manual_seed(0)
    s = torch.where(torch.rand(q.shape, generator=g, dtype=torch.float64) > 0.5, 1.0, -1.0)
    units = []
    for k in range(3):
        truth = randomize(torchcal.RobotModel(iiwa, tools, orders=4, backlash=True), 20 + k)
        qq, dd = q.repeat(2, 1), s.repeat(2, 1)
        tool = torch.arange(2).repeat_interleave(len(q))
        with torch.no_grad():
            xyz = truth.points(qq, tool, dd) + 2e-5 * torch.randn(len(qq), 3, generator=g, dtype=torch.float64)
        units.append(Measurements(q=qq, tool=tool, xyz=xyz, direction=dd, pose=torch.arange(len(q)).repeat(2),
                                  rows=torch.arange(len(qq)) + 1, has_direction=True))

    def make():
        return torchcal.RobotModel(iiwa, tools, orders=3, backlash=True)

    fp = FleetProblem(make, units, noise)
    assert fp.structure is not None and fp.n == 7  # the factored path, as for a bundled robot
    out = fit_fleet(make, units, noise, ftol=1e-8)  # the single fit's stopping point: the same optimum
    for u, r in zip(units, out.results):
        alone = torchcal.fit(make(), u, noise)
        assert r.success and alone.success
        assert abs(r.fun - alone.fun) <= 1e-6 * alone.fun


def test_a_units_row_order_moves_nothing_but_its_joint_errors():
    """The fleet walks each unit's rows pose by pose (FleetProblem.row_order); what it reports is in the data's
    own order: a unit whose rows come shuffled lands on the same parameters, its joint errors shuffled alike,
    and they are its separate fit's joint errors row for row (fails if the order is not mapped back)."""
    from torchcal.identify.fleet import fit_fleet

    robot = torchcal.load_robot("fanuc_lrmate200i")
    noise = torchcal.NoiseModel.from_robot(robot)
    truths = fleet_truths(robot, TOOLS[:2], 2, 4, []).truths
    q = torchcal.sim.quasi_random_commands(robot.joint_map.limits, 30, 4)
    units = [torchcal.simulate(t, q, [0, 1], noise, 70 + k) for k, t in enumerate(truths)]
    perm = torch.randperm(len(units[1]), generator=torch.Generator().manual_seed(9))

    def make():
        return torchcal.RobotModel(robot, TOOLS[:2], orders=2, backlash=True)

    out = fit_fleet(make, units, noise, ftol=1e-10, streams=1)
    shuffled = fit_fleet(make, [units[0], units[1].subset(perm)], noise, ftol=1e-10, streams=1)
    assert _rel(shuffled.batch.x, out.batch.x) < 1e-8
    v, vs = out.results[1].v, shuffled.results[1].v
    assert _rel(vs, v[perm]) < 1e-6 and _rel(vs, v) > 0.1  # a different order indeed
    alone = torchcal.fit(make(), units[1], noise)
    assert _rel(v[:len(units[1])], alone.v) < 1e-4  # (a row mixed up: ~1)


def test_each_units_pair_products_serve_whichever_units_a_step_takes(problems):
    """Units of their own programs: the pair products formed once for the whole fleet (FleetProblem's
    _pair_products) give, for any units a step takes (a run of them, or units apart), the steps of products
    formed from those units' basis values in the step itself (fails if a step is handed other units' products)."""
    dense, fact, X, g = problems
    assert fact.pp is None  # the units' own programs
    V = 2e-5 * torch.randn(fact.M, fact.R, fact.n, generator=g, dtype=torch.float64) * fact.rows[..., None]
    for which in ([0, 1, 2], [1, 2], [0, 2], [2]):
        w = torch.tensor(which)
        lin = fact.linearize(X[w], V[w], w)
        mu = torch.full((len(which),), 1e-4, dtype=torch.float64)
        got = fact.step(lin, V[w], X[w] - fact.mean, mu, w)
        ref = structured_steps(lin, fact.structure, fact.slots[w], fact.w_v[w], V[w], fact.lam, X[w] - fact.mean, mu,
                               fact.keep[w])
        for x, y in zip(got, ref):
            assert _rel(x, y) < 1e-12


@settings(max_examples=40, deadline=None)
@given(rows=hst.integers(1, 40), poses=hst.integers(1, 12), cols=hst.integers(1, 5), seed=hst.integers(0, 2**31 - 1),
       directions=hst.booleans())
def test_pose_groups_are_torch_uniques_rows(rows, poses, cols, seed, directions):
    """A unit's poses (pose_groups) against torch.unique over the rows of (command, directions): the same pose of
    each row, the same counts, and the order a stable sort of the rows by pose (so each pose's rows keep theirs)."""
    g = torch.Generator().manual_seed(seed)
    distinct = torch.randn(poses, cols, generator=g, dtype=torch.float64)
    distinct[:, 0] = torch.randint(0, 2, (poses,), generator=g).to(distinct)  # ties in the first column
    pick = torch.randint(0, poses, (rows,), generator=g)
    q = distinct[pick]
    s = torch.where(torch.rand(rows, cols, generator=g) > 0.5, 1.0, -1.0).double() if directions else None
    (inv, order, counts), = pose_groups([q], [s])
    key = q if s is None else torch.cat([q, s], 1)
    _, inv_ref, counts_ref = torch.unique(key, dim=0, return_inverse=True, return_counts=True)
    assert torch.equal(inv, inv_ref) and torch.equal(counts, counts_ref)
    assert torch.equal(order, torch.argsort(inv_ref, stable=True))
    # a second unit with the same program shares the grouping; one with another program does not
    again, other = pose_groups([q, q.clone(), q + 1.0], [s, s, s])[1:]
    assert all(torch.equal(a, b) for a, b in zip(again, (inv, order, counts)))
    slots = slots_of(pose_groups([q], [s]), rows)
    assert torch.equal(torch.sort(slots[slots < rows]).values, torch.arange(rows))  # every row in one slot
    assert bool((inv[slots.clamp(max=rows - 1)][slots < rows] == torch.arange(inv_ref.max() + 1)[:, None].expand_as(slots)[slots < rows]).all())


@pytest.mark.parametrize("form", ["dense", "torch", "compiled"])
def test_a_steps_system_solved_again_is_the_step_for_that_residual(problems, form, monkeypatch):
    """Resolve (geodesic acceleration's second solve) reuses a step's damped system: for another residual r it
    gives what a fresh step with r for the residual and no prior offsets (V = 0, X at the prior mean) gives."""
    dense, fact, X, g = problems
    if form == "compiled" and not fleet_kernel.available("cpu"):
        pytest.skip("numba not importable")
    if form == "torch":
        monkeypatch.setattr(fleet_kernel, "available", lambda device: False)
    V = 2e-5 * torch.randn(fact.M, fact.R, fact.n, generator=g, dtype=torch.float64) * fact.rows[..., None]
    mu = torch.tensor([1e-8, 1e-3, 1e-1], dtype=torch.float64)
    w = torch.arange(fact.M)
    r = torch.randn(fact.M, fact.R, 3, generator=g, dtype=torch.float64) * fact.rows[..., None]
    zero_v, zero_x = torch.zeros_like(V), torch.zeros_like(X)
    if form == "dense":
        f, A, C = dense.linearize(X, V, w)
        *_, resolve = schur_steps(f, A, C, dense.w_v, V, dense.lam, X - dense.mean, mu, dense.keep, again=True)
        fresh = schur_steps(r, A, C, dense.w_v, zero_v, dense.lam, zero_x, mu, dense.keep)[0]
    else:
        lin = fact.linearize(X, V, w)
        args = (fact.structure, fact.slots, fact.w_v)
        *_, resolve = structured_steps(lin, *args, V, fact.lam, X - fact.mean, mu, fact.keep, again=True)
        fresh = structured_steps((r, *lin[1:]), *args, zero_v, fact.lam, zero_x, mu, fact.keep)[0]
    assert _rel(resolve(r), fresh) < 1e-10
    assert resolve.scale.shape == X.shape and bool((resolve.scale >= 0).all())


@pytest.mark.parametrize("dense_normal", [False, True])
def test_geodesic_acceleration_reaches_each_units_optimum_in_fewer_iterations(dense_normal):
    """A fleet solved with geodesic acceleration lands where the plain Levenberg-Marquardt solve lands (each
    unit's own optimum), in fewer unit iterations: units of Paper II's FANUC truth (own truths, own programs,
    random approach directions), whose residuals curve along the first steps. dense_normal: the GPU's path (one
    dense normal matrix a unit; its trial residual by the whole linearization), here on the CPU."""
    from torchcal.identify.batched import solve_batched
    from torchcal.identify.fleet import FLEET_FTOL

    robot = torchcal.load_robot("fanuc_lrmate200i")
    noise = torchcal.NoiseModel.from_robot(robot)
    fleet = fleet_truths(robot, TOOLS, 4, 1, [2])
    lim = robot.joint_map.limits
    units = []
    for k, t in enumerate(fleet.truths):
        q = torchcal.sim.quasi_random_commands(lim, 60, 5 + k)
        g = torch.Generator().manual_seed(k)
        d = torch.where(torch.rand(q.shape, generator=g, dtype=torch.float64) > 0.5, 1.0, -1.0)
        units.append(torchcal.simulate(t, q, [0, 1, 2], noise, 30 + k, directions=d))

    def make():
        return torchcal.RobotModel(robot, TOOLS, orders=4, backlash=True)

    def solve(ftol, accelerate):
        fp = FleetProblem(make, units, noise, dense_normal=dense_normal)
        assert fp.dense_normal == dense_normal
        out = solve_batched(fp, ftol=ftol, accelerate=accelerate).results
        assert all(r.success for r in out)
        return out

    for p, f in zip(solve(1e-10, False), solve(1e-10, True)):  # to the optimum (seen: 1e-11 apart)
        assert abs(f.fun - p.fun) <= 1e-8 * p.fun
    # at the fleet's own tolerance (seen: 18 unit iterations against 14)
    on, off = solve(FLEET_FTOL, True), solve(FLEET_FTOL, False)
    assert sum(r.nit for r in on) <= sum(r.nit for r in off) - 2
    if not dense_normal:  # fit_fleet's switch reaches the solve (one stream: the same arithmetic as above)
        from torchcal.identify.fleet import fit_fleet

        for acc, ref in ((True, on), (False, off)):
            got = fit_fleet(make, units, noise, accelerate=acc, streams=1).results
            assert [r.nit for r in got] == [r.nit for r in ref] and [r.fun for r in got] == [r.fun for r in ref]
