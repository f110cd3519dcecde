"""3-DOF compensation (position_only) for models fitted from one measured point per pose.

One reflector fixes the modeled flange's orientation only up to a constant turn that the tool vector takes back:
two such models predict the same points everywhere, and the commands must not depend on which one the fit chose.
"""

import math

import numpy as np
import pandas as pd
import pytest
import torch
from typer.testing import CliRunner

from tests.conftest import random_commands, randomize, write_targets
from torchcal.compensate import compensate, observed_dof
from torchcal.compensate.targets import compensate_targets
from torchcal.kinematics.transforms import homogeneous
from torchcal.models.robot import RobotModel

TOOL = [[0.06, 0.03, 0.12]]  # one reflector, off the J6 axis (m)


def _turned_twin(fanuc, angle):
    """A one-tool model and its exact twin whose flange is turned by ``angle`` (rad) about J6's axis (a turn that
    commutes with the joint), the tool vector turned back: every tool point is the same, the flange orientation
    differs everywhere by the turn."""
    tool = torch.tensor(TOOL, dtype=torch.float64)
    model = randomize(RobotModel(fanuc, tool, orders=3, backlash=False), 11)
    with torch.no_grad():
        model.joint_errors.coef[5] = 0.0  # E_6 is then the turn alone
    twin = randomize(RobotModel(fanuc, tool, orders=3, backlash=False), 11)
    twin.load_state_dict(model.state_dict())
    q0 = random_commands(fanuc, 1, 3)
    with torch.no_grad():
        F0 = model.flange(q0, base=False)
        # the constant term of E_6's rotation about the joint axis: set through the series' value at q0
        axis = model.axes[5].to(torch.float64)
        twin.joint_errors.coef[5, :3, 0] = 1.0
        unit = twin.joint_errors.twists(twin.error_variables(q0), None)[0, 5, :3]  # the constant term per unit
        twin.joint_errors.coef[5, :3, 0] = angle * axis / unit
        M = torch.linalg.solve(F0, twin.flange(q0, base=False))[0]  # F_twin = F M (a constant right factor)
        t = model.tools()[0]
        t_twin = M[:3, :3].T @ (t - M[:3, 3])
        twin.tools.delta[0] = t_twin - twin.tools.nominal[0]
    return model, twin


def _tool_point(model, q, t):
    with torch.no_grad():
        F = model.flange(q, base=False)
    return (F[:, :3, :3] @ t)[..., 0] + F[:, :3, 3] if t.ndim == 3 else F[:, :3, :3] @ t + F[:, :3, 3]


def test_observed_dof_counts_what_the_tools_see(fanuc):
    def dof(tools):
        return observed_dof(RobotModel(fanuc, torch.tensor(tools, dtype=torch.float64), orders=0))

    assert dof([[0.0, 0.0, 0.1]]) == (3, None)
    assert dof([[0.0, 0.0, 0.1], [0.0, 0.0, 0.1]])[0] == 3  # two tools at one point
    d, axis = dof([[0.0, 0.0, 0.1], [0.05, 0.0, 0.1]])
    assert d == 5 and torch.allclose(axis.abs(), torch.tensor([1.0, 0.0, 0.0], dtype=torch.float64))
    d, axis = dof([[0.0, 0.0, 0.1], [0.0, 0.0, 0.2], [0.0, 0.0, 0.3]])  # three on one line
    assert d == 5 and torch.allclose(axis.abs(), torch.tensor([0.0, 0.0, 1.0], dtype=torch.float64))
    assert dof([[0.0, 0.0, 0.1], [0.05, 0.0, 0.1], [0.0, 0.05, 0.1]]) == (6, None)


def test_observed_dof_counts_only_the_tools_the_fit_measured(fanuc, tmp_path):
    """A config of three tools whose data measured tool 0 only: one point per pose, so 3-DOF (the three tools'
    vectors said 6, and 'auto' restored an orientation nobody measured: 4 deg of joint motion); the fit records
    the measured tools and a saved run keeps them."""
    import torchcal
    from torchcal.io.rundir import load_model, save_model

    tools = torch.tensor([[0.0, 0.0, 0.1], [0.05, 0.0, 0.1], [0.0, 0.05, 0.1]], dtype=torch.float64)
    truth = torchcal.TruthRobot.fanuc_paper2(fanuc, tools, 0)
    q = torchcal.sim.quasi_random_commands(fanuc.joint_map.limits, 40, 0)
    noise = torchcal.NoiseModel.from_robot(fanuc)
    model = RobotModel(fanuc, tools, orders=1)
    assert observed_dof(model) == (6, None) and model.measured_tools is None  # nothing known yet: every tool
    torchcal.fit(model, torchcal.simulate(truth, q, [0], noise, 0), noise, fixed=("tools",))
    assert model.measured_tools == [0] and observed_dof(model) == (3, None)
    save_model(tmp_path, model)
    assert observed_dof(load_model(tmp_path)) == (3, None)
    torchcal.fit(model, torchcal.simulate(truth, q, [0, 1, 2], noise, 0), noise)
    assert model.measured_tools == [0, 1, 2] and observed_dof(model) == (6, None)


def test_two_one_tool_models_that_predict_the_same_points_give_the_same_3dof_commands(fanuc):
    model, twin = _turned_twin(fanuc, math.radians(3.0))
    q = random_commands(fanuc, 300, 5)
    tool = torch.zeros(300, dtype=torch.long)
    with torch.no_grad():
        assert torch.allclose(model.points(q, tool), twin.points(q, tool), atol=1e-12, rtol=0)
        assert float((model.flange(q)[:, :3, :3] - twin.flange(q)[:, :3, :3]).abs().max()) > 0.03  # 3 deg apart
    a = compensate(model, q, position_only=True, tool_point=model.tools()[0].detach())
    b = compensate(twin, q, position_only=True, tool_point=twin.tools()[0].detach())
    both = a.converged & b.converged
    assert int(both.sum()) >= 295
    assert float((a.q[both] - b.q[both]).abs().max()) < 1e-9
    # the 6-DOF commands follow the fit's choice of orientation (the turn is undone by the joints)
    a6, b6 = compensate(model, q), compensate(twin, q)
    both6 = a6.converged & b6.converged
    assert float((a6.q[both6] - b6.q[both6]).abs().max()) > math.radians(1.0)
    # the tool point lands on the nominal robot's point for the nominal tool (the tool set's frame: a translation)
    with torch.no_grad():
        reach = _tool_point(model, a.q, model.tools()[0])
        Fn = model.nominal_flange(q)
        want = Fn[:, :3, :3] @ model.tools.nominal[0] + Fn[:, :3, 3]
    assert float((reach - want)[a.converged].norm(dim=-1).max()) < 1e-9
    # and far less joint motion than the twin's 6-DOF correction, which undoes its (unobserved) 3 deg turn
    assert float(a.correction[both].median()) < 0.3 * float(b6.correction[both6].median())


def test_the_3dof_correction_is_the_smallest_one(fanuc):
    """At the solution the correction is orthogonal to the tool point's null space (the first-order condition of
    min |q - q_nom| subject to reaching the point) up to second order in the correction, with the Jacobian taken
    by finite differences. (A 6-DOF solution, or a chord taken at another point, is off it by first order.)"""
    model, _ = _turned_twin(fanuc, 0.0)
    q = random_commands(fanuc, 40, 9)
    c = model.tools()[0].detach()
    res = compensate(model, q, position_only=True, tool_point=c)
    ok = res.converged
    assert int(ok.sum()) >= 38
    dq = (res.q - q)[ok]
    qs = res.q[ok]
    h = 1e-6
    J = torch.stack([(_tool_point(model, qs + h * e, c) - _tool_point(model, qs - h * e, c)) / (2 * h)
                     for e in torch.eye(6, dtype=torch.float64)], -1)  # (B, 3, 6)
    N = torch.eye(6, dtype=torch.float64) - torch.linalg.pinv(J) @ J
    null = (N @ dq[..., None])[..., 0].norm(dim=-1)
    size = dq.norm(dim=-1)
    # the chord iteration's steps lie in the row space of the Jacobian at q_nom: off it by second order in |dq|
    assert float((null / size).median()) < 1e-2
    assert bool((null <= 5.0 * size**2).all())
    assert float(dq.norm(dim=-1).min()) > 1e-5  # the commands did change


def test_position_only_and_a_free_axis_are_not_given_together(fanuc):
    from torchcal.core.exceptions import InputError

    model = RobotModel(fanuc, torch.tensor(TOOL, dtype=torch.float64), orders=0)
    q = random_commands(fanuc, 3, 1)
    with pytest.raises(InputError, match="position_only"):
        compensate(model, q, position_only=True, free_tool_axis=True)


def test_targets_reach_the_tool_point_only(fanuc):
    model, twin = _turned_twin(fanuc, math.radians(2.0))
    q = random_commands(fanuc, 30, 6)
    with torch.no_grad():
        Fn = model.nominal_flange(q)
    T = Fn.clone()
    T[:, :3, 3] = Fn[:, :3, :3] @ model.tools.nominal[0] + Fn[:, :3, 3]
    a = compensate_targets(model, T, q, position_only=True)
    b = compensate_targets(twin, T, q, position_only=True)
    both = a.converged & b.converged
    assert int(both.sum()) >= 28
    assert float((a.q[both] - b.q[both]).abs().max()) < 1e-9
    reach = _tool_point(model, a.q, model.tools()[0].detach())
    assert float((reach - T[:, :3, 3])[both].norm(dim=-1).max()) < 1e-9


def test_cli_compensates_a_one_tool_run_position_only_by_default(fanuc, tmp_path):
    from torchcal.cli import app
    from torchcal.io.rundir import save_model

    _, model = _turned_twin(fanuc, math.radians(3.0))  # a fit that chose a flange turned 3 deg
    run = tmp_path / "run"
    run.mkdir()
    save_model(run, model)
    q = random_commands(fanuc, 20, 2)
    df = pd.DataFrame({f"q{j + 1}": np.degrees(q[:, j].numpy()) for j in range(6)})
    df.to_csv(tmp_path / "in.csv", index=False)
    runner = CliRunner()
    r = runner.invoke(app, ["compensate", str(run), str(tmp_path / "in.csv"), str(tmp_path / "auto.csv")])
    assert r.exit_code == 0, r.output
    assert "3-DOF" in r.output and "--dof 6" in r.output
    r6 = runner.invoke(app, ["compensate", str(run), str(tmp_path / "in.csv"), str(tmp_path / "six.csv"), "--dof", "6"])
    assert r6.exit_code == 0, r6.output
    assert "3-DOF" not in r6.output
    auto, six = pd.read_csv(tmp_path / "auto.csv"), pd.read_csv(tmp_path / "six.csv")
    assert auto.converged.all()
    qa = torch.tensor(np.radians(auto[[f"q{j + 1}" for j in range(6)]].to_numpy()))
    reach = _tool_point(model, qa, model.tools()[0].detach())
    with torch.no_grad():
        Fn = model.nominal_flange(q)
    want = Fn[:, :3, :3] @ model.tools.nominal[0] + Fn[:, :3, 3]
    assert float((reach - want).norm(dim=-1).max()) < 1e-8  # m, after the file's digits
    assert auto.max_dq.median() < 0.5 * six.max_dq.median()
    bad = runner.invoke(app, ["compensate", str(run), str(tmp_path / "in.csv"), str(tmp_path / "x.csv"), "--dof", "4"])
    assert bad.exit_code == 2 and "--dof '4'" in bad.output
    bad = runner.invoke(app, ["compensate", str(run), str(tmp_path / "in.csv"), str(tmp_path / "x.csv"), "--dof", "5"])
    assert bad.exit_code == 2 and "--free-tool-axis" in bad.output


def test_targets_file_of_a_one_tool_run(fanuc, tmp_path):
    from torchcal.cli import app
    from torchcal.io.rundir import save_model

    model, _ = _turned_twin(fanuc, math.radians(3.0))
    run = tmp_path / "run"
    run.mkdir()
    save_model(run, model)
    q = random_commands(fanuc, 12, 4)
    with torch.no_grad():
        Fn = model.nominal_flange(q)
    T = homogeneous(Fn[:, :3, :3], Fn[:, :3, :3] @ model.tools.nominal[0] + Fn[:, :3, 3])
    write_targets(tmp_path / "targets.csv", T, q)
    r = CliRunner().invoke(app, ["compensate", str(run), str(tmp_path / "targets.csv"), str(tmp_path / "out.csv")])
    assert r.exit_code == 0, r.output
    assert "3-DOF" in r.output
    out = pd.read_csv(tmp_path / "out.csv")
    assert out.converged.all()
    qc = torch.tensor(np.radians(out[[f"q{j + 1}" for j in range(6)]].to_numpy()))
    reach = _tool_point(model, qc, model.tools()[0].detach())
    assert float((reach - T[:, :3, 3]).norm(dim=-1).max()) < 1e-8
    assert out.max_dq.max() < 1.0  # deg: no turn of the unobserved orientation


def test_the_dof_notes_say_which_tool_point_and_why(fanuc):
    """--dof 3 on a run of several tools names the point restored; auto on a run measured with one of three tools
    says so (its note used to speak of the run's one tool)."""
    from torchcal.app.files import compensation_dof

    tools = torch.tensor([[0.0, 0.0, 0.1], [0.05, 0.0, 0.1], [0.0, 0.05, 0.1]], dtype=torch.float64)
    three = RobotModel(fanuc, tools, orders=0)
    opts, note = compensation_dof(three, "3")
    assert opts == {"position_only": True} and "the row's tool column; tool 0 where the file has none" in note
    assert compensation_dof(RobotModel(fanuc, tools[:1], orders=0), "3")[1] is None
    three.measured_tools = [0]
    opts, note = compensation_dof(three, "auto")
    assert opts == {"position_only": True} and note.startswith("the run's data measured only tool 0 of its 3")
