"""The compensate command's options: a large correction bound is not a large Newton step."""

import math

import pytest
import torch

from torchcal.app.files import run_compensation_options


@pytest.mark.parametrize("bound_deg, step_deg", [(30.0, 5.0), (2.0, 2.0)])
def test_the_step_bound_is_the_smaller_of_the_correction_bound_and_the_default_step(tmp_path, bound_deg, step_deg):
    prismatic = torch.tensor([False, False, True])
    opts = run_compensation_options(tmp_path / "no_run", max_correction_deg=bound_deg, prismatic=prismatic)
    want_c = torch.tensor([math.radians(bound_deg)] * 2 + [bound_deg * 1e-3], dtype=torch.float64)
    want_s = torch.tensor([math.radians(step_deg)] * 2 + [step_deg * 1e-3], dtype=torch.float64)
    torch.testing.assert_close(torch.as_tensor(opts["max_correction"]), want_c)
    torch.testing.assert_close(torch.as_tensor(opts["max_step"]), want_s)
    plain = run_compensation_options(tmp_path / "no_run", max_correction_deg=bound_deg)
    assert plain["max_step"] == pytest.approx(math.radians(step_deg))
