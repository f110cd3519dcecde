"""The Paper III truth simulator: angle reading (17)-(22), SDK rebuild, tracker noise (47), ranges, AT targets."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch
from hypothesis import given, settings
from hypothesis import strategies as st

import torchcal
from torchcal.core import units
from torchcal.sim.sensor_truth import (
    SensorTruth,
    from_spherical,
    head_angles,
    sigma_distance,
    sigma_level,
    sts_angles,
    sts_angles_of,
    sts_rotation,
    to_spherical,
    tracker_noisy_points,
    triangle_normal,
)

DEG = units.DEG


@pytest.fixture(scope="module")
def robot():
    return torchcal.load_robot("fanuc_lrmate200i")


@pytest.fixture(scope="module")
def truth(robot):
    return SensorTruth(robot, seed=3)


def _rot(axis, a):
    c, s = math.cos(a), math.sin(a)
    if axis == "x":
        return np.array([[1, 0, 0], [0, c, -s], [0, s, c]])
    return np.array([[c, -s, 0], [s, c, 0], [0, 0, 1]])


def _pose_from_angles(psi, theta, level, beam_el, beam_az, d=2.5):
    """Independent construction (numpy): sensor at distance d seen along (az, el); the head frame s2 has
    y_s2 toward the tracker, x_s2 ⟂ y_s2 inclined by `level` above the horizontal (g = +z); R_s0 = R_s2 (Rz Rx)^T."""
    u = np.array([math.cos(beam_el) * math.cos(beam_az), math.cos(beam_el) * math.sin(beam_az), math.sin(beam_el)])
    p = d * u
    y = -u
    h = np.cross(y, [0, 0, 1.0])
    h /= np.linalg.norm(h)
    w = np.cross(h, y)
    # x = cos t h + sin t w with x . z = sin t |y x z| = sin(level)
    t = math.asin(math.sin(level) / np.linalg.norm(np.cross(y, [0, 0, 1.0])))
    x = math.cos(t) * h + math.sin(t) * w
    R2 = np.stack([x, y, np.cross(x, y)], 1)
    R0 = R2 @ (_rot("z", psi) @ _rot("x", theta)).T
    return torch.tensor(R0), torch.tensor(p)


@settings(max_examples=40, deadline=None)
@given(psi=st.floats(-170, 170), theta=st.floats(-50, 50), level=st.floats(-55, 55),
       el=st.floats(-20, 20), az=st.floats(-180, 180))
def test_angle_reading_inverts_a_known_head(psi, theta, level, el, az):
    """(20)-(21) with the inclination reading give back the angles a pose was built from."""
    R, p = _pose_from_angles(psi * DEG, theta * DEG, level * DEG, el * DEG, az * DEG)
    g = torch.tensor([0.0, 0.0, 1.0])
    a = sts_angles(R[None], p[None], g)[0] / DEG
    assert torch.allclose(a, torch.tensor([psi, theta, level]), atol=1e-7)
    # the SDK rebuild is the inverse: same rotation from (p, angles, g)
    x_hint = R @ torch.tensor([math.cos(psi * DEG), math.sin(psi * DEG), 0.0])
    R_back = sts_rotation(p[None], (a * DEG)[None], g, x_hint[None])[0]
    assert torch.allclose(R_back, R, atol=1e-10)


def test_head_angles_reduce_to_paper_and_skew_keeps_beam():
    """ε = 0: (20) exactly; ε ≠ 0: the real head Rz(ψ) Ry(ε) Rx(θ) still points y_s2 along the beam."""
    R, p = _pose_from_angles(40 * DEG, 20 * DEG, 10 * DEG, 5 * DEG, 30 * DEG)
    psi, theta, _ = head_angles(R[None], p[None], 0.0)
    assert abs(float(psi) - 40 * DEG) < 1e-10 and abs(float(theta) - 20 * DEG) < 1e-10
    eps = 0.5 * DEG
    psi, theta, x = head_angles(R[None], p[None], eps)
    Ry = torch.tensor([[math.cos(eps), 0, math.sin(eps)], [0, 1.0, 0], [-math.sin(eps), 0, math.cos(eps)]])
    y_head = R @ torch.tensor(_rot("z", float(psi))) @ Ry @ torch.tensor(_rot("x", float(theta))) @ torch.tensor([0, 1.0, 0])
    assert torch.allclose(y_head, -p / p.norm(), atol=1e-12)
    assert abs(float(x[0] @ y_head)) < 1e-12  # level axis stays ⟂ the beam


def test_sigma_level_and_distance_follow_46_47():
    s = sigma_level(torch.tensor([0.0, 30.0, -30.0, 45.0, 60.0]) * DEG) / DEG
    assert torch.allclose(s, torch.tensor([0.0025, 0.0025, 0.0025, 0.00505, 0.0076]), atol=1e-12)
    d = sigma_distance(torch.tensor([1.0, 2.0, 2.8]))
    assert torch.allclose(d, torch.tensor([5e-6, 5e-6, 7e-6]))


def test_spherical_noise_matches_its_linear_covariance():
    """Monte Carlo of the spherical draw vs J diag(σ²) Jᵀ by finite differences of (34) (own reference)."""
    p = torch.tensor([[1.9, -1.2, -0.4]])
    n = 40000
    z = torch.randn(n, 3, generator=torch.Generator().manual_seed(0))
    x = tracker_noisy_points(p.expand(n, 3), z)
    a, b, d = (t[0] for t in to_spherical(p))
    J = torch.stack([(from_spherical(a + h[0], b + h[1], d + h[2]) - from_spherical(a - h[0], b - h[1], d - h[2])) / 2e-7
                     for h in 1e-7 * torch.eye(3)], 1)  # (3, 3) columns d/d(α, β, d)
    S = torch.diag(torch.tensor([3.5e-6, 3.5e-6, float(sigma_distance(d))]) ** 2)
    C = J @ S @ J.T
    emp = torch.cov(x.T)
    assert torch.allclose(x.mean(0), p[0], atol=3 * math.sqrt(float(C.diagonal().max()) / n))
    assert float((emp - C).abs().max() / C.diagonal().max()) < 0.04


def test_sampled_commands_are_valid_and_rejections_counted(truth):
    s = truth.sample_commands(60, seed=1, batch=400)
    assert s.q.shape == (60, 6) and bool(truth.valid(s.q).all())
    assert s.n_rejected == sum(s.rejected.values()) and s.n_rejected > 0
    a = sts_angles_of(truth.sensor_pose(s.q), truth.gravity) / DEG
    assert float(a[:, 1].abs().max()) <= 55 and float(a[:, 2].abs().max()) <= 60
    # the candidates dropped really were outside: the raw sequence has invalid poses among its first `drawn`
    raw = torchcal.sim.quasi_random_commands(truth.limits, 400, 1)[: s.drawn]
    ok = truth._range_flags(raw, margin_deg=0.5)[0]
    assert int(ok.sum()) == 60 and bool(ok[-1]) and torch.equal(raw[ok], s.q)
    with pytest.raises(ValueError, match="outside the STS ranges"):
        truth.measure_sts(raw[~truth.valid(raw)][:2], None, 0)


def test_exact_measurement_is_the_true_pose(robot):
    """noise=False, unmodelled=False: the exported (p, R) is the true sensor pose = flange · mount."""
    t = SensorTruth(robot, seed=5, noise=False, unmodelled=False)
    s = t.sample_commands(20, seed=2)
    m = t.measure_sts(s.q, s.direction, seed=0)
    T = t.robot_truth.flange(s.q, s.direction, base=True) @ t.mount
    assert torch.allclose(m.xyz, T[:, :3, 3], atol=1e-12)
    assert torch.allclose(m.extra["rotation"], T[:, :3, :3], atol=1e-10)
    assert torch.allclose(m.extra["sts_angles"], sts_angles_of(T, t.gravity), atol=1e-12)


def test_noise_and_head_errors_have_the_papers_size(truth):
    s = truth.sample_commands(100, seed=4)
    m = truth.measure_sts(s.q, s.direction, seed=9)
    T = truth.sensor_pose(s.q, s.direction, m.extra["v"])
    pos = (m.xyz - T[:, :3, 3]).norm(dim=-1)
    assert 5e-6 < float(pos.mean()) < 25e-6  # tracker at 2-3 m: ~10 µm per axis
    zt, zm = T[:, :3, 2], m.extra["rotation"][:, :, 2]
    ang = torch.acos((zt * zm).sum(-1).clamp(-1, 1))
    assert 1e-5 < float(ang.mean()) < 4e-4  # level-sensor dominated: 0.0025-0.0076° (4e-5-1.3e-4 rad)
    # the distance from the tracker is 2-3 m as Paper III's set-up
    d = m.xyz.norm(dim=-1)
    assert 1.8 < float(d.min()) and float(d.max()) < 3.1
    # the gravity the model does not know
    tilt = math.degrees(math.acos(float(truth.gravity[2])))
    assert abs(tilt - 0.03) < 1e-9
    # static readings (5.3): one robot position, so only the sensor's own noise varies: σ_φ of (46)
    q1 = s.q[:1].repeat(300, 1)
    st_ = truth.measure_sts(q1, torch.ones_like(q1), seed=3, static=True)
    assert bool((st_.extra["v"] == st_.extra["v"][0]).all())
    phi = st_.extra["sts_angles"][:, 2]
    ratio = float(phi.std() / sigma_level(phi.mean()))
    assert 0.85 < ratio < 1.15


def test_targets_form_the_papers_triangle(truth):
    s = truth.sample_commands(30, seed=5)
    m = truth.measure_targets(s.q, s.direction, seed=1)
    assert len(m) == 90 and m.tool.tolist() == [0] * 30 + [1] * 30 + [2] * 30
    P = m.extra["xyz_exact"].reshape(3, 30, 3).transpose(0, 1)  # (poses, vertex, xyz)
    a, b, c = ((P[:, i] - P[:, j]).norm(dim=-1) for i, j in ((0, 1), (1, 2), (2, 0)))
    area = 0.5 * torch.linalg.cross(P[:, 1] - P[:, 0], P[:, 2] - P[:, 0], dim=-1).norm(dim=-1)
    radius = a * b * c / (4 * area)
    assert torch.allclose(radius, torch.full_like(radius, 0.0665), atol=5e-4)  # Paper III 6.2: 66.43 mm
    # the triangle's normal is the flange z axis (targets share one z in the flange frame)
    F = truth.robot_truth.flange(s.q, s.direction, base=True)
    n = triangle_normal(P)
    assert float((1 - (n * F[:, :3, 2]).sum(-1).abs()).max()) < 1e-5
