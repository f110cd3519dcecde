"""`torchcal fleet` on a local Ray with 2 workers against the local engine: the same 100-unit fleet, one unit's
file broken. Prints whether every fitted model is identical bit for bit and what happened to the broken unit.

    python experiments/fleet/ray_check.py [--units 100] [--out runs/fleet_ray_check]   (needs pip install -e ".[ray]")
"""

from __future__ import annotations

import argparse
import shutil
import sys
import time
from pathlib import Path

import torchcal  # noqa: F401  before torch: its OpenMP threads then sleep while waiting (torchcal.core.threads)
import torch

import torchcal
import torchcal.sim
from torchcal.core import units as U
from torchcal.io.csv import write_measurements
from torchcal.sim.fleet import fleet_truths

TOOLS_MM = [[33.06, 57.73, 161.22], [57.26, -33.86, 161.22], [-33.96, -57.23, 161.22]]


def write_fleet(out: Path, count: int, broken: int | None) -> Path:
    """``count`` simulated FANUCs' identification files under out/units (one program, 250 poses x 3 tools, order 6
    + backlash truths, J3 gearboxes damaged on units 7, 23, 42, 61, 88), unit ``broken``'s with a non-number in its
    40th row; -> the fleet config out/fleet.yaml. ``out`` is emptied first."""
    shutil.rmtree(out, ignore_errors=True)
    (out / "units").mkdir(parents=True)
    robot = torchcal.load_robot("fanuc_lrmate200i")
    tools = U.mm_to_m(torch.tensor(TOOLS_MM, dtype=torch.float64))
    noise = torchcal.NoiseModel.from_robot(robot)
    fleet = fleet_truths(robot, tools, count, 0, [u for u in (7, 23, 42, 61, 88) if u < count])
    q = torchcal.sim.quasi_random_commands(robot.joint_map.limits, 250, 0)
    g = torch.Generator().manual_seed(0)
    dirs = torch.where(torch.rand(q.shape, generator=g, dtype=torch.float64) > 0.5, 1.0, -1.0)
    for k, t in enumerate(fleet.truths):
        write_measurements(out / "units" / f"unit{k:03d}.csv", torchcal.simulate(t, q, [0, 1, 2], noise, k, directions=dirs),
                           robot)
    if broken is not None:
        bad = out / "units" / f"unit{broken:03d}.csv"
        lines = bad.read_text().splitlines()
        cells = lines[40].split(",")
        cells[-1] = "n/a"
        lines[40] = ",".join(cells)
        bad.write_text("\n".join(lines) + "\n")
    tools_txt = ", ".join(f"[{x}, {y}, {z}]" for x, y, z in TOOLS_MM)
    cfg = out / "fleet.yaml"
    cfg.write_text(f"robot: fanuc_lrmate200i\ntools: [{tools_txt}]\ndata: {{identification: units}}\n"
                   "model: {order: 6, backlash: true}\nfleet: {cell: 50}\n")
    return cfg


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--units", type=int, default=100)
    ap.add_argument("--broken", type=int, default=13, help="the unit whose file gets a non-number")
    ap.add_argument("--out", default="runs/fleet_ray_check")
    args = ap.parse_args(argv)
    import ray

    from torchcal.app.fleet import run_fleet
    from torchcal.io.rundir import load_model

    out = Path(args.out)
    cfg = write_fleet(out, args.units, args.broken)
    t = time.perf_counter()
    local = run_fleet(cfg, out=out / "local")
    t_local = time.perf_counter() - t
    ray.init(num_cpus=2, include_dashboard=False, log_to_driver=False)
    try:
        t = time.perf_counter()
        remote = run_fleet(cfg, ["fleet.engine=ray"], out=out / "ray")
        t_ray = time.perf_counter() - t
    finally:
        ray.shutdown()
    same, fitted = 0, 0
    for a, b in zip(local.rows, remote.rows):
        if a["status"] != "fitted" or b["status"] != "fitted":
            continue
        fitted += 1
        ma, mb = load_model(local.run_dir / "units" / a["unit"]), load_model(remote.run_dir / "units" / b["unit"])
        same += all(torch.equal(x, y) for x, y in zip(ma.state_dict().values(), mb.state_dict().values()))
    failed = [(r["unit"], r["reason"].splitlines()[-1].strip()) for r in remote.rows if r["status"] == "failed"]
    print(f"local engine {t_local:.1f} s, Ray (local, 2 workers) {t_ray:.1f} s; fitted {fitted} units on both; "
          f"identical bit for bit: {same}/{fitted} ({'PASS' if same == fitted == args.units - 1 else 'FAIL'})")
    print(f"reported, not fitted: {failed}")
    print(f"flagged (Ray run): {[r['unit'] for r in remote.rows if r.get('flagged')]}: "
          + "; ".join(f"{r['unit']}: {r['findings']}" for r in remote.rows if r.get("flagged")))
    return 0


if __name__ == "__main__":
    sys.exit(main())
