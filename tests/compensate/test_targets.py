"""Cartesian targets in: calibrated commands reach the target on the model; the corrected target round-trips
through the controller's nominal IK; the nominal IK recovers the controller's own command."""

from __future__ import annotations

import torch
from conftest import random_commands, randomize, write_targets

from torchcal.compensate.toolset import tool_poses
from torchcal.compensate import damped_least_squares, nominal_sigma_min
from torchcal.compensate.targets import compensate_targets
from torchcal.kinematics.transforms import homogeneous, pose_error
from torchcal.models.robot import RobotModel


def _tool_pose(F, t):
    return homogeneous(F[:, :3, :3], F[:, :3, 3] + (F[:, :3, :3] @ t[..., None])[..., 0])


def test_targets_reach_the_model_and_round_trip(fanuc, tools_m):
    model = randomize(RobotModel(fanuc, tools_m, orders=3, backlash=True), 5)
    with torch.no_grad():  # identified tool corrections, so the real tool differs from the controller's
        model.tools.delta.copy_(torch.tensor([[1e-4, -2e-4, 3e-4], [0.0, 1e-4, 0.0], [-1e-4, 0.0, 2e-4]],
                                             dtype=torch.float64))
    B = 200
    q_ctrl = random_commands(fanuc, B, 7)  # what the controller's nominal IK chooses for each target
    tool = torch.arange(B) % 3
    with torch.no_grad():
        T = _tool_pose(model.nominal_flange(q_ctrl), model.tools.nominal[tool])  # the program's targets
    g = torch.Generator().manual_seed(8)
    seed = q_ctrl + 0.02 * torch.randn(B, 6, generator=g, dtype=torch.float64)  # a seed near the branch
    s = torch.ones(B, 6, dtype=torch.float64)
    res = compensate_targets(model, T, seed, tool, s)
    ok = res.converged
    assert ok.double().mean() > 0.9
    assert all((r == "") == bool(c) for r, c in zip(res.reason, ok.tolist()))
    # the nominal IK found the controller's own commands (same branch), away from singularities (there two
    # solutions of one pose lie close together, and any of them is the controller's)
    clear = ok & (nominal_sigma_min(model, q_ctrl) > 0.02)  # m/rad: 0.35 mm/deg
    assert int(clear.sum()) > 100
    assert float((res.q_nominal[clear] - q_ctrl[clear]).abs().max()) < 1e-8
    with torch.no_grad():
        # the calibrated commands put the model's identified tool on the target
        reach = tool_poses(model, res.q, tool, s)
        assert float(pose_error(reach[ok], T[ok]).norm(dim=-1).max()) < 1e-9
        # the corrected target, through the controller's nominal IK (nominal tool), gives the calibrated commands
        nominal = RobotModel(fanuc, tools_m, orders=0, backlash=None)
        t_nom = model.tools.nominal[tool]
        goal = homogeneous(res.command_target[:, :3, :3],
                           res.command_target[:, :3, 3] - (res.command_target[:, :3, :3] @ t_nom[..., None])[..., 0])
        back = damped_least_squares(nominal, seed, goal, None)
    # (off a singular surface: next to one, two solutions of the corrected target lie close together, and which
    # one an IK finds depends on its steps, not on the target)
    assert float((back.q[clear] - res.q[clear]).abs().max()) < 1e-8
    # and the correction matters: the uncorrected target sends the tool off by the model's error
    with torch.no_grad():
        off = _tool_pose(model.flange(q_ctrl, s, base=False), model.tools()[tool])
    assert float(pose_error(off, T)[:, 3:].norm(dim=-1).mean()) > 1e-4


def test_an_unreachable_target_says_so(fanuc, tools_m):
    model = randomize(RobotModel(fanuc, tools_m, orders=1), 2, rot=5e-4, trans=5e-5)
    q = random_commands(fanuc, 2, 3)
    with torch.no_grad():
        T = _tool_pose(model.nominal_flange(q), model.tools.nominal[[0, 0]])
    T[1, :3, 3] += 5.0  # 5 m away
    res = compensate_targets(model, T, q, 0)
    assert bool(res.converged[0]) and not bool(res.converged[1])
    assert res.reason[0] == "" and res.reason[1].startswith("out of reach")


def test_compensate_command_on_a_targets_file(tmp_path, fanuc, tools_m):
    """`torchcal compensate RUN targets.csv out.csv`: rpy targets with seeds in q1..q6; the calibrated commands
    and the corrected targets come back per row; the commands reach the target on the run's model."""
    import numpy as np
    import pandas as pd
    from typer.testing import CliRunner

    from torchcal.cli import app
    from torchcal.io.rundir import save_model

    model = randomize(RobotModel(fanuc, tools_m, orders=2, backlash=True), 9, rot=5e-4, trans=5e-5)
    run = tmp_path / "run"
    run.mkdir()
    save_model(run, model)
    q = random_commands(fanuc, 20, 4)
    tool = torch.arange(20) % 3
    with torch.no_grad():
        T = _tool_pose(model.nominal_flange(q), model.tools.nominal[tool])
    df = pd.read_csv(write_targets(tmp_path / "targets.csv", T, q, label=[f"P{i}" for i in range(20)], tool=tool.numpy()))
    r = CliRunner().invoke(app, ["compensate", str(run), str(tmp_path / "targets.csv"), str(tmp_path / "out.csv")])
    assert r.exit_code == 0, r.output
    assert "compensated 20 Cartesian targets" in r.output
    out = pd.read_csv(tmp_path / "out.csv", keep_default_na=False)
    assert list(out.label) == list(df.label) and {"x_cmd", "rz_cmd", "reason", "converged"} <= set(out.columns)
    ok = out.converged.to_numpy().astype(bool)
    assert ok.mean() > 0.8
    qc = torch.tensor(np.radians(out[[f"q{j + 1}" for j in range(6)]].to_numpy()), dtype=torch.float64)
    with torch.no_grad():
        reach = tool_poses(model, qc, tool)
    err = pose_error(reach, T)
    assert float(err[torch.from_numpy(ok), 3:].norm(dim=-1).max()) < 1e-9  # m (file digits: 1e-10 deg)
    assert all((reason == "") == bool(c) for reason, c in zip(out.reason, ok))
    # the file's silent defaults are said: no dir1..dir6 on a backlash model; its rows name their tools
    said = " ".join(r.output.split())
    assert "targets.csv: no dir1..dir6 columns: the model's backlash terms are left out" in said
    assert "no 'tool' column" not in said
    df.drop(columns="tool").assign(**{f"dir{j + 1}": 1 for j in range(6)}).to_csv(tmp_path / "t0.csv", index=False)
    r = CliRunner().invoke(app, ["compensate", str(run), str(tmp_path / "t0.csv"), str(tmp_path / "out0.csv")])
    said = " ".join(r.output.split())
    assert r.exit_code == 0 and "t0.csv: no 'tool' column: every target is for tool 0" in said, said
    assert "backlash terms are left out" not in said
    # a target out of reach is counted among those that did not converge (the count agrees with the file)
    far = df.copy()
    far.loc[0, "x"] += 3000.0
    far.to_csv(tmp_path / "t_far.csv", index=False)
    r = CliRunner().invoke(app, ["compensate", str(run), str(tmp_path / "t_far.csv"), str(tmp_path / "out_far.csv")])
    got = pd.read_csv(tmp_path / "out_far.csv", keep_default_na=False)
    bad = int((~got.converged.astype(bool)).sum())
    within = got.within_limits.astype(bool)
    said = " ".join(r.output.split())
    assert got.reason[0].startswith("out of reach") and bad >= 1
    # the unreachable row keeps its seed (the IK's last iterate was no command: J2 at 803 deg in a helper's run)
    joints = [f"q{j + 1}" for j in range(6)]
    assert np.allclose(got.loc[0, joints].to_numpy(float), far.loc[0, joints].to_numpy(float), atol=1e-8)
    assert float(got.max_dq[0]) == 0.0 and bool(got.within_limits[0])
    assert (f"{bad} of 20 commands flagged ({int((~got.converged.astype(bool) & within).sum())} did not converge or "
            f"are out of reach, {int((~within).sum())} outside") in said, said
    # x, y, z with no orientation and no tool column: targets, not commands; refused rather than read as commands
    # with x, y, z ignored (a tracker file's points name their tool and compensate as commands, as before)
    df.drop(columns=["rx", "ry", "rz"]).to_csv(tmp_path / "t_xyz.csv", index=False)
    r = CliRunner().invoke(app, ["compensate", str(run), str(tmp_path / "t_xyz.csv"), str(tmp_path / "out_x.csv")])
    said = " ".join(r.output.split())
    assert r.exit_code == 2 and "t_xyz.csv" in said and "x, y, z without an orientation" in said, said
    assert not (tmp_path / "out_x.csv").exists()
    # targets in metres, and an orientation given twice: refused, nothing written
    metres = df.copy()
    metres[["x", "y", "z"]] = metres[["x", "y", "z"]] / 1000.0
    metres.to_csv(tmp_path / "t_m.csv", index=False)
    r = CliRunner().invoke(app, ["compensate", str(run), str(tmp_path / "t_m.csv"), str(tmp_path / "out_m.csv")])
    said = " ".join(r.output.split())
    assert r.exit_code == 2 and "t_m.csv: columns x, y, z" in said and "look like metres" in said, said
    both = df.assign(qw=1.0, qx=0.0, qy=0.0, qz=0.0)
    both.to_csv(tmp_path / "t_both.csv", index=False)
    r = CliRunner().invoke(app, ["compensate", str(run), str(tmp_path / "t_both.csv"), str(tmp_path / "out_b.csv")])
    said = " ".join(r.output.split())
    assert r.exit_code == 2 and "both rx, ry, rz and qw, qx, qy, qz are given" in said, said
    assert not (tmp_path / "out_m.csv").exists() and not (tmp_path / "out_b.csv").exists()


def test_every_flagged_command_says_why(fanuc, tools_m):
    """compensate's reasons agree with its flags: '' exactly for converged rows within the range, 'joint limit'
    for rows outside it, 'needs more than the bound' only where the correction reached the bound."""
    import math

    from torchcal.compensate import compensate

    model = randomize(RobotModel(fanuc, tools_m, orders=3, backlash=True), 11, rot=3e-3, trans=3e-4)
    lim = fanuc.joint_map.limits
    q = random_commands(fanuc, 400, 12)
    q[:40, 1] = lim[1, 1] - 1e-4  # at the upper limit of joint 2: corrections may leave the range
    bound = math.radians(2.0)
    res = compensate(model, q, torch.ones_like(q), max_correction=bound, max_step=bound)
    why = res.reasons(bound)
    ok = res.converged & res.within_limits
    assert all((w == "") == bool(c) for w, c in zip(why, ok.tolist()))
    assert all(w.startswith("joint limit") for w, inside in zip(why, res.within_limits.tolist()) if not inside)
    more = torch.tensor([w.startswith("needs more") for w in why])
    assert bool(more.any())
    # 'needs more than the bound': the unbounded solver's solution lies beyond it, or it finds none
    free = compensate(model, q[more], torch.ones_like(q[more]), max_correction=None, max_step=None, null_damping=0.0,
                      branch=False)
    assert bool((~free.converged | (free.correction > bound)).all())
    assert not bool(res.within_limits.all())


def test_a_targets_file_marks_the_rows_approached_from_an_unseen_direction(tmp_path, fanuc, tools_m):
    """The console counts targets approached from a direction the identification data never covered: the output
    names them (the column was missing from the targets output while the console pointed to it)."""
    import numpy as np
    import pandas as pd
    from typer.testing import CliRunner

    from torchcal.analysis.coverage import DirectionCoverage
    from torchcal.cli import app
    from torchcal.io.rundir import save_model

    model = randomize(RobotModel(fanuc, tools_m, orders=2, backlash=True), 9, rot=5e-4, trans=5e-5)
    q_id = random_commands(fanuc, 500, 59)
    s_id = torch.where(torch.rand(q_id.shape, generator=torch.Generator().manual_seed(60)) < 0.5, -1.0, 1.0).double()
    s_id[:, 1] = 1.0  # joint 2 approached from below only
    model.coverage = DirectionCoverage.from_data(q_id, s_id, model.command_limits, bins=4)
    run = tmp_path / "run"
    run.mkdir()
    save_model(run, model)
    q = random_commands(fanuc, 12, 4)
    s = torch.ones_like(q)
    s[::3, 1] = -1.0
    with torch.no_grad():
        T = _tool_pose(model.nominal_flange(q), model.tools.nominal[[0] * 12])
    write_targets(tmp_path / "t.csv", T, q, **{f"dir{j + 1}": s[:, j].numpy().astype(int) for j in range(6)})
    r = CliRunner().invoke(app, ["compensate", str(run), str(tmp_path / "t.csv"), str(tmp_path / "o.csv")])
    assert r.exit_code == 0, r.output
    out = pd.read_csv(tmp_path / "o.csv")
    assert list(out.direction_outside) == (s[:, 1] < 0).tolist()
    assert "4 of 12 commands approach a joint from a direction" in " ".join(r.output.split())
    assert np.isfinite(out.max_dq).all()


def test_a_targets_file_with_its_orientations_in_radians_is_refused(tmp_path, fanuc, tools_m):
    """rx, ry, rz typed in radians came back as flagged rows with nothing said of the unit: the seeds (the
    controller's commands for the targets, here 2 deg off) show where the tool points, and the file's angles
    match them only as radians."""
    import numpy as np
    import pandas as pd
    from typer.testing import CliRunner

    from torchcal.cli import app
    from torchcal.io.rundir import save_model

    model = randomize(RobotModel(fanuc, tools_m, orders=1), 9, rot=5e-4, trans=5e-5)
    run = tmp_path / "run"
    run.mkdir()
    save_model(run, model)
    q = random_commands(fanuc, 30, 4)
    with torch.no_grad():
        T = _tool_pose(model.nominal_flange(q), model.tools.nominal[[0] * 30])
    seeds = q + torch.deg2rad(2.0 * torch.randn(q.shape, generator=torch.Generator().manual_seed(1), dtype=q.dtype))
    seeds = torch.minimum(torch.maximum(seeds, model.command_limits[:, 0]), model.command_limits[:, 1])
    def both(stem, seeds):  # the targets in degrees (the contract) and the same numbers typed in radians
        write_targets(tmp_path / f"{stem}deg.csv", T, seeds)
        df = pd.read_csv(tmp_path / f"{stem}deg.csv")
        df[["rx", "ry", "rz"]] = np.radians(df[["rx", "ry", "rz"]])
        df.to_csv(tmp_path / f"{stem}rad.csv", index=False)

    both("", seeds)
    r = CliRunner().invoke(app, ["compensate", str(run), str(tmp_path / "deg.csv"), str(tmp_path / "o.csv")])
    assert r.exit_code == 0, r.output
    r = CliRunner().invoke(app, ["compensate", str(run), str(tmp_path / "rad.csv"), str(tmp_path / "o2.csv")])
    said = " ".join(r.output.split())
    assert r.exit_code != 0 and "rad.csv" in said and "the orientations look like radians" in said, said
    assert not (tmp_path / "o2.csv").exists()
    r = CliRunner().invoke(app, ["compensate", str(run), str(tmp_path / "rad.csv"), str(tmp_path / "o3.csv"),
                                 "--units-checked"])
    assert r.exit_code == 0, r.output  # the user's word: read as degrees, the rows flagged as before
    assert not pd.read_csv(tmp_path / "o3.csv").converged.all()
    # seeds that are only hints of the branch (8 deg off per joint): still told apart
    hints = q + torch.deg2rad(8.0 * torch.randn(q.shape, generator=torch.Generator().manual_seed(2), dtype=q.dtype))
    hints = torch.minimum(torch.maximum(hints, model.command_limits[:, 0]), model.command_limits[:, 1])
    both("hint_", hints)
    r = CliRunner().invoke(app, ["compensate", str(run), str(tmp_path / "hint_rad.csv"), str(tmp_path / "o4.csv")])
    assert r.exit_code != 0 and "look like radians" in " ".join(r.output.split()), r.output
    r = CliRunner().invoke(app, ["compensate", str(run), str(tmp_path / "hint_deg.csv"), str(tmp_path / "o5.csv")])
    assert "look like radians" not in " ".join(r.output.split()), r.output
