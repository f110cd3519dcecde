"""Profile the batched fleet solve on a small fleet (default 12 units): where each iteration's time goes.

    python experiments/fleet/profile_fleet.py [--units 12] [--mode torch|pyinstrument|plain]
"""
from __future__ import annotations

import argparse
import sys
import time

import torchcal  # noqa: F401  (before torch: OpenMP wait policy)
import torch

import torchcal.sim
from torchcal.core import units as U
from torchcal.identify import fit
from torchcal.identify.fleet import fit_fleet
from torchcal.sim.fleet import fleet_truths

TOOLS_MM = [[33.06, 57.73, 161.22], [57.26, -33.86, 161.22], [-33.96, -57.23, 161.22]]


def setup(M, seed=0, damaged=(7,)):
    robot = torchcal.load_robot("fanuc_lrmate200i")
    tools = U.mm_to_m(torch.tensor(TOOLS_MM, dtype=torch.float64))
    noise = torchcal.NoiseModel.from_robot(robot)
    fleet = fleet_truths(robot, tools, M, seed, [d for d in damaged if d < M])
    lim = robot.joint_map.limits
    q = torchcal.sim.quasi_random_commands(lim, 250, seed)
    g = torch.Generator().manual_seed(seed)
    dirs = torch.where(torch.rand(q.shape, generator=g, dtype=torch.float64) > 0.5, 1.0, -1.0)
    ident = [torchcal.simulate(t, q, [0, 1, 2], noise, 1000 * seed + k, directions=dirs) for k, t in enumerate(fleet.truths)]

    def make():
        return torchcal.RobotModel(robot, tools, orders=6, backlash=True)

    return make, ident, noise


def main(argv=None):
    ap = argparse.ArgumentParser()
    ap.add_argument("--units", type=int, default=12)
    ap.add_argument("--mode", default="plain")
    ap.add_argument("--out", default="/tmp/fleet_profile")
    a = ap.parse_args(argv)
    make, ident, noise = setup(a.units)
    fit(make(), ident[0], noise)
    t = time.perf_counter(); r = fit(make(), ident[0], noise); t1 = time.perf_counter() - t
    print(f"one fit {t1:.3f} s, {r.nit} it, nfev {r.nfev}")
    if a.mode == "torch":
        from torch.profiler import profile, ProfilerActivity
        with profile(activities=[ProfilerActivity.CPU], record_shapes=True) as prof:
            t = time.perf_counter(); out = fit_fleet(make, ident, noise); tf = time.perf_counter() - t
        print(prof.key_averages().table(sort_by="self_cpu_time_total", row_limit=40))
    elif a.mode == "pyinstrument":
        import pyinstrument
        p = pyinstrument.Profiler(interval=0.002)
        p.start(); t = time.perf_counter(); out = fit_fleet(make, ident, noise); tf = time.perf_counter() - t; p.stop()
        print(p.output_text(unicode=False, color=False, show_all=False))
    else:
        t = time.perf_counter(); out = fit_fleet(make, ident, noise); tf = time.perf_counter() - t
    its = [r.nit for r in out.results]
    print(f"fleet {a.units}: {tf:.3f} s = {tf / t1:.1f} x one fit; batched iterations {out.batch.iterations}, per-unit nit {its}")


if __name__ == "__main__":
    sys.exit(main())
