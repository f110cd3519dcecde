"""Outputs are whole or absent, never over an input, over an earlier result only with --force (torchcal.io.atomic)."""

import os
import stat

import pandas as pd
import pytest
import torch
from typer.testing import CliRunner

from conftest import XYZCB_TOOLS, random_commands
from torchcal.cli import app
from torchcal.io.atomic import OutputExistsError, WriteError, atomic_path, atomic_write_text, check_output
from torchcal.io.rundir import PARTIAL_FILE, load_model, run_log, save_model
from torchcal.models.machine import MachineModel
from torchcal.models.sensor_rig import SensorRig
from torchcal.models.robot import RobotModel

runner = CliRunner()


def invoke(*args):
    return runner.invoke(app, [str(a) for a in args])


def _error_line(r) -> str:
    lines = [line for line in r.output.strip().splitlines() if line.strip()]
    assert len(lines) == 1 and "Traceback" not in r.output, r.output
    return lines[0]


@pytest.fixture
def robot_run(tmp_path, fanuc, tools_m):
    """A run directory holding a (nominal) robot model and a commands CSV with measured x, y, z."""
    run = tmp_path / "run"
    run.mkdir()
    save_model(run, RobotModel(fanuc, tools_m, orders=1))
    q = torch.rad2deg(random_commands(fanuc, 5, 3)).numpy()
    df = pd.DataFrame(q, columns=[f"q{i}" for i in range(1, 7)])
    df.insert(0, "tool", 0)
    df.insert(0, "pose", range(5))
    df["x"], df["y"], df["z"] = 1.0, 2.0, 3.0
    df.to_csv(tmp_path / "in.csv", index=False)
    return run, tmp_path / "in.csv"


def _read_only(folder):
    """chmod a folder read-only; skip where that does not stop writes (root)."""
    folder.chmod(stat.S_IRUSR | stat.S_IXUSR)
    if os.access(folder, os.W_OK):
        folder.chmod(stat.S_IRWXU)
        pytest.skip("chmod does not make folders read-only here (running as root)")


# ------------------------------------------------------------------ the helper
def test_a_failed_write_leaves_the_earlier_file_and_no_temporary(tmp_path):
    path = atomic_write_text(tmp_path / "result.csv", "complete,earlier\n")
    with pytest.raises(WriteError, match=r"result\.csv: not written \(RuntimeError: basic_ios::clear"):
        with atomic_path(path) as tmp:
            tmp.write_text("cut mid-r")  # what a full disk or a crash leaves
            raise RuntimeError("basic_ios::clear: iostream error")
    assert path.read_text() == "complete,earlier\n"
    assert os.listdir(tmp_path) == ["result.csv"]
    with pytest.raises(KeyboardInterrupt):  # Ctrl-C mid-write: same, and still an interrupt
        with atomic_path(path) as tmp:
            tmp.write_text("cut")
            raise KeyboardInterrupt
    assert path.read_text() == "complete,earlier\n" and os.listdir(tmp_path) == ["result.csv"]


def test_save_model_on_a_full_disk_leaves_no_truncated_model(tmp_path, fanuc, tools_m, monkeypatch):
    def full_disk(obj, f, *args, **kwargs):
        f.write(b"PK\x03\x04truncated")  # save_model hands torch.save an open file
        raise RuntimeError("[enforce fail at inline_container.cc:626] . unexpected pos 64 vs 0")

    monkeypatch.setattr(torch, "save", full_disk)
    with pytest.raises(WriteError, match="model.pt: not written"):
        save_model(tmp_path, RobotModel(fanuc, tools_m, orders=1))
    assert os.listdir(tmp_path) == []


def test_check_output_compares_resolved_paths(tmp_path, monkeypatch):
    (tmp_path / "a.csv").write_text("x\n")
    monkeypatch.chdir(tmp_path)
    with pytest.raises(OutputExistsError, match="is also the input"):
        check_output(tmp_path / "sub" / ".." / "a.csv", force=True, inputs=["a.csv"])
    (tmp_path / "link.csv").symlink_to(tmp_path / "a.csv")
    with pytest.raises(OutputExistsError, match="is also the input"):
        check_output("link.csv", force=True, inputs=[tmp_path / "a.csv"])


def test_run_log_marks_a_failed_run_partial(tmp_path):
    with run_log(tmp_path):
        assert (tmp_path / PARTIAL_FILE).is_file()  # a killed process leaves it too
    assert not (tmp_path / PARTIAL_FILE).exists()
    with pytest.raises(ZeroDivisionError) as err:
        with run_log(tmp_path):
            1 / 0
    assert (tmp_path / PARTIAL_FILE).is_file() and err.value.run_dir == tmp_path


# ----------------------------------------------------------- predict / compensate
@pytest.mark.parametrize("command", ["predict", "compensate"])
def test_output_equal_to_input_is_refused(robot_run, command):
    run, src = robot_run
    before = src.read_text()
    # the same file spelled differently, --force or not: the measured data would be lost
    for spelled in (src, src.parent / "." / src.name):
        r = invoke(command, run, src, spelled, "--force")
        assert r.exit_code == 2
        assert "is also the input" in _error_line(r) and str(src) in r.output
    assert src.read_text() == before


def test_predict_replaces_an_existing_output_only_with_force(robot_run, tmp_path):
    run, src = robot_run
    out = tmp_path / "pred.csv"
    out.write_text("earlier result\n")
    r = invoke("predict", run, src, out)
    assert r.exit_code == 2
    line = _error_line(r)
    assert str(out) in line and "already exists" in line and "--force" in line
    assert out.read_text() == "earlier result\n"
    r = invoke("predict", run, src, out, "--force")
    assert r.exit_code == 0, r.output
    assert len(pd.read_csv(out)) == 5
    assert sorted(os.listdir(tmp_path)) == ["in.csv", "pred.csv", "pred.csv.provenance.json", "run"]


def test_predict_into_a_read_only_folder_is_one_line(robot_run, tmp_path):
    run, src = robot_run
    folder = tmp_path / "ro"
    folder.mkdir()
    _read_only(folder)
    try:
        r = invoke("predict", run, src, folder / "pred.csv")
    finally:
        folder.chmod(stat.S_IRWXU)
    assert r.exit_code == 2
    line = _error_line(r)
    assert str(folder / "pred.csv") in line and "Permission denied" in line
    assert os.listdir(folder) == []


def test_a_read_only_filesystem_is_one_line(robot_run, tmp_path, monkeypatch):
    """EROFS (a read-only mount; chmod cannot make one for root): the path and the OS reason, no file left."""
    import errno

    from torchcal.io import atomic

    real_open = os.open

    def read_only(path, flags, *args):
        if flags & os.O_CREAT:
            raise OSError(errno.EROFS, os.strerror(errno.EROFS), str(path))
        return real_open(path, flags, *args)

    run, src = robot_run
    monkeypatch.setattr(atomic.os, "open", read_only)
    r = invoke("predict", run, src, tmp_path / "pred.csv")
    assert r.exit_code == 2
    assert _error_line(r) == f"error: {tmp_path / 'pred.csv'}: not written (Read-only file system)"
    assert sorted(os.listdir(tmp_path)) == ["in.csv", "run"]


@pytest.mark.parametrize("option, value", [("--max-correction-deg", "-1"), ("--max-correction-deg", "nan"),
                                           ("--tol-deg", "0")])
def test_compensate_rejects_bad_bounds_in_degrees(robot_run, tmp_path, option, value):
    run, src = robot_run
    r = invoke("compensate", run, src, tmp_path / "c.csv", option, value)
    assert r.exit_code == 2
    assert f"{option} {float(value):g}: must be a positive number of degrees" in _error_line(r)
    assert not (tmp_path / "c.csv").exists()


@pytest.mark.parametrize("kind", ["machine", "sensor"])
def test_compensate_refuses_machine_and_sensor_runs(tmp_path, fanuc, machine, kind):
    run = tmp_path / "run"
    run.mkdir()
    if kind == "machine":
        save_model(run, MachineModel(machine, XYZCB_TOOLS.double(), orders=1))
        cols, n, hint = ["tool", "q1", "q2", "q3", "q4", "q5"], 5, "export-tables"
    else:
        save_model(run, SensorRig.for_robot(fanuc, orders=1))
        cols, n, hint = ["tool", *[f"q{i}" for i in range(1, 7)]], 6, "it predicts sensor poses (torchcal predict)"
    pd.DataFrame([[0] + [0.0] * n], columns=cols).to_csv(tmp_path / "in.csv", index=False)
    r = invoke("compensate", run, tmp_path / "in.csv", tmp_path / "c.csv")
    assert r.exit_code == 2
    line = _error_line(r)
    assert "cannot compensate commands" in line and hint in line
    assert not (tmp_path / "c.csv").exists()


# ---------------------------------------------------------------- export-tables
def test_export_tables_linuxcnc_over_existing_outputs(tmp_path, machine):
    run = tmp_path / "run"
    run.mkdir()
    save_model(run, MachineModel(machine, XYZCB_TOOLS.double(), orders=1))
    assert load_model(run).axis_errors is not None
    taken = tmp_path / "taken.txt"
    taken.write_text("keep me\n")
    r = invoke("export-tables", run, taken, "--format", "linuxcnc")
    assert r.exit_code == 2
    assert str(taken) in _error_line(r) and "already exists" in r.output
    assert taken.read_text() == "keep me\n"
    comp = tmp_path / "comp"
    assert invoke("export-tables", run, comp, "--format", "linuxcnc").exit_code == 0
    ini = (comp / "linuxcnc_comp.ini").read_text()
    r = invoke("export-tables", run, comp, "--format", "linuxcnc")
    assert r.exit_code == 2
    line = _error_line(r)
    assert f"{comp}: already holds B.comp, C.comp" in line and "--force" in line
    r = invoke("export-tables", run, comp, "--format", "linuxcnc", "--force")
    assert r.exit_code == 0, r.output
    assert (comp / "linuxcnc_comp.ini").read_text() == ini
    assert not [p for p in os.listdir(comp) if p.startswith(".")]  # no temporaries left


# ------------------------------------------------------------------- plan-poses
def test_plan_poses_count_is_bounded_up_front(tmp_path):
    r = invoke("plan-poses", "fanuc_lrmate200i", 100000000000, tmp_path / "p.csv")
    assert r.exit_code == 2
    assert "COUNT 100000000000: plan between 1 and 100000 poses" in _error_line(r)
    out = tmp_path / "p.csv"
    out.write_text("earlier plan\n")
    r = invoke("plan-poses", "fanuc_lrmate200i", 20, out)
    assert r.exit_code == 2 and "--force" in _error_line(r) and out.read_text() == "earlier plan\n"
