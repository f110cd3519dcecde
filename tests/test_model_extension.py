"""A researcher's RobotModel subclass with an error term of its own: every evaluation path sees the term (the
fast backends used to freeze only the built-in terms: compensation converged 0.6 mm off, silently)."""

from __future__ import annotations

import pytest
import torch
from torch import nn

import torchcal
from conftest import random_commands, randomize
from torchcal.analysis.stats import point_residuals
from torchcal.compensate import compensate


class CrossCoupling(nn.Module):
    """dθ_j = a sin(u_i + u_j) + b cos(u_i + u_j) on one joint pair (a term torchcal's model does not have)."""

    def __init__(self, i: int, j: int):
        super().__init__()
        self.i, self.j = i, j
        self.coef = nn.Parameter(torch.tensor([1.4e-3, -1.0e-3], dtype=torch.float64))

    def forward(self, u: torch.Tensor) -> torch.Tensor:
        s = u[:, self.i] + u[:, self.j]
        return self.coef[0] * torch.sin(s) + self.coef[1] * torch.cos(s)


class CrossModel(torchcal.RobotModel):
    def __init__(self, *args, **kwargs):
        super().__init__(*args, **kwargs)
        self.cross = CrossCoupling(1, 2)

    def _variables(self, q, v):
        theta, u, comp = super()._variables(q, v)
        extra = torch.zeros_like(theta)
        extra[:, 2] = self.cross(u)
        return theta + extra, u, comp


class SaggingWrist(torchcal.RobotModel):
    """No module of its own, a fixed term in an overridden method (found by the override)."""

    def _variables(self, q, v):
        theta, u, comp = super()._variables(q, v)
        return theta + 1e-3 * torch.cos(theta[:, 1:2]) * (torch.arange(theta.shape[1]) == 4).to(theta), u, comp


@pytest.mark.parametrize("cls", [CrossModel, SaggingWrist])
def test_compensation_and_compiled_residuals_see_a_subclass_term(fanuc, tools_m, cls):
    model = cls(fanuc, tools_m, orders=2, backlash=True)
    randomize(model, 3)
    assert model.extended() and not torchcal.RobotModel(fanuc, tools_m, orders=2).extended()
    q = random_commands(fanuc, 300, 5)
    d = torch.where(torch.rand(q.shape, generator=torch.Generator().manual_seed(1), dtype=torch.float64) > 0.5,
                    1.0, -1.0)
    res = compensate(model, q, d, tool_set=False)
    ok = res.converged
    assert int(ok.sum()) > 250
    with torch.no_grad():
        got = model.flange(res.q[ok], d[ok])[:, :3, 3]  # in the measurement frame (base identity here)
        want = model.nominal_flange(q[ok])[:, :3, 3]
    assert float((got - want).norm(dim=1).max()) < 1e-9  # m: the subclass's flange lands, its term included
    tool = torch.zeros(40, dtype=torch.long)
    with torch.no_grad():  # points the nominal robot predicts: the residuals are the model's whole error
        data = torchcal.Measurements.from_tensors(q[:40], tool, model.nominal_points(q[:40], tool), direction=d[:40])
    compiled = point_residuals(model, data, compiled=True)
    plain = point_residuals(model, data, compiled=False)
    assert float((compiled - plain).abs().max()) < 1e-12


def test_a_saved_subclass_says_how_to_load_it(fanuc, tools_m, tmp_path):
    """load_model cannot know a researcher's class: it says so (it raised torch's state-dict error), and the
    documented way back gives the same model."""
    from torchcal.io.rundir import RunDirError, load_model, save_model

    model = CrossModel(fanuc, tools_m, orders=2)
    randomize(model, 4)
    save_model(tmp_path, model)
    with pytest.raises(RunDirError, match=r"model.pt: the saved parameters do not fit a RobotModel \(it has no "
                                          r"cross.coef: saved from a subclass\?"):
        load_model(tmp_path)
    again = CrossModel(fanuc, tools_m, orders=2)
    again.load_state_dict(torch.load(tmp_path / "model.pt", weights_only=True)["state_dict"])
    q = random_commands(fanuc, 10, 1)
    with torch.no_grad():
        assert torch.equal(again.flange(q), model.flange(q))
