"""The fitted FANUC and its truth for experiments/compensation/run.py (cached under runs/compensation).

Paper II's simulated FANUC LR Mate 200i (:meth:`TruthRobot.fanuc_paper2`, seed 0, errors on the joint
command), 250 identification poses measured with the three tools of Table 4 (Paper II's noise),
order 6 + backlash fitted by the default solver: the model of experiments/paper2_fanuc/run.py.
"""

from __future__ import annotations

import torchcal  # noqa: F401  first (OMP_WAIT_POLICY)

import time
from pathlib import Path

import torch

from torchcal.core import units
from torchcal.identify import NoiseModel, Prior, fit
from torchcal.kinematics import load_robot
from torchcal.models.robot import RobotModel
from torchcal.sim import TruthRobot, quasi_random_commands, simulate

ROOT = Path(__file__).resolve().parents[2]
TOOLS_MM = [[33.06, 57.73, 161.22], [57.26, -33.86, 161.22], [-33.96, -57.23, 161.22]]  # Paper II Table 4


def setup(seed: int = 0, cache: Path | None = None):
    """-> (robot, truth, fitted model, tools (3, 3) m); the fit is cached (state dict) in ``cache``."""
    robot = load_robot("fanuc_lrmate200i")
    tools = units.mm_to_m(torch.tensor(TOOLS_MM, dtype=torch.float64))
    truth = TruthRobot.fanuc_paper2(robot, tools, seed)
    model = RobotModel(robot, tools, orders=6, backlash=True)
    cache = cache or ROOT / "runs" / "compensation" / f"model_seed{seed}.pt"
    if cache.exists():
        model.load_state_dict(torch.load(cache))
    else:
        noise = NoiseModel.paper2()
        q_id = quasi_random_commands(robot.joint_map.limits, 250, seed, shuffle=False)
        data = simulate(truth, q_id, [0, 1, 2], noise, seed)
        t0 = time.perf_counter()
        fit(model, data, noise, Prior())
        print(f"fitted order 6 + backlash on 250 poses in {time.perf_counter() - t0:.1f} s -> {cache}")
        cache.parent.mkdir(parents=True, exist_ok=True)
        torch.save(model.state_dict(), cache)
    return robot, truth, model, tools


if __name__ == "__main__":
    setup()
