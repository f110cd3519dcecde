"""plan_poses: quasi-random reachable poses in a backlash-decorrelating order, and the plan-poses command."""

import math

import pytest
import torch
from typer.testing import CliRunner

from torchcal.cli import app
from torchcal.io.csv import read_table
from torchcal.analysis.planning import PlanningError, decorrelating_order, plan_poses
from torchcal.sim.sampling import approach_directions

runner = CliRunner()


@pytest.fixture(scope="module")
def plans(fanuc):
    return {o: plan_poses(fanuc, 150, seed=2, order=o) for o in ("decorrelate", "shuffle", "sequence")}


def test_limits_and_reachability(fanuc, plans):
    lim = fanuc.joint_map.limits
    for plan in plans.values():
        assert plan.q.shape == (150, 6) and plan.directions.shape == (150, 6)
        assert bool(((plan.q >= lim[:, 0]) & (plan.q <= lim[:, 1])).all())
        F = fanuc.chain.fk(fanuc.joint_map.to_joint(plan.q))
        assert torch.allclose(F[:, :3, 3], plan.flange)
        assert bool((plan.flange[:, 2] >= 0.0).all()) and bool((plan.flange.norm(dim=1) >= 0.2).all())
        assert torch.equal(plan.directions, approach_directions(plan.q))
    # the three orders visit the same poses
    key = lambda q: q[torch.argsort(q[:, 0])]  # noqa: E731
    assert torch.equal(key(plans["decorrelate"].q), key(plans["sequence"].q))
    assert plans["sequence"].stats["rejected"]["below_plane"] > 0     # some FANUC poses reach below the shoulder
    m = plan_poses(fanuc, 40, seed=1, margin=0.1, min_height=0.1, min_tool_distance=0.6)
    w = lim[:, 1] - lim[:, 0]
    assert bool(((m.q >= lim[:, 0] + 0.1 * w - 1e-12) & (m.q <= lim[:, 1] - 0.1 * w + 1e-12)).all())
    assert bool((m.flange[:, 2] >= 0.1).all()) and bool((m.flange.norm(dim=1) >= 0.6).all())
    assert m.stats["rejected"]["near_base"] > 0


def test_deterministic_for_a_seed(fanuc):
    a = plan_poses(fanuc, 60, seed=5)
    b = plan_poses(fanuc, 60, seed=5)
    c = plan_poses(fanuc, 60, seed=6)
    assert torch.equal(a.q, b.q) and a.stats == b.stats
    assert not torch.allclose(a.q, c.q)


def test_decorrelated_order_beats_sequence_and_shuffle(plans):
    dec, shuf, seq = (plans[o].stats for o in ("decorrelate", "shuffle", "sequence"))
    assert seq["max_abs_corr"] > 0.75 and seq["max_r2"] > 0.6          # sequence order: s ≈ sign(q - mid)
    assert shuf["max_abs_corr"] > 0.4                                  # a shuffle keeps E[s | q] = 2u - 1
    assert dec["max_abs_corr"] < 0.2 and dec["max_r2"] < 0.12
    assert sum(dec["one_sided_bins"]) == 0
    assert dec["sequence"]["corr"] == pytest.approx(seq["corr"])       # reported for comparison
    assert plans["decorrelate"].coverage().both_fraction().min() == 1.0
    rows = plans["decorrelate"].table(["a", "b", "c", "d", "e", "f"])
    assert rows[0]["joint"] == "a" and rows[0]["corr"] == dec["corr"][0]


def test_decorrelating_order_is_a_permutation(fanuc):
    q = plan_poses(fanuc, 50, seed=0, order="sequence").q
    perm = decorrelating_order(q, fanuc.joint_map.limits, seed=3, start=torch.zeros(6))
    assert sorted(perm.tolist()) == list(range(50))
    assert decorrelating_order(q[:0], fanuc.joint_map.limits).numel() == 0
    p = plan_poses(fanuc, 30, seed=0, start=torch.zeros(6))
    assert torch.equal(p.directions, approach_directions(p.q, torch.zeros(6)))


def test_tracker_visibility(fanuc):
    tracker = torch.tensor([1.5, 0.0, 0.5], dtype=torch.float64)
    p = plan_poses(fanuc, 60, seed=0, tracker=tracker, max_incidence_deg=50.0)
    F = fanuc.chain.fk(fanuc.joint_map.to_joint(p.q))
    los = tracker - F[:, :3, 3]
    cos = (los * F[:, :3, 2]).sum(1) / los.norm(dim=1)
    assert bool((cos >= math.cos(math.radians(50.0)) - 1e-12).all())
    assert p.stats["rejected"]["not_visible"] > 0


def test_errors(fanuc):
    with pytest.raises(PlanningError, match="reachable"):
        plan_poses(fanuc, 10, min_height=5.0, max_draws=200)
    with pytest.raises(PlanningError):
        plan_poses(fanuc, 10, order="sorted")
    with pytest.raises(PlanningError):
        plan_poses(fanuc, 10, tracker=[1.0, 2.0])
    with pytest.raises(ValueError):
        plan_poses(fanuc, 0)


def test_the_keep_out_sphere_moves_with_a_rail(tmp_path):
    """Around the rail's origin, a planned flange could sit inside the arm's own column once the carriage moved;
    the sphere is centred on the carried base (a fixed base: unchanged)."""
    import torchcal
    from torchcal.analysis.planning import _carried_base

    path = tmp_path / "rail.urdf"
    path.write_text(
        '<robot name="r"><link name="a"/><link name="b"/><link name="c"/><link name="d"/><link name="e"/>'
        '<joint name="rail" type="prismatic"><parent link="a"/><child link="b"/><axis xyz="1 0 0"/>'
        '<limit lower="0" upper="3" effort="1" velocity="1"/></joint>'
        '<joint name="j1" type="revolute"><parent link="b"/><child link="c"/><origin xyz="0 0 0.4"/><axis xyz="0 0 1"/>'
        '<limit lower="-3" upper="3" effort="1" velocity="1"/></joint>'
        '<joint name="j2" type="revolute"><parent link="c"/><child link="d"/><origin xyz="0.1 0 0.3"/><axis xyz="0 1 0"/>'
        '<limit lower="-1.5" upper="1.5" effort="1" velocity="1"/></joint>'
        '<joint name="j3" type="revolute"><parent link="d"/><child link="e"/><origin xyz="0 0 0.6"/><axis xyz="0 1 0"/>'
        '<limit lower="-2" upper="2" effort="1" velocity="1"/></joint></robot>')
    robot = torchcal.load_robot(str(path))
    theta = torch.tensor([[2.5, 0.3, 0.2, -0.4], [0.7, -1.0, 0.5, 0.1]], dtype=torch.float64)
    assert torch.allclose(_carried_base(robot.chain, theta), torch.tensor([[2.5, 0.0, 0.0], [0.7, 0.0, 0.0]],
                                                                        dtype=torch.float64), atol=1e-15)
    fixed = torchcal.load_robot("fanuc_lrmate200i")
    assert _carried_base(fixed.chain, torch.rand(5, 6, dtype=torch.float64)).abs().max() == 0
    plan = plan_poses(robot, 60, seed=2, min_tool_distance=0.5)
    F = robot.chain.fk(robot.joint_map.to_joint(plan.q))
    base = torch.stack([plan.q[:, 0], torch.zeros(60, dtype=torch.float64), torch.zeros(60, dtype=torch.float64)], 1)
    assert float((F[:, :3, 3] - base).norm(dim=1).min()) >= 0.5


def test_csv_round_trip(fanuc, tmp_path):
    plan = plan_poses(fanuc, 40, seed=1)
    path = plan.to_csv(tmp_path / "plan.csv", fanuc)
    assert path.read_text().splitlines()[0] == "pose,q1,q2,q3,q4,q5,q6"
    data, _ = read_table(path, fanuc, n_tools=None, require_xyz=False, require_pose=True)
    assert torch.allclose(data.q, plan.q, atol=1e-10, rtol=0)  # 12 significant digits in deg
    assert data.pose.tolist() == list(range(40))
    assert torch.equal(approach_directions(data.q), plan.directions)
    m = plan.measurements(tools=3)
    assert len(m) == 120 and m.has_direction and torch.isnan(m.xyz).all()


def test_cli_plan_poses(fanuc, tmp_path):
    out = tmp_path / "poses.csv"
    r = runner.invoke(app, ["plan-poses", "fanuc_lrmate200i", "60", str(out), "--seed", "4", "--tracker", "-1500,0,500"])
    assert r.exit_code == 0, r.output
    assert "corr" in r.output and "J2" in r.output and "wrote 60 poses" in r.output
    assert "not visible from the tracker" in r.output
    r2 = runner.invoke(app, ["plan-poses", "fanuc_lrmate200i", "20", str(tmp_path / "p2.csv")])
    assert r2.exit_code == 0 and "not visible" not in r2.output  # no tracker given: no visibility to speak of
    data, _ = read_table(out, fanuc, n_tools=None, require_xyz=False, require_pose=True)
    ref = plan_poses(fanuc, 60, seed=4, tracker=[-1.5, 0.0, 0.5])
    assert torch.allclose(data.q, ref.q, atol=1e-10, rtol=0)  # 12 significant digits in deg


@pytest.mark.parametrize("args, message", [
    (["--tracker", "1,2"], "--tracker"),
    (["--order", "sorted"], "plan-poses: --order must be one of"),
    (["--min-height-mm", "5000"], "relax --min-height-mm / --min-distance-mm / --max-incidence-deg"),
    # NaN passed every check: a NaN incidence bound switched the visibility test off silently
    (["--max-incidence-deg", "nan"], "--max-incidence-deg nan: give an angle in (0, 180]"),
    (["--max-incidence-deg", "-5"], "--max-incidence-deg -5.0: give an angle"),
    (["--min-distance-mm", "-100"], "--min-distance-mm -100.0: give a distance >= 0"),
])
def test_cli_plan_poses_bad_inputs(tmp_path, args, message):
    """Each message names the option the user typed, not the library function's argument."""
    r = runner.invoke(app, ["plan-poses", "fanuc_lrmate200i", "20", str(tmp_path / "p.csv"), *args])
    assert r.exit_code == 2, r.output
    assert message in " ".join(r.output.split())


def test_cli_unknown_robot(tmp_path):
    r = runner.invoke(app, ["plan-poses", "no_such_robot", "20", str(tmp_path / "p.csv")])
    assert r.exit_code == 2 and "no_such_robot" in r.output
