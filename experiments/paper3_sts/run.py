"""Paper III on a simulated FANUC LR Mate 200i carrying a SmartTRACK sensor (STS), every table beside the paper's.

    python experiments/paper3_sts/run.py [--seed 0] [--quick] [--threads 1] [--ftol F] [--json OUT.json]

Sections (Paper III numbering):
  Set-up      the truth (:class:`torchcal.sim.sensor_truth.SensorTruth`) and how many quasi-random
              commands the STS ranges rejected
  5.2         orientation repeatability (41)-(45) next to ISO 9283 position repeatability
  5.3 / Fig 10 measurement covariance: angle sigmas at five STS configurations vs (46), tracker
              position covariance (36) vs the sample, D1's linearized-vs-Monte-Carlo check
  Figs 11-12  validation residuals of the adaptive models ((33), strategies 'information' and
              'literal') and of the non-adaptive models ((31)) at 50, 75, ..., 250 identification poses
  Time        whole adaptive sequence vs whole non-adaptive sequence
  Tables 3-4  the 250-pose STS model: positional and angular residuals, identification and validation
  Tables 5-6  the AT method on the same robot (250 poses x 3 target set-ups) vs the STS model
  Targets     each issue target with PASS / FAIL

The paper's numbers come from its real robot and are printed for scale; the
simulated robot's errors are drawn, not the paper's robot.
"""

from __future__ import annotations

import argparse
import json
import math
import platform
import sys
import time

import torchcal  # noqa: F401  before torch: its OpenMP threads then sleep while waiting (torchcal.core.threads)
import torch
from rich.console import Console
from rich.table import Table

from torchcal.core import units
from torchcal.analysis.orientation import orientation_repeatability
from torchcal.analysis.repeatability import iso9283_repeatability
from torchcal.analysis.stats import percent_decrease, point_residuals, residual_stats
from torchcal.identify import NoiseModel, Prior, fit
from torchcal.identify.online import OnlineCalibration
from torchcal.kinematics import load_robot
from torchcal.measure import PointTargets
from torchcal.models.sensor_rig import SensorRig
from torchcal.measure.sts import STSInstrument, level_sigma_deg, sts_angles
from torchcal.measure.tracker import TrackerNoise, covariance_check
from torchcal.measure.triangle import triangle_frame
from torchcal.core.measurements import Measurements
from torchcal.models.robot import RobotModel
from torchcal.sim.sensor_truth import SensorTruth

MM = units.m_to_mm(1.0)
DEG = units.DEG
console = Console(highlight=False, width=140)

# Paper III, real robot
PAPER_T3 = {"id_nominal": (9.218, 12.087, 12.797), "id_modeled": (0.114, 0.278, 0.288),
            "val_nominal": (9.301, 12.627, 12.959), "val_modeled": (0.118, 0.384, 0.311)}  # mm
PAPER_T4 = {"id_nominal": (0.0155, 0.0227, 0.0271), "id_modeled": (0.00045, 0.0011, 0.0012),
            "val_nominal": (0.0157, 0.0230, 0.0271), "val_modeled": (0.0004, 0.0012, 0.0012)}  # rad
PAPER_T5 = {"Nominal": (10.191, 12.923, 13.856), "AT": (0.136, 0.396, 0.338), "STS": (0.118, 0.384, 0.311)}
PAPER_T6 = {"Nominal": (0.0155, 0.0227, None), "AT": (0.0007, 0.0015, 0.0016), "STS": (0.00045, 0.0011, 0.0012)}
PAPER_REPEAT = (0.03, 1.22e-4)  # mm, rad (5.2)
ORDER = 3
TOL_ADAPTIVE = 0.05
TOL_TIME = 0.25
TOL_COV = 0.02


def fmt(x, digits=4):
    return "-" if x is None or (isinstance(x, float) and math.isnan(x)) else f"{x:.{digits}f}"


def angle_between(a: torch.Tensor, b: torch.Tensor) -> torch.Tensor:
    """Angle (R,) rad between unit vectors (R, 3): atan2 keeps precision at 1e-5 rad."""
    return torch.atan2(torch.linalg.cross(a, b, dim=-1).norm(dim=-1), (a * b).sum(-1))


class Setup:
    """Truth, commands and all simulated data of one seed."""

    def __init__(self, seed: int, quick: bool):
        self.seed = seed
        self.robot = load_robot("fanuc_lrmate200i")
        self.truth = SensorTruth(self.robot, seed)
        self.n_val = 100 if quick else 300
        self.sizes = list(range(50, (125 if quick else 250) + 1, 25))
        n_id = self.sizes[-1]
        # Paper III 5.5: the first 300 measurements are the validation set, the identification poses follow
        self.sample = self.truth.sample_commands(self.n_val + n_id, seed)
        q, s = self.sample.q, self.sample.direction
        self.sts = self.truth.measure_sts(q, s, seed + 1)
        self.val = self.sts.subset(torch.arange(self.n_val))
        self.ident = self.sts.subset(torch.arange(self.n_val, self.n_val + n_id))
        self.tracker = TrackerNoise.paper3()
        self.noise = NoiseModel.from_robot(self.robot, sigma_m=1e-5)
        # AT (6.1): three set-ups over the identification poses, the third set-up over the validation poses
        self.at_ident = self.truth.measure_targets(q[self.n_val:], s[self.n_val:], seed + 2)
        self.at_val = self.truth.measure_targets(q[: self.n_val], s[: self.n_val], seed + 3, targets=(2,))

    def instrument(self, data: Measurements) -> STSInstrument:
        return STSInstrument.from_measurements(data, noise=self.tracker, gravity=self.truth.virtual_level)

    def rig(self) -> SensorRig:
        return SensorRig.for_robot(self.robot, orders=ORDER, base_nominal=self.truth.base_nominal,
                                   mount=self.truth.mount_nominal)

    def first(self, n: int) -> Measurements:
        return self.ident.subset(torch.arange(n))


# --------------------------------------------------------------------------- evaluation
def sts_residuals(rig: SensorRig, data: Measurements, nominal: bool = False) -> tuple[torch.Tensor, torch.Tensor]:
    """Positional (m) and angular (rad, z_s0 axes, 5.5) residuals (R,) of a rig on STS rows, v = 0."""
    with torch.no_grad():
        T = rig.nominal_sensor_pose(data.q) if nominal else rig.sensor_pose(data.q, None, data.direction)
    pos = (T[:, :3, 3] - data.xyz).norm(dim=-1)
    ang = angle_between(T[:, :3, 2], data.extra["rotation"][:, :, 2])
    return pos, ang


def sts_truth_error(rig: SensorRig, data: Measurements) -> tuple[torch.Tensor, torch.Tensor]:
    """Model minus the noise-free truth (v = 0): position (m) and z_s0 angle (rad) per row."""
    with torch.no_grad():
        T = rig.sensor_pose(data.q, None, data.direction)
    return (T[:, :3, 3] - data.extra["xyz_exact"]).norm(dim=-1), angle_between(T[:, :3, 2], data.extra["rotation_exact"][:, :, 2])


def section_setup(S: Setup):
    d = S.truth.describe()
    s = S.sample
    dist = S.sts.xyz.norm(dim=-1)
    a = S.sts.extra["sts_angles"] / DEG
    console.print(f"[bold]Set-up[/bold] (seed {S.seed}): tracker {float(dist.min()):.2f}-{float(dist.max()):.2f} m from the "
                  f"sensor; mount error {d['mount_error_mm']} mm / {d['mount_error_deg']}°; gravity tilted "
                  f"{d['gravity_tilt_deg']}° from the tracker z; head errors the model lacks: axis skew "
                  f"{d['axis_skew_deg']}°, yaw eccentricity {d['yaw_eccentricity_deg']}°, level bias {d['level_bias_deg']}° "
                  f"+ cubic {d['level_cubic_deg']}°; robot gear ripple and cross-coupling on.")
    console.print(f"commands: {s.q.shape[0]} valid of {s.drawn} quasi-random candidates over Table 2's ranges; "
                  f"rejected {s.n_rejected} (roll only {s.rejected['roll']}, level only {s.rejected['level']}, "
                  f"both {s.rejected['both']}); measured roll {float(a[:, 1].min()):.1f}..{float(a[:, 1].max()):.1f}°, "
                  f"level {float(a[:, 2].min()):.1f}..{float(a[:, 2].max()):.1f}°. "
                  f"{S.n_val} validation poses first, then {S.sizes[-1]} identification poses.")
    return {"drawn": s.drawn, "rejected": s.rejected, "truth": {k: v for k, v in d.items() if k != "robot"}}


def section_repeatability(S: Setup):
    """5.2: 5 poses x 20 STS readings, each cycle approached from the same direction (ISO 9283)."""
    P, K = 5, 20
    q = S.val.q[:P].repeat_interleave(K, 0)
    m = S.truth.measure_sts(q, torch.ones_like(q), S.seed + 11)
    ro = orientation_repeatability(m.extra["rotation"].reshape(P, K, 3, 3), axis=2)
    rp = iso9283_repeatability(m.xyz.reshape(P, K, 3)) * MM
    console.print(f"[bold]5.2 repeatability[/bold] ({P} poses x {K}): ISO 9283 position RP max {float(rp.max()):.4f} mm "
                  f"(paper ±{PAPER_REPEAT[0]} mm); orientation R_o (41)-(45) max {float(ro.worst):.3e} rad "
                  f"(paper ±{PAPER_REPEAT[1]:.3g} rad)")
    return {"position_mm": [float(x) for x in rp], "orientation_rad": [float(x) for x in ro.ro]}


def section_covariance(S: Setup, quick: bool):
    """5.3: 500 static readings at five configurations with |φ| ≈ 0, 15, 30, 45, 58°; tracker covariance check."""
    pool = S.truth.sample_commands(400, S.seed + 20)
    T = S.truth.sensor_pose(pool.q)
    lev = (sts_angles(T[:, :3, :3], T[:, :3, 3], S.truth.gravity) / DEG)[:, 2].abs()
    targets = [0.0, 15.0, 30.0, 45.0, 58.0]
    idx = torch.stack([(lev - t).abs().argmin() for t in targets])
    M = 500
    # the robot stands still during a configuration's readings: one joint-error draw per configuration
    ms = [S.truth.measure_sts(pool.q[i:i + 1].repeat(M, 1), torch.ones(M, 6, dtype=torch.float64), S.seed + 30 + k,
                              static=True) for k, i in enumerate(idx.tolist())]
    m = Measurements(torch.cat([x.q for x in ms]), torch.cat([x.tool for x in ms]), torch.cat([x.xyz for x in ms]),
                     torch.cat([x.direction for x in ms]), torch.cat([x.pose for x in ms]), torch.arange(1, 5 * M + 1),
                     True, "static", {"rotation": torch.cat([x.extra["rotation"] for x in ms])})
    ang = sts_angles(m.extra["rotation"], m.xyz, S.truth.virtual_level).reshape(5, M, 3)  # (20)-(21) on the export
    ang = torch.cat([torch.atan2(torch.sin(ang[..., :1] - ang[:, :1, :1]), torch.cos(ang[..., :1] - ang[:, :1, :1])),
                     ang[..., 1:]], -1)  # unwrap yaw about the first reading
    sd = ang.std(1) / DEG  # (5, 3) deg
    mean_phi = (ang[:, :, 2].mean(1) / DEG)
    t = Table(title="5.3 / Figure 10: angle standard deviations (deg) at five STS configurations, 500 static readings each; (46) beside")
    for c in ("config", "level φ", "σ_ψ", "(46)", "σ_θ", "(46)", "σ_φ", "(46)", "σ_x µm", "σ_y µm", "σ_z µm", "(36) x/y/z µm"):
        t.add_column(c, justify="right")
    xyz = m.xyz.reshape(5, M, 3)
    out = []
    for k in range(5):
        phi = float(mean_phi[k])
        lin = S.tracker.covariance(xyz[k].mean(0, keepdim=True))[0].diagonal().sqrt() * 1e6
        emp = xyz[k].std(0) * 1e6
        s46 = float(level_sigma_deg(torch.tensor(phi)))
        t.add_row(str(k + 1), f"{phi:.1f}", f"{float(sd[k, 0]):.5f}", "0.00050", f"{float(sd[k, 1]):.5f}", "0.00050",
                  f"{float(sd[k, 2]):.5f}", f"{s46:.5f}", *(f"{float(x):.2f}" for x in emp),
                  "/".join(f"{float(x):.2f}" for x in lin))
        out.append({"level_deg": phi, "sigma_deg": [float(x) for x in sd[k]], "sigma_46_level_deg": s46,
                    "sigma_xyz_um": [float(x) for x in emp], "sigma_xyz_36_um": [float(x) for x in lin]})
    console.print(t)
    console.print("σ_ψ, σ_θ include the yaw/roll readings' own noise only (the robot stands still); the head errors the "
                  "model lacks are systematic and do not show here.", style="dim")
    n = 50_000 if quick else 200_000
    t0 = time.perf_counter()
    worst_grid = covariance_check(S.tracker, None, n, S.seed)
    pts = S.sts.xyz[torch.linspace(0, len(S.sts) - 1, 12).long()]
    worst_setup = covariance_check(S.tracker, pts, n, S.seed + 1)
    dt = time.perf_counter() - t0
    console.print(f"tracker covariance (36) linearized vs Monte Carlo ({n} samples per point): worst element deviation "
                  f"{100 * worst_grid:.2f} % over the working-range grid, {100 * worst_setup:.2f} % over 12 of this "
                  f"set-up's sensor positions ({dt:.1f} s)")
    return {"configs": out, "cov_worst_grid": worst_grid, "cov_worst_setup": worst_setup, "mc_samples": n}


def section_adaptive(S: Setup, solver: dict):
    """Figures 11-12 and the modeling time; solver: options for every fit and update alike (e.g. ftol)."""
    inst_all = S.instrument(S.ident)
    prior = Prior()
    # warm-up, not timed: the first fit of a process imports torch.func / dynamo (seconds), which
    # would otherwise be charged to whichever sequence runs first
    fit(S.rig(), S.first(10), S.noise, prior, instrument=inst_all.subset(torch.arange(10)), max_iter=2)
    rows = {}
    seqs = {}
    finals = {}
    for strategy in ("information", "literal"):
        rig = S.rig()
        oc = OnlineCalibration(rig, S.noise, prior, strategy=strategy, **solver)
        wall, cpu = [], []
        prev = 0
        for n in S.sizes:
            idx = torch.arange(prev, n)
            t0, c0 = time.perf_counter(), time.process_time()
            step = oc.update(S.ident.subset(idx), inst_all.subset(idx))
            wall.append(time.perf_counter() - t0)
            cpu.append(time.process_time() - c0)
            pos, ang = sts_residuals(rig, S.val)
            rows[(strategy, n)] = (residual_stats(pos * MM), residual_stats(ang), step.result.nit, wall[-1], cpu[-1])
            prev = n
        seqs[strategy] = (sum(wall), sum(cpu))
        finals[strategy] = rig
        console.print(f"  adaptive '{strategy}' done: {seqs[strategy][0]:.1f} s", style="dim")
    wall, cpu = [], []
    for n in S.sizes:
        rig = S.rig()
        idx = torch.arange(n)
        t0, c0 = time.perf_counter(), time.process_time()
        r = fit(rig, S.first(n), S.noise, prior, instrument=inst_all.subset(idx), **solver)
        wall.append(time.perf_counter() - t0)
        cpu.append(time.process_time() - c0)
        pos, ang = sts_residuals(rig, S.val)
        rows[("batch", n)] = (residual_stats(pos * MM), residual_stats(ang), r.nit, wall[-1], cpu[-1])
        finals["batch"] = rig
    seqs["batch"] = (sum(wall), sum(cpu))
    console.print(f"  non-adaptive done: {seqs['batch'][0]:.1f} s", style="dim")
    for title, k, unit, dig in (("Figure 11: validation positional residuals (mm)", 0, "mm", 4),
                                ("Figure 12: validation angular residuals (rad, z_s0 axes)", 1, "rad", 6)):
        t = Table(title=f"{title}: adaptive (33) 'information' / 'literal' vs non-adaptive (31); Δ = adaptive vs non-adaptive mean")
        for c in ("N", "info mean", "info G99", "Δ info", "literal mean", "literal G99", "Δ literal", "non-adapt mean", "non-adapt G99"):
            t.add_column(c, justify="right")
        for n in S.sizes:
            b = rows[("batch", n)][k]
            cells = [str(n)]
            for strat in ("information", "literal"):
                a = rows[(strat, n)][k]
                cells += [fmt(a.mean, dig), fmt(a.gamma99, dig), f"{100 * (a.mean - b.mean) / b.mean:+.2f} %"]
            cells += [fmt(b.mean, dig), fmt(b.gamma99, dig)]
            t.add_row(*cells)
        console.print(t)
    t = Table(title="Modeling time per model: wall s / process CPU s, iterations")
    for c in ("N", "info s", "info it", "literal s", "literal it", "non-adapt s", "non-adapt it"):
        t.add_column(c, justify="right")
    for n in S.sizes:
        t.add_row(str(n), *(x for strat in ("information", "literal", "batch")
                            for x in (f"{rows[(strat, n)][3]:.2f} / {rows[(strat, n)][4]:.2f}", str(rows[(strat, n)][2]))))
    console.print(t)
    b = seqs["batch"]
    console.print("whole sequence (wall / CPU): " + ", ".join(
        f"adaptive '{k}' {seqs[k][0]:.1f} / {seqs[k][1]:.1f} s ({100 * seqs[k][0] / b[0]:.1f} / {100 * seqs[k][1] / b[1]:.1f} %)"
        for k in ("information", "literal")) + f", non-adaptive {b[0]:.1f} / {b[1]:.1f} s ({torch.get_num_threads()} threads). "
        "Paper: 70 min vs 5 h (23 %). The target is judged on CPU time: wall time on a shared machine measures the "
        "other processes too.")
    return rows, seqs, finals


def section_tables_3_4(S: Setup, rig: SensorRig, label: str):
    n = S.sizes[-1]
    ident = S.first(n)
    res = {}
    for name, data in (("id", ident), ("val", S.val)):
        for kind, nom in (("nominal", True), ("modeled", False)):
            p, a = sts_residuals(rig, data, nominal=nom)
            res[f"{name}_{kind}"] = (residual_stats(p * MM), residual_stats(a))
    out = {}
    for k, title, unit, paper, dig in ((0, "Table 3: positional residuals (mm)", "mm", PAPER_T3, 4),
                                       (1, "Table 4: angular residuals (rad, z_s0)", "rad", PAPER_T4, 6)):
        t = Table(title=f"{title}, {label} STS model, order {ORDER}, {n} identification poses; paper's real robot beside")
        for c in ("set", "mean", "paper", "% decr.", "max", "paper", "Gamma 99 %", "paper"):
            t.add_column(c, justify="right")
        for key, lab in (("id_nominal", "identification nominal"), ("id_modeled", "identification modeled"),
                         ("val_nominal", "validation nominal"), ("val_modeled", "validation modeled")):
            s = res[key][k]
            base = res[key.split("_")[0] + "_nominal"][k]
            pct = "" if "nominal" in key else f"{percent_decrease(base.mean, s.mean):.2f}"
            p = paper[key]
            t.add_row(lab, fmt(s.mean, dig), fmt(p[0], dig), pct, fmt(s.max, dig), fmt(p[1], dig), fmt(s.gamma99, dig), fmt(p[2], dig))
            out[f"{key}_{unit}"] = s.as_dict() if hasattr(s, "as_dict") else {"mean": s.mean, "max": s.max, "gamma99": s.gamma99}
        console.print(t)
    tp, ta = sts_truth_error(rig, S.val)
    g_err = float(angle_between(rig.gravity_vector().detach()[None], S.truth.gravity[None]))
    console.print(f"against the noise-free truth (validation): position {float(tp.mean()) * MM:.4f} mm mean / "
                  f"{float(tp.max()) * MM:.4f} max, z_s0 {float(ta.mean()):.2e} rad mean / {float(ta.max()):.2e} max; "
                  f"fitted gravity {g_err:.1e} rad from the true one (tracker z: {math.radians(0.03):.1e} rad)")
    out["truth_pos_mean_mm"], out["truth_ang_mean_rad"], out["gravity_error_rad"] = float(tp.mean()) * MM, float(ta.mean()), g_err
    return out


def at_normals(points: torch.Tensor, n: int) -> torch.Tensor:
    """Triangle normals (n, 3) from tool-major points (3 n, 3) (D1's triangle_frame z axis)."""
    P = points.reshape(3, n, 3)
    return triangle_frame(P[0], P[1], P[2])[:, :3, 2]


def section_tables_5_6(S: Setup, sts_rig: SensorRig):
    n = S.sizes[-1]
    at = RobotModel(S.robot, S.truth.targets_nominal, orders=ORDER, base_nominal=S.truth.base_nominal)
    inst = PointTargets.from_measurements(S.at_ident, cov=S.tracker.covariance(S.at_ident.xyz))
    t0 = time.perf_counter()
    r = fit(at, S.at_ident, S.noise, Prior(), instrument=inst)
    dt = time.perf_counter() - t0
    # Table 5: validation positional residuals, each model on its own validation measurements
    at_val = residual_stats(point_residuals(at, S.at_val) * MM)
    at_nom = residual_stats(point_residuals(at, S.at_val, nominal=True) * MM)
    p_sts = sts_residuals(sts_rig, S.val)[0]
    p_nom = sts_residuals(sts_rig, S.val, nominal=True)[0]
    t = Table(title=f"Table 5: validation positional residuals (mm), {S.n_val} poses; AT: target 3, STS: sensor origin; paper beside")
    for c in ("model", "mean", "paper", "max", "paper", "Gamma 99 %", "paper"):
        t.add_column(c, justify="right")
    rows5 = {"Nominal (AT target 3)": (at_nom, PAPER_T5["Nominal"]), "Nominal (STS)": (residual_stats(p_nom * MM), None),
             "AT": (at_val, PAPER_T5["AT"]), "STS": (residual_stats(p_sts * MM), PAPER_T5["STS"])}
    for k, (s, p) in rows5.items():
        t.add_row(k, fmt(s.mean), fmt(p[0], 3) if p else "", fmt(s.max), fmt(p[1], 3) if p else "", fmt(s.gamma99),
                  fmt(p[2], 3) if p else "")
    console.print(t)
    # Table 6: identification-set angular residuals; AT orientation = normal of the measured triangle
    meas = at_normals(S.at_ident.xyz, n)
    tools = torch.arange(3).repeat_interleave(n)
    with torch.no_grad():
        pred = at_normals(at.points(S.at_ident.q, tools, S.at_ident.direction), n)
        nom = at_normals(at.nominal_points(S.at_ident.q, tools), n)
        true_n = at_normals(S.at_ident.extra["xyz_exact"], n)
    at_ang, at_nom_ang, at_truth = angle_between(pred, meas), angle_between(nom, meas), angle_between(pred, true_n)
    ident = S.first(n)
    a_id = sts_residuals(sts_rig, ident)[1]
    _, a_id_nom = sts_residuals(sts_rig, ident, nominal=True)
    _, a_id_truth = sts_truth_error(sts_rig, ident)
    t = Table(title=f"Table 6: identification-set angular residuals (rad), {n} poses; AT: triangle normal, STS: z_s0; paper beside")
    for c in ("model", "mean", "paper", "max", "paper", "Gamma 99 %", "paper", "vs truth mean"):
        t.add_column(c, justify="right")
    rows6 = {"Nominal (AT triangle)": (residual_stats(at_nom_ang), PAPER_T6["Nominal"], None),
             "Nominal (STS)": (residual_stats(a_id_nom), None, None),
             "AT": (residual_stats(at_ang), PAPER_T6["AT"], float(at_truth.mean())),
             "STS": (residual_stats(a_id), PAPER_T6["STS"], float(a_id_truth.mean()))}
    for k, (st, p, tr) in rows6.items():
        t.add_row(k, fmt(st.mean, 6), fmt(p[0], 5) if p else "", fmt(st.max, 6), fmt(p[1], 5) if p else "",
                  fmt(st.gamma99, 6), fmt(p[2], 5) if p and p[2] else "", fmt(tr, 6) if tr is not None else "")
    console.print(t)
    console.print(f"AT model: {r.message}, {r.nit} iterations, {dt:.1f} s. 'vs truth': the model's orientation against "
                  "the noise-free true triangle normal / z_s0 (what the measured residual cannot separate from noise).")
    return {"t5": {k: {"mean": v[0].mean, "max": v[0].max, "gamma99": v[0].gamma99} for k, v in rows5.items()},
            "t6": {k: {"mean": v[0].mean, "max": v[0].max, "gamma99": v[0].gamma99, "truth_mean": v[2]} for k, v in rows6.items()}}


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--quick", action="store_true", help="100 validation poses, models at 50-125 poses (< 1 min)")
    ap.add_argument("--threads", type=int, default=1,
                    help="torch threads (default 1: the models are small, and a second thread only spin-waits, "
                         "which inflates the CPU time the timing target is judged on)")
    ap.add_argument("--ftol", type=float, default=None,
                    help="LM relative cost-reduction tolerance for every model (default: the solver's, 1e-8)")
    ap.add_argument("--json", default=None, help="write every number to this file")
    a = ap.parse_args(argv)
    torch.set_num_threads(a.threads)
    t_start = time.perf_counter()
    console.print(f"torchcal Paper III experiment, seed {a.seed}{' (quick)' if a.quick else ''}; python "
                  f"{platform.python_version()}, torch {torch.__version__}")
    S = Setup(a.seed, a.quick)
    out = {"seed": a.seed, "quick": a.quick, "setup": section_setup(S)}
    out["repeatability"] = section_repeatability(S)
    out["covariance"] = section_covariance(S, a.quick)
    rows, seqs, finals = section_adaptive(S, {} if a.ftol is None else {"ftol": a.ftol})
    out["tables_3_4"] = section_tables_3_4(S, finals["information"], "adaptive 'information'")
    out["tables_5_6"] = section_tables_5_6(S, finals["information"])
    # ------------------------------------------------------------------ targets
    t = Table(title="Issue targets")
    for c in ("target", "value", "limit", "result"):
        t.add_column(c)
    verdicts = []

    def add(name, value, limit, ok):
        verdicts.append(ok)
        t.add_row(name, value, limit, "[green]PASS[/green]" if ok else "[red]FAIL[/red]")

    for strat in ("information", "literal"):
        for k, what in ((0, "position"), (1, "angle")):
            dev = max(abs(rows[(strat, n)][k].mean - rows[("batch", n)][k].mean) / rows[("batch", n)][k].mean for n in S.sizes)
            add(f"adaptive '{strat}' within 5 % of non-adaptive, validation mean {what}, every N",
                f"worst {100 * dev:.2f} %", "≤ 5 %", dev <= TOL_ADAPTIVE)
    for strat in ("information", "literal"):
        ratio = seqs[strat][1] / seqs["batch"][1]
        add(f"whole adaptive '{strat}' sequence CPU time / non-adaptive", f"{100 * ratio:.1f} % (wall "
            f"{100 * seqs[strat][0] / seqs['batch'][0]:.1f} %)", "≤ 25 %", ratio <= TOL_TIME)
    t6 = out["tables_5_6"]["t6"]
    add("STS angular residual below the AT model's (Table 6, identification mean)",
        f"{t6['STS']['mean']:.2e} vs {t6['AT']['mean']:.2e} rad", "STS < AT", t6["STS"]["mean"] < t6["AT"]["mean"])
    cov = out["covariance"]
    worst = max(cov["cov_worst_grid"], cov["cov_worst_setup"])
    add("tracker covariance (36) vs Monte Carlo, worst element", f"{100 * worst:.2f} %", "≤ 2 %", worst <= TOL_COV)
    console.print(t)
    wall = time.perf_counter() - t_start
    console.print(f"run time {wall:.1f} s; {sum(verdicts)}/{len(verdicts)} targets PASS")
    out["targets_pass"] = [bool(v) for v in verdicts]
    out["wall_s"] = wall
    out["adaptive"] = {f"{s}/{n}": {"pos_mean_mm": v[0].mean, "pos_g99_mm": v[0].gamma99, "ang_mean_rad": v[1].mean,
                                    "ang_g99_rad": v[1].gamma99, "iterations": v[2], "seconds": v[3], "cpu_seconds": v[4]} for (s, n), v in rows.items()}
    out["sequence_seconds"] = {k: {"wall": v[0], "cpu": v[1]} for k, v in seqs.items()}
    if a.json:
        with open(a.json, "w") as f:
            json.dump(out, f, indent=1, default=float)
    return 0 if all(verdicts) else 1  # a FAIL is a failure for scripts and CI too


if __name__ == "__main__":
    sys.exit(main())
