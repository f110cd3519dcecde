"""Probe (device): GPU compensation with the damped path's CUDA graphs on and off, side by side in one process.

float64 and float32, 4·10^6 poses (the bench's largest batch), alternated after a warm-up; the damped least
squares' own time and row count per call (a synchronizing wrapper), and the rows' verdicts compared.
`python bench/gpu_compensation_probe.py [--poses N] [--rounds R]`.
"""
import argparse
import os
import time

import torchcal  # noqa: F401  before torch: its OpenMP threads then sleep while waiting (torchcal.core.threads)
import torch

import torchcal
import torchcal.sim
from torchcal.compensate import compensate, damped_graph, newton
from torchcal.core import units as U
from torchcal.identify import fit

ap = argparse.ArgumentParser()
ap.add_argument("--poses", type=int, default=4_000_000)
ap.add_argument("--rounds", type=int, default=3)
args = ap.parse_args()
TOOLS = U.mm_to_m(torch.tensor([[33.06, 57.73, 161.22], [57.26, -33.86, 161.22], [-33.96, -57.23, 161.22]],
                               dtype=torch.float64))
robot = torchcal.load_robot("fanuc_lrmate200i")
noise = torchcal.NoiseModel.from_robot(robot)
truth = torchcal.TruthRobot.fanuc_paper2(robot, TOOLS, 0)
q = torchcal.sim.quasi_random_commands(robot.joint_map.limits, 250, 0)
data = torchcal.simulate(truth, q, [0, 1, 2], noise, 0)
m = torchcal.RobotModel(robot, TOOLS, orders=6, backlash=True)
fit(m, data, noise)
g = torchcal.RobotModel(robot, TOOLS, orders=6, backlash=True).cuda()
g.load_state_dict(m.state_dict())
g32 = torchcal.RobotModel(robot, TOOLS, orders=6, backlash=True).cuda()
g32.load_state_dict(m.state_dict())
g32 = g32.float()
N = args.poses
qp = torchcal.sim.quasi_random_commands(robot.joint_map.limits, N, 11).cuda()
s = torch.ones_like(qp)
print(torch.cuda.get_device_name(), "torch", torch.__version__, "poses", N)

damped_log = []
inner = newton.damped_least_squares


def timed_damped(*a, **k):  # the damped path's own time (synchronized) and rows
    torch.cuda.synchronize()
    t = time.perf_counter()
    r = inner(*a, **k)
    torch.cuda.synchronize()
    damped_log.append((a[1].shape[0], time.perf_counter() - t, int(r.iterations.max()) if r.iterations.numel() else 0))
    return r


newton.damped_least_squares = timed_damped
graph_log = []
inner_graph = damped_graph.solve_fixed_shape


def logged_graph(*a, **k):  # the graphs' events: the eager first iteration, the capture, the replays
    o = inner_graph(*a, **k)
    graph_log.append(o.get("events"))
    return o


damped_graph.solve_fixed_shape = logged_graph


def graph_times():
    """-> 'first/capture/replays' in ms for each damped call of the last compensate (after its synchronize)."""
    out = []
    for ev in graph_log:
        if ev:
            out.append("/".join(f"{ev[i].elapsed_time(ev[i + 1]):.0f}" for i in range(3)))
    return ", ".join(out)


def one(model, qq, ss, graphs):
    os.environ["TORCHCAL_CUDA_GRAPHS"] = "1" if graphs else "0"
    damped_log.clear()
    graph_log.clear()
    torch.cuda.synchronize()
    t = time.perf_counter()
    r = compensate(model, qq, ss)
    torch.cuda.synchronize()
    return time.perf_counter() - t, r, list(damped_log)


for name, model, qq, ss in (("float64", g, qp, s), ("float32", g32, qp.float(), s.float())):
    res = {}
    for graphs in (True, False):  # warm-up of both
        one(model, qq, ss, graphs)
    times = {True: [], False: []}
    for _ in range(args.rounds):
        for graphs in (True, False):
            t, r, log = one(model, qq, ss, graphs)
            times[graphs].append(t)
            res[graphs] = r
            dl = "; ".join(f"{rows} rows {sec * 1e3:.0f} ms max it {it}" for rows, sec, it in log)
            gt = f"  graph ms first/capture/replays: {graph_times()}" if graphs else ""
            print(f"{name} graphs {'on ' if graphs else 'off'} {t:.3f} s  {N / t:.3g} poses/s  damped: {dl}{gt}",
                  flush=True)
    a, b = res[True], res[False]
    same = float((a.status == b.status).double().mean())
    ok = a.converged & b.converged
    dq = (a.q[ok] - b.q[ok]).abs().amax(-1)
    print(f"{name}: best on {N / min(times[True]):.3g}, off {N / min(times[False]):.3g} poses/s; "
          f"median on/off {sorted(times[True])[len(times[True]) // 2] / sorted(times[False])[len(times[False]) // 2]:.2f}; "
          f"status equal {same:.6f}; converged on {float(a.converged.double().mean()):.4f} "
          f"off {float(b.converged.double().mean()):.4f}; |dq| max {float(dq.max()):.1e}, "
          f"> 1e-8 rad: {int((dq > 1e-8).sum())} of {int(ok.sum())}", flush=True)
os.environ["TORCHCAL_CUDA_GRAPHS"] = "1"
import cProfile, pstats  # noqa: E401,E402
pr = cProfile.Profile()
pr.enable()
one(g, qp, s, True)
pr.disable()
pstats.Stats(pr).sort_stats("cumulative").print_stats(18)
