"""The fleet target's ratio, measured interleaved: (one batched solve of M units) / (ONE separate fit), side by side.

Issue 18: a fleet of 100 simulated FANUCs (250 x 3 poses each, order 6 +
backlash, own truths from torchcal.sim.fleet) in one batched solve within
10x the time of ONE fit on 2 cores. The machine is shared, so the two are
timed alternately in one process (fit, fleet, fit, fleet, ...) and each
fleet solve is divided by the mean of the fits around it; the median of
those ratios is printed, with every run. "ONE fit" is torchcal.fit on one
unit's data with the same model, noise and prior (its whole call: gauge
fixing included, as the fleet's time includes its gauge). Each at its own
default stopping tolerance: the fleet at FLEET_FTOL (1e-4, every unit within
0.03 % of its own fit's validation residual: experiments/fleet/run.py checks
the issue's 1 %), the fit at 1e-8; ``--ftol 1e-8`` times the fleet at the
fit's.

    python experiments/fleet/ratio.py [--units 100] [--repeats 2] [--dense] [--threads N] [--ftol F] [--own-programs]
"""

from __future__ import annotations

import argparse
import statistics
import sys
import time

import torchcal  # noqa: F401  (before torch: the OpenMP wait policy)
import torch

import torchcal.sim
from torchcal.core import units as U
from torchcal.identify import fit
from torchcal.identify.fleet import FLEET_FTOL, fit_fleet
from torchcal.sim.fleet import fleet_truths

TOOLS_MM = [[33.06, 57.73, 161.22], [57.26, -33.86, 161.22], [-33.96, -57.23, 161.22]]  # Paper II Table 4


def program(lim, seed: int):
    """(commands (250, n), approach directions (250, n) of +-1) of one measuring program, from its seed."""
    q = torchcal.sim.quasi_random_commands(lim, 250, seed)
    g = torch.Generator().manual_seed(seed)
    return q, torch.where(torch.rand(q.shape, generator=g, dtype=torch.float64) > 0.5, 1.0, -1.0)


def unit_program(lim, seed: int, k: int):
    """Unit k's own program (``--own-programs``), apart from the fleet's one program of the same seed."""
    return program(lim, 1000 * seed + 1 + k)


def fleet_data(units: int, seed: int = 0, damaged=(7, 23, 42, 61, 88), own_programs: bool = False):
    """(make, identification data per unit, noise) of experiments/fleet/run.py's fleet. own_programs: each unit
    measured with its own program (its own commands and approach directions) instead of one for all."""
    robot = torchcal.load_robot("fanuc_lrmate200i")
    tools = U.mm_to_m(torch.tensor(TOOLS_MM, dtype=torch.float64))
    noise = torchcal.NoiseModel.from_robot(robot)
    fleet = fleet_truths(robot, tools, units, seed, [d for d in damaged if d < units])
    lim = robot.joint_map.limits
    programs = [unit_program(lim, seed, k) for k in range(units)] if own_programs else [program(lim, seed)] * units
    ident = [torchcal.simulate(t, q, [0, 1, 2], noise, 1000 * seed + k, directions=d)
             for k, (t, (q, d)) in enumerate(zip(fleet.truths, programs))]

    def make():
        return torchcal.RobotModel(robot, tools, orders=6, backlash=True)

    return make, ident, noise


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--units", type=int, default=100)
    ap.add_argument("--repeats", type=int, default=2)
    ap.add_argument("--dense", action="store_true", help="the dense batched path (before the factored one)")
    ap.add_argument("--threads", type=int, default=None, help="fix the thread count of both (default: by work)")
    ap.add_argument("--ftol", type=float, default=None, help="the fleet's stopping tolerance (default FLEET_FTOL)")
    ap.add_argument("--own-programs", action="store_true",
                    help="each unit measured with its own program (commands and approach directions)")
    a = ap.parse_args(argv)
    if a.threads:
        from torchcal.core.threads import set_threads

        set_threads(a.threads)
    make, ident, noise = fleet_data(a.units, own_programs=a.own_programs)
    opts = {"structured": False} if a.dense else {}
    if a.ftol is not None:
        opts["ftol"] = a.ftol
    fit(make(), ident[0], noise)  # warm-up: imports, allocator
    fit_fleet(make, ident[:2], noise, **opts)  # warm-up: compiled kernels
    ones, ratios = [], []

    def one(k):
        t = time.perf_counter()
        r = fit(make(), ident[k % len(ident)], noise)
        ones.append(time.perf_counter() - t)
        return r

    one(0)
    for rep in range(a.repeats):
        before = ones[-1]
        t, c = time.perf_counter(), time.process_time()
        out = fit_fleet(make, ident, noise, **opts)
        tf = time.perf_counter() - t
        cores = (time.process_time() - c) / tf  # the CPU share the fleet got (two streams beside a busy core: ~1.3)
        one(rep + 1)
        ref = 0.5 * (before + ones[-1])
        ratios.append(tf / ref)
        print(f"run {rep}: fleet of {a.units} {tf:.2f} s, one fit {before:.3f} / {ones[-1]:.3f} s -> ratio {tf / ref:.1f} "
              f"(batched iterations {out.batch.iterations}, unit iterations {sum(r.nit for r in out.results)}, "
              f"fleet CPU time / wall time {cores:.2f})", flush=True)
    print(f"ratio fleet / one fit: median {statistics.median(ratios):.1f} (target <= 10); one fit median "
          f"{statistics.median(ones):.3f} s; threads {torch.get_num_threads()}; fleet ftol "
          f"{a.ftol if a.ftol is not None else FLEET_FTOL:g}; {'each unit its own program' if a.own_programs else 'one program'}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
