"""Inputs that used to pass silently or fail vaguely: unit slips, stale or foreign update data, transposed
rotations, duplicate YAML keys, capped table sizes, simulate's order, tab-separated files, folders given as
files, truncated URDFs, unit / joint-type mismatches, a local folder named like a bundled robot."""

import math
import shutil

import numpy as np
import pandas as pd
import pytest
import torch
from scipy.spatial.transform import Rotation
from typer.testing import CliRunner

from torchcal.cli import app
from torchcal.io.csv import DataError, read_measurements
from torchcal.kinematics import load_robot
from torchcal.kinematics.urdf import URDFError, load_urdf
from torchcal.core.measurements import Measurements

runner = CliRunner()
POSES = 20

pytestmark = pytest.mark.usefixtures("one_thread")


class _Result:
    """exit_code and output with rich's line wrapping undone (messages are one line; the console wraps them)."""

    def __init__(self, r):
        self.exit_code, self.output = r.exit_code, " ".join(r.output.split())


def invoke(*args):
    return _Result(runner.invoke(app, [str(a) for a in args]))


@pytest.fixture(scope="module")
def fitted(tmp_path_factory, one_thread):
    root = tmp_path_factory.mktemp("checks")
    sim = root / "sim"
    r = invoke("simulate", sim, "--identification", POSES, "--validation", 10, "--seed", 5)
    assert r.exit_code == 0, r.output
    r = invoke("fit", sim / "fit.yaml", "model.order=1", "plots=false", "data.truth=null", f"out={root / 'run'}", "-q")
    assert r.exit_code == 0, r.output
    return {"root": root, "sim": sim, "run": root / "run"}


def _radians(src, dst):
    df = pd.read_csv(src)
    for c in [f"q{i}" for i in range(1, 7)]:
        df[c] = np.radians(df[c])
    df.to_csv(dst, index=False)
    return dst


# ------------------------------------------------------------------------- 1. joints in radians
def test_radian_joints_refused_by_predict_and_compensate_warned_by_fit(fitted, tmp_path):
    sim, run = fitted["sim"], fitted["run"]
    rad = _radians(sim / "validation.csv", tmp_path / "rad.csv")
    for cmd in ("predict", "compensate"):
        r = invoke(cmd, run, rad, tmp_path / f"{cmd}.csv")
        assert r.exit_code == 2, r.output
        assert "rad.csv" in r.output and "q1" in r.output and "radians" in r.output and "--units-checked" in r.output
        assert not (tmp_path / f"{cmd}.csv").exists()
        r = invoke(cmd, run, rad, tmp_path / f"{cmd}.csv", "--units-checked")
        assert r.exit_code == 0, r.output
    # degrees pass untouched
    assert invoke("predict", run, sim / "validation.csv", tmp_path / "ok.csv").exit_code == 0
    # fit: the points decide. They fit the joints read as radians: refused, naming the file, before any run starts
    ident = _radians(sim / "identification.csv", tmp_path / "ident_rad.csv")
    args = ("fit", sim / "fit.yaml", "model.order=1", "plots=false", "data.truth=null", "data.validation=null",
            f"data.identification={ident}", f"out={tmp_path / 'run'}")
    r = invoke(*args)
    assert r.exit_code == 2 and "ident_rad.csv: columns q1..q6: the joints are radians" in r.output, r.output
    assert not (tmp_path / "run").exists()
    r = invoke(*args, "--units-checked")  # the user's word: fitted as degrees (poorly)
    assert r.exit_code == 0, r.output


def test_joints_that_only_look_like_radians_are_warned_not_refused(fanuc):
    """Near-home commands in degrees (every joint within +-6 deg) look like radians; their points fit degrees, so
    the check must not refuse them. The same points with the commands rewritten in radians are refused."""
    from tests.conftest import fanuc_dh_reference
    from torchcal.io.unit_checks import UnitsError, check_radians, degrees_confirmed, radian_columns

    g = np.random.default_rng(3)
    q_deg = g.uniform(-6.0, 6.0, (40, 6))  # every joint within the radian bound
    F = fanuc_dh_reference(q_deg)  # an independent forward model: the points of degrees
    tool = np.array([0.0, 0.0, 0.1])
    xyz = F[:, :3, 3] + F[:, :3, :3] @ tool
    R = len(q_deg)

    def data(q_file):
        return Measurements(q=torch.tensor(np.radians(q_file)), tool=torch.zeros(R, dtype=torch.long),
                            xyz=torch.tensor(xyz), direction=torch.zeros(R, 6), pose=torch.arange(R),
                            rows=torch.arange(1, R + 1), source="near_home.csv")

    tools = torch.tensor(tool[None])
    d = data(q_deg)
    assert radian_columns(d.q, fanuc)  # it looks like radians ...
    assert degrees_confirmed(check_radians(d, fanuc, tools))  # ... but the points say degrees: only a warning
    with pytest.raises(UnitsError, match="near_home.csv: columns q1..q6: the joints are radians"):
        check_radians(data(np.radians(q_deg)), fanuc, tools)  # the same poses written in radians


def test_import_tracker_warns_on_radian_joints(tmp_path, fanuc):
    from torchcal.models.robot import RobotModel
    from tests.conftest import random_commands

    q = random_commands(fanuc, 15, 3)
    model = RobotModel(fanuc, torch.tensor([[0.0, 0.0, 0.1]]), orders=1)
    with torch.no_grad():
        pts = model.nominal_points(q, torch.zeros(15, dtype=torch.long)).numpy() * 1e3
    np.savetxt(tmp_path / "joints.txt", q.numpy())  # radians where degrees belong
    np.savetxt(tmp_path / "smr.txt", pts)
    r = invoke("import-tracker", tmp_path / "m.csv", "--joints", tmp_path / "joints.txt", "--target",
               tmp_path / "smr.txt", "--robot", "fanuc_lrmate200i")
    assert r.exit_code == 0, r.output
    assert "warning:" in r.output and "joints.txt: joint columns q1" in r.output and "radians" in r.output


# ------------------------------------------------------------------------- 2. points in metres
def test_fit_refuses_points_in_metres(fitted, tmp_path):
    sim = fitted["sim"]
    df = pd.read_csv(sim / "identification.csv")
    df[["x", "y", "z"]] = df[["x", "y", "z"]] / 1000.0
    df.to_csv(tmp_path / "m.csv", index=False)
    args = ("fit", sim / "fit.yaml", "model.order=1", "plots=false", "data.truth=null", "data.validation=null",
            f"data.identification={tmp_path / 'm.csv'}", f"out={tmp_path / 'run'}", "-q")
    r = invoke(*args)
    assert r.exit_code == 2, r.output
    assert "m.csv" in r.output and "x, y, z" in r.output and "metres" in r.output and "~1e+03" in r.output
    assert not (tmp_path / "run").exists()
    # the override lets it through (to whatever the fit makes of it)
    r = invoke(*args, "data.units_checked=true")
    assert r.exit_code == 0 and "convert them, or pass" not in " ".join(r.output.split())
    # the implausible nominal residual still names the scale the points suggest
    assert "they look like metres" in " ".join(r.output.split())


@pytest.mark.parametrize("divisor, unit", [(10.0, "centimetres"), (25.4, "inches")])
def test_fit_names_points_in_centimetres_or_inches(fitted, tmp_path, divisor, unit):
    """The distance ratio (0.1, 0.039) is inside the refusal's (0.02, 50) bounds: the fit 'calibrated' a robot ten
    times too small, 677 mm nominal to 0.019 mm modeled, saying only that the description may not be the robot."""
    sim = fitted["sim"]
    df = pd.read_csv(sim / "identification.csv")
    df[["x", "y", "z"]] = df[["x", "y", "z"]] / divisor
    df.to_csv(tmp_path / "c.csv", index=False)
    r = invoke("fit", sim / "fit.yaml", "model.order=1", "plots=false", "data.truth=null", "data.validation=null",
               f"data.identification={tmp_path / 'c.csv'}", f"out={tmp_path / 'run'}", "-q")
    # not refused (real single-joint series measured off the flange sit at 0.15), but named where the nominal
    # residual says the description is not the robot
    text = " ".join(r.output.split())
    assert "far beyond any plausible calibration error" in text and f"they look like {unit}" in text, r.output
    r = invoke("fit", sim / "fit.yaml", "model.order=1", "plots=false", "data.truth=null", "data.validation=null",
               f"out={tmp_path / 'good'}", "-q")
    assert "they look like" not in r.output


# ------------------------------------------------------------------------- 3. update
def test_update_refuses_stale_parent_data_missing_directions_and_another_robot(fitted, tmp_path):
    sim, run = fitted["sim"], fitted["run"]
    root = tmp_path
    new = pd.read_csv(sim / "validation.csv")
    new["tool"] = 2
    new.to_csv(root / "new.csv", index=False)
    # no approach directions for a backlash model
    new.drop(columns=[f"dir{i}" for i in range(1, 7)]).to_csv(root / "nodir.csv", index=False)
    r = invoke("update", run, root / "nodir.csv", "--out", root / "u1", "-q")
    assert r.exit_code == 2 and "nodir.csv" in r.output and "dir1..dir6" in r.output and "rows 1..10" in r.output
    # another robot's data: points far off the parent's model
    far = new.copy()
    far["x"] += 1500.0
    far.to_csv(root / "far.csv", index=False)
    r = invoke("update", run, root / "far.csv", "--out", root / "u2", "-q")
    assert r.exit_code == 2 and "far.csv" in r.output and "misses these points" in r.output
    assert not (root / "u2").exists()
    # one gross row among good ones (another reflector): named by its row, not absorbed
    gross = new.copy()
    gross.loc[3, "x"] += 50.0
    gross.to_csv(root / "gross.csv", index=False)
    r = invoke("update", run, root / "gross.csv", "--out", root / "u5", "-q")
    assert r.exit_code == 2 and "gross.csv" in r.output and "row 4" in r.output and "misses this point by 5" in r.output
    assert not (root / "u5").exists()
    # the parent's identification file edited after the fit
    ident = sim / "identification.csv"
    keep = ident.read_bytes()
    try:
        df = pd.read_csv(ident)
        df.loc[0, "x"] += 0.5
        df.to_csv(ident, index=False)
        r = invoke("update", run, root / "new.csv", "--out", root / "u3", "-q")
        assert r.exit_code == 2 and "identification.csv" in r.output and "changed since the fit" in r.output
    finally:
        ident.write_bytes(keep)
    r = invoke("update", run, root / "new.csv", "--out", root / "u4", "-q")
    assert r.exit_code == 0, r.output
    assert "repeat rows of the parent's identification file" not in r.output
    # two of the parent's own rows given again: said by their rows (they would count twice), not refused
    ident_rows = pd.read_csv(sim / "identification.csv").iloc[:2]
    pd.concat([new, ident_rows], ignore_index=True).to_csv(root / "again.csv", index=False)
    r = invoke("update", run, root / "again.csv", "--out", root / "u6")
    assert r.exit_code == 0, r.output
    out = " ".join(r.output.split())
    assert f"2 rows ({len(new) + 1}, {len(new) + 2}) repeat rows of the parent's identification file" in out, out


# ------------------------------------------------------------------------- 4. transposed rotations
def _sensor_rows(robot, n=12, seed=0):
    g = torch.Generator().manual_seed(seed)
    lim = robot.joint_map.limits
    q = lim[:, 0] + torch.rand(n, robot.n, generator=g, dtype=torch.float64) * (lim[:, 1] - lim[:, 0])
    F = robot.chain.fk(robot.joint_map.to_joint(q))
    A = torch.from_numpy(Rotation.from_euler("xyz", [0.3, -0.2, 1.0]).as_matrix())    # tracker frame
    M = torch.from_numpy(Rotation.from_euler("xyz", [0.1, 0.4, -0.7]).as_matrix())    # sensor mount
    R = A @ F[:, :3, :3] @ M
    xyz = (A @ F[:, :3, 3:])[:, :, 0] + torch.tensor([2.0, 0.5, 0.3], dtype=torch.float64)
    return q, xyz, R


def test_transposed_sensor_rotations_are_named(tmp_path, fanuc):
    from torchcal.io.sensor_csv import read_pose_measurements, write_pose_measurements

    q, xyz, R = _sensor_rows(fanuc)
    data = Measurements.from_tensors(q, 0, xyz, pose=torch.arange(len(q)))
    data.extra["rotation"] = R
    good = read_pose_measurements(write_pose_measurements(tmp_path / "ok.csv", data, fanuc), fanuc)
    assert torch.allclose(good.extra["rotation"], R, atol=1e-10)
    data.extra["rotation"] = R.transpose(1, 2).contiguous()
    path = write_pose_measurements(tmp_path / "t.csv", data, fanuc)
    with pytest.raises(DataError, match=r"column 'r11\.\.r33': the rotations look transposed") as err:
        read_pose_measurements(path, fanuc)
    assert "t.csv" in str(err.value)


def test_a_sensor_file_in_metres_is_refused_by_the_sensor_fit(tmp_path, fanuc):
    """A 6-DOF probe's export in metres was fitted "to 0.013 mm" (the UR10's T-Mac data divided by 1000): the
    sensor fit now checks the points' scale as the point fit does, with the same override."""
    from torchcal.app.config import load_config
    from torchcal.app.sensor import load_sensor_inputs
    from torchcal.io.sensor_csv import write_pose_measurements
    from torchcal.io.unit_checks import UnitsError

    q, xyz, R = _sensor_rows(fanuc, n=30)
    cfg = tmp_path / "sensor.yaml"
    cfg.write_text("robot: fanuc_lrmate200i\ndata: {identification: poses.csv}\nsensor: {kind: pose}\n")
    for name, scale in (("poses.csv", 1.0), ("poses_m.csv", 1e-3)):
        data = Measurements.from_tensors(q, 0, xyz * scale, pose=torch.arange(len(q)))
        data.extra["rotation"] = R
        write_pose_measurements(tmp_path / name, data, fanuc)
    assert len(load_sensor_inputs(load_config(cfg)).ident) == 30  # in mm: read
    with pytest.raises(UnitsError, match="poses_m.csv: columns x, y, z.*metres"):
        load_sensor_inputs(load_config(cfg, ["data.identification=" + str(tmp_path / "poses_m.csv")]))
    over = load_config(cfg, ["data.identification=" + str(tmp_path / "poses_m.csv"), "data.units_checked=true"])
    assert len(load_sensor_inputs(over).ident) == 30  # the override holds


# ------------------------------------------------------------------------- 5. duplicate YAML keys
def test_config_key_given_twice_is_refused(fitted, tmp_path):
    text = (fitted["sim"] / "fit.yaml").read_text()
    cfg = tmp_path / "dup.yaml"
    cfg.write_text(text.replace("model:", "seed: 7\nmodel:", 1))
    lines = cfg.read_text().splitlines()
    seed_lines = [i + 1 for i, ln in enumerate(lines) if ln.startswith("seed:")]
    r = invoke("fit", cfg, "--dry-run")
    assert r.exit_code == 2 and "dup.yaml" in r.output and "'seed'" in r.output
    assert f"lines {seed_lines[0]} and {seed_lines[1]}" in r.output, r.output
    assert "backlash: true}" in text
    cfg.write_text(text.replace("backlash: true}", "backlash: true, order: 2}"))  # nested, in one flow mapping
    r = invoke("fit", cfg, "--dry-run")
    assert r.exit_code == 2 and "'order'" in r.output and "twice" in r.output


def test_an_override_for_another_commands_section_is_said(fitted):
    """fleet.* given to `torchcal fit` changes nothing: the user who meant it must hear so before the run."""
    cfg = fitted["sim"] / "fit.yaml"
    r = invoke("fit", cfg, "--dry-run", "fleet.engine=ray", "model.order=2")
    assert r.exit_code == 0, r.output
    said = [ln for ln in r.output.splitlines() if ln.startswith("warning:")]
    assert len(said) == 1 and "'fleet.engine=ray' has no effect on `torchcal fit`" in said[0]
    assert "`torchcal fleet`" in said[0]


# ------------------------------------------------------------------------- 6. export-tables --points
def test_export_tables_points_above_the_siemens_cap_is_refused(tmp_path, monkeypatch):
    import torchcal.io.rundir as rundir

    import torch

    import torchcal
    from torchcal.models.machine import MachineModel

    machine = MachineModel(torchcal.load_robot("five_axis_xyzcb"), torch.zeros(1, 3, dtype=torch.float64), orders=1)
    monkeypatch.setattr(rundir, "load_model", lambda run_dir, **kw: machine)
    r = invoke("export-tables", tmp_path, tmp_path / "t.mpf", "--format", "siemens-cec", "--points", 3000)
    assert r.exit_code == 2 and "--points 3000" in r.output and "2000" in r.output and "--max-points" in r.output


# ------------------------------------------------------------------------- 7. simulate --order
def test_simulate_checks_the_order_as_fit_does(tmp_path):
    r = invoke("simulate", tmp_path / "s", "--identification", 5, "--validation", 0, "--order", 11)
    assert r.exit_code == 2 and "model.order" in r.output and "11" in r.output
    assert not (tmp_path / "s").exists()


# ------------------------------------------------------------------------- 8-9. tab-separated files, folders
def test_tab_separated_file_is_read_and_folder_is_named(fitted, tmp_path, fanuc):
    sim = fitted["sim"]
    df = pd.read_csv(sim / "validation.csv")
    df.to_csv(tmp_path / "tab.csv", index=False, sep="\t")
    a = read_measurements(tmp_path / "tab.csv", fanuc, 3)
    b = read_measurements(sim / "validation.csv", fanuc, 3)
    assert torch.equal(a.q, b.q) and torch.equal(a.xyz, b.xyz)
    (tmp_path / "folder.csv").mkdir()
    with pytest.raises(DataError, match="is a directory"):
        read_measurements(tmp_path / "folder.csv", fanuc, 3)
    r = invoke("predict", fitted["run"], tmp_path / "folder.csv", tmp_path / "p.csv")
    assert r.exit_code == 2 and "folder.csv" in r.output and "is a directory" in r.output


# ------------------------------------------------------------------------- 10. truncated URDF
def test_truncated_urdf_names_the_file(tmp_path):
    from torchcal.kinematics.robot import urdf_dir

    text = (urdf_dir() / "fanuc_lrmate200i.urdf").read_text()
    for cut in (0.3, 0.5, 0.7, 0.9):
        p = tmp_path / f"cut{cut}.urdf"
        p.write_text(text[: int(len(text) * cut)])
        with pytest.raises(URDFError, match=f"cut{cut}.urdf"):
            load_urdf(p)
    # a required attribute lost: the parser used to raise a bare TypeError / AttributeError
    ur10 = (urdf_dir() / "ur10.urdf").read_text()
    for attr, what in (('<mass value="7.1"/>', "link 'shoulder_link': <mass> has no value"),
                       ('<axis xyz="0 0 1"/>', "<axis> has no xyz")):
        assert attr in ur10
        p = tmp_path / "lost.urdf"
        p.write_text(ur10.replace(attr, attr.split()[0] + "/>", 1))
        with pytest.raises(URDFError) as err:
            load_urdf(p)
        assert "lost.urdf" in str(err.value) and what in str(err.value)


# ------------------------------------------------------------------------- 11. unit / joint type mismatch
def test_joint_type_mismatch_names_the_joint(tmp_path):
    from torchcal.kinematics.robot import urdf_dir

    src = urdf_dir() / "fanuc_lrmate200i.yaml"
    text = src.read_text()
    shutil.copy(urdf_dir() / "fanuc_lrmate200i.urdf", tmp_path / "fanuc_lrmate200i.urdf")
    first = text.index("unit: deg")
    (tmp_path / "r.yaml").write_text(text[:first] + "unit: mm" + text[first + len("unit: deg"):])
    with pytest.raises(URDFError) as err:
        load_robot(tmp_path / "r.yaml")
    msg = str(err.value)
    assert "joints[0]" in msg and "'mm' (prismatic)" in msg and "is revolute" in msg


# ------------------------------------------------------------------------- 12. a folder named like a bundled robot
def test_local_folder_named_like_a_bundled_robot(tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)
    (tmp_path / "ur10").mkdir()
    (tmp_path / "ur10" / "data.csv").write_text("x\n1\n")
    assert load_robot("ur10").n == 6  # no URDF there: the bundled robot
    (tmp_path / "ur10" / "mine.urdf").write_text("<robot name='x'/>")
    with pytest.raises(URDFError, match=r"local folder .*mine\.urdf.*bundled 'ur10'"):
        load_robot("ur10")


def test_an_experiments_config_without_its_data_says_which_script_writes_them(tmp_path):
    """`torchcal fit experiments/X/fit.yaml` before `python experiments/X/run.py`: the message says to run it."""
    (tmp_path / "run.py").write_text("# writes the data\n")
    cfg = tmp_path / "fit.yaml"
    cfg.write_text("robot: fanuc_lrmate200i\ntools: [[0, 0, 100]]\ndata: {identification: data/ident.csv}\n")
    r = invoke("fit", cfg)
    assert r.exit_code == 2
    assert "file not found" in r.output and f"python {tmp_path / 'run.py'}" in r.output.replace("\n", "")


# ------------------------------------------------------------------------- 13. limits in the other angle unit
def test_urdf_limits_in_degrees_and_joint_map_limits_in_radians_are_refused(tmp_path):
    """A URDF's limits are radians, a joint map's degrees; written the other way round the joint ranges (and the
    error polynomials' domain) are 57x off. Each is refused naming the file and joints; the right units load."""
    import re

    from torchcal.kinematics.robot import urdf_dir

    text = (urdf_dir() / "fanuc_lrmate200i.urdf").read_text()

    def to_degrees(m):
        return f'{m.group(1)}="{math.degrees(float(m.group(2))):.6g}"'

    deg = re.sub(r'(lower|upper)="([-0-9.eE]+)"', to_degrees, text)
    assert deg != text
    (tmp_path / "deg.urdf").write_text(deg)
    with pytest.raises(URDFError) as err:
        load_robot(tmp_path / "deg.urdf")
    assert "deg.urdf" in str(err.value) and "6 of 6 revolute joints have limits beyond one turn" in str(err.value)
    (tmp_path / "rad.urdf").write_text(text)
    assert load_robot(tmp_path / "rad.urdf").n == 6  # the same robot in radians loads

    yml = (urdf_dir() / "fanuc_lrmate200i.yaml").read_text().replace("urdf: fanuc_lrmate200i.urdf", "urdf: rad.urdf")
    assert load_robot(_write(tmp_path / "deg.yaml", yml)).n == 6

    def to_radians(m):
        return f"lower: {math.radians(float(m.group(1))):.6g}, upper: {math.radians(float(m.group(2))):.6g}"

    rad = re.sub(r"lower: ([-0-9.]+), upper: ([-0-9.]+)", to_radians, yml)
    with pytest.raises(URDFError) as err:
        load_robot(_write(tmp_path / "rad.yaml", rad))
    assert "rad.yaml" in str(err.value) and "they look like radians" in str(err.value) and "'J1'" in str(err.value)


def test_a_joint_map_lists_every_missing_key_at_once(tmp_path):
    from torchcal.kinematics.robot import urdf_dir

    shutil.copy(urdf_dir() / "fanuc_lrmate200i.urdf", tmp_path / "fanuc_lrmate200i.urdf")
    yml = (urdf_dir() / "fanuc_lrmate200i.yaml").read_text()
    yml = yml.replace("{name: J2, unit: deg, lower: -30, upper: 100}", "{name: J2, unit: deg}")
    yml = yml.replace("{name: J5, unit: deg, lower: -90, upper: 90}", "{name: J5, lower: -90, upper: 90}")
    with pytest.raises(URDFError) as err:
        load_robot(_write(tmp_path / "r.yaml", yml))
    assert "joints[1] is missing 'lower', 'upper'; joints[4] is missing 'unit'" in str(err.value)


def _write(path, text):
    path.write_text(text)
    return path


# ------------------------------------------------------------------------- 14. a model worse than the nominal robot
def test_a_fit_worse_than_the_nominal_robot_is_said(fitted, tmp_path):
    """Validation points of a robot that is exactly nominal (an independent DH forward model): the fitted errors
    of the simulated robot can only make it worse there, and the run must say so rather than only print a
    negative decrease."""
    from tests.conftest import PAPER2_TOOLS_MM, fanuc_dh_reference

    sim = fitted["sim"]
    val = pd.read_csv(sim / "validation.csv")
    q = val[[f"q{i}" for i in range(1, 7)]].to_numpy()
    F = fanuc_dh_reference(q)
    tools = np.asarray(PAPER2_TOOLS_MM)[val["tool"].to_numpy()] / 1000.0
    val[["x", "y", "z"]] = (F[:, :3, 3] + np.einsum("rij,rj->ri", F[:, :3, :3], tools)) * 1000.0
    val.to_csv(tmp_path / "nominal.csv", index=False)
    r = invoke("fit", sim / "fit.yaml", "model.order=1", "plots=false", "report=false", "data.truth=null",
               f"data.validation={tmp_path / 'nominal.csv'}", f"out={tmp_path / 'run'}")
    assert r.exit_code == 0, r.output
    assert "the fitted model is worse than the nominal robot on the validation set" in r.output, r.output
    assert "worse than the nominal robot on the identification set" not in r.output
    assert "pull the whole fit" not in r.output
    # one identification row cut inside a number (210 mm off): the do-not-deploy warning names it as a cause
    ident = pd.read_csv(sim / "identification.csv")
    ident.loc[17, "x"] += 210.0
    ident.to_csv(tmp_path / "gross.csv", index=False)
    r = invoke("fit", sim / "fit.yaml", "model.order=1", "plots=false", "report=false", "data.truth=null",
               f"data.identification={tmp_path / 'gross.csv'}", f"data.validation={tmp_path / 'nominal.csv'}",
               f"out={tmp_path / 'run2'}")
    said = " ".join(r.output.split())
    assert r.exit_code == 0 and "(row 18) pull the whole fit" in said, said


# ------------------------------------------------------------------------- 15. a run that did not finish
def test_a_partial_run_is_not_deployed(fitted, tmp_path):
    """A run directory still holding PARTIAL (its fit failed or was interrupted) may hold a failed solver's last
    iterate: predict, compensate, update and the exports refuse it, naming the file to delete once checked."""
    sim = fitted["sim"]
    run = tmp_path / "partial"
    shutil.copytree(fitted["run"], run)
    (run / "PARTIAL").write_text("This run did not finish.\n")
    for args in (("predict", run, sim / "validation.csv", tmp_path / "p.csv"),
                 ("compensate", run, sim / "validation.csv", tmp_path / "c.csv"),
                 ("update", run, sim / "validation.csv", "--out", tmp_path / "u"),
                 ("export-urdf", run, tmp_path / "cal.urdf")):
        r = invoke(*args)
        assert r.exit_code == 2 and "this run did not finish" in r.output and "PARTIAL" in r.output, (args, r.output)
        assert not any((tmp_path / n).exists() for n in ("p.csv", "c.csv", "u", "cal.urdf"))
    (run / "PARTIAL").unlink()  # the user's word: checked
    assert invoke("predict", run, sim / "validation.csv", tmp_path / "p.csv").exit_code == 0


def test_near_home_degrees_are_not_refused_where_the_points_or_the_run_say_degrees(tmp_path):
    """A run identified on near-home poses in degrees: predict and compensate must take its own files (its points
    fit degrees; its commands are within the run's own span) instead of calling them radians."""
    import torchcal
    from tests.conftest import PAPER2_TOOLS_MM

    robot = load_robot("fanuc_lrmate200i")
    tools = torch.tensor(PAPER2_TOOLS_MM, dtype=torch.float64) / 1000.0
    truth = torchcal.TruthRobot.fanuc_paper2(robot, tools, 4)
    g = torch.Generator().manual_seed(2)
    q = torch.deg2rad(torch.rand(40, 6, generator=g, dtype=torch.float64) * 10.0 - 5.0)  # within +-5 deg
    data = torchcal.simulate(truth, q, [0, 1, 2], torchcal.NoiseModel.from_robot(robot), 1)
    torchcal.write_measurements(tmp_path / "home.csv", data, robot)
    cfg = tmp_path / "home.yaml"
    cfg.write_text(f"robot: fanuc_lrmate200i\ntools: {PAPER2_TOOLS_MM}\ndata: {{identification: home.csv}}\n"
                   "model: {order: 0, backlash: false}\nplots: false\nreport: false\nout: run\n")
    r = invoke("fit", cfg, "-q")
    assert r.exit_code == 0 and "but the measured points fit them read as degrees" in r.output, r.output
    run = tmp_path / "run"
    assert invoke("predict", run, tmp_path / "home.csv", tmp_path / "p.csv").exit_code == 0  # its points decide
    cmds = pd.read_csv(tmp_path / "home.csv").drop(columns=["x", "y", "z"])
    cmds.to_csv(tmp_path / "cmds.csv", index=False)
    r = invoke("compensate", run, tmp_path / "cmds.csv", tmp_path / "c.csv")  # no points: the run's span decides
    assert r.exit_code == 0, r.output
    # update and sweep read such files the same way, and say so
    r = invoke("update", run, tmp_path / "home.csv", "--out", tmp_path / "u", "-q")
    assert r.exit_code == 0 and "but the measured points fit them read as degrees" in r.output, r.output
    r = invoke("sweep", cfg, "model.order=0,1", "--out", tmp_path / "sw", "-q")
    said = [ln for ln in r.output.splitlines() if "fit them read as degrees" in ln]
    assert r.exit_code == 0 and len(said) == 1 and said[0].startswith("warning:"), r.output
    # (against a run fitted over the whole range such commands are still refused: the test of section 1)


@pytest.mark.parametrize("span_deg", [80.0, 5.0])
def test_a_machines_rotary_axes_typed_in_radians_are_refused(machine, span_deg):
    """On a machine tool the linear axes dominate the distances between rows, so the distance ratio cannot tell
    rotary axes in radians; the shape of the (rigidly aligned) point cloud can. Degrees near home are not refused."""
    from torchcal.io.unit_checks import UnitsError, check_units

    g = torch.Generator().manual_seed(3)
    lim = machine.joint_map.limits
    n = machine.joint_map.n
    rotary = ~machine.joint_map.prismatic
    q = lim[:, 0] + (lim[:, 1] - lim[:, 0]) * torch.rand(60, n, generator=g, dtype=torch.float64)
    q[:, rotary] = math.radians(span_deg) * (2 * torch.rand(60, int(rotary.sum()), generator=g, dtype=torch.float64) - 1)
    tools = torch.tensor([[0.0, 0.0, 0.4], [0.0, 0.0, 0.5]], dtype=torch.float64)
    tool = torch.arange(60) % 2
    F = machine.chain.fk(machine.joint_map.to_joint(q))
    Y = torch.tensor([[0.0, -1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, 1.0]], dtype=torch.float64)  # the tracker's frame
    xyz = (F[:, :3, 3] + (F[:, :3, :3] @ tools[tool][..., None])[..., 0]) @ Y.T + torch.tensor([1.0, 2.0, 0.5])
    typed = q.clone()
    typed[:, rotary] = q[:, rotary] * math.pi / 180.0  # radians in the file, read as degrees

    def rows(qq):
        return Measurements(qq, tool, xyz, torch.zeros_like(qq), torch.arange(60) // 2, torch.arange(60), False,
                            "machine.csv")

    if span_deg > 10:
        with pytest.raises(UnitsError, match=r"machine.csv: the rotary columns look like radians"):
            check_units(rows(typed), machine, tools)
    check_units(rows(q), machine, tools)  # the same points with their degrees: nothing to say


def test_a_sensor_fit_on_rotations_of_another_convention_says_do_not_deploy(tmp_path, fanuc):
    """A T-Mac file imported with the wrong rotation order was fitted to 93 mm, "converged", with no warning (the
    point runs' checks were missing from sensor runs). The same rows with each rotation rebuilt from its angles
    in another Euler order are now warned about; the true rows are not."""
    from scipy.spatial.transform import Rotation

    from torchcal.app.config import load_config
    from torchcal.app.sensor import run_sensor_fit
    from torchcal.io.sensor_csv import write_pose_measurements

    q, xyz, R = _sensor_rows(fanuc, n=40)
    angles = Rotation.from_matrix(R.numpy()).as_euler("xyz")
    wrong = torch.from_numpy(Rotation.from_euler("zyx", angles).as_matrix())  # (ZYX: refused as transposed)
    for name, rot in (("poses.csv", R), ("zyx.csv", wrong)):
        data = Measurements.from_tensors(q, 0, xyz, pose=torch.arange(len(q)))
        data.extra["rotation"] = rot
        write_pose_measurements(tmp_path / name, data, fanuc)
    cfg = tmp_path / "sensor.yaml"
    cfg.write_text("robot: fanuc_lrmate200i\ndata: {identification: poses.csv}\nsensor: {kind: pose, mount: estimate}\n"
                   "measurement_frame: estimate\nmodel: {order: 0, backlash: false}\nreport: false\nplots: false\n")
    good = run_sensor_fit(load_config(cfg, [f"out={tmp_path / 'good'}"]))
    assert not any("do not deploy" in w or "plausible" in w for w in good.warnings), good.warnings
    # the log and the report say which weights a pose sensor used (noise.sigma_m is none of them)
    assert "pose weights: torchcal's default" in (good.run_dir / "run.log").read_text()
    from torchcal.report import render_report

    page = render_report(good.run_dir)
    assert "Tracker noise sigma" not in page and "each row&#x27;s sx..srz" in page.replace("'", "&#x27;")
    bad = run_sensor_fit(load_config(cfg, [f"out={tmp_path / 'bad'}", f"data.identification={tmp_path / 'zyx.csv'}"]))
    worse = [w for w in bad.warnings if "worse than the nominal robot" in w and "do not deploy" in w]
    far = [w for w in bad.warnings if "beyond any plausible calibration error" in w]
    assert len(worse) == 1 and len(far) == 1, bad.warnings
    assert all("import-tmac --convention" in w for w in worse + far)


def test_a_position_only_sensor_fit_is_not_judged_by_its_made_up_orientation():
    """sensor.position_only fits never see the orientation: a real UR10 run halved its position error and was told
    not to deploy because the orientation it made up was worse than nominal. Judged on position alone."""
    from types import SimpleNamespace

    from torchcal.app.sensor import warn_implausible_pose_fit

    said = []
    progress = SimpleNamespace(warn=said.append)
    ev = {"identification": {"position_mm": {"nominal": {"mean": 0.92}, "modeled": {"mean": 0.42}},
                             "orientation_deg": {"nominal": {"mean": 0.07}, "modeled": {"mean": 4.9}}}}
    ok = SimpleNamespace(success=True)
    warn_implausible_pose_fit(ok, ev, progress, position_only=True)
    assert said == []
    warn_implausible_pose_fit(ok, ev, progress, position_only=False)  # a full-pose fit that got worse: said
    assert len(said) == 1 and "orientation mean 4.9000 against 0.0700 deg" in said[0]
    ev["identification"]["position_mm"]["modeled"]["mean"] = 1.5  # worse in position: said, position only or not
    said.clear()
    warn_implausible_pose_fit(ok, ev, progress, position_only=True)
    assert len(said) == 1 and "position mean 1.5000" in said[0] and "orientation" not in said[0]
