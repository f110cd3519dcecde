"""Paper I's axis perturbation model (2)-(7): compensation-table functions of the axis commands.

The uncompensated machine is the nominal one driven by perturbed commands,

    F_AP(q) = F_nom(q + dq(q))                                   (2)
    dq_i(q) = sum_j f_ij(q_j)                                    (3)
    f_ij(q_j) = sum_k a_k,ij g_k(qbar_j),  qbar_j in [-1, 1]     (4)-(7)

with g_k the Chebyshev polynomials of the command q_j normalized over its
range (7). f_ij is the table a controller offers that maps axis j's command
to a correction of axis i's command: i is the OUTPUT axis (its unit is axis
i's: m for a prismatic axis, rad for a revolute one), j the INPUT axis. Any
subset of (i, j) pairs can be switched on (a controller offers only some
tables), each with its own order. The compensation table is -dq(q).

Nothing here is specific to the XYZCB machine: the axes are the controller
commands of any serial chain (:class:`torchcal.kinematics.Robot`).
"""

from __future__ import annotations

from typing import Sequence

import torch
from torch import nn

from ..core.basis import chebyshev, chebyshev_with_derivative, normalize
from ..core.params import ANGLE, LENGTH, ParamGroup

MAX_ORDER = 12

PRIOR_SIGMA_LENGTH = 1e-3
"""Declared prior sigma (m) of every coefficient of a table whose output axis is prismatic: 1 mm,
about 3x Paper I's nominal volumetric error (Table 4: 0.3 mm mean, 0.74 mm max)."""

PRIOR_SIGMA_ANGLE = 1e-3
"""Declared prior sigma (rad, 0.057 deg) of every coefficient of a table whose output axis is revolute:
1 mrad moves a 0.5 m tool by 0.5 mm, the same scale as :data:`PRIOR_SIGMA_LENGTH`."""


def order_table(orders, n: int, pairs=None) -> torch.Tensor:
    """(n, n) long table of Chebyshev orders, -1 where the table f_ij is off.

    orders: int (every enabled pair), or an (n, n) table (rows: output axis i,
    columns: input axis j; -1 switches a table off); pairs: optional list of
    enabled (i, j), 0-based (the others are off).
    """
    t = torch.as_tensor(orders, dtype=torch.long)
    if t.ndim == 0:
        t = t.expand(n, n).clone()
    if t.shape != (n, n):
        raise ValueError(f"axis perturbation orders: expected an int or an ({n}, {n}) table, got shape {tuple(t.shape)}")
    t = t.clone()
    if pairs is not None:
        keep = torch.zeros(n, n, dtype=torch.bool)
        for i, j in pairs:
            if not (0 <= int(i) < n and 0 <= int(j) < n):
                raise ValueError(f"axis perturbation pair ({i}, {j}) names an axis outside 0..{n - 1}")
            keep[int(i), int(j)] = True
        t = torch.where(keep, t, torch.full_like(t, -1))
    if (t < -1).any() or (t > MAX_ORDER).any():
        raise ValueError(f"axis perturbation order must be in 0..{MAX_ORDER} (or -1 to switch a table off), got {t.tolist()}")
    return t


def perturbation(coef: torch.Tensor, lam: torch.Tensor) -> torch.Tensor:
    """dq (3) from Chebyshev coefficients.

    coef: (n, n, K) masked coefficients a_k,ij (output i, input j); lam: (B, n)
    normalized commands qbar (7). -> (B, n): dq_i = sum_j sum_k a_k,ij g_k(lam_j).
    """
    basis = chebyshev(lam, coef.shape[-1] - 1)  # (B, n_j, K)
    return torch.einsum("bjk,ijk->bi", basis, coef)


class AxisPerturbation(nn.Module):
    """Learnable dq(q) of (3)-(7) for the n controller axes of a machine.

    limits: (n, 2) command range per axis, SI (m / rad): the normalization (7);
    prismatic: (n,) bool; orders: int or (n, n) table (-1: table off), rows =
    output axis i, columns = input axis j; pairs: optional list of enabled
    (i, j) (0-based), the others off; axis_names: names for parameters and
    tables (default q1..qn).

    Parameter ``coef`` (n, n, K), K = max order + 1; entries beyond a table's
    order and of switched-off tables are masked out (zero, not learned).

    Example:
        >>> lim = torch.tensor([[0.0, 1.0], [-3.0, 3.0]], dtype=torch.float64)
        >>> ap = AxisPerturbation(lim, torch.tensor([True, False]), orders=2, pairs=[(0, 0), (0, 1), (1, 1)])
        >>> ap.pairs, ap.delta(torch.zeros(4, 2, dtype=torch.float64)).shape
        ([(0, 0), (0, 1), (1, 1)], torch.Size([4, 2]))
    """

    def __init__(self, limits: torch.Tensor, prismatic, orders=6, pairs=None, axis_names: Sequence[str] | None = None):
        super().__init__()
        limits = torch.as_tensor(limits, dtype=torch.float64)
        n = limits.shape[0]
        if limits.shape != (n, 2) or not bool((limits[:, 0] < limits[:, 1]).all()):
            raise ValueError(f"axis perturbation: limits must be (n, 2) with lower < upper, got {limits.tolist()}")
        table = order_table(orders, n, pairs)
        K = int(table.max().clamp(min=0)) + 1
        self.axis_names = list(axis_names or [f"q{i + 1}" for i in range(n)])
        if len(self.axis_names) != n:
            raise ValueError(f"axis perturbation: {len(self.axis_names)} axis names for {n} axes")
        self.register_buffer("limits", limits.clone())
        self.register_buffer("prismatic", torch.as_tensor(prismatic, dtype=torch.bool).clone())
        self.register_buffer("orders", table)
        self.register_buffer("mask", torch.arange(K)[None, None, :] <= table[..., None])
        self.coef = nn.Parameter(torch.zeros(n, n, K, dtype=torch.float64))

    # ----------------------------------------------------------- the table interface
    @property
    def n(self) -> int:
        return self.limits.shape[0]

    @property
    def pairs(self) -> list[tuple[int, int]]:
        """Enabled tables as (output axis i, input axis j), 0-based, row-major."""
        return [(int(i), int(j)) for i, j in (self.orders >= 0).nonzero().tolist()]

    def normalized(self, q: torch.Tensor) -> torch.Tensor:
        """Commands (..., n) SI -> qbar (..., n) in [-1, 1] over the limits, (7)."""
        return normalize(q, self.limits[:, 0].to(q), self.limits[:, 1].to(q))

    def masked_coef(self) -> torch.Tensor:
        """(n, n, K) coefficients with the switched-off entries zeroed."""
        return self.coef * self.mask

    def delta(self, q: torch.Tensor) -> torch.Tensor:
        """dq(q) (3): commands (B, n) SI -> command perturbations (B, n) SI (m / rad per output axis)."""
        return perturbation(self.masked_coef(), self.normalized(q))

    def forward(self, q: torch.Tensor) -> torch.Tensor:
        """Same as :meth:`delta`."""
        return self.delta(q)

    def f(self, i: int, j: int, x: torch.Tensor) -> torch.Tensor:
        """Table function f_ij (6) at input-axis values x (K,) SI -> (K,) SI (output axis i's unit).

        Zero for a table that is switched off.
        """
        x = torch.as_tensor(x, dtype=self.coef.dtype, device=self.coef.device)
        lam = normalize(x, self.limits[j, 0], self.limits[j, 1])
        return (chebyshev(lam, self.coef.shape[-1] - 1) * self.masked_coef()[i, j]).sum(-1)

    def df(self, i: int, j: int, x: torch.Tensor) -> torch.Tensor:
        """d f_ij / d q_j at x (K,) SI -> (K,) (output unit per input unit, e.g. m/rad)."""
        x = torch.as_tensor(x, dtype=self.coef.dtype, device=self.coef.device)
        lam = normalize(x, self.limits[j, 0], self.limits[j, 1])
        _, d = chebyshev_with_derivative(lam, self.coef.shape[-1] - 1)
        scale = 2.0 / (self.limits[j, 1] - self.limits[j, 0])
        return (d * self.masked_coef()[i, j]).sum(-1) * scale

    def slopes(self, q: torch.Tensor) -> torch.Tensor:
        """D(q) = d dq / d q (B, n, n): D[b, i, j] = f_ij'(q_j) (the paper's (35), (42)-(44) slopes)."""
        lam = self.normalized(q)
        _, d = chebyshev_with_derivative(lam, self.coef.shape[-1] - 1)  # (B, n_j, K)
        scale = 2.0 / (self.limits[:, 1] - self.limits[:, 0])
        return torch.einsum("bjk,ijk->bij", d, self.masked_coef()) * scale.to(q)

    def design(self, q: torch.Tensor) -> torch.Tensor:
        """Chebyshev values (B, n, K) of each input axis' normalized command: d dq_i / d a_k,ij = design[b, j, k]."""
        return chebyshev(self.normalized(q), self.coef.shape[-1] - 1)

    # ------------------------------------------------------------ declarations
    def entry_names(self, prefix: str = "axis") -> list[str]:
        """Name of every ``coef`` entry (row-major), e.g. 'axis.f_Z_B.c3' (output Z, input B)."""
        n, _, K = self.coef.shape
        names = self.axis_names
        return [f"{prefix}.f_{names[i]}_{names[j]}.c{k}" for i in range(n) for j in range(n) for k in range(K)]

    def param_groups(self, prefix: str = "axis_errors") -> list[ParamGroup]:
        """``coef``, role 'axis': kind = that of the OUTPUT axis i (length for prismatic, angle for
        revolute); prior sigma :data:`PRIOR_SIGMA_LENGTH` (1 mm) / :data:`PRIOR_SIGMA_ANGLE` (1 mrad)
        for every order. Only enabled tables' existing orders are in the mask."""
        n, _, K = self.coef.shape
        out_prismatic = self.prismatic.cpu()[:, None, None].expand(n, n, K).flatten().tolist()
        kinds = [LENGTH if p else ANGLE for p in out_prismatic]
        sigma = torch.tensor([PRIOR_SIGMA_LENGTH if p else PRIOR_SIGMA_ANGLE for p in out_prismatic], dtype=torch.float64)
        return [ParamGroup(f"{prefix}.coef", "axis", self.entry_names(), kinds, sigma, self.mask.clone())]
