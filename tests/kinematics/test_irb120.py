"""The bundled ABB IRB 120: URDF + joint map against an independent DH reference, limits, and pk's own FK."""

import math

import numpy as np
import pytest
import torch

from conftest import random_commands, standard_dh
from torchcal.kinematics import bundled_robots, load_robot

DEG = math.pi / 180


def irb120_dh_reference(q_deg: np.ndarray) -> np.ndarray:
    """Flange (ABB tool0) pose (N, 4, 4), metres, from the IRB 120's standard DH with plain numpy.

    d = [290, 0, 0, 302, 0, 72] mm, a = [0, 270, 70, 0, 0, 0] mm,
    alpha = [-90, 0, -90, 90, -90, 0] deg, theta = q + [0, -90, 0, 0, 0, 0] deg,
    then Rz(180 deg) from DH frame 6 to tool0.
    """
    q = np.radians(np.atleast_2d(q_deg))
    theta = q + np.radians([0, -90, 0, 0, 0, 0])
    out = standard_dh(theta, [290, 0, 0, 302, 0, 72], [0, 270, 70, 0, 0, 0], np.radians([-90, 0, -90, 90, -90, 0]))
    out = out @ np.diag([-1.0, -1.0, 1.0, 1.0])  # Rz(180 deg)
    out[:, :3, 3] /= 1000.0
    return out


@pytest.fixture(scope="module")
def irb120():
    return load_robot("abb_irb120")


def test_bundled(irb120):
    assert "abb_irb120" in bundled_robots()
    assert irb120.name == "abb_irb120" and irb120.n == 6
    assert irb120.joint_map.names == ["J1", "J2", "J3", "J4", "J5", "J6"]


def test_matches_independent_dh_reference(irb120):
    q = random_commands(irb120, 500, 0)
    # include the limit corners' neighbourhood too: J6 beyond +-180 deg
    q[:4, 5] = torch.tensor([-400.0, 400.0, -270.0, 390.0]) * DEG
    T = irb120.chain.fk(irb120.joint_map.to_joint(q))
    ref = irb120_dh_reference(q.numpy() / DEG)
    # positions to 1e-12 mm (1e-15 m), rotations to 1e-14
    assert np.abs(T[:, :3, 3].numpy() - ref[:, :3, 3]).max() < 1e-15
    assert np.abs(T[:, :3, :3].numpy() - ref[:, :3, :3]).max() < 1e-14


def test_zero_pose_is_abb_calibration_position(irb120):
    T = irb120.chain.fk(irb120.joint_map.to_joint(torch.zeros(1, 6, dtype=torch.float64)))[0]
    # flange centre at (302 + 72, 0, 290 + 270 + 70) mm
    assert torch.allclose(T[:3, 3] * 1000, torch.tensor([374.0, 0.0, 630.0], dtype=torch.float64), atol=1e-12)
    # tool0: z along base +x, x along base -z (ABB quaternion [0.7071, 0, 0.7071, 0])
    expected = torch.tensor([[0.0, 0.0, 1.0], [0.0, 1.0, 0.0], [-1.0, 0.0, 0.0]], dtype=torch.float64)
    assert torch.allclose(T[:3, :3], expected, atol=1e-15)


def test_joint_directions_follow_abb_convention(irb120):
    """+J2 tilts the upper arm forward (+x), +J3 the forearm down (-z), +J1 turns towards +y."""
    def flange(q):
        return irb120.chain.fk(irb120.joint_map.to_joint(torch.tensor([q], dtype=torch.float64) * DEG))[0, :3, 3] * 1000

    p0 = flange([0, 0, 0, 0, 0, 0])
    assert flange([0, 10, 0, 0, 0, 0])[0] > p0[0] + 50
    assert flange([0, 0, 10, 0, 0, 0])[2] < p0[2] - 50
    assert flange([10, 0, 0, 0, 0, 0])[1] > 50


def test_limits(irb120):
    lim = irb120.joint_map.limits / DEG
    expected = torch.tensor([[-165, 165], [-110, 110], [-110, 70], [-160, 160], [-120, 120], [-400, 400]], dtype=torch.float64)
    assert torch.allclose(lim, expected, atol=1e-12)
    # the URDF's limits are the range of the DH angles over the controller box (theta2 = q2 - 90)
    assert torch.allclose(irb120.chain.limits, irb120.joint_map.joint_ranges(), atol=1e-15)
    assert torch.allclose(irb120.chain.limits[1] / DEG, torch.tensor([-200.0, 20.0], dtype=torch.float64))


def test_joint_map_round_trip(irb120):
    q = random_commands(irb120, 10, 2)
    theta = irb120.joint_map.to_joint(q)
    assert torch.allclose(theta[:, 1], q[:, 1] - 90 * DEG, atol=1e-15)
    assert torch.equal(theta[:, [0, 2, 3, 4, 5]], q[:, [0, 2, 3, 4, 5]])
    assert torch.allclose(irb120.joint_map.to_command(theta), q, atol=1e-15)


# ROS-Industrial abb_irb120_support (irb120_3_58): every link frame parallel to the base at the controller
# zero; joint origins (m), axes, and each link's mass (kg) and centre of mass in its own frame
ROSI_ORIGIN = [(0, 0, 0), (0, 0, 0.29), (0, 0, 0.27), (0, 0, 0.07), (0.302, 0, 0), (0.072, 0, 0)]
ROSI_AXIS = ["z", "y", "y", "x", "y", "x"]
ROSI_MASS = [3.067, 3.909, 2.944, 1.328, 0.546, 0.137]
ROSI_COM = [(9.77e-05, -0.00012, 0.23841), (0.00078, -0.00212, 0.10124), (0.02281, 0.00106, 0.05791),
            (0.2247, 0.00015, 0.00041), (-0.00109, 3.68e-05, 6.22e-05), (-0.00706, -0.00017, -1.32e-06)]


def _rot(axis: str, a: np.ndarray) -> np.ndarray:
    c, s = np.cos(a), np.sin(a)
    R = np.tile(np.eye(3), (a.shape[0], 1, 1))
    i, j = {"x": (1, 2), "y": (2, 0), "z": (0, 1)}[axis]
    R[:, i, i], R[:, i, j], R[:, j, i], R[:, j, j] = c, -s, s, c
    return R


def irb120_rosi_gravity_torques(q_deg: np.ndarray, g: float = 9.80665) -> np.ndarray:
    """(N, 6) controller degrees -> (N, 6) N·m holding torques on the ROS-I chain: tau_j = sum over links
    l >= j of m_l g_vec . (z_j x (c_l - o_j)); ABB's joint directions are the ROS-I axes' positive sense."""
    q = np.radians(np.atleast_2d(q_deg))
    N = q.shape[0]
    R, p = np.tile(np.eye(3), (N, 1, 1)), np.zeros((N, 3))
    axes, origins, coms = [], [], []
    for j in range(6):
        p = p + R @ np.array(ROSI_ORIGIN[j])
        unit = np.eye(3)["xyz".index(ROSI_AXIS[j])]
        axes.append(R @ unit)
        origins.append(p)
        R = R @ _rot(ROSI_AXIS[j], q[:, j])
        coms.append(p + R @ np.array(ROSI_COM[j]))
    gvec = np.array([0.0, 0.0, -g])
    tau = np.zeros((N, 6))
    for j in range(6):
        for l in range(j, 6):
            tau[:, j] += ROSI_MASS[l] * (np.cross(axes[j], coms[l] - origins[j]) @ gvec)
    return tau


def test_inertials_give_the_ros_industrial_models_gravity_torques(irb120):
    """The URDF's <inertial> blocks, carried from ROS-I's link frames into this file's, give the holding
    torques that the ROS-I chain itself gives (an independent FK, frames and axes of its own)."""
    from torchcal.error_models.compliance import GravityCompliance

    comp = GravityCompliance(irb120, joints=[1, 2, 4], mode="gravity")
    assert comp.mode == "gravity" and float(comp.masses.sum()) == pytest.approx(sum(ROSI_MASS))
    q = random_commands(irb120, 300, seed=3)
    tau = comp.functions(irb120.joint_map.to_joint(q))[..., 0].numpy()  # (B, 3): J2, J3, J5
    ref = irb120_rosi_gravity_torques(np.degrees(q.numpy()))[:, [1, 2, 4]]
    assert np.abs(tau - ref).max() < 1e-9  # N·m; J2 holds up to ~10 N·m
    assert np.abs(ref[:, 0]).max() > 5.0
