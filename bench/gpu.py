"""Bench: the hot paths on the CPU and on a CUDA GPU, side by side in one process (needs a GPU; prints why not).

Cases (FANUC LR Mate 200i of Paper II, simulated; order 6 + backlash; float64 unless said):
- compensation of 10^6 poses on the GPU (float64 and float32) against 10^5 on the CPU: poses per second
  (target on the GPU: >= 5e6 poses/s);
- prediction (model.points) of 10^6 rows;
- one fit (250 poses x 3 tools);
- a fleet of 100 units (250 x 3 each, every unit its own truth, one batched solve): GPU against the CPU
  with 2 threads (the 2-core machine the issue means; target: the GPU >= 10x faster).

    python bench/gpu.py [--units 100] [--cpu-threads 2] [--skip-cpu-fleet] [--only fleet] [--repeats 2]

Every timing is the best of ``--repeats`` after a warm-up call (CUDA context and handles, numba's compiled
kernels on the CPU side): one-time costs are not counted on either side.
"""

from __future__ import annotations

import torchcal  # noqa: F401  first: OMP_WAIT_POLICY=PASSIVE before torch loads

import argparse
import sys
import time

import torch

import torchcal.sim
from torchcal.core import units as U
from torchcal.compensate import compensate
from torchcal.identify import fit
from torchcal.identify.fleet import fit_fleet
from torchcal.sim.fleet import fleet_truths
from torchcal.core.threads import set_threads

TOOLS = U.mm_to_m(torch.tensor([[33.06, 57.73, 161.22], [57.26, -33.86, 161.22], [-33.96, -57.23, 161.22]],
                               dtype=torch.float64))


def timed(fn, device, repeats: int = 1):
    fn()  # warm-up (kernels, allocator)
    best = float("inf")
    for _ in range(repeats):
        if device.type == "cuda":
            torch.cuda.synchronize()
        t = time.perf_counter()
        out = fn()
        if device.type == "cuda":
            torch.cuda.synchronize()
        best = min(best, time.perf_counter() - t)
    return best, out


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--units", type=int, default=100)
    ap.add_argument("--cpu-threads", type=int, default=2)
    ap.add_argument("--skip-cpu-fleet", action="store_true")
    ap.add_argument("--only", default="", help="comma list of: fit, prediction, compensation, fleet (default: all)")
    ap.add_argument("--dry-run", action="store_true", help=argparse.SUPPRESS)
    ap.add_argument("--repeats", type=int, default=2, help="fleet timings: the best of this many after a warm-up")
    ap.add_argument("--accelerate", choices=("default", "on", "off", "both"), default="both",
                    help="the GPU fleet's geodesic acceleration (fit_fleet(accelerate=)): default (off on a GPU until "
                         "measured), on, off, or both timed side by side (a row each)")
    args = ap.parse_args(argv)
    if args.dry_run:  # the script's own check, without a GPU: the CPU stands in, small sizes
        gpu, cpu = torch.device("cpu"), torch.device("cpu")
        torch.cuda.synchronize = lambda *a: None
        torch.cuda.get_device_name = lambda *a: "none (dry run)"
    elif not torch.cuda.is_available():
        print("no CUDA device here: the GPU figures stay unmeasured (run this where a GPU is)")
        return 0
    else:
        gpu, cpu = torch.device("cuda"), torch.device("cpu")
    print(f"GPU: {torch.cuda.get_device_name(0)}; CPU side: {args.cpu_threads} threads of "
          f"{torch.get_num_threads()} available; torch {torch.__version__}")
    set_threads(args.cpu_threads)
    robot = torchcal.load_robot("fanuc_lrmate200i")
    noise = torchcal.NoiseModel.from_robot(robot)
    lim = robot.joint_map.limits
    truth = torchcal.TruthRobot.fanuc_paper2(robot, TOOLS, 0)
    q = torchcal.sim.quasi_random_commands(lim, 250, 0)
    data = torchcal.simulate(truth, q, [0, 1, 2], noise, 0)

    def make(dev):
        return torchcal.RobotModel(robot, TOOLS, orders=6, backlash=True).to(dev)

    only = {x.strip() for x in args.only.split(",") if x.strip()} or {"fit", "prediction", "compensation", "fleet"}
    fused = "unavailable"
    try:
        import numba
        fused = f"numba {numba.__version__}"
    except ImportError as e:  # the CPU side then runs the torch ops: say so, it changes the CPU figures
        fused = f"numba not importable ({e}): CPU side on torch ops"
    print(f"CPU compiled kernels: {fused}")
    rows = []

    def add(row):  # printed as it comes: a run stopped at its time limit keeps what it measured
        rows.append(row)
        print("  ".join(row), flush=True)

    model = make(cpu)
    fit(model, data, noise)
    mg = make(gpu)
    mg.load_state_dict(model.state_dict())
    if "fit" in only:
        t_c, rc = timed(lambda: fit(make(cpu), data, noise), cpu)
        dg = data.to(gpu)
        t_g, rg = timed(lambda: fit(make(gpu), dg, noise), gpu)
        add(("one fit, 250 x 3", f"{t_c:.2f} s", f"{t_g:.2f} s", f"{t_c / t_g:.1f}x",
                     f"cost {rc.fun:.1f} / {rg.fun:.1f}"))
    N = 10 ** 4 if args.dry_run else 10 ** 6
    NC = N // 10  # the CPU side's batch
    qp = torchcal.sim.quasi_random_commands(lim, N, 3)
    tool = torch.randint(0, 3, (N,), generator=torch.Generator().manual_seed(0))
    s = torch.ones_like(qp)
    qpg, toolg, sg = qp.to(gpu), tool.to(gpu), s.to(gpu)
    if "prediction" in only:
        with torch.no_grad():
            t_c, pc = timed(lambda: model.points(qp[:NC], tool[:NC], s[:NC]), cpu)
            t_g, pg = timed(lambda: mg.points(qpg, toolg, sg), gpu, 3)
        err = float((pg[:NC].cpu() - pc).norm(dim=1).max())
        add(("prediction (rows/s)", f"{NC / t_c:.3g}", f"{N / t_g:.3g}", f"{(N / t_g) / (NC / t_c):.0f}x",
                     f"max |GPU - CPU| {err:.1e} m"))
    if "compensation" in only:
        t_c, cc = timed(lambda: compensate(model, qp[:NC], s[:NC]), cpu)
        t_g, cg = timed(lambda: compensate(mg, qpg, sg), gpu, 3)
        ok = cc.converged & cg.converged[:NC].cpu()
        dqr = (cg.q[:NC].cpu()[ok] - cc.q[ok]).abs().max(1).values
        # near a singularity two exact solutions a few tenths of a degree apart can both lie within the bound:
        # count the rows where the two devices chose differently rather than quote one max
        dq, differ = float(dqr.median()), int((dqr > 1e-8).sum())
        add(("compensation float64 (poses/s)", f"{NC / t_c:.3g}", f"{N / t_g:.3g}",
                     f"{(N / t_g) / (NC / t_c):.0f}x", f"target >= 5e6 on the GPU: {'PASS' if N / t_g >= 5e6 else 'MISS'}; "
                                                          f"median |dq| {dq:.1e} rad, {differ} of {int(ok.sum())} rows > 1e-8 rad apart; converged {float(cg.converged.float().mean()):.4f}"))
        m32 = make(gpu)
        m32.load_state_dict(model.state_dict())
        m32 = m32.to(torch.float32)
        q32, s32 = qpg.float(), sg.float()
        t_g, c32 = timed(lambda: compensate(m32, q32, s32), gpu, 3)
        # the float32 answers judged in float64: the modeled flange position they reach against the nominal target
        ok32 = c32.converged.cpu()
        with torch.no_grad():
            q64 = c32.q.double()
            reach = (mg.flange(q64, sg, base=False)[:, :3, 3] - mg.nominal_flange(qpg)[:, :3, 3]).norm(dim=1).cpu()
        add(("compensation float32 (poses/s)", "", f"{N / t_g:.3g}", "",
                     f"converged {float(ok32.float().mean()):.4f}; position of the converged float32 commands, judged in "
                     f"float64: max {float(reach[ok32].max()) * 1e6:.2f} µm off the target"))
        # a larger batch: the GPU is bound by kernel launches, which do not grow with the batch
        q4 = torchcal.sim.quasi_random_commands(lim, 4 * N, 11).to(gpu)
        s4 = torch.ones_like(q4)
        t_g, c4 = timed(lambda: compensate(mg, q4, s4), gpu, 2)
        add((f"compensation float64, {4 * N:.0e} poses (poses/s)", "", f"{4 * N / t_g:.3g}", "",
                     f"target >= 5e6: {'PASS' if 4 * N / t_g >= 5e6 else 'MISS'}; converged {float(c4.converged.float().mean()):.4f}"))
        q4f, s4f = q4.float(), s4.float()
        t_g, c4f = timed(lambda: compensate(m32, q4f, s4f), gpu, 2)
        add((f"compensation float32, {4 * N:.0e} poses (poses/s)", "", f"{4 * N / t_g:.3g}", "",
                     f"converged {float(c4f.converged.float().mean()):.4f}"))
        q4 = s4 = c4 = q4f = s4f = c4f = None  # free the GPU memory before the fleet
    if "fleet" in only:
        fleet = fleet_truths(robot, TOOLS, args.units, 0, [u for u in (7, 23, 42, 61, 88) if u < args.units])
        g = torch.Generator().manual_seed(0)
        dirs = torch.where(torch.rand(q.shape, generator=g, dtype=torch.float64) > 0.5, 1.0, -1.0)
        units = [torchcal.simulate(t, q, [0, 1, 2], noise, k, directions=dirs) for k, t in enumerate(fleet.truths)]
        ug = [u.to(gpu) for u in units]

        def fleet_time(dev, us, accelerate=None):
            fit_fleet(lambda: make(dev), us[:3], noise, accelerate=accelerate)  # warm-up: CUDA handles, numba's kernels
            best, out = float("inf"), None
            for _ in range(max(1, args.repeats)):
                if dev.type == "cuda":
                    torch.cuda.synchronize()
                t = time.perf_counter()
                out = fit_fleet(lambda: make(dev), us, noise, accelerate=accelerate)
                if dev.type == "cuda":
                    torch.cuda.synchronize()
                best = min(best, time.perf_counter() - t)
            return best, out

        modes = {"default": [None], "on": [True], "off": [False], "both": [False, True]}[args.accelerate]
        gpu_runs = [(acc, *fleet_time(gpu, ug, acc)) for acc in modes]  # (accelerate, time, FleetFit)
        _, t_g, fg = gpu_runs[0]
        if args.skip_cpu_fleet:
            t_c, note = float("nan"), "CPU side skipped"
        else:
            t_c, fc = fleet_time(cpu, units)
            d = max(abs(a.fun / b.fun - 1) for a, b in zip(fg.results, fc.results))
            note = f"largest relative cost difference GPU / CPU {d:.1e}"
        for acc, t_g, fg in gpu_runs:
            how = "" if acc is None else f", GPU acceleration {'on' if acc else 'off'}"
            its = sum(r.nit for r in fg.results)
            add((f"fleet of {args.units} (one batched solve{how})", f"{t_c:.2f} s", f"{t_g:.2f} s",
                 f"{t_c / t_g:.1f}x", f"target GPU >= 10x the {args.cpu_threads}-thread CPU: "
                                      f"{'PASS' if t_c / t_g >= 10 else 'MISS'}; GPU unit iterations {its}; {note}"))
    w = max(len(r[0]) for r in rows)
    print(f"{'case':<{w}}  {'CPU':>10}  {'GPU':>10}  {'GPU/CPU':>8}  note")
    for r in rows:
        print(f"{r[0]:<{w}}  {r[1]:>10}  {r[2]:>10}  {r[3]:>8}  {r[4]}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
