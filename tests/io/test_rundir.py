"""Run directories: placement, model persistence, strict JSON, versions, the log."""

import json
import logging
from pathlib import Path

import pytest
import torch

from conftest import random_commands, randomize
from torchcal.io.rundir import (RunDirError, collect_versions, load_model, make_run_dir, run_log, save_model,
                                write_json)
from torchcal.models.robot import RobotModel


def test_run_dir_placement(tmp_path):
    out = tmp_path / "runs"
    assert make_run_dir(out) == out  # absent -> itself
    (tmp_path / "empty").mkdir()
    assert make_run_dir(tmp_path / "empty") == tmp_path / "empty"  # empty -> itself
    (out / "model.pt").write_text("earlier run")
    a, b = make_run_dir(out), make_run_dir(out)
    # out holds a run: the next runs go beside it, never inside it, never into one another
    assert a == tmp_path / "runs-2" and a.is_dir() and not any(a.iterdir())
    (a / "config.yaml").write_text("second run")
    assert make_run_dir(out) == tmp_path / "runs-3"
    assert b == a  # an empty folder left by a run that never started is reused
    assert sorted(p.name for p in out.iterdir()) == ["model.pt"]
    assert (out / "model.pt").read_text() == "earlier run"
    # a folder of earlier runs (not a run itself): a fresh timestamped folder inside it
    many = tmp_path / "many"
    (many / "old").mkdir(parents=True)
    c, d = make_run_dir(many), make_run_dir(many)
    assert c.parent == many and d.parent == many and c != d and c.name != "old"
    (tmp_path / "file").write_text("x")
    with pytest.raises(RunDirError, match="not a folder"):
        make_run_dir(tmp_path / "file")


def test_second_fit_goes_beside_the_first(tmp_path):
    """A run writes config.yaml first; the next make_run_dir(out) must not nest into it."""
    out = tmp_path / "out"
    first = make_run_dir(out)
    (first / "config.yaml").write_text("robot: x")
    (first / "plots").mkdir()
    second = make_run_dir(out)
    assert second.parent == tmp_path and second != first
    assert not second.is_relative_to(first)


def test_model_round_trip(tmp_path, fanuc, tools_m):
    model = randomize(RobotModel(fanuc, tools_m, orders=[1, 2, 0, 3, 1, 2], backlash=True), seed=4)
    save_model(tmp_path, model, orders=[1, 2, 0, 3, 1, 2])
    back = load_model(tmp_path)
    assert back.spec() == model.spec()
    q = random_commands(fanuc, 25, 1)
    tool = torch.arange(25) % 3
    s = torch.where(torch.rand(25, 6, generator=torch.Generator().manual_seed(2)) > 0.5, 1.0, -1.0)
    with torch.no_grad():
        assert torch.equal(back.points(q, tool, s), model.points(q, tool, s))
        assert torch.equal(back.flange(q, s, base=False), model.flange(q, s, base=False))
    # the loaded values are not the all-zero defaults of from_spec
    assert back.joint_errors.coef.abs().max() > 0
    assert torch.equal(load_model(tmp_path / "model.pt").base.twist, model.base.twist)
    # the same model saved again is the same bytes (a deliverable's hash must not change when nothing did)
    first = (tmp_path / "model.pt").read_bytes()
    save_model(tmp_path / "again", model, orders=[1, 2, 0, 3, 1, 2])
    assert (tmp_path / "again" / "model.pt").read_bytes() == first


def test_load_model_errors(tmp_path):
    with pytest.raises(RunDirError, match="no model here"):
        load_model(tmp_path)
    (tmp_path / "model.pt").write_bytes(b"not a torch file")
    with pytest.raises(RunDirError, match="not a readable torchcal model"):
        load_model(tmp_path)


def test_json_is_strict_and_versions_complete(tmp_path):
    p = write_json(tmp_path / "m.json", {"a": float("nan"), "b": torch.tensor([1.5, 2.0]), "c": [float("inf"), 1]})
    assert json.loads(p.read_text()) == {"a": None, "b": [1.5, 2.0], "c": [None, 1]}
    v = collect_versions("cpu")
    for key in ("python", "platform", "torchcal", "torch", "numpy", "scipy", "pytorch_kinematics", "yourdfpy", "git", "device"):
        assert key in v
    assert v["torch"] == torch.__version__ and v["device"] == "cpu"
    from importlib import metadata

    assert v["numba"] == metadata.version("numba")  # the compiled kernels' version is part of what produced a run


def test_versions_record_what_changes_the_bits(monkeypatch, tmp_path):
    """Threads, the environment choosing them, the command line, and which source ran (the version string is the
    same for every commit, and a plain install has no git checkout)."""
    import hashlib
    import sys

    import torchcal

    monkeypatch.setenv("OMP_NUM_THREADS", "1")
    monkeypatch.delenv("MKL_NUM_THREADS", raising=False)
    monkeypatch.setattr(sys, "argv", ["torchcal", "fit", "my config.yaml", "seed=3"])
    v = collect_versions("cpu")
    assert v["environment"]["OMP_NUM_THREADS"] == "1" and "MKL_NUM_THREADS" not in v["environment"]
    assert v["command"] == "torchcal fit 'my config.yaml' seed=3"
    assert v["torch_threads"] == torch.get_num_threads() and v["cpus_available"] >= 1
    # the source hash, recomputed independently over the package's files
    root = Path(torchcal.__file__).resolve().parent
    h = hashlib.sha256()
    for p in sorted(root.rglob("*.py")):
        h.update(p.relative_to(root).as_posix().encode() + p.read_bytes())
    assert v["torchcal_source_sha256"] == h.hexdigest() and v["torchcal_source"] == str(root)


def test_run_log_records_failures(tmp_path):
    with pytest.raises(ZeroDivisionError):
        with run_log(tmp_path) as log:
            log.info("step one")
            1 / 0
    text = (tmp_path / "run.log").read_text()
    assert "step one" in text and "run failed" in text and "ZeroDivisionError" in text
    assert not any(isinstance(h, logging.FileHandler) for h in logging.getLogger("torchcal").handlers)


def test_a_fleet_run_given_for_a_model_names_a_unit_folder(tmp_path):
    """predict / compensate / verify given a fleet run: the model is per unit; the message names one's folder."""
    from torchcal.io.rundir import RunDirError, load_model

    (tmp_path / "fleet" / "units" / "unit07").mkdir(parents=True)
    (tmp_path / "fleet" / "summary.csv").write_text("unit,status\nunit07,fitted\n")
    with pytest.raises(RunDirError, match=r"is a fleet run; give one unit's folder, e.g. .*units/unit07"):
        load_model(tmp_path / "fleet")
