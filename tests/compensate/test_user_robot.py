"""A robot we do not bundle: a 7-axis arm whose URDF a user wrote from a datasheet's DH table.

The KUKA LBR iiwa 14 R820's standard DH parameters (d = 360, 0, 420, 0, 400, 0, 126 mm; a = 0; alpha = -90,
90, 90, -90, -90, 90, 0 deg), folded into URDF joints the usual way (joint i's origin carries link i-1's a,
d and alpha). Checked against a plain-numpy DH product (conftest.standard_dh), then compensated and solved
for Cartesian targets next to its elbow singularity (q4 = 0, the arm stretched to the edge of its reach),
where rows the solver cannot finish must say why.
"""

from __future__ import annotations

import math

import numpy as np
import torch

import torchcal
from torchcal.compensate.result import SINGULAR_FLOOR
from torchcal.compensate.targets import tool_pose

from conftest import ALPHA_DEG, D_MM, randomize, standard_dh

REASONS = ("out of reach", "needs more than the bound", "joint limit", "singular", "branch change")
"""The causes a flagged row may give (issue 17: out of reach, more than the bound, joint limit, singular; and
the branch test's own)."""


def _elbow_stretched(robot, count, seed):
    """Commands with q4 within 1 deg of zero (the stretched elbow), the other joints over 80 % of their range."""
    g = torch.Generator().manual_seed(seed)
    lim = robot.joint_map.limits * 0.8
    q = lim[:, 0] + torch.rand(count, 7, generator=g) * (lim[:, 1] - lim[:, 0])
    q[:, 3] = math.radians(1.0) * (2 * torch.rand(count, generator=g) - 1)
    return q


def _modeled_sigma_min(model, q, h=1e-6):
    """sigma_min (B,) of the modeled flange Jacobian by central differences of model.flange (independent of the
    solver's kernels); orientation by the rotation log of R(q + h e_j) R(q - h e_j)^T."""
    cols = []
    for j in range(q.shape[1]):
        e = torch.zeros_like(q)
        e[:, j] = h
        with torch.no_grad():
            Fp, Fm = model.flange(q + e, base=False), model.flange(q - e, base=False)
        dp = (Fp[:, :3, 3] - Fm[:, :3, 3]) / (2 * h)
        dR = Fp[:, :3, :3] @ Fm[:, :3, :3].transpose(1, 2)
        w = 0.5 * torch.stack([dR[:, 2, 1] - dR[:, 1, 2], dR[:, 0, 2] - dR[:, 2, 0], dR[:, 1, 0] - dR[:, 0, 1]], -1)
        cols.append(torch.cat([dp, w / (2 * h)], -1))
    return torch.linalg.svdvals(torch.stack(cols, -1))[:, -1]


def test_the_dh_urdf_matches_the_dh_table(iiwa):
    q = torch.tensor(np.random.default_rng(0).uniform(-2.0, 2.0, (50, 7)))
    model = torchcal.RobotModel(iiwa, torch.zeros(1, 3), orders=1)
    with torch.no_grad():
        F = model.nominal_flange(q).numpy()
    ref = standard_dh(q.numpy(), D_MM, [0.0] * 7, np.radians(ALPHA_DEG))
    ref[:, :3, 3] /= 1000.0
    assert np.abs(F - ref).max() < 1e-12


def test_next_to_the_elbow_singularity_every_flagged_row_says_why(iiwa):
    tools = torch.tensor([[0.0, 0.0, 0.1]])
    model = randomize(torchcal.RobotModel(iiwa, tools, orders=3), 0)
    with torch.no_grad():  # the arm's errors only: the tool at its nominal vector, the flange is what is compensated
        model.tools.delta.zero_()
    q = _elbow_stretched(iiwa, 400, 1)
    res = torchcal.compensate(model, q)
    reasons = res.reasons()
    flagged = [i for i, r in enumerate(reasons) if r]
    assert flagged, "the stretched elbow should leave some rows unreachable or unfinished"
    assert all(reasons[i].startswith(REASONS) for i in flagged), {reasons[i] for i in flagged}
    # a row said to end on a singular surface does: the modeled Jacobian there has lost rank
    sing = torch.tensor([i for i in flagged if reasons[i].startswith("singular: ended")], dtype=torch.long)
    if sing.numel():
        assert bool((_modeled_sigma_min(model, res.q[sing]) < 1.01 * SINGULAR_FLOOR).all())
    # converged rows put the modeled flange on the nominal one (Paper II (46))
    ok = res.converged
    with torch.no_grad():
        d = model.flange(res.q[ok], base=False)[:, :3, 3] - model.nominal_flange(q[ok])[:, :3, 3]
    assert float(d.norm(dim=-1).max()) < 1e-9


def test_targets_on_the_7_axis_arm_reach_the_model_or_say_why(iiwa):
    tools = torch.tensor([[0.0, 0.0, 0.1]])
    model = randomize(torchcal.RobotModel(iiwa, tools, orders=3), 1)
    q = torch.cat([_elbow_stretched(iiwa, 200, 2), _elbow_stretched(iiwa, 200, 3)])
    q[200:, 3] += math.radians(30.0)  # and half of them with a bent elbow: the common case
    tool = torch.zeros(q.shape[0], dtype=torch.long)
    with torch.no_grad():
        T = tool_pose(model.nominal_flange(q), model.tools.nominal[tool])
    tr = torchcal.compensate_targets(model, T, q, tool)
    assert all(r.startswith(REASONS) for r in tr.reason if r), {r for r in tr.reason if r}
    assert bool(tr.converged[200:].all())  # away from the singularity every target is reached
    ok = tr.converged
    with torch.no_grad():
        reach = tool_pose(model.flange(tr.q[ok], base=False), model.tools()[tool[ok]])
    assert float((reach[:, :3, 3] - T[ok, :3, 3]).norm(dim=-1).max()) < 1e-9


def test_configuration_flags_for_a_7_axis_arm_are_refused_naming_why(iiwa, tmp_path):
    """Flags describe 6R arms: a 7-axis targets file with shoulder, elbow, wrist columns gets a message, no traceback."""
    import pandas as pd
    from typer.testing import CliRunner

    from torchcal.cli import app
    from torchcal.io.rundir import save_model

    save_model(tmp_path / "run", torchcal.RobotModel(iiwa, torch.zeros(1, 3, dtype=torch.float64), orders=0))
    pd.DataFrame({"x": [500.0], "y": [0.0], "z": [600.0], "rx": [180.0], "ry": [0.0], "rz": [0.0],
                  "shoulder": [1], "elbow": [1], "wrist": [1]}).to_csv(tmp_path / "t.csv", index=False)
    r = CliRunner().invoke(app, ["compensate", str(tmp_path / "run"), str(tmp_path / "t.csv"), str(tmp_path / "o.csv")])
    assert r.exit_code == 2 and "defined for 6R arms" in r.output and "7 joints" in r.output, r.output
