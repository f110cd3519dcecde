"""``torchcal update`` end to end: fit -> update -> update, and what predict / compensate / a further update read."""

import json
import shutil

import pandas as pd
import pytest
import torch
from typer.testing import CliRunner

from torchcal.cli import app
from torchcal.app.config import load_config
from torchcal.io.csv import read_measurements
from torchcal.io.rundir import load_model
from torchcal.app.files import run_compensation_options

runner = CliRunner()
POSES, VAL_POSES, FIRST, SECOND = 36, 20, 24, 30

pytestmark = pytest.mark.usefixtures("one_thread")


def invoke(*args):
    return runner.invoke(app, [str(a) for a in args])


@pytest.fixture(scope="module")
def runs(tmp_path_factory, one_thread):
    """A fit on the first 24 poses, two updates (6 + 6 poses), and a fit on all 36 poses for reference."""
    root = tmp_path_factory.mktemp("update")
    sim = root / "sim"
    assert invoke("simulate", sim, "--identification", POSES, "--validation", VAL_POSES, "--seed", 3).exit_code == 0
    ident = pd.read_csv(sim / "identification.csv")
    parts = {"first": ident[ident.pose < FIRST], "b1": ident[(ident.pose >= FIRST) & (ident.pose < SECOND)],
             "b2": ident[ident.pose >= SECOND]}
    for name, df in parts.items():
        df.to_csv(root / f"{name}.csv", index=False)
    common = ("model.order=1", "plots=false", "data.truth=null")
    for name, data in (("run", root / "first.csv"), ("all", sim / "identification.csv")):
        r = invoke("fit", sim / "fit.yaml", *common, f"data.identification={data}", f"out={root / name}", "-q")
        assert r.exit_code == 0, r.output
    r1 = invoke("update", root / "run", root / "b1.csv", "--out", root / "run1", "-q")
    assert r1.exit_code == 0, r1.output
    r2 = invoke("update", root / "run1", root / "b2.csv", "--out", root / "run2", "-q")
    assert r2.exit_code == 0, r2.output
    return {"root": root, "sim": sim, "out1": r1.output, "out2": r2.output}


def _val_points(run, sim, fanuc):
    data = read_measurements(sim / "validation.csv", fanuc, 3)
    with torch.no_grad():
        return load_model(run).points(data.q, data.tool, data.direction), data.xyz


def test_update_writes_a_run_directory_with_its_lineage(runs):
    root = runs["root"]
    for name in ("config.yaml", "versions.json", "run.log", "model.pt", "online.pt", "fit.json", "update.json",
                 "metrics.json"):
        assert (root / "run2" / name).is_file(), name
    u1 = json.loads((root / "run1" / "update.json").read_text())
    u2 = json.loads((root / "run2" / "update.json").read_text())
    assert u1["parent"] == str((root / "run").resolve()) and u1["history"] == "identification data"
    assert u2["lineage"] == [str((root / "run").resolve()), str((root / "run1").resolve())]
    assert u2["history"] == "online state" and u2["strategy"] == "information"
    assert (u1["rows"], u1["new_rows"]) == (3 * SECOND, 3 * (SECOND - FIRST))
    # the new rows are hashed with the parent's inputs: a chained update reads them as this run's
    from torchcal.io.rundir import file_sha256

    h2 = json.loads((root / "run2" / "data_hashes.json").read_text())
    assert h2["update.new"]["sha256"] == file_sha256(root / "b2.csv")
    assert h2["data.identification"]["sha256"] == file_sha256(root / "first.csv")
    assert (u2["rows"], u2["new_rows"]) == (3 * POSES, 3 * (POSES - SECOND))
    metrics = json.loads((root / "run2" / "metrics.json").read_text())
    assert metrics["parent"] == u2["parent"] and set(metrics["sets"]) == {"update", "validation"}
    assert "run directory:" in runs["out2"] and "108 rows in 3 batches" in runs["out2"]
    # the config is the parent's, still a valid config of its own
    assert load_config(root / "run2" / "config.yaml").model.order == 1
    assert torch.load(root / "run2" / "online.pt", weights_only=True)["rows"] == 3 * POSES


def test_chained_updates_land_on_the_fit_of_all_rows(runs, fanuc):
    """fit(24 poses) + update(6) + update(6) ~ fit(36 poses): the earlier rows enter as carried information.

    Measured on the validation poses: 3.0 µm largest gap to the all-rows fit, against 700 µm between the
    first fit and the all-rows fit; the bound (2 % of that) leaves room for solver tolerances.
    """
    root, sim = runs["root"], runs["sim"]
    p_all, _ = _val_points(root / "all", sim, fanuc)
    p_first, _ = _val_points(root / "run", sim, fanuc)
    p_upd, _ = _val_points(root / "run2", sim, fanuc)
    before = float((p_first - p_all).norm(dim=1).max())
    after = float((p_upd - p_all).norm(dim=1).max())
    assert before > 5e-5
    assert after < 0.02 * before


def test_predict_and_compensate_read_an_updated_run(runs, fanuc):
    root, sim = runs["root"], runs["sim"]
    val = pd.read_csv(sim / "validation.csv").drop(columns=["x", "y", "z"])
    val.to_csv(root / "cmd.csv", index=False)
    r = invoke("predict", root / "run2", root / "cmd.csv", root / "pred.csv")
    assert r.exit_code == 0, r.output
    pred = pd.read_csv(root / "pred.csv")[["x", "y", "z"]].to_numpy()
    p_upd, _ = _val_points(root / "run2", sim, fanuc)
    assert abs(pred - p_upd.numpy() * 1e3).max() < 1e-9
    # what `torchcal compensate` reads from a run: the model and the config's compensation options (the
    # command itself runs in test_cli; its first call JIT-compiles the fused kernel, far over a unit test's time)
    assert run_compensation_options(root / "run2", max_correction_deg=2.0) == pytest.approx(
        run_compensation_options(root / "run", max_correction_deg=2.0))
    assert load_model(root / "run2").coverage.n_rows == 3 * POSES  # direction coverage of every row so far


def test_literal_strategy_from_a_fit_run_and_strategy_mismatch(runs):
    root = runs["root"]
    r = invoke("update", root / "run", root / "b1.csv", "--out", root / "lit", "--strategy", "literal", "-q")
    assert r.exit_code == 0, r.output
    state = torch.load(root / "lit" / "online.pt", weights_only=True)
    assert state["strategy"] == "literal" and state["literal"]["v"].shape == (3 * SECOND, 6)
    r = invoke("update", root / "lit", root / "b2.csv", "--out", root / "lit2", "--strategy", "information")
    assert r.exit_code == 2 and "literal" in r.output and not (root / "lit2").exists()
    r = invoke("update", root / "run", root / "b1.csv", "--out", root / "bad", "--strategy", "kalman")
    assert r.exit_code == 2 and "kalman" in r.output


def test_missing_history_falls_back_to_synthetic_rows(runs, fanuc):
    """A fit run whose identification CSV is gone: the update says so and keeps the model near the data."""
    root, sim = runs["root"], runs["sim"]
    moved = root / "moved"
    shutil.copytree(root / "run", moved)
    cfg = (moved / "config.yaml").read_text()
    (moved / "config.yaml").write_text(cfg.replace(str(root / "first.csv"), str(root / "gone.csv")))
    r = invoke("update", moved, root / "b1.csv", "--out", root / "syn")
    assert r.exit_code == 0, r.output
    assert "synthetic" in r.output
    assert json.loads((root / "syn" / "update.json").read_text())["history"] == "synthetic"
    p_syn, xyz = _val_points(root / "syn", sim, fanuc)
    p_run1, _ = _val_points(root / "run1", sim, fanuc)
    # the stand-in information keeps the model where the data put it (measured 1.08x the true-history update)
    assert (p_syn - xyz).norm(dim=1).mean() < 1.3 * (p_run1 - xyz).norm(dim=1).mean()


def test_bad_inputs_name_the_file(runs):
    root = runs["root"]
    lines = (root / "b1.csv").read_text().splitlines()
    head = lines[0].split(",")
    row = lines[3].split(",")
    row[head.index("q2")] = "abc"
    lines[3] = ",".join(row)
    (root / "bad.csv").write_text("\n".join(lines) + "\n")
    r = invoke("update", root / "run", root / "bad.csv", "--out", root / "never")
    assert r.exit_code == 2 and "bad.csv" in r.output and "q2" in r.output
    assert not (root / "never").exists()
    r = invoke("update", root / "sim", root / "b1.csv", "--out", root / "never")
    assert r.exit_code == 2 and "config.yaml" in r.output


def test_unit_slips_in_new_rows_are_named_as_such(runs):
    """Radian joints and metre points in an update's rows: the fit's unit checks, not 'misses by 600 mm'."""
    import numpy as np

    root = runs["root"]
    b1 = pd.read_csv(root / "b1.csv")
    rad, metres = b1.copy(), b1.copy()
    q = [f"q{i}" for i in range(1, 7)]
    rad[q] = np.radians(rad[q])
    metres[["x", "y", "z"]] = metres[["x", "y", "z"]] / 1000.0
    rad.to_csv(root / "b1_rad.csv", index=False)
    metres.to_csv(root / "b1_m.csv", index=False)
    r = invoke("update", root / "run", root / "b1_rad.csv", "--out", root / "never")
    assert r.exit_code == 2 and "b1_rad.csv: columns q1..q6: the joints are radians" in r.output, r.output
    r = invoke("update", root / "run", root / "b1_m.csv", "--out", root / "never")
    assert r.exit_code == 2 and "b1_m.csv: columns x, y, z" in r.output and "look like metres" in r.output
    assert not (root / "never").exists()
    # the user's word skips the check; the rows then meet the update's own plausibility check
    r = invoke("update", root / "run", root / "b1_m.csv", "--out", root / "never", "--units-checked")
    assert r.exit_code == 2 and "look like metres" not in r.output and "misses these points" in r.output


@pytest.fixture(scope="module")
def sensor_runs(tmp_path_factory, fanuc, one_thread):
    """A 6-DOF STS run (Paper III) on 24 poses and its update with 10 more (simulated FANUC + STS + tracker)."""
    import yaml

    from torchcal.identify.online import cat_measurements
    from torchcal.io.sensor_csv import write_pose_measurements
    from torchcal.sim import SensorTruth

    root = tmp_path_factory.mktemp("sensor")
    truth = SensorTruth(fanuc, 0)
    sample = truth.sample_commands(44, 0)
    data = truth.measure_sts(sample.q, sample.direction, 0)
    first, new, val = (data.subset(torch.arange(a, b)) for a, b in ((0, 24), (24, 34), (34, 44)))
    for name, d in (("first", first), ("new", new), ("val", val), ("all", cat_measurements([first, new]))):
        write_pose_measurements(root / f"{name}.csv", d, fanuc)
    for name, ident in (("run", "first.csv"), ("all", "all.csv")):
        cfg = {"robot": "fanuc_lrmate200i", "sensor": {"kind": "sts"}, "model": {"order": 1}, "plots": False,
               "data": {"identification": ident, "validation": "val.csv"}, "out": name}
        (root / f"{name}.yaml").write_text(yaml.safe_dump(cfg))
    r = invoke("fit", root / "run.yaml", "-q")
    assert r.exit_code == 0, r.output
    r = invoke("update", root / "run", root / "new.csv", "--out", root / "run1", "-q")
    assert r.exit_code == 0, r.output
    return {"root": root, "val": val, "new": new}


def _sensor_positions(run, data):
    with torch.no_grad():
        return load_model(run).sensor_pose(data.q, None, data.direction)[:, :3, 3]


def test_sensor_run_update_reads_the_sensor_contract(sensor_runs):
    """The update reads the sensor CSV, builds the fit's STS instrument and moves the rig towards the new rows."""
    root, new = sensor_runs["root"], sensor_runs["new"]
    metrics = json.loads((root / "run1" / "metrics.json").read_text())
    assert set(metrics["sets"]) == {"update", "validation"}
    assert "position_mm" in metrics["sets"]["validation"] and "orientation_deg" in metrics["sets"]["update"]
    assert json.loads((root / "run1" / "update.json").read_text())["history"] == "identification data"
    before = (_sensor_positions(root / "run", new) - new.xyz).norm(dim=1).mean()
    after = (_sensor_positions(root / "run1", new) - new.xyz).norm(dim=1).mean()
    assert after < 0.6 * before  # the new rows are fitted now (measured 0.39x)
    r = invoke("update", root / "run1", root / "new.csv", "--out", root / "run2", "-q")  # and once more, from the state
    assert r.exit_code == 0, r.output
    assert json.loads((root / "run2" / "update.json").read_text())["history"] == "online state"


def test_sensor_run_literal_strategy_chains(sensor_runs):
    """The literal strategy stores the rows; a further update rebuilds their STS instrument from the config."""
    root = sensor_runs["root"]
    for parent, out, extra in (("run", "lit1", ("--strategy", "literal")), ("lit1", "lit2", ())):
        r = invoke("update", root / parent, root / "new.csv", "--out", root / out, "-q", *extra)
        assert r.exit_code == 0, r.output
    assert torch.load(root / "lit2" / "online.pt", weights_only=True)["literal"]["v"].shape[0] == 44


def test_sensor_run_update_lands_on_the_fit_of_all_rows(sensor_runs):
    """fit(24 poses) + update(10) ~ fit(34) for the STS rig. Measured on 10 validation poses: 0.4 µm largest
    sensor-position gap, against 360 µm between the first fit and the all-rows fit."""
    root, val = sensor_runs["root"], sensor_runs["val"]
    r = invoke("fit", root / "all.yaml", "-q")
    assert r.exit_code == 0, r.output
    p_all, p_first, p_upd = (_sensor_positions(root / name, val) for name in ("all", "run", "run1"))
    before = float((p_first - p_all).norm(dim=1).max())
    assert before > 5e-5
    assert float((p_upd - p_all).norm(dim=1).max()) < 0.02 * before


def test_updating_with_the_validation_set_says_it_is_no_longer_held_out(runs, tmp_path):
    """The config's validation file given as the update's data (or a copy of it): the model is fitted to it, so
    its residual is no held-out figure: said, and not reported as 'validation'."""
    import shutil

    copy = tmp_path / "val_copy.csv"
    shutil.copy(runs["sim"] / "validation.csv", copy)
    r = invoke("update", runs["root"] / "run", copy, "--out", tmp_path / "u", "-q")
    assert r.exit_code == 0, r.output
    said = " ".join(r.output.split())
    assert "the update's data are the config's validation set" in said and "no held-out" in said
    metrics = json.loads((tmp_path / "u" / "metrics.json").read_text())
    assert set(metrics["sets"]) == {"update"}


def test_an_update_into_a_taken_out_says_where_it_went(runs, tmp_path):
    """--out naming a folder that holds a run already: the update goes beside it and its log says why."""
    r1 = invoke("update", runs["root"] / "run", runs["root"] / "b1.csv", "--out", tmp_path / "u", "-q")
    r2 = invoke("update", runs["root"] / "run", runs["root"] / "b1.csv", "--out", tmp_path / "u", "-q")
    assert r1.exit_code == 0 and r2.exit_code == 0, r1.output + r2.output
    assert f"{tmp_path / 'u'} holds a run already" in (tmp_path / "u-2" / "run.log").read_text()
    assert "holds a run already" not in (tmp_path / "u" / "run.log").read_text()


def test_sensor_run_update_refuses_positions_in_metres(sensor_runs):
    """The sensor update checks the new rows' units as the sensor fit does (its positions at the flange)."""
    import pandas as pd

    root = sensor_runs["root"]
    df = pd.read_csv(root / "new.csv")
    df[["x", "y", "z"]] = df[["x", "y", "z"]] / 1000.0
    df.to_csv(root / "new_m.csv", index=False)
    r = invoke("update", root / "run", root / "new_m.csv", "--out", root / "run_m", "-q")
    assert r.exit_code == 2 and "new_m.csv: columns x, y, z" in r.output and "metres" in r.output, r.output
    assert not (root / "run_m").exists()  # refused before anything was written


def test_an_update_from_a_moved_tracker_is_said(runs, tmp_path):
    """New rows measured from another tracker placement (3 mm, 0.3 deg): the update would absorb the move into the
    robot, so it says that one rigid motion explains the parent's miss; rows from the parent's placement say
    nothing of the kind."""
    import math

    import pandas as pd

    df = pd.read_csv(runs["root"] / "b1.csv")
    a = math.radians(0.3)
    R = torch.tensor([[math.cos(a), -math.sin(a), 0.0], [math.sin(a), math.cos(a), 0.0], [0.0, 0.0, 1.0]],
                     dtype=torch.float64)
    xyz = torch.tensor(df[["x", "y", "z"]].to_numpy()) @ R.T + torch.tensor([3.0, -1.0, 0.5], dtype=torch.float64)
    df[["x", "y", "z"]] = xyz.numpy()
    df.to_csv(tmp_path / "moved.csv", index=False)
    r = invoke("update", runs["root"] / "run", tmp_path / "moved.csv", "--out", tmp_path / "u", "-q")
    assert r.exit_code == 0, r.output
    said = " ".join(r.output.split())
    assert "moved.csv: the model's residual falls from" in said and "did the tracker stand elsewhere?" in said
    r = invoke("update", runs["root"] / "run", runs["root"] / "b1.csv", "--out", tmp_path / "same", "-q")
    assert r.exit_code == 0 and "tracker stand elsewhere" not in r.output


def test_a_sensor_update_from_a_moved_tracker_is_said_and_its_miss_recorded(sensor_runs, tmp_path):
    """A sensor run's update judges the new rows as a point run's does: the parent's miss of the sensor positions
    is recorded, one rigid motion explaining it is said (positions and rotations turned 0.3 deg, moved 3 mm), and
    the rows of the parent's placement say nothing of the kind."""
    import json
    import math

    import pandas as pd

    root = sensor_runs["root"]
    df = pd.read_csv(root / "new.csv")
    a = math.radians(0.3)
    Y = torch.tensor([[math.cos(a), -math.sin(a), 0.0], [math.sin(a), math.cos(a), 0.0], [0.0, 0.0, 1.0]],
                     dtype=torch.float64)
    xyz = torch.tensor(df[["x", "y", "z"]].to_numpy()) @ Y.T + torch.tensor([3.0, -1.0, 0.5], dtype=torch.float64)
    df[["x", "y", "z"]] = xyz.numpy()
    rot = [f"r{i}{j}" for i in (1, 2, 3) for j in (1, 2, 3)]
    R = torch.tensor(df[rot].to_numpy()).reshape(-1, 3, 3)
    df[rot] = (Y @ R).reshape(-1, 9).numpy()
    df.to_csv(tmp_path / "moved.csv", index=False)
    r = invoke("update", root / "run", tmp_path / "moved.csv", "--out", tmp_path / "u", "-q")
    assert r.exit_code == 0, r.output
    said = " ".join(r.output.split())
    assert "moved.csv: the model's residual falls from" in said and "did the tracker stand elsewhere?" in said
    miss = json.loads((tmp_path / "u" / "metrics.json").read_text())["parent_model_on_new_rows_mm"]
    assert miss is not None and miss["mean"] > 2.0  # the 3 mm move, seen in the sensor positions
    r = invoke("update", root / "run", root / "new.csv", "--out", tmp_path / "same", "-q")
    assert r.exit_code == 0 and "tracker stand elsewhere" not in r.output
    same = json.loads((tmp_path / "same" / "metrics.json").read_text())["parent_model_on_new_rows_mm"]
    assert same is not None and same["mean"] < 0.5 * miss["mean"]


def test_a_sensor_update_without_directions_for_a_backlash_model_is_refused(sensor_runs, tmp_path):
    """The rig's backlash terms live on its robot model: rows without dir1..dirN are refused as for a point run."""
    import pandas as pd
    import yaml

    root = sensor_runs["root"]
    cfg = yaml.safe_load((root / "run.yaml").read_text())
    cfg["model"]["backlash"] = True
    cfg["data"] = {"identification": str(root / "first.csv")}
    cfg["out"] = str(tmp_path / "bl")
    (tmp_path / "bl.yaml").write_text(yaml.safe_dump(cfg))
    r = invoke("fit", tmp_path / "bl.yaml", "-q")
    assert r.exit_code == 0, r.output
    df = pd.read_csv(root / "new.csv")
    df.drop(columns=[c for c in df.columns if c.startswith("dir")]).to_csv(tmp_path / "nodir.csv", index=False)
    r = invoke("update", tmp_path / "bl", tmp_path / "nodir.csv", "--out", tmp_path / "u", "-q")
    assert r.exit_code == 2 and "dir1..dir6" in r.output and "backlash terms" in r.output, r.output
    assert not (tmp_path / "u").exists()


def test_backlash_the_parent_could_not_see_is_said_to_be_held(runs, tmp_path):
    """A parent fitted on rows that approached every joint from +1 pinned its backlash (collinear with the joint
    offsets); rows from -1 cannot free it in an update, which keeps the parent's gauge: the update says so and
    names the joints. Rows from +1 again say nothing."""
    root = runs["root"]
    dirs = [f"dir{j}" for j in range(1, 7)]
    for name, sign in (("plus", 1), ("minus", -1)):
        df = pd.read_csv(root / ("first.csv" if name == "plus" else "b1.csv"))
        df[dirs] = sign
        df.to_csv(tmp_path / f"{name}.csv", index=False)
    r = invoke("fit", runs["sim"] / "fit.yaml", "model.order=1", "model.backlash=true", "plots=false",
               "data.truth=null", "data.validation=null", f"data.identification={tmp_path / 'plus.csv'}",
               f"out={tmp_path / 'p'}", "-q")
    assert r.exit_code == 0, r.output
    pinned = json.loads((tmp_path / "p" / "fit.json").read_text())["pinned_names"]
    assert any(".backlash." in n for n in pinned)
    r = invoke("update", tmp_path / "p", tmp_path / "minus.csv", "--out", tmp_path / "u", "-q")
    assert r.exit_code == 0, r.output
    said = " ".join(r.output.split())
    assert "is held at the parent's value" in said and "J2" in said, said
    r = invoke("update", tmp_path / "p", tmp_path / "plus.csv", "--out", tmp_path / "u2", "-q")
    assert r.exit_code == 0 and "held at the parent's value" not in r.output
