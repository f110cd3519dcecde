"""Configuration flags (torchcal.compensate.flags): our reading factors det J of the nominal kinematics, the
wrist flip changes only the wrist flag, the seeds found for flags reach the target with those flags, an offset
wrist is refused, and a targets file may name the branch by flags instead of seed commands."""

from __future__ import annotations

import math

import numpy as np
import pandas as pd
import pytest
import torch
from conftest import random_commands, randomize

import torchcal
from torchcal.compensate.toolset import tool_poses
from torchcal.compensate.flags import configuration_flags, seeds_for_flags
from torchcal.compensate.kernel import FlangeKernel
from torchcal.compensate.newton import nominal_sigma_min
from torchcal.kinematics.transforms import homogeneous, pose_error
from torchcal.models.robot import RobotModel


def _nominal(name):
    robot = torchcal.load_robot(name)
    return RobotModel(robot, torch.zeros(1, 3, dtype=torch.float64), orders=0)


@pytest.mark.parametrize("name", ["fanuc_lrmate200i", "abb_irb120"])
def test_the_flags_factor_det_j(name):
    """sign(det J) = const * shoulder * elbow * wrist over the whole joint range: each flag flips exactly where one
    factor of det J vanishes (det J from the nominal Jacobian, not from the flags' geometry)."""
    model = _nominal(name)
    q = random_commands(model.robot, 3000, 2).double()
    f = configuration_flags(model, q)
    _, _, J = FlangeKernel(model).nominal_flange_jacobian(q.T.contiguous())
    d = torch.sign(torch.linalg.det(J.permute(2, 0, 1)))
    prod = f.prod(-1) * d
    assert bool((prod == prod[0]).all()) and float(prod[0].abs()) == 1.0
    assert torch.unique(f, dim=0).shape[0] == 8  # all eight configurations occur


def test_the_wrist_flip_changes_only_the_wrist_flag(fanuc):
    """(q4 + pi, -q5, q6 + pi) reaches the same flange pose on a FANUC (axes 4 and 6 opposite directions of one
    line through the wrist centre): it is the other wrist configuration."""
    model = _nominal("fanuc_lrmate200i")
    q = random_commands(fanuc, 200, 3).double()
    q[:, 3] = q[:, 3].clamp(-2.5, 0.6)  # keep q4 + pi inside +-190 deg
    q[:, 5] = q[:, 5].clamp(-6.0, 3.0)
    flip = q.clone()
    flip[:, 3] += math.pi
    flip[:, 4] = -q[:, 4]
    flip[:, 5] += math.pi
    with torch.no_grad():
        assert float(pose_error(model.nominal_flange(q), model.nominal_flange(flip)).abs().max()) < 1e-12
    a, b = configuration_flags(model, q), configuration_flags(model, flip)
    keep = a[:, 2] != 0
    assert torch.equal(a[keep, :2], b[keep, :2]) and torch.equal(a[keep, 2], -b[keep, 2])


@pytest.mark.parametrize("name", ["fanuc_lrmate200i", "abb_irb120"])
def test_seeds_for_flags_reach_the_target_on_the_requested_branch(name):
    model = _nominal(name)
    q = random_commands(model.robot, 400, 5).double()
    q = q[nominal_sigma_min(model, q) > 0.02][:40]  # clear of the singular surfaces, where flags are defined
    with torch.no_grad():
        T = model.nominal_flange(q)
    flags = configuration_flags(model, q)
    seed, found = seeds_for_flags(model, T, flags, starts=32)
    assert float(found.double().mean()) > 0.95
    with torch.no_grad():
        err = pose_error(model.nominal_flange(seed[found]), T[found]).norm(dim=-1)
    assert float(err.max()) < 1e-9
    assert torch.equal(configuration_flags(model, seed[found]), flags[found])
    # the other seven configurations of one target: where found, each has its flags and reaches the target
    one = T[:1].expand(8, 4, 4)
    combos = torch.tensor([[a, b, c] for a in (-1, 1) for b in (-1, 1) for c in (-1, 1)], dtype=torch.float64)
    s8, f8 = seeds_for_flags(model, one, combos, starts=16)
    assert int(f8.sum()) >= 2
    assert torch.equal(configuration_flags(model, s8[f8]), combos[f8])


def test_an_offset_wrist_is_refused():
    model = _nominal("ur10")
    with pytest.raises(ValueError, match="spherical wrist"):
        configuration_flags(model, torch.zeros(1, 6, dtype=torch.float64))


def _targets_table(model, q, tool):
    from torchcal.compensate.targets import pose_rpy

    t = model.tools.nominal[tool]
    with torch.no_grad():
        F = model.nominal_flange(q)
    T = homogeneous(F[:, :3, :3], F[:, :3, 3] + (F[:, :3, :3] @ t[..., None])[..., 0])
    xyzrpy = pose_rpy(T)
    df = pd.DataFrame({"tool": tool.numpy()})
    for i, c in enumerate(("x", "y", "z")):
        df[c] = xyzrpy[:, i].numpy() * 1000.0
    for i, c in enumerate(("rx", "ry", "rz")):
        df[c] = np.degrees(xyzrpy[:, 3 + i].numpy())
    return df, T


def test_a_targets_file_with_flags_instead_of_seeds(tmp_path, fanuc, tools_m):
    from typer.testing import CliRunner

    from torchcal.cli import app
    from torchcal.io.rundir import save_model

    model = randomize(RobotModel(fanuc, tools_m, orders=2, backlash=True), 9, rot=5e-4, trans=5e-5)
    run = tmp_path / "run"
    run.mkdir()
    save_model(run, model)
    q = random_commands(fanuc, 60, 14).double()
    q = q[nominal_sigma_min(model, q) > 0.03][:15]
    tool = torch.arange(q.shape[0]) % 3
    df, T = _targets_table(model, q, tool)
    flags = configuration_flags(model, q)
    for j, c in enumerate(("shoulder", "elbow", "wrist")):
        df[c] = flags[:, j].numpy().astype(int)
    df.to_csv(tmp_path / "targets.csv", index=False)
    r = CliRunner().invoke(app, ["compensate", str(run), str(tmp_path / "targets.csv"), str(tmp_path / "out.csv")])
    assert r.exit_code == 0, r.output
    out = pd.read_csv(tmp_path / "out.csv", keep_default_na=False)
    ok_np = out.converged.to_numpy().astype(bool)
    assert ok_np.mean() > 0.8 and all((w == "") == c for w, c in zip(out.reason, ok_np))
    ok = torch.from_numpy(ok_np)
    qc = torch.tensor(np.radians(out[[f"q{j + 1}" for j in range(6)]].to_numpy()[ok_np].astype(float)))
    reach = tool_poses(model, qc, tool[ok])  # the identified tool in the tool set's frame (.toolset)
    assert float(pose_error(reach, T[ok]).norm(dim=-1).max()) < 1e-9
    assert torch.equal(configuration_flags(model, qc), flags[ok])  # on the branch the flags name
    # a flag that is not +-1: the file, row and column are named
    df.loc[3, "elbow"] = 0
    df.to_csv(tmp_path / "bad.csv", index=False)
    r = CliRunner().invoke(app, ["compensate", str(run), str(tmp_path / "bad.csv"), str(tmp_path / "out2.csv")])
    assert r.exit_code != 0 and "bad.csv" in r.output and "elbow" in r.output and "row 4" in r.output
    # seeds and flags both: the seeds give the branch, and that is said (flags contradicting the seeds ran silently)
    assert "flags are not read" not in " ".join(
        CliRunner().invoke(app, ["compensate", str(run), str(tmp_path / "targets.csv"), str(tmp_path / "o3.csv")]).output.split())
    df.loc[3, "elbow"] = -1
    both = df.copy()
    for j in range(6):
        both[f"q{j + 1}"] = np.degrees(q[:, j].numpy())
    both.to_csv(tmp_path / "both.csv", index=False)
    r = CliRunner().invoke(app, ["compensate", str(run), str(tmp_path / "both.csv"), str(tmp_path / "out4.csv")])
    assert r.exit_code == 0, r.output
    assert "both seed commands" in " ".join(r.output.split()) and "flags are not read" in " ".join(r.output.split())


def test_a_target_with_no_solution_for_its_flags_has_no_command_and_no_numbers(tmp_path, fanuc, tools_m):
    """A flag combination the nominal IK cannot reach: q1..qN empty, and no max_dq or within_limits made up for a
    command that does not exist; the console counts it as not converged, not as outside the range."""
    from typer.testing import CliRunner

    from torchcal.cli import app
    from torchcal.io.rundir import save_model

    model = randomize(RobotModel(fanuc, tools_m, orders=1), 9, rot=5e-4, trans=5e-5)
    save_model(tmp_path / "run", model)
    q = random_commands(fanuc, 60, 14).double()
    q = q[nominal_sigma_min(model, q) > 0.03][:6]
    df, _ = _targets_table(model, q, torch.zeros(q.shape[0], dtype=torch.long))
    flags = configuration_flags(model, q)
    for j, c in enumerate(("shoulder", "elbow", "wrist")):
        df[c] = flags[:, j].numpy().astype(int)
    df.loc[0, "z"] = 5000.0  # out of every branch's reach
    df.to_csv(tmp_path / "t.csv", index=False)
    r = CliRunner().invoke(app, ["compensate", str(tmp_path / "run"), str(tmp_path / "t.csv"), str(tmp_path / "o.csv")])
    assert r.exit_code == 0, r.output
    out = pd.read_csv(tmp_path / "o.csv", keep_default_na=False)
    assert "no nominal IK solution" in out.reason[0]
    assert out.q1[0] == "" and out.max_dq[0] == "" and out.within_limits[0] == ""
    assert "0 outside the controller range" in r.output.replace("\n", " ")
