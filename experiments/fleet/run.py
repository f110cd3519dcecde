"""A fleet of simulated FANUC LR Mate 200i (Paper II), fitted in one batched solve.

Every unit has its own truth (torchcal.sim.fleet: Paper II's error sources,
its own joint-dependent draws, a unit-to-unit spread of the constants, the
unmodelled ripple and cross-coupling), a few units a damaged gearbox. All
units are measured with one program (the same 250 quasi-random commands and
approach directions, three reflectors, Paper II's noise), as a plant
measures every unit of a type; --own-programs gives each unit its own.

Printed: the batched fleet solve against ONE separate fit (time ratio), each
unit's validation residual against its separately fitted one, the flagged
units against the damaged ones, and the fleet prior for a unit measured
with 30 poses.

    python experiments/fleet/run.py [--units 100] [--damaged 7,23,42,61,88] [--seed 0] [--device cpu]
        [--threads N] [--reference K] [--own-programs]
"""

from __future__ import annotations

import argparse
import sys
import time

import torchcal  # noqa: F401  before torch: its OpenMP threads then sleep while waiting (torchcal.core.threads)
import torch

import torchcal
import torchcal.sim
from torchcal.core import units as U
from torchcal.identify import fit
from torchcal.identify.layout import ParameterLayout
from torchcal.identify.fleet import fit_fleet, fleet_prior, parameter_outliers
from torchcal.sim.fleet import fleet_truths

TOOLS_MM = [[33.06, 57.73, 161.22], [57.26, -33.86, 161.22], [-33.96, -57.23, 161.22]]  # Paper II Table 4


def model_error_mm(model, truth, q, tools) -> float:
    """Mean distance (mm) between the model's and the truth's noise-free tool points at commands q, every tool,
    approached from the + side."""
    T = len(tools)
    qq = q.repeat(T, 1)
    tool = torch.arange(T, device=q.device).repeat_interleave(q.shape[0])
    d = torch.ones_like(qq)
    with torch.no_grad():
        return float(U.m_to_mm((model.points(qq, tool, d) - truth.points(qq, tool, d)).norm(dim=1).mean()))


def residual_mm(model, data) -> float:
    with torch.no_grad():
        return float(U.m_to_mm((model.points(data.q, data.tool, data.direction) - data.xyz).norm(dim=1).mean()))


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--units", type=int, default=100)
    ap.add_argument("--damaged", default="7,23,42,61,88", help="units (0-based) with a damaged J3 gearbox")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--device", default="cpu")
    ap.add_argument("--threads", type=int, default=None)
    ap.add_argument("--own-programs", action="store_true", help="each unit measured with its own program (commands "
                                                                     "and approach directions)")
    ap.add_argument("--reference", type=int, default=None, help="units fitted separately for the 1 %% check "
                                                                   "(default: all)")
    args = ap.parse_args(argv)
    if args.threads:
        from torchcal.core.threads import set_threads

        set_threads(args.threads)
    dev = torch.device(args.device)
    robot = torchcal.load_robot("fanuc_lrmate200i")
    tools = U.mm_to_m(torch.tensor(TOOLS_MM, dtype=torch.float64))
    noise = torchcal.NoiseModel.from_robot(robot)
    damaged = [int(s) for s in args.damaged.split(",") if s.strip() and int(s) < args.units]
    fleet = fleet_truths(robot, tools, args.units, args.seed, damaged)
    lim = robot.joint_map.limits
    q = torchcal.sim.quasi_random_commands(lim, 250, args.seed)
    g = torch.Generator().manual_seed(args.seed)
    dirs = torch.where(torch.rand(q.shape, generator=g, dtype=torch.float64) > 0.5, 1.0, -1.0)  # one program
    qv = torchcal.sim.quasi_random_commands(lim, 300, args.seed + 1)[100:]  # disjoint validation commands
    dv = torch.where(torch.rand(qv.shape, generator=g, dtype=torch.float64) > 0.5, 1.0, -1.0)
    t0 = time.perf_counter()
    programs = [(q, dirs)] * args.units
    if args.own_programs:  # each unit its own commands and approach directions (ratio.py's)
        from ratio import unit_program  # the same folder: run as a script

        programs = [unit_program(lim, args.seed, k) for k in range(args.units)]
    ident = [torchcal.simulate(t, qk, [0, 1, 2], noise, 1000 * args.seed + k, directions=dk)
             for k, (t, (qk, dk)) in enumerate(zip(fleet.truths, programs))]
    val = [torchcal.simulate(t, qv, [2], noise, 1000 * args.seed + 500 + k, directions=dv) for k, t in enumerate(fleet.truths)]
    if dev.type != "cpu":
        ident, val = [d.to(dev) for d in ident], [d.to(dev) for d in val]
    print(f"fleet: {args.units} simulated FANUC LR Mate 200i, 250 poses x 3 tools each "
          f"({'each unit its own program' if args.own_programs else 'one program'}), "
          f"damaged J3 gearbox on units {damaged}; simulated in {time.perf_counter() - t0:.1f} s; device {dev}, "
          f"{torch.get_num_threads()} threads")

    def make():
        return torchcal.RobotModel(robot, tools, orders=6, backlash=True).to(dev)

    # ONE fit, the way torchcal fit runs it (warm-up first: imports, allocator; for the fleet its compiled
    # kernels, loaded once per process). experiments/fleet/ratio.py times the two interleaved, several times.
    fit(make(), ident[0], noise)
    fit_fleet(make, ident[:2], noise)
    t = time.perf_counter()
    single = make()
    r0 = fit(single, ident[0], noise)
    t_one = time.perf_counter() - t
    t = time.perf_counter()
    out = fit_fleet(make, ident, noise)
    if dev.type == "cuda":
        torch.cuda.synchronize()
    t_fleet = time.perf_counter() - t
    conv = sum(r.success for r in out.results)
    print(f"ONE fit: {t_one:.2f} s ({r0.nit} iterations); the fleet in one batched solve: {t_fleet:.2f} s = {t_fleet / t_one:.1f} x one fit "
          f"(target <= 10 x); {conv}/{args.units} converged")

    # every unit against its separately fitted validation residual
    K = args.units if args.reference is None else min(args.reference, args.units)
    t = time.perf_counter()
    worst, rows = 0.0, []
    for k in range(K):
        alone = make()
        fit(alone, ident[k], noise)
        a, b = residual_mm(out.models[k], val[k]), residual_mm(alone, val[k])
        rows.append((k, a, b))
        worst = max(worst, abs(a / b - 1.0))
    print(f"validation residual, fleet vs each unit fitted alone ({K} units, {time.perf_counter() - t:.1f} s): "
          f"largest relative difference {100 * worst:.3f} % (target <= 1 %): {'PASS' if worst <= 0.01 else 'FAIL'}")
    for k, a, b in rows[:5]:
        print(f"  unit {k:3d}: fleet {a:.4f} mm, alone {b:.4f} mm")

    score, findings = parameter_outliers(out)
    found = sorted({o.unit for o in findings})
    print(f"outliers (a joint's transmission error or backlash with robust z > 5 and 3x the fleet median): {found}; damaged {damaged}: "
          f"{'PASS' if found == sorted(damaged) else 'FAIL'}")
    for o in findings[:8]:
        print(f"  {o}")

    # fleet prior: a unit measured with 30 poses, the prior from the other units (the flagged ones left out)
    k = next(i for i in range(args.units) if i not in damaged)
    block, mean = fleet_prior(out, exclude=[k] + found)
    few = ident[k].subset(torch.isin(ident[k].pose, torch.arange(30, device=ident[k].pose.device)))
    m30a, m30p, m250 = make(), make(), make()
    fit(m30a, few, noise)
    ParameterLayout(m30p).set(mean.to(dev))  # start at the fleet's mean
    # no gauge pins: the prior determines what 30 poses cannot (pinning would hold those at the start instead)
    fit(m30p, few, noise, blocks=[block], gauge=False)
    fit(m250, ident[k], noise)
    truth = fleet.truths[k]
    e30a, e30p, e250 = (model_error_mm(m, truth, qv, tools) for m in (m30a, m30p, m250))
    print(f"fleet prior, unit {k} (model error against its truth at 200 validation commands, 3 tools): "
          f"30 poses alone {e30a:.4f} mm; 30 poses + fleet prior {e30p:.4f} mm; 250 poses alone {e250:.4f} mm; "
          f"ratio {e30p / e250:.2f} (target <= 1.5): {'PASS' if e30p <= 1.5 * e250 else 'FAIL'}")
    # the same unit measured on 30 poses designed for the prior (what `torchcal plan-poses --fleet` picks; the
    # candidates' approach directions drawn at random, as there); experiments/fleet/prior.py: more units, the
    # oracle bound
    from torchcal.analysis.fleet_design import design_poses

    free = torch.zeros(mean.shape[0], dtype=torch.bool, device=mean.device)
    free[[ParameterLayout(make()).names().index(nm) for nm in block.names]] = True
    qc = torchcal.sim.quasi_random_commands(lim, 2000, args.seed + 7).to(dev)
    pick, pred = design_poses(make(), mean, block.cov.to(mean), free, qc, 30, noise, qv.to(dev), args.seed + 7)
    gd = torch.Generator().manual_seed(args.seed + 7)
    dc = torch.where(torch.rand(qc.shape, generator=gd, dtype=torch.float64) > 0.5, 1.0, -1.0).to(dev)
    designed = torchcal.simulate(truth, qc[pick], [0, 1, 2], noise, 1000 * args.seed + 900 + k, directions=dc[pick])
    m30d = make()
    ParameterLayout(m30d).set(mean.to(dev))
    fit(m30d, designed.to(dev), noise, blocks=[block], gauge=False)
    e30d = model_error_mm(m30d, truth, qv, tools)
    print(f"  on 30 poses designed for the prior: {e30d:.4f} mm (predicted {U.m_to_mm(float(pred[-1])):.4f} mm RMS), "
          f"ratio {e30d / e250:.2f} (target <= 1.5): {'PASS' if e30d <= 1.5 * e250 else 'FAIL'}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
