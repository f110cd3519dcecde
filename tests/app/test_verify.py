"""torchcal verify: a run's model judged on new measurements, with the tracker moved or not (known truths)."""

import math

import numpy as np
import pandas as pd
import pytest
import torch
from typer.testing import CliRunner

from tests.conftest import random_commands, randomize
from torchcal.cli import app
from torchcal.core.measurements import Measurements
from torchcal.io.rundir import save_model
from torchcal.kinematics.transforms import homogeneous, rpy_to_matrix
from torchcal.models.robot import RobotModel

MOVE = homogeneous(rpy_to_matrix(torch.tensor([0.3, -0.2, 2.1], dtype=torch.float64)),
                   torch.tensor([2.5, -1.0, 0.4], dtype=torch.float64))  # a new tracker placement, m


def _write_points(path, q, tool, xyz):
    df = pd.DataFrame({"pose": np.arange(len(q)) + 1, "tool": tool.numpy()})
    for j in range(q.shape[1]):
        df[f"q{j + 1}"] = np.degrees(q[:, j].numpy())
    for i, c in enumerate("xyz"):
        df[c] = xyz[:, i].numpy() * 1000.0
    df.to_csv(path, index=False)
    return path


@pytest.fixture(scope="module")
def point_run(fanuc, tools_m, tmp_path_factory):
    root = tmp_path_factory.mktemp("verify")
    model = randomize(RobotModel(fanuc, tools_m, orders=2, backlash=False), 4)
    save_model(root / "run", model)
    q = random_commands(fanuc, 40, 6).repeat_interleave(3, 0)
    tool = torch.arange(120) % 3
    with torch.no_grad():
        xyz = model.points(q, tool)
    return root, model, q, tool, xyz


def test_the_runs_own_robot_verifies_to_zero_and_the_nominal_does_not(point_run):
    root, model, q, tool, xyz = point_run
    path = _write_points(root / "same.csv", q, tool, xyz)
    r = CliRunner().invoke(app, ["verify", str(root / "run"), str(path), "--out", str(root / "same_rows.csv")])
    assert r.exit_code == 0, r.output
    rows = pd.read_csv(root / "same_rows.csv")
    assert len(rows) == 120 and rows.modeled_mm.max() < 1e-6  # the file's digits
    with torch.no_grad():
        nominal = (model.nominal_points(q, tool) - xyz).norm(dim=-1) * 1000.0
    assert np.allclose(rows.nominal_mm.to_numpy(), nominal.numpy(), atol=1e-6)
    assert "Verification" in r.output and "moved" not in r.output and "tracker stand elsewhere" not in r.output


def test_a_moved_tracker_is_found_and_taken_out(point_run):
    """Measurements seen from a tracker moved by MOVE: without --new-frame the model misses by metres; with it the
    residual is the file's rounding and the reported motion is MOVE's at the robot base."""
    root, model, q, tool, xyz = point_run
    moved = xyz @ MOVE[:3, :3].T + MOVE[:3, 3]
    path = _write_points(root / "moved.csv", q, tool, moved)
    runner = CliRunner()
    r = runner.invoke(app, ["verify", str(root / "run"), str(path), "--out", str(root / "rows.csv")])
    assert r.exit_code == 0, r.output
    assert pd.read_csv(root / "rows.csv").modeled_mm.min() > 100.0
    said = " ".join(r.output.split())
    assert "once its predictions are moved by one rigid motion: did the tracker stand elsewhere? --new-frame" in said
    r = runner.invoke(app, ["verify", str(root / "run"), str(path), "--new-frame", "--out", str(root / "rows2.csv"),
                            "--units-checked"])
    assert r.exit_code == 0, r.output
    rows = pd.read_csv(root / "rows2.csv")
    assert rows.modeled_mm.max() < 1e-6
    with torch.no_grad():
        o = model.base()[:3, 3]
    moved_mm = float((MOVE[:3, :3] @ o + MOVE[:3, 3] - o).norm()) * 1000.0
    turned = math.degrees(math.acos((float(MOVE[:3, :3].trace()) - 1.0) / 2.0))
    line = [ln for ln in r.output.splitlines() if ln.startswith("measurement frame re-estimated")][0]
    assert f"moved {moved_mm:.3f} mm" in line and f"turned {turned:.4f} deg" in line
    # the nominal robot gets its own best frame: its residual is its shape error, not the tracker's move
    with torch.no_grad():
        assert rows.nominal_mm.mean() < 10.0


def test_verify_refuses_a_file_outside_the_contract(point_run):
    root, *_ = point_run
    (root / "bad.csv").write_text("pose,tool,q1,q2,q3,q4,q5,q6,x,y,z\n1,0,0,0,0,0,0,0,abc,0,0\n")
    r = CliRunner().invoke(app, ["verify", str(root / "run"), str(root / "bad.csv")])
    assert r.exit_code == 2 and "bad.csv" in r.output and "row 1" in r.output and "x" in r.output


def test_a_sensor_run_verifies_position_and_angle(fanuc, tmp_path):
    from torchcal.io.sensor_csv import write_pose_measurements
    from torchcal.models.sensor_rig import SensorRig

    rig = SensorRig.for_robot(fanuc, orders=1)
    randomize(rig.model, 8)
    save_model(tmp_path / "run", rig)
    q = random_commands(fanuc, 30, 2)
    with torch.no_grad():
        T = MOVE @ rig.sensor_pose(q)
    data = Measurements(q, torch.zeros(30, dtype=torch.long), T[:, :3, 3], torch.zeros_like(q),
                        torch.arange(1, 31), torch.arange(1, 31), False, "sim", {"rotation": T[:, :3, :3]})
    write_pose_measurements(tmp_path / "poses.csv", data, fanuc)
    r = CliRunner().invoke(app, ["verify", str(tmp_path / "run"), str(tmp_path / "poses.csv"), "--new-frame",
                                 "--out", str(tmp_path / "rows.csv")])
    assert r.exit_code == 0, r.output
    rows = pd.read_csv(tmp_path / "rows.csv")
    assert rows.modeled_mm.max() < 1e-6 and rows.modeled_deg.max() < 1e-6
    assert rows.nominal_deg.mean() > 1e-3  # the nominal chain's orientation error is seen
    # the same poses exported in metres: refused as the sensor fit and update refuse them
    data.xyz = data.xyz / 1000.0
    write_pose_measurements(tmp_path / "poses_m.csv", data, fanuc)
    r = CliRunner().invoke(app, ["verify", str(tmp_path / "run"), str(tmp_path / "poses_m.csv"), "--new-frame"])
    assert r.exit_code == 2 and "poses_m.csv: columns x, y, z" in r.output and "metres" in r.output, r.output
