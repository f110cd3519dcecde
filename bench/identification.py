"""Bench: identification against scipy ``least_squares`` (same problem) and against FIGAROH (IRB 120), quiet and loaded.

1. scipy: the FANUC order-6 + backlash fit (250 x 3, the bench's ``torchcal simulate`` data) solved
   by ``scipy.optimize.least_squares`` on the SAME problem: torchcal's ``CalibrationProblem``
   after its gauge fixing, unknowns = the same free parameters plus every row's joint errors v,
   residual = the same whitened vector whose sum of squares is torchcal's V (instrument rows,
   sqrt(Sigma_v^-1) v, the prior rows), Jacobian = torchcal's closed-form one as a sparse matrix
   (so both solvers pay the same model evaluations); method 'trf' with the LSMR trust-region
   solver (scipy's choice for large sparse problems; 'lm' would need the dense 7 017 x 4 767
   Jacobian), stopped (its ``callback``) once its V is within 0.1 % of the V torchcal converged to,
   at most 300 evaluations. Printed: time ratio scipy / torchcal to the same V.
2. FIGAROH (PyPI ``figaroh``, its geometric calibration pipeline, ``BaseCalibration``) on the real
   IRB 120 + FARO data, same 70/30 split as experiments/irb120_faro/run.py (seed 0), at its most
   complete level: ``calibration_level: full_params`` (6 placement errors per joint, reduced to
   its base parameters by its QR selection, then the ones the frames absorb dropped),
   ``include_non_geometric: true`` (one joint stiffness per joint times the gravity torque from the
   URDF's inertials, pinocchio), unknown base frame (the tracker's) and three unknown marker
   positions, its closed-form frame guess, ``scipy.optimize.least_squares`` LM. FIGAROH 1.0.2
   drops the stiffness parameters when the base frame is unknown (``add_base_name`` writes the 6
   base names over the first 6 entries of ``param_name``, which are the stiffnesses, instead of
   over the first 6 geometric base parameters); the bench patches that at run time
   (:func:`patch_figaroh`), nothing of FIGAROH is copied here. Beside it, torchcal's model of the
   shipped config without the constraint: order 4 + backlash + gravity compliance (J2, J3, J5),
   far-frame alignment then the MLE (as run.py). Times: identification from data in memory
   (FIGAROH: ``initialize()`` = parameter selection + ``solve()``; torchcal: ``align()`` + ``fit()``).
   Held-out: mean / max distance over the validation poses measured by all three reflectors
   (FIGAROH needs every marker of a sample), the same rows for both.
   Targets: torchcal faster than FIGAROH (time ratio FIGAROH / torchcal >= 1) and better held-out
   mean (FIGAROH mean / torchcal mean >= 1), quiet and loaded.

    python bench/identification.py [--quick] [--irb120-data DIR]
"""

from __future__ import annotations

import torchcal  # noqa: F401  first: OMP_WAIT_POLICY=PASSIVE before torch loads

import contextlib
import io
import logging
import sys
import time
import warnings

import numpy as np

import data as bench_data
from harness import Context, Row, at_least, guarded, main, need

NAME = "identification"


# ====================================================================== 1. scipy least_squares, same problem


SCIPY_REL = 1e-3  # scipy "reaches torchcal" when its V is within 0.1 % of torchcal's converged V
SCIPY_MAX_NFEV = 300


def scipy_fit(make, ident, noise, prior, ftol: float, V_target: float | None = None):
    """least_squares on torchcal's own problem, stopped once V <= V_target (if given).

    -> (seconds, V at the end, nfev, njev, model, reached V_target)."""
    import torch
    from scipy import sparse
    from scipy.optimize import least_squares

    from torchcal.identify.fit import problem_work
    from torchcal.identify.gauge import fix_gauge
    from torchcal.identify.problem import CalibrationProblem
    from torchcal.core.threads import threads_for_work

    model = make()
    t0 = time.perf_counter()
    problem = CalibrationProblem(model, ident, noise, prior)
    with threads_for_work(problem_work(problem)):
        fix_gauge(problem)
        x0 = problem.layout.get()
        P = x0.numel()
        R, n = problem.data.q.shape
        d = problem.dim
        sw = problem.w_v_cost.sqrt()  # (R, n)
        sp = problem.prior_precision.sqrt()  # (P,)

        def split(z):
            z = torch.from_numpy(z)
            return z[:P], z[P:].reshape(R, n)

        def fun(z):
            x, v = split(z)
            f = problem.residual(x, v)
            return torch.cat([f.reshape(-1), (sw * v).reshape(-1), sp * (x - problem.prior_mean)]).numpy()

        # sparsity pattern: instrument rows see every parameter and their own row's n joint errors
        rows_v = (torch.arange(R * d) // d)[:, None] * n + torch.arange(n)[None, :]  # (R d, n) v column of each entry

        def jac(z):
            x, v = split(z)
            f, A, C = problem.linearize(x, v)
            top_a = sparse.csr_matrix(A.reshape(R * d, P).numpy())
            top_c = sparse.csr_matrix((C.reshape(R * d, n).reshape(-1).numpy(),
                                       (np.repeat(np.arange(R * d), n), rows_v.reshape(-1).numpy())), shape=(R * d, R * n))
            mid = sparse.hstack([sparse.csr_matrix((R * n, P)), sparse.diags(sw.reshape(-1).numpy())])
            bot = sparse.hstack([sparse.diags(sp.numpy()), sparse.csr_matrix((P, R * n))])
            return sparse.vstack([sparse.hstack([top_a, top_c]), mid, bot]).tocsr()

        def stop(intermediate_result):
            if V_target is not None and 2.0 * intermediate_result.cost <= V_target:
                raise StopIteration

        z0 = torch.cat([x0, problem.v_zero().reshape(-1)]).numpy()
        sol = least_squares(fun, z0, jac=jac, method="trf", tr_solver="lsmr", x_scale="jac", ftol=ftol,
                            xtol=1e-10, gtol=1e-10, max_nfev=SCIPY_MAX_NFEV, callback=stop)
        x, v = split(sol.x)
        problem.layout.set(x)
    dt = time.perf_counter() - t0
    V = float(2.0 * sol.cost)
    return dt, V, sol.nfev, sol.njev, model, V_target is not None and V <= V_target


def scipy_case(ctx: Context) -> list[Row]:
    from fit import fanuc_fit_setup
    from torchcal.identify import fit

    make, ident, noise, prior, opts = fanuc_fit_setup(ctx)
    fit(make(), ident, noise, prior, **opts)  # warm-up

    def measure(loaded):
        t0 = time.perf_counter()
        res = fit(make(), ident, noise, prior, **opts)
        t_tc = time.perf_counter() - t0
        t_sp, V_sp, nfev, njev, _, reached = scipy_fit(make, ident, noise, prior, opts.get("ftol", 1e-8),
                                                         V_target=res.fun * (1 + SCIPY_REL))
        return {"tc": t_tc, "sp": t_sp, "V_tc": res.fun, "V_sp": V_sp, "nit": res.nit, "nfev": nfev, "njev": njev,
                "reached": reached}

    a, b, other = ctx.both(measure, label="scipy vs torchcal")
    reach = ("reached torchcal's V (+0.1 %)" if a["reached"] and b["reached"] else
             f"did NOT reach torchcal's V (+0.1 %) in {SCIPY_MAX_NFEV} evaluations: the ratio is a lower bound")
    return [Row(NAME, "FANUC order 6 + backlash (250 x 3): time scipy least_squares (trf/lsmr) / torchcal LM to "
                      "the same V, same residual and parameters", a["sp"] / a["tc"], b["sp"] / b["tc"], unit="x",
                other_cpu=other,
                note=f"torchcal {a['tc']:.2f} / {b['tc']:.2f} s ({a['nit']} it), scipy {a['sp']:.1f} / {b['sp']:.1f} s "
                     f"({a['njev']} Jacobians); scipy {reach}; V scipy / torchcal {a['V_sp'] / a['V_tc']:.4f}")]


# ====================================================================== 2. FIGAROH on the IRB 120


def patch_figaroh():
    """FIGAROH 1.0.2: keep the joint stiffnesses (``include_non_geometric``) with an unknown base frame.

    ``calculate_base_kinematics_regressor`` appends the geometric base parameters AFTER the
    stiffness names (``base_mapping_slice`` records where); ``add_base_name`` then, at
    ``full_params``, writes the 6 base-frame names over ``param_name[0:6]`` (assuming the geometric
    ones start there), i.e. over the stiffnesses, which silently vanish from the fit. The patched
    function writes them over the first 6 geometric base parameters instead (unchanged without
    stiffnesses). Patched in ``figaroh.calibration.base_calibration``'s namespace, at run time.
    """
    import figaroh.calibration.base_calibration as bc
    from figaroh.calibration.parameter import BASE_TPL

    original = getattr(bc.add_base_name, "__wrapped__", bc.add_base_name)

    def add_base_name(cfg):
        if cfg["calib_model"] == "full_params" and cfg.get("non_geom") and "base_mapping_slice" in cfg:
            start = cfg["base_mapping_slice"][0]
            cfg["param_name"][start:start + len(BASE_TPL)] = list(BASE_TPL)
        else:
            original(cfg)

    add_base_name.__wrapped__ = original
    bc.add_base_name = add_base_name
    return original


def unpatch_figaroh(original):
    import figaroh.calibration.base_calibration as bc

    bc.add_base_name = original


def figaroh_inputs(ctx: Context):
    """FIGAROH's CSVs (x1..z3 in m, joint1..joint6 = URDF joint variables in rad) of the bench's split,
    a URDF copy whose fixed 'flange' joint is renamed (pinocchio would have two frames named 'flange'),
    and the complete-pose validation arrays."""
    import pandas as pd
    import torch

    robot, ident, val = bench_data.irb120_measurements(ctx)
    out = ctx.workdir / "figaroh"
    out.mkdir(exist_ok=True)

    def wide(m):
        th = robot.joint_map.to_joint(m.q).numpy()
        rows = {}
        for i in range(len(m)):
            p = int(m.pose[i])
            r = rows.setdefault(p, {f"joint{j + 1}": th[i, j] for j in range(6)})
            t = int(m.tool[i]) + 1
            r[f"x{t}"], r[f"y{t}"], r[f"z{t}"] = (float(c) for c in m.xyz[i])
        df = pd.DataFrame([r | {"pose": p} for p, r in rows.items()])
        return df.dropna().reset_index(drop=True)  # FIGAROH needs every marker of a sample

    ident_df, val_df = wide(ident), wide(val)
    ident_df.to_csv(out / "identification.csv", index=False)
    val_df.to_csv(out / "validation.csv", index=False)
    urdf = (bench_data.ROOT / "urdf/abb_irb120.urdf").read_text()
    urdf = urdf.replace('<joint name="flange" type="fixed">', '<joint name="flange_fixed" type="fixed">')
    (out / "abb_irb120.urdf").write_text(urdf)
    complete = set(val_df["pose"].astype(int))
    keep = torch.tensor([int(p) in complete for p in val.pose])
    return out, ident_df, val_df, val.subset(torch.nonzero(keep)[:, 0])


def figaroh_config(folder, n_samples: int, elasticity: bool):
    import yaml

    cfg = {"robot": {"name": "abb_irb120"},
           "tasks": {"calibration": {
               "enabled": True, "type": "calibration",
               "parameters": {"calibration_level": "full_params", "include_non_geometric": elasticity,
                              "outlier_threshold": None},
               "kinematics": {"base_frame": "universe", "tool_frame": "link6"},
               "measurements": {"markers": [{"name": f"SMR{i}", "reference_joint": "joint6",
                                             "measurable_dof": [True, True, True, False, False, False]}
                                            for i in (1, 2, 3)],
                                "poses": {"base_pose": [0.0] * 6, "tool_pose": [0.0] * 6}},
               "data": {"source_file": str(folder / "identification.csv"), "number_of_samples": n_samples}}}}
    path = folder / f"figaroh_{'elastic' if elasticity else 'geometric'}.yaml"
    path.write_text(yaml.safe_dump(cfg, sort_keys=False))
    return path


def run_figaroh(folder, ident_df, val_df, elasticity: bool) -> dict:
    """FIGAROH's identification of the IRB 120 -> seconds (initialize, solve), held-out errors (mm), parameter names."""
    from figaroh.calibration.base_calibration import BaseCalibration
    from figaroh.calibration.calibration_tools import calc_updated_fkm
    from figaroh.tools.load_robot import load_robot as figaroh_robot

    class IRB120Calibration(BaseCalibration):
        def cost_function(self, var):  # position of three markers, metres, unweighted (one tracker)
            return self.PEE_measured - calc_updated_fkm(self.model, self.data, var, self.q_measured, self.calib_config)

    cfg = figaroh_config(folder, len(ident_df), elasticity)
    sink = io.StringIO()
    with contextlib.redirect_stdout(sink), warnings.catch_warnings():
        warnings.simplefilter("ignore")
        robot = figaroh_robot(str(folder / "abb_irb120.urdf"))
        t0 = time.perf_counter()
        calib = IRB120Calibration(robot, str(cfg))
        calib.calib_config["known_baseframe"] = False  # the tracker's frame
        calib.calib_config["known_tipframe"] = False  # the three reflectors on the tool
        calib.initialize()
        t1 = time.perf_counter()
        result = calib.solve(enable_logging=False)
        t2 = time.perf_counter()
    names = list(calib.calib_config["param_name"])
    qv = np.zeros((len(val_df), robot.model.nq))
    qv[:, :6] = val_df[[f"joint{j}" for j in range(1, 7)]].to_numpy()
    cfg_val = dict(calib.calib_config, NbSample=len(val_df))
    pred = calc_updated_fkm(calib.model, calib.data, result.x, qv, cfg_val).reshape(3, 3, len(val_df))
    meas = np.stack([val_df[[f"x{k}", f"y{k}", f"z{k}"]].to_numpy().T for k in (1, 2, 3)])
    err = np.linalg.norm(pred - meas, axis=1) * 1e3
    return {"init": t1 - t0, "solve": t2 - t1, "total": t2 - t0, "mean": float(err.mean()), "max": float(err.max()),
            "params": names, "stiffness": [n for n in names if n.startswith("k_")], "success": bool(result.success)}


def run_torchcal_irb(robot, ident, val_complete) -> dict:
    """Order 4 + backlash + gravity compliance (J2, J3, J5), unconstrained: align + fit, as experiments/irb120_faro/run.py."""
    import torch

    from torchcal.core import units
    from torchcal.analysis.stats import point_residuals
    from torchcal.identify import NoiseModel, Prior, fit
    from torchcal.identify.alignment import align
    from torchcal.models.robot import RobotModel

    noise = NoiseModel.from_robot(robot, sigma_m=units.mm_to_m(0.005))
    t0 = time.perf_counter()
    al = align(robot, ident, n_tools=3)
    model = RobotModel(robot, al.tools, orders=4, backlash=True, base_nominal=al.base_nominal,
                       compliance={"mode": "gravity", "joints": [1, 2, 4]})
    res = fit(model, ident, noise, Prior(), max_iter=300)
    dt = time.perf_counter() - t0
    with torch.no_grad():
        r = point_residuals(model, val_complete) * 1e3
    return {"total": dt, "mean": float(r.mean()), "max": float(r.max()), "nit": res.nit, "success": bool(res.success)}


def figaroh_case(ctx: Context) -> list[Row]:
    need("figaroh", 'pip install figaroh (pulls pinocchio as PyPI "pin"), or pip install -e ".[bench]"')
    need("pinocchio", 'pip install pin')
    logging.getLogger("figaroh").setLevel(logging.ERROR)
    folder, ident_df, val_df, val_complete = figaroh_inputs(ctx)
    robot, ident, _ = bench_data.irb120_measurements(ctx)
    original = patch_figaroh()
    try:
        def measure(loaded):
            tc = run_torchcal_irb(robot, ident, val_complete)
            fg = run_figaroh(folder, ident_df, val_df, elasticity=True)
            out = {"tc": tc, "fg": fg}
            if not ctx.quick and not loaded:  # FIGAROH's geometric level alone, for reference (quiet only)
                out["fg_geo"] = run_figaroh(folder, ident_df, val_df, elasticity=False)
            return out

        a, b, other = ctx.both(measure, label="FIGAROH vs torchcal")
    finally:
        unpatch_figaroh(original)
    tc_a, tc_b, fg_a, fg_b = a["tc"], b["tc"], a["fg"], b["fg"]
    n_val = len(val_df)
    rows = [
        Row(NAME, "IRB 120 identification time: torchcal order 4 + backlash + gravity compliance (J2, J3, J5), "
                  "align + fit", tc_a["total"], tc_b["total"], unit="s", other_cpu=other,
            note=f"held out {tc_a['mean']:.4f} / {tc_a['max']:.3f} mm (mean / max, {n_val} complete poses x 3), "
                 f"{tc_a['nit']} LM iterations"),
        Row(NAME, "IRB 120 identification time: FIGAROH full_params + joint elasticity (patched), "
                  "initialize + solve", fg_a["total"], fg_b["total"], unit="s", other_cpu=other,
            note=f"held out {fg_a['mean']:.4f} / {fg_a['max']:.3f} mm; {len(fg_a['params'])} parameters incl. "
                 f"stiffness {', '.join(fg_a['stiffness']) or 'none'}; initialize {fg_a['init']:.1f} s + solve "
                 f"{fg_a['solve']:.1f} s quiet"),
        Row(NAME, "IRB 120: time FIGAROH / torchcal (torchcal faster)", fg_a["total"] / tc_a["total"],
            fg_b["total"] / tc_b["total"], unit="x", target=at_least(1, "x"), other_cpu=other),
        Row(NAME, "IRB 120: held-out mean FIGAROH / torchcal (torchcal more accurate)", fg_a["mean"] / tc_a["mean"],
            fg_b["mean"] / tc_b["mean"], unit="x", target=at_least(1, "x"),
            note=f"same 70/30 split as run.py (seed 0), validation poses with all three reflectors"),
    ]
    if "fg_geo" in a:
        g = a["fg_geo"]
        rows.append(Row(NAME, "IRB 120: FIGAROH full_params without elasticity (reference, quiet only)", g["total"],
                        None, unit="s", other_cpu=other,
                        note=f"held out {g['mean']:.4f} / {g['max']:.3f} mm, {len(g['params'])} parameters"))
    return rows


def run(ctx: Context) -> list[Row]:
    return (guarded(NAME, "scipy least_squares vs torchcal", lambda: scipy_case(ctx), ctx)
            + guarded(NAME, "IRB 120: FIGAROH vs torchcal", lambda: figaroh_case(ctx), ctx, target=at_least(1, "x")))


if __name__ == "__main__":
    sys.exit(main([sys.modules[__name__]], description=__doc__.split("\n")[0]))
