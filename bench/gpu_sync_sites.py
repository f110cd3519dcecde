"""Device probe: where the GPU fleet solve waits for the device (host syncs), by torchcal source line.

torch.cuda.set_sync_debug_mode("warn") warns at every synchronizing call; each warning's Python stack is
attributed to its innermost torchcal frame and counted.

    python bench/gpu_sync_sites.py [--units 100]
"""

from __future__ import annotations

import torchcal  # noqa: F401  first: OMP_WAIT_POLICY=PASSIVE before torch loads

import argparse
import collections
import traceback
import warnings

import torch

import torchcal.sim
from torchcal.core import units as U
from torchcal.identify.fleet import fit_fleet
from torchcal.sim.fleet import fleet_truths

TOOLS = U.mm_to_m(torch.tensor([[33.06, 57.73, 161.22], [57.26, -33.86, 161.22], [-33.96, -57.23, 161.22]],
                               dtype=torch.float64))


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("--units", type=int, default=100)
    args = ap.parse_args()
    gpu = torch.device("cuda")
    robot = torchcal.load_robot("fanuc_lrmate200i")
    noise = torchcal.NoiseModel.from_robot(robot)
    q = torchcal.sim.quasi_random_commands(robot.joint_map.limits, 250, 0)
    fleet = fleet_truths(robot, TOOLS, args.units, 0, [7, 23, 42, 61, 88])
    units = [torchcal.simulate(t, q, [0, 1, 2], noise, k).to(gpu) for k, t in enumerate(fleet.truths)]

    def make():
        return torchcal.RobotModel(robot, TOOLS, orders=6, backlash=True).to(gpu)

    fit_fleet(make, units[:3], noise)  # warm-up
    sites = collections.Counter()

    def hook(message, category, filename, lineno, file=None, line=None):
        frames = [f for f in traceback.extract_stack()[:-1] if "torchcal" in f.filename and "bench" not in f.filename]
        key = " <- ".join(f"{f.filename.split('torchcal/')[-1]}:{f.lineno}" for f in frames[-2:][::-1]) or "?"
        sites[key] += 1

    warnings.showwarning = hook
    warnings.simplefilter("always")
    torch.cuda.set_sync_debug_mode("warn")
    fit_fleet(make, units, noise)
    torch.cuda.set_sync_debug_mode("default")
    total = sum(sites.values())
    print(f"host syncs in one fleet solve of {args.units} units: {total}")
    for k, v in sites.most_common(30):
        print(f"{v:6d}  {k}")


if __name__ == "__main__":
    main()
