"""Gravity compliance (torchcal/errors/compliance.py) and its integration into RobotModel and identification."""

import json

import pytest
import torch
from scipy.spatial.transform import Rotation
from torch.func import jacrev

from conftest import assert_point_jacobians_match_autograd, random_commands, randomize
from torchcal.error_models.compliance import GravityCompliance, arm_angle_functions, gravity_torques, read_inertials
from torchcal.identify import NoiseModel, ParameterLayout, Prior, fit
from torchcal.kinematics import load_robot
from torchcal.kinematics.fk import chain_frames
from torchcal.core.measurements import Measurements
from torchcal.models.robot import RobotModel

# A small arm with inertials: vertical joint 1, two parallel horizontal joints (2, 3), a wrist roll (4),
# a fixed flange link carrying a mass, and a static base with a mass (which must not count).
ARM = [  # name, parent, child, xyz, rpy, axis
    ("j1", "base", "l1", (0.0, 0.0, 0.2), (0.0, 0.0, 0.0), (0.0, 0.0, 1.0)),
    ("j2", "l1", "l2", (0.05, 0.01, 0.1), (0.0, 0.0, 0.1), (0.0, 1.0, 0.0)),
    ("j3", "l2", "l3", (0.0, 0.0, 0.3), (0.0, 0.05, 0.0), (0.0, 1.0, 0.0)),
    ("j4", "l3", "l4", (0.25, 0.0, 0.02), (0.0, 0.0, 0.3), (1.0, 0.0, 0.0)),
]
LINKS = {  # link: (mass, com xyz in the link frame)
    "base": (9.0, (0.0, 0.0, 0.05)),
    "l1": (4.0, (0.01, 0.0, 0.08)),
    "l2": (3.0, (0.02, 0.01, 0.15)),
    "l3": (2.0, (0.12, -0.01, 0.01)),
    "l4": (0.5, (0.03, 0.0, 0.0)),
    "flange": (0.3, (0.0, 0.01, 0.02)),
}
FLANGE = ((0.06, 0.0, 0.0), (0.0, 0.4, 0.0))  # fixed joint l4 -> flange
G = torch.tensor([0.0, 0.0, -9.80665])


def arm_urdf(inertials: bool = True) -> str:
    def link(name):
        if not inertials or name not in LINKS:
            return f'<link name="{name}"/>'
        m, c = LINKS[name]
        return (f'<link name="{name}"><inertial><origin xyz="{c[0]} {c[1]} {c[2]}" rpy="0.3 0.2 0.1"/><mass value="{m}"/>'
                f'<inertia ixx="0.01" ixy="0" ixz="0" iyy="0.01" iyz="0" izz="0.01"/></inertial></link>')

    parts = ['<?xml version="1.0"?><robot name="arm">'] + [link(n) for n in ("base", "l1", "l2", "l3", "l4", "flange")]
    for name, parent, child, xyz, rpy, axis in ARM:
        parts.append(
            f'<joint name="{name}" type="revolute"><parent link="{parent}"/><child link="{child}"/>'
            f'<origin xyz="{xyz[0]} {xyz[1]} {xyz[2]}" rpy="{rpy[0]} {rpy[1]} {rpy[2]}"/><axis xyz="{axis[0]} {axis[1]} {axis[2]}"/>'
            f'<limit lower="-2.5" upper="2.5" effort="10" velocity="1"/></joint>')
    (xyz, rpy) = FLANGE
    parts.append(f'<joint name="fl" type="fixed"><parent link="l4"/><child link="flange"/>'
                 f'<origin xyz="{xyz[0]} {xyz[1]} {xyz[2]}" rpy="{rpy[0]} {rpy[1]} {rpy[2]}"/></joint></robot>')
    return "".join(parts)


@pytest.fixture()
def arm(tmp_path):
    path = tmp_path / "arm.urdf"
    path.write_text(arm_urdf())
    return load_robot(path)


def reference_potential(theta: torch.Tensor) -> torch.Tensor:
    """V(theta) = -Σ m g·c over the moving links, with a separate homogeneous-matrix FK (one pose, theta (n,))."""
    def T(xyz, rpy):
        M = torch.eye(4, dtype=torch.float64)
        M[:3, :3] = torch.tensor(Rotation.from_euler("xyz", rpy).as_matrix())  # URDF rpy = extrinsic x, y, z
        M[:3, 3] = torch.tensor(xyz)
        return M

    def rot(axis, angle):
        a = torch.tensor(axis, dtype=torch.float64)
        K = torch.zeros(3, 3, dtype=torch.float64)
        K[0, 1], K[0, 2], K[1, 2] = -a[2], a[1], -a[0]
        K = K - K.T
        M = torch.eye(4, dtype=torch.float64)
        M[:3, :3] = torch.eye(3) + torch.sin(angle) * K + (1 - torch.cos(angle)) * (K @ K)
        return M

    frame, V = torch.eye(4, dtype=torch.float64), torch.zeros((), dtype=torch.float64)
    frames = {}
    for i, (_, _, child, xyz, rpy, axis) in enumerate(ARM):
        frame = frame @ T(xyz, rpy) @ rot(axis, theta[i])
        frames[child] = frame
    frames["flange"] = frames["l4"] @ T(*FLANGE)
    for name, M in frames.items():
        m, c = LINKS[name]
        com = M[:3, :3] @ torch.tensor(c) + M[:3, 3]
        V = V - m * (G @ com)
    return V


def test_gravity_torque_matches_potential_energy(arm):
    inert, why = read_inertials(arm_urdf(), arm.chain)
    assert inert is not None, why
    assert sorted(inert.links) == ["flange", "l1", "l2", "l3", "l4"]  # the static base does not count
    theta = random_commands(arm, 4, 0)
    c = arm.chain
    tau, dtau = gravity_torques(c.origins, c.axes, c.prismatic, theta, inert.masses, inert.coms, inert.link_joint, G, derivative=True)
    ref_tau = torch.stack([-jacrev(reference_potential)(t) for t in theta])
    ref_dtau = torch.stack([-jacrev(jacrev(reference_potential))(t) for t in theta])
    assert ref_tau.abs().max() > 1.0  # the arm really is loaded
    assert torch.allclose(tau, ref_tau, atol=1e-12)
    assert torch.allclose(tau[:, 0], torch.zeros(4), atol=1e-12)  # vertical axis: no gravity torque
    assert torch.allclose(dtau, ref_dtau, atol=1e-11)
    # the module picks gravity mode from the inertials, default joints = horizontal ones at home
    comp = GravityCompliance(arm)
    # (j4 rolls about a tilted axis: not horizontal)
    assert comp.mode == "gravity" and comp.joints.tolist() == [1, 2]
    assert torch.allclose(comp.functions(theta)[..., 0], ref_tau[:, 1:3], atol=1e-12)


def test_arm_angle_functions_and_slopes(fanuc):
    comp = GravityCompliance(fanuc)
    assert comp.mode == "functions" and comp.joints.tolist() == [1, 2]
    theta = fanuc.joint_map.to_joint(random_commands(fanuc, 5, 1))
    f, df = arm_angle_functions(theta, comp.joints, comp.signs)
    # FANUC: URDF axis 3 is flipped, so the forearm angle is theta2 - theta3 (= -90 deg - q3)
    phi2 = theta[:, 1] - theta[:, 2]
    assert torch.allclose(f, torch.stack([theta[:, 1].sin(), theta[:, 1].cos(), phi2.sin(), phi2.cos()], 1), atol=1e-15)
    num = torch.stack([jacrev(lambda t: arm_angle_functions(t[None], comp.joints, comp.signs)[0][0])(t) for t in theta])
    assert torch.allclose(df, num, atol=1e-15)


def _jacobians_match_autograd(m, robot, tools_count, seed):
    B = 6
    q = random_commands(robot, B, seed)
    n = q.shape[1]
    tool = torch.arange(B) % tools_count
    s = torch.sign(torch.randn(B, n, generator=torch.Generator().manual_seed(seed + 1)))
    v = 1e-3 * torch.randn(B, n, generator=torch.Generator().manual_seed(seed + 2))
    params, J = assert_point_jacobians_match_autograd(m, q, tool, s, v)
    assert "compliance.coef" in params and set(params) <= set(J)
    # flange Jacobian w.r.t. controller q: the deflection's own slope must be in it
    from torchcal.kinematics.transforms import pose_error

    F, Jf = m.flange_jacobian(q, s)
    h = 1e-6
    for j in range(n):
        dq = torch.zeros_like(q)
        dq[:, j] = h
        num = (pose_error(F, m.flange(q + dq, s, base=False)) - pose_error(F, m.flange(q - dq, s, base=False))) / (2 * h)
        assert torch.allclose(num, Jf[:, :, j], atol=1e-8), j


def test_jacobians_functions_mode(fanuc, tools_m):
    m = randomize(RobotModel(fanuc, tools_m, orders=3, backlash=True, compliance=True), 5, rot=1e-2, trans=1e-3)
    with torch.no_grad():
        m.compliance.coef.copy_(torch.randn(m.compliance.coef.shape, generator=torch.Generator().manual_seed(3)) * 0.05)
    _jacobians_match_autograd(m, fanuc, 3, 20)


def test_jacobians_gravity_mode(arm):
    tools = torch.tensor([[0.0, 0.0, 0.1], [0.05, 0.02, 0.08]])
    m = randomize(RobotModel(arm, tools, orders=2, compliance={"mode": "gravity", "joints": [1, 2, 3]}), 6, rot=1e-2, trans=1e-3)
    assert m.compliance.mode == "gravity"
    with torch.no_grad():
        # large enough that a missing slope term would show: ~0.02 rad at ~10 N·m
        m.compliance.coef.copy_(torch.tensor([[2e-3], [-1.5e-3], [3e-3]]))
    _jacobians_match_autograd(m, arm, 2, 30)


def test_compliance_off_is_unchanged(fanuc, tools_m):
    off = randomize(RobotModel(fanuc, tools_m, orders=3, backlash=True), 11, rot=1e-2, trans=1e-3)
    assert off.compliance is None
    assert set(dict(off.named_parameters())) == {"joint_errors.coef", "joint_errors.backlash", "base.twist", "tools.delta"}
    assert not any("compliance" in k for k in off.state_dict())
    assert set(off.spec()) == {"robot", "tools", "orders", "backlash", "base_nominal", "error_variable"}
    B = 12
    q = random_commands(fanuc, B, 12)
    tool = torch.arange(B) % 3
    s = torch.sign(torch.randn(B, 6, generator=torch.Generator().manual_seed(13)))
    v = 1e-3 * torch.randn(B, 6, generator=torch.Generator().manual_seed(14))
    # the measurement model (25) written out as before compliance existed: E_i on the commands (24), joints on θ
    theta = off.joint_variables(q + v)
    E = off.joint_errors(off.error_variables(q + v), s)
    F = chain_frames(off.origins, off.axes, off.prismatic, theta, E, off.tip, off.base())[2]
    assert torch.equal(off.points(q, tool, s, v), off.tool_points(F, tool))
    # switched on with zero coefficients: bit-identical outputs and Jacobians
    on = RobotModel(fanuc, tools_m, orders=3, backlash=True, compliance=True)
    on.load_state_dict(off.state_dict(), strict=False)
    assert torch.equal(on.points(q, tool, s, v), off.points(q, tool, s, v))
    p0, J0 = off.point_jacobians(q, tool, s, v)
    p1, J1 = on.point_jacobians(q, tool, s, v)
    assert torch.equal(p0, p1) and all(torch.equal(J0[k], J1[k]) for k in J0)
    assert torch.equal(off.flange_jacobian(q, s)[1], on.flange_jacobian(q, s)[1])


def test_spec_round_trip(fanuc, tools_m, arm):
    for robot, tools, option in ((fanuc, tools_m, True), (arm, tools_m[:2], {"mode": "gravity", "joints": ["j2", "j3"]})):
        m = randomize(RobotModel(robot, tools, orders=2, compliance=option), 3)
        with torch.no_grad():
            m.compliance.coef.copy_(torch.randn(m.compliance.coef.shape, generator=torch.Generator().manual_seed(4)) * 1e-3)
        spec = json.loads(json.dumps(m.spec()))  # plain data
        m2 = RobotModel.from_spec(spec)
        m2.load_state_dict(m.state_dict())
        assert m2.compliance.mode == m.compliance.mode and torch.equal(m2.compliance.joints, m.compliance.joints)
        q = random_commands(robot, 10, 4)
        tool = torch.arange(10) % tools.shape[0]
        assert torch.equal(m.points(q, tool), m2.points(q, tool))
    assert m.compliance.joints.tolist() == [1, 2]


def test_layout_prior_and_missing_jacobian(fanuc, tools_m):
    m = RobotModel(fanuc, tools_m, orders=1, compliance=True)
    layout = ParameterLayout(m)
    names = [n for n in layout.names() if n.startswith("compliance.")]
    assert names == ["compliance.joint2.sin_phi1", "compliance.joint2.cos_phi1", "compliance.joint2.sin_phi2",
                     "compliance.joint2.cos_phi2", "compliance.joint3.sin_phi2", "compliance.joint3.cos_phi2"]
    prec = Prior(compliance=2e-2).precision(layout)
    is_comp = torch.tensor([n.startswith("compliance.") for n in layout.names()])
    assert torch.allclose(prec[is_comp], torch.full((6,), 1 / 4e-4))
    q = random_commands(fanuc, 4, 0)
    _, J = m.point_jacobians(q, torch.zeros(4, dtype=torch.long))
    del J["compliance.coef"]
    with pytest.raises(KeyError, match="compliance.coef"):
        layout.flatten_jacobian(J, 4)


def test_compensation_kernel_evaluates_compliance_models(fanuc, tools_m):
    """With compliance the kernel hands the modeled flange to the model (never the fused kernel)."""
    from torchcal.compensate.kernel import FlangeKernel

    m = randomize(RobotModel(fanuc, tools_m, orders=2, backlash=True, compliance=True), 4)
    with torch.no_grad():
        m.compliance.coef.copy_(torch.randn(m.compliance.coef.shape, generator=torch.Generator().manual_seed(5)) * 2e-3)
    k = FlangeKernel(m)
    assert k.fused is None
    with pytest.raises(ValueError, match="compliance"):
        FlangeKernel(m, fused=True)
    q = random_commands(fanuc, 30, 6)
    s = torch.sign(torch.randn(30, 6, generator=torch.Generator().manual_seed(7)))
    with torch.no_grad():
        F, J0 = m.flange_jacobian(q, s)
        Fn = m.nominal_flange(q)
    R, p, J = k.flange_jacobian(q.T.contiguous(), s.T.contiguous())
    assert torch.allclose(p.T, F[:, :3, 3], atol=1e-15, rtol=0) and torch.allclose(J.permute(2, 0, 1), J0, atol=1e-15, rtol=0)
    R, p = k.flange(q.T.contiguous(), s.T.contiguous())
    assert torch.allclose(R.permute(2, 0, 1), F[:, :3, :3], atol=1e-15, rtol=0)
    Rn, pn, _ = k.nominal_flange_jacobian(q.T.contiguous())  # the nominal chain has no compliance
    assert torch.allclose(pn.T, Fn[:, :3, 3], atol=2e-15, rtol=0)


def test_fit_recovers_compliance(fanuc, tools_m):
    """Noise-free data from known constant errors + compliance: LM recovers the compliance coefficients."""
    truth = randomize(RobotModel(fanuc, tools_m, orders=0, compliance=True), 21)
    c_true = torch.tensor([[2e-3, -1e-3, 6e-4, 1.2e-3], [0.0, 0.0, 1.5e-3, -8e-4]])
    with torch.no_grad():
        truth.compliance.coef.copy_(c_true)
    poses = 30
    q = random_commands(fanuc, poses, 22)
    s = torch.sign(torch.diff(torch.cat([torch.zeros(1, 6), q]), dim=0))
    qq, ss = q.repeat(3, 1), s.repeat(3, 1)
    tool = torch.arange(3).repeat_interleave(poses)
    with torch.no_grad():
        p = truth.points(qq, tool, ss)
    data = Measurements(qq, tool, p, ss, torch.arange(poses).repeat(3), torch.arange(1, 3 * poses + 1), True, "sim")
    # no prior: noise-free data must give the truth to rounding (the default prior would bias it by ~1e-7 rad,
    # on the scale of the tracker noise, checked below with a looser bound)
    for prior, rtol in ((None, 1e-6), (Prior(), 1e-3)):
        model = RobotModel(fanuc, tools_m, orders=0, compliance=True)
        res = fit(model, data, NoiseModel.paper2(), prior=prior, method="lm", ftol=1e-15, xtol=1e-14)
        assert res.success, res.message
        assert not any(n.startswith("compliance.") for n in res.pinned)
        err = (model.compliance.coef.detach() - c_true).abs().max()
        assert err <= rtol * c_true.abs().max(), (prior, err)
    assert (model.points(qq, tool, ss) - p).abs().max() < 1e-7


def test_gravity_mode_without_inertials_is_a_clear_error(fanuc, tools_m):
    """model.compliance: {mode: gravity} on a robot whose URDF has no inertials is a torchcal error (the CLI's
    one-line 'error:'), still a ValueError for library callers, naming what is missing."""
    from torchcal.core.exceptions import TorchcalError

    with pytest.raises(TorchcalError, match="needs the URDF inertials") as info:
        RobotModel(fanuc, tools_m, orders=1, compliance={"mode": "gravity"})
    assert isinstance(info.value, ValueError)
