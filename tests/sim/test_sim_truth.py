import math

import numpy as np
import pytest
import torch
from hypothesis import given, settings
from hypothesis import strategies as st

from conftest import PRISMATIC_URDF, fanuc_dh_reference, random_commands
from torchcal.kinematics import load_robot
from torchcal.kinematics.transforms import so3_exp, twist_to_transform
from torchcal.models.robot import RobotModel
from torchcal.sim import TruthRobot, harmonic_limit, perpendicular_axes, quasi_random_commands
from torchcal.sim.truth import (
    PAPER2_BETA_DEG, PAPER2_DELTA_A_MM, PAPER2_DELTA_ALPHA_DEG, PAPER2_DELTA_D_MM, PAPER2_THETA_OFFSET_DEG,
)

DEG = math.pi / 180
JOINT_DEPENDENT = ("pitch_scale", "pitch_amp", "wave_amp", "out_amp", "wobble", "backlash", "ripple_amp", "cross_amp")
CONSTANT = ("origin_shift", "origin_tilt", "center", "mastering")
FRAMES = ("base_twist", "tools_delta")


def keep_only(truth: TruthRobot, *names: str) -> TruthRobot:
    """Zero every error buffer except ``names`` (phases and variations are harmless alone)."""
    with torch.no_grad():
        for name in JOINT_DEPENDENT + CONSTANT + FRAMES:
            if name not in names:
                getattr(truth, name).zero_()
    return truth


def signs(B: int, n: int, seed: int) -> torch.Tensor:
    return torch.where(torch.rand(B, n, generator=torch.Generator().manual_seed(seed)) < 0.5, -1.0, 1.0)


def dh_reference(q_deg: np.ndarray, dtheta_deg, dd_mm, da_mm, dalpha_deg, beta_deg) -> np.ndarray:
    """Paper II Table 2 + (7)-(8): Rz(θ+Δθ) Tz(d+Δd) Tx(a+Δa) Rx(α+Δα) Ry(β), plain numpy, metres."""
    q = np.radians(np.atleast_2d(q_deg))
    theta = np.stack([q[:, 0], q[:, 1] - np.pi / 2, q[:, 1] + q[:, 2], q[:, 3], q[:, 4], q[:, 5]], 1)
    theta = theta + np.radians(dtheta_deg)
    d = np.array([0, 0, 0, -290, 0, -80.0]) + np.append(dd_mm, 0.0)
    a = np.array([150, 250, 75, 0, 0, 0.0]) + np.append(da_mm, 0.0)
    alpha = np.radians(np.array([-90, 180, -90, 90, -90, 180.0]) + np.append(dalpha_deg, 0.0))
    beta = np.radians(np.append(beta_deg, 0.0))
    out = np.tile(np.eye(4), (q.shape[0], 1, 1))
    for i in range(6):
        ct, st_ = np.cos(theta[:, i]), np.sin(theta[:, i])
        Rz = np.zeros((q.shape[0], 4, 4))
        Rz[:, 0, 0], Rz[:, 0, 1], Rz[:, 1, 0], Rz[:, 1, 1] = ct, -st_, st_, ct
        Rz[:, 2, 2] = Rz[:, 3, 3] = 1.0
        ca, sa, cb, sb = np.cos(alpha[i]), np.sin(alpha[i]), np.cos(beta[i]), np.sin(beta[i])
        Tl = np.array([[1, 0, 0, a[i]], [0, ca, -sa, 0], [0, sa, ca, d[i]], [0, 0, 0, 1.0]])  # Tz Tx Rx
        Ry = np.array([[cb, 0, sb, 0], [0, 1, 0, 0], [-sb, 0, cb, 0], [0, 0, 0, 1.0]])
        out = out @ Rz @ (Tl @ Ry)
    out[:, :3, 3] /= 1000.0
    return out


def test_zero_truth_is_nominal_fk(fanuc, tools_m):
    truth = TruthRobot(fanuc, tools_m)
    q = random_commands(fanuc, 200, 0)
    s = signs(200, 6, 1)
    F = truth.flange(q, s)
    assert torch.equal(F, fanuc.chain.fk(fanuc.joint_map.to_joint(q)))
    assert np.abs(F.numpy() - fanuc_dh_reference(q.numpy() / DEG)).max() < 1e-15
    tool = torch.arange(200) % 3
    assert torch.equal(truth.points(q, tool, s), truth.nominal_points(q, tool))


def test_table9_constants_match_independent_dh_with_paper_perturbations(fanuc, tools_m):
    """Constants only: the truth must be Paper II (7)-(8) with Table 9's values, Hayati β included."""
    truth = keep_only(TruthRobot.fanuc_paper2(fanuc, tools_m, 0), "origin_shift", "origin_tilt", "mastering")
    q = random_commands(fanuc, 300, 2)
    ref = dh_reference(q.numpy() / DEG, PAPER2_THETA_OFFSET_DEG, PAPER2_DELTA_D_MM, PAPER2_DELTA_A_MM,
                       PAPER2_DELTA_ALPHA_DEG, PAPER2_BETA_DEG)
    assert np.abs(truth.flange(q).numpy() - ref).max() < 1e-14
    # and the errors are not negligible: mm-level at the flange
    nominal = fanuc_dh_reference(q.numpy() / DEG)
    assert np.linalg.norm(ref[:, :3, 3] - nominal[:, :3, 3], axis=1).mean() > 1e-3


def test_mastering_on_joint1_rotates_points_about_base_z(fanuc, tools_m):
    truth = TruthRobot(fanuc, tools_m)
    delta = 0.37 * DEG
    with torch.no_grad():
        truth.mastering[0] = delta
    q = random_commands(fanuc, 100, 3)
    tool = torch.arange(100) % 3
    Rz = so3_exp(torch.tensor([0.0, 0.0, delta]))
    assert torch.allclose(truth.points(q, tool), truth.nominal_points(q, tool) @ Rz.T, atol=1e-15)


def _expected_angle_error(truth: TruthRobot, u: np.ndarray, s: np.ndarray) -> np.ndarray:
    """The documented Δθ formula, written again in numpy from the buffers (revolute joints).

    u: the error variables (the commands for 'command' joints); the cross-coupling
    of joint i reads joint i + 1 (the last joint: joint n - 1).
    """
    b = {k: getattr(truth, k).numpy() for k in
         ("mastering", "pitch_scale", "pitch_amp", "pitch_phase", "wave_amp", "wave_phase", "backlash",
          "backlash_var", "backlash_phase", "ripple_amp", "ripple_freq", "ripple_phase", "cross_amp", "cross_phase")}
    wave = sum(b["wave_amp"][:, k] * np.cos((k + 1) * u + b["wave_phase"][:, k]) for k in range(2))
    pitch = u * (b["pitch_scale"] + b["pitch_amp"] * np.sin(u / 2 + b["pitch_phase"]))
    back = b["backlash"] * (1 + b["backlash_var"] * np.sin(u + b["backlash_phase"]))
    ripple = b["ripple_amp"] * np.cos(b["ripple_freq"] * u + b["ripple_phase"])
    nb = np.r_[np.arange(1, u.shape[1]), u.shape[1] - 2]
    cross = b["cross_amp"] * np.sin(u + u[:, nb] + b["cross_phase"])
    return b["mastering"] + pitch + wave + ripple + cross + s * back


def test_angle_errors_are_rotations_about_the_joint_axes(fanuc, tools_m):
    """Mastering, pitch, strain wave, ripple, cross-coupling and backlash = the nominal robot at θ + Δθ(u, s).

    The FANUC truth's errors follow the commands (Paper II (24)): u = q, not θ
    (θ3 = q2 + q3); before the error-variable choice this test evaluated Δθ on θ.
    """
    truth = keep_only(TruthRobot.fanuc_paper2(fanuc, tools_m, 4), "mastering", "pitch_scale", "pitch_amp",
                      "wave_amp", "backlash", "ripple_amp", "cross_amp")
    assert truth.error_variable == ["command"] * 6
    q = random_commands(fanuc, 150, 5)
    s = signs(150, 6, 6)
    theta = fanuc.joint_map.to_joint(q)
    u = truth.error_variables(q)
    assert torch.equal(u, q)
    dth = _expected_angle_error(truth, q.numpy(), s.numpy())
    assert np.allclose(truth.angle_error(u, s).numpy(), dth, atol=1e-17, rtol=1e-12)
    q_actual = fanuc.joint_map.to_command(theta + torch.from_numpy(dth))
    tool = torch.arange(150) % 3
    assert torch.allclose(truth.points(q, tool, s), truth.nominal_points(q_actual, tool), atol=1e-14)


def test_backlash_changes_sign_with_direction(fanuc, tools_m):
    truth = keep_only(TruthRobot.fanuc_paper2(fanuc, tools_m, 7), "backlash")
    q = random_commands(fanuc, 400, 8)
    u = truth.error_variables(q)
    ones = torch.ones_like(q)
    up, down, none = truth.angle_error(u, ones), truth.angle_error(u, -ones), truth.angle_error(u, 0 * ones)
    assert torch.equal(up, -down) and bool((up > 0).all()) and torch.equal(none, torch.zeros_like(none))
    # 0.005-0.02 deg, varying with the joint angle by at most +-30 %, and really varying
    mean = truth.backlash
    assert bool(((mean >= 0.005 * DEG) & (mean <= 0.02 * DEG)).all())
    ratio = up / mean
    assert bool(((ratio > 0.69) & (ratio < 1.31)).all())
    assert bool((ratio.max(0).values - ratio.min(0).values > 0.05).all())
    # the points move between the two approach directions, and not at all without backlash
    tool = torch.arange(400) % 3
    gap = (truth.points(q, tool, ones) - truth.points(q, tool, -ones)).norm(dim=1)
    assert gap.mean() > 1e-5
    assert torch.equal(truth.points(q, tool, 0 * ones), truth.nominal_points(q, tool))


def test_tilt_wobble_and_centre_of_joint1_act_in_the_base_frame(fanuc, tools_m):
    """Joint 1's frame is the base frame, so its errors before the joint move the whole arm rigidly."""
    full = TruthRobot.fanuc_paper2(fanuc, tools_m, 9)
    q = random_commands(fanuc, 120, 10)
    tool = torch.arange(120) % 3
    th1 = fanuc.joint_map.to_joint(q)[:, 0].numpy()
    nominal = full.nominal_points(q, tool)

    tilt = keep_only(TruthRobot.fanuc_paper2(fanuc, tools_m, 9), "out_amp")
    with torch.no_grad():
        tilt.out_amp[1:] = 0.0
    a, ph = tilt.out_amp[0].numpy(), tilt.out_phase[0].numpy()  # (axis, harmonic)
    ex = sum(a[0, k] * np.cos((k + 1) * th1 + ph[0, k]) for k in range(2))
    ey = sum(a[1, k] * np.cos((k + 1) * th1 + ph[1, k]) for k in range(2))
    R = so3_exp(torch.from_numpy(np.stack([ex, ey, 0 * ex], 1)))
    assert torch.allclose(tilt.points(q, tool), (R @ nominal[..., None])[..., 0], atol=1e-15)
    assert (tilt.points(q, tool) - nominal).norm(dim=1).mean() > 1e-5

    wob = keep_only(TruthRobot.fanuc_paper2(fanuc, tools_m, 9), "wobble", "center")
    with torch.no_grad():
        wob.wobble[1:] = 0.0
        wob.center[1:] = 0.0
    W = wob.wobble[0].numpy()  # (axis, [cos, sin])
    shift = np.stack([W[0, 0] * np.cos(th1) + W[0, 1] * np.sin(th1), W[1, 0] * np.cos(th1) + W[1, 1] * np.sin(th1),
                      0 * th1], 1) + wob.center[0].numpy()
    assert torch.allclose(wob.points(q, tool), nominal + torch.from_numpy(shift), atol=1e-15)


def test_joint_error_transforms_are_rigid_and_perpendicular(fanuc, tools_m):
    truth = keep_only(TruthRobot.fanuc_paper2(fanuc, tools_m, 11), "out_amp", "wobble")
    u = truth.error_variables(random_commands(fanuc, 50, 12))
    E = truth.joint_transforms(u)
    R, p = E[..., :3, :3], E[..., :3, 3]
    eye = torch.eye(3).expand_as(R)
    assert torch.allclose(R.transpose(-1, -2) @ R, eye, atol=1e-15)
    assert torch.allclose(torch.linalg.det(R), torch.ones(50, 6), atol=1e-15)
    axes = truth.axes  # z for every DH joint: tilt about x, y; wobble in the x-y plane
    w = 0.5 * torch.stack([R[..., 2, 1] - R[..., 1, 2], R[..., 0, 2] - R[..., 2, 0], R[..., 1, 0] - R[..., 0, 1]], -1)
    assert float((w * axes).sum(-1).abs().max()) < 1e-12
    # the wobble moves the centre in the (tilted) joint plane
    p_plane = (R.transpose(-1, -2) @ p[..., None])[..., 0]
    assert float((p_plane * axes).sum(-1).abs().max()) < 1e-15
    assert float(w.norm(dim=-1).max()) > 1e-5 and float(p.norm(dim=-1).max()) > 1e-6


@settings(max_examples=50, deadline=None)
@given(st.lists(st.floats(-1, 1), min_size=3, max_size=3).filter(lambda v: sum(x * x for x in v) > 1e-2))
def test_perpendicular_axes_are_a_right_handed_frame(v):
    a = torch.tensor([v]) / torch.tensor([v]).norm()
    uw = perpendicular_axes(a)[0]
    frame = torch.stack([uw[0], uw[1], a[0]], 1)
    assert torch.allclose(frame.T @ frame, torch.eye(3), atol=1e-14)
    assert torch.allclose(torch.linalg.det(frame), torch.tensor(1.0), atol=1e-14)


def test_like_with_like_against_robot_model(fanuc, tools_m):
    """Constant centre offsets, mastering, base error and tools mean the same thing in RobotModel."""
    truth = keep_only(TruthRobot.fanuc_paper2(fanuc, tools_m, 13), "center", "mastering", "base_twist", "tools_delta")
    model = RobotModel(fanuc, tools_m, orders=0)
    with torch.no_grad():
        model.joint_errors.coef[:, 2, 0] = truth.mastering
        model.joint_errors.coef[:, 3:, 0] = truth.center
        model.base.twist.copy_(truth.base_twist)
        model.tools.delta.copy_(truth.tools_delta)
    q = random_commands(fanuc, 100, 14)
    tool = torch.arange(100) % 3
    with torch.no_grad():
        assert torch.allclose(truth.points(q, tool), model.points(q, tool), atol=1e-15)
        assert torch.allclose(truth.flange(q, base=False), model.flange(q, base=False), atol=1e-15)
        assert torch.allclose(truth.flange(q, base=True), model.flange(q, base=True), atol=1e-15)
    base = torch.eye(4)
    base[:3, 3] = torch.tensor([1.0, 2.0, 0.5])
    shifted = keep_only(TruthRobot.fanuc_paper2(fanuc, tools_m, 13, base_nominal=base), "base_twist")
    E = twist_to_transform(shifted.base_twist)
    assert torch.allclose(shifted.flange(q, base=True), base @ E @ shifted.nominal_flange(q), atol=1e-15)
    assert torch.allclose(shifted.flange(q, base=False), E @ shifted.nominal_flange(q), atol=1e-15)


def test_truth_file_round_trip_keeps_the_measurement_frame(fanuc, tools_m, tmp_path):
    from torchcal.io.truth import load_truth, save_truth

    base = twist_to_transform(torch.tensor([0.1, -0.2, 0.3, 1.5, -0.5, 0.2], dtype=torch.float64))
    truth = TruthRobot.fanuc_paper2(fanuc, tools_m, 5, base_nominal=base)
    back = load_truth(save_truth(tmp_path / "truth.json", truth, "fanuc_paper2", 5), fanuc)
    q = random_commands(fanuc, 20, 6)
    s = torch.sign(torch.randn(20, 6, generator=torch.Generator().manual_seed(7)))
    tool = torch.arange(20) % 3
    assert torch.equal(back.base_nominal, truth.base_nominal)
    assert torch.allclose(back.points(q, tool, s), truth.points(q, tool, s), atol=1e-15, rtol=0)


def test_seeds_reproduce_and_differ(fanuc, tools_m):
    for make in (TruthRobot.fanuc_paper2, TruthRobot.random):
        a, b, c = make(fanuc, tools_m, 21), make(fanuc, tools_m, 21), make(fanuc, tools_m, 22)
        for k, v in a.state_dict().items():
            assert torch.equal(v, b.state_dict()[k]), k
        q = random_commands(fanuc, 20, 0)
        tool = torch.arange(20) % 3
        s = signs(20, 6, 0)
        assert torch.equal(a.points(q, tool, s), b.points(q, tool, s))
        assert (a.points(q, tool, s) - c.points(q, tool, s)).norm(dim=1).min() > 1e-6


def test_fanuc_magnitudes_and_order6_representability(fanuc, tools_m):
    truth = TruthRobot.fanuc_paper2(fanuc, tools_m, 0)
    q = quasi_random_commands(fanuc.joint_map.limits, 300, 0)
    tool = torch.arange(300) % 3
    err = (truth.points(q, tool, torch.ones_like(q)) - truth.nominal_points(q, tool)).norm(dim=1)
    assert 2e-3 < float(err.mean()) < 7e-3  # Paper II: 3.4 mm after aligning the tracker frame
    d = truth.describe()
    assert d["mastering_deg"][:5] == list(PAPER2_THETA_OFFSET_DEG[:5])
    assert 0.2 < d["base_translation_mm"] < 0.45 and 0.005 < d["base_rotation_deg"] < 0.015
    assert all(0.05 <= t <= 0.2 for t in d["tool_correction_mm"])
    assert max(d["wave_ptp_deg"][1:3]) > 0.1  # the paper's in-plane errors on joints 2-3
    assert all(0.01 < x < 0.6 for x in d["wave_ptp_deg"])
    assert d["error_variable"] == ["command"] * 6 and d["angle_terms_unit"] == ["deg"] * 6
    fit_err = truth.chebyshev_fit_error(order=6)
    for name, e in fit_err.items():
        if name != "ripple":  # the modelled sources are sized to be representable
            assert max(e["rel"]) < 0.05, name
    assert max(fit_err["in_plane"]["max_abs"]) < 0.005  # deg: ~0.02 mm at half a metre
    # the unmodelled gear ripple is not (by design), and small: <= 0.0015 deg amplitude
    assert min(fit_err["ripple"]["rel"]) > 0.5
    assert all(0.0 < x <= 0.003 for x in d["ripple_ptp_deg"])
    assert all(9 <= c <= 15 for c in d["ripple_cycles_per_rev"])
    assert all(0.0 < x <= 0.001 for x in d["cross_coupling_deg"])
    assert d["cross_coupling_with"] == ["joint2", "joint3", "joint4", "joint5", "joint6", "joint5"]


def test_chebyshev_fit_error_flags_a_non_polynomial_error(fanuc, tools_m):
    """The representability check itself must see 2 cycles/rev over a full revolution (joint 4)."""
    truth = TruthRobot(fanuc, tools_m)
    with torch.no_grad():
        truth.wave_amp[3, 1] = 0.05 * DEG
        truth.wave_amp[1, 1] = 0.05 * DEG  # joint 2 spans 130 deg: fine
    rel = truth.chebyshev_fit_error(order=6)["in_plane"]["rel"]
    assert rel[3] > 0.2 and rel[1] < 0.01
    assert harmonic_limit(2 * math.pi, 2) < 0.05 and harmonic_limit(130 * DEG, 1) == 1.0


def test_joint_dependent_share_of_the_error(fanuc, tools_m):
    """A constant-geometry model fitted to exact truth leaves roughly the paper's ~20 % (CPA: 0.705 of 3.418 mm)."""
    from torchcal.identify import NoiseModel, fit
    from torchcal.sim import simulate

    truth = TruthRobot.fanuc_paper2(fanuc, tools_m, 0)
    q = quasi_random_commands(fanuc.joint_map.limits, 120, 1)
    data = simulate(truth, q, [0, 1, 2], None, 0)
    model = RobotModel(fanuc, tools_m, orders=0)
    zero = torch.zeros(6)
    fit(model, data, NoiseModel(5e-6, zero, zero), max_iter=30)
    with torch.no_grad():
        resid = (model.points(data.q, data.tool) - data.xyz).norm(dim=1).mean()
    nominal = (truth.nominal_points(data.q, data.tool) - data.xyz).norm(dim=1).mean()
    assert 0.08 < float(resid / nominal) < 0.35


def test_float32_and_batch_shapes(fanuc, tools_m):
    truth = TruthRobot.fanuc_paper2(fanuc, tools_m, 3)
    q = random_commands(fanuc, 10, 1)
    tool = torch.arange(10) % 3
    s = signs(10, 6, 2)
    p64 = truth.points(q, tool, s)
    p32 = truth.points(q.float(), tool, s.float())
    assert p32.dtype == torch.float32 and p64.dtype == torch.float64 and p64.shape == (10, 3)
    assert torch.allclose(p32.double(), p64, atol=1e-5)


def test_random_truth_on_a_prismatic_robot(tmp_path):
    path = tmp_path / "rpr.urdf"
    path.write_text(PRISMATIC_URDF)
    robot = load_robot(path)
    tools = torch.tensor([[0.0, 0.0, 0.05], [0.0, 0.03, 0.05]])
    q = quasi_random_commands(robot.joint_map.limits, 200, 0)
    tool = torch.arange(200) % 2
    zero = TruthRobot.random(robot, tools, 5, scale=0.0)
    assert torch.equal(zero.points(q, tool, torch.ones_like(q)), zero.nominal_points(q, tool))
    truth = TruthRobot.random(robot, tools, 5)
    err = (truth.points(q, tool, torch.ones_like(q)) - truth.nominal_points(q, tool)).norm(dim=1).mean()
    assert 5e-5 < float(err) < 5e-3
    double = TruthRobot.random(robot, tools, 5, scale=2.0)
    err2 = (double.points(q, tool, torch.ones_like(q)) - double.nominal_points(q, tool)).norm(dim=1).mean()
    assert 1.8 < float(err2 / err) < 2.2  # small errors: linear in their scale
    # a prismatic joint's mastering is a length along its axis
    only = keep_only(TruthRobot.random(robot, tools, 5), "mastering")
    theta = robot.joint_map.to_joint(q)
    moved = robot.joint_map.to_command(theta + only.mastering)
    assert torch.allclose(only.points(q, tool), only.nominal_points(moved, tool), atol=1e-15)
    assert 1e-6 < abs(float(only.mastering[1])) < 2e-3
    assert all(max(e["rel"]) < 0.05 for k, e in truth.chebyshev_fit_error().items() if k != "ripple")


def test_fanuc_constructor_rejects_other_robots(tmp_path):
    path = tmp_path / "rpr.urdf"
    path.write_text(PRISMATIC_URDF)
    with pytest.raises(ValueError, match="6"):
        TruthRobot.fanuc_paper2(load_robot(path), torch.zeros(1, 3), 0)


# ---------------------------------------------------------------- error variable (Paper II (24))
STRUCTURE = ("ranges", "error_coupling", "error_offset")


def same_gears_on_joint_variable(truth: TruthRobot, robot, tools_m) -> TruthRobot:
    """The same error buffers evaluated on the URDF joint variables instead of the commands."""
    other = TruthRobot(robot, tools_m, error_variable="joint")
    state = {k: v for k, v in truth.state_dict().items() if k not in STRUCTURE}
    other.load_state_dict({**other.state_dict(), **state})
    return other


def test_error_variable_structure_matches_the_joint_map(fanuc, tools_m):
    """u = q (command) or θ (joint) per joint, over the command limits or the URDF variable's range."""
    mixed = ["command", "command", "joint", "command", "joint", "command"]
    truth = TruthRobot(fanuc, tools_m, error_variable=mixed)
    assert truth.error_variable == mixed
    A, b = fanuc.joint_map.with_error_variable(mixed).error_map()
    assert torch.equal(truth.error_coupling, A) and torch.equal(truth.error_offset, b)
    assert torch.equal(truth.ranges, fanuc.joint_map.with_error_variable(mixed).error_ranges())
    q = random_commands(fanuc, 40, 1)
    u = truth.error_variables(q)
    theta = fanuc.joint_map.to_joint(q)
    assert torch.equal(u[:, [0, 1, 3, 5]], q[:, [0, 1, 3, 5]])
    assert torch.allclose(u[:, [2, 4]], theta[:, [2, 4]], atol=1e-15)
    with pytest.raises(ValueError, match="joint3"):
        TruthRobot(fanuc, tools_m, error_variable=["command", "command", "urdf", "command", "command", "command"])


def test_gears_follow_the_command_the_joint_received(fanuc, tools_m):
    """A positioning error v moves the gear too: the errors follow q + v, not q."""
    truth = TruthRobot.fanuc_paper2(fanuc, tools_m, 2)
    q = random_commands(fanuc, 30, 3)
    v = 1e-3 * torch.randn(30, 6, generator=torch.Generator().manual_seed(4))
    s = signs(30, 6, 5)
    tool = torch.arange(30) % 3
    assert torch.allclose(truth.points(q, tool, s, v), truth.points(q + v, tool, s), atol=1e-15)


def test_command_truth_differs_from_joint_truth_on_j3_only(fanuc, tools_m):
    """Same gears, evaluated on q3 (command) or θ3 = q2 + q3 (joint): the FANUC's J3 differs by
    tenths of a millimetre where q2 is far from 0 and not at all where q2 = 0; joints whose
    command is their URDF variable (1, 4, 5, 6) do not differ at all."""
    cmd = TruthRobot.fanuc_paper2(fanuc, tools_m, 0)
    jnt = same_gears_on_joint_variable(cmd, fanuc, tools_m)
    q = random_commands(fanuc, 400, 6)
    s = signs(400, 6, 7)
    fc, fj = cmd.error_functions(cmd.error_variables(q)), jnt.error_functions(jnt.error_variables(q))
    same = [0, 3, 4, 5]
    for k in fc:
        cols = same if k != "cross" else [3, 4, 5]  # joint 1's cross-coupling reads joint 2 (θ2 = q2 - 90°)
        assert torch.equal(fc[k][:, cols], fj[k][:, cols]), k
    # J3's gear errors alone: no difference at q2 = 0, a large one for |q2| >= 60 deg
    only3_c, only3_j = cmd, jnt
    for t in (only3_c, only3_j):
        with torch.no_grad():
            for name in JOINT_DEPENDENT:
                buf = getattr(t, name)
                buf[:2] = 0.0
                buf[3:] = 0.0
    tool = torch.arange(400) % 3
    q0 = q.clone()
    q0[:, 1] = 0.0
    assert torch.allclose(only3_c.points(q0, tool, s), only3_j.points(q0, tool, s), atol=1e-15)
    far = q[:, 1].abs() > 60 * DEG
    gap = (only3_c.points(q, tool, s) - only3_j.points(q, tool, s)).norm(dim=1)
    assert far.sum() > 50
    assert float(gap[far].mean()) > 1e-4  # > 0.1 mm
    assert float(gap[~far].mean()) < float(gap[far].mean())


def test_constructors_draw_the_same_identity_joints_for_either_variable(fanuc, tools_m):
    """Joints whose command is their URDF variable get the same draws and the same points contribution."""
    cmd = TruthRobot.fanuc_paper2(fanuc, tools_m, 8)
    jnt = TruthRobot.fanuc_paper2(fanuc, tools_m, 8, error_variable="joint")
    assert jnt.error_variable == ["joint"] * 6
    for name in JOINT_DEPENDENT + CONSTANT:
        assert torch.equal(getattr(cmd, name)[[0, 3, 4, 5]], getattr(jnt, name)[[0, 3, 4, 5]]), name
    q = random_commands(fanuc, 200, 9)
    tool = torch.arange(200) % 3
    s = torch.ones_like(q)
    gap = (cmd.points(q, tool, s) - jnt.points(q, tool, s)).norm(dim=1)
    assert float(gap.mean()) > 1e-4  # J2's and J3's errors sit elsewhere on the other variable


def test_unmodelled_sources_are_small_and_can_be_switched_off(fanuc, tools_m):
    on = TruthRobot.fanuc_paper2(fanuc, tools_m, 3)
    off = TruthRobot.fanuc_paper2(fanuc, tools_m, 3, unmodelled=False)
    for k, v in off.state_dict().items():
        if k.startswith(("ripple", "cross")) and k != "cross_joint":
            assert not v.any(), k
        else:
            assert torch.equal(v, on.state_dict()[k]), k  # their own random stream: nothing else moves
    q = quasi_random_commands(fanuc.joint_map.limits, 300, 4)
    tool = torch.arange(300) % 3
    s = torch.ones_like(q)
    d = (on.points(q, tool, s) - off.points(q, tool, s)).norm(dim=1)
    assert 3e-6 < float(d.mean()) < 1.5e-5 and float(d.max()) < 4e-5  # a few µm to ~10 µm at the tool
    assert TruthRobot.random(fanuc, tools_m, 3).ripple_amp.abs().min() > 0
    assert not TruthRobot.random(fanuc, tools_m, 3, unmodelled=False).cross_amp.any()


def test_truth_file_records_the_error_variable_and_old_files_load_as_joint(fanuc, tools_m, tmp_path):
    import json

    from torchcal.io.truth import load_truth, save_truth

    mixed = ["command", "joint", "joint", "command", "command", "command"]
    q = random_commands(fanuc, 20, 6)
    s = signs(20, 6, 7)
    tool = torch.arange(20) % 3
    for ev in ("command", "joint", mixed):
        truth = TruthRobot.fanuc_paper2(fanuc, tools_m, 5, error_variable=ev)
        path = save_truth(tmp_path / "truth.json", truth, "fanuc_paper2", 5)
        blob = json.loads(path.read_text())
        assert blob["error_variable"] == truth.error_variable
        back = load_truth(path, fanuc)
        assert back.error_variable == truth.error_variable
        assert torch.equal(back.points(q, tool, s), truth.points(q, tool, s))
    # a file from before the error variable existed: no key, no new buffers; its errors followed θ
    old = TruthRobot.fanuc_paper2(fanuc, tools_m, 5, error_variable="joint", unmodelled=False)
    blob = json.loads(save_truth(tmp_path / "old.json", old, "fanuc_paper2", 5).read_text())
    del blob["error_variable"]
    for k in list(blob["state_si"]):
        if k.startswith(("ripple", "cross", "error_")):
            del blob["state_si"][k]
    (tmp_path / "old.json").write_text(json.dumps(blob))
    back = load_truth(tmp_path / "old.json", fanuc)
    assert back.error_variable == ["joint"] * 6
    assert torch.equal(back.points(q, tool, s), old.points(q, tool, s))
