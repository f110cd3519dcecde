"""Shared fixtures: the bundled FANUC, Paper II's tool vectors, an independent DH reference."""

from __future__ import annotations

import torchcal  # noqa: F401  before torch, as users do: it sets OMP_WAIT_POLICY=PASSIVE (torchcal.core.threads)

import math  # noqa: E402

import numpy as np  # noqa: E402
import pytest  # noqa: E402
import torch  # noqa: E402

torch.set_default_dtype(torch.float64)

# Paper II, Table 4 (mm)
PAPER2_TOOLS_MM = [[33.06, 57.73, 161.22], [57.26, -33.86, 161.22], [-33.96, -57.23, 161.22]]


def standard_dh(theta: np.ndarray, d, a, alpha) -> np.ndarray:
    """Π of standard DH transforms with plain numpy (independent of torchcal).

    theta: (N, n) rad; d, a: (n,) mm; alpha: (n,) rad -> (N, 4, 4), translation in mm.
    """
    out = np.tile(np.eye(4), (theta.shape[0], 1, 1))
    for i in range(theta.shape[1]):
        ct, st = np.cos(theta[:, i]), np.sin(theta[:, i])
        ca, sa = np.cos(alpha[i]), np.sin(alpha[i])
        T = np.zeros((theta.shape[0], 4, 4))
        T[:, 0] = np.stack([ct, -st * ca, st * sa, a[i] * ct], 1)
        T[:, 1] = np.stack([st, ct * ca, -ct * sa, a[i] * st], 1)
        T[:, 2, 1], T[:, 2, 2], T[:, 2, 3], T[:, 3, 3] = sa, ca, d[i], 1.0
        out = out @ T
    return out


def fanuc_dh_reference(q_deg: np.ndarray) -> np.ndarray:
    """Flange pose (N, 4, 4), metres, from Paper II Table 2 with plain numpy (independent of torchcal)."""
    q = np.radians(np.atleast_2d(q_deg))
    theta = np.stack([q[:, 0], q[:, 1] - np.pi / 2, q[:, 1] + q[:, 2], q[:, 3], q[:, 4], q[:, 5]], 1)
    out = standard_dh(theta, [0, 0, 0, -290, 0, -80], [150, 250, 75, 0, 0, 0], np.radians([-90, 180, -90, 90, -90, 180]))
    out[:, :3, 3] /= 1000.0
    return out


@pytest.fixture(scope="session")
def fanuc():
    from torchcal.kinematics import load_robot

    return load_robot("fanuc_lrmate200i")


@pytest.fixture(scope="session")
def tools_m():
    return torch.tensor(PAPER2_TOOLS_MM) * 1e-3


XYZCB_TOOLS = torch.tensor([[0.0, 0.0, 0.4029], [0.0, 0.0, 0.5009]])
"""Paper I (32): the XYZCB machine's two tool vectors [0, 0, l_t], m."""


@pytest.fixture(scope="module")
def machine():
    """The bundled XYZCB machine tool of Paper I."""
    from torchcal.kinematics import load_robot

    return load_robot("five_axis_xyzcb")


def random_commands(robot, count: int, seed: int) -> torch.Tensor:
    g = torch.Generator().manual_seed(seed)
    lim = robot.joint_map.limits
    return lim[:, 0] + torch.rand(count, lim.shape[0], generator=g) * (lim[:, 1] - lim[:, 0])


def write_targets(path, T: torch.Tensor, seeds: torch.Tensor, **columns):
    """A Cartesian targets CSV (x, y, z mm, rx, ry, rz deg URDF roll-pitch-yaw, q1..qN seeds in deg) for poses T
    (B, 4, 4) in metres; ``columns`` go first (label=..., tool=...)."""
    import pandas as pd

    from torchcal.compensate.targets import pose_rpy

    xyzrpy = pose_rpy(T)
    df = pd.DataFrame(dict(columns))
    for i, c in enumerate("xyz"):
        df[c] = xyzrpy[:, i].numpy() * 1000.0
    for i, c in enumerate(("rx", "ry", "rz")):
        df[c] = np.degrees(xyzrpy[:, 3 + i].numpy())
    for j in range(seeds.shape[1]):
        df[f"q{j + 1}"] = np.degrees(seeds[:, j].numpy())
    df.to_csv(path, index=False)
    return path


def randomize(model, seed: int, rot: float = 2e-3, trans: float = 2e-4, decay: float = 2.0):
    """Fill a RobotModel with seeded random errors decaying with the Chebyshev order."""
    g = torch.Generator().manual_seed(seed)
    je = model.joint_errors
    with torch.no_grad():
        k = torch.arange(je.coef.shape[-1])
        c = torch.randn(je.coef.shape, generator=g) / (1.0 + k) ** decay
        c[:, :3] *= rot
        c[:, 3:] *= trans
        je.coef.copy_(c * je.mask)
        kb = torch.arange(je.backlash.shape[-1])
        je.backlash.copy_(torch.randn(je.backlash.shape, generator=g) * rot * 0.1 / (1.0 + kb) ** decay * je.backlash_mask)
        model.base.twist.copy_(torch.randn(6, generator=g) * torch.tensor([rot] * 3 + [trans * 5] * 3))
        model.tools.delta.copy_(torch.randn(model.tools.delta.shape, generator=g) * trans)
    return model


@pytest.fixture(scope="module")
def damped_problem(fanuc, tools_m):
    """A randomized FANUC model, 400 commands, directions, their nominal poses T (a calibration-sized correction
    away on the model) and poses `far` stretched out of reach: what the damped least squares' variants are
    compared on (tests/compensate/test_damped_*.py)."""
    from torchcal.models.robot import RobotModel

    model = randomize(RobotModel(fanuc, tools_m, orders=4, backlash=True), 5, rot=3e-3, trans=3e-4)
    q = random_commands(fanuc, 400, 6)
    g = torch.Generator().manual_seed(7)
    s = torch.where(torch.rand(q.shape, generator=g) < 0.5, -1.0, 1.0).double()
    with torch.no_grad():
        T = model.nominal_flange(q)
    far = T.clone()
    far[:, :3, 3] *= 1.0 + 0.5 * torch.rand(q.shape[0], 1, generator=g, dtype=torch.float64)  # many out of reach
    return model, q, s, T, far


def assert_reachable_alike(a, b, model, q):
    """Two damped least squares results (a: a variant, b: the torch loop) on reachable targets: the same verdicts,
    the same commands away from singular poses, converged to the residual bound, iteration counts within one."""
    from torchcal.compensate.newton import nominal_sigma_min

    assert torch.equal(a.converged, b.converged) and torch.equal(a.stationary, b.stationary)
    clear = a.converged & (nominal_sigma_min(model, q) > 0.02)
    assert int(clear.sum()) > 0.75 * q.shape[0]
    assert float((a.q[clear] - b.q[clear]).abs().max()) < 1e-9
    assert float(a.residual[a.converged].max()) <= 1e-12
    assert (a.iterations[clear] - b.iterations[clear]).abs().max() <= 1


def assert_compensation_reaches_the_goal(model, q, s, least_converged: int):
    """compensate() on commands q (B, n), directions s: at least ``least_converged`` rows converge, and each
    converged row's modeled flange lands on the compensation goal to 1e-9 m. -> the result."""
    from torchcal.compensate import compensate, compensation_goal

    res = compensate(model, q, s)
    assert int(res.converged.sum()) >= least_converged
    with torch.no_grad():
        Fa = model.flange(res.q, s, base=False)
        goal = compensation_goal(model, q)
    ok = res.converged
    assert float((Fa[ok, :3, 3] - goal[ok, :3, 3]).norm(dim=-1).max()) < 1e-9
    return res


def assert_flange_jacobian_matches_finite_differences(model, q, s, h: float = 1e-6, atol: float = 1e-8):
    """RobotModel.flange_jacobian (body frame, per command) against central differences of RobotModel.flange."""
    n = q.shape[1]
    with torch.no_grad():
        F, J = model.flange_jacobian(q, s)
        Rt = F[:, :3, :3].transpose(1, 2)
        for j in range(n):
            dq = torch.zeros(n, dtype=torch.float64)
            dq[j] = h
            Fp, Fm = model.flange(q + dq, s, base=False), model.flange(q - dq, s, base=False)
            v = Rt @ ((Fp[:, :3, 3] - Fm[:, :3, 3]) / (2 * h))[..., None]
            dR = Rt @ (Fp[:, :3, :3] - Fm[:, :3, :3]) / (2 * h)
            w = torch.stack([dR[:, 2, 1], dR[:, 0, 2], dR[:, 1, 0]], -1)
            assert torch.allclose(v[..., 0], J[:, :3, j], atol=atol), j
            assert torch.allclose(w, J[:, 3:, j], atol=atol), j


def assert_point_jacobians_match_autograd(model, q, tool, s, v):
    """RobotModel.point_jacobians against torch.func.jacrev, every parameter group and v.

    -> (parameters by name, the closed-form Jacobians) for further checks.
    """
    from torch.func import functional_call, jacrev

    p, J = model.point_jacobians(q, tool, s, v)
    assert torch.allclose(p, model.points(q, tool, s, v), atol=1e-15)
    params = {k: t.detach() for k, t in model.named_parameters()}
    for name in params:
        def f(x, name=name):
            return functional_call(model, {**params, name: x}, (q, tool, s, v))
        assert torch.allclose(jacrev(f)(params[name]), J[name], atol=1e-13), name
    Jv = jacrev(lambda vv: model.points(q, tool, s, vv))(v)
    assert torch.allclose(torch.stack([Jv[b, :, b] for b in range(q.shape[0])]), J["v"], atol=1e-13)
    return params, J


@pytest.fixture(scope="module")
def one_thread():
    """Tiny problems: on a shared 2-core machine torch's intra-op threads make fits several times slower."""
    old = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(old)


# a revolute-prismatic-revolute arm with non-z axes: the cases the FANUC does not exercise
PRISMATIC_URDF = """<?xml version="1.0"?>
<robot name="rpr">
  <link name="base"/><link name="l1"/><link name="l2"/><link name="l3"/>
  <joint name="j1" type="revolute"><parent link="base"/><child link="l1"/>
    <origin xyz="0 0 0.4" rpy="0 0 0"/><axis xyz="0 0 1"/><limit lower="-2" upper="2" effort="1" velocity="1"/></joint>
  <joint name="j2" type="prismatic"><parent link="l1"/><child link="l2"/>
    <origin xyz="0.2 0 0" rpy="0 1.5707963267948966 0"/><axis xyz="0 0 1"/><limit lower="0" upper="0.5" effort="1" velocity="1"/></joint>
  <joint name="j3" type="revolute"><parent link="l2"/><child link="l3"/>
    <origin xyz="0 0 0.1" rpy="0 0 0"/><axis xyz="1 0 0"/><limit lower="-3" upper="3" effort="1" velocity="1"/></joint>
</robot>
"""


# the KUKA LBR iiwa 14 R820's standard DH parameters (a = 0): a robot users bring, from its datasheet
D_MM = [360.0, 0.0, 420.0, 0.0, 400.0, 0.0, 126.0]
ALPHA_DEG = [-90.0, 90.0, 90.0, -90.0, -90.0, 90.0, 0.0]
LIMIT_DEG = [170, 120, 170, 120, 170, 120, 175]


def ctrl_c_on_call(monkeypatch, module, name: str, call: int = 2) -> None:
    """Replace ``module.name`` by a wrapper that raises KeyboardInterrupt (Ctrl-C) on its ``call``-th call and
    runs the real function otherwise: an interrupted run, reproducibly."""
    real, calls = getattr(module, name), []

    def stopped(*args, **kwargs):
        calls.append(1)
        if len(calls) == call:
            raise KeyboardInterrupt
        return real(*args, **kwargs)

    monkeypatch.setattr(module, name, stopped)


def _urdf_from_dh(path):
    """A user's URDF of the KUKA LBR iiwa 14 R820 written from its datasheet's standard DH table (joint i's
    origin carries link i-1's a, d and alpha): a 7-axis robot torchcal does not bundle."""
    joints, prev = [], (0.0, 0.0, 0.0)  # (d, a, alpha) of the previous link
    for i, (d, al, lim) in enumerate(zip(D_MM, ALPHA_DEG, LIMIT_DEG)):
        pd, pa, pal = prev
        parent = "base_link" if i == 0 else f"link{i}"
        joints.append(f'<link name="link{i + 1}"/><joint name="a{i + 1}" type="revolute"><parent link="{parent}"/>'
                      f'<child link="link{i + 1}"/><origin xyz="{pa / 1e3} 0 {pd / 1e3}" rpy="{math.radians(pal)} 0 0"/>'
                      f'<axis xyz="0 0 1"/><limit lower="{-math.radians(lim)}" upper="{math.radians(lim)}" '
                      'effort="1" velocity="1"/></joint>')
        prev = (d, 0.0, al)
    pd, pa, pal = prev
    flange = (f'<link name="flange"/><joint name="flange_joint" type="fixed"><parent link="link7"/>'
              f'<child link="flange"/><origin xyz="{pa / 1e3} 0 {pd / 1e3}" rpy="{math.radians(pal)} 0 0"/></joint>')
    path.write_text('<robot name="iiwa14_from_dh"><link name="base_link"/>' + "".join(joints) + flange + "</robot>")
    return path


@pytest.fixture(scope="session")
def iiwa(tmp_path_factory):
    return torchcal.load_robot(str(_urdf_from_dh(tmp_path_factory.mktemp("user") / "iiwa14.urdf")))
