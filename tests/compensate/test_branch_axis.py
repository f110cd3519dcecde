"""The default bound tells a branch change from a wrist correction; 5-DOF compensation for axisymmetric tools.

- next to the wrist (q5 of 4-9 deg) a small orientation error needs q4 and q6 to turn by more than the
  former 5 deg bound: the default converges there, on q_nom's branch (same configuration flags);
- a solution on another branch (here the commanded q5 changes sign: a wrist flip of the controller's
  flags) is refused and flagged with the reason 'branch change', although it lies well inside the bound;
- with ``free_tool_axis`` the tool point and the tool axis's direction are reached exactly, the rotation
  about the axis is left free, and next to the wrist the joints move less than for 6-DOF.
"""

import math

import pytest
import torch

from conftest import random_commands, randomize
from torchcal.compensate.toolset import compensation_goal, inverse, model_tool_set_frame, tool_poses
from torchcal.compensate import FlangeKernel, branch_changed, compensate
from torchcal.compensate.result import BRANCH, CONVERGED
from torchcal.compensate.targets import compensate_targets
from torchcal.kinematics.transforms import homogeneous, pose_error
from torchcal.models.robot import RobotModel

DEG = math.pi / 180


@pytest.fixture(scope="module")
def model(fanuc, tools_m):
    return randomize(RobotModel(fanuc, tools_m, orders=6, backlash=1), 21, rot=4e-3)


def wrist_commands(fanuc, count, seed):
    """Random commands with |q5| between 4 and 9 deg, both signs, away from the stretched elbow (theta3 =
    q2 + q3 near 75.5 deg: there the modeled arm falls short of many nominal poses, out of reach)."""
    q = random_commands(fanuc, 3 * count, seed)
    q = q[(torch.rad2deg(q[:, 1] + q[:, 2]) - 75.5).abs() > 12.0][:count]
    g = torch.Generator().manual_seed(seed + 1)
    mag = (4.0 + 5.0 * torch.rand(count, generator=g, dtype=torch.float64)) * DEG
    q[:, 4] = torch.where(torch.arange(count) % 2 == 0, 1.0, -1.0).double() * mag
    return q


def wrist_flag(q):
    return torch.sign(torch.sin(q[:, 4]))


def test_next_to_the_wrist_the_default_converges_on_the_branch(model, fanuc):
    q = wrist_commands(fanuc, 200, 80)
    s = torch.ones_like(q)
    res = compensate(model, q, s)
    old = compensate(model, q, s, max_correction=5 * DEG)
    c = res.converged
    assert c.double().mean() >= 0.98
    free = compensate(model, q[~c], s[~c], max_correction=None, max_step=None, null_damping=0.0, branch=False)
    assert not bool(free.converged.any())  # the flagged rows: no solution at all
    # the wrist needs more than the former bound here, and those rows converge now
    need = c & (res.correction > 5 * DEG)
    assert int(need.sum()) >= 5 and not bool(old.converged[need].any())
    assert bool((res.correction[c] <= 30 * DEG).all())
    # (46) holds, recomputed with RobotModel, and every converged command keeps q_nom's flags
    with torch.no_grad():
        de = pose_error(model.flange(res.q, s, base=False), compensation_goal(model, q))
    assert float(de[c].norm(dim=-1).max()) <= 1e-11
    assert torch.equal(wrist_flag(res.q[c]), wrist_flag(q[c]))
    assert not bool(branch_changed(FlangeKernel(model), q, res.q, c).any())
    # where the former bound converged, the solution is the same
    both = c & old.converged
    assert torch.allclose(res.q[both], old.q[both], atol=1e-10, rtol=0)


def test_a_branch_flip_inside_the_bound_is_refused_with_a_reason(fanuc, tools_m):
    """A joint-5 offset of 0.1 rad: F_a(q) = F_n(q + o), so the exact correction of q5 = 0.05 rad is q5 = -0.05:
    the commanded q5 changes sign (the wrist flag flips), 5.7 deg away, well inside the 30 deg bound."""
    m = RobotModel(fanuc, tools_m, orders=2)
    with torch.no_grad():
        m.joint_errors.coef[4, 2, 0] = 0.1
        m.joint_errors.coef[:4, 2, 0] = 1e-3  # and small offsets elsewhere
    q = random_commands(fanuc, 20, 81)
    q[:10, 4] = 0.05  # these flip
    q[10:, 4] = 0.5  # these stay on their branch: q5 = 0.4
    res = compensate(m, q)
    free = compensate(m, q, branch=False)
    assert bool(free.converged.all())  # the flipped solution exists and is a small correction ...
    assert bool((free.q[:10, 4] < 0).all()) and bool((free.correction[:10] < 6 * DEG).all())
    assert not bool(res.converged[:10].any())  # ... but it is another branch: refused
    assert bool((res.status[:10] == BRANCH).all())
    why = res.reasons()
    assert all(w.startswith("branch change") for w in why[:10])
    assert bool(res.converged[10:].all()) and all(w == "" for w in why[10:])
    assert bool((res.status[10:] == CONVERGED).all())
    assert bool((res.q[10:, 4] > 0).all())
    # the test itself: a wrist flip of the same pose, an elbow-side change, and a small correction
    k = FlangeKernel(m)
    q0 = random_commands(fanuc, 50, 82)
    q0[:, 4] = q0[:, 4].abs().clamp_min(0.2)
    flip = q0.clone()
    flip[:, 3] += math.pi
    flip[:, 4] = -flip[:, 4]
    flip[:, 5] += math.pi
    with torch.no_grad():
        assert float(pose_error(m.nominal_flange(flip), m.nominal_flange(q0)).norm(dim=-1).max()) < 1e-12
    assert bool(branch_changed(k, q0, flip).all())
    assert not bool(branch_changed(k, q0, q0 + 1e-3).any())


def tool_axis_errors(model, q_new, q_nom, s, c, a):
    """Position error of the tool point c and angle between the tool axes a (flange frame), and the rotation
    about the axis: (B,) m, (B,) rad, (B,) rad."""
    with torch.no_grad():
        # in the tool set's frame (.toolset), which compensation puts in the nominal flange's place; c is a point
        # of the modeled flange (an identified tool point), a the tool's axis
        G = model_tool_set_frame(model)
        Fa = model.flange(q_new, s, base=False) @ G
        Fn = model.nominal_flange(q_nom)
        c = inverse(G)[:3, :3] @ c + inverse(G)[:3, 3]
    pa = Fa[:, :3, 3] + Fa[:, :3, :3] @ c
    pn = Fn[:, :3, 3] + Fn[:, :3, :3] @ c
    ax_a, ax_n = Fa[:, :3, :3] @ a, Fn[:, :3, :3] @ a
    ang = torch.atan2(torch.linalg.cross(ax_a, ax_n).norm(dim=-1), (ax_a * ax_n).sum(-1))
    spin = pose_error(Fa, Fn)[:, 3:] @ a
    return (pa - pn).norm(dim=-1), ang, spin


@pytest.mark.parametrize("axis", ["z", "oblique"])
def test_five_dof_reaches_point_and_axis_and_moves_less(model, fanuc, axis):
    q = wrist_commands(fanuc, 120, 83)
    s = torch.ones_like(q)
    if axis == "z":
        a, c, opt = torch.tensor([0.0, 0.0, 1.0], dtype=torch.float64), torch.tensor([0.0, 0.0, 0.16], dtype=torch.float64), True
    else:
        a = torch.tensor([1.0, 1.0, 2.0], dtype=torch.float64) / math.sqrt(6.0)
        c = torch.tensor([0.04, 0.04, 0.08], dtype=torch.float64)  # a point on the axis
        opt = a * 3.0  # any length
    five = compensate(model, q, s, free_tool_axis=opt, tool_point=c)
    six = compensate(model, q, s)
    f = five.converged
    assert f.double().mean() >= 0.98
    dp, ang, spin = tool_axis_errors(model, five.q, q, s, c, a)
    assert float(dp[f].max()) <= 1e-11 and float(ang[f].max()) <= 1e-11
    assert float(spin[f].abs().max()) > 1e-5  # the rotation about the axis is left free, not restored
    # reported residual = the 5-DOF error recomputed; pose_error is the full error at the tool point
    assert float(five.residual[f].max()) <= 1e-11
    # less joint motion (Euclidean norm of q_new - q_nom, what the pseudo-inverse steps minimize); for a z axis
    # the wrist's q4 still turns as much (the axis's direction near q5 = 0 needs it) and q6 no longer does
    both = f & six.converged
    n5, n6 = (five.q - q)[both].norm(dim=-1), (six.q - q)[both].norm(dim=-1)
    assert float(n5.mean()) < 0.85 * float(n6.mean())
    assert float((n5 <= n6 + 1e-9).double().mean()) >= 0.95
    assert bool((wrist_flag(five.q[f]) == wrist_flag(q[f])).all())


def test_five_dof_targets(model, fanuc):
    """compensate_targets with free_tool_axis: the identified tool point on the target, its z axis along the target's."""
    q = wrist_commands(fanuc, 60, 84)
    tool = torch.arange(60) % 3
    with torch.no_grad():
        F = model.nominal_flange(q)
        t = model.tools.nominal[tool]
        T = homogeneous(F[:, :3, :3], F[:, :3, 3] + (F[:, :3, :3] @ t[..., None])[..., 0])
    s = torch.ones_like(q)
    res = compensate_targets(model, T, q, tool, s, free_tool_axis=True)
    six = compensate_targets(model, T, q, tool, s)
    ok = res.converged
    assert ok.double().mean() >= 0.95 and all((r == "") == bool(k) for r, k in zip(res.reason, ok.tolist()))
    with torch.no_grad():
        Fa = model.flange(res.q, s, base=False)
        tip = Fa[:, :3, 3] + (Fa[:, :3, :3] @ model.tools()[tool][..., None])[..., 0]
    assert float((tip - T[:, :3, 3])[ok].norm(dim=-1).max()) < 1e-9
    za, zt = tool_poses(model, res.q, tool, s)[:, :3, 2], T[:, :3, 2]  # the tool set's z axis (.toolset)
    assert float(torch.linalg.cross(za, zt)[ok].norm(dim=-1).max()) < 1e-9
    both = ok & six.converged
    assert float((res.q - res.q_nominal)[both].norm(dim=-1).mean()) < float((six.q - six.q_nominal)[both].norm(dim=-1).mean())


def test_free_tool_axis_input_checks(model, fanuc):
    q = random_commands(fanuc, 3, 85)
    with pytest.raises(ValueError, match="free_tool_axis"):
        compensate(model, q, free_tool_axis=[0.0, 0.0, 0.0])
    with pytest.raises(ValueError, match="tool_point"):
        compensate(model, q, tool_point=[0.0, 0.0, 0.1])
    with pytest.raises(ValueError, match="tool_point"):
        compensate(model, q, free_tool_axis=True, tool_point=torch.zeros(2, 3))
