"""SensorRig: the closed loop tracker -> base -> robot -> mount of Paper III (13)-(16), (27)."""

import math

import numpy as np
import pytest
import torch
from conftest import fanuc_dh_reference, random_commands

from torchcal.identify.gauge import fix_gauge
from torchcal.identify.layout import ParameterLayout
from torchcal.identify.problem import CalibrationProblem, NoiseModel, Prior
from torchcal.io.rundir import load_model, save_model
from torchcal.kinematics.transforms import twist_to_transform
from torchcal.measure import PointTargets, PoseInstrument
from torchcal.models.sensor_rig import SensorRig
from torchcal.measure.gravity import gravity_from_xy
from torchcal.models.sensor_rig import GRAVITY_PRIOR_SIGMA
from torchcal.core.measurements import Measurements

DEG = math.pi / 180


def tracker_base() -> torch.Tensor:
    """Robot base seen from a tracker 2 m away, turned to face it."""
    T = torch.eye(4)
    T[:3, :3] = torch.tensor([[-1.0, 0, 0], [0, -1, 0], [0, 0, 1]])
    T[:3, 3] = torch.tensor([2.0, 0.3, -0.2])
    return T


MOUNT = twist_to_transform(torch.tensor([0.1, -0.2, 0.3, 0.01, 0.05, 0.03]))


@pytest.fixture
def rig(fanuc):
    return SensorRig.for_robot(fanuc, orders=2, base_nominal=tracker_base(), mount=MOUNT)


def test_nominal_sensor_pose_is_tracker_base_flange_mount(fanuc, rig):
    """Independent reference: Paper II's DH table in numpy, composed with base and mount by hand."""
    q = random_commands(fanuc, 20, 0)
    ref = tracker_base().numpy() @ fanuc_dh_reference(q.numpy() / DEG) @ MOUNT.numpy()
    with torch.no_grad():
        T = rig.sensor_pose(q)
    assert np.abs(T.numpy() - ref).max() < 1e-12
    assert torch.allclose(rig.points(q, torch.zeros(20, dtype=torch.long)), T[:, :3, 3])
    assert torch.allclose(rig.nominal_sensor_pose(q), T, atol=1e-12)


def test_mount_correction_acts_on_the_sensor_side(fanuc, rig):
    """(16): T_s0^n E_s0^n, the correction expressed in the sensor frame."""
    q = random_commands(fanuc, 5, 1)
    b = torch.tensor([1e-3, -2e-3, 5e-4, 1e-4, 2e-4, -3e-4])
    with torch.no_grad():
        T0 = rig.sensor_pose(q)
        rig.mount.twist.copy_(b)
        T1 = rig.sensor_pose(q)
    assert torch.allclose(T1, T0 @ twist_to_transform(b), atol=1e-14)


def test_gravity_vector_is_paper_27():
    g = gravity_from_xy(torch.tensor([0.1, -0.2]))
    assert torch.allclose(g, torch.tensor([0.1, -0.2, math.sqrt(1 - 0.01 - 0.04)]))
    assert abs(float(g.norm()) - 1) < 1e-15


def test_gravity_argument_is_checked(fanuc):
    rig = SensorRig.for_robot(fanuc, orders=1, gravity=[0.0, 0.6, 0.8])
    assert torch.allclose(rig.gravity_vector(), torch.tensor([0.0, 0.6, 0.8]))
    with pytest.raises(ValueError, match="not normalized"):
        SensorRig.for_robot(fanuc, orders=1, gravity=[0.0, 0.6, 0.9])
    with pytest.raises(ValueError, match="g_z > 0"):
        SensorRig.for_robot(fanuc, orders=1, gravity=[0.0, 0.6, -0.8])


def test_parameter_groups_declare_every_parameter(rig):
    layout = ParameterLayout(rig)
    names = [n for n, _ in rig.named_parameters()]
    assert names == [g.name for g in layout._all_groups]
    by = {g.name: g for g in layout._all_groups}
    assert not by["model.tools.delta"].mask.any()  # tool vectors never identified on a rig
    assert by["mount.twist"].role == "tool" and by["mount.twist"].entry_names[0] == "mount.eps_x"
    assert by["mount.twist"].kinds == ["angle"] * 3 + ["length"] * 3
    assert by["gravity"].kinds == ["dimensionless"] * 2 and by["gravity"].role == "gravity"
    sigma = Prior().sigma(layout)
    gi = [i for i, n in enumerate(layout.names()) if n.startswith("gravity")]
    assert torch.allclose(sigma[gi], torch.full((2,), GRAVITY_PRIOR_SIGMA))
    mi = [i for i, n in enumerate(layout.names()) if n.startswith("mount")]
    assert torch.allclose(sigma[mi], torch.tensor([0.1] * 3 + [1e-2] * 3))  # the Prior's frame sigmas


def test_save_and_load_round_trip(tmp_path, fanuc, rig):
    g = torch.Generator().manual_seed(3)
    with torch.no_grad():
        for p in rig.parameters():
            p.copy_(torch.randn(p.shape, generator=g) * 1e-3)
    from torchcal.analysis.coverage import DirectionCoverage

    qc = random_commands(fanuc, 12, 8)
    rig.coverage = DirectionCoverage.from_data(qc, torch.ones_like(qc), rig.command_limits)  # as fit() sets it
    assert rig.model.coverage is rig.coverage
    save_model(tmp_path, rig)
    back = load_model(tmp_path)
    assert back.coverage is not None and back.coverage.to_dict() == rig.coverage.to_dict()
    assert type(back) is SensorRig
    q = random_commands(fanuc, 7, 2)
    with torch.no_grad():
        assert torch.equal(back.sensor_pose(q), rig.sensor_pose(q))
        assert torch.equal(back.gravity_vector(), rig.gravity_vector())
    assert back.spec() == rig.spec()


def _pose_data(rig, q):
    with torch.no_grad():
        T = rig.sensor_pose(q)
    data = Measurements.from_tensors(q, 0, T[:, :3, 3])
    data.extra["rotation"] = T[:, :3, :3]
    return data


def test_gauge_keeps_the_mount_and_pins_last_joint_constants(fanuc, rig, one_thread):
    """6-DOF data: the mount is kept (role 'tool' ranks before joints); joint 6's constant terms it duplicates are pinned."""
    q = random_commands(fanuc, 40, 4)
    data = _pose_data(rig, q)
    noise = NoiseModel.from_robot(fanuc)
    problem = CalibrationProblem(rig, data, noise, Prior(), instrument=PoseInstrument.from_measurements(data))
    pinned = fix_gauge(problem)
    free = problem.layout.names()
    assert all(f"mount.{t}" in free for t in ("eps_x", "eps_y", "eps_z", "delta_x", "delta_y", "delta_z"))
    assert all(f"base.{t}" in free for t in ("eps_x", "eps_y", "eps_z", "delta_x", "delta_y", "delta_z"))
    # a constant rotation about / shift along the last joint's axis (z) commutes with it: the mount's job
    assert {"joint6.eps_z.c0", "joint6.delta_z.c0"} <= set(pinned)
    assert not any(n.startswith("gravity") for n in free)  # no level angle in pose data: gravity unobservable
    # the kept problem is full rank
    _, A, _ = problem.linearize(problem.layout.get(), problem.v_zero())
    Af = A.reshape(-1, A.shape[-1])
    assert torch.linalg.matrix_rank(Af / Af.norm(dim=0)) == Af.shape[1]


def test_point_targets_fit_the_rig_and_pin_mount_rotation(fanuc, rig, one_thread):
    q = random_commands(fanuc, 30, 5)
    data = _pose_data(rig, q)
    problem = CalibrationProblem(rig, data, NoiseModel.from_robot(fanuc), Prior(),
                                 instrument=PointTargets.from_measurements(data, sigma=1e-5))
    f, _, _ = problem.linearize(problem.layout.get(), problem.v_zero())
    assert f.abs().max() < 1e-9
    pinned = fix_gauge(problem)
    # with points only, the mount's rotation moves no measured point: pinned (zero columns)
    assert {"mount.eps_x", "mount.eps_y", "mount.eps_z"} <= set(pinned)
