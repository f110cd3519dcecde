"""Residual statistics: Gamma 99 % against a known Gamma law, residuals against known offsets."""

from __future__ import annotations

import numpy as np
import pytest
import torch
from hypothesis import given, settings
from hypothesis import strategies as st
from scipy import stats

from torchcal.analysis import gamma99, percent_decrease, point_residuals, residual_stats, stats_table
from torchcal.analysis.stats import ResidualStats, grouped_stats
from torchcal.core.measurements import Measurements


def test_gamma99_matches_true_quantile_of_a_large_gamma_sample():
    # residuals of 0.1 mm scale, shape like Fig. 13; with 1e5 draws the fitted 99 % point
    # is within ~0.5 % of the truth, while an empirical or normal-based quantile is not the target
    a, scale = 2.5, 4e-5
    x = stats.gamma.rvs(a, scale=scale, size=100_000, random_state=np.random.default_rng(3))
    truth = stats.gamma.ppf(0.99, a, scale=scale)
    g = gamma99(torch.as_tensor(x))
    assert g == pytest.approx(truth, rel=0.02)
    # a normal 99 % point of the same data is far off: the test would catch a wrong family
    assert abs(np.mean(x) + 2.326 * np.std(x) - truth) / truth > 0.05


def test_gamma99_is_unit_consistent_and_residual_stats_exact():
    x = stats.gamma.rvs(3.0, scale=1.0, size=300, random_state=np.random.default_rng(0))
    s = residual_stats(torch.as_tensor(x))
    assert s.mean == pytest.approx(x.mean(), rel=1e-14)
    assert s.max == x.max() and s.count == 300
    assert residual_stats(x * 1e-3).gamma99 == pytest.approx(s.gamma99 * 1e-3, rel=1e-6)
    assert s.scaled(2.0).gamma99 == pytest.approx(2 * s.gamma99)


def test_gamma99_undefined_cases():
    assert np.isnan(gamma99([1.0]))
    assert np.isnan(residual_stats([0.0, 1.0, 2.0]).gamma99)  # a zero residual has zero Gamma likelihood
    with pytest.raises(ValueError, match="negative"):
        residual_stats([1.0, -1.0])
    with pytest.raises(ValueError, match="not finite"):
        residual_stats([1.0, float("nan")])


class OffsetModel:
    """Predicts q[:, :3] (+ v[:, :3] if v is passed): a stand-in with a known prediction."""

    def points(self, q, tool, direction=None, v=None):
        p = q[:, :3].clone()
        return p if v is None else p + v[:, :3]

    def nominal_points(self, q, tool):
        return torch.zeros(q.shape[0], 3, dtype=q.dtype)


def test_point_residuals_equal_known_offsets():
    g = torch.Generator().manual_seed(0)
    q = torch.randn(50, 6, generator=g, dtype=torch.float64)
    direction = torch.randn(50, 3, generator=g, dtype=torch.float64)
    length = torch.rand(50, generator=g, dtype=torch.float64) * 1e-3
    offset = direction / direction.norm(dim=1, keepdim=True) * length[:, None]
    data = Measurements.from_tensors(q, torch.zeros(50, dtype=torch.long), q[:, :3] + offset)
    r = point_residuals(OffsetModel(), data)
    assert r.shape == (50,)
    torch.testing.assert_close(r, length, rtol=0, atol=1e-15)
    torch.testing.assert_close(point_residuals(OffsetModel(), data, nominal=True), (q[:, :3] + offset).norm(dim=1))


def test_point_residuals_on_robot_model_ignore_joint_errors(fanuc, tools_m):
    from torchcal.models.robot import RobotModel

    model = RobotModel(fanuc, tools_m, orders=1)
    g = torch.Generator().manual_seed(1)
    lim = fanuc.joint_map.limits
    q = lim[:, 0] + torch.rand(20, 6, generator=g, dtype=torch.float64) * (lim[:, 1] - lim[:, 0])
    tool = torch.randint(0, 3, (20,), generator=g)
    shift = torch.tensor([1e-4, -2e-4, 3e-4], dtype=torch.float64)
    with torch.no_grad():
        xyz = model.points(q, tool) + shift
    data = Measurements.from_tensors(q, tool, xyz)
    torch.testing.assert_close(point_residuals(model, data), shift.norm().expand(20), rtol=0, atol=1e-12)


def test_point_residuals_name_rows_without_measurements():
    q = torch.zeros(3, 6, dtype=torch.float64)
    xyz = torch.zeros(3, 3, dtype=torch.float64)
    xyz[1, 0] = float("nan")
    with pytest.raises(ValueError, match=r"rows \[2\]"):
        point_residuals(OffsetModel(), Measurements.from_tensors(q, 0, xyz))


def test_percent_decrease_and_table_reproduce_paper_table7():
    rows = {
        "Nominal": ResidualStats(3.418, 8.210, 8.721, 300),
        "Modeled": ResidualStats(0.104, 0.261, 0.277, 300),
        "Compensated": ResidualStats(0.102, 0.287, 0.264, 300),
    }
    t = stats_table(rows, reference="Nominal")
    assert [r["label"] for r in t] == list(rows)
    assert t[0]["mean_decrease"] is None
    # Table 7: 96.96 / 96.82 / 96.82 % and 97.02 / 96.50 / 97.00 %
    assert t[1]["mean_decrease"] == pytest.approx(96.96, abs=0.01)
    assert t[1]["max_decrease"] == pytest.approx(96.82, abs=0.01)
    assert t[1]["gamma99_decrease"] == pytest.approx(96.82, abs=0.01)
    assert t[2]["mean_decrease"] == pytest.approx(97.02, abs=0.01)
    assert t[2]["max_decrease"] == pytest.approx(96.50, abs=0.01)
    # the paper's 97.00 % was taken from unrounded values: 0.264 / 8.721 gives 96.97 %
    assert t[2]["gamma99_decrease"] == pytest.approx(97.00, abs=0.05)
    assert percent_decrease(2.0, 0.5) == 75.0
    assert "mean_decrease" not in stats_table(rows)[0]
    with pytest.raises(KeyError):
        stats_table(rows, reference="CPA")


def test_grouped_stats_split_by_label():
    r = torch.tensor([1.0, 2.0, 3.0, 10.0, 20.0])
    g = torch.tensor([1, 1, 1, 2, 2])
    out = grouped_stats(r, g)
    assert out[1].mean == pytest.approx(2.0) and out[2].max == 20.0 and out[2].count == 2


@settings(max_examples=30, deadline=None)
@given(shape=st.floats(0.3, 50.0), scale=st.floats(1e-6, 1e3), n=st.integers(2, 400), seed=st.integers(0, 10_000))
def test_gamma99_equals_scipy_stats_gamma_fit(shape, scale, n, seed):
    """The closed-form MLE (Newton on log a - digamma(a) = s) gives scipy.stats.gamma.fit(floc=0)'s quantile."""
    from scipy import stats

    x = np.random.default_rng(seed).gamma(shape, scale, size=n)
    a, _, sc = stats.gamma.fit(x / x.mean(), floc=0)
    ref = stats.gamma.ppf(0.99, a, loc=0, scale=sc) * x.mean()
    assert gamma99(x) == pytest.approx(ref, rel=1e-6)


def test_gamma_density_and_fit_match_scipy_stats():
    from torchcal.core.gamma_fit import gamma_mle, gamma_pdf

    x = np.random.default_rng(3).gamma(2.5, 0.04, size=300)
    a, scale = gamma_mle(x)
    a_ref, _, scale_ref = stats.gamma.fit(x, floc=0)
    assert a == pytest.approx(a_ref, rel=1e-6) and scale == pytest.approx(scale_ref, rel=1e-6)
    xs = np.linspace(0, 0.5, 50)
    np.testing.assert_allclose(gamma_pdf(xs, a, scale), stats.gamma.pdf(xs, a, scale=scale), rtol=1e-10, atol=1e-300)
    assert gamma_mle(np.full(5, 0.1)) is None


@settings(max_examples=60, deadline=None)
@given(a=st.floats(0.05, 500.0), q=st.floats(1e-6, 1 - 1e-6), scale=st.floats(1e-6, 1e3))
def test_gamma_ppf_inverts_scipy_special_gammainc(a, q, scale):
    """The Newton / bisection quantile (torch.special) equals scipy's inverse of the regularized incomplete gamma."""
    from scipy import special

    from torchcal.core.gamma_fit import gamma_ppf

    assert gamma_ppf(q, a, scale) == pytest.approx(float(special.gammaincinv(a, q)) * scale, rel=1e-8)


@settings(max_examples=12, deadline=None)
@given(seed=st.integers(0, 10_000), directions=st.booleans(), backlash=st.booleans(), order=st.integers(0, 5))
def test_compiled_point_residuals_are_the_models(fanuc, tools_m, seed, directions, backlash, order):
    """point_residuals(compiled=True) (compensation's compiled flange kernel) gives a RobotModel's own residuals,
    random errors in every term, with and without approach directions; a model the kernel cannot take (gravity
    compliance) falls back to its own points."""
    from conftest import randomize
    from torchcal.models.robot import RobotModel

    g = torch.Generator().manual_seed(seed)
    lim = fanuc.joint_map.limits
    q = lim[:, 0] + torch.rand(40, 6, generator=g, dtype=torch.float64) * (lim[:, 1] - lim[:, 0])
    s = torch.where(torch.rand(40, 6, generator=g) > 0.5, 1.0, -1.0).to(torch.float64)
    tool = torch.randint(0, 3, (40,), generator=g)
    xyz = 0.5 * torch.rand(40, 3, generator=g, dtype=torch.float64)
    data = Measurements.from_tensors(q, tool, xyz, direction=s if directions else None)
    from torchcal.kinematics.transforms import twist_to_transform

    tracker = twist_to_transform(torch.tensor([0.3, -0.2, 1.1, 1.5, -0.4, 0.2], dtype=torch.float64))  # the frame
    for compliance in (False, True):
        model = randomize(RobotModel(fanuc, tools_m, orders=order, backlash=backlash, base_nominal=tracker,
                                     compliance=compliance), seed)
        torch.testing.assert_close(point_residuals(model, data, compiled=True), point_residuals(model, data),
                                   rtol=0, atol=1e-13)
