"""The calibration report of a real (tiny) fit: self-contained, the run's own numbers, honest gaps, Chromium renders it."""

import html
import json
import re
import shutil
import subprocess
from pathlib import Path

import numpy as np
import pandas as pd
import pytest
from typer.testing import CliRunner

from torchcal import TorchcalError
from torchcal.cli import app
from torchcal.report import MAX_REPORT_BYTES, ReportError, write_report

runner = CliRunner()
POSES, VAL_POSES = 30, 20

pytestmark = pytest.mark.usefixtures("one_thread")  # conftest: tiny problems run faster on one thread


def invoke(*args):
    return runner.invoke(app, [str(a) for a in args])


@pytest.fixture(scope="module")
def run(tmp_path_factory, one_thread):
    """simulate + fit (order 1, plots on, with a truth: the compensation check runs) -> the run directory."""
    root = tmp_path_factory.mktemp("report")
    sim = root / "sim"
    r = invoke("simulate", sim, "--identification", POSES, "--validation", VAL_POSES, "--seed", 3)
    assert r.exit_code == 0, r.output
    r = invoke("fit", sim / "fit.yaml", "model.order=1", f"out={root / 'run'}", "-q")
    assert r.exit_code == 0, r.output
    # the report `torchcal fit` wrote itself, kept before the fixtures below write theirs
    (root / "fit_report.html").write_bytes((root / "run" / "report.html").read_bytes())
    return root / "run"


def test_fit_writes_the_report_of_a_finished_run(run):
    """`torchcal fit` writes report.html by default, after the run is complete: no 'did not finish' banner."""
    text = (run.parent / "fit_report.html").read_text(encoding="utf-8")
    assert "Accuracy before and after calibration" in text
    assert not (run / "PARTIAL").exists() and "did not finish" not in text


def test_parameter_uncertainty_is_the_runs_parameters_csv(run, report):
    """Every free parameter's σ shown is parameters.csv's (Laplace std the fit wrote, mm / deg), 2 digits."""
    import csv

    _, text = report
    with (run / "parameters.csv").open(newline="") as f:
        rows = list(csv.DictReader(f))
    assert rows and all(float(r["std"]) > 0 for r in rows)
    for r in rows[:25]:
        assert f'<td>{r["name"]}</td><td class="n">' in text
        cell = f'<td class="n">{float(r["std"]):.2g}</td>'
        row_start = text.index(f'<td>{r["name"]}</td>')
        assert cell in text[row_start: row_start + 300], r["name"]


@pytest.fixture(scope="module")
def report(run):
    path = write_report(run)
    return path, path.read_text(encoding="utf-8")


def _cells(text: str) -> dict[str, tuple[float, str]]:
    """data-key -> (exact value, the text shown) of every number the report marks."""
    found = re.findall(r'<td class="n" data-key="([^"]+)" data-value="([^"]+)">([^<]*)</td>', text)
    return {k: (float(v), html.unescape(shown)) for k, v, shown in found}


def test_report_is_written_beside_the_run_and_self_contained(run, report):
    path, text = report
    assert path == run / "report.html" and text.startswith("<!DOCTYPE html>")
    assert path.stat().st_size <= MAX_REPORT_BYTES
    assert "<script" not in text.lower() and "http://" not in text and "https://" not in text
    # every src / href of the page is inline: data: URIs (images) or anchors
    for attr, value in re.findall(r'\b(src|href)\s*=\s*"([^"]*)"', text):
        assert value.startswith(("data:", "#")), (attr, value[:60])
    imgs = re.findall(r"<img [^>]*src=\"([^\"]+)\"", text)
    pngs = sorted((run / "plots").glob("*.png"))
    assert len(pngs) >= 4 and len(imgs) == len(pngs)
    assert all(src.startswith("data:image/png;base64,") for src in imgs)
    for sid in ("summary", "instrument", "data", "checks", "accuracy", "histograms", "plots", "parameters", "solver",
                "compensation", "versions"):
        assert f'<section id="{sid}"' in text, sid


def test_accuracy_numbers_are_the_runs_metrics(run, report):
    """Every mean / max / Gamma 99 % of metrics.json's table6 and table7 appears exactly, shown to 0.1 um."""
    _, text = report
    metrics = json.loads((run / "metrics.json").read_text())
    cells = _cells(text)
    rows = metrics["table6"] + [r for r in metrics["table7"] if r["residual"] == "Compensated"]
    assert len(rows) == 5
    for row in rows:
        key = f"{row['set'].lower()}.{row['residual'].lower()}"
        for stat in ("mean", "max", "gamma99"):
            value, shown = cells[f"{key}.{stat}"]
            assert value == row[stat] and shown == f"{row[stat]:.4f}", (key, stat)
    # RMS: recomputed here from residuals.csv with numpy (the report sums with math.fsum)
    res = pd.read_csv(run / "residuals.csv")
    for set_name in ("identification", "validation"):
        for col, kind in (("nominal_mm", "nominal"), ("modeled_mm", "modeled")):
            want = float(np.sqrt(np.mean(res.loc[res.set == set_name, col].to_numpy() ** 2)))
            assert cells[f"{set_name}.{kind}.rms"][0] == pytest.approx(want, rel=1e-12)
    comp = metrics["compensation"]["compensated"]
    assert cells["compensation.compensated.mean"][0] == comp["mean"]


def test_parameters_are_the_models(run, report):
    """The constant terms shown are model.pt's values in mm / deg (checked against the raw state dict)."""
    import torch

    _, text = report
    state = torch.load(run / "model.pt", weights_only=True)["state_dict"]
    base = state["base.twist"].tolist()  # eps (rad), delta (m)
    for name, value in zip(("eps_x", "eps_y", "eps_z"), base[:3]):
        assert f"<td>base.{name}</td><td class=\"n\">{np.degrees(value):.6f}</td>" in text
    for name, value in zip(("delta_x", "delta_y", "delta_z"), base[3:]):
        assert f"<td>base.{name}</td><td class=\"n\">{value * 1000:.6f}</td>" in text


def test_missing_files_say_not_available(run, tmp_path):
    """A run without residuals, plots, model, fit record and compensation check still reports, and says what lacks."""
    bare = tmp_path / "bare"
    shutil.copytree(run, bare)
    for name in ("residuals.csv", "model.pt", "fit.json", "versions.json", "report.html"):
        (bare / name).unlink(missing_ok=True)
    shutil.rmtree(bare / "plots")
    metrics = json.loads((bare / "metrics.json").read_text())
    del metrics["compensation"], metrics["data_checks"]
    (bare / "metrics.json").write_text(json.dumps(metrics))
    text = write_report(bare).read_text()

    def section(sid):
        return re.search(rf'<section id="{sid}".*?</section>', text, re.S).group(0)

    assert "not available" in section("histograms") and "residuals.csv" in section("histograms")
    assert "not available" in section("plots") and "<img" not in text
    assert "not available" in section("parameters") and "model.pt" in section("parameters")
    assert "not available" in section("compensation")
    assert "not available" in section("checks")
    assert "not available" in section("versions") and "versions.json" in section("versions")
    assert "RMS: not available" in section("accuracy")
    # the accuracy numbers still come from metrics.json
    assert _cells(text)["validation.modeled.mean"][0] == metrics["sets"]["validation"]["modeled"]["mean"]


def test_the_page_says_which_code_rendered_it(run, tmp_path):
    """`torchcal report RUN_DIR` renders an archived run with the code installed now; the page showed only the
    run's versions, so a report re-rendered by newer code looked like the original."""
    from torchcal.io.provenance import source_sha256

    text = html.unescape(write_report(run).read_text())
    assert f"torchcal source sha256 {source_sha256()[:12]}... (the code that ran the fit)" in text
    other = tmp_path / "other"
    shutil.copytree(run, other)
    v = json.loads((other / "versions.json").read_text())
    v["torchcal_source_sha256"] = "0" * 64  # a run made by other code
    (other / "versions.json").write_text(json.dumps(v))
    assert "(other code than the run's)" in html.unescape(write_report(other).read_text())


def test_without_metrics_json_the_warnings_are_unknown_not_absent(run, tmp_path):
    """The run's warnings live in metrics.json: a report regenerated without it must not say 'no warnings'."""
    bare = tmp_path / "nometrics"
    shutil.copytree(run, bare)
    (bare / "metrics.json").unlink()
    (bare / "report.html").unlink()
    text = write_report(bare).read_text()
    assert "warnings unknown: metrics.json is missing" in text or "metrics.json" in text
    assert "No warnings: the run raised none" not in text and ">no warnings<" not in text


def test_a_set_without_a_gamma_fit_or_a_worse_model_still_reports(run, tmp_path):
    """One validation row has no Gamma 99 % (null in metrics.json): the report shows '–'; a model worse than the
    nominal robot is said to be worse, not '-27.5 % less'."""
    odd = tmp_path / "odd"
    shutil.copytree(run, odd)
    (odd / "report.html").unlink()
    metrics = json.loads((odd / "metrics.json").read_text())
    for r in metrics["table6"]:
        if r.get("set") == "Validation":
            r["gamma99"] = None
            if str(r.get("residual")).startswith("Modeled"):
                r["mean_decrease"] = -27.5
    (odd / "metrics.json").write_text(json.dumps(metrics))
    text = write_report(odd).read_text()
    assert "27.5 % more: worse than before" in text and "-27.5 % less" not in text
    card = re.search(r"Gamma 99 %, held-out validation</div><div class=\"v\">(.*?)</div>", text)
    assert card is not None and card.group(1) == "–"


@pytest.mark.parametrize("estimated", [False, True])
def test_tools_say_whether_the_alignment_estimated_them(run, tmp_path, estimated):
    """alignment.json lists the tools either way; only where it estimated them may the report say so."""
    bare = tmp_path / "aligned"
    shutil.copytree(run, bare, ignore=shutil.ignore_patterns("plots", "report.html"))
    tools = [[60.5, 80.25, 120.0], [10.0, -20.0, 100.0]]
    (bare / "alignment.json").write_text(json.dumps({"estimated_frame": True, "estimated_tools": estimated,
                                                      "tools_mm": tools}))
    text = write_report(bare).read_text()
    if estimated:
        assert "60.500, 80.250, 120.000 mm (estimated from the data by the alignment" in text
    else:
        assert "estimated from the data" not in text and "mm (flange frame, from the config" in text


def test_strings_from_files_are_escaped(run, tmp_path):
    bare = tmp_path / "evil"
    shutil.copytree(run, bare, ignore=shutil.ignore_patterns("plots", "model.pt", "report.html"))
    metrics = json.loads((bare / "metrics.json").read_text())
    metrics["warnings"] = ['<script>alert("x")</script> & <img src=x>']
    (bare / "metrics.json").write_text(json.dumps(metrics))
    text = write_report(bare, out=tmp_path / "evil.html").read_text()
    assert "<script" not in text and "<img src=x>" not in text
    assert "&lt;script&gt;alert(&quot;x&quot;)&lt;/script&gt; &amp; &lt;img src=x&gt;" in text
    assert not (bare / "report.html").exists()  # out= was honoured


def test_not_a_run_directory_is_a_clear_error(tmp_path):
    (tmp_path / "notes.txt").write_text("hello")
    with pytest.raises(ReportError, match=re.escape(str(tmp_path))) as info:
        write_report(tmp_path)
    assert isinstance(info.value, TorchcalError) and "not a run directory" in str(info.value)
    with pytest.raises(ReportError, match="not a folder"):
        write_report(tmp_path / "absent")
    assert not (tmp_path / "report.html").exists()


def _chromium():
    return shutil.which("chromium") or shutil.which("chromium-browser")


@pytest.mark.skipif(_chromium() is None, reason="no chromium / chromium-browser on PATH (Debian package 'chromium')")
def test_chromium_renders_the_report(report, tmp_path):
    """Headless Chromium loads the page with no console error, and its screenshot is not blank."""
    from PIL import Image

    path, _ = report
    shot = tmp_path / "report.png"
    base = [_chromium(), "--headless", "--disable-gpu", "--no-sandbox", "--hide-scrollbars",
            f"--user-data-dir={tmp_path / 'profile'}"]
    proc = subprocess.run(base + ["--enable-logging=stderr", "--v=0", f"--screenshot={shot}",
                                  "--window-size=1280,2000", path.as_uri()],
                          capture_output=True, text=True, timeout=120)
    assert shot.is_file(), proc.stderr[-2000:]
    console = [line for line in proc.stderr.splitlines() if "CONSOLE" in line or "Uncaught" in line]
    assert not console, console
    dom = subprocess.run(base + ["--dump-dom", path.as_uri()], capture_output=True, text=True, timeout=120)
    assert dom.returncode == 0 and "Accuracy before and after calibration" in dom.stdout
    pixels = np.asarray(Image.open(shot).convert("L"), dtype=np.float64)
    assert pixels.shape == (2000, 1280)
    assert pixels.std() > 10.0 and (pixels < 128).mean() > 0.005  # text and tables drawn, not a white page
