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
