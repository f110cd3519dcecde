"""Compensation tables from the axis perturbation model, Paper I (2)-(3), and the controller's lookup.

Paper I (2): the compensated command q^ = q - dq(q) makes the machine follow
its nominal kinematics to first order, dq_i(q) = sum_j f_ij(q_j) (3). A
controller offers look-up tables, each mapping one INPUT axis j's command to
a correction ADDED to one OUTPUT axis i's command; so table T_ij holds
-f_ij sampled on axis j:

    q^_i = q_i + sum_j T_ij(q_j),   T_ij(x) = -f_ij(x)

A table's grid is equally spaced and spans the input axis's WHOLE command
range (the controller holds the end value beyond a table; a table that
stopped at the measured region would hold a wrong value over the rest).
Between grid points the controller interpolates linearly; :func:`apply_tables`
does the same, batched over commands.

Units: SI inside (m for a prismatic axis, rad for a revolute one; the
correction has the OUTPUT axis's unit, the grid the INPUT axis's). The file
writers of :mod:`torchcal.export.controller` convert to mm / deg.
"""

from __future__ import annotations

import warnings
from dataclasses import dataclass, field

import torch

from ..core import units
from ..core.exceptions import TorchcalError

DEFAULT_POINTS = 101
"""Grid points per table by default: 1 % of the axis range apart (9.8 mm on Paper I's Z, 5.4 deg on C)."""


class TableError(TorchcalError, ValueError):
    """Base of the compensation-table errors. ``ok``: the results that were fine (kept);
    ``failed``: {table name: reason} for the rest."""

    def __init__(self, message: str, ok=None, failed: dict | None = None):
        self.ok = ok
        self.failed = dict(failed or {})
        super().__init__(message)


class TableAxisError(TableError):
    """A table names an axis the machine does not have (or two tables share the same pair)."""


class TableRangeError(TableError):
    """Axis commands outside the range a table covers (the controller would hold the end value)."""


class TableSizeError(TableError):
    """A table has more points than the controller allows, or too few to be a table."""


class TableSlopeWarning(UserWarning, TorchcalError):
    """The table's slope at an end is large: the controller holds the end value beyond it."""


@dataclass
class CompensationTable:
    """One controller table T_ij: correction of OUTPUT axis i as a function of INPUT axis j's command.

    output_axis, input_axis: 0-based axis indices; output_name, input_name: axis
    names; input: (K,) grid, SI (the input axis's unit), strictly increasing
    (equally spaced when built by :func:`compensation_tables`); correction: (K,)
    SI (the output axis's unit) to ADD to the output axis's command;
    output_prismatic, input_prismatic: axis kinds (for file units).

    Example:
        >>> t = CompensationTable(0, 1, "X", "Y", [0.0, 1.0], [0.0, 2e-3], True, True)
        >>> t.name, t(torch.tensor([0.5, 3.0], dtype=torch.float64)).tolist()   # linear inside, end value held beyond
        ('X(Y)', [0.001, 0.002])
    """

    output_axis: int
    input_axis: int
    output_name: str
    input_name: str
    input: torch.Tensor
    correction: torch.Tensor
    output_prismatic: bool
    input_prismatic: bool
    meta: dict = field(default_factory=dict)

    def __post_init__(self):
        self.input = torch.as_tensor(self.input, dtype=torch.float64)
        self.correction = torch.as_tensor(self.correction, dtype=torch.float64).to(self.input.device)
        if self.input.ndim != 1 or self.input.shape != self.correction.shape:
            raise TableSizeError(f"table {self.name}: input {tuple(self.input.shape)} and correction "
                                 f"{tuple(self.correction.shape)} must be two (K,) vectors")
        if self.input.numel() < 2:
            raise TableSizeError(f"table {self.name}: needs at least 2 points, has {self.input.numel()}")
        if not bool((self.input[1:] > self.input[:-1]).all()):
            raise TableSizeError(f"table {self.name}: input grid must be strictly increasing")
        if not bool(torch.isfinite(self.input).all() and torch.isfinite(self.correction).all()):
            raise TableSizeError(f"table {self.name}: holds non-finite values")

    @property
    def name(self) -> str:
        """'OUT(IN)', e.g. 'Z(B)': the correction of Z as a function of B."""
        return f"{self.output_name}({self.input_name})"

    @property
    def size(self) -> int:
        return int(self.input.numel())

    @property
    def lower(self) -> float:
        return float(self.input[0])

    @property
    def upper(self) -> float:
        return float(self.input[-1])

    @property
    def step(self) -> float:
        """Grid spacing (mean; equal for tables built here), SI."""
        return (self.upper - self.lower) / (self.size - 1)

    def equally_spaced(self, rtol: float = 1e-9) -> bool:
        d = self.input[1:] - self.input[:-1]
        return bool(((d - self.step).abs() <= rtol * max(abs(self.step), 1e-300) + 1e-15).all())

    def __call__(self, x: torch.Tensor) -> torch.Tensor:
        """Linear interpolation at x (...,) SI, holding the end values beyond the grid -> (...,) SI."""
        return interpolate(self.input.to(x), self.correction.to(x), x)

    def end_slopes(self) -> torch.Tensor:
        """(2,) slope of the correction at the lower and upper end (output unit per input unit), from the last segments."""
        x, y = self.input, self.correction
        return torch.stack([(y[1] - y[0]) / (x[1] - x[0]), (y[-1] - y[-2]) / (x[-1] - x[-2])])

    def to(self, device) -> CompensationTable:
        self.input, self.correction = self.input.to(device), self.correction.to(device)
        return self

    def file_units(self) -> tuple[torch.Tensor, torch.Tensor]:
        """(input, correction) in mm / deg (each in its own axis's unit), float64 on the CPU."""
        def conv(x, prismatic):
            x = x.detach().to("cpu", torch.float64)
            return units.m_to_mm(x) if prismatic else units.rad_to_deg(x)
        return conv(self.input, self.input_prismatic), conv(self.correction, self.output_prismatic)


def interpolate(grid: torch.Tensor, values: torch.Tensor, x: torch.Tensor) -> torch.Tensor:
    """Piecewise-linear lookup with the end values held: grid (K,) increasing, values (K,), x (...,) -> (...,).

    Example:
        >>> interpolate(torch.tensor([0.0, 1.0, 3.0]), torch.tensor([0.0, 1.0, 0.0]), torch.tensor([-1.0, 0.5, 2.0, 9.0])).tolist()
        [0.0, 0.5, 0.5, 0.0]
    """
    xc = x.clamp(grid[0], grid[-1])
    k = torch.searchsorted(grid, xc.contiguous(), right=True).clamp(1, grid.numel() - 1)
    x0, x1 = grid[k - 1], grid[k]
    y0, y1 = values[k - 1], values[k]
    w = (xc - x0) / (x1 - x0)
    return y0 + w * (y1 - y0)


def _axis_perturbation(obj):
    """The AxisPerturbation-like object (pairs, limits, prismatic, axis_names, f) of a model or itself."""
    need = ("pairs", "limits", "prismatic", "axis_names", "f")
    if all(hasattr(obj, a) for a in need):
        return obj
    for name in ("axis_errors", "axis_perturbation", "perturbation", "ap"):
        sub = getattr(obj, name, None)
        if sub is not None and all(hasattr(sub, a) for a in need):
            return sub
    raise TypeError(f"compensation_tables: {type(obj).__name__} is neither an axis perturbation model "
                    f"(pairs, limits, prismatic, axis_names, f) nor a model holding one as .axis_errors")


def compensation_tables(ap_or_model, points_per_table: int = DEFAULT_POINTS, pairs=None) -> list[CompensationTable]:
    """The controller tables -f_ij of an axis perturbation model, Paper I (2)-(3).

    ap_or_model: an :class:`~torchcal.error_models.axis_perturbation.AxisPerturbation`
    or a model holding one as ``.axis_errors`` (:class:`torchcal.models.machine.MachineModel`);
    points_per_table: grid points K, equally spaced over the input axis's whole
    command range (``limits[j]``); pairs: (output i, input j) pairs to export,
    0-based ints or axis names (default: every enabled table of the model).
    Returns one :class:`CompensationTable` per pair, in the given order.

    Raises :class:`TableAxisError` for a pair naming an axis the machine lacks
    (``.ok`` holds the tables of the valid pairs, ``.failed`` the bad ones) and
    :class:`TableSizeError` for K < 2.

    Example:
        >>> import torch
        >>> from torchcal.error_models.axis_perturbation import AxisPerturbation
        >>> ap = AxisPerturbation(torch.tensor([[0.0, 1.0], [-3.0, 3.0]], dtype=torch.float64), [True, False], 2)
        >>> with torch.no_grad():
        ...     ap.coef[0, 1, 1] = 1e-4          # f_XY(q) = 1e-4 * qbar_Y
        >>> t = compensation_tables(ap, points_per_table=5, pairs=[(0, 1)])[0]
        >>> t.name, [round(v * 1e4, 6) + 0.0 for v in t.correction.tolist()]
        ('q1(q2)', [1.0, 0.5, 0.0, -0.5, -1.0])
    """
    ap = _axis_perturbation(ap_or_model)
    K = int(points_per_table)
    if K < 2:
        raise TableSizeError(f"compensation_tables: points_per_table must be >= 2, got {points_per_table}")
    names = list(ap.axis_names)
    n = len(names)

    def axis(a):
        if isinstance(a, str):
            return names.index(a) if a in names else None
        a = int(a)
        return a if 0 <= a < n else None

    wanted = list(ap.pairs) if pairs is None else list(pairs)
    tables, failed = [], {}
    limits = ap.limits.detach()
    prismatic = [bool(p) for p in ap.prismatic.detach().cpu()]
    seen = set()
    for pair in wanted:
        if len(pair) != 2:
            failed[str(pair)] = "a pair is (output axis, input axis)"
            continue
        i, j = axis(pair[0]), axis(pair[1])
        if i is None or j is None:
            bad = pair[0] if i is None else pair[1]
            failed[f"{pair[0]}({pair[1]})"] = f"axis {bad!r} is not one of the machine's axes {names} (0..{n - 1})"
            continue
        if (i, j) in seen:
            failed[f"{names[i]}({names[j]})"] = "listed twice"
            continue
        seen.add((i, j))
        grid = torch.linspace(float(limits[j, 0]), float(limits[j, 1]), K, dtype=torch.float64, device=limits.device)
        with torch.no_grad():
            corr = -ap.f(i, j, grid).detach().to(torch.float64)
        tables.append(CompensationTable(i, j, names[i], names[j], grid, corr, prismatic[i], prismatic[j]))
    if failed:
        raise TableAxisError("compensation_tables: " + "; ".join(f"{k}: {v}" for k, v in failed.items())
                             + f" ({len(tables)} valid table(s) kept in .ok)", ok=tables, failed=failed)
    return tables


def _check_axes(tables, n: int) -> None:
    bad = {t.name: f"axis index {max(t.output_axis, t.input_axis)} but q has {n} axes"
           for t in tables if not (0 <= t.output_axis < n and 0 <= t.input_axis < n)}
    if bad:
        raise TableAxisError("apply_tables: " + "; ".join(f"{k}: {v}" for k, v in bad.items()), failed=bad)


def apply_tables(tables, q: torch.Tensor, outside: str = "raise", tol: float = 1e-9) -> torch.Tensor:
    """Compensated commands q^_i = q_i + sum_j T_ij(q_j), as the controller computes them.

    tables: list of :class:`CompensationTable`; q: (B, n) commands, SI ->
    (B, n) SI. Linear interpolation between grid points; beyond a table's grid
    the controller holds the end value: ``outside="hold"`` does that,
    ``outside="raise"`` (default) raises :class:`TableRangeError` listing the
    rows and axes (1-based rows) that leave a table's range by more than tol
    (SI) — a command outside a table that spans the axis's whole range is a
    command outside the machine's travel.

    Example:
        >>> t = CompensationTable(0, 1, "X", "Y", [0.0, 1.0], [0.0, 1e-3], True, True)
        >>> apply_tables([t], torch.tensor([[0.2, 0.5], [0.3, 1.0]], dtype=torch.float64)).tolist()
        [[0.2005, 0.5], [0.301, 1.0]]
    """
    if outside not in ("raise", "hold"):
        raise ValueError(f"apply_tables: outside must be 'raise' or 'hold', got {outside!r}")
    if q.ndim != 2:
        raise ValueError(f"apply_tables: q must be (B, n), got {tuple(q.shape)}")
    _check_axes(tables, q.shape[1])
    if outside == "raise":
        problems = {}
        for t in tables:
            x = q[:, t.input_axis]
            out = (x < t.lower - tol) | (x > t.upper + tol)
            if out.any():
                rows = (out.nonzero()[:, 0] + 1).tolist()
                conv = units.m_to_mm if t.input_prismatic else units.rad_to_deg
                unit = "mm" if t.input_prismatic else "deg"
                lo, hi = conv(t.lower), conv(t.upper)
                first = conv(float(x[rows[0] - 1]))
                problems[t.name] = (f"{len(rows)} row(s) with {t.input_name} outside [{lo:.6g}, {hi:.6g}] {unit}, "
                                    f"rows {rows[:10]}{' ...' if len(rows) > 10 else ''} (row {rows[0]}: {first:.6g} {unit})")
        if problems:
            raise TableRangeError("apply_tables: commands outside the tables' ranges (the controller would hold "
                                  "the end value; pass outside='hold' to do the same): "
                                  + "; ".join(f"{k}: {v}" for k, v in problems.items()), failed=problems)
    out = q.clone()
    for t in tables:   # a loop over a handful of tables; each lookup is batched over the B commands
        out[:, t.output_axis] = out[:, t.output_axis] + t(q[:, t.input_axis])
    return out


def normalized_end_slopes(tables) -> torch.Tensor:
    """(T, 2) end slopes of every table times the input axis's half range (Paper I (30)'s unit):
    the change of the correction over half the input axis's travel at that slope, SI (output unit)."""
    return torch.stack([t.end_slopes() * 0.5 * (t.upper - t.lower) for t in tables]) if tables else torch.zeros(0, 2)


def warn_end_slopes(tables, limit_mm: float = 0.4, lever_mm: float = 500.0) -> list[str]:
    """Warn (:class:`TableSlopeWarning`) about tables whose slope at an end is large; returns the messages.

    Large: the slope times the input axis's half range (Paper I (30)) exceeds
    limit_mm for a prismatic output axis, or limit_mm / lever_mm rad for a
    revolute one (a tool lever_mm long moves limit_mm). Default 0.4 mm: Paper
    I's constraint c. Beyond the table the controller holds the end value, so a
    steep end means the correction stops following the model abruptly there.
    """
    msgs = []
    if not tables:
        return msgs
    s = normalized_end_slopes(tables)
    for t, (lo, hi) in zip(tables, s.tolist()):
        lim = limit_mm * units.MM if t.output_prismatic else limit_mm / lever_mm
        for end, v in (("lower", lo), ("upper", hi)):
            if abs(v) > lim:
                conv = units.m_to_mm if t.output_prismatic else units.rad_to_deg
                unit = "mm" if t.output_prismatic else "deg"
                msg = (f"table {t.name}: slope at the {end} end is {conv(v):.4g} {unit} per half range of "
                       f"{t.input_name} (limit {conv(lim):.4g}); the controller holds the end value beyond the table")
                msgs.append(msg)
                warnings.warn(msg, TableSlopeWarning, stacklevel=2)
    return msgs


def tables_delta(tables, q: torch.Tensor) -> torch.Tensor:
    """sum_j T_ij(q_j) per output axis (B, n) SI, holding end values (the tables' total correction)."""
    return apply_tables(tables, q, outside="hold") - q


__all__ = [
    "DEFAULT_POINTS",
    "CompensationTable",
    "TableAxisError",
    "TableError",
    "TableRangeError",
    "TableSizeError",
    "TableSlopeWarning",
    "apply_tables",
    "compensation_tables",
    "interpolate",
    "normalized_end_slopes",
    "tables_delta",
    "warn_end_slopes",
]
