"""Compensation of a model whose flange depends on the whole configuration (fine joint tables): the snapshot
hands the backends the model itself (``live``), so the compensated command reaches the nominal flange on the
model's own FK, fine tables included. Before the snapshot the fast path ignored the tables."""

import torch

import torchcal
from torchcal.compensate import compensate


def test_compensation_with_fine_joint_tables_reaches_the_nominal_flange():
    robot = torchcal.load_robot("fanuc_lrmate200i")
    lo, hi = robot.joint_map.limits[:, 0], robot.joint_map.limits[:, 1]
    fine = {"lower": (lo + 0.2).tolist(), "upper": (hi - 0.2).tolist(), "spacing": 0.05}
    model = torchcal.RobotModel(robot, torch.zeros(1, 3, dtype=torch.float64), orders=2, fine=fine)
    g = torch.Generator().manual_seed(11)
    with torch.no_grad():
        model.joint_errors.coef.normal_(0.0, 2e-4, generator=g)
        model.fine.values.normal_(0.0, 3e-4, generator=g)  # ~0.02 deg ripple on every joint
    assert model.flange_snapshot().live is model
    q = lo + 0.3 + (hi - lo - 0.6) * torch.rand(200, robot.joint_map.n, generator=g, dtype=torch.float64)
    res = compensate(model, q)
    ok = res.converged & res.within_limits
    assert ok.float().mean() > 0.95
    with torch.no_grad():
        reached = model.flange(res.q[ok], base=False)
        target = model.nominal_flange(q[ok])
    assert (reached[:, :3, 3] - target[:, :3, 3]).norm(dim=-1).max() < 1e-9
    # and the tables matter: without them the same commands miss by far more
    without = torchcal.RobotModel(robot, torch.zeros(1, 3, dtype=torch.float64), orders=2)
    without.load_state_dict({k: v for k, v in model.state_dict().items() if not k.startswith("fine")}, strict=False)
    with torch.no_grad():
        off = (without.flange(res.q[ok], base=False)[:, :3, 3] - target[:, :3, 3]).norm(dim=-1).max()
    assert off > 1e-6
