"""torchcal fleet with fleet.baseline: a re-measured fleet compared unit by unit with its earlier calibration.

The truth of the second campaign is written here, from what happens to a fleet between two campaigns, not from
the model: every unit's links grow with the season (15 K, steel) and the tracker stands elsewhere; one unit
crashed (joint 2's mastering moved), one had its joint-3 gearbox swapped (new transmission-error phases and
amplitudes); the second campaign measures other commands in another order, with new noise, and one unit is
gone and a new one measured.
"""

from __future__ import annotations

import copy
import math

import numpy as np
import pandas as pd
import pytest
import torch

import torchcal
import torchcal.sim
from torchcal.core import units as U
from torchcal.core.exceptions import ConfigError
from torchcal.identify.alignment import kabsch
from torchcal.sim.fleet import fleet_truths

TOOLS = torch.tensor([[0.033, 0.058, 0.161], [0.057, -0.034, 0.161], [-0.034, -0.057, 0.161]], dtype=torch.float64)
CRASHED, SWAPPED, GONE = 2, 4, 6
COUNT = 8


@pytest.fixture(scope="module")
def robot():
    return torchcal.load_robot("fanuc_lrmate200i")


def _second_campaign(truths, seed=5):
    """The truths a year later: a season for every unit, a crash and a gearbox swap (module docstring)."""
    g = np.random.default_rng(seed)
    later = [copy.deepcopy(t) for t in truths]
    with torch.no_grad():
        for t in later:
            t.origins[:, :3, 3] *= 1 + 15 * 1.2e-5  # thermal growth of every link
            t.tip[:3, 3] *= 1 + 15 * 1.2e-5
            # the tracker set up elsewhere: the measurement frame moves by ~0.05 deg and ~2 mm
            t.base_twist += torch.from_numpy(np.concatenate([g.normal(0, 0.05, 3) * U.DEG,
                                                             g.normal(0, 2.0, 3) * U.MM]))
        later[CRASHED].mastering[1] += 0.03 * U.DEG
        swap = later[SWAPPED]
        swap.wave_phase[2] = torch.from_numpy(g.uniform(0, 2 * math.pi, swap.wave_phase.shape[1]))
        swap.wave_amp[2] *= torch.from_numpy(g.uniform(0.8, 1.2, swap.wave_amp.shape[1]))
    return later


def _write_campaign(folder, robot, truths, names, seed, reverse):
    from torchcal.io.csv import write_measurements

    noise = torchcal.NoiseModel.from_robot(robot)
    lim = robot.joint_map.limits
    q = torchcal.sim.quasi_random_commands(lim, 90, seed)
    if reverse:
        q = q.flip(0)
    g = torch.Generator().manual_seed(seed)
    dirs = torch.where(torch.rand(q.shape, generator=g, dtype=torch.float64) > 0.5, 1.0, -1.0)
    folder.mkdir()
    data = {}
    for k, (name, t) in enumerate(zip(names, truths)):
        d = torchcal.simulate(t, q, [0, 1, 2], noise, 1000 * seed + k, directions=dirs)
        write_measurements(folder / f"{name}.csv", d, robot)
        data[name] = d
    return data


def _config(tmp_path, name, ident, order=3):
    tools = ", ".join(f"[{x * 1000:.2f}, {y * 1000:.2f}, {z * 1000:.2f}]" for x, y, z in TOOLS.tolist())
    cfg = tmp_path / name
    cfg.write_text(f"robot: fanuc_lrmate200i\ntools: [{tools}]\ndata: {{identification: {ident}}}\n"
                   f"model: {{order: {order}, backlash: true}}\nout: runs\nreport: false\n")
    return cfg


@pytest.fixture(scope="module")
def campaigns(robot, tmp_path_factory):
    """Two campaigns of one fleet on disk, the first fitted: (tmp, first run, second config, truths, data)."""
    from torchcal.app.fleet import run_fleet

    tmp = tmp_path_factory.mktemp("recheck")
    first = fleet_truths(robot, TOOLS, COUNT + 1, 0, []).truths
    names = [f"unit{k:02d}" for k in range(COUNT + 1)]
    _write_campaign(tmp / "year1", robot, first[:COUNT], names[:COUNT], 1, False)
    run1 = run_fleet(_config(tmp, "year1.yaml", "year1"), out=tmp / "run1")
    later = _second_campaign(first)
    keep = [k for k in range(COUNT + 1) if k != GONE]  # one unit gone, the last one new
    data2 = _write_campaign(tmp / "year2", robot, [later[k] for k in keep], [names[k] for k in keep], 2, True)
    return tmp, run1, _config(tmp, "year2.yaml", "year2"), (first, later, names, keep), data2


def _truth_change_mm(old_truth, new_truth, d) -> float:
    """RMS change of the true tool points at the second campaign's commands, rigidly aligned (the reference)."""
    with torch.no_grad():
        a = old_truth.points(d.q, d.tool, d.direction)
        b = new_truth.points(d.q, d.tool, d.direction)
        R, t = kabsch(a, b)
        return U.m_to_mm(float(((a @ R.T + t) - b).norm(dim=-1).pow(2).mean().sqrt()))


def test_recheck_names_the_crashed_and_the_swapped_unit(campaigns, robot):
    from torchcal.app.fleet import run_fleet

    tmp, run1, cfg2, (first, later, names, keep), data2 = campaigns
    res = run_fleet(cfg2, [f"fleet.baseline={run1.run_dir}"], out=tmp / "run2")
    rows = {r["unit"]: r for r in res.rows}
    changed = {c.unit for c in res.changes}
    assert changed == {names[CRASHED], names[SWAPPED]}
    swap = next(c for c in res.changes if c.unit == names[SWAPPED])
    assert swap.joints and swap.joints[0][:2] == ("joint3", "transmission error change")
    # every compared unit's change at the tool is the truth's own, but for the two fits' own model errors (order 3
    # on 90 poses: 0.02-0.04 mm more than the truth's 0.082 mm season)
    for k in keep[:-1]:
        name = names[k]
        truth = _truth_change_mm(first[k], later[k], data2[name])
        assert rows[name]["change_rms_mm"] == pytest.approx(truth, abs=0.05), name
        assert rows[name]["changed"] == (k in (CRASHED, SWAPPED))
    new = names[keep[-1]]
    assert "not in fleet.baseline" in rows[new]["change"] and "change_rms_mm" not in rows[new]
    assert any(names[GONE] in w and "not fitted in this run" in w for w in res.warnings)
    # the files: summary.csv's columns, changes.csv's rows (every compared unit: the tool and 2 x 6 joint rows)
    summary = pd.read_csv(res.run_dir / "summary.csv")
    assert {"change_rms_mm", "change_max_mm", "changed", "change"} <= set(summary.columns)
    changes = pd.read_csv(res.run_dir / "changes.csv")
    assert len(changes) == (len(keep) - 1) * 13
    tool_rows = changes[changes["joint"] == "tool"].set_index("unit")
    assert tool_rows.loc[names[SWAPPED], "robust_z"] > 5
    import json

    fleet = json.loads((res.run_dir / "fleet.json").read_text())
    assert fleet["baseline"] == str(run1.run_dir) and len(fleet["changes"]) == 2
    # the fleet report's section names both, and the units' table marks them
    from torchcal.report import render_report

    html = render_report(res.run_dir)
    assert "Changed since the baseline" in html
    section = html.split("Changed since the baseline", 1)[1].split("<section", 1)[0]
    assert names[CRASHED] in section.split("<svg", 1)[0] and names[SWAPPED] in section.split("<svg", 1)[0]
    assert names[0] not in section.split("<svg", 1)[0]
    # the strip charts: every compared unit a dot in the tool's chart, only the changed ones named in red
    tool_chart = section[section.index("Change at the tool since the baseline"):]
    tool_chart = tool_chart[:tool_chart.index("</svg>")]
    assert tool_chart.count('data-name="') == len(keep) - 1
    assert changes.loc[changes["joint"] == "tool", "beyond"].sum() >= 1


def test_baseline_of_another_structure_is_refused_before_the_solve(campaigns):
    from torchcal.app.fleet import run_fleet

    tmp, run1, _, _, _ = campaigns
    cfg = _config(tmp, "year2_order2.yaml", "year2", order=2)
    with pytest.raises(ConfigError, match="fleet.baseline.*another model structure"):
        run_fleet(cfg, [f"fleet.baseline={run1.run_dir}"], out=tmp / "refused")
    assert not (tmp / "refused").exists()  # refused before the run directory: no empty PARTIAL run left behind


def test_baseline_that_is_not_a_fleet_run_is_refused(campaigns):
    from torchcal.app.fleet import run_fleet

    tmp, _, cfg2, _, _ = campaigns
    with pytest.raises(ConfigError, match="fleet.baseline.*not a `torchcal fleet` run directory"):
        run_fleet(cfg2, [f"fleet.baseline={tmp / 'year1'}"], out=tmp / "refused2")


def test_an_unreadable_earlier_model_is_said_and_the_rest_compared(campaigns):
    """A baseline unit whose model.pt is broken (the first: the structure check before the solve reads the next
    one) is named with its file; every other unit is compared and every unit's new calibration is written (nothing
    fitted is lost)."""
    import shutil

    from torchcal.app.fleet import run_fleet

    tmp, run1, cfg2, (_, _, names, keep), _ = campaigns
    base = tmp / "run1_damaged"
    shutil.copytree(run1.run_dir, base)
    broken = base / "units" / names[0] / "model.pt"
    broken.write_bytes(broken.read_bytes()[:100])
    res = run_fleet(cfg2, [f"fleet.baseline={base}"], out=tmp / "run2b")
    rows = {r["unit"]: r for r in res.rows}
    assert "not compared" in rows[names[0]]["change"] and "model.pt" in rows[names[0]]["change"]
    assert "change_rms_mm" not in rows[names[0]]
    assert all("change_rms_mm" in rows[names[k]] for k in keep[:-1] if k != 0)
    assert {c.unit for c in res.changes} == {names[CRASHED], names[SWAPPED]}
    assert all((res.run_dir / "units" / names[k] / "model.pt").is_file() for k in keep)


def test_units_not_re_measured_are_left_out_of_the_fleets_changes(campaigns):
    """Only some units re-measured, the others' files kept: their change is zero by construction, and those zeros
    made the fleet's scatter vanish (a healthy re-measured unit scored z 1e10). Now they are named 'not
    re-measured' and left out; the crashed unit is still the one changed, no healthy one is."""
    import shutil

    from torchcal.app.fleet import run_fleet

    tmp, run1, _, (_, _, names, keep), _ = campaigns
    mixed = tmp / "mixed"
    shutil.copytree(tmp / "year1", mixed)
    again = [CRASHED, 0, 1, 3, 5]  # re-measured this year; 7 keeps last year's file
    for k in again:
        shutil.copy(tmp / "year2" / f"{names[k]}.csv", mixed / f"{names[k]}.csv")
    res = run_fleet(_config(tmp, "mixed.yaml", "mixed"), [f"fleet.baseline={run1.run_dir}"], out=tmp / "run_mixed")
    rows = {r["unit"]: r for r in res.rows}
    kept = [names[k] for k in range(COUNT) if k not in again]
    assert all(rows[n]["change"].startswith("not re-measured") for n in kept)
    assert any("not re-measured" in w and all(n in w for n in kept) for w in res.warnings)
    assert {c.unit for c in res.changes} == {names[CRASHED]}
    assert all(not rows[names[k]]["changed"] for k in again if k != CRASHED)
