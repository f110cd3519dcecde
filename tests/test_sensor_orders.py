"""model.order: auto on a 6-DOF sensor run (Paper III): the order search on the sensor's own residuals."""

from __future__ import annotations

import json

import pytest
import torch
import yaml
from typer.testing import CliRunner

from torchcal.cli import app


def test_sensor_run_chooses_its_orders(tmp_path, fanuc, one_thread):
    from torchcal.io.sensor_csv import write_pose_measurements
    from torchcal.sim import SensorTruth

    truth = SensorTruth(fanuc, 1)
    sample = truth.sample_commands(70, 1)
    data = truth.measure_sts(sample.q, sample.direction, 1)
    ident, val = data.subset(torch.arange(0, 50)), data.subset(torch.arange(50, 70))
    write_pose_measurements(tmp_path / "ident.csv", ident, fanuc)
    write_pose_measurements(tmp_path / "val.csv", val, fanuc)
    means = {}
    for order in ("auto", 0, 2):
        cfg = {"robot": "fanuc_lrmate200i", "sensor": {"kind": "sts"}, "plots": False,
               "model": {"order": order, "backlash": False, "candidates": [0, 1, 2]},
               "data": {"identification": "ident.csv", "validation": "val.csv"}, "out": f"run_{order}"}
        (tmp_path / f"{order}.yaml").write_text(yaml.safe_dump(cfg))
        r = CliRunner().invoke(app, ["fit", str(tmp_path / f"{order}.yaml"), "-q"])
        assert r.exit_code == 0, r.output
        metrics = json.loads((tmp_path / f"run_{order}" / "metrics.json").read_text())
        means[order] = metrics["sets"]["validation"]["position_mm"]["modeled"]["mean"]
    chosen = json.loads((tmp_path / "run_auto" / "orders.json").read_text())
    assert chosen["criterion"] == "loo" or chosen["criterion"] == "validation"
    assert all(o in (0, 1, 2) for o in chosen["orders"])
    # the search lands at least as well as the better of the fixed extremes (within the criterion's noise)
    assert means["auto"] <= 1.05 * min(means[0], means[2])
