"""DirectionCoverage: per joint / position bin record of the approach directions in the data."""

import json

import pytest
import torch

from torchcal.analysis.coverage import DirectionCoverage

LIMITS = torch.tensor([[-1.0, 1.0], [0.0, 4.0]], dtype=torch.float64)


def pattern():
    """Joint 1: below the middle only -1, above only +1 (the Sobol sequence-order pattern).
    Joint 2: bins 0..3 of 4, every bin both directions except bin 3 (only +1) and bin 2 (only unknown)."""
    q1 = torch.linspace(-0.95, 0.95, 20, dtype=torch.float64)
    s1 = torch.where(q1 < 0, -1.0, 1.0)
    q2 = torch.tensor([0.5, 0.5, 1.5, 1.5, 2.5, 2.5, 3.5, 3.5] * 2 + [0.2, 1.2, 3.9, 0.7], dtype=torch.float64)
    s2 = torch.tensor([-1, 1, -1, 1, 0, 0, 1, 1] * 2 + [1, -1, 1, -1], dtype=torch.float64)
    return torch.stack([q1, q2], 1), torch.stack([s1, s2], 1)


def test_counts_and_queries():
    q, s = pattern()
    cov = DirectionCoverage.from_data(q, s, LIMITS, bins=4)
    assert cov.counts.shape == (2, 4, 3)
    assert cov.n_rows == 20
    assert int(cov.counts.sum()) == 40
    # joint 1: bins 0, 1 only -1; bins 2, 3 only +1
    assert cov.seen()[0].tolist() == [[True, False], [True, False], [False, True], [False, True]]
    # joint 2: bin 2 only unknowns, bin 3 only +1
    assert cov.seen()[1].tolist() == [[True, True], [True, True], [False, False], [False, True]]
    assert cov.counts[1, 2].tolist() == [0, 4, 0]
    assert cov.both_fraction().tolist() == [0.0, 0.5]

    qq = torch.tensor([[-0.5, 0.5], [-0.5, 3.5], [0.5, 3.5], [0.5, 2.5], [0.9, 2.5], [-5.0, 9.0]], dtype=torch.float64)
    ss = torch.tensor([[-1, -1], [1, 1], [1, -1], [0, 1], [-1, 0], [-1, 1]], dtype=torch.float64)
    out = cov.outside_joints(qq, ss)
    assert out.tolist() == [[False, False], [True, False], [False, True], [False, True], [True, False], [False, False]]
    assert cov.outside(qq, ss).tolist() == [False, True, True, True, True, False]
    # counts at the query (direction 0: every row of that bin)
    assert cov.counts_at(qq[:1], ss[:1]).tolist() == [[5, 3]]
    assert cov.counts_at(torch.tensor([[0.0, 2.5]]), torch.zeros(1, 2)).tolist() == [[5, 4]]
    # min_count raises the bar
    assert cov.outside_joints(qq[:1], ss[:1], min_count=4).tolist() == [[False, True]]


def test_unknown_direction_never_outside_and_no_direction_data():
    q, s = pattern()
    cov = DirectionCoverage.from_data(q, torch.zeros_like(s), LIMITS, bins=3)
    assert cov.has_directions.tolist() == [False, False]
    assert not cov.outside(q, torch.zeros_like(s)).any()
    assert cov.outside(q, s).all()        # known directions were never seen


def test_batched_shapes_dtypes_and_1d_query():
    q, s = pattern()
    cov = DirectionCoverage.from_data(q.float(), s.long(), LIMITS, bins=8)
    assert cov.outside_joints(q[0], s[0]).shape == (1, 2)
    big = q.repeat(500, 1)
    assert cov.outside(big, s.repeat(500, 1)).shape == (10000,)
    assert not cov.outside(big, s.repeat(500, 1)).any()   # the data itself is always inside


def test_dict_round_trip_json():
    q, s = pattern()
    cov = DirectionCoverage.from_data(q, s, LIMITS, bins=5)
    d = json.loads(json.dumps(cov.to_dict()))
    back = DirectionCoverage.from_dict(d)
    assert torch.equal(back.counts, cov.counts) and torch.equal(back.limits, cov.limits)
    assert back.bins == 5
    qq, ss = torch.rand(50, 2, dtype=torch.float64) * 4 - 1, torch.randint(-1, 2, (50, 2)).double()
    assert torch.equal(back.outside_joints(qq, ss), cov.outside_joints(qq, ss))


def test_update_adds_rows():
    q, s = pattern()
    a = DirectionCoverage.from_data(q[:10], s[:10], LIMITS, bins=4)
    b = a.update(q[10:], s[10:])
    assert torch.equal(b.counts, DirectionCoverage.from_data(q, s, LIMITS, bins=4).counts)
    assert a.n_rows == 10


def test_table():
    q, s = pattern()
    rows = DirectionCoverage.from_data(q, s, LIMITS, bins=4).table(["A", "B"])
    assert rows[0] == {"joint": "A", "bins": 4, "both": 0, "minus_only": 2, "plus_only": 2, "none": 0}
    assert rows[1]["none"] == 1 and rows[1]["plus_only"] == 1


@pytest.mark.parametrize("bad", [
    dict(direction=torch.full((3, 2), 2.0)),
    dict(q=torch.zeros(3, 3)),
    dict(limits=torch.tensor([[1.0, -1.0], [0.0, 1.0]])),
    dict(bins=0),
])
def test_validation(bad):
    args = dict(q=torch.zeros(3, 2), direction=torch.ones(3, 2), limits=LIMITS, bins=4)
    args.update(bad)
    with pytest.raises(ValueError):
        DirectionCoverage.from_data(**args)


def test_from_dict_rejects_unknown_format():
    with pytest.raises(ValueError):
        DirectionCoverage.from_dict({"format": "other", "limits": [[0, 1]], "counts": [[[0, 0, 0]]]})


@pytest.mark.skipif(not torch.cuda.is_available(), reason="needs CUDA")
def test_cuda_queries():
    q, s = pattern()
    cov = DirectionCoverage.from_data(q.cuda(), s.cuda(), LIMITS.cuda(), bins=4)
    out = cov.outside_joints(q.cuda(), s.cuda())
    assert out.device.type == "cuda" and not out.any()
    assert torch.equal(cov.to("cuda").outside(q.cuda(), -s.cuda()).cpu(), cov.outside(q, -s))
