"""backlash_confounding: direction/position dependence per joint and backlash identifiability per coefficient."""

import json

import pytest
import torch

from torchcal.analysis.confounding import backlash_confounding, direction_position_dependence
from torchcal.identify import NoiseModel
from torchcal.core.measurements import Measurements
from torchcal.models.robot import RobotModel
from torchcal.sim.sampling import approach_directions, quasi_random_commands


def sobol_data(robot, count, shuffle, seed=0, tools=1):
    q = quasi_random_commands(robot.joint_map.limits, count, seed, shuffle=shuffle)
    s = approach_directions(q)
    N = q.shape[0]
    return Measurements.from_tensors(q.repeat(tools, 1), torch.arange(tools).repeat_interleave(N),
                                     direction=s.repeat(tools, 1), pose=torch.arange(N).repeat(tools))


def test_sequence_order_is_confounded_shuffle_less(fanuc):
    seq = backlash_confounding(sobol_data(fanuc, 250, shuffle=False), limits=fanuc.joint_map.limits)
    shuf = backlash_confounding(sobol_data(fanuc, 250, shuffle=True), limits=fanuc.joint_map.limits)
    assert seq.joint_names == [f"J{j}" for j in range(1, 7)]
    assert float(seq.r2.max()) > 0.75                       # J2: s ≈ sign(q2 - mid)
    assert float(seq.correlation.max()) > 0.8
    # a shuffle leaves the E[s | q] = 2u - 1 dependence (R² ≈ 1/3), clearly below the sequence's
    assert float(shuf.r2.mean()) < 0.45 < float(seq.r2[1:4].mean())
    w = seq.warnings()
    assert any(m.startswith("J2:") and "confounded" in m for m in w)
    assert not any(m.startswith("J2:") for m in shuf.warnings())
    rows = seq.table()
    assert [r["joint"] for r in rows] == seq.joint_names and rows[1]["r2"] == pytest.approx(float(seq.r2[1]))
    assert rows[1]["backlash_vif"] is None
    json.dumps(seq.to_dict())


def test_random_independent_directions_low(fanuc):
    q = quasi_random_commands(fanuc.joint_map.limits, 400, 3)
    s = torch.where(torch.rand(q.shape, generator=torch.Generator().manual_seed(1)) < 0.5, -1.0, 1.0)
    rep = backlash_confounding(Measurements.from_tensors(q, 0, direction=s), limits=fanuc.joint_map.limits)
    assert float(rep.r2.max()) < 0.06 and float(rep.correlation.abs().max()) < 0.2
    assert rep.warnings() == [] and int(rep.one_sided_bins.sum()) == 0


def test_exact_values_against_numpy_style_reference():
    g = torch.Generator().manual_seed(0)
    q = torch.rand(200, 2, generator=g, dtype=torch.float64) * 2 - 1
    s = torch.stack([torch.where(q[:, 0] > 0.2, 1.0, -1.0), torch.where(torch.rand(200, generator=g) < 0.5, 1.0, -1.0)], 1)
    s[:10, 1] = 0.0                                           # unknown directions are left out
    lim = torch.tensor([[-1.0, 1.0], [-1.0, 1.0]], dtype=torch.float64)
    rows, corr, r2, plus = direction_position_dependence(q, s, lim, order=3)
    assert rows.tolist() == [200, 190]
    keep = s[:, 1] != 0
    ref = torch.corrcoef(torch.stack([s[keep, 1], q[keep, 1]]))[0, 1]
    assert float(corr[1]) == pytest.approx(float(ref), abs=1e-12)
    X = torch.stack([torch.ones(190), q[keep, 1], 2 * q[keep, 1] ** 2 - 1, 4 * q[keep, 1] ** 3 - 3 * q[keep, 1]], 1)
    y = s[keep, 1]
    res = y - X @ torch.linalg.lstsq(X, y[:, None]).solution[:, 0]
    assert float(r2[1]) == pytest.approx(float(1 - res.square().sum() / (y - y.mean()).square().sum()), abs=1e-10)
    assert float(plus[0]) == pytest.approx(float((s[:, 0] > 0).double().mean()))
    assert float(r2[0]) > 0.6                                 # a step is well explained by a cubic


def test_one_sided_joint_and_no_directions():
    q = torch.linspace(-1, 1, 50, dtype=torch.float64)[:, None].repeat(1, 2)
    s = torch.stack([torch.ones(50), torch.where(torch.arange(50) % 2 == 0, 1.0, -1.0)], 1).double()
    rep = backlash_confounding(Measurements.from_tensors(q, 0, direction=s), names=["A", "B"])
    assert torch.isnan(rep.correlation[0]) and float(rep.r2[0]) == 1.0
    w = rep.warnings()
    assert len(w) == 1 and w[0].startswith("A: every row approaches from +1")
    none = backlash_confounding(Measurements.from_tensors(q, 0))
    assert none.rows.tolist() == [0, 0] and none.warnings() == [] and torch.isnan(none.r2).all()
    with pytest.raises(ValueError):
        backlash_confounding(Measurements.from_tensors(q, 0, direction=s), names=["A"])


@pytest.fixture(scope="module")
def small_model(fanuc, tools_m):
    return RobotModel(fanuc, tools_m, orders=2, backlash=1)


def test_backlash_parameters_identifiability(fanuc, small_model):
    seq = backlash_confounding(sobol_data(fanuc, 120, shuffle=False, tools=2), model=small_model,
                               noise=NoiseModel.paper2())
    names = [p.name for p in seq.parameters]
    assert names == small_model.joint_errors.parameter_names()[1]
    assert seq.joint_names == small_model.joint_errors.joint_names
    j2 = {p.name: p for p in seq.parameters if p.joint == 1}
    assert all(0.0 <= p.r2_joint <= p.r2_position + 1e-9 <= 1.0 + 1e-9 for p in seq.parameters)
    assert max(p.r2_position for p in j2.values()) > 0.8
    assert all(p.corr_with.startswith("joint2.") for p in j2.values())
    dec = backlash_confounding(sobol_data(fanuc, 120, shuffle=True, tools=2), model=small_model,
                               noise=NoiseModel.paper2())
    assert max(p.vif for p in dec.parameters if p.joint == 1) < max(p.vif for p in j2.values())
    w = seq.warnings(vif_threshold=5.0)
    assert any(m.startswith("joint2.backlash.") and "poorly identifiable" in m for m in w)
    assert {r["name"] for r in seq.parameter_table()} == set(names)
    assert seq.table()[1]["backlash_vif"] == pytest.approx(max(p.vif for p in j2.values()))
    # the plain (unwhitened) Jacobian gives the same picture
    plain = backlash_confounding(sobol_data(fanuc, 120, shuffle=False, tools=2), model=small_model)
    assert max(p.r2_position for p in plain.parameters if p.joint == 1) > 0.8


def test_model_without_backlash_has_no_parameters(fanuc, tools_m):
    m = RobotModel(fanuc, tools_m, orders=1, backlash=None)
    rep = backlash_confounding(sobol_data(fanuc, 40, shuffle=False), model=m)
    assert rep.parameters == [] and rep.joint_names == m.joint_errors.joint_names


def test_few_shuffled_poses_are_judged_by_the_adjusted_r2(fanuc):
    """A shuffled order's R² (≈ 1/3) plus what a cubic fits by chance on 30 rows passes 0.5 for one joint in six:
    the warning reads the R² adjusted for the rows (checked against its definition in numpy), which halves those
    chance warnings, while a sequence-ordered set of the same size still warns."""
    import numpy as np

    from torchcal.analysis.confounding import R2_THRESHOLD, adjusted_r2

    assert adjusted_r2(0.51, 30, 3) == pytest.approx(1 - 0.49 * 29 / 26) and adjusted_r2(0.51, 3, 3) == 0.51
    warned = plain = 0
    for seed in range(40):
        rep = backlash_confounding(sobol_data(fanuc, 30, shuffle=True, seed=seed), limits=fanuc.joint_map.limits)
        warned += sum("confounded" in m for m in rep.warnings())
        plain += int((rep.r2 > R2_THRESHOLD).sum())
        for j in range(6):
            n, r2 = int(rep.rows[j]), float(rep.r2[j])
            assert adjusted_r2(r2, n, 3) == pytest.approx(float(1 - (1 - np.float64(r2)) * (n - 1) / (n - 4)))
    assert plain > 20 and warned < 0.6 * plain  # 240 joints: 38 plain, 20 adjusted
    seq = backlash_confounding(sobol_data(fanuc, 30, shuffle=False), limits=fanuc.joint_map.limits)
    assert sum("confounded" in m for m in seq.warnings()) >= 3  # J2-J4 (R² 0.74-0.85)
