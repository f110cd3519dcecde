"""The error variable of each joint (Paper II (24)): command q_i or URDF θ_i, whatever the coupling."""

import pytest
import torchcal
import torch
from hypothesis import given, settings
from hypothesis import strategies as st

from torchcal.kinematics.joint_map import JointMap, normalize_error_variable


@st.composite
def joint_maps(draw):
    n = draw(st.integers(2, 6))
    seed = draw(st.integers(0, 10_000))
    g = torch.Generator().manual_seed(seed)
    A = torch.eye(n, dtype=torch.float64) + 0.5 * torch.randn(n, n, generator=g, dtype=torch.float64).tril(-1)  # invertible
    offset = torch.randn(n, generator=g, dtype=torch.float64)
    lo = -1.0 - torch.rand(n, generator=g, dtype=torch.float64)
    limits = torch.stack([lo, lo + 0.5 + 2 * torch.rand(n, generator=g, dtype=torch.float64)], 1)
    ev = draw(st.lists(st.sampled_from(["command", "joint"]), min_size=n, max_size=n))
    return JointMap([f"J{i + 1}" for i in range(n)], A, offset, limits, torch.zeros(n, dtype=torch.bool), ev), seed


@settings(max_examples=40, deadline=None)
@given(joint_maps())
def test_error_map_follows_the_chosen_variable(jm_seed):
    jm, seed = jm_seed
    q = torch.rand(7, jm.n, generator=torch.Generator().manual_seed(seed + 1), dtype=torch.float64)
    q = jm.limits[:, 0] + q * (jm.limits[:, 1] - jm.limits[:, 0])
    A, b = jm.error_map()
    u = q @ A.T + b
    theta = jm.to_joint(q)
    for i, var in enumerate(jm.error_variable):
        assert torch.allclose(u[:, i], q[:, i] if var == "command" else theta[:, i], atol=1e-14)
    # the ranges are those of the variable over the command box: every u lies inside, and each end is reached
    r = jm.error_ranges()
    assert (u >= r[:, 0] - 1e-12).all() and (u <= r[:, 1] + 1e-12).all()
    corners = torch.where(torch.rand(512, jm.n, generator=torch.Generator().manual_seed(seed + 2)) < 0.5,
                          jm.limits[:, 0], jm.limits[:, 1])
    uc = corners @ A.T + b
    assert torch.allclose(uc.min(0).values, r[:, 0], atol=1e-12) or jm.n > 5  # 512 corners cover 2^n for n <= 5
    assert torch.allclose(uc.max(0).values, r[:, 1], atol=1e-12) or jm.n > 5


def test_error_variable_names_the_joint_when_wrong():
    with pytest.raises(ValueError, match="J2.*'gearbox'"):
        normalize_error_variable(["command", "gearbox"], 2, ["J1", "J2"])
    with pytest.raises(ValueError, match="one entry per joint"):
        normalize_error_variable(["command"], 2)
    assert normalize_error_variable("joint", 3) == ["joint"] * 3


def _robot_files(tmp_path, yaml_edit=None, urdf_edit=None):
    """A copy of the bundled FANUC's YAML and URDF in tmp_path, each optionally edited as text."""
    from torchcal.kinematics.robot import urdf_dir

    y = (urdf_dir() / "fanuc_lrmate200i.yaml").read_text()
    u = (urdf_dir() / "fanuc_lrmate200i.urdf").read_text()
    (tmp_path / "fanuc_lrmate200i.urdf").write_text(urdf_edit(u) if urdf_edit else u)
    (tmp_path / "robot.yaml").write_text(yaml_edit(y) if yaml_edit else y)
    return tmp_path / "robot.yaml"


@pytest.mark.parametrize("edit,message", [
    (lambda y: y.replace("  - [0, 1, 1, 0, 0, 0]", "  - [0, 1, 1, 0, 0]"),
     r"robot.yaml: coupling\[2\] \(URDF joint 3\) must hold 6 numbers .* got 5 numbers"),
    (lambda y: y.replace("offset: [0, -90, 0, 0, 0, 0]", "offset: [0, -90, 0, 0, 0]"),
     r"robot.yaml: 'offset' must hold 6 numbers .* got 5 entries"),
    (lambda y: y.replace("upper: 100}", "upper: 1O0}", 1),
     r"robot.yaml: joints\[0\] \('J1'\) upper: '1O0' is not a number"),
    (lambda y: y.replace("error_variable: command", "error_varaible: joint"),
     r"unknown key 'error_varaible' \(did you mean 'error_variable'\?\)"),
    (lambda y: y.replace("{name: J5,", "{name: J4,"), r"joint name \['J4'\] given twice"),
])
def test_a_typed_joint_map_mistake_names_the_file_and_the_entry(tmp_path, edit, message):
    from torchcal.kinematics.urdf import URDFError

    with pytest.raises(URDFError, match=message):
        torchcal.load_robot(str(_robot_files(tmp_path, edit)))


def test_a_urdf_in_millimetres_is_named(tmp_path):
    import re

    from torchcal.kinematics.urdf import URDFError

    def to_mm(u):  # every origin's xyz times 1000
        return re.sub(r'xyz="([^"]+)"', lambda m: 'xyz="' + " ".join(str(float(v) * 1000) for v in m.group(1).split())
                      + '"', u)

    with pytest.raises(URDFError, match=r"fanuc_lrmate200i.urdf: the link offsets add up to .* look like millimetres"):
        torchcal.load_robot(str(_robot_files(tmp_path, None, to_mm)))
    torchcal.load_robot(str(_robot_files(tmp_path)))  # the metres themselves load


def test_one_joint_typed_in_radians_is_warned(tmp_path, caplog):
    path = _robot_files(tmp_path, lambda y: y.replace("lower: -90, upper: 90}", "lower: -1.571, upper: 1.571}"))
    with caplog.at_level("WARNING", logger="torchcal"):
        robot = torchcal.load_robot(str(path))
    assert robot.n == 6 and "joints[4] 'J5' [-1.571, 1.571]" in caplog.text and "radians typed here?" in caplog.text
