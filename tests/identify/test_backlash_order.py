import torch

from conftest import random_commands, randomize
from torchcal.identify import NoiseModel, Prior
from torchcal.identify.backlash import select_backlash_orders
from torchcal.core.measurements import Measurements
from torchcal.models.robot import RobotModel


def _data(truth, robot, poses, seed, noise):
    q = random_commands(robot, poses, seed)
    # random approach directions, independent of position: the backlash is identifiable
    s = torch.where(torch.rand(q.shape, generator=torch.Generator().manual_seed(seed + 1)) < 0.5, -1.0, 1.0).to(q)
    qq, ss = q.repeat(3, 1), s.repeat(3, 1)
    tool = torch.arange(3).repeat_interleave(poses)
    g = torch.Generator().manual_seed(seed + 2)
    with torch.no_grad():
        v = torch.randn(qq.shape, generator=g, dtype=qq.dtype) * noise.joint_variance(ss).sqrt()
        p = truth.points(qq, tool, ss, v) + torch.randn(qq.shape[0], 3, generator=g, dtype=qq.dtype) * noise.sigma_m
    return Measurements(qq, tool, p, ss, torch.arange(poses).repeat(3), torch.arange(1, 3 * poses + 1), True, "sim")


def test_backlash_switched_on_where_the_data_show_it(fanuc, tools_m):
    truth = randomize(RobotModel(fanuc, tools_m, orders=1, backlash=0), 3, rot=1e-3, trans=1e-4)
    with torch.no_grad():
        truth.joint_errors.backlash.copy_(torch.full_like(truth.joint_errors.backlash, 2e-4))  # ~0.01 deg per joint
    noise = NoiseModel.paper2()
    data = _data(truth, fanuc, 60, 5, noise)

    def make(orders, backlash):
        return RobotModel(fanuc, tools_m, orders=orders, backlash=backlash)

    sel = select_backlash_orders(make, [1] * 6, data, None, noise, Prior(), candidates=(-1, 0), start=-1, per_joint=False)
    assert sel.orders == [0] * 6  # starting from "off", the real backlash is significantly better
    scores = {tuple(r["orders"]): r["score"] for r in sel.table}
    assert scores[(0,) * 6] < scores[(-1,) * 6]
    # a candidate is only kept when it wins by the margin: starting at 0, switching off never wins
    sel0 = select_backlash_orders(make, [1] * 6, data, None, noise, Prior(), candidates=(-1, 0), start=0, per_joint=False)
    assert sel0.orders == [0] * 6
