"""torchcal fleet: batched per-unit fits equal separate fits; broken units reported; outliers; the fleet prior."""

from __future__ import annotations

import importlib.util
import json

import pytest
import torch

import torchcal
import torchcal.sim
from torchcal.identify import fit
from torchcal.identify.fleet import fit_fleet, fleet_prior, parameter_outliers, stack_units
from torchcal.sim.fleet import fleet_truths

TOOLS = torch.tensor([[0.033, 0.058, 0.161], [0.057, -0.034, 0.161], [-0.034, -0.057, 0.161]], dtype=torch.float64)


@pytest.fixture(scope="module")
def robot():
    return torchcal.load_robot("fanuc_lrmate200i")


def _units(robot, count, poses=60, seed=0, damaged=(), same_program=True):
    noise = torchcal.NoiseModel.from_robot(robot)
    fleet = fleet_truths(robot, TOOLS, count, seed, damaged)
    lim = robot.joint_map.limits
    out = []
    for k, t in enumerate(fleet.truths):
        # one program (same commands) or each unit its own commands and pose count
        q = torchcal.sim.quasi_random_commands(lim, poses if same_program else poses + 7 * k, 0 if same_program else k)
        out.append(torchcal.simulate(t, q, [0, 1, 2], noise, 100 + k))
    return fleet, out, noise


@pytest.mark.parametrize("same_program", [True, False])
def test_fleet_equals_separate_fits(robot, same_program):
    """Every unit of the batched solve lands where its own fit lands (own data, own convergence; padded rows of
    shorter units must not count)."""
    _, units, noise = _units(robot, 3, same_program=same_program)

    def make():
        return torchcal.RobotModel(robot, TOOLS, orders=2, backlash=True)

    out = fit_fleet(make, units, noise, ftol=1e-8)  # the single fit's stopping point: the same optimum
    for k, d in enumerate(units):
        alone = make()
        r = fit(alone, d, noise)
        assert out.results[k].success and r.success
        assert out.results[k].fun == pytest.approx(r.fun, rel=1e-7)
        with torch.no_grad():
            a = out.models[k].points(d.q, d.tool, d.direction)
            b = alone.points(d.q, d.tool, d.direction)
        assert float((a - b).norm(dim=1).max()) < 1e-8  # m


def test_fleet_default_tolerance_keeps_every_unit_at_its_own_fit(robot):
    """At its default stopping tolerance (FLEET_FTOL, looser than a single fit's) every unit's cost is within
    10 ftol of its own fit's optimum and its validation residual within 0.5 % (the issue allows 1 %), in no
    more iterations than at the single fit's tolerance."""
    from torchcal.identify.fleet import FLEET_FTOL

    fleet, units, noise = _units(robot, 4, poses=80, same_program=False)
    q = torchcal.sim.quasi_random_commands(robot.joint_map.limits, 60, 11)
    val = [torchcal.simulate(t, q, [0, 1, 2], noise, 300 + k) for k, t in enumerate(fleet.truths)]

    def make():
        return torchcal.RobotModel(robot, TOOLS, orders=4, backlash=True)

    def residual(model, d):
        with torch.no_grad():
            return float((model.points(d.q, d.tool, d.direction) - d.xyz).norm(dim=1).mean())

    loose, tight = fit_fleet(make, units, noise), fit_fleet(make, units, noise, ftol=1e-8)
    assert sum(r.nit for r in loose.results) <= sum(r.nit for r in tight.results)
    for k, d in enumerate(units):
        alone = make()
        r = fit(alone, d, noise)
        gap = (loose.results[k].fun - r.fun) / r.fun
        assert -1e-7 <= gap <= 10 * FLEET_FTOL
        assert residual(loose.models[k], val[k]) == pytest.approx(residual(alone, val[k]), rel=5e-3)


def test_stack_units_pads_and_masks(robot):
    _, units, _ = _units(robot, 2, poses=10, same_program=False)
    st = stack_units(units)
    assert st["q"].shape[:2] == (2, max(len(u) for u in units))
    assert st["rows"].sum(1).tolist() == [len(u) for u in units]
    with pytest.raises(ValueError, match="unit 1"):
        bad = units[1].subset(torch.arange(len(units[1])))
        bad.xyz[3] = float("nan")
        stack_units([units[0], bad])


def test_damaged_gearbox_is_flagged(robot):
    """The units whose truth got a damaged J3 gearbox are the ones flagged (and on joint 3)."""
    _, units, noise = _units(robot, 12, poses=80, damaged=[4, 9])
    out = fit_fleet(lambda: torchcal.RobotModel(robot, TOOLS, orders=3, backlash=True), units, noise)
    _, findings = parameter_outliers(out)
    assert sorted({f.unit for f in findings}) == [4, 9]
    assert all(f.joint == out.models[0].joint_errors.joint_names[2] for f in findings)


def test_fleet_prior_beats_few_poses_alone(robot):
    """A unit measured with few poses is modeled better with the fleet's prior than alone."""
    from torchcal.identify.layout import ParameterLayout

    fleet, units, noise = _units(robot, 10, poses=80)

    def make():
        return torchcal.RobotModel(robot, TOOLS, orders=2, backlash=True)

    out = fit_fleet(make, units[1:], noise)
    block, mean = fleet_prior(out)
    few = units[0].subset(torch.isin(units[0].pose, torch.arange(12)))
    alone, helped = make(), make()
    fit(alone, few, noise)
    ParameterLayout(helped).set(mean)
    fit(helped, few, noise, blocks=[block], gauge=False)
    q = torchcal.sim.quasi_random_commands(robot.joint_map.limits, 50, 9)
    tool = torch.zeros(50, dtype=torch.long)
    with torch.no_grad():
        truth = fleet.truths[0].points(q, tool)
        e_alone = float((alone.points(q, tool) - truth).norm(dim=1).mean())
        e_help = float((helped.points(q, tool) - truth).norm(dim=1).mean())
    assert e_help < 0.5 * e_alone


def _write_fleet(tmp_path, robot, count=4, broken=None, poses=40):
    from torchcal.io.csv import write_measurements

    fleet, units, _ = _units(robot, count, poses=poses)
    (tmp_path / "ident").mkdir()
    for k, d in enumerate(units):
        write_measurements(tmp_path / "ident" / f"unit{k:02d}.csv", d, robot)
    if broken is not None:
        p = tmp_path / "ident" / f"unit{broken:02d}.csv"
        lines = p.read_text().splitlines()
        cells = lines[5].split(",")
        cells[-1] = "abc"
        lines[5] = ",".join(cells)
        p.write_text("\n".join(lines) + "\n")
    tools = ", ".join(f"[{x * 1000:.2f}, {y * 1000:.2f}, {z * 1000:.2f}]" for x, y, z in TOOLS.tolist())
    cfg = tmp_path / "fleet.yaml"
    cfg.write_text(f"robot: fanuc_lrmate200i\ntools: [{tools}]\ndata: {{identification: ident}}\n"
                   f"model: {{order: 2, backlash: true}}\nout: runs\n")
    return cfg


def test_fleet_command_writes_unit_runs_and_reports_a_broken_unit(tmp_path, robot):
    from torchcal.app.fleet import run_fleet
    from torchcal.io.rundir import load_model

    cfg = _write_fleet(tmp_path, robot, count=4, broken=2)
    res = run_fleet(cfg, out=tmp_path / "fleet-run")
    status = {r["unit"]: r["status"] for r in res.rows}
    assert status == {"unit00": "fitted", "unit01": "fitted", "unit02": "failed", "unit03": "fitted"}
    bad = next(r for r in res.rows if r["unit"] == "unit02")
    assert "unit02.csv" in bad["reason"] and "row" in bad["reason"]  # names the file and the row
    assert (res.run_dir / "summary.csv").is_file()
    model = load_model(res.run_dir / "units" / "unit01")
    assert isinstance(model, torchcal.RobotModel)


def test_a_fleet_unit_is_a_run_that_update_and_the_fleet_inputs_check(tmp_path, robot):
    """Each unit directory starts like a fit's (config, versions, the data's hashes): `torchcal update` of a unit whose
    identification file changed since is refused; an interrupted fleet (PARTIAL) is refused as a prior and as a
    baseline."""
    import json
    from pathlib import Path

    from torchcal.app.config import ConfigError, load_config, updated
    from torchcal.app.fleet import run_fleet
    from torchcal.app.fleet_baseline import baseline_units
    from torchcal.app.fleet_prior import prior_from_fleet_run
    from torchcal.app.update import run_update
    from torchcal.io.rundir import PARTIAL_FILE, RunDirError

    cfg = _write_fleet(tmp_path, robot, count=3)
    run = run_fleet(cfg, out=tmp_path / "fleet-run").run_dir
    unit = run / "units" / "unit01"
    assert (unit / "versions.json").is_file()
    hashes = json.loads((unit / "data_hashes.json").read_text())
    assert Path(hashes["data.identification"]["path"]).name == "unit01.csv"
    f = tmp_path / "ident" / "unit01.csv"
    f.write_text(f.read_text().replace(",", ", ", 1))  # changed since the fit (one byte more)
    with pytest.raises((ConfigError, RunDirError, ValueError), match="changed since the fit"):
        run_update(unit, tmp_path / "ident" / "unit00.csv", tmp_path / "upd")
    (run / PARTIAL_FILE).write_text("interrupted\n")
    with pytest.raises(RunDirError, match="did not finish"):
        prior_from_fleet_run(run)
    with pytest.raises(RunDirError, match="did not finish"):
        baseline_units(updated(load_config(cfg), {"fleet.baseline": str(run)}), "fleet.yaml")


def test_fleet_command_fails_only_the_unit_of_another_format(tmp_path, robot):
    """A unit whose file lacks the approach directions the others have cannot share their solve (one model
    structure): it alone is reported, naming its file and why, and the others are fitted (before, the whole cell
    failed with them)."""
    import pandas as pd

    from torchcal.app.fleet import run_fleet

    cfg = _write_fleet(tmp_path, robot, count=4)
    f = tmp_path / "ident" / "unit01.csv"
    d = pd.read_csv(f)
    d.drop(columns=[c for c in d.columns if c.startswith("dir")]).to_csv(f, index=False)
    res = run_fleet(cfg, out=tmp_path / "fleet-run")
    status = {r["unit"]: r["status"] for r in res.rows}
    assert status == {"unit00": "fitted", "unit01": "failed", "unit02": "fitted", "unit03": "fitted"}
    bad = next(r for r in res.rows if r["unit"] == "unit01")
    assert "unit01.csv" in bad["reason"] and "approach directions" in bad["reason"]
    assert not any("model.backlash" in w for w in res.warnings)
    for k in (0, 2, 3):  # a fleet without directions at all: fitted, and told its backlash is not identifiable
        f = tmp_path / "ident" / f"unit{k:02d}.csv"
        d = pd.read_csv(f)
        d.drop(columns=[c for c in d.columns if c.startswith("dir")]).to_csv(f, index=False)
    res = run_fleet(cfg, out=tmp_path / "fleet-run-2")
    assert all(r["status"] == "fitted" for r in res.rows)
    assert any("model.backlash is on" in w for w in res.warnings)


def test_fleet_command_stops_at_fleet_ftol(tmp_path, robot):
    """fleet.ftol governs the units' stopping (more iterations at 1e-12 than at the default); a bad value is refused
    naming the key; a solver.ftol set in a fleet's config is warned about, not silently ignored."""
    from torchcal.app.config import FleetConfig
    from torchcal.app.fleet import run_fleet
    from torchcal.core.exceptions import ConfigError
    from torchcal.identify.fleet import FLEET_FTOL

    assert FleetConfig().ftol == FLEET_FTOL  # the config's default is the library's
    cfg = _write_fleet(tmp_path, robot, count=3)
    loose = run_fleet(cfg, out=tmp_path / "a")
    tight = run_fleet(cfg, ["fleet.ftol=1e-12", "solver.ftol=1e-9"], out=tmp_path / "b")
    assert sum(r["iterations"] for r in tight.rows) > sum(r["iterations"] for r in loose.rows)
    assert any("solver.ftol" in w for w in tight.warnings) and not any("solver.ftol" in w for w in loose.warnings)
    with pytest.raises(ConfigError, match="fleet.ftol"):
        run_fleet(cfg, ["fleet.ftol=0"], out=tmp_path / "c")


def test_fleet_command_names_what_it_does_not_use(tmp_path, robot):
    """Validation files are matched by name: a unit without one and a file that names no unit are warned about
    (not silently skipped); two files naming one unit are refused before anything runs."""
    import shutil

    from torchcal.app.fleet import run_fleet
    from torchcal.core.exceptions import ConfigError

    cfg = _write_fleet(tmp_path, robot, count=3)
    (tmp_path / "val").mkdir()
    shutil.copy(tmp_path / "ident" / "unit00.csv", tmp_path / "val" / "unit00.csv")
    shutil.copy(tmp_path / "ident" / "unit01.csv", tmp_path / "val" / "unit77.csv")
    cfg.write_text(cfg.read_text().replace("identification: ident", "identification: ident, validation: val"))
    res = run_fleet(cfg, out=tmp_path / "fleet-run")
    rows = {r["unit"]: r for r in res.rows}
    assert "validation_mean_mm" in rows["unit00"] and "validation_mean_mm" not in rows["unit01"]
    # each unit's model keeps its own data's span (predict / compensate judge extrapolation by it)
    import numpy as np
    import pandas as pd

    from torchcal.io.rundir import load_model

    span = np.degrees(load_model(res.run_dir / "units" / "unit01").data_span.numpy())
    own = pd.read_csv(tmp_path / "ident" / "unit01.csv")[[f"q{i}" for i in range(1, 7)]]
    assert np.allclose(span[:, 0], own.min().to_numpy()) and np.allclose(span[:, 1], own.max().to_numpy())
    gap = [w for w in res.warnings if "no file" in w]
    assert len(gap) == 1 and "unit01, unit02" in gap[0]
    assert any("unit77.csv" in w for w in res.warnings)
    assert "unit77.csv" in (res.run_dir / "run.log").read_text()
    # a validation file is the unit's by its stem, whatever its extension's case; what is not a measurement file
    # is named; a broken validation file costs the unit its held-out columns, not its fit
    shutil.move(tmp_path / "ident" / "unit01.csv", tmp_path / "ident" / "unit01.CSV")
    shutil.copy(tmp_path / "val" / "unit00.csv", tmp_path / "val" / "unit01.tsv")
    (tmp_path / "ident" / "README.txt").write_text("campaign notes")
    lines = (tmp_path / "val" / "unit00.csv").read_text().splitlines()
    lines[3] = lines[3].replace(",", ",x", 1)
    (tmp_path / "val" / "unit00.csv").write_text("\n".join(lines) + "\n")
    res = run_fleet(cfg, out=tmp_path / "fleet-run-stems")
    rows = {r["unit"]: r for r in res.rows}
    assert rows["unit01"]["status"] == "fitted" and "validation_mean_mm" in rows["unit01"]
    assert rows["unit00"]["status"] == "fitted" and "validation_mean_mm" not in rows["unit00"]
    assert any("unit00" in w and "validation file not used" in w and "row 3" in w for w in res.warnings)
    import pandas as pd  # and the files say why its validation columns are empty (only the console and log did)

    summary = pd.read_csv(res.run_dir / "summary.csv", dtype={"unit": str}).set_index("unit")
    assert "row 3" in summary.loc["unit00", "validation_error"] and pd.isna(summary.loc["unit01", "validation_error"])
    assert "row 3" in json.loads((res.run_dir / "fleet.json").read_text())["units"][0]["validation_error"]
    assert any("README.txt" in w for w in res.warnings)
    assert not any("byte-identical" in w for w in res.warnings)
    shutil.move(tmp_path / "ident" / "unit01.CSV", tmp_path / "ident" / "unit01.csv")
    # a unit's file copied under another name: said (two "units" with no spread between them)
    shutil.copy(tmp_path / "ident" / "unit00.csv", tmp_path / "ident" / "unit09.csv")
    res = run_fleet(cfg, out=tmp_path / "fleet-run-copy")
    assert [w for w in res.warnings if "byte-identical" in w] == [
        "units unit00, unit09 have byte-identical identification files: one unit measured once?"]
    (tmp_path / "ident" / "unit09.csv").unlink()
    shutil.copy(tmp_path / "ident" / "unit02.csv", tmp_path / "ident" / "unit02.tsv")
    with pytest.raises(ConfigError, match="unit02.csv and unit02.tsv"):
        run_fleet(cfg, out=tmp_path / "fleet-run-2")
    assert not (tmp_path / "fleet-run-2").exists()


def test_fleet_command_judges_a_unit_with_too_few_poses_apart(tmp_path, robot):
    """A unit with fewer equations than parameters is fitted (the prior holds it) but reported as not
    determined: no outlier score, not flagged, left out of the fleet prior; the others are scored as before."""
    import math

    from torchcal.app.fleet import run_fleet
    from torchcal.app.fleet_prior import prior_from_fleet_run
    from torchcal.io.csv import write_measurements

    cfg = _write_fleet(tmp_path, robot, count=4)
    _, units, _ = _units(robot, 5, poses=40)
    write_measurements(tmp_path / "ident" / "unit09.csv", units[4].subset(units[4].pose < 5), robot)
    res = run_fleet(cfg, out=tmp_path / "fleet-run")
    rows = {r["unit"]: r for r in res.rows}
    thin = rows["unit09"]
    assert thin["status"] == "fitted" and thin["rows"] == 15 and thin["determined"] is False
    assert math.isnan(thin["outlier_score"]) and thin["flagged"] is False and "too few poses" in thin["findings"]
    for k in range(4):
        r = rows[f"unit{k:02d}"]
        assert r["determined"] is True and math.isfinite(r["outlier_score"])
    got = prior_from_fleet_run(res.run_dir)
    assert got.left_out == ["unit09"] and len(got.units) == 4
    # its run directory predicts and compensates, saying the model is the prior's (it said nothing); a determined
    # unit's does not
    from torchcal.app.files import compensate_file, predict_file

    cmds = tmp_path / "cmds.csv"
    cmds.write_text("q1,q2,q3,q4,q5,q6\n" + "10,20,30,40,50,60\n-10,10,20,-30,40,-50\n")
    for unit, said in (("unit09", True), ("unit01", False)):
        run = res.run_dir / "units" / unit
        for done in (predict_file(run, cmds, tmp_path / f"p_{unit}.csv"),
                     compensate_file(run, cmds, tmp_path / f"c_{unit}.csv")):
            assert any("not determined by its data" in w and "too few poses" in w for w in done.warnings) is said


def test_fleet_command_chooses_one_backlash_structure(tmp_path, robot):
    """model.backlash: true is resolved once on every unit's rows, not per cell on its first unit: with one
    unit per cell and one unit whose joint-1 direction follows its position (alone it would get the low
    order), every unit's model has the same backlash orders, the pooled choice, also in its own config."""
    import pandas as pd

    from torchcal.app.config import load_config
    from torchcal.app.fleet import run_fleet
    from torchcal.identify.backlash import default_backlash_orders
    from torchcal.io.csv import read_measurements
    from torchcal.io.rundir import load_model

    import numpy as np

    cfg = _write_fleet(tmp_path, robot, count=4)
    g = np.random.default_rng(3)
    for k in range(4):  # directions independent of position (identifiable backlash), unit00's joint 1 not
        f = tmp_path / "ident" / f"unit{k:02d}.csv"
        d = pd.read_csv(f)
        signs = g.choice([-1, 1], size=(d["pose"].max() + 1, 6))[d["pose"].to_numpy()]
        for j in range(6):
            d[f"dir{j + 1}"] = signs[:, j]
        if k == 0:
            d["dir1"] = np.where(d["q1"] >= d["q1"].median(), 1, -1)
        d.to_csv(f, index=False)
    lim = robot.joint_map.limits
    data = [read_measurements(tmp_path / "ident" / f"unit{k:02d}.csv", robot, 3) for k in range(4)]
    alone = default_backlash_orders([3] * 6, data[0].q, data[0].direction, lim)[0]
    pooled = default_backlash_orders([3] * 6, torch.cat([u.q for u in data]), torch.cat([u.direction for u in data]),
                                     lim)[0]
    others = default_backlash_orders([3] * 6, data[1].q, data[1].direction, lim)[0]
    assert alone != others  # the case: decided per cell, the units would differ
    res = run_fleet(cfg, ["fleet.cell=1", "model.order=3"], out=tmp_path / "fleet-run")
    assert all(r["status"] == "fitted" for r in res.rows)
    for r in res.rows:
        model = load_model(res.run_dir / "units" / r["unit"])
        assert model.joint_errors.backlash_orders.tolist() == pooled, r["unit"]
        unit_cfg = load_config(res.run_dir / "units" / r["unit"] / "config.yaml")
        assert list(unit_cfg.model.backlash) == pooled
    # a new unit with backlash: true and the fleet's prior takes the fleet's orders, not its own data's (unit00's
    # file alone would choose others, and the prior would not fit its model)
    from torchcal.app.fit import run_fit

    run = run_fit(load_config(cfg, ["model.order=3", f"prior.fleet={res.run_dir}", f"data.identification={tmp_path / 'ident' / 'unit00.csv'}",
                                    "plots=false", "report=false", f"out={tmp_path / 'new'}"]))
    assert run.model.joint_errors.backlash_orders.tolist() == pooled != alone


@pytest.mark.skipif(importlib.util.find_spec("ray") is None, reason="Ray not installed (pip install 'torchcal[ray]')")
def test_ray_engine_matches_local(tmp_path, robot):
    """fleet.engine=ray (a local Ray, 2 workers) computes what the local engine computes, cell by cell."""
    import ray

    from torchcal.app.fleet import run_fleet

    cfg = _write_fleet(tmp_path, robot, count=4)
    local = run_fleet(cfg, ["fleet.cell=2"], out=tmp_path / "local")
    ray.init(num_cpus=2, include_dashboard=False, log_to_driver=False)
    try:
        remote = run_fleet(cfg, ["fleet.engine=ray", "fleet.cell=2"], out=tmp_path / "ray")
    finally:
        ray.shutdown()
    from torchcal.io.rundir import load_model

    for r in local.rows:  # the models: bit for bit (same cells, same threads)
        ma, mb = load_model(local.run_dir / "units" / r["unit"]), load_model(remote.run_dir / "units" / r["unit"])
        for (k, a), (_, b) in zip(ma.state_dict().items(), mb.state_dict().items()):
            assert torch.equal(a, b), k
    for a, b in zip(local.rows, remote.rows):
        assert a["unit"] == b["unit"] and a["status"] == b["status"] == "fitted"
        assert a["identification_mean_mm"] == b["identification_mean_mm"]


def test_fit_with_the_prior_of_a_fleet_run(tmp_path, robot):
    """`torchcal fit ... prior.fleet=FLEET_RUN`: a new unit measured with a few poses, fitted with the fleet run's
    parameter distribution as its prior, is modeled far better than the same config without it; the prior comes
    from the fitted units only (the broken one is left out) and the run records it; a model of another structure
    is refused naming the key."""
    from torchcal.app.config import load_config
    from torchcal.app.fit import run_fit
    from torchcal.app.fleet import run_fleet
    from torchcal.app.fleet_prior import prior_from_fleet_run
    from torchcal.core.exceptions import ConfigError
    from torchcal.identify.layout import ParameterLayout
    from torchcal.io.csv import write_measurements
    from torchcal.io.rundir import load_model

    cfg = _write_fleet(tmp_path, robot, count=7, broken=3)
    fleet_run = run_fleet(cfg, out=tmp_path / "fleet-run").run_dir
    # the prior: the six readable units' mean, unit03 (its file is broken) left out
    got = prior_from_fleet_run(fleet_run)
    assert got.left_out == ["unit03"] and len(got.units) == 6
    X = torch.stack([ParameterLayout(load_model(fleet_run / "units" / u)).get() for u in got.units])
    torch.testing.assert_close(got.mean, X.mean(0))
    # a new unit of the type (its own truth, as the fleet's units), measured with 12 poses
    truth = fleet_truths(robot, TOOLS, 8, 0).truths[7]
    noise = torchcal.NoiseModel.from_robot(robot)
    q = torchcal.sim.quasi_random_commands(robot.joint_map.limits, 12, 5)
    write_measurements(tmp_path / "new.csv", torchcal.simulate(truth, q, [0, 1, 2], noise, 77), robot)
    base = cfg.read_text().replace("identification: ident", "identification: new.csv")
    (tmp_path / "new.yaml").write_text(base)
    qv = torchcal.sim.quasi_random_commands(robot.joint_map.limits, 60, 9)
    tool = torch.zeros(60, dtype=torch.long)

    def error(run):
        with torch.no_grad():
            return float((run.model.points(qv, tool) - truth.points(qv, tool)).norm(dim=1).mean())

    common = ["plots=false", "report=false", f"out={tmp_path / 'runs'}"]
    alone = run_fit(load_config(tmp_path / "new.yaml", common))
    helped = run_fit(load_config(tmp_path / "new.yaml", common + [f"prior.fleet={fleet_run}"]))
    assert error(helped) < 0.5 * error(alone)
    import json

    rec = json.loads((helped.run_dir / "fit.json").read_text())["fleet_prior"]
    assert rec["units"] == 6 and rec["left_out"] == ["unit03"]
    # a unit of the type lies no farther from the fleet than its spread explains (its own truth, as the fleet's):
    # said, recorded, not warned (identify/test_fleet_prior.py holds d^2 to its expectation and a damaged unit)
    t = rec["tension"]
    assert 0.0 < t["expected"] < rec["entries"] and t["ratio"] == pytest.approx(t["d2"] / t["expected"])
    assert sum(share for _, share in t["groups"]) == pytest.approx(t["d2"], rel=1e-9)
    assert not any("farther from the fleet" in w for w in helped.warnings), (t, helped.warnings)
    # the run reports the same unit fitted alone beside it: what the plain run of the same config computes
    cmp = json.loads((helped.run_dir / "metrics.json").read_text())["fleet_prior"]
    plain = json.loads((alone.run_dir / "metrics.json").read_text())["sets"]["identification"]["modeled"]
    mine = json.loads((helped.run_dir / "metrics.json").read_text())["sets"]["identification"]["modeled"]
    for k in ("mean", "max", "gamma99"):
        assert cmp["alone"]["identification"][k] == pytest.approx(plain[k], rel=1e-9)
        assert cmp["with_prior"]["identification"][k] == pytest.approx(mine[k], rel=1e-12)
    assert "validation" not in cmp["alone"]
    from torchcal.report import render_report

    page = render_report(helped.run_dir)  # the calibration report names the fleet the prior came from
    assert "Prior from a fleet" in page and "left out: unit03" in page and "fitted alone" in page
    with pytest.raises(ConfigError, match="prior.fleet"):
        run_fit(load_config(tmp_path / "new.yaml", common + [f"prior.fleet={fleet_run}", "model.order=1"]))
    with pytest.raises(ConfigError, match="prior.enabled=false"):
        load_config(tmp_path / "new.yaml", [f"prior.fleet={fleet_run}", "prior.enabled=false"])
    # a sweep cell with the fleet prior is the prior's fit, whatever else the grid varies (before, a batched cell
    # silently left the prior out)
    from torchcal.app.sweep import run_sweep

    sw = run_sweep(tmp_path / "new.yaml", common[:2] + [f"prior.fleet={fleet_run}", "solver.method=lm,lbfgs"],
                   out=tmp_path / "sweep")
    lm = next(r for r in sw.rows if r["solver.method"] == "lm")
    assert lm["identification_mean_mm"] == pytest.approx(mine["mean"], rel=1e-12)
    # and a fleet is fitted under its config's own prior: a fleet prior there is refused, as is another solver
    for bad, key in ((f"prior.fleet={fleet_run}", "prior.fleet"), ("solver.method=lbfgs", "solver.method")):
        with pytest.raises(ConfigError, match=key):
            run_fleet(cfg, [bad], out=tmp_path / "refused")
    assert not (tmp_path / "refused").exists()


def test_plan_poses_designed_for_a_fleet_prior(tmp_path, robot):
    """`torchcal plan-poses ... --fleet RUN`: the poses picked for the fleet's prior predict a smaller model error
    than the plain plan's first ones, the prediction falls with every pick, the plan is written in visiting
    order; and a unit fitted with the prior on the designed poses is modeled better than on the plain ones."""
    from typer.testing import CliRunner

    from torchcal.app.commands import plan_poses_file
    from torchcal.app.config import load_config
    from torchcal.app.fit import run_fit
    from torchcal.app.fleet import run_fleet
    from torchcal.cli import app
    from torchcal.io.csv import write_measurements

    cfg = _write_fleet(tmp_path, robot, count=7)
    fleet_run = run_fleet(cfg, out=tmp_path / "fleet-run").run_dir
    plan, _ = plan_poses_file("fanuc_lrmate200i", 12, tmp_path / "designed.csv", seed=3, fleet=fleet_run,
                              candidates=300)
    d = plan.stats["design"]
    assert len(plan) == 12 and (tmp_path / "designed.csv").is_file()
    assert d["predicted_rms_mm"] < 0.8 * d["plain_predicted_rms_mm"] < 0.8 * d["prior_rms_mm"]
    r = CliRunner().invoke(app, ["plan-poses", "fanuc_lrmate200i", "12", str(tmp_path / "cli.csv"), "--seed", "3",
                                 "--fleet", str(fleet_run), "--candidates", "300"])
    assert r.exit_code == 0, r.output
    assert "designed for the prior" in r.output
    # a fleet of another type: refused, naming both (six joints each, the same layout: nothing else would tell)
    r = CliRunner().invoke(app, ["plan-poses", "abb_irb120", "12", str(tmp_path / "abb.csv"), "--fleet", str(fleet_run),
                                 "--candidates", "300"])
    assert r.exit_code != 0 and "fanuc_lrmate200i" in r.output and "abb_irb120" in r.output
    # a single unit's run directory is no fleet: one message naming the option, not a missing-file traceback
    (tmp_path / "one_run").mkdir()
    r = CliRunner().invoke(app, ["plan-poses", "fanuc_lrmate200i", "12", str(tmp_path / "one.csv"), "--fleet",
                                 str(tmp_path / "one_run")])
    assert r.exit_code == 2 and "not a `torchcal fleet` run directory" in " ".join(r.output.split())
    # measured on a new unit of the type, fitted with the fleet's prior: designed against plain poses
    truth = fleet_truths(robot, TOOLS, 8, 0).truths[7]
    noise = torchcal.NoiseModel.from_robot(robot)
    plain = plan_poses_file("fanuc_lrmate200i", 12, tmp_path / "plain.csv", seed=3)[0]
    qv = torchcal.sim.quasi_random_commands(robot.joint_map.limits, 100, 9)
    tool = torch.zeros(100, dtype=torch.long)
    errors = {}
    for name, p in (("designed", plan), ("plain", plain)):
        write_measurements(tmp_path / f"{name}_meas.csv", torchcal.simulate(truth, p.q, [0, 1, 2], noise, 77,
                                                                              directions=p.directions), robot)
        (tmp_path / f"{name}.yaml").write_text(cfg.read_text().replace("identification: ident",
                                                                        f"identification: {name}_meas.csv"))
        run = run_fit(load_config(tmp_path / f"{name}.yaml", ["plots=false", "report=false", f"out={tmp_path / 'r'}",
                                                               f"prior.fleet={fleet_run}"]))
        with torch.no_grad():
            errors[name] = float((run.model.points(qv, tool) - truth.points(qv, tool)).norm(dim=1).mean())
    assert errors["designed"] < errors["plain"]


def _moved(data, k):
    """``data`` seen from a tracker that stood elsewhere for unit k: its points under a rigid move (turned about z
    by 90-300 deg and tilted, 1-2 m away) -> (moved Measurements, R (3, 3), t (3,))."""
    import math
    from dataclasses import replace

    a, b = math.radians(90 + 70 * k), math.radians(3 + k)
    Rz = torch.tensor([[math.cos(a), -math.sin(a), 0], [math.sin(a), math.cos(a), 0], [0, 0, 1]], dtype=torch.float64)
    Rx = torch.tensor([[1, 0, 0], [0, math.cos(b), -math.sin(b)], [0, math.sin(b), math.cos(b)]], dtype=torch.float64)
    R, t = Rz @ Rx, torch.tensor([1.2 + 0.2 * k, -0.8 + 0.4 * k, -0.3], dtype=torch.float64)
    return replace(data, xyz=data.xyz @ R.T + t), R, t


def test_fleet_estimates_each_units_measurement_frame(tmp_path, robot):
    """Each unit measured from wherever its tracker stood (its own rigid move of the points, which the fleet in the
    base frame lacks), with measurement_frame: estimate: every unit's frame from its own data; its model predicts
    the measured points where the same unit measured in its base frame predicts them, moved by the tracker's true
    placement, with the same residuals; alignment.json holds the placement. With the frame left at the base, a
    unit the fit cannot bring home is flagged naming the measurement frame, judged for no outlier and left out
    of the fleet prior."""
    from torchcal.app.fleet import run_fleet
    from torchcal.app.fleet_prior import prior_from_fleet_run
    from torchcal.io.csv import write_measurements
    from torchcal.io.rundir import load_model

    _, units, _ = _units(robot, 4, poses=40)
    moves = []
    for sub in ("base", "moved"):
        (tmp_path / sub).mkdir()
    for k, d in enumerate(units):
        m, R, t = _moved(d, k)
        moves.append((R, t))
        write_measurements(tmp_path / "base" / f"unit{k:02d}.csv", d, robot)
        write_measurements(tmp_path / "moved" / f"unit{k:02d}.csv", m, robot)
    tools = ", ".join(f"[{x * 1000:.2f}, {y * 1000:.2f}, {z * 1000:.2f}]" for x, y, z in TOOLS.tolist())
    cfg = tmp_path / "fleet.yaml"
    cfg.write_text(f"robot: fanuc_lrmate200i\ntools: [{tools}]\ndata: {{identification: moved}}\n"
                   "model: {order: 2, backlash: true}\nmeasurement_frame: estimate\nout: runs\nreport: false\n")
    home = run_fleet(cfg, ["data.identification=" + str(tmp_path / "base"), "measurement_frame=base"],
                     out=tmp_path / "home")
    away = run_fleet(cfg, out=tmp_path / "away")
    for k, (a, b) in enumerate(zip(away.rows, home.rows)):
        assert a["status"] == b["status"] == "fitted" and not a["flagged"], a
        assert a["identification_mean_mm"] == pytest.approx(b["identification_mean_mm"], rel=0.01)
        R, t = moves[k]
        d = units[k]
        with torch.no_grad():
            pa = load_model(away.run_dir / "units" / a["unit"]).points(d.q, d.tool, d.direction)
            pb = load_model(home.run_dir / "units" / b["unit"]).points(d.q, d.tool, d.direction) @ R.T + t
        assert float((pa - pb).norm(dim=1).max()) < 1e-5  # m
        placed = json.loads((away.run_dir / "units" / a["unit"] / "alignment.json").read_text())
        assert torch.allclose(torch.tensor(placed["frame"]["xyz_mm"], dtype=torch.float64), t * 1000, atol=5.0)
    # the same files with the frame left at the robot base
    lost = run_fleet(cfg, ["measurement_frame=base"], out=tmp_path / "lost")
    # lost: after the fit, or before it where the fit's base frame brought it home (a 1.6 m miss fitted to 0.08 mm)
    far = [r for r in lost.rows if max(r["identification_mean_mm"], r["identification_nominal_mean_mm"]) > 20.0]
    assert far, "no unit stayed lost: the case is not exercised"
    for r in far:
        assert r["flagged"] and "measurement frame" in r["findings"] and r["outlier_score"] != r["outlier_score"]
    if len(lost.rows) - len(far) >= 3:
        assert {r["unit"] for r in far} <= set(prior_from_fleet_run(lost.run_dir).left_out)
    else:  # too few left for a spread: refused, counting only the units that were not flagged
        from torchcal.core.exceptions import ConfigError

        with pytest.raises(ConfigError, match=f"has {len(lost.rows) - len(far)} fitted, unflagged units"):
            prior_from_fleet_run(lost.run_dir)
    assert f"{len(far)} flagged" in (lost.run_dir / "run.log").read_text()


def test_fleet_interrupted_keeps_the_units_it_fitted(tmp_path, robot, monkeypatch):
    """Ctrl-C during the second cell: the first cell's units are written with their models, summary.csv names
    the others as interrupted, the run stays marked PARTIAL and the interrupt goes on to the caller."""
    import pandas as pd

    import torchcal.app.fleet as fleet_app
    from conftest import ctrl_c_on_call

    cfg = _write_fleet(tmp_path, robot, count=4)
    ctrl_c_on_call(monkeypatch, fleet_app, "fit_cell")
    with pytest.raises(KeyboardInterrupt) as info:
        fleet_app.run_fleet(cfg, ["fleet.cell=2"], out=tmp_path / "cut")
    run = tmp_path / "cut"
    assert info.value.run_dir == run and (run / "PARTIAL").exists()
    table = pd.read_csv(run / "summary.csv").set_index("unit")
    assert list(table["status"]) == ["fitted", "fitted", "failed", "failed"]
    assert table.loc["unit02", "reason"].startswith("Interrupted")
    assert (run / "units" / "unit01" / "model.pt").exists() and not (run / "units" / "unit02").exists()


def test_fleet_where_no_unit_can_be_fitted_says_why(tmp_path, robot):
    """Every unit failing before its fit is one error with the first unit's reason (file, row, column), and
    summary.csv holds every unit's."""
    from torchcal.app.fleet import run_fleet
    from torchcal.core.exceptions import ConfigError

    cfg = _write_fleet(tmp_path, robot, count=2)
    for p in (tmp_path / "ident").iterdir():
        p.write_text(p.read_text().splitlines()[0] + "\n1,2\n")  # a row two cells short
    with pytest.raises(ConfigError, match="no unit could be fitted; unit00: DataError") as info:
        run_fleet(cfg, out=tmp_path / "none")
    assert "unit00.csv" in str(info.value)
    assert (tmp_path / "none" / "summary.csv").read_text().count("failed") == 2
    with pytest.raises(ConfigError, match="inside data.identification"):  # a run among the units' files: refused
        run_fleet(cfg, out=tmp_path / "ident" / "run")
    assert not (tmp_path / "ident" / "run").exists()


def test_baseline_measured_with_other_tools_is_refused(tmp_path, robot):
    """A re-check compares campaigns measured with the same tool vectors: remounted targets would move every
    unit's points by the targets' move, which is no change of the robot. Refused before the solve."""
    from torchcal.app.fleet import run_fleet
    from torchcal.core.exceptions import ConfigError

    cfg = _write_fleet(tmp_path, robot, count=3)
    first = run_fleet(cfg, ["report=false"], out=tmp_path / "first").run_dir
    moved = cfg.read_text().replace("[33.00,", "[40.00,")
    assert moved != cfg.read_text()
    cfg.write_text(moved)
    with pytest.raises(ConfigError, match="other tool vectors"):
        run_fleet(cfg, [f"fleet.baseline={first}"], out=tmp_path / "second")
    assert not (tmp_path / "second" / "units").exists()


def test_a_gross_row_is_named_and_noise_is_not(tmp_path, robot):
    """One row 5 mm off (a reflector off its nest) is warned about by its unit, file row and residual; the
    units measured with tracker noise alone raise no such warning."""
    from torchcal.app.fleet import run_fleet

    cfg = _write_fleet(tmp_path, robot, count=4)
    p = tmp_path / "ident" / "unit01.csv"
    lines = p.read_text().splitlines()
    header = lines[0].split(",")
    cells = lines[31].split(",")
    cells[header.index("x")] = f"{float(cells[header.index('x')]) + 5.0:.6f}"
    lines[31] = ",".join(cells)
    p.write_text("\n".join(lines) + "\n")
    res = run_fleet(cfg, ["report=false"], out=tmp_path / "run")
    far = [w for w in res.warnings if "far beyond the rest" in w]
    assert len(far) == 1 and "unit unit01" in far[0] and "row 31 (" in far[0], far


def test_far_rows_leave_gaussian_noise_alone():
    from torchcal.analysis.stats import far_rows

    g = torch.Generator().manual_seed(0)
    noise = torch.randn(20000, 3, generator=g, dtype=torch.float64).norm(dim=1)  # Maxwell: tracker noise alone
    assert far_rows(noise).numel() == 0
    noise[123] = 16.0  # ~10x the median norm (1.54)
    assert far_rows(noise).tolist() == [123]


def test_a_unit_measured_with_fewer_tools_is_not_judged(tmp_path, robot):
    """A unit whose file holds one reflector's rows while the others hold three: its wrist is seen through one point,
    its features differ for that alone (it was flagged 'joint6 transmission error 14.5x the fleet median'), so it
    is fitted, said, and not scored."""
    import pandas as pd

    from torchcal.app.fleet import run_fleet

    cfg = _write_fleet(tmp_path, robot, count=6, poses=60)  # one tool's 60 rows: equations enough for the model
    p = tmp_path / "ident" / "unit05.csv"
    df = pd.read_csv(p)
    df[df["tool"] == 0].to_csv(p, index=False)
    res = run_fleet(cfg, out=tmp_path / "run")
    row = next(r for r in res.rows if r["unit"] == "unit05")
    assert row["status"] == "fitted" and not row["flagged"] and row["determined"] is False
    assert row["findings"] == "not scored: tools [1, 2] never measured, unlike the fleet's other units"
    assert any("unit unit05: tools [1, 2] never measured" in w for w in res.warnings)
    from torchcal.io.rundir import load_model

    # each unit's model knows the tools its data measured: compensation restores only what they observed
    assert load_model(res.run_dir / "units" / "unit05").measured_tools == [0]
    assert load_model(res.run_dir / "units" / "unit00").measured_tools == [0, 1, 2]


def test_a_unit_that_is_not_the_fleets_robot_is_flagged_and_left_out(tmp_path, robot):
    """A sister arm 12 mm longer (nominal residual far above the fleet's, under 20 mm) and a unit whose tool labels
    0 and 1 are swapped (nominal residual ~100 mm) are fitted to a few hundredths of a mm, since the model absorbs
    either: they were scored as units of the type and entered the fleet prior, silently. Now each is flagged with
    its nominal residual, unscored, and left out of the prior; a fleet whose every unit is so (a wrong tool
    vector in the config) exits nonzero with its run written."""
    from typer.testing import CliRunner

    from torchcal.app.fleet import run_fleet
    from torchcal.app.fleet_prior import prior_from_fleet_run
    from torchcal.cli import app
    from torchcal.io.csv import write_measurements

    cfg = _write_fleet(tmp_path, robot, count=5)
    sister = fleet_truths(robot, TOOLS, 6, 0).truths[5]
    with torch.no_grad():
        sister.origin_shift[2, 0] += 0.012  # the upper arm 12 mm longer
    q = torchcal.sim.quasi_random_commands(robot.joint_map.limits, 40, 0)
    noise = torchcal.NoiseModel.from_robot(robot)
    write_measurements(tmp_path / "ident" / "unit05.csv", torchcal.simulate(sister, q, [0, 1, 2], noise, 105), robot)
    lines = (tmp_path / "ident" / "unit04.csv").read_text().splitlines()
    head = lines[0].split(",")
    t = head.index("tool")

    def swap(line):
        cells = line.split(",")
        cells[t] = {"0": "1", "1": "0"}.get(cells[t], cells[t])
        return ",".join(cells)

    (tmp_path / "ident" / "unit06.csv").write_text("\n".join([lines[0]] + [swap(x) for x in lines[1:]]) + "\n")
    res = run_fleet(cfg, out=tmp_path / "fleet-run")
    rows = {r["unit"]: r for r in res.rows}
    assert all(r["status"] == "fitted" for r in res.rows)
    assert rows["unit05"]["identification_mean_mm"] < 0.2 and rows["unit06"]["identification_mean_mm"] < 1.0
    assert rows["unit05"].get("implausible") and "the fleet's median" in rows["unit05"]["findings"]
    assert 5.0 < rows["unit05"]["identification_nominal_mean_mm"] < 20.0
    assert rows["unit06"].get("implausible") and "tool vectors and labels" in rows["unit06"]["findings"]
    assert rows["unit06"]["identification_nominal_mean_mm"] > 20.0
    from torchcal.analysis.stats import point_residuals  # one pass for the fleet: each unit's own nominal residual
    from torchcal.io.csv import read_measurements
    from torchcal.io.rundir import load_model

    for name in ("unit00", "unit05", "unit06"):
        own = point_residuals(load_model(res.run_dir / "units" / name), read_measurements(
            tmp_path / "ident" / f"{name}.csv", robot, 3), nominal=True)
        assert rows[name]["identification_nominal_mean_mm"] == pytest.approx(float(own.mean()) * 1000, rel=1e-12)
    assert not any(rows[f"unit0{k}"].get("implausible") or rows[f"unit0{k}"]["flagged"] for k in range(5))
    assert sorted(prior_from_fleet_run(res.run_dir).left_out) == ["unit05", "unit06"]
    assert sum("not scored for outliers, left out of the fleet prior" in w for w in res.warnings) == 2
    # the config's tools 30 mm off: every unit so; the run is written and the command says nothing is usable
    text = cfg.read_text().replace("161.00]", "191.00]")
    assert text != cfg.read_text()
    (tmp_path / "bad.yaml").write_text(text)
    r = CliRunner().invoke(app, ["fleet", str(tmp_path / "bad.yaml"), "--out", str(tmp_path / "bad-run"), "-q",
                                 "report=false"])
    assert r.exit_code == 1 and "nothing to deploy" in r.output, r.output
    assert (tmp_path / "bad-run" / "summary.csv").is_file()


def test_a_badly_damaged_gearbox_is_named_at_its_joint_not_called_another_robot(tmp_path, robot):
    """A J3 gearbox with 0.3 deg of backlash and 10x its strain-wave error raises the unit's nominal residual past
    the another-robot rule (2x the fleet's median, robust z > threshold): judged against the fleet's features it is
    named at joint 3 and scored, not called another robot (the review's case: flagged 'another robot?', no joint)."""
    from torchcal.app.fleet import run_fleet
    from torchcal.io.csv import write_measurements

    fleet = fleet_truths(robot, TOOLS, 8, 0, damaged={5: 2}, damage={"backlash_deg": 0.3, "wave": 10.0})
    noise = torchcal.NoiseModel.from_robot(robot)
    (tmp_path / "ident").mkdir()
    q = torchcal.sim.quasi_random_commands(robot.joint_map.limits, 40, 0)
    g = torch.Generator().manual_seed(3)
    s = torch.where(torch.rand(q.shape, generator=g) < 0.5, -1.0, 1.0).double()
    for k, t in enumerate(fleet.truths):
        write_measurements(tmp_path / "ident" / f"unit{k:02d}.csv",
                           torchcal.simulate(t, q, [0, 1, 2], noise, 100 + k, directions=s), robot)
    tools = ", ".join(f"[{x * 1000:.2f}, {y * 1000:.2f}, {z * 1000:.2f}]" for x, y, z in TOOLS.tolist())
    cfg = tmp_path / "fleet.yaml"
    cfg.write_text(f"robot: fanuc_lrmate200i\ntools: [{tools}]\ndata: {{identification: ident}}\n"
                   "model: {order: 2, backlash: true}\nout: runs\nreport: false\n")
    res = run_fleet(cfg, out=tmp_path / "fleet-run")
    rows = {r["unit"]: r for r in res.rows}
    nominal = torch.tensor([rows[f"unit{k:02d}"]["identification_nominal_mean_mm"] for k in range(8)])
    others = torch.cat([nominal[:5], nominal[6:]])
    assert float(nominal[5]) > 2.0 * float(others.median())  # the case: past the ratio of the another-robot rule
    bad = rows["unit05"]
    assert bad["flagged"] and not bad.get("implausible") and "another robot" not in bad["findings"], bad
    assert bad["findings"].startswith("joint3") and "nominal residual" in bad["findings"]
    assert bad["outlier_score"] == bad["outlier_score"]  # scored
    assert any(f.unit == "unit05" and f.joint == "joint3" for f in res.findings)
