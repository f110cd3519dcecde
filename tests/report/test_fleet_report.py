"""The fleet report of a real (small) `torchcal fleet` run: the run's own numbers, the fleet's features behind each
finding (against the unit models themselves), honest gaps, self-contained."""

import csv
import html
import json
import math
import re
import shutil

import pytest
import torch
from typer.testing import CliRunner

import torchcal
import torchcal.sim
from torchcal.cli import app
from torchcal.identify.fleet import joint_features
from torchcal.io.rundir import load_model
from torchcal.report import render_report
from torchcal.sim.fleet import fleet_truths

TOOLS = torch.tensor([[0.033, 0.058, 0.161], [0.057, -0.034, 0.161], [-0.034, -0.057, 0.161]], dtype=torch.float64)
DAMAGED = 3

pytestmark = pytest.mark.usefixtures("one_thread")


@pytest.fixture(scope="module")
def fleet_run(tmp_path_factory, one_thread):
    """10 simulated FANUCs (unit 3 with a damaged J3 gearbox), validation files for all but unit 9, and one unit
    whose file has a cell that is no number -> the run directory of `torchcal fleet`."""
    from torchcal.app.fleet import run_fleet
    from torchcal.io.csv import write_measurements

    root = tmp_path_factory.mktemp("fleet_report")
    robot = torchcal.load_robot("fanuc_lrmate200i")
    noise = torchcal.NoiseModel.from_robot(robot)
    fleet = fleet_truths(robot, TOOLS, 10, 0, [DAMAGED])
    lim = robot.joint_map.limits
    q = torchcal.sim.quasi_random_commands(lim, 70, 0)
    qv = torchcal.sim.quasi_random_commands(lim, 20, 5)
    (root / "ident").mkdir()
    (root / "val").mkdir()
    for k, t in enumerate(fleet.truths):
        write_measurements(root / "ident" / f"unit{k:02d}.csv", torchcal.simulate(t, q, [0, 1, 2], noise, 10 + k), robot)
        if k != 9:
            write_measurements(root / "val" / f"unit{k:02d}.csv", torchcal.simulate(t, qv, [0], noise, 50 + k), robot)
    lines = (root / "ident" / "unit00.csv").read_text().splitlines()
    cells = lines[4].split(",")
    cells[-1] = "n/a<b>"
    lines[4] = ",".join(cells)
    (root / "ident" / "broken.csv").write_text("\n".join(lines) + "\n")
    tools = ", ".join(f"[{x * 1000:.2f}, {y * 1000:.2f}, {z * 1000:.2f}]" for x, y, z in TOOLS.tolist())
    cfg = root / "fleet.yaml"
    cfg.write_text(f"robot: fanuc_lrmate200i\ntools: [{tools}]\ndata: {{identification: ident, validation: val}}\n"
                   f"model: {{order: 3, backlash: true}}\nout: runs\n")
    res = run_fleet(cfg, out=root / "fleet-run")
    return res


def _values(text):
    return {m.group(1): float(m.group(2)) for m in re.finditer(r'data-key="([^"]+)" data-value="([^"]+)"', text)}


def _features(run_dir):
    with (run_dir / "features.csv").open(newline="") as f:
        return list(csv.DictReader(f))


def test_the_fleet_writes_its_report_self_contained(fleet_run):
    text = (fleet_run.run_dir / "report.html").read_text(encoding="utf-8")
    assert "Fleet calibration report" in text and "fanuc_lrmate200i" in text
    assert "<script" not in text and "http://" not in text and "https://" not in text
    fleet = json.loads((fleet_run.run_dir / "fleet.json").read_text())
    for u in fleet["units"]:
        assert f"<td>{u['unit']}</td>" in text
    bad = next(u for u in fleet["units"] if u["unit"] == "broken")
    assert bad["status"] == "failed" and html.escape(bad["reason"], quote=True) in text  # escaped, not markup
    assert "<b>" not in text.split("Every unit")[1].split("</table>")[0]
    assert "for 2 unit(s): broken, unit09 (their validation columns stay empty)" in html.unescape(text)  # the warning
    # the broken unit's warning keeps its second line, where the row and the column are (only its first was shown)
    warned = text.split('class="warnings">')[1].split("</ul>")[0]
    assert "broken.csv" in warned and "column &#x27;z&#x27;" in warned and "row 4" in warned


def test_the_reports_numbers_are_the_runs(fleet_run):
    text = (fleet_run.run_dir / "report.html").read_text(encoding="utf-8")
    shown = _values(text)
    fleet = json.loads((fleet_run.run_dir / "fleet.json").read_text())
    fitted = [u for u in fleet["units"] if u["status"] == "fitted"]
    assert len(fitted) == 10
    for u in fitted:
        assert shown[f"{u['unit']}/identification_mean_mm"] == u["identification_mean_mm"]
        assert shown[f"{u['unit']}/identification_max_mm"] == u["identification_max_mm"]
        if u["unit"] != "unit09":
            assert shown[f"{u['unit']}/validation_mean_mm"] == u["validation_mean_mm"]
    assert "unit09/validation_mean_mm" not in shown


def test_flagged_units_show_the_features_of_their_models(fleet_run):
    """The damaged unit is flagged on joint 3; every feature value in features.csv (and in the report's table and
    figure) is joint_features of that unit's saved model, rad -> deg; a row is flagged exactly where its value
    exceeds its flag level."""
    run = fleet_run.run_dir
    text = (run / "report.html").read_text(encoding="utf-8")
    rows = _features(run)
    flagged = {r["unit"] for r in rows if r["flagged"] == "True"}
    assert flagged == {f"unit{DAMAGED:02d}"}
    assert {r["joint"] for r in rows if r["flagged"] == "True"} == {"joint3"}
    models = {}
    for r in rows:
        if r["unit"] not in models:
            models[r["unit"]] = joint_features(load_model(run / "units" / r["unit"]))
        j = int(r["joint"].removeprefix("joint")) - 1
        assert r["value_unit"] == "deg"
        assert float(r["value"]) == pytest.approx(math.degrees(float(models[r["unit"]][r["feature"]][j])), rel=1e-8)
        assert (r["flagged"] == "True") == (float(r["value"]) > float(r["flag_level"]))
    shown = _values(text)
    for r in rows:
        if r["flagged"] == "True":
            assert shown[f"{r['unit']}/{r['joint']}/{r['feature']}"] == pytest.approx(float(r["value"]), rel=1e-8)
    dots = re.findall(r'<circle [^>]*data-name="([^"]+)" data-value="([^"]+)"', text)
    assert len(dots) == len(rows)
    assert sorted((n, round(float(v), 6)) for n, v in dots) == sorted((r["unit"], round(float(r["value"]), 6))
                                                                      for r in rows)


def test_a_fleet_run_missing_files_says_so(fleet_run, tmp_path):
    copy = tmp_path / "copy"
    shutil.copytree(fleet_run.run_dir, copy)
    (copy / "features.csv").unlink()
    (copy / "versions.json").unlink()
    text = render_report(copy)
    assert "the fleet&#x27;s joint features: not available (features.csv not in the run directory" in text
    assert "versions: not available" in text
    assert f"unit{DAMAGED:02d}: joint3" in text  # the findings fleet.json keeps are still listed


def test_a_fleet_run_that_stopped_early_gets_the_fleet_report(fleet_run, tmp_path):
    """A fleet killed before it wrote fleet.json (config.yaml, run.log, PARTIAL left) is still reported as a
    fleet, saying what is missing, not as one robot's calibration without a model."""
    copy = tmp_path / "cut"
    copy.mkdir()
    for name in ("config.yaml", "run.log", "versions.json"):
        shutil.copy(fleet_run.run_dir / name, copy / name)
    (copy / "PARTIAL").write_text("did not finish")
    text = render_report(copy)
    assert "Fleet calibration report" in text and "Calibration report —" not in text
    assert "fleet summary: not available" in text


def test_report_command_on_a_fleet_run(fleet_run, tmp_path):
    out = tmp_path / "again.html"
    res = CliRunner().invoke(app, ["report", str(fleet_run.run_dir), "--out", str(out)])
    assert res.exit_code == 0, res.output
    assert "Fleet calibration report" in out.read_text(encoding="utf-8")


@pytest.mark.skipif((shutil.which("chromium") or shutil.which("chromium-browser")) is None,
                    reason="no chromium / chromium-browser on PATH (Debian package 'chromium')")
def test_chromium_renders_the_fleet_report(fleet_run, tmp_path):
    """Headless Chromium loads the page with no console error, the strip charts' dots are in its DOM, and its
    screenshot is not blank."""
    import subprocess

    import numpy as np
    from PIL import Image

    exe = shutil.which("chromium") or shutil.which("chromium-browser")
    path = fleet_run.run_dir / "report.html"
    shot = tmp_path / "fleet.png"
    base = [exe, "--headless", "--disable-gpu", "--no-sandbox", "--hide-scrollbars", f"--user-data-dir={tmp_path / 'p'}"]
    proc = subprocess.run(base + ["--enable-logging=stderr", "--v=0", f"--screenshot={shot}", "--window-size=1280,1600",
                                  path.as_uri()], capture_output=True, text=True, timeout=120)
    assert shot.is_file(), proc.stderr[-2000:]
    assert not [line for line in proc.stderr.splitlines() if "CONSOLE" in line or "Uncaught" in line]
    dom = subprocess.run(base + ["--dump-dom", path.as_uri()], capture_output=True, text=True, timeout=120)
    assert dom.returncode == 0 and dom.stdout.count("<circle") == len(_features(fleet_run.run_dir))
    pixels = np.asarray(Image.open(shot).convert("L"), dtype=np.float64)
    assert pixels.std() > 10.0 and (pixels < 128).mean() > 0.005


def test_fleet_command_lists_the_units_that_need_a_look(fleet_run, tmp_path, monkeypatch):
    """`torchcal fleet` on more units than the console table holds lists the failed and flagged ones (every unit
    stays in summary.csv), and says where the fleet report is."""
    import torchcal.cli as cli

    root = tmp_path / "f"
    src = fleet_run.run_dir.parent  # the fixture's unit files and config
    shutil.copytree(src / "ident", root / "ident")
    shutil.copy(src / "fleet.yaml", root / "fleet.yaml")
    monkeypatch.setattr(cli, "FLEET_TABLE_ROWS", 3)
    res = CliRunner().invoke(app, ["fleet", str(root / "fleet.yaml"), "data.validation=null", "--out",
                                   str(root / "run"), "-q"])
    assert res.exit_code == 0, res.output
    table = res.output.split("Fleet: 11 units")[1].split("run directory")[0]
    listed = set(re.findall(r"\b(unit\d\d|broken)\b", table))
    assert listed == {"broken", f"unit{DAMAGED:02d}"}, table
    assert "2 of 11 units shown" in " ".join(table.split())
    assert f"fleet report: {root / 'run' / 'report.html'}" in res.output
    with (root / "run" / "summary.csv").open(newline="") as f:
        assert len(list(csv.DictReader(f))) == 11


def test_a_failed_runs_traceback_stays_out_of_the_warnings():
    """Continuation lines belong to their warning; a failed run's traceback (logged as an error) is for run.log."""
    from torchcal.report.rundata import log_warnings

    log = ("2026-11-28 08:00:00 INFO start\n"
           "2026-11-28 08:00:01 WARNING unit u1: not fitted: u1.csv: 1 problem in the data:\n"
           "  - row 4 (line 5), column 'z': 'n/a' is not a finite number\n"
           "2026-11-28 08:00:02 ERROR run failed\n"
           "Traceback (most recent call last):\n"
           '  File "x.py", line 1, in <module>\n'
           "ValueError: boom\n")
    assert log_warnings(log) == ["unit u1: not fitted: u1.csv: 1 problem in the data:\n"
                                 "  - row 4 (line 5), column 'z': 'n/a' is not a finite number", "error: run failed"]
