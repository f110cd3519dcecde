"""model.order: auto on a machine tool (Paper I's axis perturbation model): the same search as for robots."""

from __future__ import annotations

import json

import torch

from torchcal.app.config import make_config
from torchcal.app.fit import run_fit
from torchcal.sim.machine_truth import MachineTruth, simulate_machine_dataset, write_machine_csv


def test_machine_run_chooses_orders_per_axis(tmp_path, one_thread):
    data, split = simulate_machine_dataset(MachineTruth(seed=3), n_commands=80, n_interpolation=20,
                                           n_extrapolation=5, seed=3)
    write_machine_csv(tmp_path / "ident.csv", data.subset(split["identification"]))
    write_machine_csv(tmp_path / "val.csv", data.subset(split["interpolation"]))
    means = {}
    for order in ("auto", 0, 3):
        cfg = make_config({"robot": "five_axis_xyzcb", "tools": [[0, 0, 402.9], [0, 0, 500.9]],
                           "model": {"kind": "axis_perturbation", "order": order, "candidates": [0, 1, 2, 3]},
                           "data": {"identification": "ident.csv", "validation": "val.csv"},
                           "noise": {"sigma_m": 0.02}, "plots": False, "out": f"run_{order}"}, base_dir=tmp_path)
        res = run_fit(cfg)
        means[order] = res.metrics["sets"]["validation"]["modeled"]["mean"]
    chosen = json.loads((tmp_path / "run_auto" / "orders.json").read_text())
    assert chosen["criterion"] == "validation" and len(chosen["orders"]) == 5
    assert means["auto"] <= 1.02 * min(means[0], means[3])
