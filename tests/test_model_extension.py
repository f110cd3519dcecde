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


class ShiftedFlange(torchcal.RobotModel):
    """A Cartesian term by overriding flange (as DEVELOPING.md describes): here a known, fixed offset (a buffer),
    so the closed-form Jacobians hold every parameter group and nothing fell back to autograd by itself."""

    def __init__(self, *args, **kwargs):
        super().__init__(*args, **kwargs)
        self.register_buffer("shift", torch.tensor([1e-3, -0.5e-3, 0.2e-3], dtype=torch.float64))

    def flange(self, q, direction=None, v=None, base: bool = True):
        F = super().flange(q, direction, v, base).clone()
        F[:, :3, 3] = F[:, :3, 3] + self.shift
        return F


def test_fit_takes_autograd_for_a_subclass_term_and_the_batched_solver_refuses(fanuc, tools_m):
    """The closed-form Jacobians know only the paper's terms: a subclass's flange override was fitted 1 mm off,
    with success. Now fit differentiates the model itself and reaches the data; fit_batch says it cannot."""
    from torchcal.identify.batched import fit_batch

    truth = ShiftedFlange(fanuc, tools_m, orders=1)
    randomize(truth, 2)
    q = random_commands(fanuc, 60, 4)
    tool = torch.arange(60) % tools_m.shape[0]
    with torch.no_grad():
        data = torchcal.Measurements.from_tensors(q, tool, truth.points(q, tool))
    model = ShiftedFlange(fanuc, tools_m, orders=1)
    assert model.extended() and not model.closed_form()
    assert torchcal.RobotModel(fanuc, tools_m, orders=1).closed_form()
    res = torchcal.fit(model, data, torchcal.NoiseModel.from_robot(fanuc))
    with torch.no_grad():
        miss = float((model.points(q, tool) - data.xyz).norm(dim=1).max())
    assert res.success and miss < 1e-6  # m: the closed form ended 1 mm off here
    with pytest.raises(ValueError, match="fit_batch needs closed-form Jacobians"):
        fit_batch(ShiftedFlange(fanuc, tools_m, orders=1), [ShiftedFlange(fanuc, tools_m, orders=1)], data)


def test_a_sensor_rig_around_a_subclass_takes_autograd(fanuc):
    """The rig's closed-form pose Jacobians go through the wrapped model's chain, which knows the paper's terms
    only: a rig around ShiftedFlange linearized without its shift (the residual itself 1 mm off), silently. The
    instrument now declines the closed form for it and linearizes exactly as autograd does."""
    from torchcal.identify import CalibrationProblem, NoiseModel, Prior
    from torchcal.measure import STSInstrument
    from torchcal.measure.base import closed_form_declined
    from torchcal.models.sensor_rig import SensorRig
    from torchcal.sim.sensor_truth import SensorTruth

    st = SensorTruth(fanuc, seed=3)
    s = st.sample_commands(15, seed=3)
    m = st.measure_sts(s.q, s.direction, seed=4)

    def rig(cls):
        inner = cls(fanuc, torch.zeros(1, 3, dtype=torch.float64), orders=1, backlash=True)
        r = SensorRig(inner, mount=st.mount_nominal, gravity=st.virtual_level)
        randomize(inner, 5)
        return r

    plain, shifted = rig(torchcal.RobotModel), rig(ShiftedFlange)
    assert not closed_form_declined(plain) and closed_form_declined(shifted)
    inst = STSInstrument.from_measurements(m, gravity=st.virtual_level)
    P = CalibrationProblem(shifted, m, NoiseModel.from_robot(fanuc), Prior(), instrument=inst)
    x, v = P.layout.get(), P.v_zero()
    f, A, C = P.linearize(x, v)
    fa, Aa, Ca = P.linearize(x, v, "autodiff")
    assert torch.equal(f, fa) and torch.equal(A, Aa) and torch.equal(C, Ca)
    with torch.no_grad():  # the shift is in the residual the instrument sees (what the closed form left out)
        p = shifted.sensor_pose(m.q, None, m.direction)[:, :3, 3]
        p0 = plain.sensor_pose(m.q, None, m.direction)[:, :3, 3]
    assert float((p - p0).norm(dim=1).min()) > 1e-3
    assert inst.predict_jacobians(plain, m.q, m.tool, m.direction, None) is not None
