"""The simulated XYZCB machine tool of Paper I: chain, magnitudes, smoothness, region, split, noise, CSV."""


import numpy as np
import pandas as pd
import pytest
import torch
from numpy.polynomial import chebyshev as npcheb

from torchcal.sim.machine_truth import (
    BAND_G,
    PAPER1_LIMITS,
    SET_CODES,
    MachineTruth,
    _rigid_fit_residuals,
    limits_si,
    measured_region_floor,
    simulate_machine_dataset,
)

LIM = limits_si()


@pytest.fixture(scope="module")
def dataset():
    truth = MachineTruth(seed=0)
    data, split = simulate_machine_dataset(truth, seed=0)
    return truth, data, split


def tool_vectors(data, lengths=(0.4029, 0.5009)):
    tv = torch.zeros(len(data), 3, dtype=torch.float64)
    tv[:, 2] = torch.tensor(lengths, dtype=torch.float64)[data.tool]
    return tv


def test_nominal_chain_matches_closed_form():
    g = torch.Generator().manual_seed(0)
    q = LIM[:, 0] + torch.rand(20, 5, generator=g, dtype=torch.float64) * (LIM[:, 1] - LIM[:, 0])
    l = 0.5
    p = MachineTruth(0).nominal_points(q, torch.tensor([0, 0, l], dtype=torch.float64))
    C, B = q[:, 3], q[:, 4]
    ref = q[:, :3] + l * torch.stack([C.cos() * B.sin(), C.sin() * B.sin(), B.cos()], 1)
    torch.testing.assert_close(p, ref, rtol=0, atol=1e-14)


def test_without_errors_the_truth_is_a_rigid_motion_of_the_nominal():
    truth = MachineTruth(seed=3, scale=0.0, unmodelled=False)
    g = torch.Generator().manual_seed(1)
    q = LIM[:, 0] + torch.rand(50, 5, generator=g, dtype=torch.float64) * (LIM[:, 1] - LIM[:, 0])
    tv = torch.tensor([0, 0, 0.45], dtype=torch.float64)
    r = _rigid_fit_residuals(truth.nominal_points(q, tv), truth.points(q, tv))
    assert r.max() < 1e-12
    # the tracker frame error E_mf is there, so the raw difference is not zero
    assert (truth.points(q, tv) - truth.nominal_points(q, tv)).norm(dim=1).min() > 1e-5


def test_reproducible_by_seed():
    q = LIM.mean(1).expand(3, 5).clone()
    q[1, 0] += 0.5
    tv = torch.tensor([0, 0, 0.5], dtype=torch.float64)
    a, b, c = MachineTruth(4).points(q, tv), MachineTruth(4).points(q, tv), MachineTruth(5).points(q, tv)
    assert torch.equal(a, b) and (a - c).norm() > 1e-6
    d1, s1 = simulate_machine_dataset(MachineTruth(4), n_commands=30, n_interpolation=3, n_extrapolation=3, seed=2)
    d2, s2 = simulate_machine_dataset(MachineTruth(4), n_commands=30, n_interpolation=3, n_extrapolation=3, seed=2)
    assert torch.equal(d1.xyz, d2.xyz) and all(torch.equal(s1[k], s2[k]) for k in s1)


def test_nominal_residual_in_paper_band(dataset):
    """Paper I Table 5: nominal 0.307 mm mean / 0.739 mm max (identification set)."""
    truth, data, split = dataset
    nom = truth.nominal_points(data.q, tool_vectors(data))
    idx = split["identification"]
    r = _rigid_fit_residuals(nom[idx], data.xyz[idx]) * 1e3
    assert 0.2 < float(r.mean()) < 0.45 and 0.4 < float(r.max()) < 1.0


def test_error_functions_smooth_bounded_and_not_polynomial():
    truth = MachineTruth(seed=0)
    s = torch.linspace(0, 1, 2001, dtype=torch.float64)[:, None]
    q = LIM[:, 0] + s * (LIM[:, 1] - LIM[:, 0])
    e = truth.component_errors(q)                                  # (K, 5, 6)
    lin, ang = e[..., :3].abs().max(), e[..., 3:].abs().max()
    assert 5e-6 < lin < 5e-4 and 5e-6 < ang < 2e-4                 # tens to hundreds of µm, tens of µrad
    d2 = e[2:] - 2 * e[1:-1] + e[:-2]                              # smooth: tiny second differences
    assert (d2.abs().amax(0) < 1e-3 * e.abs().amax(0) + 1e-15).all()
    # each axis is a function of its own position only: moving another axis leaves it unchanged
    q2 = q.clone()
    q2[:, 0] = q2.flip(0)[:, 0]
    torch.testing.assert_close(truth.component_errors(q2)[:, 1:], e[:, 1:])
    # non-polynomial: an order-6 Chebyshev fit leaves a visible remainder on some component of C
    lam = np.linspace(-1, 1, 2001)
    rem = []
    for c in range(6):
        y = e[:, 3, c].numpy()
        fit = npcheb.chebval(lam, npcheb.chebfit(lam, y, 6))
        rem.append(np.abs(y - fit).max() / (np.abs(y).max() + 1e-30))
    assert max(rem) > 1e-3


def test_region_shape_and_split(dataset):
    _, data, split = dataset
    assert [len(split[k]) for k in ("identification", "interpolation", "extrapolation")] == [490, 50, 50]
    allrows = torch.cat(list(split.values())).sort().values
    assert torch.equal(allrows, torch.arange(len(data)))
    assert data.n_poses == 295 and torch.equal(torch.bincount(data.pose), torch.full((295,), 2))
    q = data.q
    lo, hi = LIM[:, 0], LIM[:, 1]
    assert ((q >= lo - 1e-12) & (q <= hi + 1e-12)).all()
    floor = measured_region_floor(q[:, 4])
    band = BAND_G * (LIM[2, 1] - LIM[2, 0])
    assert (q[:, 2] >= floor - 1e-12).all()
    ext, ide = split["extrapolation"], torch.cat([split["identification"], split["interpolation"]])
    assert (q[ext, 2] < floor[ext] + band + 1e-12).all() and (q[ide, 2] >= floor[ide] + band - 1e-12).all()
    # no low Z at large |B|
    big_b = q[:, 4].abs() > 0.8 * LIM[4].abs().max()
    assert (q[big_b, 2] > LIM[2, 0] + 0.2 * (LIM[2, 1] - LIM[2, 0])).all()
    # some extrapolation points lie below every identification Z: the Z tables are extrapolated there
    assert (q[ext, 2] < q[split["identification"], 2].min()).sum() >= 5
    assert set(data.extra["set"].tolist()) == set(SET_CODES.values())


def test_tracker_noise_sigma():
    truth = MachineTruth(seed=1)
    data, _ = simulate_machine_dataset(truth, n_commands=400, seed=3, axis_sigma=(0.0, 0.0), tracker_sigma_mm=0.01)
    d = (data.xyz - data.extra["xyz_exact"]) * 1e3
    assert abs(float(d.std()) - 0.01) < 0.0012 and abs(float(d.mean())) < 0.0015


def test_unmodelled_sources_are_small_but_present():
    g = torch.Generator().manual_seed(2)
    q = LIM[:, 0] + torch.rand(100, 5, generator=g, dtype=torch.float64) * (LIM[:, 1] - LIM[:, 0])
    tv = torch.tensor([0, 0, 0.5009], dtype=torch.float64)
    t1 = torch.ones(100, dtype=torch.float64)
    on, off = MachineTruth(0), MachineTruth(0, unmodelled=False)
    diff = (on.points(q, tv, t=t1) - off.points(q, tv, t=t1)).norm(dim=1)
    assert 5e-6 < float(diff.mean()) < 1e-4
    drift = (on.points(q, tv, t=t1) - on.points(q, tv, t=0 * t1)).norm(dim=1)   # thermal drift along pose order
    assert 5e-6 < float(drift.mean()) < 1e-4
    assert float((off.points(q, tv, t=t1) - off.points(q, tv, t=0 * t1)).abs().max()) == 0.0


def test_csv_contract(tmp_path):
    truth = MachineTruth(seed=0)
    p = tmp_path / "m.csv"
    data, _ = simulate_machine_dataset(truth, n_commands=20, n_interpolation=2, n_extrapolation=2, seed=0, csv_path=p)
    df = pd.read_csv(p)
    assert list(df.columns) == ["pose", "tool", "q1", "q2", "q3", "q4", "q5", "x", "y", "z", "set"]
    np.testing.assert_allclose(df[["q1", "q2", "q3"]].to_numpy(), data.q[:, :3].numpy() * 1e3, rtol=1e-11)
    np.testing.assert_allclose(df[["q4", "q5"]].to_numpy(), np.degrees(data.q[:, 3:].numpy()), rtol=1e-11)
    np.testing.assert_allclose(df[["x", "y", "z"]].to_numpy(), data.xyz.numpy() * 1e3, rtol=1e-11)
    lo, hi = np.array(PAPER1_LIMITS).T
    qf = df[["q1", "q2", "q3", "q4", "q5"]].to_numpy()
    assert (qf >= lo - 1e-6).all() and (qf <= hi + 1e-6).all()


def test_true_error_slopes_per_half_axis_motion():
    """The docstring's slopes: the machine's own tool-tip error changes by under a millimetre over half of
    any linear axis's travel or of B's, C (540 deg) by at most ~1.3 mm (tool length and tracker frame excluded)."""
    truth = MachineTruth(seed=0, unmodelled=False)
    truth.tool_len.zero_()
    truth.base_eps.zero_()
    truth.base_delta.zero_()
    g = torch.Generator().manual_seed(0)
    q = LIM[:, 0] + torch.rand(500, 5, generator=g, dtype=torch.float64) * (LIM[:, 1] - LIM[:, 0])
    tv = torch.tensor([0, 0, 0.5009], dtype=torch.float64)
    half = (LIM[:, 1] - LIM[:, 0]) / 2
    h = 1e-6
    out = []
    for i in range(5):
        dq = torch.zeros(5, dtype=torch.float64)
        dq[i] = h
        e1 = truth.points(q + dq, tv) - truth.nominal_points(q + dq, tv)
        e0 = truth.points(q - dq, tv) - truth.nominal_points(q - dq, tv)
        out.append(float(((e1 - e0) / (2 * h) * half[i]).norm(dim=1).max()) * 1e3)
    assert max(out[:3] + out[4:]) < 0.8 and out[3] < 1.5
    assert min(out) > 0.1          # every axis carries errors that change along it


def test_csv_reads_back_through_the_contract_reader(tmp_path):
    from torchcal.io.csv import read_measurements
    from torchcal.kinematics import load_robot

    p = tmp_path / "m.csv"
    data, _ = simulate_machine_dataset(MachineTruth(seed=0), n_commands=12, n_interpolation=2, n_extrapolation=2,
                                       seed=0, csv_path=p)
    back = read_measurements(p, load_robot("five_axis_xyzcb"), n_tools=2)
    torch.testing.assert_close(back.q, data.q, rtol=1e-11, atol=1e-14)
    torch.testing.assert_close(back.xyz, data.xyz, rtol=1e-11, atol=1e-14)
    assert torch.equal(back.tool, data.tool) and torch.equal(back.pose, data.pose)
    assert [int(v) for v in back.extra["set"]] == data.extra["set"].tolist()   # extra columns come back as text
