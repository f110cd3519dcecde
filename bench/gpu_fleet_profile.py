"""Device probe: where the GPU fleet's time goes (structured vs dense path, then a torch.profiler table), or,
with --sync-sites, where it waits for the device: every host sync (torch.cuda.set_sync_debug_mode("warn"))
counted by its innermost torchcal source lines.

    python bench/gpu_fleet_profile.py [--units 100] [--modes default,structured,dense] [--no-table] [--sync-sites]
                                      [--cprofile]

--cprofile: where the host's time goes in one GPU fleet solve (after a warm-up): cProfile's functions by their
own time and by cumulative time (the GPU waits on the host there, so the host's time is the solve's).
"""

from __future__ import annotations

import torchcal  # noqa: F401  first: OMP_WAIT_POLICY=PASSIVE before torch loads

import argparse
import collections
import time
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
    ap.add_argument("--sync-sites", action="store_true")
    ap.add_argument("--modes", default="default,structured,dense", help="fit_fleet's structured=None, True, False")
    ap.add_argument("--no-table", action="store_true", help="timings only, no torch.profiler table")
    ap.add_argument("--cprofile", action="store_true", help="cProfile of the host's time in one solve")
    args = ap.parse_args()
    gpu = torch.device("cuda")
    robot = torchcal.load_robot("fanuc_lrmate200i")
    noise = torchcal.NoiseModel.from_robot(robot)
    q = torchcal.sim.quasi_random_commands(robot.joint_map.limits, 250, 0)
    fleet = fleet_truths(robot, TOOLS, args.units, 0, [7, 23, 42, 61, 88])
    g = torch.Generator().manual_seed(0)
    dirs = torch.where(torch.rand(q.shape, generator=g, dtype=torch.float64) > 0.5, 1.0, -1.0)
    units = [torchcal.simulate(t, q, [0, 1, 2], noise, k, directions=dirs).to(gpu) for k, t in enumerate(fleet.truths)]

    def make():
        return torchcal.RobotModel(robot, TOOLS, orders=6, backlash=True).to(gpu)

    if args.sync_sites:
        return sync_sites(make, units, noise)
    if args.cprofile:
        return host_profile(make, units, noise)
    best = {}
    modes = {"default": None, "structured": True, "dense": False}
    for label in args.modes.split(","):
        structured = modes[label]
        times = []
        for _ in range(3):
            torch.cuda.synchronize()
            t = time.perf_counter()
            r = fit_fleet(make, units, noise, structured=structured)
            torch.cuda.synchronize()
            times.append(time.perf_counter() - t)
        best[structured] = min(times[1:])
        print(f"{label} (structured={structured}): {[f'{x:.3f}' for x in times]} s; unit iterations max "
              f"{max(u.nit for u in r.results)}, sum {sum(u.nit for u in r.results)}", flush=True)
    if args.no_table:
        return
    fast = min(best, key=best.get)
    from torch.profiler import ProfilerActivity, profile

    with profile(activities=[ProfilerActivity.CPU, ProfilerActivity.CUDA]) as prof:
        fit_fleet(make, units, noise, structured=fast)
        torch.cuda.synchronize()
    ka = prof.key_averages()
    print(ka.table(sort_by="self_cpu_time_total", row_limit=22, max_name_column_width=48))
    print(ka.table(sort_by="self_cuda_time_total", row_limit=12, max_name_column_width=48))
    n_launch = sum(e.count for e in ka if e.key in ("cudaLaunchKernel", "cudaLaunchKernelExC"))
    n_sync = sum(e.count for e in ka if "Synchronize" in e.key or e.key in ("aten::item", "aten::nonzero"))
    print(f"kernel launches {n_launch}, host syncs (item/nonzero/synchronize) {n_sync}")


def host_profile(make, units, noise) -> None:
    """cProfile of one fleet solve after two warm-ups: the top functions by own and by cumulative time."""
    import cProfile
    import pstats

    for _ in range(2):
        fit_fleet(make, units, noise)
    torch.cuda.synchronize()
    pr = cProfile.Profile()
    t = time.perf_counter()
    pr.enable()
    fit_fleet(make, units, noise)
    torch.cuda.synchronize()
    pr.disable()
    print(f"profiled solve {time.perf_counter() - t:.3f} s (with cProfile's overhead)")
    st = pstats.Stats(pr)
    st.sort_stats("tottime").print_stats(25)
    st.sort_stats("cumulative").print_stats(45)


def sync_sites(make, units, noise) -> None:
    """Count the host syncs of one fleet solve by their two innermost torchcal frames."""
    fit_fleet(make, units[:3], noise)  # warm-up
    sites = collections.Counter()

    def hook(message, category, filename, lineno, file=None, line=None):
        frames = [f for f in traceback.extract_stack()[:-1] if "torchcal" in f.filename and "bench" not in f.filename]
        sites[" <- ".join(f"{f.filename.split('torchcal/')[-1]}:{f.lineno}" for f in frames[-2:][::-1]) or "?"] += 1

    warnings.showwarning = hook
    warnings.simplefilter("always")
    torch.cuda.set_sync_debug_mode("warn")
    fit_fleet(make, units, noise)
    torch.cuda.set_sync_debug_mode("default")
    print(f"host syncs in one fleet solve of {len(units)} units: {sum(sites.values())}")
    for k, v in sites.most_common(30):
        print(f"{v:6d}  {k}")


if __name__ == "__main__":
    main()
