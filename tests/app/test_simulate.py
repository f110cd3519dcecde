"""torchcal.sim.simulate_dataset: what `torchcal simulate` writes, as a library function."""

import json

import pytest
import torch

from conftest import PAPER2_TOOLS_MM
from torchcal.app.config import ConfigError
from torchcal.io.csv import read_measurements
from torchcal.io.truth import load_truth, truth_noise
from torchcal.app.simulate import default_joint_variances, simulate_dataset
from torchcal.sim import TruthRobot
from torchcal.app.simulate import PAPER2_TOOLS_MM as DATASET_TOOLS_MM


def test_writes_the_data_set_and_records_the_error_variable(fanuc, tmp_path):
    paths = simulate_dataset(tmp_path / "sim", identification=12, validation=6, seed=3)
    assert set(paths) == {"identification", "validation", "truth", "config"}
    assert all(p.is_file() for p in paths.values())
    assert len(read_measurements(paths["identification"], fanuc, 3)) == 36  # each pose with the 3 tools
    assert len(read_measurements(paths["validation"], fanuc, 3)) == 6
    blob = json.loads(paths["truth"].read_text())
    assert blob["kind"] == "fanuc_paper2" and blob["error_variable"] == ["command"] * 6
    truth = load_truth(paths["truth"])
    fresh = TruthRobot.fanuc_paper2(fanuc, torch.tensor(PAPER2_TOOLS_MM) * 1e-3, 3)
    q = torch.zeros(4, 6)
    tool = torch.arange(4) % 3
    assert truth.error_variable == ["command"] * 6
    assert torch.allclose(truth.points(q, tool), fresh.points(q, tool), atol=1e-15)
    assert truth_noise(paths["truth"]) is not None
    assert DATASET_TOOLS_MM == PAPER2_TOOLS_MM
    assert "errors follow: command" in paths["config"].read_text()


def test_joint_truth_and_bad_options(fanuc, tmp_path):
    paths = simulate_dataset(tmp_path / "j", identification=5, validation=0, seed=1, error_variable="joint")
    assert "validation" not in paths
    assert load_truth(paths["truth"]).error_variable == ["joint"] * 6
    with pytest.raises(ConfigError, match="already holds"):
        simulate_dataset(tmp_path / "j", identification=5, validation=0)
    with pytest.raises(ConfigError, match="error-variable"):
        simulate_dataset(tmp_path / "x", identification=5, error_variable="urdf")
    with pytest.raises(ConfigError, match="validation-tool"):
        simulate_dataset(tmp_path / "y", identification=5, validation_tool=3)
    fwd, bwd = default_joint_variances(6)
    assert len(fwd) == len(bwd) == 6 and default_joint_variances(3)[0] == [sorted(fwd)[3]] * 3


def test_a_robot_is_simulated_with_its_own_repeatability(tmp_path):
    """The simulated joints repeat as the robot's YAML declares (the ABB's own 1.16e-7 deg², not the FANUC's
    Table 5), and fit.yaml states those variances; a robot without one gets the documented defaults."""
    import yaml

    import torchcal
    from torchcal.core import units

    abb = torchcal.load_robot("abb_irb120")
    paths = simulate_dataset(tmp_path / "abb", robot="abb_irb120", identification=12, validation=0, order=1)
    noise = yaml.safe_load(paths["config"].read_text())["noise"]
    scale2 = units.joint_scale(abb.joint_map.prismatic) ** 2
    assert noise["joint_var_fwd"] == pytest.approx((abb.repeatability.var_fwd / scale2).tolist(), rel=1e-10)
    assert noise["joint_var_bwd"] == pytest.approx((abb.repeatability.var_bwd / scale2).tolist(), rel=1e-10)
    assert noise["joint_var_fwd"] != default_joint_variances(6)[0]
    truth = truth_noise(paths["truth"])
    assert torch.allclose(truth.joint_var_fwd, abb.repeatability.var_fwd, rtol=1e-10)


def test_an_interrupted_overwrite_leaves_no_mixed_set(tmp_path, monkeypatch):
    """--force over an earlier set, interrupted while writing: the folder must not hold a fit.yaml that pairs the
    new identification file with the old validation file and truth (a fit of it reported 2 mm for 0.05)."""
    import torchcal.io.csv as csv

    simulate_dataset(tmp_path / "sim", identification=8, validation=4, seed=0)
    real = csv.write_measurements
    calls = []

    def interrupted_on_second(path, *args, **kwargs):
        calls.append(path)
        if len(calls) == 2:  # the validation file: Ctrl-C
            raise KeyboardInterrupt
        return real(path, *args, **kwargs)

    monkeypatch.setattr(csv, "write_measurements", interrupted_on_second)
    with pytest.raises(KeyboardInterrupt):
        simulate_dataset(tmp_path / "sim", identification=8, validation=4, seed=7, force=True)
    left = sorted(p.name for p in (tmp_path / "sim").iterdir())
    assert left == ["identification.csv"]  # the new one alone: incomplete, and `torchcal fit` has nothing to start
    monkeypatch.setattr(csv, "write_measurements", real)
    paths = simulate_dataset(tmp_path / "sim", identification=8, validation=4, seed=7, force=True)
    assert json.loads(paths["truth"].read_text())["seed"] == 7


def test_a_robot_without_repeatability_is_simulated_with_a_stand_in_that_is_said(tmp_path, caplog):
    """No silent fallback to another robot's numbers: the stand-in is warned and written into fit.yaml."""
    from torchcal.app.simulate import simulate_dataset
    from torchcal.kinematics.robot import urdf_dir

    with caplog.at_level("WARNING", logger="torchcal"):
        paths = simulate_dataset(tmp_path / "bare", str(urdf_dir() / "abb_irb120.urdf"), 12, 4)
    assert "declares no repeatability" in caplog.text and "FANUC Table 5" in caplog.text
    assert "not this robot's" in paths["config"].read_text()
    caplog.clear()
    with caplog.at_level("WARNING", logger="torchcal"):
        paths = simulate_dataset(tmp_path / "own", "ur10", 12, 4)  # its YAML declares one: nothing to say
    assert "declares no repeatability" not in caplog.text and "not this robot's" not in paths["config"].read_text()


def test_the_bundled_machine_is_simulated_as_paper_ones_and_fits_as_a_machine(tmp_path):
    """simulate -> fit -> tables for a machine builder: the XYZCB gets Paper I's machine and an axis perturbation
    config (no robot tools, no backlash, no truth.json), which fits as written."""
    from torchcal.app.config import load_config
    from torchcal.app.fit import run_fit

    paths = simulate_dataset(tmp_path / "m", "five_axis_xyzcb", 60, 20, order=2)
    assert "truth" not in paths and {"identification", "validation", "config"} <= set(paths)
    cfg = load_config(paths["config"])
    assert cfg.model.kind == "axis_perturbation" and [t[2] for t in cfg.tools] == [402.9, 500.9]
    res = run_fit(load_config(paths["config"], ["plots=false", "report=false", f"out={tmp_path / 'run'}"]))
    assert res.metrics["table6"][3]["mean"] < 0.3 * res.metrics["table6"][2]["mean"]  # validation: modeled vs nominal
    with pytest.raises(ConfigError, match="--pose-order sequence: robot options"):
        simulate_dataset(tmp_path / "m2", "five_axis_xyzcb", 60, 20, pose_order="sequence")
