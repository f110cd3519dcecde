"""The greedy gauge test against a direct reference: a column is dependent exactly when adding it
does not raise the rank of the independent columns kept before it (SVD rank, independent of the
Gram-Schmidt code)."""

import torch
from hypothesis import given, settings
from hypothesis import strategies as st

from torchcal.identify.gauge import dependent_columns, dependent_columns_masked, gauge_basis


def _reference(A, order, keep=None, rtol=1e-7):
    P = A.shape[1]
    keep = torch.ones(P, dtype=torch.bool) if keep is None else keep
    An = A / A.norm(dim=0).clamp(min=1e-300)
    kept, dep = [], torch.zeros(P, dtype=torch.bool)
    for j in order.tolist():
        if not keep[j]:
            continue
        if kept:
            Q = torch.linalg.svd(An[:, kept], full_matrices=False)[0]
            new = (An[:, j] - Q @ (Q.T @ An[:, j])).norm()
        else:
            new = An[:, j].norm()
        if new < rtol:
            dep[j] = True
        else:
            kept.append(j)
    return dep


def _matrix(seed, rows, rank, P):
    """rows x P, rank ``rank``: a few exact duplicates / combinations among random columns."""
    g = torch.Generator().manual_seed(seed)
    base = torch.randn(rows, rank, generator=g, dtype=torch.float64)
    mix = torch.randn(rank, P, generator=g, dtype=torch.float64)
    # the first `rank` columns independent, the rest combinations of 2-3 of them
    mix[:, :rank] = torch.eye(rank, dtype=torch.float64) + 0.1 * mix[:, :rank]
    sparse = torch.rand(rank, P - rank, generator=g) < 0.15
    mix[:, rank:] *= sparse
    A = base @ mix
    return A[:, torch.randperm(P, generator=g)]


@settings(max_examples=10, deadline=None)
@given(seed=st.integers(0, 10_000), extra_rows=st.integers(0, 30), deficit=st.integers(1, 12))
def test_greedy_matches_rank_reference_when_rows_barely_exceed_columns(seed, extra_rows, deficit):
    """Rows close to P is where a Householder QR's noise reflectors pinned independent columns."""
    P = 40
    A = _matrix(seed, P + extra_rows, P - deficit, P)
    order = torch.randperm(P, generator=torch.Generator().manual_seed(seed + 1))
    got = dependent_columns(A, order)
    assert torch.equal(got, _reference(A, order))
    assert int(got.sum()) == P - int(torch.linalg.matrix_rank(A))


@settings(max_examples=6, deadline=None)
@given(seed=st.integers(0, 10_000))
def test_masked_subsets_match_each_subset_alone(seed):
    P = 30
    A = _matrix(seed, 45, 22, P)
    g = torch.Generator().manual_seed(seed)
    order = torch.randperm(P, generator=g)
    keep = torch.rand(7, P, generator=g) < 0.7
    got = dependent_columns_masked(gauge_basis(A, order), keep)
    for m in range(keep.shape[0]):
        assert torch.equal(got[m], _reference(A, order, keep[m]))


@settings(max_examples=10, deadline=None)
@given(seed=st.integers(0, 10_000), d=st.integers(1, 12))
def test_early_duplicates_do_not_pin_later_independent_columns(seed, d):
    """Multiples of the first column come first in the order, then the rest of a square full-rank
    basis: exactly the d multiples are dependent (a QR's noise reflectors for them used to use up
    the dimensions the last columns need, and pinned d more)."""
    g = torch.Generator().manual_seed(seed)
    base = torch.randn(30, 30, generator=g, dtype=torch.float64)
    A = torch.cat([base[:, :1], base[:, :1] * (0.5 + torch.rand(1, d, generator=g, dtype=torch.float64)), base[:, 1:]], 1)
    got = dependent_columns(A)
    assert got[1:d + 1].all() and int(got.sum()) == d
    masked = dependent_columns_masked(gauge_basis(A), torch.ones(2, A.shape[1], dtype=torch.bool))
    assert torch.equal(masked[0], got) and torch.equal(masked[1], got)


def test_fix_gauge_pins_the_same_names_from_a_warm_start(fanuc, tools_m):
    """A model whose joint errors are already fitted (a warm start) has the same exact redundancies as a fresh
    one; judged at its own parameters, joint 1's tilted eps_z.c0 only nearly duplicates base.eps_z and was
    left free. The model's parameters must come back unchanged."""
    from conftest import random_commands, randomize
    from torchcal.identify import CalibrationProblem, NoiseModel, Prior
    from torchcal.identify.gauge import fix_gauge
    from torchcal.models.robot import RobotModel

    fresh = RobotModel(fanuc, tools_m, orders=2, backlash=1)
    warm = randomize(RobotModel(fanuc, tools_m, orders=2, backlash=1), 3)
    q = random_commands(fanuc, 40, 2)
    tool = torch.arange(120) % 3
    with torch.no_grad():
        xyz = warm.points(q.repeat(3, 1), tool)
    from torchcal.core.measurements import Measurements

    data = Measurements(q.repeat(3, 1), tool, xyz, torch.ones(120, 6), torch.arange(40).repeat(3),
                        torch.arange(1, 121), True, "sim")
    names = {}
    for label, model in (("fresh", fresh), ("warm", warm)):
        before = {k: v.clone() for k, v in model.state_dict().items()}
        problem = CalibrationProblem(model, data, NoiseModel.paper2(), Prior())
        names[label] = fix_gauge(problem)
        assert all(torch.equal(before[k], v) for k, v in model.state_dict().items())
    assert "joint1.eps_z.c0" in names["fresh"]
    assert names["warm"] == names["fresh"]


@settings(max_examples=25, deadline=None)
@given(seed=st.integers(0, 10_000), P=st.integers(1, 70), rank_deficit=st.integers(0, 20),
       block=st.integers(1, 40))
def test_blocked_full_test_equals_the_column_by_column_test(seed, P, rank_deficit, block):
    """The blocked greedy test of the full column set (one QR per block, restarting after each pinned column)
    pins exactly the columns that the column-by-column Gram-Schmidt pins, whatever the block size and
    wherever the dependent columns fall against the block edges."""
    from torchcal.identify.gauge import _greedy, _greedy_full, _unit_columns_in_order

    rank = max(1, P - rank_deficit)
    A = _matrix(seed, P + 5, rank, P) if rank < P else torch.randn(P + 5, P, dtype=torch.float64,
                                                                  generator=torch.Generator().manual_seed(seed))
    Bt, _ = _unit_columns_in_order(A, torch.arange(P))
    full = _greedy_full(Bt, 1e-7, block)
    assert torch.equal(full, _greedy(Bt, torch.ones(1, P, dtype=torch.bool), 1e-7)[0])
    assert int(full.sum()) == P - int(torch.linalg.matrix_rank(A))


@settings(max_examples=25, deadline=None)
@given(seed=st.integers(0, 10_000), P=st.integers(2, 60), rows=st.integers(1, 30), block=st.integers(1, 40))
def test_fewer_rows_than_columns_pins_all_but_the_rank(seed, P, rows, block):
    """Three poses of one tool give 9 rows for hundreds of parameters: the blocked test must pin every column
    beyond the rows' rank (it crashed where a block had more columns than the data had rows) and agree with
    the column-by-column test."""
    from torchcal.identify.gauge import _greedy, _greedy_full, _unit_columns_in_order

    rows = min(rows, P - 1)
    A = torch.randn(rows, P, dtype=torch.float64, generator=torch.Generator().manual_seed(seed))
    Bt, _ = _unit_columns_in_order(A, torch.arange(P))
    full = _greedy_full(Bt, 1e-7, block)
    assert torch.equal(full, _greedy(Bt, torch.ones(1, P, dtype=torch.bool), 1e-7)[0])
    assert int(full.sum()) == P - int(torch.linalg.matrix_rank(A))
