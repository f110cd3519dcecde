"""Issue #18: a fleet prior for a unit measured with 30 poses, against the same unit fitted alone with 250.

The fleet (torchcal.sim.fleet, Paper II's FANUC truth with a unit-to-unit
spread, a few damaged gearboxes) is measured with one program (250
quasi-random commands, three tools) and fitted in one batched solve, as in
experiments/fleet/run.py. For each of several healthy test units the prior
is the other units' mean and covariance (the flagged outliers left out); the
unit is then fitted with 30 poses:

- alone (no prior beyond the default weak one);
- with the fleet prior, on the program's first 30 poses;
- with the fleet prior, on 30 poses designed for that prior
  (torchcal.analysis.fleet_design.greedy_design: Bayesian I-optimal, i.e. the
  predicted model error at the validation commands, greedily from a
  candidate set of quasi-random commands, linearized at the fleet mean);
- the same two with an ORACLE prior: the mean and sample covariance of a
  separate, larger fleet (other seeds, no damage) fitted with 250 poses;

and reported against the unit fitted alone with all 250 poses. The model
error is the mean distance between the fitted model's and the truth's
noise-free tool points at 200 validation commands, every tool. "pred" is the
linearized posterior's predicted RMS model error (parameter part only, no
unmodelled error). The error of each 30-pose fit with a prior is also split
by joint (its parameter difference to the 250-pose fit, mapped to the
validation points one group of entries at a time).

    python experiments/fleet/prior.py [--units 100] [--test 5] [--oracle 1500] [--candidates 2000] [--poses 30]
        [--seed 0] [--threads N] [--methods shrunk,ledoit-wolf,factor,block] [--oracle-methods sample,block]
        [--curve 45,60,90]

--units is the size of the fleet the prior comes from (as in run.py); --test the number of healthy units
fitted with few poses. Defaults: about 8 min on one thread (the 1500-unit oracle fleet: 4 min).
"""

from __future__ import annotations

import argparse
import statistics
import sys
import time
from pathlib import Path

import torchcal  # noqa: F401  first: it sets OMP_WAIT_POLICY=PASSIVE
import torch

import torchcal.sim
from torchcal.analysis.fleet_design import (error_weight, greedy_design, known_group_gain, pose_jacobians,
                                            posterior_covariance, predicted_mse)
from torchcal.core import units as U
from torchcal.core.measurements import Measurements
from torchcal.identify import fit
from torchcal.identify.blocks import GaussianPrior
from torchcal.identify.fleet import fit_fleet, parameter_outliers
from torchcal.identify.fleet_prior import prior_from_parameters
from torchcal.identify.layout import ParameterLayout
from torchcal.identify.problem import CalibrationProblem, Prior
from torchcal.sim.fleet import fleet_truths

sys.path.insert(0, str(Path(__file__).resolve().parent))
from run import model_error_mm  # noqa: E402  the same error measure as experiments/fleet/run.py

TOOLS_MM = [[33.06, 57.73, 161.22], [57.26, -33.86, 161.22], [-33.96, -57.23, 161.22]]  # Paper II Table 4
TARGET = 1.5


def jacobian_at(make, x, data, noise):
    """Whitened A (R, 3, P), C (R, 3, n), w_v (R, n) of the model with full-layout values x (P,) on data's rows."""
    model = make()
    prob = CalibrationProblem(model, data, noise, Prior())
    _, A, C = prob.linearize(x.to(prob.layout.get()), prob.v_zero())
    return A, C, prob.w_v


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--units", type=int, default=100, help="units in the fleet the prior comes from")
    ap.add_argument("--damaged", default="7,23,42,61,88", help="units (0-based) with a damaged J3 gearbox")
    ap.add_argument("--test", type=int, default=5, help="healthy units fitted with few poses (the first ones)")
    ap.add_argument("--oracle", type=int, default=1500, help="units of the separate oracle fleet (0: none; 300 units "
                                                             "give an over-confident sample covariance in 267 entries)")
    ap.add_argument("--candidates", type=int, default=2000, help="candidate commands for the designed poses")
    ap.add_argument("--poses", type=int, default=30)
    ap.add_argument("--methods", default="shrunk", help="fleet covariance estimators (fleet_prior's method), "
                                                        "comma-separated: shrunk, ledoit-wolf, factor, block")
    ap.add_argument("--oracle-methods", default="sample", help="covariance estimators of the oracle prior")
    ap.add_argument("--curve", default="", help="more designed pose counts to fit with the first --methods prior "
                                                 "(and the oracle's), e.g. 45,60,90: how many poses reach the target")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--threads", type=int, default=None)
    args = ap.parse_args(argv)
    if args.threads:
        from torchcal.core.threads import set_threads

        set_threads(args.threads)
    t_start = time.perf_counter()
    robot = torchcal.load_robot("fanuc_lrmate200i")
    tools = U.mm_to_m(torch.tensor(TOOLS_MM, dtype=torch.float64))
    noise = torchcal.NoiseModel.from_robot(robot)
    damaged = [int(s) for s in args.damaged.split(",") if s.strip() and int(s) < args.units]
    lim = robot.joint_map.limits
    T = tools.shape[0]

    def make():
        return torchcal.RobotModel(robot, tools, orders=6, backlash=True)

    # ---- the fleet and its program (as experiments/fleet/run.py)
    fleet = fleet_truths(robot, tools, args.units, args.seed, damaged)
    q = torchcal.sim.quasi_random_commands(lim, 250, args.seed)
    g = torch.Generator().manual_seed(args.seed)
    dirs = torch.where(torch.rand(q.shape, generator=g, dtype=torch.float64) > 0.5, 1.0, -1.0)
    qv = torchcal.sim.quasi_random_commands(lim, 300, args.seed + 1)[100:]  # validation commands
    ident = [torchcal.simulate(t, q, [0, 1, 2], noise, 1000 * args.seed + k, directions=dirs)
             for k, t in enumerate(fleet.truths)]
    out = fit_fleet(make, ident, noise)
    _, findings = parameter_outliers(out)
    found = sorted({o.unit for o in findings})
    X, keep, names = out.batch.x, out.batch.keep, out.batch.names
    free = keep.all(0)
    base_sigma = Prior().sigma(out.layout).to(X)
    print(f"fleet: {args.units} units, 250 poses x {T} tools, damaged {damaged}, flagged {found}; "
          f"{int(free.sum())} of {X.shape[1]} entries free; {time.perf_counter() - t_start:.0f} s")

    # ---- the oracle: a separate, healthy fleet (seed + 1: units seed' * 100003 + k, disjoint), same program
    Xo = None
    if args.oracle > 0:
        t = time.perf_counter()
        ofleet = fleet_truths(robot, tools, args.oracle, args.seed + 1)
        odata = [torchcal.simulate(tr, q, [0, 1, 2], noise, 1000 * (args.seed + 1) + k, directions=dirs)
                 for k, tr in enumerate(ofleet.truths)]
        oout = fit_fleet(make, odata, noise)
        if not bool((oout.batch.keep.all(0) == free).all()):
            raise RuntimeError("the oracle fleet's gauge differs from the fleet's")
        Xo = oout.batch.x
        del odata
        print(f"oracle fleet: {args.oracle} healthy units (seed {args.seed + 1}), fitted with 250 poses: "
              f"{time.perf_counter() - t:.0f} s")

    # ---- candidates and the linearization at the fleet mean
    healthy = [m for m in range(args.units) if m not in damaged and m not in found]
    xbar = X[healthy].mean(0)
    Nc = args.candidates
    qc = torchcal.sim.quasi_random_commands(lim, Nc, args.seed + 7)
    gc = torch.Generator().manual_seed(args.seed + 7)
    dc = torch.where(torch.rand(qc.shape, generator=gc, dtype=torch.float64) > 0.5, 1.0, -1.0)
    cand = torchcal.simulate(fleet.truths[0], qc, [0, 1, 2], None, 0, directions=dc)  # rows: tool-major
    rows_c = torch.arange(T * Nc).reshape(T, Nc).T  # (Nc, T)
    A, C, w_v = jacobian_at(make, xbar, cand, noise)
    Bc = pose_jacobians(A[..., free], C, w_v, rows_c)  # (Nc, 9, k)
    first = ident[0].subset(ident[0].pose < args.poses)
    A, C, w_v = jacobian_at(make, xbar, first, noise)
    B30 = pose_jacobians(A[..., free], C, w_v, torch.arange(T * args.poses).reshape(T, args.poses).T)
    val = Measurements.from_tensors(qv.repeat(T, 1), torch.arange(T).repeat_interleave(qv.shape[0]), torch.zeros(T * qv.shape[0], 3),
                                    direction=torch.ones(T * qv.shape[0], qv.shape[1]))
    A, _, _ = jacobian_at(make, xbar, val, noise)
    G = A[..., free].reshape(-1, int(free.sum())) * noise.sigma_m  # metres per unit parameter
    W = error_weight(G)
    del A, C

    # error groups: the entries of each joint (its error terms and backlash), the base, the tools
    fnames = [nm for nm, f in zip(names, free.tolist()) if f]
    jn = list(make().joint_errors.joint_names)
    groups = {f"J{i + 1}": [k for k, nm in enumerate(fnames) if nm.startswith(jn[i] + ".")] for i in range(len(jn))}
    groups["base"] = [k for k, nm in enumerate(fnames) if nm.startswith("base.")]
    groups["tools"] = [k for k, nm in enumerate(fnames) if nm.startswith("tool")]
    rest = sorted(set(range(len(fnames))) - {k for v in groups.values() for k in v})
    if rest:
        groups["other"] = rest

    def split(cov):
        """RMS model error (mm) each group carries in the posterior cov (k, k): sqrt of the predicted mean squared
        error's drop if the group were known (known_group_gain)."""
        return {a: float(U.m_to_mm(torch.tensor(b).clamp(min=0).sqrt())) for a, b in known_group_gain(cov, W, groups).items()}

    def fit_prior(parts, data):
        block = GaussianPrior(parts.names, parts.mean, parts.cov)
        model = make()
        mean = torch.zeros(X.shape[1], dtype=X.dtype)
        mean[parts.free] = parts.mean
        ParameterLayout(model).set(mean)
        fit(model, data, noise, blocks=[block], gauge=False)
        return model

    A, C, w_v = jacobian_at(make, xbar, ident[0], noise)
    B250 = pose_jacobians(A[..., free], C, w_v, torch.arange(T * 250).reshape(T, 250).T)
    cov0 = torch.diag(base_sigma[free].pow(2))
    post250 = posterior_covariance(cov0, B250)
    print(f"250 poses alone, predicted RMS model error (parameter part, default prior): "
          f"{float(U.m_to_mm(predicted_mse(post250, W).sqrt())):.4f} mm; by group if known: "
          + ", ".join(f"{a} {b:.4f}" for a, b in split(post250).items()))
    del A, C, B250

    methods = [s.strip() for s in args.methods.split(",") if s.strip()]
    omethods = [s.strip() for s in args.oracle_methods.split(",") if s.strip()]
    curve = [int(s) for s in args.curve.split(",") if s.strip()]
    test = [m for m in healthy][: args.test]
    print(f"test units {test}; candidates {Nc}; {args.poses} poses each; prior covariance: the other "
          f"{len(healthy) - 1} healthy units ({', '.join(methods)})" + (f", oracle: {args.oracle} units" if Xo is not None else ""))
    table = []
    for k in test:
        t = time.perf_counter()
        others = [m for m in healthy if m != k]
        priors = {m: prior_from_parameters(X[others], keep[others], names, base_sigma, method=m, pin_gauge=True)
                  for m in methods}
        if Xo is not None:
            for m in omethods:
                priors["oracle" if m == "sample" else f"oracle-{m}"] = prior_from_parameters(
                    Xo, oout.batch.keep, names, base_sigma, method=m, pin_gauge=True)
        # the unit's data: its program (first poses), and its truth measured at every candidate (designed subsets)
        few = ident[k].subset(ident[k].pose < args.poses)
        cdata = torchcal.simulate(fleet.truths[k], qc, [0, 1, 2], noise, 1000 * args.seed + 700 + k, directions=dc)
        truth = fleet.truths[k]
        m250, m30a = make(), make()
        fit(m250, ident[k], noise)
        fit(m30a, few, noise)
        e250, e30a = model_error_mm(m250, truth, qv, tools), model_error_mm(m30a, truth, qv, tools)
        row = {"unit": k, "250": e250, "30 alone": e30a}
        print(f"unit {k}: 250 poses alone {e250:.4f} mm; {args.poses} poses alone {e30a:.4f} mm "
              f"(x{e30a / e250:.1f})")
        for pname, parts in priors.items():
            cov = parts.cov[free][:, free]  # the prior on the free entries (the pins are not free)
            pick, obj = greedy_design(Bc, cov, args.poses, W, "A")
            designed = cdata.subset(torch.isin(cdata.pose, pick))
            for label, data, Bs in (("first", few, B30), ("designed", designed, Bc[pick])):
                model = fit_prior(parts, data)
                e = model_error_mm(model, truth, qv, tools)
                post = posterior_covariance(cov, Bs)
                pred = float(U.m_to_mm(predicted_mse(post, W).sqrt()))
                sp = split(post)
                row[f"{pname} {label}"] = e
                top = sorted(sp.items(), key=lambda kv: -kv[1])[:4]
                print(f"  + {pname:11s} prior, {label:8s} {args.poses}: {e:.4f} mm, ratio {e / e250:.2f} "
                      f"(pred RMS {pred:.4f} mm, of it by group if known: "
                      + ", ".join(f"{a} {b:.4f}" for a, b in top) + ")")
        for pname in [methods[0]] + [p_ for p_ in priors if p_.startswith("oracle")]:
            if not curve:
                break
            parts = priors[pname]
            cov = parts.cov[free][:, free]
            pick, obj = greedy_design(Bc, cov, max(curve), W, "A")
            line = []
            for n_ in curve:
                model = fit_prior(parts, cdata.subset(torch.isin(cdata.pose, pick[:n_])))
                e = model_error_mm(model, truth, qv, tools)
                row[f"{pname} designed {n_}"] = e
                line.append(f"{n_}: {e:.4f} mm x{e / e250:.2f} (pred {float(U.m_to_mm(obj[n_].sqrt())):.4f})")
            print(f"  + {pname} prior, designed: " + "; ".join(line))
        print(f"  ({time.perf_counter() - t:.0f} s)")
        table.append(row)

    # ---- summary
    keys = [c for c in table[0] if c not in ("unit", "250")]
    print(f"\nsummary over {len(table)} healthy units (model error, mm; ratio = / 250 poses alone):")
    print("  unit   250 alone  " + "  ".join(f"{c:>17s}" for c in keys))
    for r in table:
        print(f"  {r['unit']:4d}   {r['250']:.4f}     " + "  ".join(f"{r[c]:.4f} (x{r[c] / r['250']:5.2f})" for c in keys))
    for c in keys:
        ratios = [r[c] / r["250"] for r in table]
        print(f"  {c:20s}: ratio median {statistics.median(ratios):.2f}, min {min(ratios):.2f}, max {max(ratios):.2f}")
    for c in keys:
        if (c.startswith(methods[0]) or c.startswith("oracle")) and c.endswith(("first", "designed")):
            ratios = [r[c] / r["250"] for r in table]
            ok = max(ratios) <= TARGET
            print(f"{args.poses} poses + {c}: worst ratio over {len(table)} units {max(ratios):.2f} "
                  f"(target <= {TARGET}): {'PASS' if ok else 'FAIL'}")
    print(f"total {time.perf_counter() - t_start:.0f} s")
    return 0


if __name__ == "__main__":
    sys.exit(main())
