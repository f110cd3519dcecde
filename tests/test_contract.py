"""The model contract (torchcal.core.contract): which model can do what, and a clear refusal otherwise."""

from __future__ import annotations

import pytest
import torch

import torchcal
from torchcal.core.contract import CalibratedModel, PredictsPoints, capabilities, require
from torchcal.models.machine import MachineModel
from torchcal.models.sensor_rig import SensorRig

Z = torch.zeros(1, 3, dtype=torch.float64)


@pytest.fixture(scope="module")
def models():
    fanuc = torchcal.load_robot("fanuc_lrmate200i")
    return {
        "robot": torchcal.RobotModel(fanuc, Z, orders=1),
        "machine": MachineModel(torchcal.load_robot("five_axis_xyzcb"), Z, orders=1),
        "sensor": SensorRig.for_robot(fanuc, orders=1),
    }


def test_every_model_is_a_calibrated_model_with_its_own_capabilities(models):
    assert all(isinstance(m, CalibratedModel) for m in models.values())
    assert capabilities(models["robot"]) == ["predict points", "compensate commands"]
    assert capabilities(models["machine"]) == ["predict points", "export tables"]
    assert capabilities(models["sensor"]) == []


@pytest.mark.parametrize("kind, capability, hint", [
    ("machine", "compensate commands", "export-tables"),
    ("sensor", "compensate commands", "sensor rig"),
    ("robot", "export tables", "torchcal compensate"),
    ("sensor", "predict points", "sensor_pose"),
])
def test_refusals_say_what_the_model_is_and_what_to_do(models, kind, capability, hint):
    with pytest.raises(TypeError) as e:
        require(models[kind], capability, "who")
    msg = str(e.value)
    assert msg.startswith("who: ") and type(models[kind]).__name__ in msg and f"cannot {capability}" in msg
    assert hint in msg


def test_compensate_refuses_a_machine_model_through_the_contract(models):
    q = torch.zeros(2, 5, dtype=torch.float64)
    with pytest.raises(TypeError, match="MachineModel cannot compensate commands"):
        torchcal.compensate(models["machine"], q)


def test_a_users_own_model_that_keeps_the_contract_is_accepted():
    """Structural typing: a model of the user's own that has the methods needs no torchcal base class."""

    class Mine:
        def points(self, q, tool=None, direction=None, v=None):
            return torch.zeros(q.shape[0], 3)

        def flange(self, q, direction=None, v=None):
            return torch.eye(4).expand(q.shape[0], 4, 4)

        def nominal_points(self, q, tool):
            return torch.zeros(q.shape[0], 3)

        def parameter_groups(self):
            return []

        def spec(self):
            return {}

    assert isinstance(Mine(), PredictsPoints)
    require(Mine(), "predict points")
    with pytest.raises(ValueError, match="unknown capability"):
        require(Mine(), "fly")


def test_export_tables_refuses_a_robot_run(tmp_path, models):
    from torchcal.export.controller import export_run_tables
    from torchcal.io.rundir import RunDirError, save_model

    save_model(tmp_path, models["robot"])
    with pytest.raises(RunDirError, match="RobotModel cannot export tables"):
        export_run_tables(tmp_path, tmp_path / "t.csv")


def test_capabilities_do_not_depend_on_static_lookup(models):
    """From Python 3.12 isinstance() with a protocol looks members up statically and misses an nn.Module's
    submodules (a machine's axis_errors): the contract looks them up as attribute access does."""
    import inspect

    from torchcal.core.contract import ExportsTables, implements

    machine = models["machine"]
    assert implements(machine, ExportsTables)
    with pytest.raises(AttributeError):
        inspect.getattr_static(machine, "axis_errors")  # what a static lookup sees: nothing


def test_compensation_backends_read_only_the_snapshot_the_model_hands_out():
    """The flange backend is built from ``flange_snapshot()`` alone: a snapshot gives the numbers the model gives,
    and changing the model afterwards does not change a kernel built before (the snapshot is a copy)."""
    from torchcal.compensate.kernel import FlangeKernel

    robot = torchcal.RobotModel(torchcal.load_robot("fanuc_lrmate200i"), Z, orders=1)
    g = torch.Generator().manual_seed(3)
    with torch.no_grad():
        robot.joint_errors.coef.normal_(0.0, 1e-3, generator=g)
    q = (torch.rand(64, robot.n, generator=g, dtype=torch.float64) - 0.5) * 2.0
    snap = robot.flange_snapshot()
    kernel = FlangeKernel(snap, fused=False)
    R, p = kernel.flange(q.T.contiguous())
    F = robot.flange(q, base=False)
    assert torch.allclose(R.permute(2, 0, 1), F[:, :3, :3], atol=1e-12)
    assert torch.allclose(p.T, F[:, :3, 3], atol=1e-12)
    with torch.no_grad():
        robot.joint_errors.coef.add_(1e-2)
    R2, p2 = kernel.flange(q.T.contiguous())
    assert torch.equal(p2, p) and not torch.allclose(robot.flange(q, base=False)[:, :3, 3], F[:, :3, 3])
