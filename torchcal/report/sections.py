"""The sections of the calibration report, each built from the run directory's files alone.

One function per section, each taking the :class:`~torchcal.report.rundata.RunFiles`
and returning HTML. A section whose files the run lacks says "not available"
and why (a sensor run has no ``residuals.csv``, a fit without a simulated truth
no compensation check, an update run no plots); no section raises for a
missing or malformed file. Values are shown in the files' units (mm, degrees,
percent); the accuracy table reads ``metrics.json``'s ``table6`` / ``table7``,
which every kind of run writes in the same layout.
"""

from __future__ import annotations

from pathlib import Path

from .html import esc, esc_lines, histogram_svg, image, kv, not_available, num, table
from .rundata import Missing, RunFiles, get, log_warnings

STAT_KEYS = ("mean", "max", "gamma99")


def kind_of(run: RunFiles) -> str:
    """'machine tool', 'robot with a 6-DOF sensor', 'robot' (from config.yaml; 'robot' when unknown)."""
    if get(run.config, "model", "kind") == "axis_perturbation":
        return "machine tool"
    if get(run.config, "sensor", "kind"):
        return "robot with a 6-DOF sensor"
    return "robot"


def _robot_source(run: RunFiles) -> str:
    robot = get(run.config, "robot")
    if robot is None:
        return "unknown (no config.yaml)"
    return f"{robot}" + ("" if Path(str(robot)).suffix else " (bundled description: URDF + joint map)")


# ------------------------------------------------------------------ title + summary
def title_block(run: RunFiles) -> str:
    robot = get(run.config, "robot", default="unknown")
    created = get(run.versions, "created", default="date not recorded")
    version = get(run.versions, "torchcal", default="unknown")
    commit = get(run.versions, "git", "commit")
    dirty = get(run.versions, "git", "dirty")
    parts = [f"{kind_of(run).capitalize()}: <b>{esc(robot)}</b>", f"run <b>{esc(run.folder.name)}</b>",
             f"{esc(created)}", f"torchcal {esc(version)}"
             + (f" (commit {esc(str(commit)[:10])}{', modified' if dirty else ''})" if commit else "")]
    banner = ""
    if run.partial:
        banner = ('<p class="banner">This run did not finish (the run directory holds a PARTIAL file): the report '
                  "shows what it had computed; see the run log at the end.</p>")
    if get(run.update, "parent"):
        banner += (f'<p class="muted">An update run (Paper III, online identification): the model of '
                   f'{esc(run.update["parent"])} with {esc(get(run.update, "new_rows"))} new rows added.</p>')
    return (f'<header class="title"><h1>Calibration report &mdash; {esc(robot)}</h1>'
            f'<div class="sub">{" &middot; ".join(parts)}</div>'
            f'<div class="note">{esc(run.folder)}</div></header>{banner}')


def _held_out(run: RunFiles):
    """(set label, nominal row, modeled row) of the held-out set, else of the identification set."""
    rows = get(run.metrics, "table6", default=[]) or []
    by_set: dict[str, dict] = {}
    for r in rows:
        if isinstance(r, dict):
            by_set.setdefault(str(r.get("set")), {})[str(r.get("residual"))] = r
    for name in ("Validation", "Update", "Identification"):
        res = by_set.get(name, {})
        nom = next((r for k, r in res.items() if k.lower().startswith("nominal") and "angle" not in k), None)
        mod = next((r for k, r in res.items() if k.lower().startswith("modeled") and "angle" not in k), None)
        if nom and mod:
            return name, nom, mod
    return None


def _mm(v) -> str:
    """A length in mm for a card, or '–' where the run has none (a Gamma fit needs more than one row)."""
    return "–" if not isinstance(v, (int, float)) else f"{v:.4f} mm"


def summary(run: RunFiles) -> str:
    held = _held_out(run)
    cards = []
    if held:
        name, nom, mod = held
        label = "held-out validation" if name == "Validation" else name.lower()
        d = mod.get("mean_decrease")
        change = "" if d is None else f" ({d:.1f} % less)" if d >= 0 else f" ({-d:.1f} % more: worse than before)"
        cards.append(("Position error, " + label, _mm(mod.get("mean")),
                      f"mean after calibration; {_mm(nom.get('mean'))} before{change}"))
        cards.append(("Gamma 99 %, " + label, _mm(mod.get("gamma99")),
                      f"99 % of positions within this (Paper II's Gamma fit, not the largest error); "
                      f"{_mm(nom.get('gamma99'))} before"))
        cards.append(("Largest error, " + label, _mm(mod.get("max")), f"{_mm(nom.get('max'))} before"))
    converged = get(run.metrics, "fit", "converged", default=get(run.fit, "converged"))
    warnings = _all_warnings(run)
    said = (f"{len(warnings)} warning(s) on the data and the model" if warnings else
            "warnings unknown: metrics.json is missing" if isinstance(run.metrics, Missing) else "no warnings")
    cards.append(("Fit", "converged" if converged else ("not converged" if converged is False else "unknown"), said))
    body = "".join(f'<div class="card"><div class="k">{esc(k)}</div><div class="v">{esc(v)}</div>'
                   f'<div class="d">{esc(d)}</div></div>' for k, v, d in cards)
    text = "" if held else not_available("accuracy summary", "metrics.json holds no residual table")
    return f'<div class="cards">{body}</div>{text}'


# ------------------------------------------------------------------ robot and instrument
def _tools(run: RunFiles):
    tools = get(run.config, "tools")
    aligned = get(run.alignment, "tools_mm")
    # alignment.json holds the tools whether or not they were estimated: the flag says which (a listed tool set
    # passes through it unchanged when only the frame was estimated)
    if isinstance(aligned, list) and get(run.alignment, "estimated_tools", default=True) is not False:
        return [(f"tool {i}", ", ".join(f"{v:.3f}" for v in t) + " mm (estimated from the data by the alignment, "
                 "before the fit; its corrections are among the parameters)") for i, t in enumerate(aligned)]
    if isinstance(tools, list):
        return [(f"tool {i}", ", ".join(f"{float(v):g}" for v in t) + " mm (flange frame, from the config; the fit's "
                                                                   "corrections are among the parameters)")
                for i, t in enumerate(tools) if isinstance(t, list)]
    if isinstance(tools, dict) and "count" in tools:
        return [("tools", f"{tools['count']} tools, positions estimated (see alignment)")]
    return []


def instrument(run: RunFiles) -> str:
    if isinstance(run.config, Missing):
        return not_available("robot and instrument", run.config.reason)
    cfg = run.config
    sensor = get(cfg, "sensor", "kind")
    pairs = [("Kind", kind_of(run)), ("Robot / machine description", _robot_source(run)),
             ("Error model", f"{get(cfg, 'model', 'kind', default='joint_dependent')}, Chebyshev order "
                             f"{get(cfg, 'model', 'order')}"
                             + (", backlash" if get(cfg, "model", "backlash") and get(
                                 cfg, "model", "kind", default="joint_dependent") == "joint_dependent" else "")
                             + (", gravity compliance" if get(cfg, "model", "compliance") else "")
                             + (", fine joint tables" if get(cfg, "model", "fine") else ""))]
    orders = get(run.metrics, "orders")
    if orders is not None:
        pairs.append(("Orders identified", ", ".join(str(o) for o in orders) if isinstance(orders, list) else str(orders)))
    if sensor:
        pairs.append(("Instrument", f"laser tracker with a 6-DOF sensor ({sensor}): position and orientation per row"))
        std = get(cfg, "sensor", "pose_std")
        if std and not get(cfg, "sensor", "position_only"):
            pairs.append(("Sensor noise (x, y, z mm; rx, ry, rz deg)", ", ".join(f"{float(s):g}" for s in std)))
        elif sensor == "pose" and not get(cfg, "sensor", "position_only"):
            pairs.append(("Sensor noise", "each row's sx..srz from the file, else torchcal's default (the run log's "
                                          "'pose weights' line)"))
        else:  # STS and position-only rigs weight by Paper III's tracker model, not noise.sigma_m
            pairs.append(("Tracker noise", "Paper III's tracker model (torchcal.measure.TrackerNoise.paper3)"))
        pairs.append(("Sensor mount", str(get(cfg, "sensor", "mount"))))
    else:
        pairs.append(("Instrument", "laser tracker, position targets (one point per tool and pose)"))
        pairs.append(("Tracker noise sigma", f"{get(cfg, 'noise', 'sigma_m')} mm (noise.sigma_m)"))
    fwd, bwd = get(cfg, "noise", "joint_var_fwd"), get(cfg, "noise", "joint_var_bwd")
    if fwd is not None or bwd is not None:
        pairs.append(("Joint variances, forward (deg²)", ", ".join(f"{float(v):.3g}" for v in fwd or [])))
        pairs.append(("Joint variances, backward (deg²)", ", ".join(f"{float(v):.3g}" for v in bwd or [])))
    else:
        pairs.append(("Joint variances", "the robot description's repeatability (see the run log)"))
    pairs.append(("Measurement frame", str(get(cfg, "measurement_frame", default="not recorded"))))
    frame = get(run.alignment, "frame", "xyz_mm") or get(run.frames, "frame_xyz_mm")
    if isinstance(frame, list):
        rpy = get(run.alignment, "frame", "rpy_deg")
        pairs.append(("Robot base in the tracker frame (estimated)", ", ".join(f"{v:.3f}" for v in frame) + " mm"
                      + (", rpy " + ", ".join(f"{v:.4f}" for v in rpy) + " deg" if isinstance(rpy, list) else "")))
    pairs += _tools(run)
    noise_log = [line.split(" INFO ", 1)[1] for line in (run.log if isinstance(run.log, str) else "").splitlines()
                 if " INFO joint variances" in line]
    if noise_log:
        pairs.append(("Noise source (run log)", noise_log[0]))
    return kv(pairs)


# ------------------------------------------------------------------ data
def data_summary(run: RunFiles) -> str:
    sets = get(run.metrics, "sets")
    out = []
    if isinstance(sets, dict) and sets:
        rows = []
        for name, s in sets.items():
            held = "held out (not fitted)" if name == "validation" else ("fitted" if name != "update" else "new rows, fitted")
            poses = get(s, "poses")
            rows.append([name, held, num(get(s, "rows")), num(poses) if poses is not None else num(None)])
        out.append(table(["Set", "Use", "Rows", "Poses"], rows, numeric=(2, 3)))
    else:
        out.append(not_available("data sets", getattr(run.metrics, "reason", "metrics.json holds no 'sets'")))
    excluded = get(run.metrics, "excluded_rows")
    if excluded:
        out.append(f"<p>Rows reported and left out of the fit (outside the sensor's range): {esc(len(excluded))}.</p>")
    elif excluded == []:
        out.append('<p class="ok">No rows were left out.</p>')
    if isinstance(run.data_hashes, dict):
        rows = [[k, get(v, "path", default=""), str(get(v, "sha256", default=""))[:16] + "…"]
                for k, v in run.data_hashes.items()]
        out.append("<h3>Data files</h3>" + table(["Config key", "File", "SHA-256"], rows))
    elif isinstance(run.config, dict):
        data = get(run.config, "data", default={}) or {}
        rows = [[k, v] for k, v in data.items() if k in ("identification", "validation", "truth") and v]
        if rows:
            out.append("<h3>Data files (config.yaml)</h3>" + table(["Config key", "File"], rows))
    if isinstance(run.update, dict):
        u = run.update
        out.append("<h3>Update</h3>" + kv([("Parent run", u.get("parent")), ("New data", u.get("new_data")),
                                          ("Strategy", u.get("strategy")), ("Rows in all / new", f"{u.get('rows')} / "
                                                                            f"{u.get('new_rows')}"),
                                          ("Lineage", " → ".join(str(p) for p in u.get("lineage") or []))]))
    return "".join(out)


def _all_warnings(run: RunFiles) -> list[str]:
    seen, out = set(), []
    flagged = get(run.metrics, "compensation", "flagged")
    extra = [f"{flagged} of {get(run.metrics, 'compensation', 'poses')} validation commands flagged by the "
             "compensation (not converged or outside the joint range; see Compensation)"] if flagged else []
    for w in list(get(run.metrics, "warnings", default=[]) or []) + log_warnings(run.log) + extra:
        if str(w) not in seen:
            seen.add(str(w))
            out.append(str(w))
    return out


def data_checks(run: RunFiles) -> str:
    out = []
    warnings = _all_warnings(run)
    if warnings:
        out.append('<ul class="warnings">' + "".join(f"<li>{esc_lines(w)}</li>" for w in warnings) + "</ul>")
    elif isinstance(run.metrics, Missing):  # the run's warnings live there: their absence says nothing
        out.append(not_available("warnings", f"{run.metrics.reason}; run.log names none"))
    elif not isinstance(run.log, Missing) or not isinstance(run.metrics, Missing):
        out.append('<p class="ok">No warnings: the run raised none on the data or the model.</p>')
    checks = get(run.metrics, "data_checks")
    if not isinstance(checks, dict):
        out.append(not_available("data checks", "metrics.json holds no 'data_checks' (sensor and update runs, "
                                 "or a run that stopped before the checks)"))
        return "".join(out)
    names = lambda xs: ", ".join(str(x.get("name", x)) if isinstance(x, dict) else str(x) for x in xs) or "none"  # noqa: E731
    out.append(kv([
        ("Parameters / equations", f"{checks.get('parameters')} / {checks.get('equations')}"),
        ("Tools never measured", names(checks.get("unobserved_tools") or [])),
        ("Parameters the data cannot determine", names(checks.get("undetermined") or [])),
        ("Barely determined combinations", names(checks.get("barely_determined") or [])),
        ("Joints approached from one side only", names(checks.get("one_sided_backlash") or [])),
    ]))
    joints = get(checks, "confounding", "joints")
    if isinstance(joints, list) and joints:
        rows = [[j.get("joint"), num(j.get("rows")), num(j.get("corr"), 3), num(j.get("r2"), 3),
                 num(j.get("plus_fraction"), 3), num(j.get("one_sided_bins")), num(j.get("backlash_vif"), 2)]
                for j in joints if isinstance(j, dict)]
        out.append("<h3>Approach direction against position (backlash confounding)</h3>"
                   + table(["Joint", "Rows", "corr", "R²", "share +", "one-sided bins", "backlash VIF"], rows,
                           numeric=(1, 2, 3, 4, 5, 6))
                   + '<p class="note">R² near 1: the approach direction follows the position, so backlash and '
                     "position-dependent errors cannot be told apart; VIF: variance inflation of the backlash "
                     "constant.</p>")
    return "".join(out)


# ------------------------------------------------------------------ accuracy
def accuracy(run: RunFiles) -> str:
    rows6 = get(run.metrics, "table6")
    if not isinstance(rows6, list) or not rows6:
        return not_available("accuracy table", getattr(run.metrics, "reason", "metrics.json holds no 'table6'"))
    rows7 = [r for r in get(run.metrics, "table7", default=[]) or [] if str(r.get("residual")) == "Compensated"]
    res = run.residuals if not isinstance(run.residuals, Missing) else None
    body = []
    for r in list(rows6) + rows7:
        if not isinstance(r, dict):
            continue
        set_name, kind = str(r.get("set")), str(r.get("residual"))
        key = f"{set_name.lower()}.{kind.lower().replace(' ', '_')}"
        which = "nominal" if kind == "Nominal" else ("modeled" if kind == "Modeled" else None)
        rms = res.rms(set_name, which) if (res and which) else None
        cells = [f"{set_name}{' (held out)' if set_name == 'Validation' else ''}",
                 "Compensated (measured)" if kind == "Compensated" else kind.replace("Modeled", "Calibrated"),
                 num(r.get("count"))]
        for k in STAT_KEYS:
            cells.append(num(r.get(k), key=f"{key}.{k}"))
            if k == "mean":
                cells.append(num(rms, key=f"{key}.rms" if rms is not None else None))
        cells += [num(r.get("mean_decrease"), 1, " %"), num(r.get("gamma99_decrease"), 1, " %")]
        body.append(("after" if kind != "Nominal" and not kind.startswith("Nominal") else "", cells))
    units = get(run.metrics, "units", default="mm, percent")
    html = table(["Set", "Residual", "Rows", "Mean", "RMS", "Max", "Gamma 99 %", "Mean decrease",
                  "Gamma 99 % decrease"], body,
                 cls="wide", numeric=(2, 3, 4, 5, 6, 7, 8))
    note = (f'<p class="note">Units: {esc(units)} (angles in degrees). Nominal: the robot as described, before '
            "calibration; Calibrated: the identified model's residual; Compensated: commands corrected by the model "
            "and measured again (every row, with its commands and flags, in compensation.csv). Gamma 99 %: the 99 % quantile of a Gamma law fitted to the residuals (Paper II, "
            "Figure 13). Decrease: percent against the nominal residual of the same set. "
            + ("RMS from residuals.csv." if res else "RMS: not available (no residuals.csv in this run).") + "</p>")
    return html + note + iso9283(run)


def iso9283(run: RunFiles) -> str:
    """ISO 9283 positional accuracy AP / repeatability RP apply only to repeated cycles to one commanded pose."""
    res = run.residuals
    if isinstance(res, Missing):
        return ""
    rows = sum(len(v) for v in res.modeled.values())
    return ("<h3>ISO 9283 positional accuracy</h3>"
            f'<p class="na">Not applicable to this run: ISO 9283 accuracy AP and repeatability RP need n &ge; 2 '
            f"cycles to the same commanded pose, and this run measured each pose once ({rows} rows in "
            "residuals.csv; only the residual magnitude per row is stored). Per pose, the distance between "
            "commanded and attained position is the residual above (its mean and maximum).</p>")


def distributions(run: RunFiles) -> str:
    res = run.residuals
    if isinstance(res, Missing):
        return not_available("residual histograms", res.reason)
    out = []
    for name in res.modeled:
        stats = {r.get("residual"): r for r in get(run.metrics, "table6", default=[]) or []
                 if isinstance(r, dict) and str(r.get("set")).lower() == name}
        for which, values, color in (("Nominal", res.nominal[name], "#8a96a6"), ("Modeled", res.modeled[name], "#1f5f99")):
            g = get(stats, which, "gamma99")
            label = "before calibration" if which == "Nominal" else "after calibration"
            out.append(histogram_svg(values, f"{name}, {label}", marks=[("Gamma 99 %", g)] if g else (), color=color))
    return f'<div class="hists">{"".join(out)}</div>'


def plots(run: RunFiles) -> str:
    if not run.plots:
        reason = ("no plots/ folder in the run directory" if not (run.folder / "plots").is_dir()
                  else "plots/ holds no PNG")
        return not_available("plots", reason + "; sensor and update runs and runs with plots: false draw none")
    return "".join(image(path, caption) for caption, path in run.plots)


__all__ = ["accuracy", "data_checks", "data_summary", "distributions", "instrument", "iso9283", "kind_of", "plots",
           "summary", "title_block"]
