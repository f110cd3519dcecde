"""torchcal sweep: grids of configs in one run directory, each cell equal to its own fit."""

from __future__ import annotations

import importlib.util
import json

import pytest
import torch

from torchcal.app.sweep import parse_grid, run_sweep
from torchcal.app.config import ConfigError, load_config
from torchcal.app.fit import run_fit
from torchcal.app.simulate import simulate_dataset


def test_parse_grid_axes_ranges_and_plain_overrides():
    plain, axes = parse_grid(["model.order=2:6:2", "noise.sigma_m=0.005,0.01", "model.order2=[1,2]", "seed=3"])
    assert axes == [("model.order", ["2", "4", "6"]), ("noise.sigma_m", ["0.005", "0.01"])]
    assert plain == ["model.order2=[1,2]", "seed=3"]
    with pytest.raises(ConfigError):
        parse_grid(["model.order=5:2"])
    with pytest.raises(ConfigError):
        parse_grid(["model.order"])
    # one key as an axis and as one value: which would win is not obvious, so neither does
    with pytest.raises(ConfigError, match="'model.order' is given both as a grid axis and as one value"):
        parse_grid(["model.order=1:3", "seed=1", "model.order=5"])


@pytest.fixture(scope="module")
def sim(tmp_path_factory):
    d = tmp_path_factory.mktemp("sweep")
    paths = simulate_dataset(d / "sim", identification=40, validation=20, seed=4, order=2)
    return paths["config"]


def test_sweep_cells_equal_their_own_fits(sim, tmp_path):
    res = run_sweep(sim, ["model.order=1:2", "data.n_poses=25,40", "data.truth=null"], out=tmp_path / "sw")
    assert len(res.rows) == 4
    assert (res.run_dir / "results.csv").exists() and (res.run_dir / "plots" / "sweep.png").exists()
    assert json.loads((res.run_dir / "sweep.json").read_text())["cells"] == 4
    from torchcal.io.rundir import file_sha256

    hashes = json.loads((res.run_dir / "data_hashes.json").read_text())  # what its cells read
    assert hashes["data.identification"]["sha256"] == file_sha256(hashes["data.identification"]["path"])
    assert (res.run_dir / "cells" / "03" / "model.pt").exists()
    # a stacked cell's model keeps the span of its own first N poses' commands (what extrapolation is judged by)
    import pandas as pd
    from torchcal.io.rundir import load_model

    cell = next(r for r in res.rows if r["data.n_poses"] == "25")
    ident = pd.read_csv(sim.parent / "identification.csv")
    first = ident[ident.pose.isin(ident.pose.drop_duplicates().iloc[:25])][[f"q{i}" for i in range(1, 7)]]
    span = load_model(res.run_dir / "cells" / f"{cell['cell']:02d}").data_span * 180.0 / 3.141592653589793
    assert torch.allclose(span[:, 1], torch.tensor(first.max().to_numpy()), atol=1e-9)
    # what an engine sends out: one group per model structure (each the batched solve of its pose counts)
    assert "4 cells over model.order, data.n_poses: 2 independent group(s)" in (res.run_dir / "run.log").read_text()
    for row in res.rows:
        cfg = load_config(sim, [f"model.order={row['model.order']}", f"data.n_poses={row['data.n_poses']}",
                                "data.truth=null", f"out={tmp_path / ('alone' + str(row['cell']))}"])
        alone = run_fit(cfg)
        ref = alone.metrics["sets"]["validation"]["modeled"]["mean"]
        assert row["converged"]
        assert abs(row["validation_mean_mm"] / ref - 1) < 0.01  # the bar; measured ~1e-4


def test_cells_that_cannot_be_stacked_run_alone(sim, tmp_path):
    res = run_sweep(sim, ["model.order=1,auto", "data.truth=null", "model.candidates=[1,2]"], out=tmp_path / "sw2")
    auto = [r for r in res.rows if r["model.order"] == "auto"][0]
    assert (res.run_dir / "cells" / f"{auto['cell']:02d}" / "metrics.json").exists()
    assert auto["validation_mean_mm"] > 0


def _broken_copy(src, dst, row=5, column="y"):
    """A copy of the measurement file ``src`` with one cell of ``column`` (data row ``row``, 1-based) not a number."""
    lines = src.read_text().splitlines()
    header = lines[0].split(",")
    cells = lines[row].split(",")
    cells[header.index(column)] = "n/a"
    lines[row] = ",".join(cells)
    dst.write_text("\n".join(lines) + "\n")
    return dst


def test_a_failing_cell_is_reported_and_the_others_finish(sim, tmp_path):
    """A cell whose data file is broken gets status 'failed' with the reason naming the file, row and column;
    the other cells are fitted and written, results.csv holds every cell."""
    import pandas as pd

    cfg = load_config(sim)
    good = cfg.data.identification
    from pathlib import Path

    bad = _broken_copy(Path(good), tmp_path / "broken.csv")
    res = run_sweep(sim, [f"data.identification={good},{bad}", "model.order=1", "data.truth=null"],
                    out=tmp_path / "sw")
    by_file = {r["data.identification"]: r for r in res.rows}
    assert by_file[str(good)]["status"] == "fitted" and by_file[str(good)]["validation_mean_mm"] > 0
    failed = by_file[str(bad)]
    assert failed["status"] == "failed"
    assert "broken.csv" in failed["reason"] and "row 5" in failed["reason"] and "'y'" in failed["reason"]
    table = pd.read_csv(res.run_dir / "results.csv")
    assert sorted(table["status"]) == ["failed", "fitted"]
    assert (res.run_dir / "cells" / f"{by_file[str(good)]['cell']:02d}" / "model.pt").exists()
    assert "1 of 2 cells failed" in (res.run_dir / "run.log").read_text()


def test_the_engine_is_not_a_grid_axis(sim, tmp_path):
    with pytest.raises(ConfigError, match="sweep.engine"):
        run_sweep(sim, ["model.order=1,2", "sweep.engine=local,ray"], out=tmp_path / "sw")
    with pytest.raises(ConfigError, match="sweep.engine"):
        run_sweep(sim, ["model.order=1,2", "sweep.engine=spark"], out=tmp_path / "sw2")


@pytest.mark.skipif(importlib.util.find_spec("ray") is None, reason="Ray not installed (pip install 'torchcal[ray]')")
def test_ray_engine_matches_local(sim, tmp_path):
    """sweep.engine=ray (a local Ray, 2 workers) computes what the local engine computes, bit for bit: the
    stacked groups and a cell fitted alone (automatic orders)."""
    import ray
    import torch

    from torchcal.io.rundir import load_model

    grid = ["model.order=1,2,auto", "data.n_poses=25,40", "data.truth=null", "model.candidates=[1,2]"]
    local = run_sweep(sim, grid, out=tmp_path / "local")
    ray.init(num_cpus=2, include_dashboard=False, log_to_driver=False)
    try:
        remote = run_sweep(sim, grid + ["sweep.engine=ray"], out=tmp_path / "ray")
    finally:
        ray.shutdown()
    assert len(local.rows) == len(remote.rows) == 6
    for a, b in zip(local.rows, remote.rows):
        assert a["status"] == b["status"] == "fitted"
        for key in ("iterations", "cost", "identification_mean_mm", "validation_mean_mm"):
            assert a[key] == b[key], (a["cell"], key)
        ma = load_model(local.run_dir / "cells" / f"{a['cell']:02d}")
        mb = load_model(remote.run_dir / "cells" / f"{b['cell']:02d}")
        for (k, x), (_, y) in zip(ma.state_dict().items(), mb.state_dict().items()):
            assert torch.equal(x, y), (a["cell"], k)
    assert "engine ray" in (remote.run_dir / "run.log").read_text()


def test_sweep_interrupted_keeps_the_cells_it_fitted(sim, tmp_path, monkeypatch):
    """Ctrl-C during the second group: the first group's cells are in results.csv and cells/, the others are
    named as interrupted, the run stays marked PARTIAL and the interrupt goes on to the caller."""
    import pandas as pd

    import torchcal.app.sweep as sweep_app
    from conftest import ctrl_c_on_call

    ctrl_c_on_call(monkeypatch, sweep_app, "sweep_group")
    with pytest.raises(KeyboardInterrupt) as info:
        run_sweep(sim, ["model.order=1:2", "data.n_poses=25,40", "data.truth=null"], out=tmp_path / "cut")
    run = tmp_path / "cut"
    assert info.value.run_dir == run and (run / "PARTIAL").exists()
    table = pd.read_csv(run / "results.csv")
    done = table[table["status"] == "fitted"]
    assert list(done["model.order"]) == [1, 1] and (table["status"] == "failed").sum() == 2
    assert table[table["status"] == "failed"]["reason"].str.startswith("Interrupted").all()
    assert all((run / "cells" / f"{c:02d}" / "model.pt").exists() for c in done["cell"])


def test_a_cell_asking_more_poses_than_the_file_fails_alone(sim, tmp_path):
    """One cell's n_poses beyond the file's 40 poses is that cell's failure, named; the cells stacked with it in
    one batched solve are still fitted. When no cell can be fitted the sweep fails (as a fleet does), its table
    written."""
    res = run_sweep(sim, ["data.n_poses=20,30,50", "model.order=1", "data.truth=null"], out=tmp_path / "sw")
    status = {r["data.n_poses"]: r["status"] for r in res.rows}
    assert status == {"20": "fitted", "30": "fitted", "50": "failed"}
    bad = [r for r in res.rows if r["status"] == "failed"][0]
    assert "override 'data.n_poses=50'" in bad["reason"] and "50 poses asked for" in bad["reason"]
    with pytest.raises(ConfigError, match="sweep: no cell could be fitted; cell 0: .*60 poses asked for"):
        run_sweep(sim, ["data.n_poses=60,70", "model.order=1", "data.truth=null"], out=tmp_path / "none")
    assert (tmp_path / "none" / "results.csv").is_file()


def test_ray_engine_without_ray_fails_before_any_run_directory(sim, tmp_path, monkeypatch):
    """The optional extra missing: one message naming the key, and no PARTIAL run directory left behind."""
    import importlib.util
    import sys

    real = importlib.util.find_spec
    monkeypatch.delitem(sys.modules, "ray", raising=False)
    monkeypatch.setattr(importlib.util, "find_spec", lambda name, *a: None if name == "ray" else real(name, *a))
    with pytest.raises(ConfigError, match=r"override 'sweep.engine=ray' .*key 'sweep.engine': ray needs Ray installed"):
        run_sweep(sim, ["model.order=1,2", "sweep.engine=ray"], out=tmp_path / "sw")
    assert not (tmp_path / "sw").exists()


def test_a_mistyped_range_is_named(sim, tmp_path):
    with pytest.raises(ConfigError, match="'model.order=a:b' is no range: lo:hi\\[:step\\] takes integers"):
        run_sweep(sim, ["model.order=a:b"], out=tmp_path / "sw")
    with pytest.raises(ConfigError, match="'model.order=' gives no values"):
        run_sweep(sim, ["model.order="], out=tmp_path / "sw")
    assert not (tmp_path / "sw").exists()


def test_joints_in_radians_are_refused_once_before_any_run_directory(sim, tmp_path):
    """A data file whose joints are radians fails every cell alike: it is refused up front, naming the file,
    with no PARTIAL sweep left behind; data.units_checked=true lets it through as the user's word."""
    import math

    import pandas as pd

    from torchcal.io.unit_checks import UnitsError

    ident = pd.read_csv(sim.parent / "identification.csv")
    qcols = [c for c in ident.columns if c.startswith("q")]
    ident[qcols] = ident[qcols] * math.pi / 180.0
    path = tmp_path / "rad.csv"
    ident.to_csv(path, index=False)
    with pytest.raises(UnitsError, match="rad.csv"):
        run_sweep(sim, ["model.order=1,2", f"data.identification={path}", "data.truth=null"], out=tmp_path / "sw")
    assert not (tmp_path / "sw").exists()
