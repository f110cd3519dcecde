"""Backlash (Paper II (13)) moves each joint about, or along, its own axis, whatever axis its URDF gives it.

Bundled robots turn every joint about +z, where E_i's eps_z is that turn. A ROS-style URDF (axes along y or x)
and a robot on a linear track (a prismatic joint) are not: there backlash used to be a turn about the joint
frame's z (a rail's lost motion became a yaw of its carriage). It now adds the turn about (move along) the
joint's own axis to E_i, and the compiled backends carry it. The reference here is the physical meaning: a lost
motion b of joint i is the chain with joint i moved by b."""

import math

import pytest
import torch

from tests.conftest import (assert_compensation_reaches_the_goal, assert_flange_jacobian_matches_finite_differences,
                            assert_point_jacobians_match_autograd)
from torchcal.core.measurements import Measurements
from torchcal.core.params import LENGTH, ANGLE
from torchcal.identify import NoiseModel, fit
from torchcal.models.robot import RobotModel

# a rail along x, then an arm written ROS-Industrial style: joint frames parallel to the base, axes z, y, y, x, y, x
JOINTS = [  # name, type, origin xyz (m), axis, limits
    ("rail", "prismatic", (0.0, 0.0, 0.2), (1, 0, 0), (0.0, 3.0)),
    ("a1", "revolute", (0.0, 0.0, 0.4), (0, 0, 1), (-2.9, 2.9)),
    ("a2", "revolute", (0.25, 0.0, 0.3), (0, 1, 0), (-1.5, 1.2)),
    ("a3", "revolute", (0.0, 0.0, 0.68), (0, 1, 0), (-2.0, 1.2)),
    ("a4", "revolute", (0.3, 0.0, 0.035), (1, 0, 0), (-3.0, 3.0)),
    ("a5", "revolute", (0.37, 0.0, 0.0), (0, 1, 0), (-2.0, 2.0)),
    ("a6", "revolute", (0.1, 0.0, 0.0), (1, 0, 0), (-3.0, 3.0)),
]


@pytest.fixture(scope="module")
def track(tmp_path_factory):
    import torchcal

    links = "".join(f'<link name="l{i}"/>' for i in range(len(JOINTS) + 1)) + '<link name="flange"/>'
    joints = "".join(
        f'<joint name="{n}" type="{t}"><parent link="l{i}"/><child link="l{i + 1}"/>'
        f'<origin xyz="{" ".join(map(str, o))}" rpy="0 0 0"/><axis xyz="{" ".join(map(str, a))}"/>'
        f'<limit lower="{lo}" upper="{hi}" effort="1" velocity="1"/></joint>'
        for i, (n, t, o, a, (lo, hi)) in enumerate(JOINTS))
    tip = (f'<joint name="tip" type="fixed"><parent link="l{len(JOINTS)}"/><child link="flange"/>'
           '<origin xyz="0.08 0 0" rpy="0 1.5707963267948966 0"/></joint>')
    path = tmp_path_factory.mktemp("track") / "track.urdf"
    path.write_text(f'<robot name="track_arm">{links}{joints}{tip}</robot>')
    return torchcal.load_robot(str(path))


TOOLS = torch.tensor([[0.03, 0.05, 0.15], [0.05, -0.03, 0.15], [-0.03, -0.05, 0.15]], dtype=torch.float64)


def _commands(robot, count, seed):
    lim = robot.joint_map.limits
    g = torch.Generator().manual_seed(seed)
    u = torch.rand(count, lim.shape[0], generator=g, dtype=torch.float64)
    return lim[:, 0] + 0.1 * (lim[:, 1] - lim[:, 0]) + 0.8 * u * (lim[:, 1] - lim[:, 0])


def _directions(count, n, seed):
    g = torch.Generator().manual_seed(seed)
    return torch.randint(0, 2, (count, n), generator=g).to(torch.float64) * 2.0 - 1.0


@pytest.mark.parametrize("joint", range(len(JOINTS)))
def test_backlash_moves_the_joint_about_or_along_its_own_axis(track, joint):
    model = RobotModel(track, TOOLS, orders=0, backlash=0)
    assert model.flange_snapshot().live is None  # the compiled backends evaluate it themselves
    b = 1e-3  # m on the rail, rad elsewhere
    with torch.no_grad():
        model.joint_errors.backlash[joint, 0] = b
    q = _commands(track, 20, joint)
    s = torch.zeros_like(q)
    s[:, joint] = 1.0
    moved = q.clone()
    moved[:, joint] += b
    tool = torch.arange(20) % 3
    with torch.no_grad():
        got = model.points(q, tool, s)
        want = model.points(moved, tool, None)
        still = model.points(q, tool, None)
    assert float((got - want).norm(dim=-1).max()) < 1e-12
    assert float((got - still).norm(dim=-1).min()) > 1e-5  # it does move the tools


def test_a_rails_backlash_is_a_length_and_an_arms_an_angle(track):
    model = RobotModel(track, TOOLS, orders=0, backlash=0)
    group = [g for g in model.joint_errors.param_groups() if g.name == "joint_errors.backlash"][0]
    assert group.kinds[0] == LENGTH and set(group.kinds[1:]) == {ANGLE}


def _random_model(track, orders, seed, lost_motion):
    """A model with random error terms and a visible lost motion on every joint (m on the rail, rad elsewhere)."""
    from tests.conftest import randomize

    model = randomize(RobotModel(track, TOOLS, orders=orders, backlash=orders - 1), seed, rot=1e-4, trans=1e-5)
    with torch.no_grad():
        model.joint_errors.backlash[:, 0] += lost_motion
    return model


def test_jacobians_match_autograd_and_finite_differences(track):
    model = _random_model(track, 2, 3, 3e-4)
    q = _commands(track, 6, 1)
    s = _directions(6, 7, 2)
    v = torch.randn(6, 7, generator=torch.Generator().manual_seed(4), dtype=torch.float64) * 1e-4
    assert_point_jacobians_match_autograd(model, q, torch.arange(6) % 3, s, v)
    assert_flange_jacobian_matches_finite_differences(model, q, s)


def test_fit_finds_the_lost_motion_of_a_rail_and_of_y_axis_joints(track):
    """Measurements of the nominal chain at q + s b (each joint's lost motion, independent of the model's form):
    an order-0 model with backlash recovers b to the noise and fits to it. With backlash about the frame's z, the
    rail's 0.1 mm and a2's 0.01 deg have no such term, and the fit did not reach them."""
    b = torch.tensor([1e-4, math.radians(0.01), math.radians(0.012), math.radians(0.008), math.radians(0.02),
                      math.radians(0.015), math.radians(0.02)], dtype=torch.float64)
    nominal = RobotModel(track, TOOLS, orders=0)
    q = _commands(track, 80, 5)
    s = _directions(80, 7, 6)
    rows = q.repeat(3, 1), s.repeat(3, 1)
    tool = torch.arange(3).repeat_interleave(80)
    with torch.no_grad():
        p = nominal.points(rows[0] + rows[1] * b, tool, None)
    p = p + torch.randn(p.shape, generator=torch.Generator().manual_seed(7), dtype=torch.float64) * 2e-6
    data = Measurements.from_tensors(rows[0], tool, p, direction=rows[1])
    model = RobotModel(track, TOOLS, orders=0, backlash=0)
    tiny = torch.full((7,), 1e-14, dtype=torch.float64)
    fit(model, data, NoiseModel(2e-6, tiny, tiny))
    got = model.joint_errors.backlash[:, 0].detach()
    assert float((got - b).abs()[0]) < 3e-6  # m: the rail's 0.1 mm to 3 µm
    assert float((got - b).abs()[1:].max()) < math.radians(0.002)
    with torch.no_grad():
        res = (model.points(data.q, data.tool, data.direction) - p).norm(dim=-1)
    assert float(res.mean()) < 1e-5  # m


def test_compensation_reaches_the_goal(track):
    model = _random_model(track, 1, 8, 2e-4)
    assert_compensation_reaches_the_goal(model, _commands(track, 60, 9), _directions(60, 7, 10), 55)


def test_robots_turning_about_z_keep_the_papers_eps_z_form(fanuc, tools_m):
    """Every bundled robot: backlash stays on eps_z, the factored fits' form."""
    from torchcal.compensate.kernel import FlangeKernel
    from torchcal.identify.structured import RobotStructure
    from torchcal.identify.layout import ParameterLayout
    from torchcal.measure import PointTargets

    model = RobotModel(fanuc, tools_m, orders=2, backlash=True)
    ez = torch.tensor([0.0, 0.0, 1.0, 0.0, 0.0, 0.0], dtype=torch.float64)
    assert torch.equal(model.joint_errors.screw, ez.expand(6, 6)) and FlangeKernel(model).bl_code == 1
    instrument = PointTargets(torch.zeros(2, 3, dtype=torch.float64), sigma=1e-5)
    assert RobotStructure.supports(model, instrument, ParameterLayout(model))
    assert RobotModel(fanuc, tools_m, orders=2, backlash=True, backlash_on="command").backlash_coupling() is not None


def test_the_factored_fit_leaves_a_rail_to_the_generic_path(track):
    """The factored (fleet) solver's backlash columns are eps_z's: a chain whose backlash acts on another axis
    takes the generic path, which has the screw."""
    from torchcal.identify.structured import RobotStructure
    from torchcal.identify.layout import ParameterLayout
    from torchcal.measure import PointTargets

    instrument = PointTargets(torch.zeros(2, 3, dtype=torch.float64), sigma=1e-5)
    assert not RobotStructure.supports(RobotModel(track, TOOLS, orders=1, backlash=0), instrument,
                                       ParameterLayout(RobotModel(track, TOOLS, orders=1, backlash=0)))
    assert RobotStructure.supports(RobotModel(track, TOOLS, orders=1), instrument,
                                   ParameterLayout(RobotModel(track, TOOLS, orders=1)))


def test_fleet_features_read_each_joints_own_axis(track):
    """The fleet's 'backlash' and 'transmission error' of a rail and of a y-axis joint: the rail's lost motion
    (was 0: read from eps_z) and a2's error about y (was its tilt about the frame's z)."""
    from torchcal.identify.fleet_outliers import joint_features

    model = RobotModel(track, TOOLS, orders=1, backlash=0)
    with torch.no_grad():
        model.joint_errors.backlash[0, 0] = 7e-5  # m: the rail
        model.joint_errors.coef[2, 1, 1] = 2e-4  # a2: eps_y c1, a turn about its own axis varying over its range
        model.joint_errors.coef[3, 2, 1] = 5e-4  # a3: eps_z c1, a tilt (its axis is y): no transmission error
    f = joint_features(model)
    assert abs(float(f["backlash"][0]) - 7e-5) < 1e-12 and float(f["backlash"][1:].abs().max()) < 1e-15
    tx = f["transmission error"]
    assert float(tx[2]) > 1e-4 and float(tx[3]) < 1e-15


def test_a_rail_written_in_metres_is_refused(track):
    """A 3 m rail in metres (0.3..2.7) is a valid-looking file that would drive the carriage 2.7 mm."""
    from torchcal.io.unit_checks import UnitsError, check_units, metre_columns

    q = _commands(track, 40, 11)  # SI: the rail in m, read from a file's mm
    tool = torch.arange(3).repeat_interleave(40)
    nominal = RobotModel(track, TOOLS, orders=0)
    with torch.no_grad():
        p = nominal.points(q.repeat(3, 1), tool, None)
    good = Measurements.from_tensors(q.repeat(3, 1), tool, p)
    assert metre_columns(good.q, track) == []
    check_units(good, track, TOOLS)  # mm as the contract says: passes
    slipped = q.clone()
    slipped[:, 0] = q[:, 0] / 1000.0  # the file's rail column holds metres
    bad = Measurements.from_tensors(slipped.repeat(3, 1), tool, p)
    assert metre_columns(bad.q, track) == ["q1"]
    with pytest.raises(UnitsError, match=r"q1 .*look like metres"):
        check_units(bad, track, TOOLS)


def test_compensated_file_of_a_rail_robot_keeps_mm_and_deg_apart(track, tmp_path):
    """max_dq took the larger of a rail's mm and an arm joint's deg in each row; now max_dq is the revolute
    joints' (deg) and max_dq_mm the rail's (mm)."""
    import numpy as np
    import pandas as pd

    from torchcal.app.files import compensate_file
    from torchcal.io.rundir import save_model

    model = _random_model(track, 1, 8, 2e-4)
    save_model(tmp_path / "run", model)
    q = _commands(track, 20, 12)
    qf = q.numpy().copy()
    qf[:, 0] *= 1000.0  # mm
    qf[:, 1:] = np.degrees(qf[:, 1:])
    cols = [f"q{i + 1}" for i in range(7)]
    frame = pd.DataFrame(qf, columns=cols)
    for i in range(7):
        frame[f"dir{i + 1}"] = 1
    frame.to_csv(tmp_path / "cmds.csv", index=False)
    compensate_file(tmp_path / "run", tmp_path / "cmds.csv", tmp_path / "out.csv")
    out = pd.read_csv(tmp_path / "out.csv")
    moved = np.abs(out[cols].to_numpy() - qf)
    assert np.allclose(out["max_dq_mm"], moved[:, 0]) and np.allclose(out["max_dq"], moved[:, 1:].max(1))


def test_a_simulated_rails_magnitudes_say_mm(track):
    """truth.json's describe lists angle-type terms under '_deg' names; a rail's are mm, which it now says."""
    from torchcal.sim.truth import TruthRobot

    d = TruthRobot.random(track, TOOLS, 0).describe()
    assert d["angle_terms_unit"] == ["mm"] + ["deg"] * 6
