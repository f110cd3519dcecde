"""Candidate models scored from one linearization (the model batch dimension of order selection).

Every check is against the slow, obvious reference: the candidate fitted on its own
(:func:`torchcal.fit`) and scored by :func:`loo_residuals` or on the validation rows.
"""

from __future__ import annotations

import pytest
import torch

from conftest import random_commands, randomize
from torchcal.identify import NoiseModel, Prior, fit
from torchcal.identify.backlash import default_backlash_orders
from torchcal.identify.candidates import SharedLinearization, StructureSearch, copy_overlap, structure_mask
from torchcal.identify.order import held_out_errors
from torchcal.core.measurements import Measurements
from torchcal.models.robot import RobotModel


def _data(truth, robot, poses, seed, noise, directions="sequence"):
    q = random_commands(robot, poses, seed)
    g = torch.Generator().manual_seed(seed + 1000)
    if directions == "random":
        s = torch.where(torch.rand(q.shape, generator=g) > 0.5, 1.0, -1.0)
    else:
        s = torch.sign(torch.diff(torch.cat([torch.zeros(1, q.shape[1]), q]), dim=0))
    T = 3
    qq, ss = q.repeat(T, 1), s.repeat(T, 1)
    tool = torch.arange(T).repeat_interleave(poses)
    with torch.no_grad():
        v = torch.randn(qq.shape, generator=g) * noise.joint_variance(ss).sqrt()
        p = truth.points(qq, tool, ss, v) + torch.randn(qq.shape[0], 3, generator=g) * noise.sigma_m
    return Measurements(qq, tool, p, ss, torch.arange(poses).repeat(T), torch.arange(1, len(qq) + 1), True, "sim")


@pytest.fixture(scope="module")
def case(fanuc, tools_m):
    noise = NoiseModel.paper2()
    truth = randomize(RobotModel(fanuc, tools_m, orders=3, backlash=1), 31)
    data = _data(truth, fanuc, 70, 32, noise)
    val = _data(truth, fanuc, 40, 33, noise)

    def make(o, b=1):
        return RobotModel(fanuc, tools_m, orders=list(o), backlash=b)

    # linearized where a search would be: at the fit of one candidate (the truth's order), the superset
    # carrying one order more with those terms at zero
    center = make([3] * 6)
    r = fit(center, data, noise, Prior())
    sup = make([4] * 6)
    copy_overlap(center, sup)
    return dict(noise=noise, data=data, val=val, make=make, sup=sup, v=r.v)


@pytest.mark.parametrize("orders", [[2] * 6, [4] * 6, [3, 2, 3, 4, 1, 3]])
def test_loo_scores_match_separate_fits(case, orders):
    """One Gauss-Newton solve from the superset's point gives the candidate's leave-one-pose-out errors of a
    separate fit (second-order accurate: sub-micrometre on a model whose residuals are ~10 µm)."""
    lin = SharedLinearization(case["sup"], case["data"], case["noise"], Prior(), v=case["v"])
    keep = lin.masks([case["make"](orders)])
    approx = lin.loo_errors(keep)[0]
    exact = held_out_errors(case["make"], orders, case["data"], None, case["noise"], Prior())
    assert torch.isfinite(exact).all()
    # the reference is an LM fit, which stops where near-redundant terms still trade a few tenths of a chi^2
    # unit (a curved valley): it differs from the exact optimum by 1-3 µm here, so that is the tolerance
    assert float((approx - exact).abs().max()) < 5e-6
    assert abs(float(approx.mean()) / float(exact.mean()) - 1) < 2e-3


def test_validation_scores_match_separate_fits(case):
    lin = SharedLinearization(case["sup"], case["data"], case["noise"], Prior(), v=case["v"], validation=case["val"])
    cands = [[2] * 6, [4] * 6]
    approx = lin.errors(lin.masks([case["make"](o) for o in cands]))
    for o, a in zip(cands, approx):
        exact = held_out_errors(case["make"], o, case["data"], case["val"], case["noise"], Prior())
        assert float((a - exact).abs().max()) < 3e-6
        assert abs(float(a.mean()) / float(exact.mean()) - 1) < 2e-3


def test_batched_and_restricted_scores_equal_one_at_a_time(case):
    """A batch, the view restricted to the batch's columns and single candidates give the same numbers."""
    lin = SharedLinearization(case["sup"], case["data"], case["noise"], Prior(), v=case["v"])
    cands = [[o] * 6 for o in range(5)]
    keep = lin.masks([case["make"](o) for o in cands])
    together = lin.loo_errors(keep, chunk=2)
    for i in range(len(cands)):
        alone = lin.loo_errors(keep[i:i + 1])[0]  # restricted to that candidate's own columns
        # (the systems differ in size, so rounding differs; the normal matrices' condition is ~1e12)
        assert torch.allclose(together[i], alone, rtol=1e-7, atol=1e-10)


def test_search_chooses_what_refitting_every_candidate_chooses(case):
    """The batched, linearized search and the one that fits every candidate pick the same orders."""
    from torchcal.identify.order import _select_orders_refit, select_orders

    args = (case["make"], case["data"], None, case["noise"], Prior())
    fast = select_orders(*args, candidates=[1, 2, 3, 4], joint_window=1)
    # select_orders' own defaults for the rest: folds 0, seed 0, per joint, 2 passes, margin 1, no progress
    slow = _select_orders_refit(*args, [1, 2, 3, 4], 0, 0, True, 2, 1, 1.0, None)
    assert fast.orders == slow.orders
    assert abs(fast.score / slow.score - 1) < 3e-3


def test_structure_mask_marks_exactly_the_candidates_entries(case, fanuc, tools_m):
    lin = SharedLinearization(case["sup"], case["data"], case["noise"], Prior(), v=case["v"], gauge=False)
    cand = RobotModel(fanuc, tools_m, orders=[0, 1, 2, 3, 4, 0], backlash=[-1, 0, 1, 1, 0, -1])
    keep = structure_mask(case["sup"], cand, lin.layout)
    names = [n for n, k in zip(lin.layout.names(), keep.tolist()) if k]
    expected = len(cand.parameter_groups()[0].mask.nonzero()) + int(cand.joint_errors.backlash_mask.sum()) + 6 + 9
    assert len(names) == expected
    assert "joint4.eps_z.c3" in names and "joint4.eps_z.c4" not in names and "joint1.eps_x.c1" not in names
    assert "joint1.backlash.c0" not in names and "joint3.backlash.c1" in names


def test_copy_overlap_warm_start_keeps_the_common_terms(fanuc, tools_m):
    a = randomize(RobotModel(fanuc, tools_m, orders=4, backlash=2), 3)
    b = RobotModel(fanuc, tools_m, orders=2, backlash=1)
    copy_overlap(a, b)
    assert torch.equal(b.joint_errors.coef, a.joint_errors.coef[..., :3])
    assert torch.equal(b.joint_errors.backlash, a.joint_errors.backlash[:, :2])
    back = RobotModel(fanuc, tools_m, orders=4, backlash=2)
    copy_overlap(b, back)
    assert torch.equal(back.joint_errors.coef[..., 3:], torch.zeros_like(back.joint_errors.coef[..., 3:]))


def test_recentred_search_matches_the_exact_fit_of_the_incumbent(case):
    """After recenter(key) the superset holds the candidate's own optimum: its cost equals a separate fit's."""
    search = StructureSearch(lambda: case["make"]([4] * 6), case["make"], case["data"], None, case["noise"], Prior(), {},
                             center=(4,) * 6)
    key = (3, 3, 3, 3, 3, 3)
    search.recenter(key)
    alone = case["make"](key)
    r = fit(alone, case["data"], case["noise"], Prior())
    e_search = search.errors([key])[key]
    e_alone = held_out_errors(case["make"], list(key), case["data"], None, case["noise"], Prior())
    assert r.success
    assert float((e_search - e_alone).abs().max()) < 3e-6
    assert abs(float(e_search.mean()) / float(e_alone.mean()) - 1) < 2e-3


def test_default_backlash_order_follows_the_data(fanuc, tools_m):
    """Random approach directions (unconfounded): the joint's order, capped at 3; sequence order: 2."""
    noise = NoiseModel.paper2()
    truth = randomize(RobotModel(fanuc, tools_m, orders=1, backlash=1), 5)
    rand = _data(truth, fanuc, 200, 7, noise, "random")
    seq = _data(truth, fanuc, 200, 7, noise, "sequence")
    lim = fanuc.joint_map.limits
    b, r2 = default_backlash_orders([6, 2, 6, 1, 6, 6], rand.q, rand.direction, lim)
    assert b == [3, 2, 3, 1, 3, 3] and max(r2) < 0.1
    b, r2 = default_backlash_orders([6] * 6, seq.q, seq.direction, lim)
    assert b == [2] * 6 and min(r2) > 0.1
