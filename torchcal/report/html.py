"""HTML building blocks of the calibration report: escaping, tables, embedded images, SVG histograms, the page.

The report must open offline, years later, on a customer's machine and print
to PDF cleanly, so the page is one file with nothing outside it: inline CSS
(``@media print`` rules keep tables and figures whole and start each major
section on a new page), images as base64 ``data:`` URIs, histograms as inline
SVG, no script and no external URL. Every string that comes from a file of the
run directory goes through :func:`esc`; numbers go through :func:`num`, which
also records the exact value in a ``data-value`` attribute so tools (and the
tests) can read the figures back without parsing the rounded text.
"""

from __future__ import annotations

import base64
import html
import io
import math
from pathlib import Path

MAX_IMAGE_BYTES = 700_000
"""A PNG larger than this is re-encoded smaller (PIL, halved until it fits); plots torchcal writes are ~50-350 kB."""

CSS = """
:root { --ink:#1d2733; --muted:#5b6776; --rule:#d5dbe3; --band:#f3f6f9; --accent:#1f5f99; --warn:#9a5b00;
        --bad:#a32121; --good:#1d6b3a; }
* { box-sizing: border-box; }
body { font: 14px/1.45 -apple-system, "Segoe UI", Roboto, "Helvetica Neue", Arial, sans-serif; color: var(--ink);
       margin: 0; background: #fff; }
main { max-width: 1100px; margin: 0 auto; padding: 28px 36px 60px; }
header.title { border-bottom: 3px solid var(--accent); padding-bottom: 14px; margin-bottom: 18px; }
header.title h1 { margin: 0 0 4px; font-size: 26px; }
header.title .sub { color: var(--muted); font-size: 15px; }
h2 { font-size: 19px; color: var(--accent); border-bottom: 1px solid var(--rule); padding-bottom: 4px; margin: 30px 0 12px; }
h3 { font-size: 15px; margin: 18px 0 8px; }
p { margin: 6px 0 10px; }
.muted, .note { color: var(--muted); }
.note { font-size: 12.5px; }
table { border-collapse: collapse; margin: 6px 0 14px; font-size: 13px; }
th, td { border: 1px solid var(--rule); padding: 4px 8px; text-align: left; vertical-align: top; }
th { background: var(--band); font-weight: 600; }
td.n, th.n { text-align: right; font-variant-numeric: tabular-nums; white-space: nowrap; }
tr.after td { font-weight: 600; }
table.kv th { width: 230px; }
table.wide { width: 100%; }
.cards { display: flex; flex-wrap: wrap; gap: 12px; margin: 8px 0 16px; }
.card { flex: 1 1 200px; border: 1px solid var(--rule); border-radius: 6px; padding: 10px 14px; background: var(--band); }
.card .k { color: var(--muted); font-size: 12px; text-transform: uppercase; letter-spacing: .04em; }
.card .v { font-size: 22px; font-weight: 600; }
.card .d { font-size: 12.5px; color: var(--muted); }
.na { color: var(--muted); font-style: italic; border-left: 3px solid var(--rule); padding: 4px 10px; }
.banner { border: 1px solid var(--bad); background: #fbeeee; color: var(--bad); padding: 8px 12px; border-radius: 4px; }
ul.warnings li { color: var(--warn); margin: 3px 0; }
.ok { color: var(--good); }
figure { margin: 10px 0 22px; }
figure img { max-width: 100%; height: auto; border: 1px solid var(--rule); }
figcaption { color: var(--muted); font-size: 12.5px; margin-top: 4px; }
svg.hist { border: 1px solid var(--rule); background: #fff; }
.hists { display: flex; flex-wrap: wrap; gap: 12px; }
details { margin: 8px 0; }
summary { cursor: pointer; color: var(--accent); }
pre { background: var(--band); border: 1px solid var(--rule); padding: 10px; font-size: 11.5px; white-space: pre-wrap;
      word-break: break-all; }
footer { margin-top: 40px; color: var(--muted); font-size: 12px; border-top: 1px solid var(--rule); padding-top: 8px; }
@page { size: A4; margin: 14mm 12mm; }
@media print {
  body { font-size: 11px; }
  main { max-width: none; padding: 0; }
  section.major { break-before: page; }
  section.first { break-before: auto; }
  h2, h3 { break-after: avoid; }
  table, figure, .card, svg, tr { break-inside: avoid; }
  thead { display: table-header-group; }
  figure img { max-height: 240mm; }
  details > summary { display: none; }
  details::details-content { content-visibility: visible; display: block; }
  pre { font-size: 8.5px; }
}
"""


def esc(value) -> str:
    """Any value as HTML text, quotes included (safe in attributes too)."""
    return html.escape("" if value is None else str(value), quote=True)


def esc_lines(value) -> str:
    """:func:`esc`, its line breaks kept (a data error names the row and the column on its second line)."""
    return esc(value).replace("\n", "<br>")


def num(value, digits: int = 4, unit: str = "", key: str | None = None) -> str:
    """A number as right-aligned cell content; ``key`` adds ``data-key`` / ``data-value`` (the exact value)."""
    if value is None or (isinstance(value, float) and not math.isfinite(value)):
        return '<td class="n">&ndash;</td>'
    if isinstance(value, bool) or not isinstance(value, (int, float)):
        return f'<td class="n">{esc(value)}</td>'
    text = f"{value:d}" if isinstance(value, int) else f"{value:.{digits}f}"
    attrs = f' data-key="{esc(key)}" data-value="{esc(repr(float(value)))}"' if key else ""
    return f'<td class="n"{attrs}>{esc(text)}{esc(unit)}</td>'


def table(header, rows, cls: str = "", numeric=()) -> str:
    """``rows``: lists of ready ``<td>`` strings or plain values (escaped); ``numeric``: header indices right-aligned."""
    head = "".join(f'<th{" class=n" if i in numeric else ""}>{esc(h)}</th>' for i, h in enumerate(header))
    body = []
    for row in rows:
        css = ""
        if isinstance(row, tuple) and len(row) == 2 and isinstance(row[0], str) and isinstance(row[1], list):
            css, row = f' class="{esc(row[0])}"', row[1]
        cells = "".join(c if isinstance(c, str) and c.startswith("<td") else f"<td>{esc(c)}</td>" for c in row)
        body.append(f"<tr{css}>{cells}</tr>")
    return (f'<table class="{esc(cls)}"><thead><tr>{head}</tr></thead><tbody>{"".join(body)}</tbody></table>')


def kv(pairs) -> str:
    """A two-column key / value table; values are escaped unless they are ready ``<td>`` cells."""
    rows = []
    for k, v in pairs:
        cell = v if isinstance(v, str) and v.startswith("<td") else f"<td>{esc(v)}</td>"
        rows.append(f"<tr><th>{esc(k)}</th>{cell}</tr>")
    return f'<table class="kv"><tbody>{"".join(rows)}</tbody></table>'


def not_available(what: str, reason: str = "") -> str:
    tail = f" ({esc(reason)})" if reason else ""
    return f'<p class="na">{esc(what)}: not available{tail}.</p>'


def _shrink_png(data: bytes) -> bytes:
    """Halve a PNG until it is under :data:`MAX_IMAGE_BYTES` (PIL, only when needed)."""
    from PIL import Image

    img = Image.open(io.BytesIO(data))
    while len(data) > MAX_IMAGE_BYTES and min(img.size) > 200:
        img = img.resize((img.size[0] // 2, img.size[1] // 2), Image.LANCZOS)
        buf = io.BytesIO()
        img.save(buf, format="PNG", optimize=True)
        data = buf.getvalue()
    return data


def image(path: Path, caption: str) -> str:
    """A PNG embedded as a ``data:`` URI inside a captioned figure; an unreadable file says so instead."""
    try:
        data = Path(path).read_bytes()
    except OSError as exc:
        return not_available(f"plot {Path(path).name}", exc.strerror or str(exc))
    if not data.startswith(b"\x89PNG\r\n\x1a\n"):
        return not_available(f"plot {Path(path).name}", "not a PNG file")
    if len(data) > MAX_IMAGE_BYTES:
        data = _shrink_png(data)
    uri = "data:image/png;base64," + base64.b64encode(data).decode("ascii")
    return (f'<figure><img src="{uri}" alt="{esc(caption)}"><figcaption>{esc(caption)} '
            f'<span class="note">(plots/{esc(Path(path).name)})</span></figcaption></figure>')


def _nice_ticks(hi: float, count: int = 5) -> list[float]:
    """Round tick values 0, step, 2 step, ... <= hi (step 1, 2, 2.5 or 5 times a power of ten)."""
    raw = hi / count
    mag = 10.0 ** math.floor(math.log10(raw))
    step = next(m * mag for m in (1, 2, 2.5, 5, 10) if m * mag >= raw)
    return [k * step for k in range(int(hi / step + 1e-9) + 1)]


def histogram_svg(values, title: str, marks=(), bins: int = 40, width: int = 496, height: int = 220,
                  color: str = "#1f5f99", xlabel: str = "residual (mm)", counted: str = "rows") -> str:
    """An inline SVG histogram of ``values`` (mm); ``marks``: (label, x) vertical lines (e.g. Gamma 99 %);
    the axis reads ``xlabel, N counted``."""
    vals = [float(v) for v in values if math.isfinite(float(v))]
    if not vals:
        return ""
    lo, hi = 0.0, max(max(vals), *(x for _, x in marks if x is not None), 1e-12)
    step = (hi - lo) / bins
    counts = [0] * bins
    for v in vals:
        counts[min(int((v - lo) / step), bins - 1)] += 1
    left, right, top, bottom = 40, 24, 26, 34
    pw, ph = width - left - right, height - top - bottom
    cmax = max(counts)
    bars = []
    for i, c in enumerate(counts):
        if c:
            h = ph * c / cmax
            bars.append(f'<rect x="{left + pw * i / bins:.1f}" y="{top + ph - h:.1f}" width="{pw / bins - 0.6:.1f}" '
                        f'height="{h:.1f}" fill="{color}"/>')
    lines = []
    for k, (label, x) in enumerate(marks):
        if x is None:
            continue
        px = left + pw * (x - lo) / (hi - lo)
        lines.append(f'<line x1="{px:.1f}" y1="{top}" x2="{px:.1f}" y2="{top + ph}" stroke="#a32121" '
                     f'stroke-dasharray="4 3"/><text x="{px - 3:.1f}" y="{top + 10 + 11 * k}" font-size="10" '
                     f'text-anchor="end" fill="#a32121">{esc(label)}</text>')
    ticks = "".join(f'<line x1="{left + pw * t / hi:.1f}" y1="{top + ph}" x2="{left + pw * t / hi:.1f}" '
                    f'y2="{top + ph + 3}" stroke="#5b6776"/><text x="{left + pw * t / hi:.1f}" y="{top + ph + 14}" '
                    f'font-size="10" text-anchor="middle">{t:g}</text>' for t in _nice_ticks(hi))
    return (f'<svg class="hist" width="{width}" height="{height}" '
            f'viewBox="0 0 {width} {height}" role="img" aria-label="{esc(title)}">'
            f'<text x="{width / 2}" y="15" font-size="12" text-anchor="middle" font-weight="600">{esc(title)}</text>'
            f'<line x1="{left}" y1="{top + ph}" x2="{left + pw}" y2="{top + ph}" stroke="#5b6776"/>'
            f'<line x1="{left}" y1="{top}" x2="{left}" y2="{top + ph}" stroke="#5b6776"/>'
            f'<text x="{left - 4}" y="{top + 8}" font-size="10" text-anchor="end">{cmax}</text>'
            f'<text x="{left - 4}" y="{top + ph}" font-size="10" text-anchor="end">0</text>'
            f'{"".join(bars)}{"".join(lines)}{ticks}'
            f'<text x="{left + pw / 2}" y="{height - 4}" font-size="10" text-anchor="middle">{esc(xlabel)}, '
            f'{len(vals)} {esc(counted)}</text></svg>')


def strip_svg(groups, title: str, ylabel: str, width: int = 1000, height: int = 260) -> str:
    """An inline SVG strip chart: one column per group, a dot per value, highlighted ones in red and labelled.

    groups: (label, [(name, value, highlighted)], median or None, level or None) per column; the median is drawn
    as a short grey bar, the level (e.g. where a unit is flagged) as a dashed red one. Every dot carries its
    name and exact value (``data-name``, ``data-value``) so the figure can be read back."""
    vals = [float(v) for _, pts, _, _ in groups for _, v, _ in pts if math.isfinite(float(v))]
    extra = [float(x) for _, _, med, lvl in groups for x in (med, lvl) if x is not None and math.isfinite(float(x))]
    if not vals:
        return ""
    hi = max(vals + extra + [1e-12]) * 1.08
    left, right, top, bottom = 56, 16, 26, 34
    pw, ph = width - left - right, height - top - bottom
    col = pw / max(1, len(groups))

    def y(v):
        return top + ph - ph * v / hi

    parts = []
    for g, (label, pts, med, lvl) in enumerate(groups):
        cx = left + col * (g + 0.5)
        parts.append(f'<text x="{cx:.1f}" y="{top + ph + 14}" font-size="10" text-anchor="middle">{esc(label)}</text>')
        if med is not None and math.isfinite(float(med)):
            parts.append(f'<line x1="{cx - col * 0.3:.1f}" y1="{y(med):.1f}" x2="{cx + col * 0.3:.1f}" y2="{y(med):.1f}" '
                         f'stroke="#5b6776" stroke-width="2"/>')
        if lvl is not None and math.isfinite(float(lvl)):
            parts.append(f'<line x1="{cx - col * 0.35:.1f}" y1="{y(lvl):.1f}" x2="{cx + col * 0.35:.1f}" '
                         f'y2="{y(lvl):.1f}" stroke="#a32121" stroke-dasharray="4 3"/>')
        side = 0  # flagged dots' names alternate right and left of their dots: near values would overprint
        for k, (name, v, hot) in enumerate(pts):
            if not math.isfinite(float(v)):
                continue
            dx = col * 0.5 * ((k * 0.618034) % 1.0 - 0.5)  # spread the dots over the column (golden-ratio jitter)
            fill = "#a32121" if hot else "#1f5f99"
            r = 3.2 if hot else 2.2
            parts.append(f'<circle cx="{cx + dx:.1f}" cy="{y(float(v)):.1f}" r="{r}" fill="{fill}" '
                         f'fill-opacity="{1.0 if hot else 0.55}" data-name="{esc(name)}" '
                         f'data-value="{esc(repr(float(v)))}"><title>{esc(name)}: {float(v):.4g}</title></circle>')
            if hot:
                tx, anchor = (cx + dx + 5, "start") if side % 2 == 0 else (cx + dx - 5, "end")
                side += 1
                parts.append(f'<text x="{tx:.1f}" y="{y(float(v)) + 3:.1f}" font-size="9" fill="#a32121" '
                             f'text-anchor="{anchor}">{esc(name)}</text>')
    ticks = "".join(f'<line x1="{left - 3}" y1="{y(t):.1f}" x2="{left}" y2="{y(t):.1f}" stroke="#5b6776"/>'
                    f'<text x="{left - 5}" y="{y(t) + 3:.1f}" font-size="10" text-anchor="end">{t:g}</text>'
                    for t in _nice_ticks(hi))
    return (f'<svg class="hist" width="{width}" height="{height}" viewBox="0 0 {width} {height}" role="img" '
            f'aria-label="{esc(title)}"><text x="{width / 2}" y="15" font-size="12" text-anchor="middle" '
            f'font-weight="600">{esc(title)}</text>'
            f'<line x1="{left}" y1="{top + ph}" x2="{left + pw}" y2="{top + ph}" stroke="#5b6776"/>'
            f'<line x1="{left}" y1="{top}" x2="{left}" y2="{top + ph}" stroke="#5b6776"/>{ticks}{"".join(parts)}'
            f'<text x="12" y="{top + ph / 2:.1f}" font-size="10" text-anchor="middle" '
            f'transform="rotate(-90 12 {top + ph / 2:.1f})">{esc(ylabel)}</text></svg>')


def section(anchor: str, title: str, body: str, major: bool = False, first: bool = False) -> str:
    cls = " ".join(c for c, on in (("major", major), ("first", first)) if on)
    return f'<section id="{esc(anchor)}" class="{cls}"><h2>{esc(title)}</h2>{body}</section>'


def page(title: str, header: str, sections: list[str], footer: str) -> str:
    """The whole document: one HTML file, inline CSS, no script, no external resource."""
    return ("<!DOCTYPE html>\n<html lang=\"en\"><head><meta charset=\"utf-8\">"
            "<meta name=\"viewport\" content=\"width=device-width, initial-scale=1\">"
            f"<title>{esc(title)}</title><style>{CSS}</style></head><body><main>"
            f"{header}{''.join(sections)}<footer>{footer}</footer></main></body></html>\n")


__all__ = ["CSS", "MAX_IMAGE_BYTES", "esc", "esc_lines", "histogram_svg", "image", "kv", "not_available", "num", "page", "section",
           "strip_svg", "table"]
