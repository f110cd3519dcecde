"""Real data for the fleet re-check's measure (issue #18, ``fleet.baseline``): two calibrations of one unchanged robot.

The ABB IRB 120 + FARO session (run.py's data) measured 1 000 poses in one go. Split into its first and its
second half (in the order they were measured: two "campaigns" one after the other, nothing done to the robot
in between) and into two random halves, each half is calibrated on its own (alignment, then order 4 +
backlash, as run.py) and the two models are compared as ``torchcal fleet fleet.baseline=...`` compares a
unit with its earlier calibration (torchcal.identify.fleet_change): the change at the tool at all 1 000
commands after a rigid alignment, and each joint's transmission error and backlash change. What that
prints is the measure's floor on real data: how far two calibrations of a robot that did not change lie
apart, beside each model's held-out residual on the other half.

    python experiments/irb120_faro/recheck.py DATA_DIR [--order 4] [--seed 0]
"""

from __future__ import annotations

import argparse
import sys
import tempfile
import time
from pathlib import Path

import torchcal  # noqa: F401  before torch: its OpenMP threads then sleep while waiting (torchcal.core.threads)
import torch

from torchcal.analysis.stats import point_residuals, residual_stats
from torchcal.core import units
from torchcal.identify import NoiseModel, fit
from torchcal.identify.alignment import align
from torchcal.identify.fleet_change import joint_changes, tool_change
from torchcal.kinematics import load_robot
from torchcal.models.robot import RobotModel

sys.path.insert(0, str(Path(__file__).resolve().parent))
from run import load  # noqa: E402  run.py's import of the raw files

MM = units.m_to_mm(1.0)


def calibrate(robot, data, order: int, noise):
    al = align(robot, data, n_tools=3)
    m = RobotModel(robot, al.tools, orders=order, backlash=True, base_nominal=al.base_nominal)
    r = fit(m, data, noise, max_iter=300)
    return m, r


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("data_dir", type=Path)
    ap.add_argument("--order", type=int, default=4)
    ap.add_argument("--seed", type=int, default=0)
    args = ap.parse_args(argv)
    robot = load_robot("abb_irb120")
    with tempfile.TemporaryDirectory() as tmp:
        _, data = load(args.data_dir, robot, Path(tmp))
    noise = NoiseModel.from_robot(robot, sigma_m=units.mm_to_m(0.005))
    poses = torch.unique(data.pose)  # in measuring order
    half = poses.numel() // 2
    g = torch.Generator().manual_seed(args.seed)
    perm = poses[torch.randperm(poses.numel(), generator=g)]
    splits = {"first / second half (measuring order)": (poses[:half], poses[half:]),
              f"two random halves (seed {args.seed})": (perm[:half], perm[half:])}
    print(f"ABB IRB 120 + FARO, {data.n_poses} poses x 3 reflectors; each half: alignment, order {args.order} + backlash")
    for label, (pa, pb) in splits.items():
        a_data, b_data = data.poses_subset(pa), data.poses_subset(pb)
        t = time.perf_counter()
        (ma, ra), (mb, rb) = calibrate(robot, a_data, args.order, noise), calibrate(robot, b_data, args.order, noise)
        t_fit = time.perf_counter() - t
        with torch.no_grad():
            held_a = residual_stats(point_residuals(ma, b_data)).scaled(MM)  # A's model on B's poses
            held_b = residual_stats(point_residuals(mb, a_data)).scaled(MM)
        d = tool_change(ma, mb, data.q, data.tool, data.direction if data.has_direction else None) * MM
        jc = joint_changes([ma], [mb])
        te = (jc["transmission error change"][0] / units.DEG).tolist()
        bl = (jc["backlash change"][0] / units.DEG).tolist()
        print(f"\n{label}: fits {t_fit:.1f} s ({ra.nit} / {rb.nit} iterations)")
        print(f"  held out on the other half: mean {held_a.mean:.4f} / {held_b.mean:.4f} mm, max {held_a.max:.4f} / "
              f"{held_b.max:.4f} mm")
        print(f"  change at the tool between the two calibrations, all {len(data)} rows: RMS "
              f"{float(d.pow(2).mean().sqrt()):.4f} mm, mean {float(d.mean()):.4f}, max {float(d.max()):.4f} mm")
        print("  transmission error change (deg): " + ", ".join(f"J{j + 1} {v:.4f}" for j, v in enumerate(te)))
        print("  backlash change (deg):           " + ", ".join(f"J{j + 1} {v:.4f}" for j, v in enumerate(bl)))
    return 0


if __name__ == "__main__":
    sys.exit(main())
