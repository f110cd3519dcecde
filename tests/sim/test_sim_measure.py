import math

import pytest
import torch

from torchcal.identify import NoiseModel
from torchcal.sim import TruthRobot, approach_directions, noise_free_points, quasi_random_commands, simulate


@pytest.fixture(scope="module")
def truth(fanuc, tools_m):
    return TruthRobot.fanuc_paper2(fanuc, tools_m, 0)


def test_rows_are_tool_major_with_shared_pose_ids(fanuc, truth):
    q = quasi_random_commands(fanuc.joint_map.limits, 30, 1)
    data = simulate(truth, q, [2, 0], NoiseModel.paper2(), seed=3)
    assert len(data) == 60 and data.has_direction and data.source == "simulated"
    assert torch.equal(data.tool, torch.tensor([2] * 30 + [0] * 30))
    assert torch.equal(data.pose, torch.arange(30).repeat(2))
    assert torch.equal(data.q, q.repeat(2, 1))
    assert torch.equal(data.direction, approach_directions(q).repeat(2, 1))
    assert torch.equal(data.rows, torch.arange(1, 61))
    assert data.extra["v"].shape == (60, 6) and data.extra["xyz_exact"].shape == (60, 3)


def test_noise_free_simulation_is_the_truth(fanuc, truth):
    q = quasi_random_commands(fanuc.joint_map.limits, 25, 2)
    data = simulate(truth, q, [0, 1, 2], None, seed=0)
    assert torch.equal(data.xyz, truth.points(data.q, data.tool, data.direction))
    assert torch.equal(noise_free_points(truth, data), data.xyz)
    assert torch.equal(data.extra["v"], torch.zeros_like(data.q))
    # given directions are used as they are (backlash follows them)
    flipped = simulate(truth, q, [0], None, seed=0, directions=-approach_directions(q))
    assert torch.equal(flipped.direction, -approach_directions(q))
    assert (flipped.xyz - data.xyz[:25]).norm(dim=1).mean() > 1e-6


def test_noise_has_the_configured_standard_deviations(fanuc, truth):
    """Tracker noise per axis and joint errors per approach direction, large-sample bounds."""
    q = quasi_random_commands(fanuc.joint_map.limits, 2000, 4)
    deg2 = (math.pi / 180) ** 2
    fwd = torch.tensor([1e-4, 4e-4, 1e-4, 9e-4, 1e-4, 1e-4]) * deg2
    bwd = torch.tensor([4e-4, 1e-4, 9e-4, 1e-4, 1e-4, 2.5e-3]) * deg2
    noise = NoiseModel(2e-5, fwd, bwd)
    data = simulate(truth, q, [0, 1], noise, seed=5)
    v = data.extra["v"]
    for sgn, var in ((1.0, fwd), (-1.0, bwd)):
        for j in range(6):
            vj = v[data.direction[:, j] == sgn, j]
            assert vj.numel() > 500
            ratio = vj.std() / var[j].sqrt()
            assert 0.9 < float(ratio) < 1.1, (sgn, j, float(ratio))
            assert abs(float(vj.mean())) < 4 * float(var[j].sqrt()) / math.sqrt(vj.numel())
    # the tracker noise is what remains once the drawn joint errors are put back
    xi = data.xyz - truth.points(data.q, data.tool, data.direction, v)
    assert torch.allclose(xi.std(0), torch.full((3,), 2e-5), rtol=0.05)
    assert float(xi.mean(0).abs().max()) < 4 * 2e-5 / math.sqrt(len(data))
    # and the joint errors really move the points (at the micrometre level of Table 5)
    assert float((data.extra["xyz_exact"] - data.xyz).norm(dim=1).mean()) > 2e-5


def test_seeds_reproduce_and_differ(fanuc, truth):
    q = quasi_random_commands(fanuc.joint_map.limits, 20, 6)
    a = simulate(truth, q, [0, 1, 2], NoiseModel.paper2(), seed=11)
    b = simulate(truth, q, [0, 1, 2], NoiseModel.paper2(), seed=11)
    c = simulate(truth, q, [0, 1, 2], NoiseModel.paper2(), seed=12)
    assert torch.equal(a.xyz, b.xyz) and torch.equal(a.extra["v"], b.extra["v"])
    assert float((a.xyz - c.xyz).abs().min()) > 0.0


def test_bad_input_names_what_is_wrong(fanuc, truth):
    q = quasi_random_commands(fanuc.joint_map.limits, 5, 0)
    with pytest.raises(ValueError, match="tool index 3"):
        simulate(truth, q, [0, 3], None, 0)
    with pytest.raises(ValueError, match=r"shape \(N, 6\)"):
        simulate(truth, q[:, :5], [0], None, 0)
    bad = approach_directions(q)
    bad[2, 4] = 0.5
    with pytest.raises(ValueError, match="pose 2, joint 5"):
        simulate(truth, q, [0], None, 0, directions=bad)
