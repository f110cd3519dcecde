"""Issue #18's re-check: 100 simulated FANUCs measured twice, each unit compared with its earlier calibration.

The second campaign's truth is written from what happens to a fleet between two campaigns (not from the
model): every unit's links grow with the season (+15 K, steel) and the tracker is set up elsewhere (~0.05 deg,
~2 mm); some units crashed (a mastering moved on joint 2, 3, 4 or 5 by 0.01-0.05 deg; a link bent: its origin
tilted 0.02 deg), some had a gearbox swapped (new transmission-error phases and amplitudes on joint 1, 2, 3, 4
or 6), one gearbox wore (torchcal.sim.fleet.damage_gearbox on joint 3). The second campaign measures its own
250 commands with other approach directions, with new noise. Both campaigns are fitted as fleets (order 6 +
backlash, one batched solve each), and torchcal.identify.fleet_change compares each unit's two models, as
``torchcal fleet fleet.baseline=RUN`` does.

Printed: per event its change at the tool (the models' and the truth's own, rigidly aligned, mm RMS), whether
the unit was named changed and which joints; the healthy units named (false alarms); the season's median.

    python experiments/fleet/recheck.py [--units 100] [--seed 0] [--own-programs]
"""

from __future__ import annotations

import argparse
import copy
import math
import statistics
import sys
import time
from pathlib import Path

import torchcal  # noqa: F401  first: it sets OMP_WAIT_POLICY=PASSIVE
import numpy as np
import torch

import torchcal.sim
from torchcal.core import units as U
from torchcal.identify.alignment import kabsch
from torchcal.identify.fleet import fit_fleet
from torchcal.identify.fleet_change import changed_units, joint_changes, tool_change
from torchcal.sim.fleet import damage_gearbox, fleet_truths

sys.path.insert(0, str(Path(__file__).resolve().parent))
from ratio import TOOLS_MM, program  # noqa: E402  the fleet's program, as run.py and ratio.py

# unit -> (what happened, how to do it to a truth); joints 0-based
EVENTS = {
    10: ("crash: J2 mastering +0.01 deg", lambda t, g: t.mastering.__setitem__(1, t.mastering[1] + 0.01 * U.DEG)),
    11: ("crash: J2 mastering +0.02 deg", lambda t, g: t.mastering.__setitem__(1, t.mastering[1] + 0.02 * U.DEG)),
    12: ("crash: J2 mastering +0.05 deg", lambda t, g: t.mastering.__setitem__(1, t.mastering[1] + 0.05 * U.DEG)),
    13: ("crash: J3 mastering -0.02 deg", lambda t, g: t.mastering.__setitem__(2, t.mastering[2] - 0.02 * U.DEG)),
    14: ("crash: J4 mastering +0.05 deg", lambda t, g: t.mastering.__setitem__(3, t.mastering[3] + 0.05 * U.DEG)),
    15: ("crash: J5 mastering +0.05 deg", lambda t, g: t.mastering.__setitem__(4, t.mastering[4] + 0.05 * U.DEG)),
    16: ("crash: link 3 bent 0.02 deg", lambda t, g: t.origin_tilt.__setitem__((2, 0), t.origin_tilt[2, 0] + 0.02 * U.DEG)),
    20: ("gearbox swap J1", None), 21: ("gearbox swap J2", None), 22: ("gearbox swap J3", None),
    23: ("gearbox swap J4", None), 24: ("gearbox swap J6", None),
    30: ("worn gearbox J3 (damage_gearbox)", lambda t, g: damage_gearbox(t, 2)),
}
SWAP_JOINT = {20: 0, 21: 1, 22: 2, 23: 3, 24: 5}


def second_campaign(truths, seed: int):
    g = np.random.default_rng([seed, 77])
    later = [copy.deepcopy(t) for t in truths]
    with torch.no_grad():
        for k, t in enumerate(later):
            t.origins[:, :3, 3] *= 1 + 15 * 1.2e-5  # the season: every link grows
            t.tip[:3, 3] *= 1 + 15 * 1.2e-5
            t.base_twist += torch.from_numpy(np.concatenate([g.normal(0, 0.05, 3) * U.DEG, g.normal(0, 2.0, 3) * U.MM]))
            if k in SWAP_JOINT:  # a new gearbox: its own phases and amplitudes
                j = SWAP_JOINT[k]
                t.wave_phase[j] = torch.from_numpy(g.uniform(0, 2 * math.pi, t.wave_phase.shape[1]))
                t.wave_amp[j] *= torch.from_numpy(g.uniform(0.8, 1.2, t.wave_amp.shape[1]))
            elif k in EVENTS:
                EVENTS[k][1](t, g)
    return later


def truth_change_mm(a, b, d) -> float:
    with torch.no_grad():
        pa, pb = a.points(d.q, d.tool, d.direction), b.points(d.q, d.tool, d.direction)
        R, t = kabsch(pa, pb)
        return U.m_to_mm(float(((pa @ R.T + t) - pb).norm(dim=-1).pow(2).mean().sqrt()))


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--units", type=int, default=100)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--threshold", type=float, default=5.0)
    ap.add_argument("--own-programs", action="store_true",
                    help="each unit measured with its own program (commands, directions) in each campaign")
    a = ap.parse_args(argv)
    t0 = time.perf_counter()
    robot = torchcal.load_robot("fanuc_lrmate200i")
    tools = U.mm_to_m(torch.tensor(TOOLS_MM, dtype=torch.float64))
    noise = torchcal.NoiseModel.from_robot(robot)
    lim = robot.joint_map.limits
    first = fleet_truths(robot, tools, a.units, a.seed, []).truths
    later = second_campaign(first, a.seed)
    if a.own_programs:
        p1 = [program(lim, 10_000 * (a.seed + 1) + k) for k in range(a.units)]
        p2 = [program(lim, 10_000 * (a.seed + 1) + 5_000 + k) for k in range(a.units)]
    else:
        p1, p2 = [program(lim, a.seed)] * a.units, [program(lim, a.seed + 500)] * a.units
    c1 = [torchcal.simulate(t, q, [0, 1, 2], noise, 1000 * a.seed + k, directions=d)
          for k, (t, (q, d)) in enumerate(zip(first, p1))]
    c2 = [torchcal.simulate(t, q, [0, 1, 2], noise, 1000 * a.seed + 500 + k, directions=d)
          for k, (t, (q, d)) in enumerate(zip(later, p2))]

    def make():
        return torchcal.RobotModel(robot, tools, orders=6, backlash=True)

    f1, f2 = fit_fleet(make, c1, noise), fit_fleet(make, c2, noise)
    t_fit = time.perf_counter() - t0
    tc = time.perf_counter()
    dist = [tool_change(o, n, d.q, d.tool, d.direction) for o, n, d in zip(f1.models, f2.models, c2)]
    rms = torch.stack([x.pow(2).mean().sqrt() for x in dist])
    joints = joint_changes(f1.models, f2.models)
    names = list(f1.models[0].joint_errors.joint_names)
    _, _, found = changed_units(rms, joints, names, robot.joint_map.prismatic, a.threshold)
    t_cmp = time.perf_counter() - tc
    by_unit = {c.unit: c for c in found}
    truth = [truth_change_mm(x, y, d) for x, y, d in zip(first, later, c2)]
    healthy = [k for k in range(a.units) if k not in EVENTS]
    print(f"{a.units} FANUCs, two campaigns of 250 x 3 poses ({'each unit its own program' if a.own_programs else 'one program'}"
          f" a campaign), order 6 + backlash; fits {t_fit:.1f} s, the comparison {t_cmp:.2f} s")
    print(f"season (the {len(healthy)} healthy units): change at the tool median {statistics.median(U.m_to_mm(float(rms[k])) for k in healthy):.4f} mm "
          f"(truth {statistics.median(truth[k] for k in healthy):.4f}), range "
          f"{min(U.m_to_mm(float(rms[k])) for k in healthy):.4f}-{max(U.m_to_mm(float(rms[k])) for k in healthy):.4f} mm")
    print(f"{'unit':>4}  {'event':<34} {'model mm':>9} {'truth mm':>9}  named  joints")
    for k, (what, _) in EVENTS.items():
        if k >= a.units:
            continue
        c = by_unit.get(k)
        where = ", ".join(f"{j} {f.split(' change')[0]} {v:.3g} deg" for j, f, v, *_ in c.joints) if c else ""
        print(f"{k:>4}  {what:<34} {U.m_to_mm(float(rms[k])):9.4f} {truth[k]:9.4f}  {'yes' if c else 'no ':<5}  {where}")
    false = [k for k in healthy if k in by_unit]
    print(f"healthy units named changed: {false or 'none'} of {len(healthy)}")
    for k in false:
        print(f"  {by_unit[k]}")
    worst = max(abs(U.m_to_mm(float(rms[k])) - truth[k]) for k in range(a.units))
    print(f"every unit's change at the tool against the truth's: largest difference {worst:.4f} mm")
    return 0


if __name__ == "__main__":
    sys.exit(main())
