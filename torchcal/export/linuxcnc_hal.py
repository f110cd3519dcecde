"""All compensation tables on LinuxCNC: a generated HAL component that applies every T_ij, cross-axis ones too.

Why: LinuxCNC's joint compensation (``[JOINT_n] COMP_FILE``, :func:`torchcal.export.controller.write_linuxcnc_comp`)
corrects a joint from its OWN position only, so it can hold the five same-axis tables T_ii of Paper I's
XYZCB machine and none of the twenty cross-axis tables f_ij (i != j), which carry most of a machine's
squareness and rotary-axis errors. A HAL component in the servo thread sees every joint at once and can
apply them all:

    q'_i = q_i + sum_j T_ij(q_j)          (Paper I (2)-(3), T_ij = -f_ij; compensate/tables.py)

Design (``--format linuxcnc-volumetric``; :func:`write_linuxcnc_volumetric` writes three files):

- ``torchcal_volcomp.h``: plain C89 (no HAL, no libm): the tables as constant arrays (grid and correction
  in mm / deg, printed with 17 significant digits so they are the doubles torchcal holds) and the lookup
  ``tcvc_corrections(q, delta)``. The lookup is :func:`torchcal.compensate.tables.interpolate` step for
  step: clamp to the grid, the last node <= x (``searchsorted(right=True)`` clamped to [1, K-1]), then
  ``y0 + w * (y1 - y0)``; beyond a table's grid the end value is held, as LinuxCNC and torchcal's
  ``apply_tables(..., outside="hold")`` do. It also counts the tables whose input is beyond the grid.
  The tests compile it with gcc and compare it with torchcal at 10^4 random positions.
- ``torchcal_volcomp.comp``: the ``halcompile`` source, a singleton component ``torchcal_volcomp`` whose
  C part is the header's text verbatim plus two functions (the pattern of LinuxCNC's own ``offset``
  component): ``update-output`` (after motion-controller) reads every joint's position command
  ``joint.N.pos-cmd`` (joint coordinates: the tables' input; ``motor-pos-cmd`` also holds the home offset)
  and adds the correction to ``joint.N.motor-pos-cmd`` on its way to the drive; ``update-feedback``
  (before motion-command-handler) subtracts the same correction from the drive's feedback, so motion sees
  its own command and no following error. Pin ``enable`` (default off; wire it to
  ``motion.is-all-homed``): before homing, joint positions are not machine positions. The correction
  steps from 0 to its value where enable rises (tens of micrometres). ``out-of-range``: some table input
  is beyond its grid (end values held).
- ``torchcal_volcomp.hal``: the wiring, per joint, between motion and the drives (stepgen pin names by
  default, ``drive_cmd`` / ``drive_fb`` templates otherwise) and the order of the servo-thread functions.

Positions are machine units: mm for prismatic axes (``[TRAJ] LINEAR_UNITS = mm``), degrees for rotary
ones, and joint N must be the model's axis in the model's coordinates (same zero, same direction). Use
either this component or the joint COMP_FILEs, never both: the component applies the T_ii too.
"""

from __future__ import annotations

import re
from dataclasses import dataclass
from datetime import UTC, datetime
from pathlib import Path

from ..compensate.tables import TableAxisError, TableSizeError, warn_end_slopes
from ..core.exceptions import TorchcalError
from ..io.atomic import atomic_write_text

COMPONENT = "torchcal_volcomp"
"""The component's name (C identifier); its HAL pins and functions are ``torchcal-volcomp.*``."""

FILES = (f"{COMPONENT}.comp", f"{COMPONENT}.h", f"{COMPONENT}.hal")
"""The files :func:`write_linuxcnc_volumetric` puts in its folder (the CLI's overwrite check names them)."""

FORMAT = "linuxcnc-volumetric"
"""The ``torchcal export-tables --format`` value."""


class TableNotWrittenWarning(UserWarning, TorchcalError):
    """A writer left tables out that its format cannot hold; the message names them and says what to use."""


@dataclass
class VolumetricComponent:
    """The generated texts: ``comp`` (halcompile source), ``header`` (standalone C), ``hal`` (wiring);
    ``axes``: [(axis name, pin prefix, joint number, unit)] in the C arrays' order; ``applied``: table names."""

    comp: str
    header: str
    hal: str
    axes: list
    applied: list


def _c(x: float) -> str:
    s = "%.17g" % x
    return s if any(ch in s for ch in ".eEn") else s + ".0"   # a double literal, never an int


def _axes(tables, joint_numbers):
    """[(axis index, name, pin prefix, joint, prismatic)] of every axis a table reads or corrects, by index."""
    seen: dict[int, tuple[str, bool]] = {}
    for t in tables:
        for idx, name, pris in ((t.output_axis, t.output_name, t.output_prismatic),
                                (t.input_axis, t.input_name, t.input_prismatic)):
            if idx in seen and seen[idx] != (name, bool(pris)):
                raise TableAxisError(f"table {t.name}: axis {idx} is {name!r} ({'mm' if pris else 'deg'}) here but "
                                     f"{seen[idx][0]!r} ({'mm' if seen[idx][1] else 'deg'}) in another table",
                                     failed={t.name: "inconsistent axis"})
            seen[idx] = (name, bool(pris))
    out, prefixes = [], set()
    for idx in sorted(seen):
        name, pris = seen[idx]
        p = re.sub(r"[^a-z0-9]+", "_", name.lower()).strip("_")
        if not re.fullmatch(r"[a-z][a-z0-9_]*", p) or p in prefixes or p in ("enable", "out_of_range"):
            p = f"axis{idx}"
        prefixes.add(p)
        if joint_numbers is not None and name not in joint_numbers:
            raise TableAxisError(f"joint_numbers has no LinuxCNC joint for axis {name!r}", failed={name: "no joint"})
        out.append((idx, name, p, int(joint_numbers[name]) if joint_numbers is not None else idx, pris))
    return out


_LOOKUP = r"""
/* Piecewise-linear lookup, end values held (torchcal.compensate.tables.interpolate, step for step):
   g: n > 1 strictly increasing grid, v: n values. */
static double tcvc_lookup(const double *g, const double *v, int n, double x)
{
    int lo = 0, hi = n - 1, mid;
    double xc = x < g[0] ? g[0] : (x > g[n - 1] ? g[n - 1] : x);
    while (hi - lo > 1) {           /* lo: the last node <= xc, at most n - 2 */
        mid = (lo + hi) / 2;
        if (g[mid] <= xc) lo = mid; else hi = mid;
    }
    return v[lo] + (xc - g[lo]) / (g[lo + 1] - g[lo]) * (v[lo + 1] - v[lo]);
}

/* delta[i] = sum_j T_ij(q[j]) for the TCVC_N_AXES axes (mm / deg, the order above);
   returns how many tables' inputs are beyond their grid (their end values held). */
static int tcvc_corrections(const double *q, double *delta)
{
    int t, i, s, n, outside = 0;
    double x;
    for (i = 0; i < TCVC_N_AXES; i++) delta[i] = 0.0;
    for (t = 0; t < TCVC_N_TABLES; t++) {
        s = tcvc_start[t];
        n = tcvc_size[t];
        x = q[tcvc_in[t]];
        if (x < tcvc_grid[s] || x > tcvc_grid[s + n - 1]) outside++;
        delta[tcvc_out[t]] += tcvc_lookup(tcvc_grid + s, tcvc_value + s, n, x);
    }
    return outside;
}
"""


def _c_body(tables, axes) -> str:
    """The C shared by the header and the .comp: axis list, table arrays, lookup."""
    pos = {idx: k for k, (idx, *_rest) in enumerate(axes)}
    starts, k = [], 0
    for t in tables:
        starts.append(k)
        k += t.size
    ints = lambda vals: ", ".join(str(v) for v in vals)  # noqa: E731
    lines = [f"#define TCVC_N_AXES {len(axes)}", f"#define TCVC_N_TABLES {len(tables)}",
             "/* axes (index into q / delta): " + ", ".join(
                 f"{pos[idx]} {name} ({'mm' if pris else 'deg'}, joint {jn})" for idx, name, _p, jn, pris in axes) + " */",
             f"static const int tcvc_out[TCVC_N_TABLES] = {{{ints(pos[t.output_axis] for t in tables)}}};",
             f"static const int tcvc_in[TCVC_N_TABLES] = {{{ints(pos[t.input_axis] for t in tables)}}};",
             f"static const int tcvc_start[TCVC_N_TABLES] = {{{ints(starts)}}};",
             f"static const int tcvc_size[TCVC_N_TABLES] = {{{ints(t.size for t in tables)}}};"]
    grid, value = [], []
    for t in tables:
        x, c = t.file_units()
        head = (f"    /* {t.name}: {t.size} points, {t.input_name} {'mm' if t.input_prismatic else 'deg'} -> "
                f"{t.output_name} correction {'mm' if t.output_prismatic else 'deg'} */")
        grid += [head] + [f"    {_c(v)}," for v in x.tolist()]
        value += [head] + [f"    {_c(v)}," for v in c.tolist()]
    lines += [f"static const double tcvc_grid[{k}] = {{", *grid, "};",
              f"static const double tcvc_value[{k}] = {{", *value, "};"]
    return "\n".join(lines) + "\n" + _LOOKUP


def _header(body: str, stamp: str) -> str:
    return (f"/* {COMPONENT}.h: torchcal compensation tables (Paper I), generated {stamp}.\n"
            "   q'_i = q_i + sum_j T_ij(q_j); plain C89, the same code as the C part of "
            f"{COMPONENT}.comp. */\n"
            "#ifndef TORCHCAL_VOLCOMP_H\n#define TORCHCAL_VOLCOMP_H\n" + body + "#endif\n")


def _comp(body: str, axes, tables, stamp: str, license: str) -> str:
    readme = [
        f"// {COMPONENT}.comp: volumetric compensation for LinuxCNC, generated by torchcal {stamp}.",
        "// Applies ALL the compensation tables of the axis perturbation model (Paper I (2)-(3)):",
        "//     q'_i = q_i + sum_j T_ij(q_j)     (mm / deg; linear between nodes, end value held beyond)",
        f"// {len(tables)} tables: " + ", ".join(t.name for t in tables),
        "// Build and install:  sudo halcompile --install " + f"{COMPONENT}.comp   (Debian: linuxcnc-uspace-dev)",
        f"// Wiring: {COMPONENT}.hal. Do NOT also load the joint COMP_FILEs of --format linuxcnc (the T_ii",
        "// are applied here). Machine units: mm and degrees; joint N = the model's axis, same coordinates.",
        "",
        f'component {COMPONENT} "torchcal volumetric compensation: every joint corrected from every joint\'s position";',
        'pin in bit enable = 0 "apply the corrections (wire to motion.is-all-homed); off: out = in, fb-out = fb-in";',
        'pin out bit out_of_range "a table input is beyond its grid: the end value is held";',
    ]
    for _idx, name, p, jn, pris in axes:
        u = "mm" if pris else "deg"
        readme += [
            f'pin in float {p}_pos "{name}: joint.{jn}.pos-cmd, {u} (the tables\' input)";',
            f'pin in float {p}_in "{name}: joint.{jn}.motor-pos-cmd, {u}";',
            f'pin out float {p}_out "{name}: {p}-in + {p}-correction, to the drive, {u}";',
            f'pin in float {p}_fb_in "{name}: the drive\'s position feedback, {u}";',
            f'pin out float {p}_fb_out "{name}: {p}-fb-in - {p}-correction, to joint.{jn}.motor-pos-fb, {u}";',
            f'pin out float {p}_correction "{name}: sum_j T_{name}j(q_j) applied, {u}";',
        ]
    readme += [
        'function update_output "after motion-controller: corrections from the joint positions, added to the commands";',
        'function update_feedback "before motion-command-handler: the applied corrections taken off the feedback";',
        f'license "{license}";',
        'author "torchcal (generated)";',
        "option singleton yes;",
        "option period no;",
        ";;",
        body,
        "FUNCTION(update_output) {",
        "    double q[TCVC_N_AXES], d[TCVC_N_AXES];",
        "    int i, outside;",
        *[f"    q[{k}] = {p}_pos;" for k, (_i, _n, p, _j, _u) in enumerate(axes)],
        "    outside = tcvc_corrections(q, d);",
        "    if (!enable) for (i = 0; i < TCVC_N_AXES; i++) d[i] = 0.0;",
        *[f"    {p}_correction = d[{k}];\n    {p}_out = {p}_in + d[{k}];" for k, (_i, _n, p, _j, _u) in enumerate(axes)],
        "    out_of_range = enable && outside > 0;",
        "}",
        "",
        "FUNCTION(update_feedback) {",
        *[f"    {p}_fb_out = {p}_fb_in - {p}_correction;" for _i, _n, p, _j, _u in axes],
        "}",
    ]
    return "\n".join(readme) + "\n"


def _hal(axes, drive_cmd: str, drive_fb: str) -> str:
    hp = COMPONENT.replace("_", "-")
    lines = [
        f"# {COMPONENT}.hal: wiring of the torchcal volumetric compensation (generated; adapt the drive pins).",
        f"# Build once: sudo halcompile --install {COMPONENT}.comp",
        "# These nets REPLACE the config's own nets from joint.N.motor-pos-cmd to the drive and from the drive to",
        "# joint.N.motor-pos-fb (a pin belongs to one net only): remove those, then add these (e.g. as a HALFILE).",
        "# Units: [TRAJ] LINEAR_UNITS = mm, ANGULAR_UNITS = degree. Remove any [JOINT_n] COMP_FILE of these joints.",
        f"loadrt {COMPONENT}",
        "# servo-thread order (addf appends; put these between the existing lines as shown):",
        "#   <drive read, e.g. stepgen.capture-position / hm2_<board>.read>",
        f"#   {hp}.update-feedback",
        "#   motion-command-handler",
        "#   motion-controller",
        f"#   {hp}.update-output",
        "#   <drive write, e.g. stepgen.update-freq / hm2_<board>.write>",
        f"addf {hp}.update-feedback servo-thread",
        f"addf {hp}.update-output servo-thread",
        f"net tcvc-enable motion.is-all-homed => {hp}.enable",
    ]
    for _idx, name, p, jn, pris in axes:
        q = p.replace("_", "-")
        cmd, fb = drive_cmd.format(joint=jn), drive_fb.format(joint=jn)
        lines += [
            f"# {name}: joint {jn}, {'mm' if pris else 'deg'}",
            f"net tcvc-{q}-pos     joint.{jn}.pos-cmd         => {hp}.{q}-pos",
            f"net tcvc-{q}-cmd     joint.{jn}.motor-pos-cmd   => {hp}.{q}-in",
            f"net tcvc-{q}-cmd-out {hp}.{q}-out    => {cmd}",
            f"net tcvc-{q}-fb      {fb}    => {hp}.{q}-fb-in",
            f"net tcvc-{q}-fb-out  {hp}.{q}-fb-out => joint.{jn}.motor-pos-fb",
        ]
    return "\n".join(lines) + "\n"


def volumetric_component(tables, joint_numbers=None, drive_cmd: str = "stepgen.{joint}.position-cmd",
                         drive_fb: str = "stepgen.{joint}.position-fb", license: str = "GPL") -> VolumetricComponent:
    """The texts of the volumetric HAL component for ``tables`` (every one applied; module docstring).

    tables: :class:`~torchcal.compensate.tables.CompensationTable` s (SI; written in mm / deg);
    joint_numbers: {axis name: LinuxCNC joint number}, default the 0-based axis index; drive_cmd, drive_fb:
    the drive's position command / feedback pins in the .hal wiring, ``{joint}`` replaced by the joint
    number; license: halcompile's ``license`` string. Raises :class:`TableSizeError` without tables,
    :class:`TableAxisError` for an axis named or typed differently by two tables or missing from
    joint_numbers.
    """
    tables = list(tables)
    if not tables:
        raise TableSizeError(f"{FORMAT}: no tables to apply")
    axes = _axes(tables, joint_numbers)
    stamp = f"{datetime.now(UTC):%Y-%m-%d %H:%M} UTC"
    body = _c_body(tables, axes)
    return VolumetricComponent(
        comp=_comp(body, axes, tables, stamp, license), header=_header(body, stamp), hal=_hal(axes, drive_cmd, drive_fb),
        axes=[(name, p, jn, "mm" if pris else "deg") for _i, name, p, jn, pris in axes],
        applied=[t.name for t in tables])


def write_linuxcnc_volumetric(folder, tables, joint_numbers=None, warn_slopes: bool = True, **kw) -> dict[str, Path]:
    """Write :data:`FILES` (the HAL component, its standalone C header, the wiring) into ``folder``.

    Every table is applied, same-axis and cross-axis; the arguments are :func:`volumetric_component`'s.
    Returns {'component': path, 'header': path, 'hal': path}. Warns (TableSlopeWarning) on steep table ends.
    """
    if warn_slopes:
        warn_end_slopes(tables)
    vc = volumetric_component(tables, joint_numbers, **kw)
    folder = Path(folder)
    folder.mkdir(parents=True, exist_ok=True)
    return {key: atomic_write_text(folder / name, text)
            for key, name, text in zip(("component", "header", "hal"), FILES, (vc.comp, vc.header, vc.hal))}


__all__ = [
    "COMPONENT",
    "FILES",
    "FORMAT",
    "TableNotWrittenWarning",
    "VolumetricComponent",
    "volumetric_component",
    "write_linuxcnc_volumetric",
]
