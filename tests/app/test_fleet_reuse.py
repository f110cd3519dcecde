"""fleet.reuse: a fleet run takes the units an earlier run fitted (unchanged data, same settings) and fits only
the others; every unit is then scored and written as in a fresh run of them all."""

from __future__ import annotations

import pandas as pd
import pytest
import torch

import torchcal
import torchcal.app.fleet as fleet_app
from torchcal.core.exceptions import ConfigError
from torchcal.io.csv import write_measurements
from torchcal.sim.fleet import fleet_truths

TOOLS = torch.tensor([[0.033, 0.058, 0.161], [0.057, -0.034, 0.161], [-0.034, -0.057, 0.161]], dtype=torch.float64)
COUNT = 4


@pytest.fixture(scope="module")
def robot():
    return torchcal.load_robot("fanuc_lrmate200i")


@pytest.fixture(scope="module")
def units(robot):
    """COUNT simulated FANUCs (unit 3 with a damaged J3 gearbox), 40 poses each, their own commands."""
    noise = torchcal.NoiseModel.from_robot(robot)
    fleet = fleet_truths(robot, TOOLS, COUNT, 0, [3])
    lim = robot.joint_map.limits
    return [torchcal.simulate(t, torchcal.sim.quasi_random_commands(lim, 40 + 5 * k, k), [0, 1, 2], noise, 100 + k)
            for k, t in enumerate(fleet.truths)]


def _fleet(tmp_path, robot, units, broken=None):
    (tmp_path / "ident").mkdir(exist_ok=True)
    for k, d in enumerate(units):
        write_measurements(tmp_path / "ident" / f"unit{k:02d}.csv", d, robot)
    if broken is not None:
        _break(tmp_path / "ident" / f"unit{broken:02d}.csv")
    tools = ", ".join(f"[{x * 1000:.2f}, {y * 1000:.2f}, {z * 1000:.2f}]" for x, y, z in TOOLS.tolist())
    cfg = tmp_path / "fleet.yaml"
    cfg.write_text(f"robot: fanuc_lrmate200i\ntools: [{tools}]\ndata: {{identification: ident}}\n"
                   f"model: {{order: 2, backlash: true}}\nout: runs\n")
    return cfg


def _break(path):
    lines = path.read_text().splitlines()
    cells = lines[5].split(",")
    cells[-1] = "abc"
    lines[5] = ",".join(cells)
    path.write_text("\n".join(lines) + "\n")


def _fitted_names(monkeypatch):
    """Record the units every batched solve of the run fits."""
    seen: list[str] = []
    real = fleet_app.fit_cell

    def spy(cfg, cell, n_threads):
        seen.extend(name for name, _ in cell)
        return real(cfg, cell, n_threads)

    monkeypatch.setattr(fleet_app, "fit_cell", spy)
    return seen


def _table(run):
    from torchcal.app.fleet_summary import read_summary

    return read_summary(run).set_index("unit")


def test_only_the_failed_unit_is_fitted_and_the_fleet_is_as_if_fitted_whole(tmp_path, robot, units, monkeypatch):
    cfg = _fleet(tmp_path, robot, units, broken=2)
    first = fleet_app.run_fleet(cfg, out=tmp_path / "first").run_dir
    assert _table(first).loc["unit02", "status"] == "failed"
    write_measurements(tmp_path / "ident" / "unit02.csv", units[2], robot)  # the file mended
    whole = fleet_app.run_fleet(cfg, out=tmp_path / "whole").run_dir  # every unit fitted afresh: the reference
    seen = _fitted_names(monkeypatch)
    again = fleet_app.run_fleet(cfg, [f"fleet.reuse={first}"], out=tmp_path / "again").run_dir
    assert seen == ["unit02"]
    got, ref, then = _table(again), _table(whole), _table(first)
    assert (got["status"] == "fitted").all()
    assert got["reused_from"].notna().tolist() == [True, True, False, True]
    for name in ("unit00", "unit01", "unit03"):  # taken as the first run fitted them, to the last digit
        assert got.loc[name, "identification_mean_mm"] == then.loc[name, "identification_mean_mm"]
        assert got.loc[name, "iterations"] == then.loc[name, "iterations"]
    # the scores are the whole fleet's: the reused units and the new one judged together, as a fresh run does
    cols = ["identification_mean_mm", "outlier_score"]
    assert (got[cols] - ref[cols]).abs().max().max() < 1e-6 * ref[cols].abs().max().max()
    assert got["flagged"].tolist() == ref["flagged"].tolist() and got.loc["unit03", "flagged"]  # the damaged J3
    feats = [pd.read_csv(r / "features.csv") for r in (again, whole)]  # the same file, row for row
    assert list(feats[0]["unit"]) == list(feats[1]["unit"])
    assert (feats[0]["robust_z"] - feats[1]["robust_z"]).abs().max() < 1e-6 * feats[1]["robust_z"].abs().max()
    a = torchcal.io.load_model(again / "units" / "unit01")
    b = torchcal.io.load_model(first / "units" / "unit01")
    assert all(torch.equal(a.state_dict()[k], b.state_dict()[k]) for k in b.state_dict())


def test_a_unit_whose_data_changed_is_fitted_again(tmp_path, robot, units, monkeypatch):
    cfg = _fleet(tmp_path, robot, units)
    first = fleet_app.run_fleet(cfg, out=tmp_path / "first").run_dir
    d = units[1].subset(torch.arange(len(units[1]) - 3))  # re-measured: three rows fewer
    write_measurements(tmp_path / "ident" / "unit01.csv", d, robot)
    seen = _fitted_names(monkeypatch)
    res = fleet_app.run_fleet(cfg, [f"fleet.reuse={first}"], out=tmp_path / "again")
    assert seen == ["unit01"]
    assert any("unit01" in w and "changed" in w for w in res.warnings)
    assert _table(res.run_dir).loc["unit01", "rows"] == len(d)


def test_validation_added_later_refits_nothing_and_a_unit_without_its_hashes_is_said(tmp_path, robot, units,
                                                                                       monkeypatch):
    cfg = _fleet(tmp_path, robot, units)
    first = fleet_app.run_fleet(cfg, out=tmp_path / "first").run_dir
    (tmp_path / "val").mkdir()
    for k, d in enumerate(units):  # validation files added a year later: evaluated, no unit refitted for them
        write_measurements(tmp_path / "val" / f"unit{k:02d}.csv", d.subset(torch.arange(10)), robot)
    (first / "units" / "unit01" / "data_hashes.json").unlink()  # a damaged earlier folder
    seen = _fitted_names(monkeypatch)
    res = fleet_app.run_fleet(cfg, [f"fleet.reuse={first}", f"data.validation={tmp_path / 'val'}"],
                              out=tmp_path / "again")
    assert seen == ["unit01"] and res.reused == COUNT - 1
    assert any("unit01 (no data_hashes.json: its data cannot be compared)" in w for w in res.warnings)
    assert _table(res.run_dir)["validation_mean_mm"].notna().all()


def test_an_interrupted_run_is_finished(tmp_path, robot, units, monkeypatch):
    from conftest import ctrl_c_on_call

    cfg = _fleet(tmp_path, robot, units)
    with monkeypatch.context() as m:
        ctrl_c_on_call(m, fleet_app, "fit_cell")  # Ctrl-C in the second cell
        with pytest.raises(KeyboardInterrupt):
            fleet_app.run_fleet(cfg, ["fleet.cell=2"], out=tmp_path / "cut")
    seen = _fitted_names(monkeypatch)
    res = fleet_app.run_fleet(cfg, ["fleet.cell=2", f"fleet.reuse={tmp_path / 'cut'}"], out=tmp_path / "rest")
    assert seen == ["unit02", "unit03"]
    assert (_table(res.run_dir)["status"] == "fitted").all() and not (res.run_dir / "PARTIAL").exists()
    from torchcal.report.fleet import render_fleet_report

    # the reports say what happened: the cut run that it did not finish, the rerun what it took from it
    assert "the run did not finish (PARTIAL)" in render_fleet_report(tmp_path / "cut")
    assert f"2 of them taken from {tmp_path / 'cut'} (fleet.reuse)" in render_fleet_report(res.run_dir)


def test_other_settings_are_refused_by_name(tmp_path, robot, units):
    cfg = _fleet(tmp_path, robot, units[:3])
    first = fleet_app.run_fleet(cfg, out=tmp_path / "first").run_dir
    with pytest.raises(ConfigError, match=r"fleet\.reuse.*other settings \(model\.order\)"):
        fleet_app.run_fleet(cfg, [f"fleet.reuse={first}", "model.order=3"], out=tmp_path / "o3")
    with pytest.raises(ConfigError, match="not a `torchcal fleet` run"):
        fleet_app.run_fleet(cfg, [f"fleet.reuse={tmp_path / 'ident'}"], out=tmp_path / "x")
    with pytest.raises(ConfigError, match="does not exist"):
        fleet_app.run_fleet(cfg, [f"fleet.reuse={tmp_path / 'nope'}"], out=tmp_path / "y")
    # what does not shape a fit may differ: another cell size, or checks skipped, fits nothing again
    res = fleet_app.run_fleet(cfg, [f"fleet.reuse={first}", "fleet.cell=1", "fleet.threshold=4",
                                    "data.units_checked=true", "solver.ftol=1e-6", "compensation.max_iter=20"],
                              out=tmp_path / "cell1")
    assert _table(res.run_dir)["reused_from"].notna().all() and res.reused == 3
    # a unit the earlier run fitted whose file is gone is named, not forgotten
    (tmp_path / "ident" / "unit02.csv").unlink()
    res = fleet_app.run_fleet(cfg, [f"fleet.reuse={first}"], out=tmp_path / "gone")
    assert any("have no identification file in this run's data: unit02" in w for w in res.warnings)


def test_units_named_by_serial_numbers_are_reused(tmp_path, robot, units, monkeypatch):
    """Unit files named 0001.csv ...: summary.csv read the names back as numbers, so nothing matched and every unit
    was refitted, silently."""
    (tmp_path / "ident").mkdir()
    for k, d in enumerate(units[:3]):
        write_measurements(tmp_path / "ident" / f"{k + 1:04d}.csv", d, robot)
    cfg = _fleet(tmp_path, robot, [])  # the config only: the files are above
    first = fleet_app.run_fleet(cfg, out=tmp_path / "first").run_dir
    seen = _fitted_names(monkeypatch)
    res = fleet_app.run_fleet(cfg, [f"fleet.reuse={first}"], out=tmp_path / "again")
    assert seen == [] and res.reused == 3
    assert list(_table(res.run_dir).index) == ["0001", "0002", "0003"]
