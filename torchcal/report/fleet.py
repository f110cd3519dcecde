"""The fleet report: one self-contained HTML page for a ``torchcal fleet`` run directory.

What a plant keeps of a fleet's calibration: how many units were measured,
fitted and failed (and why), each unit's accuracy, which units lie far from
the fleet and on which joint (a damaged gearbox, a bad measurement), with the
fleet's own distribution of every joint feature behind each finding, the
warnings on the data, and the exact versions and config. Written from the run
directory's files alone (``fleet.json``, ``features.csv``, ``config.yaml``,
``versions.json``, ``run.log``), with the single-run report's page, tables and
figures (:mod:`torchcal.report.html`); a file the run lacks makes its section
say "not available", never an error.
"""

from __future__ import annotations

import csv
import math
import statistics
from pathlib import Path

from .html import esc, esc_lines, histogram_svg, kv, not_available, num, page, section, strip_svg, table
from .model_sections import appendix
from .rundata import Missing, _json, _text, _yaml, get, log_warnings

FLEET_FILE = "fleet.json"
"""The file that makes a run directory a fleet's (``torchcal fleet`` writes it last)."""

# 'angle error': the same feature in the features.csv of runs before it was named 'transmission error'
FEATURE_TITLES = {"transmission error": "Transmission error (RMS over the joint's range, about its own axis)",
                  "angle error": "Transmission error (RMS over the joint's range, about its own axis)",
                  "backlash": "Backlash (half the difference between the two approach directions)"}


def is_fleet_run(run_dir) -> bool:
    """A ``torchcal fleet`` run directory: its fleet.json, or, where the run stopped before writing it, a
    config whose identification data are a folder and no model of its own (a fit's run has model.pt)."""
    folder = Path(run_dir)
    if (folder / FLEET_FILE).is_file():
        return True
    if (folder / "model.pt").is_file() or not (folder / "config.yaml").is_file():
        return False
    ident = get(_yaml(_text(folder / "config.yaml")), "data", "identification", default=None)
    return isinstance(ident, str) and Path(ident).is_dir()


def _csv_rows(path: Path, need: set, numbers: tuple, flag: str, absent: str):
    """A table the run wrote (features.csv, changes.csv) -> list of rows, the ``numbers`` columns present parsed
    as floats and ``flag`` a bool (False where absent), or Missing (``absent``: why the file may not be there)."""
    if not path.is_file():
        return Missing(f"{path.name} not in the run directory ({absent})")
    rows = []
    try:
        with path.open(newline="", encoding="utf-8") as f:
            reader = csv.DictReader(f)
            if not need <= set(reader.fieldnames or ()):
                return Missing(f"{path.name} lacks the columns {sorted(need - set(reader.fieldnames or ()))}")
            for line, row in enumerate(reader, start=2):
                try:
                    for k in numbers:
                        if k in row:
                            row[k] = float(row[k])
                except (TypeError, ValueError):
                    return Missing(f"{path.name}, row {line}: a value that is not a number")
                row[flag] = str(row.get(flag, "")).strip().lower() == "true"
                rows.append(row)
    except (OSError, UnicodeDecodeError, csv.Error) as exc:
        return Missing(f"{path.name} is not readable ({type(exc).__name__}: {exc})")
    return rows


def _features(path: Path):
    """features.csv -> list of rows (floats parsed, 'flagged' a bool), or Missing."""
    return _csv_rows(path, {"unit", "joint", "feature", "value", "value_unit", "fleet_median", "robust_z",
                            "flag_level", "flagged"}, ("value", "fleet_median", "ratio", "robust_z", "flag_level"),
                     "flagged", "fewer than 3 units with data enough to judge, or a run before torchcal wrote it")


def _strip_charts(rows: list, value: str, hot, titles: dict) -> list[str]:
    """One strip chart per feature of ``rows`` (features.csv's or changes.csv's), a column per joint, a dot per
    unit (its ``value``, red where ``hot(row)``), the fleet's median and flag level drawn."""
    out = []
    for feature in dict.fromkeys(r["feature"] for r in rows):
        mine = [r for r in rows if r["feature"] == feature]
        groups = []
        for joint in dict.fromkeys(r["joint"] for r in mine):
            pts = [r for r in mine if r["joint"] == joint]
            groups.append((joint, [(r["unit"], r[value], hot(r)) for r in pts], pts[0].get("fleet_median"),
                           pts[0].get("flag_level")))
        unit_names = sorted({r["value_unit"] for r in mine})
        out.append(strip_svg(groups, titles.get(feature, feature), f"{feature} ({', '.join(unit_names)})"))
    return out


def _float(x):
    try:
        v = float(x)
    except (TypeError, ValueError):
        return None
    return v if math.isfinite(v) else None


def _median(xs):
    """The median of the values that are there (None where none is)."""
    xs = [x for x in xs if x is not None]
    return statistics.median(xs) if xs else None


class FleetFiles:
    """The files of a fleet run directory the report shows, each its content or a :class:`Missing`."""

    def __init__(self, folder: Path):
        self.folder = folder.resolve()
        self.fleet = _json(folder / FLEET_FILE)
        self.config_text = _text(folder / "config.yaml")
        self.config = _yaml(self.config_text)
        self.versions = _json(folder / "versions.json")
        self.log = _text(folder / "run.log")
        self.partial = (folder / "PARTIAL").exists()  # interrupted or failed: the units are those done by then
        self.features = _features(folder / "features.csv")
        units = get(self.fleet, "units", default=[])
        self.units = [u for u in units if isinstance(u, dict)] if isinstance(units, list) else []


def _title(run: FleetFiles) -> str:
    robot = get(run.config, "robot", default="unknown")
    created = get(run.versions, "created", default="date not recorded")
    version = get(run.versions, "torchcal", default="unknown")
    return (f'<header class="title"><h1>Fleet calibration report &mdash; {esc(robot)}</h1>'
            f'<div class="sub">{len(run.units)} units &middot; run <b>{esc(run.folder.name)}</b> &middot; '
            f'{esc(created)} &middot; torchcal {esc(version)}</div><div class="note">{esc(run.folder)}</div></header>')


def _summary(run: FleetFiles) -> str:
    if isinstance(run.fleet, Missing):
        return not_available("fleet summary", run.fleet.reason)
    fitted = [u for u in run.units if u.get("status") == "fitted"]
    failed = [u for u in run.units if u.get("status") == "failed"]
    flagged = [u for u in fitted if u.get("flagged")]
    reused = [u for u in fitted if u.get("reused_from")]
    cards = [("Units", f"{len(run.units)}", f"{len(fitted)} fitted, {len(failed)} failed"
              + (f", {len(reused)} of them taken from {reused[0]['reused_from']} (fleet.reuse)" if reused else "")
              + ("; the run did not finish (PARTIAL): interrupted or failed" if run.partial else "")),
             ("Flagged", f"{len(flagged)}", ", ".join(str(u.get("unit")) for u in flagged) or "no unit lies far from "
              "the fleet")]
    if get(run.fleet, "baseline", default=None):
        changed = [u for u in fitted if u.get("changed")]
        cards.append(("Changed", f"{len(changed)}", ", ".join(str(u.get("unit")) for u in changed) or
                      "no unit changed far beyond the fleet since the baseline"))
    ident = _median(_float(u.get("identification_mean_mm")) for u in fitted)
    if ident is not None:
        cards.append(("Identification residual", f"{ident:.4f} mm", "median over the units of each unit's mean"))
    val = _median(_float(u.get("validation_mean_mm")) for u in fitted)
    if val is not None:
        cards.append(("Held-out residual", f"{val:.4f} mm", "median over the units of each unit's validation mean"))
    t, ts = _float(get(run.fleet, "time_s")), _float(get(run.fleet, "solve_time_s"))
    if t is not None:
        cards.append(("Time", f"{t:.1f} s", f"batched solves {ts:.1f} s; engine {get(run.fleet, 'engine', default='?')}, "
                      f"{get(run.fleet, 'cell', default='?')} units a solve" if ts is not None else ""))
    body = "".join(f'<div class="card"><div class="k">{esc(k)}</div><div class="v">{esc(v)}</div>'
                   f'<div class="d">{esc(d)}</div></div>' for k, v, d in cards)
    return f'<div class="cards">{body}</div>'


def _flagged(run: FleetFiles) -> str:
    intro = ("<p>A unit is flagged where one of its joints' features lies far above the fleet's: a robust z-score "
             f"(median and MAD of the fleet) above {esc(get(run.fleet, 'threshold', default='the threshold'))} and "
             f"at least {esc(get(run.fleet, 'min_ratio', default='3'))} times the fleet median. One-sided: damage and "
             "bad measurements add error. Check the gearbox of the named joint, or remeasure the unit.</p>")
    if isinstance(run.features, Missing):
        findings = get(run.fleet, "findings", default=[]) or []
        if findings:
            return intro + "<ul>" + "".join(f"<li>{esc(f)}</li>" for f in findings) + "</ul>" + \
                not_available("the fleet's feature values", run.features.reason)
        return not_available("outlier judgement", run.features.reason)
    hot = sorted((r for r in run.features if r["flagged"]), key=lambda r: -r["robust_z"])
    if not hot:
        return intro + '<p class="ok">No unit lies far from the fleet on any joint.</p>'
    rows = [[r["unit"], r["joint"], r["feature"], num(r["value"], 4, "", key=f"{r['unit']}/{r['joint']}/{r['feature']}"),
             r["value_unit"], num(r["fleet_median"], 4), num(r.get("ratio"), 1), num(r["robust_z"], 1)] for r in hot]
    return intro + table(["unit", "joint", "feature", "value", "unit of value", "fleet median", "x median",
                          "robust z"], rows, numeric=(3, 5, 6, 7))


def _changes(run: FleetFiles) -> str:
    """fleet.baseline: what changed since the earlier run (torchcal.identify.fleet_change)."""
    base = get(run.fleet, "baseline", default=None)
    compared = [u for u in run.units if _float(u.get("change_rms_mm")) is not None]
    intro = (f"<p>Each unit fitted in both runs compared with its calibration in <b>{esc(base)}</b>: the distance "
             "between the points its earlier and its new model predict at its new commands (each with its own tool "
             "vectors, after the best rigid alignment: the tracker stands elsewhere in each campaign). A unit is "
             "changed where that lies far above the fleet's own changes (robust z above "
             f"{esc(get(run.fleet, 'threshold', default='the threshold'))}, at least "
             f"{esc(get(run.fleet, 'change_min_ratio', default='1.5'))} times the fleet's median), or beyond the "
             "fleet's scatter (z alone) where one joint's transmission error changed far beyond the fleet's; the "
             "joints named are those whose transmission error or backlash changed far beyond the fleet's. Check "
             "the named joint's gearbox, or the unit's mastering and links where none is named.</p>")
    if not compared:
        return intro + not_available("changes", "no unit of this run was fitted in the baseline run")
    med = _median(_float(u.get("change_rms_mm")) for u in compared)
    found = get(run.fleet, "changes", default=[]) or []
    body = (f'<p>{len(compared)} units compared; the fleet\'s median change at the tool <b>{med:.4f} mm</b> RMS '
            "(the season, the targets' mounting and the calibrations' own scatter).</p>")
    body += ("<ul>" + "".join(f"<li>{esc(f)}</li>" for f in found) + "</ul>" if found else
             '<p class="ok">No unit changed far beyond the fleet.</p>')
    hist = histogram_svg([_float(u.get("change_rms_mm")) for u in compared], "Change at the tool per unit (RMS)",
                         bins=30, xlabel="change since the baseline (mm)", counted="units")
    return intro + body + f'<div class="hists">{hist}</div>' + _change_strips(run, compared)


CHANGE_TITLES = {"tool change": "Change at the tool since the baseline (RMS over the unit's commands)",
                 "transmission error change": "Transmission error change per joint (RMS over the range, mean left out)",
                 "backlash change": "Backlash change per joint (mean over the range)"}


def _change_strips(run: FleetFiles, compared: list) -> str:
    """changes.csv as strip charts: a dot per unit, the fleet's median and the level beyond which a change lies;
    red: the changed units' changes beyond the fleet's."""
    rows = _csv_rows(run.folder / "changes.csv", {"unit", "joint", "feature", "change", "value_unit"},
                     ("change", "fleet_median", "ratio", "robust_z", "flag_level"), "beyond",
                     "a run before torchcal wrote it")
    if isinstance(rows, Missing):
        return not_available("the fleet's changes per joint", rows.reason)
    changed = {str(u.get("unit")) for u in compared if u.get("changed")}
    intro = ("<p>Each dot is one unit's change; the grey bar is the fleet's median change, the dashed red bar the "
             "level beyond which a change lies far from the fleet's; the changed units' changes beyond it are red "
             "and named.</p>")
    return intro + "".join(_strip_charts(rows, "change", lambda r: r["unit"] in changed and r["beyond"],
                                         CHANGE_TITLES))


def _distributions(run: FleetFiles) -> str:
    if isinstance(run.features, Missing):
        return not_available("the fleet's joint features", run.features.reason)
    intro = ("<p>Each dot is one unit's feature of one joint; the grey bar is the fleet median, the dashed red bar the "
             "level above which a unit is flagged; flagged units are red and named.</p>")
    return intro + "".join(_strip_charts(run.features, "value", lambda r: r["flagged"], FEATURE_TITLES))


def _accuracy(run: FleetFiles) -> str:
    fitted = [u for u in run.units if u.get("status") == "fitted"]
    if not fitted:
        return not_available("accuracy per unit", "no unit was fitted")
    hists = [histogram_svg([_float(u.get("identification_mean_mm")) or float("nan") for u in fitted],
                           "Identification residual per unit (mean)", bins=30, xlabel="mean residual (mm)",
                           counted="units")]
    val = [_float(u.get("validation_mean_mm")) for u in fitted]
    if any(v is not None for v in val):
        hists.append(histogram_svg([v if v is not None else float("nan") for v in val],
                                   "Held-out residual per unit (mean)", bins=30, xlabel="mean residual (mm)",
                                   counted="units", color="#1d6b3a"))
    else:
        hists.append(not_available("held-out accuracy", "no data.validation folder in the fleet's config"))
    return f'<div class="hists">{"".join(hists)}</div>'


def _units(run: FleetFiles) -> str:
    if not run.units:
        return not_available("units", get(run.fleet, "reason", default="fleet.json holds no units")
                             if not isinstance(run.fleet, Missing) else run.fleet.reason)
    has_val = any(_float(u.get("validation_mean_mm")) is not None for u in run.units)
    header = ["unit", "status", "rows", "converged", "iterations", "identification mean (mm)", "identification max (mm)"]
    if has_val:
        header += ["validation mean (mm)", "validation max (mm)"]
    has_change = any(_float(u.get("change_rms_mm")) is not None for u in run.units)
    if has_change:
        header += ["change at the tool (mm)"]
    header += ["outlier score", "findings / reason"]
    rows = []
    for u in run.units:
        name = str(u.get("unit"))
        r = [name, u.get("status", "?"), num(u.get("rows")), "yes" if u.get("converged") else
             ("no" if u.get("converged") is False else ""), num(u.get("iterations")),
             num(_float(u.get("identification_mean_mm")), 4, key=f"{name}/identification_mean_mm"),
             num(_float(u.get("identification_max_mm")), 4, key=f"{name}/identification_max_mm")]
        if has_val:
            r += [num(_float(u.get("validation_mean_mm")), 4, key=f"{name}/validation_mean_mm"),
                  num(_float(u.get("validation_max_mm")), 4, key=f"{name}/validation_max_mm")]
        if has_change:
            r += [num(_float(u.get("change_rms_mm")), 4, key=f"{name}/change_rms_mm")]
        r += [num(_float(u.get("outlier_score")), 1),
              "; ".join(x for x in (u.get("findings"), u.get("change") if u.get("changed") else None) if x)
              or u.get("reason") or ""]
        css = "after" if u.get("flagged") or u.get("changed") else ""
        rows.append((css, r) if css else r)
    numeric = tuple(i for i, h in enumerate(header) if h not in ("unit", "status", "converged", "findings / reason"))
    return table(header, rows, cls="wide", numeric=numeric)


def _warnings(run: FleetFiles) -> str:
    if isinstance(run.log, Missing):
        return not_available("warnings", run.log.reason)
    found = [w for w in log_warnings(run.log) if not w.startswith("flagged: ")]  # the findings have their section
    if not found:
        return '<p class="ok">No warnings: the run raised none on the data or the config.</p>'
    return '<ul class="warnings">' + "".join(f"<li>{esc_lines(w)}</li>" for w in found) + "</ul>"


def _appendix(run: FleetFiles) -> str:
    return appendix(run) + kv([("Each unit's own run", "units/<name>/: config.yaml (a torchcal fit of it refits the "
                                "unit alone), model.pt, metrics.json")])


def render_fleet_report(run_dir) -> str:
    """The fleet report of ``run_dir`` (a ``torchcal fleet`` run directory) as an HTML string."""
    run = FleetFiles(Path(run_dir))
    robot = get(run.config, "robot", default=run.folder.name)
    parts = [
        section("summary", "Summary", _summary(run), major=True, first=True),
        section("flagged", "Units far from the fleet", _flagged(run)),
        *([section("changes", "Changed since the baseline", _changes(run))]
          if get(run.fleet, "baseline", default=None) else []),
        section("features", "The fleet's joints", _distributions(run), major=True),
        section("accuracy", "Accuracy per unit", _accuracy(run)),
        section("units", "Every unit", _units(run), major=True),
        section("warnings", "Warnings on the data and the config", _warnings(run)),
        section("versions", "Versions and configuration", _appendix(run), major=True),
    ]
    footer = (f"Written by torchcal from the files of {esc(run.folder)}; this page is self-contained "
              "(no network, no script).")
    return page(f"Fleet calibration report — {robot} — {run.folder.name}", _title(run), parts, footer)


__all__ = ["FLEET_FILE", "is_fleet_run", "render_fleet_report"]
