"""Bench: cost against the number of poses, 10^3 .. 10^6, for a fit and for compensation; the exponent.

- fit: a simulated FANUC (Paper II's truth, seed 0, quasi-random commands, one tool, Table 5
  noise) identified with an order-1 model without backlash, LM to convergence; the number of
  iterations is printed beside the time, since it may change with N. Memory: the LM linearizes
  all rows at once (~12 kB per row for this model, peak RSS 1.2 GB at 10^5 rows), so 10^6 rows
  would need ~12 GB: the fit stops at 10^5 unless BENCH_FIT_MAX_POSES=1000000 is set;
- compensation: the order-6 + backlash model of bench/compensation.py, uniform commands, random
  approach directions.
Each size is timed quiet and loaded (once); the exponent is the least-squares slope of log(time)
against log(N) over all sizes (1 = linear), the note adds the slope over the largest decade alone
(fixed per-call costs weigh least there). --quick stops at 10^5.

    python bench/scaling.py [--quick]
"""

from __future__ import annotations

import torchcal  # noqa: F401  first: OMP_WAIT_POLICY=PASSIVE before torch loads

import gc
import os
import resource
import sys

import numpy as np

from harness import Context, Row, guarded, main

NAME = "scaling"


def slope(ns, ts) -> float:
    return float(np.polyfit(np.log(np.asarray(ns, float)), np.log(np.asarray(ts, float)), 1)[0])


def top_decade(Ns, times) -> str:
    """The exponent over the largest decade alone (fixed costs weigh least there)."""
    if len(Ns) < 2:
        return ""
    return (f"exponent over the largest decade {slope(Ns[-2:], times['q'][-2:]):.2f} / "
            f"{slope(Ns[-2:], times['l'][-2:]):.2f}")


def sizes(ctx: Context) -> list[int]:
    return [1_000, 10_000, 100_000] if ctx.quick else [1_000, 10_000, 100_000, 1_000_000]


FIT_MAX_POSES = int(float(os.environ.get("BENCH_FIT_MAX_POSES", "1e5")))


def fit_case(ctx: Context) -> Row:
    import torch

    from torchcal.identify import NoiseModel, fit
    from torchcal.kinematics import load_robot
    from torchcal.models.robot import RobotModel
    from torchcal.sim import TruthRobot, quasi_random_commands, simulate

    robot = load_robot("fanuc_lrmate200i")
    tools = torch.tensor([[0.03306, 0.05773, 0.16122]], dtype=torch.float64)
    truth = TruthRobot.fanuc_paper2(robot, tools, 0)
    noise = NoiseModel.paper2()
    times = {"q": [], "l": []}
    its, others = [], ([], [])
    Ns = [N for N in sizes(ctx) if N <= FIT_MAX_POSES]
    for N in Ns:
        q = quasi_random_commands(robot.joint_map.limits, N, 0)
        data = simulate(truth, q, [0], noise, seed=0)
        if N == Ns[0]:
            fit(RobotModel(robot, tools, orders=1, backlash=None), data, noise)  # warm-up
        p = ctx.pair(lambda: fit(RobotModel(robot, tools, orders=1, backlash=None), data, noise), repeats=1,
                     label=f"fit N={N}")
        times["q"].append(p.q)
        times["l"].append(p.l)
        its.append(f"{p.out_quiet[0].nit}/{p.out_loaded[0].nit}")
        others[0].append(p.other[0])
        others[1].append(p.other[1])
        del data, p
        gc.collect()
    rss = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024 ** 2
    note = "; ".join(f"N={N:.0e}: {tq:.2f} / {tl:.2f} s ({it} it)" for N, tq, tl, it in
                     zip(Ns, times["q"], times["l"], its)) + f"; {top_decade(Ns, times)}; peak RSS {rss:.1f} GB"
    return Row(NAME, f"fit cost exponent, FANUC order 1, 1 tool, {Ns[0]:.0e}..{Ns[-1]:.0e} poses",
               slope(Ns, times["q"]), slope(Ns, times["l"]), unit="", note=note,
               other_cpu=(float(np.mean(others[0])), float(np.mean(others[1]))))


def compensation_case(ctx: Context) -> Row:
    import torch

    from compensation import realistic_model, uniform_commands
    from torchcal.compensate import compensate
    from torchcal.core.units import deg_to_rad

    model = realistic_model(0)
    bound = deg_to_rad(5.0)
    Ns = sizes(ctx)
    times = {"q": [], "l": []}
    others = ([], [])
    compensate(model, uniform_commands(model, 256, 1), None, max_step=bound, max_correction=bound)  # warm-up
    for N in Ns:
        q = uniform_commands(model, N, 1)
        g = torch.Generator().manual_seed(2)
        s = torch.where(torch.rand(q.shape, generator=g) < 0.5, -1.0, 1.0).to(torch.float64)
        p = ctx.pair(lambda: compensate(model, q, s, max_step=bound, max_correction=bound), repeats=1,
                     label=f"compensate N={N}")
        times["q"].append(p.q)
        times["l"].append(p.l)
        others[0].append(p.other[0])
        others[1].append(p.other[1])
        del q, s, p
        gc.collect()
    note = "; ".join(f"N={N:.0e}: {tq:.3g} / {tl:.3g} s" for N, tq, tl in zip(Ns, times["q"], times["l"])) + \
        f"; {top_decade(Ns, times)}"
    return Row(NAME, f"compensation cost exponent, order 6 + backlash, {Ns[0]:.0e}..{Ns[-1]:.0e} poses",
               slope(Ns, times["q"]), slope(Ns, times["l"]), unit="", note=note,
               other_cpu=(float(np.mean(others[0])), float(np.mean(others[1]))))


def run(ctx: Context) -> list[Row]:
    return (guarded(NAME, "fit cost exponent", lambda: fit_case(ctx), ctx)
            + guarded(NAME, "compensation cost exponent", lambda: compensation_case(ctx), ctx))


if __name__ == "__main__":
    sys.exit(main([sys.modules[__name__]], description=__doc__.split("\n")[0]))
