"""The bundled UR10: URDF + joint map against an independent standard-DH product, limits, repeatability."""

import math

import numpy as np
import pytest
import torch

from torchcal.identify import NoiseModel
from torchcal.kinematics import bundled_robots, load_robot

# Universal Robots' published UR10 (CB3) DH parameters, mm and rad
D_MM = [127.3, 0.0, 0.0, 163.941, 115.7, 92.2]
A_MM = [0.0, -612.0, -572.3, 0.0, 0.0, 0.0]
ALPHA = [math.pi / 2, 0.0, 0.0, math.pi / 2, -math.pi / 2, 0.0]


def ur10_dh(theta: np.ndarray) -> np.ndarray:
    """(N, 6) rad -> (N, 4, 4) flange poses in mm: Π_i Rz(θ_i) Tz(d_i) Tx(a_i) Rx(α_i), written out per factor."""
    out = np.tile(np.eye(4), (theta.shape[0], 1, 1))
    for i in range(6):
        out = out @ ur10_dh_step(i, theta[:, i])
    return out


def ur10_dh_step(i: int, th: np.ndarray) -> np.ndarray:
    """One factor Rz(θ_i) Tz(d_i) Tx(a_i) Rx(α_i), (N, 4, 4), translation in mm."""
    N = th.shape[0]
    c, s = np.cos(th), np.sin(th)
    Rz = np.tile(np.eye(4), (N, 1, 1))
    Rz[:, 0, 0], Rz[:, 0, 1], Rz[:, 1, 0], Rz[:, 1, 1] = c, -s, s, c
    Tz, Tx, Rx = np.eye(4), np.eye(4), np.eye(4)
    Tz[2, 3] = D_MM[i]
    Tx[0, 3] = A_MM[i]
    ca, sa = math.cos(ALPHA[i]), math.sin(ALPHA[i])
    Rx[1:3, 1:3] = [[ca, -sa], [sa, ca]]
    return Rz @ Tz @ Tx @ Rx


@pytest.fixture(scope="module")
def ur10():
    return load_robot("ur10")


def test_bundled(ur10):
    assert "ur10" in bundled_robots()
    assert ur10.n == 6 and ur10.joint_map.names[0] == "shoulder_pan_joint" and ur10.joint_map.names[5] == "wrist_3_joint"
    assert torch.equal(ur10.joint_map.coupling, torch.eye(6, dtype=torch.float64))
    assert ur10.joint_map.error_variable == ["command"] * 6


def test_matches_independent_dh_product(ur10):
    g = torch.Generator().manual_seed(0)
    q = (torch.rand(400, 6, generator=g, dtype=torch.float64) * 2 - 1) * 2 * math.pi
    T = ur10.chain.fk(ur10.joint_map.to_joint(q)).numpy()
    ref = ur10_dh(q.numpy())
    assert np.abs(T[:, :3, 3] * 1000 - ref[:, :3, 3]).max() < 1e-12  # mm
    assert np.abs(T[:, :3, :3] - ref[:, :3, :3]).max() < 1e-14


def test_zero_pose(ur10):
    T = ur10.chain.fk(torch.zeros(1, 6, dtype=torch.float64))[0]
    # stretched along base -x: x = a2 + a3, y = -(d4 + d6), z = d1 - d5
    expected = torch.tensor([-612.0 - 572.3, -(163.941 + 92.2), 127.3 - 115.7], dtype=torch.float64)
    assert torch.allclose(T[:3, 3] * 1000, expected, atol=1e-12)


def test_limits_and_repeatability(ur10):
    lim = ur10.joint_map.limits * 180 / math.pi
    assert torch.allclose(lim, torch.tensor([[-360.0, 360.0]] * 6, dtype=torch.float64), atol=1e-12)
    noise = NoiseModel.from_robot(ur10)
    # +-0.1 mm = 3 sigma at 1.3 m reach, on each joint alone
    sigma = 0.1e-3 / 3 / 1.3
    assert torch.allclose(noise.joint_var_fwd, torch.full((6,), sigma**2, dtype=torch.float64), rtol=2e-3)
    assert torch.equal(noise.joint_var_fwd, noise.joint_var_bwd)
    assert "0.1 mm" in noise.source


# Universal Robots' published UR10 (CB3) dynamics: masses (kg), centres of mass (m) in DH frame i
MASS = [7.1, 12.7, 4.27, 2.0, 2.0, 0.365]
COM_DH = [[0.021, 0.0, 0.027], [0.38, 0.0, 0.158], [0.24, 0.0, 0.068], [0.0, 0.007, 0.018], [0.0, 0.007, 0.018],
          [0.0, 0.0, -0.026]]


def ur10_gravity_torques(theta: np.ndarray, g: float = 9.80665) -> np.ndarray:
    """(N, 6) rad -> (N, 6) N·m holding torques, from the DH table alone: tau_j = sum over links l >= j of
    m_l g_vec . (z_{j-1} x (c_l - o_{j-1})), where joint j turns about z of DH frame j-1."""
    N = theta.shape[0]
    frames = [np.tile(np.eye(4), (N, 1, 1))]
    for i in range(6):
        frames.append(frames[-1] @ ur10_dh_step(i, theta[:, i]))
    gvec = np.array([0.0, 0.0, -g])
    coms = [frames[l + 1][:, :3, :3] @ np.array(COM_DH[l]) + frames[l + 1][:, :3, 3] / 1000.0 for l in range(6)]
    tau = np.zeros((N, 6))
    for j in range(6):
        z, o = frames[j][:, :3, 2], frames[j][:, :3, 3] / 1000.0
        for l in range(j, 6):
            tau[:, j] += MASS[l] * (np.cross(z, coms[l] - o) @ gvec)
    return tau


def test_inertials_give_the_dh_tables_gravity_torques(ur10):
    """The URDF's <inertial> blocks (converted from DH frames to link frames) give the same holding torques
    as the published table evaluated on the DH chain directly; 'gravity' compliance uses them."""
    from torchcal.error_models.compliance import GravityCompliance

    comp = GravityCompliance(ur10, joints=[1, 2, 3, 4], mode="gravity")
    assert comp.mode == "gravity" and float(comp.masses.sum()) == pytest.approx(sum(MASS))
    g = torch.Generator().manual_seed(1)
    q = (torch.rand(300, 6, generator=g, dtype=torch.float64) * 2 - 1) * 2 * math.pi
    tau = comp.functions(ur10.joint_map.to_joint(q))[..., 0]  # (B, 4): joints 2..5
    ref = ur10_gravity_torques(q.numpy())[:, 1:5]
    assert np.abs(tau.numpy() - ref).max() < 1e-9  # N·m; the shoulder holds up to ~100 N·m
    assert np.abs(ref[:, 0]).max() > 50.0
