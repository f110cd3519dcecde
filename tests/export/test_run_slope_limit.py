"""export-tables judges the tables' end slopes against the run's own constraint c, not always Paper I's 0.4 mm."""

import json

import pytest

from torchcal.export.controller import run_slope_limit_mm


@pytest.mark.parametrize("content, want", [
    ({"c": 0.8}, 0.84), ({"c": None}, 0.4), ({"c": 0.2}, 0.21), (None, 0.4),
])
def test_limit_follows_the_runs_constraint(tmp_path, content, want):
    if content is not None:
        (tmp_path / "constraint.json").write_text(json.dumps(content))
    assert run_slope_limit_mm(tmp_path) == pytest.approx(want)
