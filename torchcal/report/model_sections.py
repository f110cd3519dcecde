"""Report sections about the identified model: parameters, solver, compensation, constraint, versions and config.

Split from :mod:`torchcal.report.sections` because these read the model
itself (``model.pt``, through :func:`torchcal.io.rundir.load_model`, the only
section that loads torch) and the solver's files rather than the residual
statistics. Parameter values are shown in mm and degrees (converted with
:mod:`torchcal.core.units`); each free parameter's uncertainty (Laplace 1 σ at
the solution, :mod:`torchcal.analysis.identifiability`) comes from the run's
``parameters.csv``, which the fit writes with its data checks; a run without it
says so instead of inventing one.
"""

from __future__ import annotations

import math

from .html import esc, kv, not_available, num, table
from .rundata import Missing, RunFiles, get

FULL_LIST_INLINE = 40
"""Parameter groups with at most this many entries are listed in full; larger ones collapse into a details box."""


def _display(values, kinds, names=None):
    """SI values and kinds [and entry names] -> (values in mm / deg / 1, unit names: per N·m for a compliance per
    torque, :func:`torchcal.core.units.entry_unit`)."""
    from ..core import units

    out, unit = [], []
    for v, k, n in zip(values, kinds, names if names is not None else [""] * len(values)):
        if k == "angle":
            out.append(units.rad_to_deg(v)), unit.append(units.entry_unit(k, n))
        elif k == "length":
            out.append(units.m_to_mm(v)), unit.append(units.entry_unit(k, n))
        else:
            out.append(v), unit.append("")
    return out, unit


def _rms(xs) -> float:
    return math.sqrt(math.fsum(x * x for x in xs) / len(xs)) if xs else float("nan")


def _group_entries(model, group):
    """[(name, value SI, kind, prior sigma SI)] of the entries of ``group`` that exist (its mask), row-major."""
    params = dict(model.named_parameters())
    p = params.get(group.name)
    if p is None:
        return []
    values = p.detach().reshape(-1).tolist()
    mask = group.mask.reshape(-1).tolist()
    sigma = group.prior_sigma.reshape(-1).tolist()
    return [(n, v, k, s) for n, v, k, s, m in zip(group.entry_names, values, group.kinds, sigma, mask) if m]


def _constant_terms(entries) -> str:
    """The order-0 terms of a joint group as a joint x term table (the constant, DH-like offsets)."""
    cells: dict[str, dict[str, tuple]] = {}
    terms: list[str] = []
    for name, v, kind, _ in entries:
        parts = name.split(".")
        if len(parts) == 3 and parts[2] == "c0":
            cells.setdefault(parts[0], {})[parts[1]] = (v, kind)
            if parts[1] not in terms:
                terms.append(parts[1])
    if not cells:
        return ""
    header = ["Joint"] + [f"{t} ({'deg' if t.startswith('eps') else 'mm'})" for t in terms]
    rows = []
    for joint, row in cells.items():
        line = [joint]
        for t in terms:
            if t in row:
                (v,), _ = _display([row[t][0]], [row[t][1]])
                line.append(num(v, 5))
            else:
                line.append(num(None))
        rows.append(line)
    return ("<h3>Constant error terms per joint (order 0: the DH-like offsets)</h3>"
            + table(header, rows, numeric=tuple(range(1, len(header)))))


def parameters(run: RunFiles) -> str:
    if not (run.folder / "model.pt").is_file():
        return not_available("identified parameters", "model.pt not in the run directory")
    from ..io.rundir import load_model

    try:
        model = load_model(run.folder)
        groups = model.parameter_groups()
    except Exception as exc:  # noqa: BLE001 - a report of a broken or foreign model.pt says why, it does not stop
        return not_available("identified parameters", f"model.pt could not be loaded: {type(exc).__name__}: {exc}")
    pinned = set(get(run.fit, "pinned_names", default=[]) or [])
    summary_rows, blocks, n_total = [], [], 0
    for g in groups:
        entries = _group_entries(model, g)
        if not entries:
            continue
        n_total += len(entries)
        by_kind: dict[str, list[float]] = {}
        for _, v, kind, _ in entries:
            by_kind.setdefault(kind, []).append(v)
        for kind, vals in by_kind.items():
            first = next(n for n, _, k, _ in entries if k == kind)  # a group's entries share their unit
            shown, unit = _display(vals, [kind] * len(vals), [first] * len(vals))
            summary_rows.append([g.name, g.role, f"{kind} ({unit[0] or '1'})", num(len(vals)),
                                 num(sum(1 for n, _, k, _ in entries if k == kind and n in pinned)),
                                 num(max(abs(x) for x in shown), 5), num(_rms(shown), 5)])
        shown, unit = _display([e[1] for e in entries], [e[2] for e in entries], [e[0] for e in entries])
        sig, _ = _display([e[3] for e in entries], [e[2] for e in entries])
        std = run.uncertainty if isinstance(run.uncertainty, dict) else {}
        rows = [[n, num(v, 6), num(f"{std[n]:.2g}" if n in std else None), u, num(s, 6), "pinned (gauge)" if n in pinned else ""]
                for (n, _, _, _), v, u, s in zip(entries, shown, unit, sig)]
        listing = table(["Parameter", "Value", "σ (1 std)", "Unit", "Prior σ", "Gauge"], rows, numeric=(1, 2, 4))
        if g.role == "joint":
            blocks.append(_constant_terms(entries))
        if len(entries) <= FULL_LIST_INLINE:
            blocks.append(f"<h3>{esc(g.name)} ({esc(g.role)})</h3>{listing}")
        else:
            blocks.append(f"<details><summary>All {len(entries)} entries of {esc(g.name)} ({esc(g.role)})</summary>"
                          f"{listing}</details>")
    head = table(["Group", "Role", "Kind (unit)", "Entries", "Pinned", "Largest |value|", "RMS value"],
                 summary_rows, numeric=(3, 4, 5, 6))
    note = (f'<p class="note">{n_total} identified parameters; pinned entries are fixed by the gauge (redundant '
            "with others, Paper II (18)). " + (
                "σ: each free parameter's standard deviation at the solution (Laplace approximation: the "
                "identification data's information plus the prior, joint errors marginalized; "
                "<code>torchcal.analysis.identifiability</code>, file parameters.csv). "
                if isinstance(run.uncertainty, dict) else
                f"Uncertainty: not available ({esc(run.uncertainty.reason)}). ")
            + "What the data could not determine is listed under Data checks.</p>")
    return note + head + "".join(blocks)


def solver(run: RunFiles) -> str:
    if isinstance(run.fit, Missing) and not isinstance(run.metrics, dict):
        return not_available("solver result", run.fit.reason)
    f = run.fit if isinstance(run.fit, dict) else {}
    pairs = [("Method", f.get("method", "lm")), ("Result", f.get("message", get(run.metrics, "fit", "converged"))),
             ("Iterations", f.get("iterations", get(run.metrics, "fit", "iterations"))),
             ("Cost (whitened residual, ½ sum of squares)", _g(f.get("cost", get(run.metrics, "fit", "cost")))),
             ("Time (s)", None if f.get("time_s") is None else f"{f['time_s']:.2f}"),
             ("Parameters / pinned by the gauge", f"{f.get('parameters')} / {f.get('pinned')}" if f else None),
             ("Joint errors eliminated (rows × joints)", f.get("joint_errors")),
             ("Order selection", get(run.metrics, "order_selection") or "fixed orders (config)"),
             ("Prior from a fleet", _fleet_prior(f.get("fleet_prior"), get(run.metrics, "fleet_prior")))]
    out = kv([(k, v) for k, v in pairs if v is not None])
    if isinstance(run.orders, dict):
        out += (f"<details><summary>Order selection record (orders.json)</summary><pre>"
                f"{esc(_short_json(run.orders))}</pre></details>")
    return out


def _fleet_prior(rec, comparison=None) -> str | None:
    """fit.json's ``fleet_prior`` (``prior.fleet``) as one line: a unit fitted with few poses owes part of its
    model to the fleet, and the report says which fleet, and (metrics.json's ``fleet_prior``) what the same data
    gave fitted alone."""
    if not isinstance(rec, dict):
        return None
    left = rec.get("left_out") or []
    line = (f"{rec.get('fleet')}: {rec.get('units')} units ({rec.get('method')} covariance, {rec.get('entries')} "
            f"entries); left out: {', '.join(map(str, left)) if left else 'none'}")
    if isinstance(comparison, dict):
        alone, mine = comparison.get("alone") or {}, comparison.get("with_prior") or {}
        key = "validation" if "validation" in alone else "identification"
        a, w = alone.get(key) or {}, mine.get(key) or {}
        if "mean" in a and "mean" in w:
            line += (f". The same data fitted alone, without the fleet: {key} mean {a['mean']:.4f} mm, max "
                     f"{a['max']:.4f} mm; with the fleet's prior {w['mean']:.4f} mm, max {w['max']:.4f} mm")
            if key == "identification":
                line += " (on the identification poses: no validation set)"
    return line


def _g(value):
    return f"{value:.6g}" if isinstance(value, float) else value


def _short_json(obj, limit: int = 20000) -> str:
    import json

    text = json.dumps(obj, indent=1)
    return text if len(text) <= limit else text[:limit] + f"\n... ({len(text) - limit} more characters in the file)"


def compensation(run: RunFiles) -> str:
    comp = get(run.metrics, "compensation")
    out = []
    if isinstance(comp, dict):
        rows = []
        for label, key in (("all validation commands", "compensated"), ("commands not flagged", "compensated_unflagged")):
            s = comp.get(key)
            if isinstance(s, dict):
                rows.append([label, num(s.get("count")), num(s.get("mean"), key=f"compensation.{key}.mean"),
                             num(s.get("max"), key=f"compensation.{key}.max"),
                             num(s.get("gamma99"), key=f"compensation.{key}.gamma99")])
        out.append(kv([("Commands compensated", comp.get("poses")), ("Converged", comp.get("converged")),
                       ("Within the joint range", comp.get("within_limits")),
                       ("Flagged (not converged or outside the range; never dropped)", comp.get("flagged")),
                       ("Approached in directions the data never covered", comp.get("direction_outside")),
                       ("Needed the damped fallback", comp.get("damped"))]))
        out.append(table(["Compensated commands, measured", "Rows", "Mean (mm)", "Max (mm)", "Gamma 99 % (mm)"], rows,
                         numeric=(1, 2, 3, 4)))
        out.append('<p class="note">Measured on the simulated robot the data came from (the run had a truth).</p>')
    else:
        out.append(not_available("compensation check", "it needs a simulated truth (data.truth) to measure compensated "
                                 "commands on; compensate real programs with 'torchcal compensate RUN_DIR' and, for "
                                 "machine tools, export controller tables with 'torchcal export-tables'"))
    c = get(run.metrics, "constraint") or (run.constraint if isinstance(run.constraint, dict) else None)
    if isinstance(c, dict):
        out.append("<h3>Slope constraint (Paper I)</h3>" + kv([
            ("Bound c", f"{c.get('c'):.4g} {c.get('units', 'mm')}" if isinstance(c.get("c"), (int, float)) else c.get("c")),
            ("Chosen", c.get("mode")), ("BORDER axes", ", ".join(map(str, c.get("border_axes") or []))),
            ("Boundary rows", c.get("boundary_rows"))]))
        sweep = [s for s in c.get("sweep") or [] if isinstance(s, dict)]
        if sweep:
            rows = [["unconstrained" if s.get("c_mm") is None else num(s.get("c_mm"), 3), num(s.get("sub_mean_mm")),
                     num(s.get("sub_max_mm")), num(s.get("boundary_mean_mm")), num(s.get("boundary_max_mm")),
                     num(s.get("max_slope_mm"), 3)] for s in sweep]
            out.append(table(["c (mm)", "Interior mean", "Interior max", "Boundary mean", "Boundary max",
                              "Largest slope"], rows, numeric=(1, 2, 3, 4, 5))
                       + '<p class="note">mm; the constraint sweep (Paper I, Figure 14): residuals inside the data '
                         "and on its boundary (BORDER rows held out) for each bound.</p>")
    return "".join(out)


def versions(run: RunFiles) -> str:
    if not isinstance(run.versions, dict):
        return not_available("versions", run.versions.reason)
    pairs = []
    for k, v in run.versions.items():
        if isinstance(v, dict):
            v = ", ".join(f"{a}: {b}" for a, b in v.items())
        pairs.append((k, "not installed" if v is None else v))
    pairs.append(("page rendered by", _renderer(run.versions)))
    return kv(pairs)


def _renderer(recorded: dict) -> str:
    """Which code rendered this page, and whether it is the run's: `torchcal report RUN_DIR` renders an archived
    run again with whatever is installed now, and the page showed only the run's versions."""
    from datetime import datetime

    from ..io.provenance import source_sha256

    now = source_sha256()
    ran = recorded.get("torchcal_source_sha256")
    same = ("the code that ran the fit" if ran == now else "other code than the run's" if ran else
            "code the run did not record")
    return f"torchcal source sha256 {now[:12]}... ({same}), {datetime.now().astimezone().isoformat(timespec='seconds')}"


def appendix(run: RunFiles) -> str:
    out = [versions(run)]
    for title, text in (("Full configuration (config.yaml)", run.config_text), ("Run log (run.log)", run.log)):
        if isinstance(text, Missing):
            out.append(not_available(title, text.reason))
        else:
            out.append(f"<details><summary>{esc(title)}</summary><pre>{esc(text)}</pre></details>")
    return "".join(out)


__all__ = ["appendix", "compensation", "parameters", "solver", "versions"]
