import math

import numpy as np
import pytest
import torch
from hypothesis import given, settings
from hypothesis import strategies as st

from conftest import fanuc_dh_reference, random_commands
from torchcal.kinematics import URDFError, load_robot, load_urdf

DEG = math.pi / 180


def test_fanuc_matches_independent_dh_reference(fanuc):
    q_deg = random_commands(fanuc, 500, 0) / DEG
    ref = fanuc_dh_reference(q_deg.numpy())
    T = fanuc.chain.fk(fanuc.joint_map.to_joint(q_deg * DEG))
    # 1e-12 mm
    assert np.abs(T.numpy() - ref).max() < 1e-15


@settings(max_examples=50, deadline=None)
@given(st.lists(st.floats(-179, 179), min_size=6, max_size=6))
def test_fanuc_dh_property(q):
    robot = load_robot("fanuc_lrmate200i")
    q_deg = torch.tensor([q])
    T = robot.chain.fk(robot.joint_map.to_joint(q_deg * DEG))
    assert np.abs(T.numpy() - fanuc_dh_reference(q_deg.numpy())).max() < 1e-15


@pytest.mark.parametrize("name", ["fanuc_lrmate200i", "abb_irb120"])
def test_pytorch_kinematics_cross_check(name):
    """pk's own chain agrees to its float32 rounding of the origins (~1e-7 m), no better."""
    import pytorch_kinematics as pk

    from torchcal.kinematics import load_robot, urdf_dir

    robot = load_robot(name)
    xml = (urdf_dir() / f"{name}.urdf").read_text()
    pkc = pk.build_serial_chain_from_urdf(xml, "flange").to(dtype=torch.float64)
    theta = robot.joint_map.to_joint(random_commands(robot, 64, 1))
    diff = (pkc.forward_kinematics(theta).get_matrix() - robot.chain.fk(theta)).abs().max()
    assert diff < 1e-6


def test_joint_map_coupling_and_round_trip(fanuc):
    jm = fanuc.joint_map
    q = random_commands(fanuc, 10, 2)
    theta = jm.to_joint(q)
    assert torch.allclose(theta[:, 1], q[:, 1] - 90 * DEG)
    assert torch.allclose(theta[:, 2], q[:, 1] + q[:, 2])
    assert torch.allclose(jm.to_command(theta), q, atol=1e-15)
    ranges = jm.joint_ranges() / DEG
    assert torch.allclose(ranges[2], torch.tensor([-60.0, 200.0]))
    assert torch.allclose(ranges[1], torch.tensor([-120.0, 10.0]))


def test_fixed_joints_fold_and_prismatic():
    xml = """<robot name="r">
      <link name="a"/><link name="b"/><link name="c"/><link name="d"/>
      <joint name="slide" type="prismatic"><parent link="a"/><child link="b"/>
        <origin xyz="0.1 0 0" rpy="0 0 0"/><axis xyz="0 0 2"/><limit lower="0" upper="0.5" effort="1" velocity="1"/></joint>
      <joint name="mount" type="fixed"><parent link="b"/><child link="c"/><origin xyz="0 0.2 0" rpy="0 0 1.5707963267948966"/></joint>
      <joint name="spin" type="revolute"><parent link="c"/><child link="d"/>
        <origin xyz="0 0 0.3"/><axis xyz="1 0 0"/><limit lower="-1" upper="1" effort="1" velocity="1"/></joint>
    </robot>"""
    chain = load_urdf(xml)
    assert chain.joint_names == ["slide", "spin"]
    assert chain.prismatic.tolist() == [True, False]
    T = chain.fk(torch.tensor([[0.25, 0.0]]))
    # slide along z by 0.25, then mount offset (0, 0.2, 0) rotated 90 deg about z, then 0.3 up
    assert torch.allclose(T[0, :3, 3], torch.tensor([0.1, 0.2, 0.55]), atol=1e-15)
    T2 = chain.fk(torch.tensor([[0.0, 0.5]]))
    # spin axis is x of the joint frame, i.e. world y after the 90 deg yaw
    assert torch.allclose(T2[0, :3, :3] @ torch.tensor([0.0, 0.0, 1.0]), torch.tensor([math.sin(0.5), 0.0, math.cos(0.5)]), atol=1e-15)


@pytest.mark.parametrize(
    "joint, needle",
    [
        ('<joint name="j1" type="revolute"><parent link="a"/><child link="b"/><axis xyz="0 0 1"/></joint>', "j1"),
        ('<joint name="j1" type="revolute"><parent link="a"/><child link="b"/><axis xyz="0 0 0"/>'
         '<limit lower="-1" upper="1" effort="1" velocity="1"/></joint>', "zero vector"),
        ('<joint name="j1" type="revolute"><parent link="a"/><child link="b"/><axis xyz="0 0 1"/>'
         '<limit lower="1" upper="-1" effort="1" velocity="1"/></joint>', "lower limit"),
        # NaN passed: a zero-vector test is False for it, and the chain crashed the fit's Cholesky
        ('<joint name="j1" type="revolute"><parent link="a"/><child link="b"/><origin xyz="nan 0 0"/>'
         '<axis xyz="0 0 1"/><limit lower="-1" upper="1" effort="1" velocity="1"/></joint>', "<origin> .*finite"),
        ('<joint name="j1" type="revolute"><parent link="a"/><child link="b"/><axis xyz="0 nan 1"/>'
         '<limit lower="-1" upper="1" effort="1" velocity="1"/></joint>', "<axis> .*finite"),
        ('<joint name="j1" type="prismatic"><parent link="a"/><child link="b"/><axis xyz="0 0 1"/>'
         '<limit lower="0" upper="inf" effort="1" velocity="1"/></joint>', "<limit> .*finite"),
    ],
)
def test_validation_names_the_joint(joint, needle):
    xml = f'<robot name="r"><link name="a"/><link name="b"/>{joint}</robot>'
    with pytest.raises(URDFError, match=needle) as err:
        load_urdf(xml)
    assert "j1" in str(err.value)


def test_bad_sources():
    with pytest.raises(URDFError, match="not found"):
        load_urdf("/nonexistent/robot.urdf")
    with pytest.raises(URDFError, match="unknown robot"):
        load_robot("no_such_robot")
    with pytest.raises(URDFError, match="not a readable URDF"):
        load_urdf("<robot name='x'><link name='a'></robot>")


def _fanuc_xml():
    from torchcal.kinematics import urdf_dir

    return (urdf_dir() / "fanuc_lrmate200i.urdf").read_text()


def test_missing_parent_link_names_the_joint_and_the_link():
    xml = _fanuc_xml().replace('<parent link="link5"/>', '<parent link="link5x"/>')
    with pytest.raises(URDFError) as err:
        load_urdf(xml, end_link="flange")
    msg = str(err.value)
    assert "joint 'joint6'" in msg and "'link5x'" in msg and "not defined" in msg
    xml = _fanuc_xml().replace('<child link="link5"/>', '<child link="link5b"/>')
    with pytest.raises(URDFError, match="joint 'joint5' names child link 'link5b'"):
        load_urdf(xml, end_link="flange")


def test_joint_without_axis_is_logged(caplog):
    import re

    xml = re.sub(r'(<joint name="joint2".*?)<axis[^>]*/>', r"\1", _fanuc_xml(), count=1, flags=re.S)
    assert xml != _fanuc_xml()
    with caplog.at_level("WARNING", logger="torchcal"):
        chain = load_urdf(xml, end_link="flange")
    assert chain.axes[1].tolist() == [1.0, 0.0, 0.0]
    assert any("joint 'joint2' has no <axis>" in r.getMessage() for r in caplog.records)


def test_urdf_error_is_a_torchcal_error():
    from torchcal.core.exceptions import TorchcalError

    with pytest.raises(TorchcalError):
        load_robot("no_such_robot")
    assert issubclass(URDFError, ValueError)


def test_unknown_error_variable_names_the_file_and_the_key(tmp_path):
    from torchcal.kinematics import urdf_dir

    text = (urdf_dir() / "fanuc_lrmate200i.yaml").read_text()
    assert "error_variable: command" in text
    path = tmp_path / "my_robot.yaml"
    path.write_text(text.replace("error_variable: command", "error_variable: encoder")
                    .replace("urdf: ", f"urdf: {urdf_dir()}/", 1) if "urdf: " in text else text)
    with pytest.raises(URDFError) as err:
        load_robot(path)
    msg = str(err.value)
    assert str(path) in msg and "error_variable" in msg and "'encoder'" in msg
