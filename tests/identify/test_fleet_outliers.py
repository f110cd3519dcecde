"""The fleet's robust scores (torchcal.identify.fleet_outliers.scores_from_values): finite and meaningful when
units share a value (a file given twice, a fleet of three), and the modified z-score of Iglewicz and Hoaglin
otherwise."""

import torch
from hypothesis import given, settings
from hypothesis import strategies as st

from torchcal.identify.fleet_outliers import MAD_FLOOR, scores_from_values


def test_equal_units_give_a_finite_score_not_one_divided_by_nothing():
    F = torch.tensor([[1.0e-4], [1.0e-4], [1.2e-4]], dtype=torch.float64)  # two units identical
    sc = scores_from_values({"rms": F}, ["J1"])
    z = sc.z["rms"][:, 0]
    assert torch.isfinite(z).all() and z.max() < 100
    # the floor: a spread of 1 % of the median, so the third unit is 20 % / 1 % = 20 MADs (times 0.6745) above
    assert abs(float(z[2]) - 0.6745 * 0.2 / MAD_FLOOR) < 1e-9


@settings(max_examples=50, deadline=None)
@given(st.lists(st.floats(1e-6, 1e-2), min_size=5, max_size=30, unique=True))
def test_a_spread_fleet_gets_the_plain_modified_z_score(values):
    F = torch.tensor(values, dtype=torch.float64)[:, None]
    med = F.median(0).values
    mad = (F - med).abs().median(0).values
    sc = scores_from_values({"rms": F}, ["J1"])
    if float(mad) >= MAD_FLOOR * float(med):  # the floor does not bite: exactly Iglewicz-Hoaglin's
        assert torch.allclose(sc.z["rms"], 0.6745 * (F - med) / mad, rtol=1e-12)
    assert torch.isfinite(sc.z["rms"]).all()
