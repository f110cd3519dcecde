"""STSInstrument: angles (17)-(27), residual (28)-(30), noise (46), range checks, identification on a simulated rig."""

import logging
import math
import time

import numpy as np
import pytest
import torch
from conftest import random_commands
from hypothesis import assume, given, settings
from hypothesis import strategies as st

from torchcal.core.exceptions import TorchcalError
from torchcal.identify import fit
from torchcal.identify.problem import CalibrationProblem, NoiseModel, Prior
from torchcal.kinematics.transforms import twist_to_transform
from torchcal.measure import STSInstrument
from torchcal.models.sensor_rig import SensorRig
from torchcal.measure.sts import (
    SensorRangeError,
    STSSelection,
    level_sigma_deg,
    paper3_angle_sigmas,
    sts_angles,
    sts_rotation,
    sts_validity,
    wrap_angle,
)
from torchcal.measure.tracker import TrackerNoise
from torchcal.core.measurements import Measurements

DEG = math.pi / 180


# ---------------------------------------------------------------- independent numpy reference (paper text)
def np_angles(R: np.ndarray, p: np.ndarray, g: np.ndarray) -> np.ndarray:
    """(17)-(22) row by row in numpy, level angle = asin(x_s2 . g) (inclination from the horizontal)."""
    out = []
    for Rr, pr in zip(R, p):
        a = -Rr.T @ pr / np.linalg.norm(pr)
        psi = math.atan2(-a[0], a[1])
        theta = math.asin(a[2])
        x = Rr @ np.array([math.cos(psi), math.sin(psi), 0.0])
        out.append([psi, theta, math.asin(float(x @ g))])
    return np.array(out)


def np_export(R_true: np.ndarray, p: np.ndarray, angles: np.ndarray, g: np.ndarray) -> np.ndarray:
    """What the tracker software reports (12) for raw angles (11): x_s2 perpendicular to the beam p, inclined
    asin(x_s2 . g) = phi, on the side of the true x_s2; y_s2 = -beam; R = R_s2 F_STS(psi, theta)^T."""
    out = []
    for Rt, pr, (psi, theta, phi) in zip(R_true, p, angles):
        b = pr / np.linalg.norm(pr)
        gp = g - (g @ b) * b
        u = gp / np.linalg.norm(gp)
        w = np.cross(b, u)
        x_true = Rt @ np.array([math.cos(psi), math.sin(psi), 0.0])
        a = math.sin(phi) / np.linalg.norm(gp)
        x2 = a * u + math.copysign(math.sqrt(1 - a * a), float(x_true @ w)) * w
        y2 = -b
        R_s2 = np.stack([x2, y2, np.cross(x2, y2)], 1)
        cz, sz, cx, sx = math.cos(psi), math.sin(psi), math.cos(theta), math.sin(theta)
        F = np.array([[cz, -sz * cx, sz * sx], [sz, cz * cx, -cz * sx], [0, sx, cx]])  # (11)
        out.append(R_s2 @ F.T)
    return np.array(out)


def tilted(gx: float, gy: float) -> torch.Tensor:
    return torch.tensor([gx, gy, math.sqrt(1 - gx * gx - gy * gy)])


# ---------------------------------------------------------------------------------- pure functions
@settings(max_examples=60, deadline=None)
@given(st.floats(-179, 179), st.floats(-55, 55), st.floats(-60, 60), st.floats(0.5, 10.0),
       st.floats(-math.pi, math.pi), st.floats(0.3, 2.8), st.floats(-0.05, 0.05), st.floats(-0.05, 0.05),
       st.sampled_from([-1.0, 1.0]))
def test_angles_round_trip(psi, theta, phi, d, az, polar, gx, gy, branch):
    """raw angles -> exported pose (sts_rotation) -> recovered angles (sts_angles): the same, any tracker tilt."""
    p = d * torch.tensor([math.cos(az) * math.sin(polar), math.sin(az) * math.sin(polar), math.cos(polar)])
    g = tilted(gx, gy)
    horizontal = math.sqrt(max(0.0, 1 - float(g @ p / d) ** 2))
    assume(abs(math.sin(phi * DEG)) < horizontal - 1e-6)
    ang = torch.tensor([psi, theta, phi]) * DEG
    R = sts_rotation(p, ang, g, branch)
    assert torch.allclose(R.T @ R, torch.eye(3), atol=1e-12) and abs(float(torch.linalg.det(R)) - 1) < 1e-12
    assert torch.allclose(sts_angles(R, p, g), ang, atol=1e-9)
    assert np.allclose(np_angles(R[None].numpy(), p[None].numpy(), g.numpy())[0], ang.numpy(), atol=1e-9)


def test_angles_match_the_numpy_reference_on_random_frames():
    g0 = torch.Generator().manual_seed(0)
    R = torch.linalg.qr(torch.randn(50, 3, 3, generator=g0))[0]
    R = R * torch.linalg.det(R)[:, None, None]
    p = torch.randn(50, 3, generator=g0) * 3
    g = tilted(0.02, -0.03)
    ref = np_angles(R.numpy(), p.numpy(), g.numpy())
    assert np.allclose(sts_angles(R, p, g).numpy(), ref, atol=1e-12)
    # exported with the branch of the true frame, the frame comes back (numpy reference and torch alike)
    assert np.allclose(np_export(R.numpy(), p.numpy(), ref, g.numpy()), R.numpy(), atol=1e-9)
    b = p / p.norm(dim=-1, keepdim=True)
    u = g - (b @ g)[:, None] * b
    w = torch.linalg.cross(b, u / u.norm(dim=-1, keepdim=True))
    x_true = (R @ torch.stack([torch.cos(torch.from_numpy(ref[:, 0])), torch.sin(torch.from_numpy(ref[:, 0])),
                               torch.zeros(50)], -1)[..., None])[..., 0]
    branch = torch.sign((x_true * w).sum(-1))
    assert torch.allclose(sts_rotation(p, torch.from_numpy(ref), g, branch), R, atol=1e-9)


def test_level_angle_is_the_inclination_from_the_horizontal():
    """Chosen reading of (21): phi = asin(x_s2 . g) = 90 deg - arccos(x_s2 . g); 0 when level, + when x_s2 points up."""
    g = torch.tensor([0.0, 0.0, 1.0])
    p = torch.tensor([3.0, 0.0, 0.0])  # horizontal beam along tracker x; y_s2 = -x
    for incl in (-59.0, -20.0, 0.0, 45.0, 59.0):
        x2 = torch.tensor([0.0, math.cos(incl * DEG), math.sin(incl * DEG)])  # perpendicular to the beam
        y2 = torch.tensor([-1.0, 0.0, 0.0])
        R = torch.stack([x2, y2, torch.linalg.cross(x2, y2)], 1)  # s0 = s2: psi = theta = 0
        ang = sts_angles(R, p, g) / DEG
        assert abs(ang[0]) < 1e-12 and abs(ang[1]) < 1e-12
        assert abs(float(ang[2]) - incl) < 1e-9
        assert abs(float(ang[2]) - (90 - math.degrees(math.acos(float(x2 @ g))))) < 1e-9
    # the range check uses this reading
    xyz = torch.stack([p, p])
    Rs = torch.stack([sts_rotation(p, torch.tensor([0.0, 0.0, 59.0 * DEG]), g), sts_rotation(p, torch.tensor([0.0, 0.0, 61.0 * DEG]), g)])
    v = sts_validity(xyz, Rs, g)
    assert v.valid.tolist() == [True, False] and v.problems[0][:2] == (1, "level")


def test_angle_sigmas_are_paper_46():
    phi = torch.tensor([0.0, -30.0, 30.0, 45.0, -60.0])
    assert torch.allclose(level_sigma_deg(phi), torch.tensor([0.0025, 0.0025, 0.0025, 0.00017 * 45 - 0.0026, 0.00017 * 60 - 0.0026]))
    assert abs(float(level_sigma_deg(torch.tensor(30.0 + 1e-9))) - 0.0025) < 1e-9  # continuous at 30 deg
    s = paper3_angle_sigmas(torch.tensor([[1.0, 0.2, 45 * DEG]])) / DEG
    assert torch.allclose(s, torch.tensor([[0.0005, 0.0005, 0.00017 * 45 - 0.0026]]))


def test_wrap_keeps_yaw_residuals_small_across_180():
    d = torch.tensor([2 * math.pi - 1e-4, -2 * math.pi + 1e-4, 0.3])
    assert torch.allclose(wrap_angle(d), torch.tensor([-1e-4, 1e-4, 0.3]), atol=1e-12)
    inst = STSInstrument(torch.ones(1, 3), torch.tensor([[math.pi - 1e-5, 0.0, 0.0]]), 1e-5)
    r = inst.residual(torch.tensor([[1.0, 1.0, 1.0, -math.pi + 1e-5, 0.0, 0.0]]), inst.observed)
    assert torch.allclose(r, torch.tensor([[0.0, 0, 0, 2e-5, 0, 0]]), atol=1e-12)


# ---------------------------------------------------------------------------------- simulated rig
def tracker_base() -> torch.Tensor:
    T = torch.eye(4)
    T[:3, :3] = torch.tensor([[-1.0, 0, 0], [0, -1, 0], [0, 0, 1]])
    T[:3, 3] = torch.tensor([2.0, 0.3, -0.2])
    return T


MOUNT = twist_to_transform(torch.tensor([0.0, 0.0, 0.0, 0.0, 0.06, 0.04]))


def make_rig(fanuc, orders=1, **kw) -> SensorRig:
    return SensorRig.for_robot(fanuc, orders=orders, base_nominal=tracker_base(), mount=MOUNT, **kw)


def sts_data(truth: SensorRig, q: torch.Tensor, g_meas: torch.Tensor, seed: int, noise: bool = True, joint_var=None):
    """STS measurements of the truth rig: raw angles from the true pose and true gravity (+ (46) noise), tracker
    noise on the position, the pose exported with the tracker's measured gravity (numpy, paper text)."""
    gen = torch.Generator().manual_seed(seed)
    qq = q if joint_var is None else q + torch.randn(q.shape, generator=gen) * joint_var.sqrt()
    with torch.no_grad():
        T = truth.sensor_pose(qq)
        g_true = truth.gravity_vector()
    R, p = T[:, :3, :3].numpy(), T[:, :3, 3].numpy()
    ang = np_angles(R, p, g_true.numpy())
    if noise:
        sig = paper3_angle_sigmas(torch.from_numpy(ang)).numpy()
        ang = ang + sig * torch.randn(ang.shape, generator=gen).numpy()
        cov = TrackerNoise.paper3().covariance(T[:, :3, 3])
        p = p + (torch.linalg.cholesky(cov) @ torch.randn(len(q), 3, 1, generator=gen))[..., 0].numpy()
    R_exp = np_export(R, p, ang, g_meas.numpy())
    data = Measurements.from_tensors(q, 0, torch.from_numpy(p))
    data.extra["rotation"] = torch.from_numpy(R_exp)
    return data


def valid_commands(rig, count, seed, g):
    """Quasi-random commands whose true pose the STS can measure (paper 5.4)."""
    q = random_commands(rig.robot, count * 4, seed)
    with torch.no_grad():
        T = rig.sensor_pose(q)
    ok = sts_validity(T[:, :3, 3], T[:, :3, :3], g).valid
    return q[ok][:count]


def test_residual_is_zero_at_the_truth(fanuc):
    """Export with the tracker's untilted gravity, truth gravity tilted: the truth rig's residual is zero."""
    rig = make_rig(fanuc, gravity=[0.01, -0.02])
    q = valid_commands(rig, 30, 0, rig.gravity_vector().detach())
    data = sts_data(rig, q, torch.tensor([0.0, 0.0, 1.0]), 0, noise=False)
    inst = STSInstrument.from_measurements(data, noise=1e-5)
    with torch.no_grad():
        r = inst.residual(inst.predict(rig, q, data.tool), inst.observed)
        assert r.abs().max() < 1e-12
        # a wrong gravity shows in the level angle only
        rig.gravity.zero_()
        r1 = inst.residual(inst.predict(rig, q, data.tool), inst.observed)
    assert r1[:, :5].abs().max() < 1e-12 and r1[:, 5].abs().max() > 1e-3


def test_autograd_jacobian_matches_finite_differences(fanuc, one_thread):
    rig = make_rig(fanuc, orders=1, gravity=[0.01, -0.02])
    g = torch.Generator().manual_seed(1)
    with torch.no_grad():
        rig.model.joint_errors.coef.copy_(torch.randn(rig.model.joint_errors.coef.shape, generator=g) * 1e-3
                                          * rig.model.joint_errors.mask)
        rig.mount.twist.copy_(torch.randn(6, generator=g) * 1e-3)
    q = valid_commands(rig, 6, 2, rig.gravity_vector().detach())
    data = sts_data(rig, q, torch.tensor([0.0, 0.0, 1.0]), 3)
    inst = STSInstrument.from_measurements(data, noise=TrackerNoise.paper3())
    problem = CalibrationProblem(rig, data, NoiseModel.from_robot(fanuc), Prior(), instrument=inst)
    x = problem.layout.get()
    v = torch.randn(q.shape, generator=g) * 1e-4
    f, A, C = problem.linearize(x, v)
    assert torch.allclose(f, problem.whitened_residual(x, v), atol=1e-9)
    h = 1e-7

    def fd(dx, dv):
        return (problem.whitened_residual(x + h * dx, v + h * dv) - problem.whitened_residual(x - h * dx, v - h * dv)) / (2 * h)

    def close(a, b):
        return torch.allclose(a, b, rtol=1e-5, atol=1e-5 * (1 + float(b.abs().max())))

    # every parameter and joint error at once along random directions, then each of the rig's own groups alone
    dx = torch.randn(x.shape, generator=g)
    dv = torch.randn(v.shape, generator=g) * 1e-2
    assert close(A @ dx + (C @ dv[..., None])[..., 0], fd(dx, dv))
    names = problem.layout.names()
    for j, name in enumerate(names):
        if name.startswith(("gravity", "mount", "base")) or name.endswith("c1"):
            e = torch.zeros_like(x)
            e[j] = 1.0
            assert close(A[:, :, j], fd(e, torch.zeros_like(v))), name
    for k in range(q.shape[1]):
        e = torch.zeros_like(v)
        e[:, k] = 1.0
        assert close(C[:, :, k], fd(torch.zeros_like(x), e))


def test_invalid_rows_are_reported_never_used(fanuc, caplog):
    rig = make_rig(fanuc)
    q = random_commands(fanuc, 60, 5)
    g = torch.tensor([0.0, 0.0, 1.0])
    with torch.no_grad():
        T = rig.sensor_pose(q)
    valid = sts_validity(T[:, :3, 3], T[:, :3, :3], g).valid
    assert 0 < int((~valid).sum()) < 60
    data = Measurements.from_tensors(q, 0, T[:, :3, 3])
    data.extra["rotation"] = T[:, :3, :3]
    bad_rows = data.rows[~valid].tolist()
    with pytest.raises(SensorRangeError) as info:
        STSInstrument.from_measurements(data, noise=1e-5)
    assert isinstance(info.value, TorchcalError) and info.value.rows == bad_rows
    assert f"row {bad_rows[0]}: " in str(info.value) and "invalid='exclude'" in str(info.value)
    assert any(w in str(info.value) for w in ("roll angle", "level angle"))
    with caplog.at_level(logging.WARNING, logger="torchcal"):
        sel = STSInstrument.from_measurements(data, noise=1e-5, invalid="exclude")
    assert isinstance(sel, STSSelection) and sel.excluded == bad_rows
    assert torch.equal(sel.valid, valid) and torch.equal(info.value.valid, valid)
    assert len(sel.instrument) == len(sel.data) == int(valid.sum())
    assert torch.equal(sel.data.rows, data.rows[valid])
    assert torch.allclose(sel.instrument.observed[:, :3], data.xyz[valid])
    assert "excluded" in caplog.text and f"row {bad_rows[0]}" in caplog.text
    # a failed reading at the tracker origin is invalid too
    data.xyz[0] = 0.0
    with pytest.raises(SensorRangeError, match="tracker origin"):
        STSInstrument.from_measurements(data.subset(torch.tensor([0])), noise=1e-5)


def test_subset_cat_and_whitening_blocks(fanuc):
    rig = make_rig(fanuc)
    q = valid_commands(rig, 10, 6, torch.tensor([0.0, 0.0, 1.0]))
    data = sts_data(rig, q, torch.tensor([0.0, 0.0, 1.0]), 6)
    inst = STSInstrument.from_measurements(data)  # default: the tracker noise of Paper III (47)
    cov = inst.weight.cov
    assert torch.allclose(cov[:, :3, :3], TrackerNoise.paper3().covariance(data.xyz))
    assert torch.allclose(cov[:, 3:, 3:], torch.diag_embed(paper3_angle_sigmas(inst.angles) ** 2))
    assert cov[:, :3, 3:].abs().max() == 0
    both = STSInstrument.cat([inst.subset(torch.arange(4)), inst.subset(torch.arange(4, 10))])
    assert torch.equal(both.observed, inst.observed) and torch.allclose(both.weight.cov, cov)


def test_identification_recovers_base_mount_and_gravity(fanuc, one_thread):
    """Truth: base, mount and gravity perturbed, joint errors zero and held; STS data with tracker, angle and
    joint noise, exported with the tracker's (untilted) gravity; fit recovers the three to noise level."""
    truth = make_rig(fanuc, gravity=[0.004, -0.007])
    with torch.no_grad():
        truth.model.base.twist.copy_(torch.tensor([2e-3, -1e-3, 3e-3, 1e-3, -2e-3, 1.5e-3]))
        truth.mount.twist.copy_(torch.tensor([-4e-3, 2e-3, 5e-3, 5e-4, -1e-3, 2e-3]))
    g_meas = torch.tensor([0.0, 0.0, 1.0])
    q = valid_commands(truth, 60, 7, truth.gravity_vector().detach())
    noise = NoiseModel.from_robot(fanuc)
    data = sts_data(truth, q, g_meas, 8, joint_var=noise.joint_var_fwd)
    rig = make_rig(fanuc)
    inst = STSInstrument.from_measurements(data, gravity=g_meas)
    result = fit(rig, data, noise, instrument=inst, fixed=("model.joint_errors",))
    assert result.success
    with torch.no_grad():
        e_base = (rig.model.base.twist - truth.model.base.twist).abs()
        e_mount = (rig.mount.twist - truth.mount.twist).abs()
        e_g = (rig.gravity - truth.gravity).abs()
    assert e_base[:3].max() < 2e-5 and e_base[3:].max() < 2e-5  # perturbations 1e-3..3e-3
    assert e_mount[:3].max() < 5e-5 and e_mount[3:].max() < 2e-5
    assert e_g.max() < 5e-5  # tilt 8e-3; 60 level readings of sigma 4e-5 rad give ~1e-5
    # whitened residuals at noise level: chi^2 per degree of freedom near 1
    f = result.fun / (len(data) * 6)
    assert 0.3 < f < 2.0


def test_linearization_is_fast(fanuc, one_thread):
    """300 rows x order-3 FANUC rig, autograd Jacobians: well under a second (after the first, tracing call)."""
    rig = make_rig(fanuc, orders=3)
    q = random_commands(fanuc, 300, 9)
    with torch.no_grad():
        T = rig.sensor_pose(q)
    data = Measurements.from_tensors(q, 0, T[:, :3, 3])
    data.extra["rotation"] = T[:, :3, :3]
    sel = STSInstrument.from_measurements(data, noise=1e-5, invalid="exclude")
    # repeat rows to 300
    idx = torch.arange(300) % len(sel.data)
    data = sel.data.subset(idx)
    inst = sel.instrument.subset(idx)
    problem = CalibrationProblem(rig, data, NoiseModel.from_robot(fanuc), Prior(), instrument=inst)
    x = problem.layout.get()
    problem.linearize(x, problem.v_zero())
    t = time.perf_counter()
    _, A, _ = problem.linearize(x, problem.v_zero())
    elapsed = time.perf_counter() - t
    assert A.shape[:2] == (300, 6) and elapsed < 1.0, elapsed


def test_full_identification_with_joint_errors_free(fanuc, one_thread):
    """Order-1 truth (seeded joint errors, base, mount, gravity tilt); everything free, gauge fixed by fit():
    validation poses predicted to ~10 um and ~1e-4 rad from 5-10 mm and 1e-2 rad nominal, chi^2 / dof ~ 1."""
    from conftest import randomize

    from torchcal.measure.pose import rotation_error

    truth = make_rig(fanuc, orders=1, gravity=[0.004, -0.007])
    randomize(truth.model, 0)
    with torch.no_grad():
        truth.mount.twist.copy_(torch.tensor([-4e-3, 2e-3, 5e-3, 5e-4, -1e-3, 2e-3]))
    g_meas = torch.tensor([0.0, 0.0, 1.0])
    g_true = truth.gravity_vector().detach()
    noise = NoiseModel.from_robot(fanuc)
    data = sts_data(truth, valid_commands(truth, 80, 7, g_true), g_meas, 8, joint_var=noise.joint_var_fwd)
    rig = make_rig(fanuc, orders=1)
    result = fit(rig, data, noise, instrument=STSInstrument.from_measurements(data, gravity=g_meas))
    assert result.success and 0.5 < result.fun / (len(data) * 6) < 1.5
    assert any(n.startswith("joint6.") for n in result.pinned)
    assert (rig.gravity - truth.gravity).abs().max() < 7e-4  # 10 % of the tilt
    qv = valid_commands(truth, 50, 17, g_true)
    with torch.no_grad():
        T, M, N = truth.sensor_pose(qv), rig.sensor_pose(qv), rig.nominal_sensor_pose(qv)
    dp = (M[:, :3, 3] - T[:, :3, 3]).norm(dim=-1)
    dr = rotation_error(M[:, :3, :3], T[:, :3, :3]).norm(dim=-1)
    assert (N[:, :3, 3] - T[:, :3, 3]).norm(dim=-1).mean() > 3e-3
    assert dp.mean() < 3e-5 and dp.max() < 1e-4 and dr.mean() < 2e-4


def test_docstring_examples():
    import doctest

    import torchcal.measure.sts as mod

    res = doctest.testmod(mod, optionflags=doctest.ELLIPSIS)
    assert res.failed == 0 and res.attempted > 0


def test_rows_without_a_pose_are_invalid_not_out_of_range():
    g = torch.tensor([0.0, 0.0, 1.0])
    p = torch.tensor([[3.0, 0.0, 0.0]] * 3)
    R = sts_rotation(p, torch.tensor([[0.1, 0.2, 0.3]] * 3), g)
    p[1, 2] = float("nan")
    R[2, 0, 0] = float("nan")
    v = sts_validity(p, R, g)
    assert v.valid.tolist() == [True, False, False]
    assert [(r, k) for r, k, _ in v.problems] == [(1, "pose"), (2, "pose")]
    assert bool(v.angles[1:].isnan().all()) and torch.allclose(v.angles[0], torch.tensor([0.1, 0.2, 0.3]))


def test_closed_form_jacobians_equal_autograd_for_every_group():
    """STSInstrument.predict_jacobians (rig pose Jacobians + closed-form angle derivatives) vs torch.func."""
    import torchcal
    from torchcal.identify import CalibrationProblem, NoiseModel, Prior
    from torchcal.models.sensor_rig import SensorRig
    from torchcal.sim.sensor_truth import SensorTruth

    robot = torchcal.load_robot("fanuc_lrmate200i")
    st = SensorTruth(robot, seed=3)
    s = st.sample_commands(20, seed=3)
    m = st.measure_sts(s.q, s.direction, seed=4)
    rig = SensorRig.for_robot(robot, 2, True, base_nominal=st.base_nominal, mount=st.mount_nominal,
                              gravity=st.virtual_level, compliance="functions")
    g = torch.Generator().manual_seed(0)
    with torch.no_grad():
        for p in rig.parameters():
            p.add_(1e-3 * torch.randn(p.shape, generator=g, dtype=p.dtype))
    inst = STSInstrument.from_measurements(m, gravity=st.virtual_level)
    P = CalibrationProblem(rig, m, NoiseModel.from_robot(robot), Prior(), instrument=inst)
    x, v = P.layout.get(), 1e-4 * torch.randn(P.v_zero().shape, generator=g, dtype=torch.float64)
    fa, Aa, Ca = P.linearize(x, v, "autodiff")
    fc, Ac, Cc = P.linearize(x, v, "closed")
    assert torch.allclose(fa, fc, atol=1e-8)
    assert (Aa - Ac).abs().max() <= 1e-9 * Aa.abs().max()
    assert (Ca - Cc).abs().max() <= 1e-9 * Ca.abs().max()
