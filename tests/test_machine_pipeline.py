"""`torchcal fit` on a machine-tool config (Paper I) and `torchcal export-tables` from its run directory."""

import json
import math

import pytest
import torch
from typer.testing import CliRunner

from torchcal.cli import app
from torchcal.compensate.tables import compensation_tables
from torchcal.export.controller import read_tables_csv
from torchcal.app.config import make_config
from torchcal.io.rundir import load_model
from torchcal.app.fit import run_fit
from torchcal.sim.machine_truth import MachineTruth, simulate_machine_dataset, write_machine_csv


@pytest.fixture(scope="module")
def machine_files(tmp_path_factory):
    root = tmp_path_factory.mktemp("machine")
    data, split = simulate_machine_dataset(MachineTruth(seed=2), n_commands=70, n_interpolation=5,
                                           n_extrapolation=5, seed=2)
    write_machine_csv(root / "ident.csv", data.subset(split["identification"]))
    write_machine_csv(root / "val.csv", data.subset(torch.cat([split["interpolation"], split["extrapolation"]])))
    return root


def _config(root, **extra):
    values = {"robot": "five_axis_xyzcb", "tools": [[0, 0, 402.9], [0, 0, 500.9]],
              "model": {"kind": "axis_perturbation", "order": 2},
              "data": {"identification": "ident.csv", "validation": "val.csv"},
              "noise": {"sigma_m": 0.02}, "plots": False, "out": "run"}
    for k, v in extra.items():
        values[k] = v
    return make_config(values, base_dir=root)


def test_constrained_machine_run_meets_its_bound_and_exports_tables(machine_files, one_thread):
    free = run_fit(_config(machine_files, out=str(machine_files / "free")))
    assert free.metrics["sets"]["validation"]["modeled"]["mean"] < free.metrics["sets"]["validation"]["nominal"]["mean"]
    c_mm = 0.2
    from torchcal.identify.constrained import max_slope_of
    from torchcal.identify.slope import slope_points

    free_model = load_model(free.run_dir)
    # the bound binds: the unconstrained model's slope exceeds it somewhere in the axis space
    assert max_slope_of(free_model, slope_points(free_model.command_limits, 256, 5)) * 1e3 > 1.5 * c_mm
    res = run_fit(_config(machine_files, constraint={"c": c_mm, "points": 256, "check_points": 256},
                          out=str(machine_files / "con")))
    summary = json.loads((res.run_dir / "constraint.json").read_text())
    assert summary["c"] == pytest.approx(c_mm)
    # the bound holds at the penalty points to its tolerance, and near it at points the fit never saw
    assert summary["result"]["max_slope_mm"] <= c_mm * 1.01
    assert summary["result"]["max_slope_check_mm"] <= c_mm * 1.05
    model = load_model(res.run_dir)
    out = machine_files / "tables.csv"
    r = CliRunner().invoke(app, ["export-tables", str(res.run_dir), str(out), "--points", "41"])
    assert r.exit_code == 0, r.output
    back = read_tables_csv(out, model.axis_errors.axis_names, model.axis_errors.prismatic)
    ref = compensation_tables(model, 41)
    assert [t.name for t in back] == [t.name for t in ref]
    for a, b in zip(back, ref):  # mm / deg on file, 1e-10 mm printed digits
        assert torch.allclose(a.correction, b.correction, atol=1e-12)
        assert torch.allclose(a.input, b.input, atol=1e-12)


def test_export_tables_refuses_a_robot_run(machine_files, tmp_path):
    r = CliRunner().invoke(app, ["export-tables", str(tmp_path), str(tmp_path / "t.csv")])
    assert r.exit_code == 2 and "no model here" in r.output


@pytest.mark.parametrize("call", [2, 3])
def test_an_interrupted_constraint_sweep_keeps_the_bounds_it_fitted(machine_files, monkeypatch, call):
    """Ctrl-C in the c: auto run's second fit (the sweep's first bound) or third (here the final fit: the sweep
    stops past the knee at 0.4 mm): the run ends interrupted, and constraint.json holds the bounds fitted by then
    with their residuals."""
    import torchcal.identify.constrained as constrained
    from conftest import ctrl_c_on_call

    ctrl_c_on_call(monkeypatch, constrained, "fit_constrained", call=call)
    bounds = []  # the c of every fit_constrained call, the interrupted one last
    stopping = constrained.fit_constrained
    monkeypatch.setattr(constrained, "fit_constrained",
                        lambda m, d, c, *a, **k: (bounds.append(c), stopping(m, d, c, *a, **k))[1])
    out = machine_files / f"cut{call}"
    with pytest.raises(KeyboardInterrupt):
        run_fit(_config(machine_files, constraint={"c": "auto", "points": 64, "check_points": 64,
                                                   "sweep": [0.4, 0.2, 0.1]}, out=str(out)))
    summary = json.loads((out / "constraint.json").read_text())
    assert summary["interrupted"] is True and summary["mode"] == "auto"
    assert [r["c_mm"] for r in summary["sweep"]] == [None, pytest.approx(0.4)][:call - 1]  # inf is written as null
    assert all(r["sub_mean_mm"] > 0 for r in summary["sweep"])
    assert (out / "PARTIAL").exists()
    # the interrupted call: the sweep's 0.4 mm bound (call 2), or the final fit at the knee, inf (call 3: 0.4 mm was
    # past it), not the sweep's next bound, which would leave the same two rows
    assert len(bounds) == call and bounds[0] == math.inf
    assert bounds[-1] == (pytest.approx(0.4e-3) if call == 2 else math.inf)
