"""Initial alignment of a far measurement frame and unknown tool vectors (torchcal.identify.alignment)."""

from dataclasses import replace

import pytest
import torch

from torchcal.identify import NoiseModel, fit
from torchcal.identify.alignment import AlignmentError, _lifted_start, _nominal_flange, align, kabsch, solve_tools
from torchcal.io.rundir import load_model, save_model
from torchcal.kinematics.transforms import homogeneous, rpy_to_matrix, so3_exp, so3_log
from torchcal.models.robot import RobotModel
from torchcal.sim import TruthRobot, quasi_random_commands, simulate

# reflectors somewhere on the flange, not Paper II's Table 4 (the alignment never sees these)
F64 = torch.float64
TOOLS_M = torch.tensor([[0.041, 0.062, 0.148], [0.071, -0.029, 0.139], [-0.052, -0.047, 0.171]], dtype=F64)


pytestmark = pytest.mark.usefixtures("one_thread")  # conftest: tiny problems run faster on one thread


def far_frame() -> torch.Tensor:
    """The robot base seen from a tracker 2.5 m away with a large arbitrary rotation."""
    xyz = torch.tensor([1.9, -1.4, 0.75], dtype=F64)
    xyz = xyz / xyz.norm() * 2.5
    return homogeneous(rpy_to_matrix(torch.tensor([2.1, -0.8, 2.6], dtype=F64)), xyz)


def rows_subset(data, keep):
    return replace(data, q=data.q[keep], tool=data.tool[keep], xyz=data.xyz[keep], direction=data.direction[keep],
                   pose=data.pose[keep], rows=data.rows[keep], extra={})


def frame_errors(T_est, T_true):
    """(rotation angle rad, translation m) between two frames."""
    return float(so3_log(T_true[:3, :3].T @ T_est[:3, :3]).norm()), float((T_est[:3, 3] - T_true[:3, 3]).norm())


@pytest.fixture(scope="module")
def paper2_far(fanuc):
    """Paper II's simulated FANUC seen from a far tracker: 60 noisy poses x 3 tools, ~30 % of the rows missing."""
    truth = TruthRobot.fanuc_paper2(fanuc, TOOLS_M, 0, base_nominal=far_frame())
    q = quasi_random_commands(fanuc.joint_map.limits, 60, 1)
    data = simulate(truth, q, [0, 1, 2], NoiseModel.paper2(), 2)
    keep = torch.rand(len(data), generator=torch.Generator().manual_seed(5)) > 0.3
    val = simulate(truth, quasi_random_commands(fanuc.joint_map.limits, 80, 1, skip=60), [0, 1, 2], None, 3)
    return truth, rows_subset(data, keep), val


# ------------------------------------------------------------------- Kabsch
def test_kabsch_recovers_a_known_rigid_motion_exactly():
    g = torch.Generator().manual_seed(0)
    src = torch.randn(4, 30, 3, generator=g)
    R = so3_exp(torch.randn(4, 3, generator=g) * 2.0)  # large rotations, batched
    t = torch.randn(4, 3, generator=g) * 3.0
    dst = src @ R.transpose(-1, -2) + t[:, None, :]
    R_est, t_est = kabsch(src, dst)
    assert (R_est - R).abs().max() < 1e-12 and (t_est - t).abs().max() < 1e-12
    # weights: a gross outlier with weight zero changes nothing
    dst2 = dst.clone()
    dst2[:, 0] += 10.0
    w = torch.ones(4, 30)
    w[:, 0] = 0.0
    R_w, t_w = kabsch(src, dst2, w)
    assert (R_w - R).abs().max() < 1e-12 and (t_w - t).abs().max() < 1e-12
    # a mirrored cloud still gives a proper rotation (no reflection)
    R_m, _ = kabsch(src[0], dst[0] * torch.tensor([1.0, 1.0, -1.0]))
    assert torch.linalg.det(R_m) == pytest.approx(1.0, abs=1e-12)


def test_tool_solve_is_the_least_squares_solution(fanuc):
    """solve_tools equals a dense least-squares solve of p = R_b (R_f t + p_f) + b for each tool."""
    g = torch.Generator().manual_seed(1)
    q = quasi_random_commands(fanuc.joint_map.limits, 25, 4)
    F = _nominal_flange(fanuc, q)
    Rb, b = so3_exp(torch.randn(3, generator=g)), torch.randn(3, generator=g)
    tool = torch.randint(0, 2, (25,), generator=g)
    xyz = torch.randn(25, 3, generator=g)  # arbitrary points: the solve must still be the LS minimiser
    t = solve_tools(Rb, b, F[:, :3, :3], F[:, :3, 3], xyz, tool, 2)
    for k in range(2):
        m = tool == k
        A = (Rb @ F[m, :3, :3]).reshape(-1, 3)
        rhs = (xyz[m] - b - F[m, :3, 3] @ Rb.T).reshape(-1)
        assert torch.allclose(t[k], torch.linalg.lstsq(A, rhs[:, None]).solution[:, 0], atol=1e-12)


# ---------------------------------------------------------- exact recovery
@pytest.mark.parametrize("start", ["lifted", "flange"])
def test_error_free_robot_gives_frame_and_tools_exactly(fanuc, start):
    """On a robot without errors the rigid model is exact: both starts must land on the truth."""
    truth = TruthRobot(fanuc, TOOLS_M, base_nominal=far_frame())
    q = quasi_random_commands(fanuc.joint_map.limits, 30, 7)
    data = simulate(truth, q, [0, 1, 2], None, 0)
    data = rows_subset(data, torch.arange(len(data)) % 4 != 1)  # rows missing, no pose has all three tools
    res = align(fanuc, data, 3, start=start)
    assert res.start == start and res.converged
    rot, trans = frame_errors(res.base_nominal, far_frame())
    assert rot < 1e-10 and trans < 1e-10
    assert (res.tools - TOOLS_M).abs().max() < 1e-10 and res.max < 1e-10


def test_lifted_start_alone_is_exact_without_errors(fanuc):
    truth = TruthRobot(fanuc, TOOLS_M, base_nominal=far_frame())
    data = simulate(truth, quasi_random_commands(fanuc.joint_map.limits, 20, 8), [0, 1, 2], None, 0)
    F = _nominal_flange(fanuc, data.q)
    Rb, b = _lifted_start(F[:, :3, :3], F[:, :3, 3], data.xyz, data.tool, 3)
    assert (Rb - far_frame()[:3, :3]).abs().max() < 1e-9 and (b - far_frame()[:3, 3]).abs().max() < 1e-9


def test_known_tools_or_known_frame_are_held(fanuc):
    truth = TruthRobot(fanuc, TOOLS_M, base_nominal=far_frame())
    data = simulate(truth, quasi_random_commands(fanuc.joint_map.limits, 15, 9), [0, 1, 2], None, 0)
    res = align(fanuc, data, tools=TOOLS_M)  # frame only: one Kabsch registration
    assert not res.estimated_tools and torch.equal(res.tools, TOOLS_M)
    assert max(frame_errors(res.base_nominal, far_frame())) < 1e-10
    res = align(fanuc, data, 3, frame=far_frame())  # tools only: linear
    assert not res.estimated_frame and torch.equal(res.base_nominal, far_frame())
    assert (res.tools - TOOLS_M).abs().max() < 1e-10


def test_unusable_data_is_refused(fanuc):
    truth = TruthRobot(fanuc, TOOLS_M, base_nominal=far_frame())
    data = simulate(truth, quasi_random_commands(fanuc.joint_map.limits, 15, 9), [0, 1], None, 0)
    with pytest.raises(AlignmentError, match=r"no rows measured with tool\(s\) \[2\]"):
        align(fanuc, data, 3)
    # one flange orientation only (the wrist never moves, joint 1 alone turns): tools and frame are confounded
    q = torch.zeros(12, 6)
    q[:, 0] = torch.linspace(-1.0, 1.0, 12)
    data = simulate(truth, q, [0], None, 0)
    with pytest.raises(AlignmentError, match="do not determine"):
        align(fanuc, data, 1)


# ------------------------------------------------------ Paper II magnitudes
def test_far_frame_recovered_within_the_robot_errors(fanuc, paper2_far):
    truth, data, _ = paper2_far
    res = align(fanuc, data, 3)
    rot, trans = frame_errors(res.base_nominal, truth.base_frame())
    # the rigid fit absorbs what it can of the robot's ~0.1-0.5 deg, ~0.5 mm constant errors: a few mrad / mm
    assert rot < 8e-3 and trans < 5e-3
    assert (res.tools - truth.tools()).norm(dim=1).max() < 3e-3
    # it is the least-squares optimum of the rigid model: no worse than the true frame and tools on the nominal chain
    F = truth.base_frame() @ _nominal_flange(fanuc, data.q)
    p_t = truth.tools()[data.tool]
    at_truth = ((F[:, :3, :3] @ p_t[..., None])[..., 0] + F[:, :3, 3] - data.xyz).norm(dim=1)
    assert res.rms <= float(at_truth.pow(2).mean().sqrt()) * (1 + 1e-9)
    assert 1e-4 < res.rms < 5e-3  # the robot's errors remain (m), nothing else
    assert res.converged and res.residuals.shape == (len(data),)


def test_full_fit_from_the_alignment_equals_fit_from_the_truth(fanuc, paper2_far):
    truth, data, val = paper2_far
    noise = NoiseModel.paper2()
    res = align(fanuc, data, 3)
    scores = []
    for tools, frame in ((res.tools, res.base_nominal), (truth.tools(), truth.base_frame())):
        model = RobotModel(fanuc, tools, orders=2, backlash=True, base_nominal=frame)
        out = fit(model, data, noise)
        assert out.success
        with torch.no_grad():
            scores.append(float((model.points(val.q, val.tool, val.direction) - val.xyz).norm(dim=1).mean()))
    aligned, given = scores
    assert abs(aligned - given) < 0.05 * given
    # and the fit does calibrate (nominal error of this robot: several mm; order 2 on 60 poses leaves ~0.3 mm of
    # the truth's command-driven J2/J3 errors, which vary over 130 deg ranges)
    assert aligned < 0.4e-3


def test_fit_from_a_far_frame_warns_and_points_to_align(fanuc, paper2_far):
    """torchcal.fit on a model whose base is left at the tracker (2.5 m off) says so before it runs its iterations
    out; the aligned model (torchcal.align, as the warning says) fits without a word."""
    import warnings

    import torchcal

    truth, data, _ = paper2_far
    with pytest.warns(UserWarning, match=r"misses the points .* by \d+\.\d mm RMS .*torchcal\.align"):
        fit(RobotModel(fanuc, TOOLS_M, orders=0, backlash=False), data, NoiseModel.paper2(), max_iter=2)
    res = torchcal.align(fanuc, data, 3)
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        fit(RobotModel(fanuc, res.tools, orders=0, backlash=False, base_nominal=res.base_nominal), data,
            NoiseModel.paper2(), max_iter=2)


def test_aligned_model_persists_through_the_run_directory(tmp_path, fanuc, paper2_far):
    truth, data, val = paper2_far
    res = align(fanuc, data, 3)
    model = RobotModel(fanuc, res.tools, orders=1, backlash=True, base_nominal=res.base_nominal)
    with torch.no_grad():
        model.base.twist.copy_(torch.tensor([1e-3, -2e-3, 5e-4, 1e-4, 2e-4, -3e-4]))
        model.tools.delta.fill_(1e-4)
    save_model(tmp_path, model, orders=[1] * 6)
    back = load_model(tmp_path)
    assert torch.equal(back.base.nominal, res.base_nominal) and torch.equal(back.tools.nominal, res.tools)
    with torch.no_grad():
        assert torch.equal(back.points(val.q, val.tool, val.direction), model.points(val.q, val.tool, val.direction))
        assert torch.equal(back.nominal_points(val.q, val.tool), model.nominal_points(val.q, val.tool))


def test_pipeline_estimates_only_what_the_config_leaves_out(fanuc, tmp_path):
    from torchcal.app.config import ConfigError, make_config
    from torchcal.app.fit import config_alignment

    truth = TruthRobot(fanuc, TOOLS_M, base_nominal=far_frame())
    data = simulate(truth, quasi_random_commands(fanuc.joint_map.limits, 15, 9), [0, 1, 2], None, 0)
    base = {"robot": "fanuc_lrmate200i", "data": {"identification": "x.csv"}}
    listed = (TOOLS_M * 1e3).tolist()
    # tools listed, frame unset: Paper II's setting, nothing estimated
    tools, frame, res = config_alignment(make_config({**base, "tools": listed}), fanuc, data)
    assert res is None and torch.equal(frame, torch.eye(4, dtype=F64)) and torch.allclose(tools, TOOLS_M, atol=1e-15)
    # tools listed, frame to estimate: frame only, the listed tools are kept
    tools, frame, res = config_alignment(make_config({**base, "tools": listed, "measurement_frame": "estimate"}), fanuc, data)
    assert res.estimated_frame and not res.estimated_tools and torch.allclose(tools, TOOLS_M, atol=1e-15)
    assert max(frame_errors(frame, far_frame())) < 1e-9
    # tools counted, frame given: tools only, the given frame is kept
    given = {"xyz_mm": (far_frame()[:3, 3] * 1e3).tolist(), "rpy_deg": [2.1 * 180 / torch.pi, -0.8 * 180 / torch.pi, 2.6 * 180 / torch.pi]}
    tools, frame, res = config_alignment(make_config({**base, "tools": {"count": 3}, "measurement_frame": given}), fanuc, data)
    assert not res.estimated_frame and res.estimated_tools
    assert (frame - far_frame()).abs().max() < 1e-12 and (tools - TOOLS_M).abs().max() < 1e-9
    # a tool the data never saw: a config error naming what could not be estimated
    with pytest.raises(ConfigError, match=r"cannot estimate the tool vectors and measurement frame.*tool\(s\) \[3\]"):
        config_alignment(make_config({**base, "tools": {"count": 4}}), fanuc, data)
