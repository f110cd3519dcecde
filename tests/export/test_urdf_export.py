"""Calibrated URDF export: exact round trips of the constant terms, joint map kept, yourdfpy loads it."""

import pytest
import torch
import yourdfpy

from conftest import random_commands, randomize
from torchcal.export import compare_urdf, constant_origins, export_urdf, urdf_only_model
from torchcal.kinematics import load_robot, urdf_dir, validate_urdf
from torchcal.kinematics.transforms import so3_exp, so3_log
from torchcal.core.measurements import Measurements
from torchcal.models.robot import RobotModel


def pose_gap(A, B):
    """Largest translation (m) and rotation (rad) difference between pose batches (B, 4, 4)."""
    dp = (A[:, :3, 3] - B[:, :3, 3]).norm(dim=1).max()
    dr = so3_log(A[:, :3, :3].transpose(1, 2) @ B[:, :3, :3]).norm(dim=1).max()
    return float(dp), float(dr)


def exported_flange(export, q):
    r = export.robot
    return r.chain.fk(r.joint_map.to_joint(q))


def constant_model(robot, tools_m, seed, scale=1.0):
    """Only order-0 joint errors + a base correction, large enough to matter (mrad, 0.1 mm)."""
    m = RobotModel(robot, tools_m, orders=0)
    g = torch.Generator().manual_seed(seed)
    with torch.no_grad():
        m.joint_errors.coef[:, :3, 0] = torch.randn(robot.n, 3, generator=g) * 5e-3 * scale
        m.joint_errors.coef[:, 3:, 0] = torch.randn(robot.n, 3, generator=g) * 5e-4 * scale
        m.base.twist.copy_(torch.randn(6, generator=g) * torch.tensor([1e-2] * 3 + [2e-3] * 3) * scale)
    return m


@pytest.mark.parametrize("base", ["joint", "link"])
def test_constant_errors_round_trip_exactly(tmp_path, fanuc, tools_m, base):
    model = constant_model(fanuc, tools_m, 1)
    out = export_urdf(model, tmp_path / "cal.urdf", base=base)
    assert out.joint_map is not None and out.joint_map.is_file()
    q = random_commands(fanuc, 200, 2)
    with torch.no_grad():
        F_model = model.flange(q, base=False)
    dp, dr = pose_gap(exported_flange(out, q), F_model)
    assert dp < 1e-12 and dr < 1e-12  # 1e-9 mm, 1e-12 rad
    # the errors are not small: the nominal robot is far off
    dp0, _ = pose_gap(fanuc.chain.fk(fanuc.joint_map.to_joint(q)), F_model)
    assert dp0 > 1e-4
    # the joint map is the same (FANUC coupling theta3 = q2 + q3, offset theta2 = q2 - 90 deg)
    for key in ("coupling", "offset", "limits"):
        assert torch.equal(getattr(out.robot.joint_map, key), getattr(fanuc.joint_map, key))
    assert out.robot.chain.joint_names == fanuc.chain.joint_names
    assert torch.equal(out.robot.chain.tip, fanuc.chain.tip)


def test_measurement_frame_can_be_included(tmp_path, fanuc, tools_m):
    T = torch.eye(4)
    T[:3, :3] = so3_exp(torch.tensor([0.4, -2.1, 1.3]))  # a tracker frame far from the base
    T[:3, 3] = torch.tensor([1.5, -2.0, 0.3])
    model = constant_model(fanuc, tools_m, 4)
    model.base.nominal.copy_(T)
    assert torch.linalg.det(T[:3, :3]) == pytest.approx(1.0)
    out = export_urdf(model, tmp_path / "cal.urdf", measurement_frame=True)
    q = random_commands(fanuc, 50, 5)
    with torch.no_grad():
        dp, dr = pose_gap(exported_flange(out, q), model.flange(q, base=True))
    assert dp < 1e-11 and dr < 1e-12  # metres-away frame: rounding of a 2.5 m offset


def test_joint_dependent_terms_stay_out(tmp_path, fanuc, tools_m):
    model = randomize(RobotModel(fanuc, tools_m, orders=3, backlash=True), 6, rot=5e-3, trans=5e-4)
    out = export_urdf(model, tmp_path / "cal.urdf", constants="c0")  # the fitted constants: test_urdf_projection.py
    q = random_commands(fanuc, 100, 7)
    # reference: the same model with every order >= 1 coefficient zeroed, backlash not applied
    ref = RobotModel(fanuc, tools_m, orders=3, backlash=True)
    ref.load_state_dict(model.state_dict())
    with torch.no_grad():
        ref.joint_errors.coef[..., 1:] = 0.0
        F_ref = ref.flange(q, base=False)
        F_full = model.flange(q, torch.ones_like(q), base=False)
    dp, dr = pose_gap(exported_flange(out, q), F_ref)
    assert dp < 1e-12 and dr < 1e-12
    assert pose_gap(exported_flange(out, q), F_full)[0] > 1e-5  # the remainder is real and not in the file
    # constant_origins is the chain-level statement of the same thing
    O = constant_origins(model)
    assert torch.allclose(O, out.robot.chain.origins, atol=1e-14, rtol=0)


def test_file_loads_with_yourdfpy_and_validates(tmp_path, fanuc, tools_m):
    model = constant_model(fanuc, tools_m, 8)
    out = export_urdf(model, tmp_path / "sub" / "cal.urdf", base="link", name="fanuc_calibrated")
    assert validate_urdf(out.urdf.read_text()) == []
    urdf = yourdfpy.URDF.load(str(out.urdf), build_scene_graph=True, load_meshes=False)
    assert urdf.robot.name == "fanuc_calibrated"
    q = random_commands(fanuc, 5, 9)
    theta = fanuc.joint_map.to_joint(q)
    with torch.no_grad():
        F_model = model.flange(q, base=False)
    for k in range(5):  # yourdfpy's own FK (numpy scene graph), one configuration at a time
        urdf.update_cfg(dict(zip(fanuc.chain.joint_names, theta[k].tolist())))
        T = torch.tensor(urdf.get_transform("flange", urdf.base_link).copy())
        assert torch.allclose(T, F_model[k], atol=1e-12)


def test_bare_urdf_source_needs_no_joint_map(tmp_path, tools_m):
    robot = load_robot(urdf_dir() / "fanuc_lrmate200i.urdf")
    model = constant_model(robot, tools_m, 10)
    out = export_urdf(model, tmp_path / "cal.urdf")
    assert out.joint_map is None and out.path == out.urdf
    q = random_commands(robot, 50, 11)
    with torch.no_grad():
        dp, dr = pose_gap(out.robot.chain.fk(q), model.flange(q, base=False))
    assert dp < 1e-12 and dr < 1e-12


def test_compare_urdf_reports_urdf_and_full_residuals(tmp_path, fanuc, tools_m):
    truth = randomize(RobotModel(fanuc, tools_m, orders=3, backlash=False), 12, rot=5e-3, trans=5e-4)
    q = random_commands(fanuc, 40, 13)
    tool = torch.arange(40) % 3
    with torch.no_grad():
        xyz = truth.points(q, tool)
    data = Measurements.from_tensors(q, tool, xyz)
    out = export_urdf(truth, tmp_path / "cal.urdf", constants="c0")
    cmp = compare_urdf(truth, out, data)
    assert cmp.full.max < 1e-9  # the truth model reproduces its own points
    assert cmp.nominal.mean > cmp.urdf.mean > cmp.full.mean
    # URDF-only residuals are those of the model with orders >= 1 zeroed (independent route)
    ref = RobotModel(fanuc, tools_m, orders=3)
    ref.load_state_dict(truth.state_dict())
    with torch.no_grad():
        ref.joint_errors.coef[..., 1:] = 0.0
        expected = (ref.points(q, tool) - xyz).norm(dim=1) * 1e3
    assert torch.allclose(cmp.residuals_mm["urdf"], expected, atol=1e-9)
    rows = {r["label"]: r for r in cmp.table()}
    assert rows["Nominal"]["mean_decrease"] is None and rows["Full model"]["mean_decrease"] > 99
    m = urdf_only_model(truth, out)
    assert m.joint_errors.coef.abs().max() == 0 and torch.equal(m.tools(), truth.tools())
    # the default, constants fitted to the whole model, does better than c0 on these points
    fitted = compare_urdf(truth, export_urdf(truth, tmp_path / "fit.urdf", count=128), data)
    assert fitted.urdf.mean < cmp.urdf.mean and fitted.full.max < 1e-9
