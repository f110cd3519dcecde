"""The console entry end to end on a tiny simulated set: simulate -> fit -> predict -> compensate, and bad inputs."""

import json
import math
import re
import subprocess
import sys
import threading
import time
from pathlib import Path

import numpy as np
import pandas as pd
import pytest
import torch
from typer.testing import CliRunner

from torchcal.app import fit as pipeline
from torchcal.compensate.toolset import compensation_goal, model_tool_set_frame
from torchcal.cli import PAPER2_TOOLS_MM, app
from torchcal.app.config import load_config
from torchcal.io.csv import read_measurements
from torchcal.io.rundir import load_model
from torchcal.io.truth import load_truth
from torchcal.kinematics.transforms import pose_error
from torchcal.sim import TruthRobot

runner = CliRunner()
POSES, VAL_POSES = 30, 20


def invoke(*args):
    return runner.invoke(app, [str(a) for a in args])


pytestmark = pytest.mark.usefixtures("one_thread")  # conftest: tiny problems run faster on one thread


@pytest.fixture(scope="module")
def e2e(tmp_path_factory, one_thread):
    """One simulate + one fit through the CLI; the spy keeps the fit's in-memory result."""
    root = tmp_path_factory.mktemp("cli")
    sim = root / "sim"
    r = invoke("simulate", sim, "--identification", POSES, "--validation", VAL_POSES, "--seed", 3)
    assert r.exit_code == 0, r.output
    captured = {}
    original = pipeline.run_fit

    def spy(cfg, console=None):
        captured["result"] = original(cfg, console)
        return captured["result"]

    with pytest.MonkeyPatch.context() as mp:
        mp.setattr(pipeline, "run_fit", spy)
        r = invoke("fit", sim / "fit.yaml", "model.order=1", f"out={root / 'run'}")
    assert r.exit_code == 0, r.output
    return {"root": root, "sim": sim, "fit_output": r.output, "result": captured["result"], "run": root / "run"}


def test_simulate_writes_contract_files(e2e, fanuc):
    sim = e2e["sim"]
    ident = pd.read_csv(sim / "identification.csv")
    val = pd.read_csv(sim / "validation.csv")
    cols = ["pose", "tool"] + [f"q{i}" for i in range(1, 7)] + [f"dir{i}" for i in range(1, 7)] + ["x", "y", "z"]
    assert list(ident.columns) == cols and list(val.columns) == cols
    assert len(ident) == 3 * POSES and sorted(ident.tool.unique()) == [0, 1, 2]
    assert len(val) == VAL_POSES and set(val.tool) == {2}
    # truth.json rebuilds exactly the robot the data came from
    truth = load_truth(sim / "truth.json")
    fresh = TruthRobot.fanuc_paper2(fanuc, torch.tensor(PAPER2_TOOLS_MM) * 1e-3, 3)
    data = read_measurements(sim / "validation.csv", fanuc, 3)
    with torch.no_grad():
        assert torch.equal(truth.points(data.q, data.tool, data.direction), fresh.points(data.q, data.tool, data.direction))
        # measured = truth + joint and tracker noise: well under a millimetre, never exact
        d = (truth.points(data.q, data.tool, data.direction) - data.xyz).norm(dim=1)
    assert 0 < d.max() < 5e-4
    cfg = load_config(sim / "fit.yaml")
    assert Path(cfg.data.identification) == (sim / "identification.csv").resolve()
    assert Path(cfg.data.truth) == (sim / "truth.json").resolve()
    # refuses to overwrite silently
    r = invoke("simulate", sim, "--identification", 5, "--validation", 5)
    assert r.exit_code == 2 and "--force" in r.output


def test_fit_writes_the_run_directory(e2e):
    run, out = e2e["run"], e2e["fit_output"]
    for name in ("config.yaml", "versions.json", "model.pt", "metrics.json", "fit.json", "run.log", "residuals.csv",
                 "plots/joint_errors.png", "plots/residuals_identification.png", "plots/residuals_validation.png",
                 "plots/compensation_validation.png"):
        assert (run / name).is_file(), name
    assert f"run directory: {run}" in out
    assert "Table 6 layout" in out and "Table 7 layout" in out
    metrics = json.loads((run / "metrics.json").read_text())
    assert [(r["set"], r["residual"]) for r in metrics["table6"]] == [
        ("Identification", "Nominal"), ("Identification", "Modeled"), ("Validation", "Nominal"), ("Validation", "Modeled")]
    assert [r["residual"] for r in metrics["table7"]] == ["Nominal", "Modeled", "Compensated"]
    nominal, modeled = metrics["table6"][2], metrics["table6"][3]
    # an order-1 model removes most of the FANUC's millimetres of error on unseen poses
    assert modeled["mean"] < 0.2 * nominal["mean"]
    assert modeled["mean_decrease"] == pytest.approx(100 * (1 - modeled["mean"] / nominal["mean"]))
    fit = json.loads((run / "fit.json").read_text())
    assert fit["converged"] and fit["pinned"] == len(fit["pinned_names"]) > 0
    versions = json.loads((run / "versions.json").read_text())
    assert versions["torch"] == torch.__version__
    # config.yaml is complete and resolved: it loads as a config of its own and names the same inputs
    again = load_config(run / "config.yaml")
    assert Path(again.data.identification) == (e2e["sim"] / "identification.csv").resolve()
    assert again.model.order == 1 and again.seed == 3


def test_compensation_csv_recomputes_table_7(e2e):
    """Every number of Table 7's compensated row from compensation.csv: the mean and max of its residuals, the flag
    count, and the compensated commands are the model's compensation of the nominal ones (recomputed here)."""
    from torchcal.compensate import compensate

    run = e2e["run"]
    metrics = json.loads((run / "metrics.json").read_text())
    rows = pd.read_csv(run / "compensation.csv", keep_default_na=False)
    val = pd.read_csv(e2e["sim"] / "validation.csv")
    assert len(rows) == len(val)
    comp = [r for r in metrics["table7"] if r["residual"] == "Compensated"][0]
    assert rows.compensated_mm.mean() == pytest.approx(comp["mean"], rel=1e-9)
    assert rows.compensated_mm.max() == pytest.approx(comp["max"], rel=1e-9)
    flagged = ~(rows.converged.astype(str).eq("True") & rows.within_limits.astype(str).eq("True"))
    assert int(flagged.sum()) == metrics["compensation"]["flagged"]
    assert all((r == "") != bool(f) for r, f in zip(rows.reason, flagged))
    cols = [f"q{i}" for i in range(1, 7)]
    q = torch.tensor(rows[cols].to_numpy()[:20] * math.pi / 180)
    d = torch.tensor(rows[[f"dir{i}" for i in range(1, 7)]].to_numpy()[:20], dtype=torch.float64)
    res = compensate(e2e["result"].model, q, d)
    again = res.q.numpy() * 180 / math.pi
    assert abs(again - rows[[c + "_compensated" for c in cols]].to_numpy()[:20]).max() < 1e-8


def test_reloaded_model_reproduces_in_memory_model(e2e, fanuc):
    model = e2e["result"].model
    back = load_model(e2e["run"])
    data = read_measurements(e2e["sim"] / "identification.csv", fanuc, 3)
    with torch.no_grad():
        assert torch.equal(back.points(data.q, data.tool, data.direction), model.points(data.q, data.tool, data.direction))
        assert torch.equal(back.points(data.q, data.tool), model.points(data.q, data.tool))


def test_predict_equals_model_points(e2e, fanuc):
    root = e2e["root"]
    val = pd.read_csv(e2e["sim"] / "validation.csv")
    inp = val.drop(columns=["pose", "x", "y", "z"])
    inp.insert(0, "label", [f"p{i}" for i in range(len(inp))])
    inp.to_csv(root / "predict_in.csv", index=False)
    r = invoke("predict", e2e["run"], root / "predict_in.csv", root / "predicted.csv")
    assert r.exit_code == 0, r.output
    out = pd.read_csv(root / "predicted.csv")
    assert list(out.columns) == list(inp.columns) + ["x", "y", "z", "outside_data"]
    assert list(out.label) == list(inp.label)
    q = read_measurements(e2e["sim"] / "validation.csv", fanuc, 3)  # same commands, as SI
    with torch.no_grad():
        p_mm = e2e["result"].model.points(q.q, q.tool, q.direction) * 1000.0
    assert np.allclose(out[["x", "y", "z"]].to_numpy(), p_mm.numpy(), rtol=0, atol=1e-7)
    # and it predicts the measured points far better than the nominal robot (which misses by ~5 mm)
    with torch.no_grad():
        nominal_mm = e2e["result"].model.nominal_points(q.q, q.tool).numpy() * 1000.0
    measured = val[["x", "y", "z"]].to_numpy()
    err = np.linalg.norm(out[["x", "y", "z"]].to_numpy() - measured, axis=1)
    err_nominal = np.linalg.norm(nominal_mm - measured, axis=1)
    assert err.mean() < 0.2 * err_nominal.mean() and err.max() < 0.4 * err_nominal.max()  # order 1 on 30 poses: ~0.5 mm
    # a measured file works as input too: its x, y, z are replaced in place, everything else kept
    r = invoke("predict", e2e["run"], e2e["sim"] / "validation.csv", root / "predicted2.csv")
    assert r.exit_code == 0, r.output
    out2 = pd.read_csv(root / "predicted2.csv")
    assert list(out2.columns) == list(val.columns) + ["outside_data"]
    assert out2.drop(columns=["x", "y", "z", "outside_data"]).equals(val.drop(columns=["x", "y", "z"]))
    assert np.allclose(out2[["x", "y", "z"]].to_numpy(), p_mm.numpy(), rtol=0, atol=1e-7)


def test_compensate_lands_on_the_nominal_flange(e2e, fanuc):
    root = e2e["root"]
    val = pd.read_csv(e2e["sim"] / "validation.csv")
    inp = val[[f"q{i}" for i in range(1, 7)] + [f"dir{i}" for i in range(1, 7)]].copy()
    inp["id"] = [f"c{i}" for i in range(len(inp))]
    inp.to_csv(root / "comp_in.csv", index=False)
    r = invoke("compensate", e2e["run"], root / "comp_in.csv", root / "compensated.csv")
    assert r.exit_code == 0, r.output
    out = pd.read_csv(root / "compensated.csv")
    assert len(out) == len(inp) and list(out.id) == list(inp.id)
    assert {"converged", "iterations", "within_limits", "max_dq"} <= set(out.columns)
    assert (out.iterations >= 1).all()
    model = e2e["result"].model
    q_nom = torch.tensor(inp[[f"q{i}" for i in range(1, 7)]].to_numpy()) * torch.pi / 180
    q_new = torch.tensor(out[[f"q{i}" for i in range(1, 7)]].to_numpy()) * torch.pi / 180
    s = torch.tensor(inp[[f"dir{i}" for i in range(1, 7)]].to_numpy(), dtype=torch.float64)
    ok = torch.tensor(out.converged.astype(bool).to_numpy())
    # the small order-1 model of this run has large errors: a row near the stretched elbow may be out of the
    # calibrated arm's reach, and is flagged rather than swung; every other row converges
    assert int(ok.sum()) >= len(out) - 2
    if not ok.all():  # a flagged row is justified: the unbounded solver needs more than 5 deg there, or fails too
        from torchcal.compensate import compensate

        free = compensate(model, q_nom[~ok], s[~ok], max_step=None, max_correction=None)
        need = (free.q - q_nom[~ok]).abs().max(dim=1).values
        assert ((~free.converged) | (need > torch.pi / 36)).all()
    assert f"{int((~ok).sum())} of {len(out)} commands flagged" in r.output or (ok.all() and "0 commands flagged" in r.output)
    assert np.allclose(out.max_dq, np.degrees((q_new - q_nom).abs().max(dim=1).values.numpy()), atol=1e-6)
    with torch.no_grad():  # the modeled flange on the nominal one, carried by the tool set's frame (.toolset)
        Fa = model.flange(q_new[ok], s[ok], base=False)
        Fn = compensation_goal(model, q_nom[ok])
    assert (Fa[:, :3, 3] - Fn[:, :3, 3]).norm(dim=1).max() < 1e-8  # m, after 12-digit rounding in the file
    assert (Fa[:, :3, :3] - Fn[:, :3, :3]).abs().max() < 1e-8
    assert (q_new - q_nom).abs().max() > 1e-5  # the commands did change (rad)


def test_compensate_with_a_free_tool_axis_reaches_the_tool_point_and_axis(e2e):
    """--free-tool-axis (5-DOF): with a tool column each row's identified tool point reaches the nominal one and
    the flange z axis its nominal direction; the rotation about it is left to the solver. A zero axis is refused."""
    root = e2e["root"]
    val = pd.read_csv(e2e["sim"] / "validation.csv").iloc[:60]
    inp = val[["tool"] + [f"q{i}" for i in range(1, 7)]].copy()
    inp.to_csv(root / "axis_in.csv", index=False)
    r = invoke("compensate", e2e["run"], root / "axis_in.csv", root / "axis_out.csv", "--free-tool-axis")
    assert r.exit_code == 0, r.output
    out = pd.read_csv(root / "axis_out.csv")
    ok = torch.tensor(out.converged.astype(bool).to_numpy())
    assert int(ok.sum()) >= len(out) - 2
    model = e2e["result"].model
    q_nom = torch.tensor(inp[[f"q{i}" for i in range(1, 7)]].to_numpy())[ok] * torch.pi / 180
    q_new = torch.tensor(out[[f"q{i}" for i in range(1, 7)]].to_numpy())[ok] * torch.pi / 180
    tool = torch.tensor(inp.tool.to_numpy())[ok]
    with torch.no_grad():  # in the tool set's frame (.toolset): the tool point lands on the nominal robot's, the
        # tool's z axis (the tool set's) along the nominal flange's
        Fa, Fn = model.flange(q_new, base=False), model.nominal_flange(q_nom)
        p = model.tools()[tool]
        G = model_tool_set_frame(model)
    reach = (Fa[:, :3, :3] @ p[:, :, None])[..., 0] + Fa[:, :3, 3]
    p_set = (p - G[:3, 3]) @ G[:3, :3]
    want = (Fn[:, :3, :3] @ p_set[:, :, None])[..., 0] + Fn[:, :3, 3]
    assert (reach - want).norm(dim=1).max() < 1e-8
    assert ((Fa[:, :3, :3] @ G[:3, :3])[:, :, 2] - Fn[:, :3, 2]).norm(dim=1).max() < 1e-8
    r = invoke("compensate", e2e["run"], root / "axis_in.csv", root / "axis_out2.csv", "--free-tool-axis",
               "--tool-axis", "0,0,0")
    assert r.exit_code == 2 and "--tool-axis '0,0,0'" in r.output


def test_compensate_flags_rows_and_keeps_them(e2e):
    root = e2e["root"]
    # commands on the controller's limits: corrections that push a joint outside are flagged, not dropped
    rows = pd.DataFrame([[100, 100, 100, 180, 90, 180], [-100, -30, -30, -180, -90, -180], [10, 20, 30, 40, 50, 60]],
                        columns=[f"q{i}" for i in range(1, 7)])
    rows.to_csv(root / "edge.csv", index=False)
    r = invoke("compensate", e2e["run"], root / "edge.csv", root / "edge_out.csv")
    assert r.exit_code == 0, r.output
    out = pd.read_csv(root / "edge_out.csv")
    assert len(out) == 3
    flagged = (~out.converged.astype(bool)) | (~out.within_limits.astype(bool))
    assert flagged.sum() >= 1 and not flagged.iloc[2]
    assert f"{int(flagged.sum())} of 3 commands flagged" in r.output
    # compensate's own output, flagged rows beyond the range included, reads back into predict: those rows are
    # predicted and marked, the others are unchanged
    beyond = ~out.within_limits.astype(bool)
    assert beyond.any()
    r = invoke("predict", e2e["run"], root / "edge_out.csv", root / "edge_pred.csv")
    assert r.exit_code == 0, r.output
    pred = pd.read_csv(root / "edge_pred.csv")
    tools = len(pred) // len(out)  # a commands file: every row for every tool of the run, tool-major
    assert len(pred) == tools * len(out)
    assert list(pred["within_limits"].astype(bool)) == list(~beyond) * tools
    said = " ".join(r.output.split())
    assert f"{int(beyond.sum())} of 3 rows command a joint outside the controller range" in said


def test_bad_inputs_exit_2_with_one_message(e2e, tmp_path):
    sim = e2e["sim"]
    bad = (sim / "identification.csv").read_text().splitlines()
    cells = bad[5].split(",")
    cells[3] = "oops"  # q2 of data row 5
    bad[5] = ",".join(cells)
    (tmp_path / "bad.csv").write_text("\n".join(bad) + "\n")
    r = invoke("fit", sim / "fit.yaml", f"data.identification={tmp_path / 'bad.csv'}", f"out={tmp_path / 'r'}")
    assert r.exit_code == 2
    assert "bad.csv" in r.output and "row 5 (line 6), column 'q2': 'oops' is not a finite number" in r.output
    assert "Traceback" not in r.output
    assert not (tmp_path / "r").exists()  # nothing was started

    r = invoke("fit", sim / "fit.yaml", "robot=no_such_robot")
    assert r.exit_code == 2 and "unknown robot 'no_such_robot'" in r.output
    r = invoke("predict", tmp_path, sim / "validation.csv", tmp_path / "p.csv")
    assert r.exit_code == 2 and "no model here" in r.output


@pytest.mark.parametrize("err", [OSError(30, "Read-only file system", "sim/identification.csv"),
                                 OSError(28, "No space left on device", "sim/identification.csv"),
                                 FileExistsError(17, "File exists", "sim")])
def test_storage_errors_are_one_message_not_a_traceback(tmp_path, monkeypatch, err):
    """A read-only mount, a full disk, a file where a folder belongs: the user's storage, exit 2, one line; any
    other OSError stays a traceback (a bug)."""
    import torchcal.app.simulate as simulate

    def broken(*args, **kwargs):
        raise err

    monkeypatch.setattr(simulate, "simulate_dataset", broken)
    r = invoke("simulate", tmp_path / "sim")
    assert r.exit_code == 2 and "error:" in r.output and err.strerror in r.output and "Traceback" not in r.output
    monkeypatch.setattr(simulate, "simulate_dataset", lambda *a, **k: (_ for _ in ()).throw(OSError(5, "I/O error")))
    r = invoke("simulate", tmp_path / "sim")
    assert r.exit_code == 1 and isinstance(r.exception, OSError)


def test_console_script_reports_config_errors(tmp_path):
    """The installed `torchcal` entry point: exit status 2, the key and file named, no traceback."""
    exe = Path(sys.executable).parent / "torchcal"
    if not exe.exists():
        pytest.skip("console script not installed (pip install -e .)")
    cfg = tmp_path / "fit.yaml"
    cfg.write_text("robot: fanuc_lrmate200i\ntools: [[0, 0, 100]]\ndata: {identification: x.csv}\nsolver: {mehtod: lm}\n")
    p = subprocess.run([str(exe), "fit", str(cfg)], capture_output=True, text=True, timeout=120)
    assert p.returncode == 2
    assert "unknown config key 'solver.mehtod'" in p.stderr and str(cfg) in p.stderr
    assert "Traceback" not in p.stderr + p.stdout


def test_fit_with_automatic_orders(e2e):
    """model.order=auto: orders chosen on the validation set, recorded in orders.json, used by the saved model."""
    out = e2e["root"] / "auto"
    r = invoke("fit", e2e["sim"] / "fit.yaml", "model.order=auto", "model.candidates=[0,1]", "plots=false",
               "data.truth=null", f"out={out}", "--quiet")
    assert r.exit_code == 0, r.output
    sel = json.loads((out / "orders.json").read_text())
    assert sel["criterion"] == "validation"
    assert len(sel["orders"]) == 6 and set(sel["orders"]) <= {0, 1}
    assert {tuple(row["orders"]) for row in sel["table"]} >= {(0,) * 6, (1,) * 6}
    # the chosen orders' own score (its latest linearization's), never worse than the best uniform order
    # (stage 1, Figure 11) beyond the ~0.1 % the scores of different linearization points differ by
    last = [row for row in sel["table"] if row["orders"] == sel["orders"]][-1]
    assert sel["score_mm"] == pytest.approx(last["score_mm"])
    assert sel["score_mm"] <= 1.005 * min(row["score_mm"] for row in sel["table"] if row["stage"].startswith("uniform"))
    assert json.loads((out / "metrics.json").read_text())["orders"] == sel["orders"]
    model = load_model(out)
    assert model.joint_errors.orders[:, 0].tolist() == sel["orders"]
    assert not (out / "plots").exists() and (out / "model.pt").exists()


def test_fit_with_automatic_orders_without_validation_set(e2e):
    """No validation set: the orders are chosen by leave-one-pose-out residuals of the identification data."""
    out = e2e["root"] / "auto_loo"
    r = invoke("fit", e2e["sim"] / "fit.yaml", "model.order=auto", "model.candidates=[0,1]", "plots=false",
               "data.validation=null", "data.truth=null", f"out={out}", "--quiet")
    assert r.exit_code == 0, r.output
    sel = json.loads((out / "orders.json").read_text())
    assert sel["criterion"] == "loo"
    assert {tuple(row["orders"]) for row in sel["table"]} >= {(0,) * 6, (1,) * 6}
    assert json.loads((out / "metrics.json").read_text())["orders"] == sel["orders"]


def test_fit_with_gravity_compliance(e2e, fanuc):
    """model.compliance=true: the saved model carries it; predict and compensate use it."""
    out = e2e["root"] / "compliance"
    r = invoke("fit", e2e["sim"] / "fit.yaml", "model.order=0", "model.compliance=true", "plots=false",
               f"out={out}", "--quiet")
    assert r.exit_code == 0, r.output
    model = load_model(out)
    assert model.compliance is not None and bool(model.compliance.coef.detach().abs().max() > 0)
    val = pd.read_csv(e2e["sim"] / "validation.csv")
    r = invoke("predict", out, e2e["sim"] / "validation.csv", e2e["root"] / "pc.csv")
    assert r.exit_code == 0, r.output
    q = read_measurements(e2e["sim"] / "validation.csv", fanuc, 3)
    with torch.no_grad():
        p_mm = model.points(q.q, q.tool, q.direction).numpy() * 1000.0
    assert np.allclose(pd.read_csv(e2e["root"] / "pc.csv")[["x", "y", "z"]].to_numpy(), p_mm, atol=1e-7)
    val[[f"q{i}" for i in range(1, 7)]].to_csv(e2e["root"] / "cmd.csv", index=False)
    r = invoke("compensate", out, e2e["root"] / "cmd.csv", e2e["root"] / "cc.csv")
    assert r.exit_code == 0, r.output
    cc = pd.read_csv(e2e["root"] / "cc.csv")
    ok = cc["converged"].to_numpy().astype(bool)
    assert ok.mean() > 0.9
    q_new = torch.tensor(np.deg2rad(cc[[f"q{i}" for i in range(1, 7)]].to_numpy()))
    q_nom = torch.tensor(np.deg2rad(val[[f"q{i}" for i in range(1, 7)]].to_numpy()))
    with torch.no_grad():  # (46) with the deflection, checked on the model itself
        de = pose_error(model.flange(q_new, base=False), compensation_goal(model, q_nom))
    assert float(de[torch.from_numpy(ok)].norm(dim=-1).max()) < 1e-9


def test_fit_far_tracker_with_unknown_tools_then_predict(tmp_path, fanuc):
    """A tracker 2.5 m away in its own frame, reflectors at unknown places (tools: {count: 3}, no frame):
    fit aligns first, records the frame and tools, and predict answers in the tracker's frame."""
    from dataclasses import replace

    from torchcal.identify import NoiseModel
    from torchcal.io.csv import write_measurements
    from torchcal.kinematics.transforms import homogeneous, rpy_to_matrix, so3_log
    from torchcal.sim import quasi_random_commands, simulate

    f64 = torch.float64
    frame = homogeneous(rpy_to_matrix(torch.tensor([-2.4, 0.6, 1.2], dtype=f64)), torch.tensor([-1.2, 2.1, -0.5], dtype=f64))
    assert 2.4 < float(frame[:3, 3].norm()) < 2.6
    tools = torch.tensor([[45.0, 55.0, 150.0], [60.0, -40.0, 170.0], [-35.0, -60.0, 140.0]], dtype=f64) * 1e-3
    truth = TruthRobot.fanuc_paper2(fanuc, tools, 4, base_nominal=frame)
    lim = fanuc.joint_map.limits
    ident = simulate(truth, quasi_random_commands(lim, 40, 6), [0, 1, 2], NoiseModel.paper2(), 1)
    keep = torch.arange(len(ident)) % 5 != 3  # not every reflector seen at every pose
    ident = replace(ident, q=ident.q[keep], tool=ident.tool[keep], xyz=ident.xyz[keep], direction=ident.direction[keep],
                    pose=ident.pose[keep], rows=torch.arange(1, int(keep.sum()) + 1), extra={})
    val = simulate(truth, quasi_random_commands(lim, 25, 6, skip=40), [0, 1, 2], NoiseModel.paper2(), 2)
    write_measurements(tmp_path / "identification.csv", ident, fanuc)
    write_measurements(tmp_path / "validation.csv", val, fanuc)
    (tmp_path / "fit.yaml").write_text(
        "robot: fanuc_lrmate200i\ntools: {count: 3}\n"
        "data: {identification: identification.csv, validation: validation.csv}\n"
        "model: {order: 1}\nplots: false\nout: run\n")
    r = invoke("fit", tmp_path / "fit.yaml", "--quiet")
    assert r.exit_code == 0, r.output
    run = tmp_path / "run"
    al = json.loads((run / "alignment.json").read_text())
    assert al["estimated_frame"] and al["estimated_tools"] and al["converged"]
    assert np.linalg.norm(np.array(al["frame"]["xyz_mm"]) - frame[:3, 3].numpy() * 1e3) < 5.0
    assert np.abs(np.array(al["tools_mm"]) - truth.tools().numpy() * 1e3).max() < 3.0
    assert 0.1 < al["residual_mm"]["rms"] < 5.0  # the nominal robot's errors, not a wrong frame (metres)
    metrics = json.loads((run / "metrics.json").read_text())
    assert metrics["alignment"] == al
    assert metrics["sets"]["validation"]["modeled"]["mean"] < 0.5 * metrics["sets"]["validation"]["nominal"]["mean"]
    assert "alignment: estimated the measurement frame and tool vectors" in (run / "run.log").read_text()
    model = load_model(run)
    with torch.no_grad():
        assert float(so3_log(frame[:3, :3].T @ model.base()[:3, :3]).norm()) < 5e-3
    # the run's config still says what the user wrote; the model carries the estimates
    assert dict(load_config(run / "config.yaml").tools) == {"count": 3}

    r = invoke("predict", run, tmp_path / "validation.csv", tmp_path / "predicted.csv")
    assert r.exit_code == 0, r.output
    out = pd.read_csv(tmp_path / "predicted.csv")
    with torch.no_grad():
        p_mm = model.points(val.q, val.tool, val.direction).numpy() * 1e3
    assert np.allclose(out[["x", "y", "z"]].to_numpy(), p_mm, rtol=0, atol=1e-7)
    err = np.linalg.norm(out[["x", "y", "z"]].to_numpy() - val.xyz.numpy() * 1e3, axis=1)
    # in the tracker's frame 2.5 m away, well under the nominal robot's millimetres (order 1 on 40 poses: ~0.8 mm
    # of ~3 mm: the truth's J2/J3 errors follow the commands over their 130 deg ranges, which order 1 barely bends to)
    nominal_mean = metrics["sets"]["validation"]["nominal"]["mean"]
    assert nominal_mean < 10.0 and err.mean() == pytest.approx(metrics["sets"]["validation"]["modeled"]["mean"], rel=1e-6)
    assert err.mean() < 0.35 * nominal_mean


# ------------------------------------------------------------ interrupts, faults, degenerate data
def _quick(*overrides):
    """Overrides for a fast fit: no compensation check, no plots."""
    return ["model.order=0", "data.truth=null", "plots=false", *overrides]


class _InterruptImport:
    """A meta-path finder: Ctrl-C while ``target`` is being imported; records every import tried afterwards."""

    def __init__(self, target):
        self.target, self.fired, self.after = target, False, []

    def find_spec(self, name, path=None, target=None):
        if self.fired:
            self.after.append(name)
        elif name == self.target:
            self.fired = True
            raise KeyboardInterrupt
        return None


def test_ctrl_c_during_start_up_is_one_line_and_130(e2e, monkeypatch):
    """The interrupt lands inside an import: the handler must not import anything (no circular-import error)."""
    finder = _InterruptImport("torchcal.app.fit")
    monkeypatch.delitem(sys.modules, "torchcal.app.fit")
    monkeypatch.setattr(sys, "meta_path", [finder, *sys.meta_path])
    r = invoke("fit", e2e["sim"] / "fit.yaml", f"out={e2e['root'] / 'never'}")
    assert finder.fired
    assert r.exit_code == 130, r.output
    assert r.output.strip() == "interrupted"
    assert not [n for n in finder.after if n.startswith(("torch", "torchcal"))]
    assert not (e2e["root"] / "never").exists()


def test_ctrl_c_in_a_real_process_during_imports(e2e):
    """The same in a real interpreter, through main(): status 130, one line on stderr, no traceback."""
    code = (
        "import sys\n"
        "class F:\n"
        "    def find_spec(self, name, path=None, target=None):\n"
        "        if name == 'torch':\n"
        "            raise KeyboardInterrupt\n"
        "sys.meta_path.insert(0, F())\n"
        "from torchcal.cli import main\n"
        f"main(['fit', {str(e2e['sim'] / 'fit.yaml')!r}])\n"
    )
    p = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120)
    assert p.returncode == 130, p.stderr
    assert p.stderr.strip() == "interrupted" and "Traceback" not in p.stderr + p.stdout


def test_ctrl_c_during_a_fit_names_the_partial_run(e2e, tmp_path, monkeypatch):
    def interrupted(*args, **kwargs):
        raise KeyboardInterrupt

    monkeypatch.setattr(pipeline, "identify_model", interrupted)
    out = tmp_path / "run"
    r = invoke("fit", e2e["sim"] / "fit.yaml", *_quick(f"out={out}"), "-q")
    assert r.exit_code == 130, r.output
    assert r.output.strip() == f"interrupted; the partial run directory is {out} (marked by its PARTIAL file)"
    log = (out / "run.log").read_text()
    assert "interrupted" in log and "Traceback" not in log
    assert (out / "config.yaml").is_file() and (out / "PARTIAL").is_file()


def test_a_failed_fit_names_and_marks_its_partial_run(e2e, tmp_path, monkeypatch):
    from torchcal.app.config import ConfigError

    def fails(*args, **kwargs):
        raise ConfigError("fit.yaml: key 'model.order': cannot be fitted")

    monkeypatch.setattr(pipeline, "identify_model", fails)
    out = tmp_path / "run"
    r = invoke("fit", e2e["sim"] / "fit.yaml", *_quick(f"out={out}"), "-q")
    assert r.exit_code == 2, r.output
    assert r.output.strip() == ("error: fit.yaml: key 'model.order': cannot be fitted; the partial run directory is "
                                f"{out} (marked by its PARTIAL file)")
    assert (out / "PARTIAL").is_file() and (out / "config.yaml").is_file()  # what was computed stays
    monkeypatch.undo()
    r = invoke("fit", e2e["sim"] / "fit.yaml", *_quick(f"out={out}"), "-q")
    assert r.exit_code == 0, r.output
    assert not (tmp_path / "run-2" / "PARTIAL").exists()  # a finished run is not marked


@pytest.fixture
def fast_progress(monkeypatch):
    """Progress lines at once and a heartbeat every 50 ms (defaults: 2 s delay, 1 s rate limit, 5 s heartbeat)."""
    from torchcal.io import progress_view

    monkeypatch.setattr(progress_view, "HEARTBEAT_S", 0.05)
    monkeypatch.setattr(progress_view, "DELAY_S", 0.0)
    monkeypatch.setattr(progress_view, "MIN_INTERVAL_S", 0.0)


def _heartbeat_alive():
    return any(t.name == "torchcal-progress-heartbeat" and t.is_alive() for t in threading.enumerate())


def test_fit_progress_when_output_is_not_a_terminal(e2e, tmp_path, monkeypatch, fast_progress):
    """Redirected output: plain progress lines on the console and the same in run.log, a heartbeat in a silent stage."""
    original = pipeline.evaluate_sets

    def slow(*args, **kwargs):
        time.sleep(0.3)  # a stage that reports nothing itself
        return original(*args, **kwargs)

    monkeypatch.setattr(pipeline, "evaluate_sets", slow)
    out = tmp_path / "run"
    r = invoke("fit", e2e["sim"] / "fit.yaml", *_quick(f"out={out}"))
    assert r.exit_code == 0, r.output
    log = (out / "run.log").read_text()
    for text in (r.output, log):
        assert re.search(r"identifying the model \(orders \[0, 0, 0, 0, 0, 0\], lm\): elapsed \d+\.\d s "
                         r"\[iteration \d+, cost [\d.e+]+\]", text), text
        assert re.search(r"evaluating the residuals: elapsed \d+\.\d s", text), text  # the heartbeat
    assert r.output.rstrip().splitlines()[-1] == f"run directory: {out}"  # nothing after the command's end
    assert not _heartbeat_alive()


def test_ctrl_c_while_progress_is_shown_is_one_line_and_130(e2e, tmp_path, monkeypatch, fast_progress):
    from torchcal.core import progress

    def interrupted(*args, **kwargs):
        with progress.task("a long fit"):
            time.sleep(0.25)  # heartbeat lines meanwhile
            raise KeyboardInterrupt

    monkeypatch.setattr(pipeline, "identify_model", interrupted)
    out = tmp_path / "run"
    r = invoke("fit", e2e["sim"] / "fit.yaml", *_quick(f"out={out}"))
    assert r.exit_code == 130, r.output
    lines = r.output.strip().splitlines()
    assert any(re.search(r"a long fit: elapsed \d+\.\d s", l) for l in lines), r.output
    assert lines[-1] == f"interrupted; the partial run directory is {out} (marked by its PARTIAL file)"
    assert sum("interrupted" in l for l in lines) == 1 and "Traceback" not in r.output
    assert not _heartbeat_alive()


def test_second_fit_into_the_same_out_goes_beside_the_first(e2e, tmp_path):
    out = tmp_path / "out"
    r1 = invoke("fit", e2e["sim"] / "fit.yaml", *_quick(f"out={out}"), "-q")
    r2 = invoke("fit", e2e["sim"] / "fit.yaml", *_quick(f"out={out}"), "-q")
    assert r1.exit_code == 0 and r2.exit_code == 0, r1.output + r2.output
    assert f"run directory: {out}\n" in r1.output
    assert f"run directory: {tmp_path / 'out-2'}\n" in r2.output
    assert not [p for p in out.iterdir() if p.is_dir() and p.name != "plots"]  # nothing nested in the first run
    assert (tmp_path / "out-2" / "model.pt").is_file()
    # the log says why the second run is not where out= pointed (and the first run's says nothing of the kind)
    assert f"{out} holds a run already" in (tmp_path / "out-2" / "run.log").read_text()
    assert "holds a run already" not in (out / "run.log").read_text()


def _rows(sim, fn, name, tmp_path):
    df = pd.read_csv(sim / "identification.csv")
    path = tmp_path / name
    fn(df).to_csv(path, index=False)
    return path


def test_identical_poses_say_what_the_data_cannot_determine(e2e, tmp_path):
    """Every row the same pose: the fit 'converges' but most parameters are pinned; say which, and why."""
    def same(df):
        first = df[df.pose == df.pose.iloc[0]].set_index("tool")
        out = df.copy()
        for c in [f"q{i}" for i in range(1, 7)] + [f"dir{i}" for i in range(1, 7)]:
            out[c] = df[c].iloc[0]
        for c in "xyz":
            out[c] = out["tool"].map(first[c])
        return out

    path = _rows(e2e["sim"], same, "same.csv", tmp_path)
    out = tmp_path / "run"
    r = invoke("fit", e2e["sim"] / "fit.yaml", *_quick(f"data.identification={path}", "model.order=1", f"out={out}"), "-q")
    assert r.exit_code == 0, r.output
    text = " ".join(r.output.split())  # rich wraps long lines
    assert "the data cannot determine" in text and "start values" in text
    assert "approach from one side only" in text and "'J1' (dir1: +1 only)" in text
    log = (out / "run.log").read_text()
    assert "WARNING" in log and "the data cannot determine" in log
    metrics = json.loads((out / "metrics.json").read_text())
    checks = metrics["data_checks"]
    fit_json = json.loads((out / "fit.json").read_text())
    assert checks["undetermined"] and set(checks["undetermined"]) <= set(fit_json["pinned_names"])
    assert len(checks["one_sided_backlash"]) == 6
    assert metrics["warnings"]


def test_few_rows_of_one_tool_say_unobserved_tools_and_too_few_poses(e2e, tmp_path):
    path = _rows(e2e["sim"], lambda df: df[df.tool == 0].head(5), "five.csv", tmp_path)
    out = tmp_path / "run"
    r = invoke("fit", e2e["sim"] / "fit.yaml", *_quick(f"data.identification={path}", f"out={out}"), "-q")
    assert r.exit_code == 0, r.output
    text = " ".join(r.output.split())
    assert "tools [1, 2] of the 3 in 'tools' are never measured" in text
    assert "too few poses for the model: 5 rows give 15 equations" in text
    assert "the data cannot determine" in text
    checks = json.loads((out / "metrics.json").read_text())["data_checks"]
    assert checks["unobserved_tools"] == [1, 2] and checks["equations"] == 15


def test_well_spread_data_raise_no_data_warnings(e2e):
    # order 1 against the truth's joint-dependent errors: the one warning is the residual beyond the noise model
    assert [w for w in e2e["result"].warnings if "what the noise model explains" not in w] == []
    assert e2e["result"].metrics["data_checks"]["undetermined"] == []


def test_a_residual_beyond_the_noise_model_is_said(e2e):
    """An order-1 fit of a truth with joint-dependent errors leaves a systematic error the tracker and the joints'
    repeatability do not explain: metrics.json keeps the ratio, and the warning names it and what to try."""
    from torchcal.analysis.noise_check import NOISE_RATIO_WARN

    metrics = e2e["result"].metrics
    rho = metrics["sets"]["validation"]["noise_ratio"]
    assert rho > NOISE_RATIO_WARN and metrics["sets"]["identification"]["noise_ratio"] > 1.0
    said = [w for w in metrics["warnings"] if f"the validation residual is {rho:.1f}x what the noise model" in w]
    assert len(said) == 1 and "model.order" in said[0] and "model.compliance" in said[0]
    assert json.loads((e2e["run"] / "metrics.json").read_text())["sets"]["validation"]["noise_ratio"] == rho


def _robot_yaml(tmp_path, urdf_text=None, repeatability=True):
    from torchcal.kinematics import urdf_dir

    text = (urdf_dir() / "fanuc_lrmate200i.yaml").read_text()
    urdf = urdf_dir() / "fanuc_lrmate200i.urdf"
    if urdf_text is not None:
        urdf = tmp_path / "robot.urdf"
        urdf.write_text(urdf_text)
    text = text.replace("urdf: fanuc_lrmate200i.urdf", f"urdf: {urdf}")
    if not repeatability:
        text = text[: text.index("repeatability:")]
    path = tmp_path / "robot.yaml"
    path.write_text(text)
    return path


def test_joint_without_axis_warns_that_the_description_may_not_be_the_robot(e2e, tmp_path):
    import re

    from torchcal.kinematics import urdf_dir

    xml = (urdf_dir() / "fanuc_lrmate200i.urdf").read_text()
    xml = re.sub(r'(<joint name="joint2".*?)<axis[^>]*/>', r"\1", xml, count=1, flags=re.S)
    robot = _robot_yaml(tmp_path, xml)
    out = tmp_path / "run"
    r = invoke("fit", e2e["sim"] / "fit.yaml", *_quick(f"robot={robot}", "solver.max_iter=3", f"out={out}"), "-q")
    assert r.exit_code == 0, r.output
    text = " ".join(r.output.split())
    assert "the robot description may not be the robot" in text and "without <axis>" in text
    assert "may not be the robot" in (out / "run.log").read_text()


def test_robot_without_noise_source_is_a_config_error(e2e, tmp_path):
    robot = _robot_yaml(tmp_path, repeatability=False)
    cfg = tmp_path / "fit.yaml"
    cfg.write_text("\n".join(l for l in (e2e["sim"] / "fit.yaml").read_text().splitlines() if "joint_var" not in l))
    for name in ("identification", "validation", "truth"):
        cfg.write_text(cfg.read_text().replace(f"{name}.csv", str(e2e["sim"] / f"{name}.csv"))
                       .replace(f"{name}.json", str(e2e["sim"] / f"{name}.json")))
    r = invoke("fit", cfg, f"robot={robot}", f"out={tmp_path / 'run'}")
    assert r.exit_code == 2, r.output
    assert "noise.joint_var_fwd" in r.output and "noise.joint_var_bwd" in r.output and "repeatability" in r.output
    assert not (tmp_path / "run").exists()
    # the bundled robot has one: no joint variances in the config are needed, and the log says where they came from
    out = tmp_path / "run2"
    r = invoke("fit", cfg, *_quick(f"out={out}"), "-q")
    assert r.exit_code == 0, r.output
    assert "joint variances: robot 'fanuc_lrmate200i' repeatability (Paper II, Table 5" in (out / "run.log").read_text()


def test_european_export_fits_with_a_note_in_the_log(e2e, tmp_path):
    src = (e2e["sim"] / "identification.csv").read_text().splitlines()
    eu = [line.replace(",", ";").replace(".", ",") for line in src]
    (tmp_path / "europe.csv").write_text("\n".join(eu) + "\n")
    out = tmp_path / "run"
    r = invoke("fit", e2e["sim"] / "fit.yaml", *_quick(f"data.identification={tmp_path / 'europe.csv'}", f"out={out}"), "-q")
    assert r.exit_code == 0, r.output
    assert "the header has" not in r.output and "European" in " ".join(r.output.split())
    assert "read as a European spreadsheet export" in (out / "run.log").read_text()
    plain = json.loads((e2e["run"] / "metrics.json").read_text())["sets"]["identification"]["nominal"]["mean"]
    eu_nominal = json.loads((out / "metrics.json").read_text())["sets"]["identification"]["nominal"]["mean"]
    assert eu_nominal == pytest.approx(plain, rel=1e-9)  # the same numbers were read


def test_confounded_directions_are_reported(tmp_path):
    """Poses in the quasi-random sequence's own order: the fit names the joints whose direction follows position."""
    sim = tmp_path / "seq"
    r = invoke("simulate", sim, "--identification", "60", "--validation", "20", "--pose-order", "sequence", "--order", "1")
    assert r.exit_code == 0, r.output
    r = invoke("fit", sim / "fit.yaml", "plots=false", "data.truth=null", f"out={tmp_path / 'run'}", "--quiet")
    assert r.exit_code == 0, r.output
    metrics = json.loads((tmp_path / "run" / "metrics.json").read_text())
    joints = metrics["data_checks"]["confounding"]["joints"]
    assert max(j["r2"] for j in joints) > 0.5
    assert any("confounded" in w for w in metrics["warnings"])
    # the same poses shuffled: no such warning
    shuf = tmp_path / "shuf"
    assert invoke("simulate", shuf, "--identification", "60", "--validation", "20", "--order", "1").exit_code == 0
    r = invoke("fit", shuf / "fit.yaml", "plots=false", "data.truth=null", f"out={tmp_path / 'run2'}", "--quiet")
    metrics = json.loads((tmp_path / "run2" / "metrics.json").read_text())
    assert not any("backlash and position are confounded" in w for w in metrics["warnings"])


def test_predict_a_commands_only_file_gives_every_tool(e2e, fanuc):
    """`plan-poses` writes pose, q1..qN only: predict answers for every tool of the run, tool by tool."""
    root = e2e["root"]
    val = pd.read_csv(e2e["sim"] / "validation.csv")
    inp = val.drop(columns=["tool", "x", "y", "z"]).drop_duplicates("pose").reset_index(drop=True)
    inp.to_csv(root / "commands_only.csv", index=False)
    r = invoke("predict", e2e["run"], root / "commands_only.csv", root / "predicted_all.csv")
    assert r.exit_code == 0, r.output
    out = pd.read_csv(root / "predicted_all.csv")
    model = e2e["result"].model
    T = model.tools.count
    assert len(out) == T * len(inp) and list(out.columns[:2]) == ["pose", "tool"]
    assert out.tool.tolist() == [t for t in range(T) for _ in range(len(inp))]
    q = torch.tensor(np.radians(inp[[f"q{i}" for i in range(1, 7)]].to_numpy()), dtype=torch.float64)
    d = torch.tensor(inp[[f"dir{i}" for i in range(1, 7)]].to_numpy(), dtype=torch.float64) \
        if "dir1" in inp.columns else None
    with torch.no_grad():
        want = torch.cat([model.points(q, torch.full((len(inp),), t), d) for t in range(T)]) * 1000.0
    assert np.allclose(out[["x", "y", "z"]].to_numpy(), want.numpy(), rtol=0, atol=1e-6)


def test_written_files_print_one_per_line_not_as_a_python_dict():
    from pathlib import Path

    from torchcal.cli import _written_lines

    lines = _written_lines({"linuxcnc": {"X": Path("/o/x.comp"), "Y": Path("/o/y.comp")}, "csv": Path("/o/t.csv")})
    assert lines == ["wrote linuxcnc: X: /o/x.comp", "wrote linuxcnc: Y: /o/y.comp", "wrote csv: /o/t.csv"]
    assert _written_lines(Path("/o/t.csv")) == ["wrote /o/t.csv"]


def test_a_file_without_directions_and_backlash_on_advises_turning_it_off(e2e, tmp_path):
    """Backlash needs both approach directions: without dir columns its terms are undetermined, and the advice
    is model.backlash: false, not 'spread the poses'."""
    ident = pd.read_csv(e2e["sim"] / "identification.csv")
    ident.drop(columns=[f"dir{i}" for i in range(1, 7)]).to_csv(tmp_path / "nodir.csv", index=False)
    r = invoke("fit", e2e["sim"] / "fit.yaml", "model.order=1", "model.backlash=true", "data.truth=null",
               f"data.identification={tmp_path / 'nodir.csv'}", "plots=false", "report=false",
               f"out={tmp_path / 'run'}", "-q")
    said = " ".join(r.output.split())
    assert r.exit_code == 0, r.output
    assert "are backlash terms, which need approach directions" in said and "set model.backlash: false" in said


def test_predict_says_what_it_changes(e2e, tmp_path):
    """Measured x, y, z replaced by predictions, and a file without tools predicted for every tool: both said."""
    val = pd.read_csv(e2e["sim"] / "validation.csv").iloc[:5]
    val.to_csv(tmp_path / "measured.csv", index=False)
    r = invoke("predict", e2e["run"], tmp_path / "measured.csv", tmp_path / "p1.csv")
    assert r.exit_code == 0 and "its columns x, y, z are replaced by the predictions" in r.output, r.output
    val[[f"q{i}" for i in range(1, 7)]].to_csv(tmp_path / "commands.csv", index=False)
    r = invoke("predict", e2e["run"], tmp_path / "commands.csv", tmp_path / "p2.csv")
    assert r.exit_code == 0 and "predicted for every one of the run's 3 tools (15 rows" in r.output, r.output
    assert "replaced" not in r.output


def test_commands_using_a_fit_that_did_not_converge_say_so(e2e, tmp_path):
    """A fit stopped by solver.max_iter is a finished run, but its model is the solver's last iterate: predict,
    compensate and export-urdf used it without a word (0.03 deg off the converged model's commands)."""
    out = tmp_path / "run"
    r = invoke("fit", e2e["sim"] / "fit.yaml", *_quick("model.order=2", "solver.max_iter=2", f"out={out}"), "-q")
    assert r.exit_code == 0, r.output
    assert json.loads((out / "fit.json").read_text())["converged"] is False
    cmds = tmp_path / "cmds.csv"
    cmds.write_text("q1,q2,q3,q4,q5,q6\n10,20,30,40,50,60\n-10,10,20,-30,40,-50\n")
    for args in (("predict", out, cmds, tmp_path / "p.csv"), ("compensate", out, cmds, tmp_path / "c.csv"),
                 ("export-urdf", out, tmp_path / "cal.urdf")):
        r = invoke(*args)
        assert r.exit_code == 0, r.output
        assert "did not converge" in " ".join(r.output.split()), (args[0], r.output)
    good = e2e["run"]  # the module's converged fit says nothing of the kind
    r = invoke("predict", good, cmds, tmp_path / "p_good.csv")
    assert r.exit_code == 0 and "did not converge" not in r.output


def test_a_rerun_of_a_runs_config_names_the_inputs_changed_since(e2e, tmp_path):
    """Re-running a run directory's own config.yaml on an edited file fitted it without a word; the truth (Table
    7's 'Compensated' row) and a robot file were not hashed at all."""
    import shutil

    sim = tmp_path / "sim"
    shutil.copytree(e2e["sim"], sim)
    first = tmp_path / "first"
    r = invoke("fit", sim / "fit.yaml", "model.order=0", "plots=false", f"out={first}", "-q")
    assert r.exit_code == 0, r.output
    recorded = json.loads((first / "data_hashes.json").read_text())
    assert {"data.identification", "data.validation", "data.truth"} <= set(recorded)
    r = invoke("fit", first / "config.yaml", f"out={tmp_path / 'same'}", "-q")
    assert r.exit_code == 0 and "has changed since" not in r.output
    lines = (sim / "identification.csv").read_text().splitlines()
    f = lines[10].split(",")
    f[-3] = str(float(f[-3]) + 0.5)  # one measured x moved by 0.5 mm
    lines[10] = ",".join(f)
    (sim / "identification.csv").write_text("\n".join(lines) + "\n")
    r = invoke("fit", first / "config.yaml", f"out={tmp_path / 'again'}", "-q")
    assert r.exit_code == 0, r.output
    text = " ".join(r.output.split())
    assert "data.identification" in text and "has changed since the run" in text and "data.validation (" not in text
    assert "has changed since" in (tmp_path / "again" / "run.log").read_text()


def test_a_truth_of_another_robot_is_named(e2e, tmp_path):
    """Table 7's compensated row is measured on data.truth: another seed's truth.json gave 1.3 mm there (0.05 mm
    with its own) without a word."""
    other = tmp_path / "other"
    r = invoke("simulate", other, "--identification", 20, "--validation", 20, "--seed", 4)
    assert r.exit_code == 0, r.output
    r = invoke("fit", e2e["sim"] / "fit.yaml", "model.order=0", "plots=false", f"data.truth={other / 'truth.json'}",
               f"out={tmp_path / 'run'}", "-q")
    assert r.exit_code == 0, r.output
    assert "does not describe the validation rows" in " ".join(r.output.split())
    assert "does not describe" not in e2e["fit_output"]  # its own truth: nothing to say


def test_deliverables_carry_their_provenance(e2e, tmp_path):
    """Compensated commands, predictions, a planned pose list and a calibrated URDF each get a sidecar naming the
    run and model (by sha256), the input, the options and the code: a file loaded on a controller named none."""
    from torchcal.io.rundir import file_sha256

    run = e2e["run"]
    cmds = tmp_path / "cmds.csv"
    cmds.write_text("q1,q2,q3,q4,q5,q6\n10,20,30,40,50,60\n-10,10,20,-30,40,-50\n")
    calls = {"c.csv": ("compensate", run, cmds, tmp_path / "c.csv", "--tol-deg", "1e-7"),
             "p.csv": ("predict", run, cmds, tmp_path / "p.csv"),
             "plan.csv": ("plan-poses", "fanuc_lrmate200i", 12, tmp_path / "plan.csv", "--seed", 5),
             "cal.urdf": ("export-urdf", run, tmp_path / "cal.urdf")}
    for name, args in calls.items():
        r = invoke(*args)
        assert r.exit_code == 0, (name, r.output)
        prov = json.loads((tmp_path / (name + ".provenance.json")).read_text())
        assert prov["sha256"] == file_sha256(tmp_path / name), name
        assert prov["written_by"]["torchcal_source_sha256"]
        if name == "plan.csv":
            assert prov["run_dir"] is None and prov["options"]["seed"] == 5 and prov["options"]["count"] == 12
        else:
            assert prov["run_dir"] == str(run.resolve()) and prov["model_sha256"] == file_sha256(run / "model.pt")
    c = json.loads((tmp_path / "c.csv.provenance.json").read_text())
    assert c["options"]["tol_deg"] == 1e-7 and c["options"]["input"]["sha256"] == file_sha256(cmds)


def test_rows_without_directions_on_a_backlash_model_are_named(e2e, tmp_path):
    """verify and a fit's validation set read rows without dir1..dirN as direction 0: the backlash left out (a
    verify residual 2x, model.order: auto choosing on it), unsaid; predict and compensate said it."""
    df = pd.read_csv(e2e["sim"] / "validation.csv")
    nodir = tmp_path / "v_nodir.csv"
    df.drop(columns=[f"dir{i}" for i in range(1, 7)]).to_csv(nodir, index=False)
    r = invoke("verify", e2e["run"], nodir)
    assert r.exit_code == 0, r.output
    assert "no dir1..dir6 columns" in " ".join(r.output.split())
    r = invoke("verify", e2e["run"], e2e["sim"] / "validation.csv")
    assert "no dir1..dir6" not in r.output
    r = invoke("fit", e2e["sim"] / "fit.yaml", *_quick(f"data.validation={nodir}", f"out={tmp_path / 'run'}"), "-q")
    assert r.exit_code == 0, r.output
    assert "validation set" in r.output and "no dir1..dir6 columns" in " ".join(r.output.split())


def test_verify_names_a_gross_row(e2e, tmp_path):
    """A 50 mm gross error in a verification file showed only as the max; fit names such rows, update refuses them."""
    df = pd.read_csv(e2e["sim"] / "validation.csv")
    df.loc[7, "x"] += 50.0
    df.to_csv(tmp_path / "v.csv", index=False)
    r = invoke("verify", e2e["run"], tmp_path / "v.csv")
    assert r.exit_code == 0, r.output
    text = " ".join(r.output.split())
    assert "lie far beyond the rest" in text and "row 8 (" in text and "after the fit" not in text
    r = invoke("verify", e2e["run"], e2e["sim"] / "validation.csv")
    assert "far beyond" not in r.output
