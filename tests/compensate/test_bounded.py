"""Bounded, minimum-norm compensation: commands stay on the nominal command's branch.

Near the wrist singularity (q5 = 0) a solver that follows the exact solution
wherever it lies turns q4 and q6 by tens of degrees (or by multiples of 2 pi)
for a calibration-sized error. compensate() keeps |q_new - q_nom| within
max_correction, damps the null space toward q_nom, and flags (never drops)
the rows that cannot meet (46) within the bound.
"""

import math

import pandas as pd
import pytest
import torch

from conftest import random_commands, randomize
from torchcal.compensate.toolset import compensation_goal
from torchcal.compensate import FlangeKernel, compensate
from torchcal.kinematics.transforms import pose_error
from torchcal.models.robot import RobotModel

BOUND = math.radians(30.0)  # compensate()'s default max_correction


def actual_error(model, q_new, q_nom, s):
    """(46) checked with RobotModel itself, not with the kernel the solver runs on."""
    with torch.no_grad():
        return pose_error(model.flange(q_new, s, base=False), compensation_goal(model, q_nom))


def directions(count, seed):
    return torch.sign(torch.randn(count, 6, generator=torch.Generator().manual_seed(seed)))


@pytest.fixture(scope="module")
def model(fanuc, tools_m):
    return randomize(RobotModel(fanuc, tools_m, orders=6, backlash=1), 21)  # the wrist tests were sized on this model


def offset_model(fanuc, tools_m, offsets):
    """Pure joint offsets (eps_z, constant term): F_a(q) = F_n(q + A^-1 o) exactly."""
    m = RobotModel(fanuc, tools_m, orders=2)
    with torch.no_grad():
        m.joint_errors.coef[:, 2, 0] = offsets
    return m


def test_wrist_singular_pose_gets_the_minimum_norm_correction(fanuc, tools_m):
    """q5 = 0 and joint offsets: the solutions form a line (q4 + t, q6 -/+ t); the one nearest q_nom is returned."""
    o = torch.tensor([1.0, -2.0, 1.5, 3.0, -1.0, 2.0], dtype=torch.float64) * 1e-3
    m = offset_model(fanuc, tools_m, o)
    q = random_commands(fanuc, 8, 5)
    q[:, 4] = 0.0
    res = compensate(m, q)
    assert res.converged.all()
    de = actual_error(m, res.q, q, None)
    assert de.norm(dim=-1).max() <= 1e-12  # (46) holds
    # the exact solutions: q_nom - A^-1 o + t n, n the null vector of the nominal Jacobian (q4/q6)
    k = FlangeKernel(m)
    _, _, J = k.nominal_flange_jacobian(q.T.contiguous())
    n = torch.linalg.svd(J.permute(2, 0, 1)).Vh[:, -1]
    assert (n[:, [3, 5]].abs() > 0.7).all()  # the wrist's q4/q6 combination
    shift = torch.linalg.solve(k.coupling, o)
    expected = -shift + (n @ shift)[:, None] * n  # the one nearest q_nom
    assert torch.allclose(res.q - q, expected, atol=1e-8, rtol=0)
    assert torch.allclose(res.correction, expected.abs().amax(-1), atol=1e-8, rtol=0)


@pytest.mark.parametrize("q5_deg", [0.0, 1e-5, 0.01, 0.5, 2.0])
def test_wrist_near_singular_rows_stay_within_the_bound(model, fanuc, q5_deg):
    q = random_commands(fanuc, 60, 50)
    q[:, 4] = math.radians(q5_deg) * torch.where(torch.arange(60) % 2 == 0, 1.0, -1.0).double()
    s = directions(60, 51)
    res = compensate(model, q, s)
    assert torch.isfinite(res.q).all()
    assert torch.equal(res.correction, (res.q - q).abs().amax(-1))
    assert (res.correction <= BOUND * (1 + 1e-12)).all()  # flagged or not: no swing
    de = actual_error(model, res.q, q, s)
    assert torch.allclose(res.pose_error, de, atol=1e-14, rtol=0)  # reported = recomputed, every row
    c = res.converged
    assert de[c].norm(dim=-1).max() <= 1e-12 if c.any() else True
    assert (res.residual[~c] > 1e-12).all()  # flagged rows are honest about it
    # the unbounded solver needs a swing for every row flagged here, or cannot reach it at all
    free = compensate(model, q, s, max_step=None, max_correction=None, null_damping=0.0)
    far = ~free.converged | (free.correction > BOUND)
    if q5_deg >= 0.01:
        from torchcal.compensate.result import BRANCH
        assert far[~c & (res.status != BRANCH)].all()  # (a branch change may be near: refused on purpose)
        near = c & free.converged & (free.correction <= math.radians(5.0))  # one calibration-sized solution
        assert torch.allclose(res.q[near], free.q[near], atol=1e-10, rtol=0)
    if q5_deg >= 2.0:
        assert c.double().mean() > 0.5  # typical wrist-near poses still compensate


def test_huge_model_error_is_flagged_and_kept(fanuc, tools_m):
    """Backlash of 0.8 rad on joint 1: rows approaching it from +/- would need a 46 deg correction."""
    m = RobotModel(fanuc, tools_m, orders=2, backlash=True)
    with torch.no_grad():
        m.joint_errors.backlash[0, 0] = 0.8
    q = random_commands(fanuc, 30, 52)
    s = directions(30, 53)
    s[::3, 0] = 0.0  # every third row: direction unknown, no backlash term, a zero correction
    huge = s[:, 0] != 0
    res = compensate(m, q, s)
    assert res.q.shape == q.shape and torch.isfinite(res.q).all()  # every row kept, in order
    assert not res.converged[huge].any()
    assert res.converged[~huge].all()
    assert torch.equal(res.q[~huge], q[~huge])
    assert (res.correction <= BOUND * (1 + 1e-12)).all()
    de = actual_error(m, res.q, q, s)
    assert torch.allclose(res.pose_error, de, atol=1e-14, rtol=0)
    assert (res.residual[huge] > 1e-3).all()
    # with room for the correction the same rows converge, turning joint 1 back by the backlash
    wide = compensate(m, q, s, max_step=math.radians(30), max_correction=math.radians(60))
    w = wide.converged & huge
    assert w.sum() >= 0.8 * huge.sum()
    assert torch.allclose((wide.q - q)[w, 0], -0.8 * s[w, 0], atol=5e-2)
    assert (wide.correction[w] > BOUND).all()
    assert (actual_error(m, wide.q, q, s)[w].norm(dim=-1) <= 1e-12).all()
    # the flagged rows alone give the same answer as in the mixed batch
    alone = compensate(m, q[huge], s[huge])
    assert torch.allclose(alone.q, res.q[huge], atol=1e-9, rtol=0)


def test_tighter_bound_flags_more_and_changes_nothing_else(model, fanuc):
    q = random_commands(fanuc, 200, 54)
    s = directions(200, 55)
    wide = compensate(model, q, s)
    tight = compensate(model, q, s, max_step=math.radians(0.3), max_correction=math.radians(0.3))
    assert (tight.correction <= math.radians(0.3) * (1 + 1e-12)).all()
    assert tight.converged.sum() < wide.converged.sum()
    assert not (tight.converged & ~wide.converged).any()
    c = tight.converged
    assert torch.allclose(tight.q[c], wide.q[c], atol=1e-10, rtol=0)
    assert (wide.correction[wide.converged & ~c] > math.radians(0.3) * 0.999).all()


def test_direction_outside_the_identification_coverage(fanuc, tools_m):
    from torchcal.analysis.coverage import DirectionCoverage

    m = randomize(RobotModel(fanuc, tools_m, orders=2, backlash=True), 56)
    q = random_commands(fanuc, 40, 57)
    s = directions(40, 58)
    assert compensate(m, q, s).direction_outside is None  # no coverage recorded
    lim = m.command_limits
    # identification data that approached joint 2 only from below
    q_id = random_commands(fanuc, 500, 59)
    s_id = directions(500, 60)
    s_id[:, 1] = 1.0
    m.coverage = DirectionCoverage.from_data(q_id, s_id, lim, bins=4)
    res = compensate(m, q, s)
    assert res.direction_outside is not None and res.direction_outside.dtype == torch.bool
    assert torch.equal(res.direction_outside, m.coverage.outside(res.q, s))
    assert torch.equal(res.direction_outside, s[:, 1] < 0)  # every other pattern was seen
    assert compensate(m, q).direction_outside is None  # no directions: nothing to judge
    assert res.summary()["direction_outside"] == int((s[:, 1] < 0).sum())


def test_cli_writes_the_correction_and_coverage_columns(fanuc, tools_m, tmp_path):
    from typer.testing import CliRunner

    from torchcal.analysis.coverage import DirectionCoverage
    from torchcal.cli import app
    from torchcal.io.rundir import save_model

    m = RobotModel(fanuc, tools_m, orders=2, backlash=True)
    with torch.no_grad():
        # joint 1 turns by 0.15 + 0.15 s1: rows with dir1 = +1 need a 17 deg correction, dir1 = -1 none
        m.joint_errors.backlash[0, 0] = 0.15
        m.joint_errors.coef[0, 2, 0] = 0.15
        m.joint_errors.coef[1, 2, 0] = 1e-3  # and everyone about 0.057 deg on joints 2 and 3
    q_id = random_commands(fanuc, 300, 61)
    s_id = directions(300, 62)
    s_id[:, 2] = -1.0
    m.coverage = DirectionCoverage.from_data(q_id, s_id, m.command_limits, bins=4)
    save_model(tmp_path, m)
    q = torch.rad2deg(random_commands(fanuc, 6, 63))
    s = directions(6, 64)
    s[:, 0] = torch.tensor([-1.0, -1.0, -1.0, 1.0, 1.0, 1.0])
    s[:, 2] = torch.tensor([-1.0, 1.0, -1.0, -1.0, 1.0, -1.0])
    df = pd.DataFrame(q.numpy(), columns=[f"q{i}" for i in range(1, 7)])
    for i in range(6):
        df[f"dir{i + 1}"] = s[:, i].numpy()
    df["id"] = [f"r{i}" for i in range(6)]
    df.to_csv(tmp_path / "in.csv", index=False)
    r = CliRunner().invoke(app, ["compensate", str(tmp_path), str(tmp_path / "in.csv"), str(tmp_path / "out.csv"),
                                 "--max-correction-deg", "5"])
    assert r.exit_code == 0, r.output
    out = pd.read_csv(tmp_path / "out.csv")
    assert list(out.id) == list(df.id)  # every row kept, in order
    assert list(out.converged) == [True] * 3 + [False] * 3
    dq = (out[[f"q{i}" for i in range(1, 7)]].to_numpy() - df[[f"q{i}" for i in range(1, 7)]].to_numpy())
    assert abs(out.max_dq.to_numpy() - abs(dq).max(axis=1)).max() < 1e-9  # degrees
    assert (out.max_dq[:3] > 0.04).all() and (out.max_dq[:3] < 0.1).all()
    assert (out.max_dq[3:] <= 5.0 + 1e-9).all()
    assert list(out.direction_outside) == [False, True, False, False, True, False]
    # the default bound (30 deg, with the branch test) lets the large corrections through
    r = CliRunner().invoke(app, ["compensate", str(tmp_path), str(tmp_path / "in.csv"), str(tmp_path / "out2.csv")])
    assert r.exit_code == 0, r.output
    out2 = pd.read_csv(tmp_path / "out2.csv")
    assert out2.converged.all() and (out2.max_dq[3:] > 10.0).all()


def test_per_joint_bounds(model, fanuc):
    """A bound per joint (deg for revolute, mm for prismatic by default): each joint stays inside its own."""
    from torchcal.compensate import per_joint_bound

    b = per_joint_bound("default", 3, torch.float64, "cpu", prismatic=[False, True, False])
    assert torch.allclose(b, torch.tensor([math.radians(30.0), 5e-3, math.radians(30.0)], dtype=torch.float64))
    step = per_joint_bound("default", 3, torch.float64, "cpu", "max_step", prismatic=[False, True, False])
    assert torch.allclose(step, torch.tensor([math.radians(5.0), 5e-3, math.radians(5.0)], dtype=torch.float64))
    assert torch.equal(per_joint_bound(0.1, 2, torch.float64, "cpu"), torch.tensor([0.1, 0.1], dtype=torch.float64))
    with pytest.raises(ValueError, match="one value per joint"):
        per_joint_bound(torch.ones(3), 2, torch.float64, "cpu")
    with pytest.raises(ValueError, match="positive"):
        per_joint_bound(0.0, 2, torch.float64, "cpu")
    q = random_commands(fanuc, 200, 70)
    s = directions(200, 71)
    scalar = compensate(model, q, s)
    same = compensate(model, q, s, max_step=torch.full((6,), math.radians(5.0)), max_correction=torch.full((6,), BOUND))
    assert torch.equal(scalar.q, same.q) and torch.equal(scalar.converged, same.converged)
    tight = torch.full((6,), BOUND, dtype=torch.float64)
    tight[3] = math.radians(0.5)  # J4 may move half a degree, the others 5
    res = compensate(model, q, s, max_step=tight, max_correction=tight)
    d = (res.q - q).abs()
    assert (d <= tight * (1 + 1e-12)).all()  # flagged or not
    assert (d[:, [0, 1, 2, 4, 5]] > math.radians(0.5)).any()  # the other joints still use their wider bound
    need = (scalar.q - q).abs()[:, 3] > math.radians(0.5)
    assert not (res.converged & scalar.converged & need).any()  # rows whose J4 needs more are not converged
