"""ISO 9283 repeatability and the joint-variance experiment of Paper II, 5.3-5.4."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from torchcal.analysis import (
    iso9283_repeatability,
    joint_variance_from_pairs,
    joint_variance_plan,
    joint_variances,
    pair_angular_errors,
)
from torchcal.core.measurements import Measurements
from torchcal.models.robot import RobotModel

F64 = torch.float64


def test_iso9283_on_points_with_known_distances():
    # pairs ±u_j keep the barycentre exactly at the centre, so l_j are the chosen lengths
    rng = np.random.default_rng(0)
    lengths = rng.uniform(0.01, 0.05, 15)
    u = rng.normal(size=(15, 3))
    u /= np.linalg.norm(u, axis=1, keepdims=True)
    centre = np.array([0.4, -0.1, 0.7])
    pts = np.concatenate([centre + lengths[:, None] * u, centre - lengths[:, None] * u])
    l = np.concatenate([lengths, lengths])
    expected = l.mean() + 3 * l.std(ddof=1)
    rp = iso9283_repeatability(torch.as_tensor(pts))
    assert rp.shape == () and float(rp) == pytest.approx(expected, rel=1e-12)
    # batched poses give the per-pose values
    both = iso9283_repeatability(torch.as_tensor(np.stack([pts, 2 * pts])))
    torch.testing.assert_close(both, torch.tensor([expected, 2 * expected], dtype=F64))


def test_iso9283_of_isotropic_gaussian_spread():
    # l ~ Maxwell(σ): mean 2σ sqrt(2/π), std σ sqrt(3 - 8/π)
    sigma = 1e-5
    x = torch.randn(40_000, 3, generator=torch.Generator().manual_seed(2), dtype=F64) * sigma
    expected = sigma * (2 * math.sqrt(2 / math.pi) + 3 * math.sqrt(3 - 8 / math.pi))
    assert float(iso9283_repeatability(x)) == pytest.approx(expected, rel=0.01)


def test_iso9283_input_errors():
    with pytest.raises(ValueError, match="at least 2 cycles"):
        iso9283_repeatability(torch.zeros(1, 3))
    bad = torch.zeros(2, 5, 3)
    bad[1, 3, 0] = float("nan")
    with pytest.raises(ValueError, match="pose 2, cycle 4"):
        iso9283_repeatability(bad)


def _ring(axis_point, axis_dir, radius, phi, height):
    w = axis_dir / np.linalg.norm(axis_dir)
    e1 = np.cross(w, [1.0, 0, 0])
    e1 /= np.linalg.norm(e1)
    e2 = np.cross(w, e1)
    return axis_point + radius * (np.cos(phi)[:, None] * e1 + np.sin(phi)[:, None] * e2) + height * w


def test_joint_variance_recovers_a_known_angular_variance():
    rng = np.random.default_rng(5)
    M, sigma = 4000, math.radians(0.003)  # per-attempt std of where the joint stops
    c, w = np.array([0.1, -0.3, 0.45]), np.array([0.2, 0.9, -0.3])
    phi = rng.uniform(-math.pi, math.pi, M)  # the whole joint range, all quadrants
    p1 = _ring(c, w, 0.3, phi + sigma * rng.normal(size=M), 0.05)
    p2 = _ring(c, w, 0.3, phi + sigma * rng.normal(size=M), 0.05)
    var = float(joint_variance_from_pairs(torch.as_tensor(p1), torch.as_tensor(p2), torch.as_tensor(c), torch.as_tensor(w)))
    # the estimate has ~M degrees of freedom: relative std sqrt(2/M) = 2.2 %
    assert var == pytest.approx(sigma**2, rel=0.1)
    # as Paper II computed it (against the midpoint of two): half the per-attempt variance
    literal = float(joint_variance_from_pairs(torch.as_tensor(p1), torch.as_tensor(p2), c, w, unbiased=False))
    assert literal == pytest.approx(sigma**2 / 2, rel=0.1)
    # each pair's two errors mirror each other about the midpoint
    e = pair_angular_errors(torch.as_tensor(p1), torch.as_tensor(p2), c, w)
    torch.testing.assert_close(e[:M], -e[M:], atol=1e-12, rtol=0)


def test_joint_variance_removes_known_tracker_noise():
    rng = np.random.default_rng(6)
    M, sigma, sigma_m, r = 4000, math.radians(0.002), 5e-6, 0.25
    c, w = np.zeros(3), np.array([0.0, 0.0, 1.0])
    phi = rng.uniform(-math.pi, math.pi, M)
    p1 = _ring(c, w, r, phi + sigma * rng.normal(size=M), 0.0) + sigma_m * rng.normal(size=(M, 3))
    p2 = _ring(c, w, r, phi + sigma * rng.normal(size=M), 0.0) + sigma_m * rng.normal(size=(M, 3))
    raw = float(joint_variance_from_pairs(torch.as_tensor(p1), torch.as_tensor(p2), c, w))
    clean = float(joint_variance_from_pairs(torch.as_tensor(p1), torch.as_tensor(p2), c, w, sigma_m=sigma_m))
    assert raw == pytest.approx(sigma**2 + (sigma_m / r) ** 2, rel=0.1)
    assert clean == pytest.approx(sigma**2, rel=0.1)


def test_joint_variance_plan_structure(fanuc):
    plan = joint_variance_plan(fanuc, positions=9)
    assert len(plan) == 6 * 2 * 9 * 2
    jm = fanuc.joint_map
    theta0 = jm.to_joint(torch.zeros(1, 6, dtype=F64))
    for j in range(6):
        for fwd in (True, False):
            sel = (plan.joint == j) & (plan.forward == fwd)
            s = 1.0 if fwd else -1.0
            d = jm.to_joint(plan.q[sel]) - theta0
            da = jm.to_joint(plan.approach[sel]) - theta0
            others = [k for k in range(6) if k != j]
            assert d[:, others].abs().max() < 1e-14 and da[:, others].abs().max() < 1e-14
            # approached from below (forward) or above (backward), each position twice
            assert ((d[:, j] - da[:, j]) * s > 0).all()
            assert torch.equal(plan.q[sel][0::2], plan.q[sel][1::2])
            assert torch.equal(plan.direction[sel][:, j], torch.full((18,), s, dtype=F64))
            assert plan.q[sel][:, j].unique().numel() == 9
    assert jm.within_limits(plan.q[plan.joint != 1]).all()
    seq, measured = plan.sequence()
    assert torch.equal(seq[measured], plan.q) and torch.equal(seq[~measured], plan.approach)


def test_joint_variances_from_a_simulated_robot(fanuc, tools_m):
    """Simulated robot with constant errors; the moving joint stops with known forward / backward spreads."""
    actual = RobotModel(fanuc, tools_m, orders=0)
    g = torch.Generator().manual_seed(3)
    with torch.no_grad():
        actual.joint_errors.coef.normal_(0.0, 1e-3, generator=g)
    sd_f = torch.deg2rad(torch.tensor([1.9e-3, 6e-4, 2.9e-3, 5.5e-3, 5.2e-3, 2.4e-2], dtype=F64))  # Table 5 scale
    sd_b = 0.6 * sd_f
    plan = joint_variance_plan(fanuc, positions=400)
    j = plan.joint
    sd = torch.where(plan.forward, sd_f[j], sd_b[j])
    v_theta = torch.zeros_like(plan.q)
    v_theta[torch.arange(len(plan)), j] = torch.randn(len(plan), generator=g, dtype=F64) * sd
    v = torch.linalg.solve(fanuc.joint_map.coupling, v_theta.T).T  # URDF-joint error -> controller space
    data = plan.to_measurements(tool=0)
    with torch.no_grad():
        data.xyz = actual.points(data.q, data.tool, v=v)
    table = joint_variances(plan, data)
    # 400 pairs per cell: relative std of a variance sqrt(2/400) = 7 %; allow about 4 of them
    torch.testing.assert_close(table.forward, sd_f**2, rtol=0.3, atol=0)
    torch.testing.assert_close(table.backward, sd_b**2, rtol=0.3, atol=0)
    rows = table.rows()
    assert [r["joint"] for r in rows] == [1, 2, 3, 4, 5, 6]
    assert rows[5]["forward_deg2"] == pytest.approx(float(table.forward[5]) * (180 / math.pi) ** 2)
    # mismatched measurements are refused by row
    bad = Measurements.from_tensors(data.q.clone(), 0, data.xyz, source="jv.csv")
    bad.q[7, 0] += 1e-3
    with pytest.raises(ValueError, match="jv.csv, row 8"):
        joint_variances(plan, bad)
