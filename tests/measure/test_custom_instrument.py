"""A researcher's instrument written from the docs alone (dim, observed, weight, predict): it fits without
subset() / to() of its own, and parameters it holds are said not to be estimated."""

from __future__ import annotations

import logging

import torch

import torchcal
from torchcal.measure import Instrument
from torchcal.measure.weights import IsotropicWeight

STATIONS = torch.tensor([[1.5, 0.0, 0.2], [0.0, 1.5, 0.4], [-1.2, -0.8, 0.1], [0.3, -1.4, 1.2]], dtype=torch.float64)


class Multilateration(Instrument):
    """Distances (m) from four fixed stations to the tool point: d = 4 per row, no x, y, z."""

    dim = 4

    def __init__(self, distances, stations, sigma=2e-5):
        self.observed = distances
        self.stations = stations
        self.weight = IsotropicWeight(sigma)

    def predict(self, model, q, tool, direction=None, v=None):
        p = model.points(q, tool, direction, v)
        return (p[:, None, :] - self.stations[None].to(p)).norm(dim=-1)


def _data(robot, tools, count, seed):
    truth = torchcal.TruthRobot.fanuc_paper2(robot, tools, seed)
    q = torchcal.sim.quasi_random_commands(robot.joint_map.limits, count, seed)
    data = torchcal.simulate(truth, q, [0], torchcal.NoiseModel.from_robot(robot), seed)
    return data, (data.xyz[:, None, :] - STATIONS[None]).norm(dim=-1)


def test_a_minimal_instrument_fits_and_its_rows_can_be_taken_apart(caplog):
    robot = torchcal.load_robot("fanuc_lrmate200i")
    tools = torch.tensor([[0.033, 0.058, 0.161]], dtype=torch.float64)
    data, dist = _data(robot, tools, 60, 0)
    inst = Multilateration(dist, STATIONS)
    half = inst.subset(torch.arange(30))  # the default subset: the per-row tensors, not the stations
    assert half.observed.shape == (30, 4) and torch.equal(half.stations, STATIONS)
    model = torchcal.RobotModel(robot, tools, orders=1)
    with torch.no_grad():
        before = float((model.points(data.q, data.tool) - data.xyz).norm(dim=1).mean())
    res = torchcal.fit(model, data, torchcal.NoiseModel.from_robot(robot), instrument=inst)
    with torch.no_grad():
        after = float((model.points(data.q, data.tool) - data.xyz).norm(dim=1).mean())
    assert res.success and after < 0.2 * before  # the points the distances imply are modeled
    assert "does not estimate" not in caplog.text


def test_parameters_an_instrument_holds_are_said_not_to_be_estimated(caplog):
    robot = torchcal.load_robot("fanuc_lrmate200i")
    tools = torch.tensor([[0.033, 0.058, 0.161]], dtype=torch.float64)
    data, dist = _data(robot, tools, 30, 1)
    inst = Multilateration(dist, torch.nn.Parameter(STATIONS + 1e-3))
    assert inst.own_parameters() == ["stations"]
    with caplog.at_level(logging.WARNING, logger="torchcal"):
        torchcal.fit(torchcal.RobotModel(robot, tools, orders=1), data, torchcal.NoiseModel.from_robot(robot),
                     instrument=inst)
    assert "Multilateration holds parameters (stations) that the fit does not estimate" in caplog.text


def test_an_nn_module_instrument_must_write_its_own_subset_and_to():
    """The defaults walk plain attributes: a Module's buffers would be missed (a subset kept all its rows)."""
    import pytest

    class ModInst(Multilateration, torch.nn.Module):
        def __init__(self, distances):
            torch.nn.Module.__init__(self)
            self.register_buffer("observed", distances)
            self.stations = STATIONS
            self.weight = IsotropicWeight(2e-5)

    inst = ModInst(torch.ones(10, 4, dtype=torch.float64))
    with pytest.raises(NotImplementedError, match="ModInst is an nn.Module.*write its own subset"):
        inst.subset(torch.arange(4))
    with pytest.raises(NotImplementedError, match="write its own to"):
        inst.to("cpu")
