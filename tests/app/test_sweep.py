"""torchcal sweep: grids of configs in one run directory, each cell equal to its own fit."""

from __future__ import annotations

import json

import pytest

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
    assert (res.run_dir / "cells" / "03" / "model.pt").exists()
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
