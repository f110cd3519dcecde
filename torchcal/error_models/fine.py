"""Fine-grained joint-angle errors: one piecewise-linear angle-error table per joint (beyond the papers).

What is left of a real arm's error after the geometric model (Paper II (19)-(24))
is often fine-grained in the joint angles: gear and encoder errors that repeat
every few degrees. Poses less than 0.1 rad apart then have errors that
correlate strongly while an order <= 10 Chebyshev series over the whole range
cannot follow them. This module adds, to each joint's variable,

    Δθ_i(θ_i) = Σ_k v_ik · w_k(θ_i)          (hat functions on knots spaced h_i)

evaluated at the commanded joint variable θ(q) (the joint errors v of the
implicit loop do not enter it, as for the gravity compliance). The knots span
the range the identification data covers, [lower_i, upper_i]; outside it the
table **holds its end value** (θ is clamped onto the range): a table knows
nothing beyond its data, and holding the last value keeps the correction
bounded where a polynomial or harmonic series would run away. A smoothness
block (:class:`SmoothnessPenalty`, second differences of the table) regularises
what the data leave free between knots; its weight per joint is chosen by
held-out validation (see ``experiments/ur10_tmac/run.py``).

Everything is SI (rad).
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from typing import Any

import torch
from torch import nn

from ..core.params import ANGLE, ParamGroup

DEFAULT_SPACING = 0.05
"""Knot spacing (rad) of the tables: about 3 degrees."""

DEFAULT_PRIOR = 1e-3
"""Prior sigma (rad, ~0.06 deg) of each table value: fine-grained errors are a fraction of a milliradian."""


def knot_counts(lower: torch.Tensor, upper: torch.Tensor, spacing: torch.Tensor) -> torch.Tensor:
    """(n,) number of knots covering [lower, upper] with spacing at most ``spacing`` (at least 2)."""
    return (torch.ceil((upper - lower) / spacing - 1e-9).clamp(min=1) + 1).to(torch.long)


def hat_weights(theta: torch.Tensor, lower: torch.Tensor, step: torch.Tensor, counts: torch.Tensor, width: int):
    """Piecewise-linear interpolation weights of each joint's table, ends held.

    theta: (B, n) joint variables; lower: (n,) first knot; step: (n,) knot
    spacing; counts: (n,) knots per joint (>= 2); width: K >= max(counts).
    -> w (B, n, K) (two non-zero weights summing to 1 per joint) and dw/dθ
    (B, n, K) (zero outside the table's range, where the end value is held).
    """
    upper = lower + step * (counts - 1).to(step)
    inside = (theta >= lower) & (theta <= upper)
    t = (torch.minimum(torch.maximum(theta, lower), upper) - lower) / step
    k0 = torch.minimum(torch.floor(t), (counts - 2).to(t)).clamp(min=0)
    f = (t - k0).clamp(0.0, 1.0)  # rounding at the upper end must not give a negative weight
    k0 = k0.to(torch.long)
    B, n = theta.shape
    w = torch.zeros(B, n, width, dtype=theta.dtype, device=theta.device)
    w = w.scatter(2, k0[..., None], (1 - f)[..., None]).scatter_add(2, (k0 + 1)[..., None], f[..., None])
    g = (inside.to(theta.dtype) / step)[..., None]
    dw = torch.zeros_like(w).scatter(2, k0[..., None], -g).scatter_add(2, (k0 + 1)[..., None], g)
    return w, dw


class FineJointErrors(nn.Module):
    """Additive joint-angle error tables Δθ_i(θ_i) (B, n) on knots, one per joint.

    lower, upper: (n,) range of each joint variable the table covers (rad,
    usually the identification data's, see :meth:`from_data`); spacing: knot
    spacing, float or (n,) (rad, default :data:`DEFAULT_SPACING`); joints:
    indices of the joints that get a table (default all; the others stay
    zero); joint_names: for the entry names ('elbow_joint.fine.k12').
    Parameter ``values`` (n, K) rad, masked to each joint's knots.
    Outside [lower_i, upper_i] the end value is held.

    Example:
        >>> import torch
        >>> fe = FineJointErrors(torch.tensor([0.0, -1.0]), torch.tensor([1.0, 1.0]), spacing=0.25)
        >>> fe.counts.tolist(), fe(torch.zeros(3, 2, dtype=torch.float64)).shape
        ([5, 9], torch.Size([3, 2]))
    """

    def __init__(self, lower, upper, spacing=DEFAULT_SPACING, joints: Sequence[int] | None = None,
                 joint_names: Sequence[str] | None = None, prior_sigma: float = DEFAULT_PRIOR):
        super().__init__()
        lower = torch.as_tensor(lower, dtype=torch.float64).flatten()
        upper = torch.as_tensor(upper, dtype=torch.float64).flatten()
        n = lower.numel()
        spacing = torch.as_tensor(spacing, dtype=torch.float64).expand(n).clone()
        if upper.shape != (n,) or not bool((upper > lower).all()):
            raise ValueError(f"FineJointErrors: upper {upper.tolist()} must exceed lower {lower.tolist()} per joint")
        if not bool((spacing > 0).all()):
            raise ValueError(f"FineJointErrors: knot spacing must be positive, got {spacing.tolist()}")
        joints = list(range(n)) if joints is None else [int(j) for j in joints]
        if any(j < 0 or j >= n for j in joints):
            raise ValueError(f"FineJointErrors: joints {joints} out of range 0..{n - 1}")
        counts = knot_counts(lower, upper, spacing)
        # the knots cover [lower, upper] exactly: the spacing shrinks to fit
        step = (upper - lower) / (counts - 1).to(torch.float64)
        on = torch.zeros(n, dtype=torch.bool)
        on[joints] = True
        counts = torch.where(on, counts, torch.full_like(counts, 2))
        K = int(counts[on].max()) if joints else 2
        self.joint_names = list(joint_names or [f"joint{i + 1}" for i in range(n)])
        self.prior = float(prior_sigma)
        self.register_buffer("lower", lower.clone())
        self.register_buffer("upper", upper.clone())
        self.register_buffer("spacing", spacing.clone())
        self.register_buffer("step", step)
        self.register_buffer("counts", counts)
        self.register_buffer("joints", torch.tensor(joints, dtype=torch.long))
        self.register_buffer("mask", (torch.arange(K)[None, :] < counts[:, None]) & on[:, None])
        self.values = nn.Parameter(torch.zeros(n, K, dtype=torch.float64))

    @classmethod
    def from_data(cls, theta: torch.Tensor, spacing=DEFAULT_SPACING, joints=None, joint_names=None,
                  prior_sigma: float = DEFAULT_PRIOR) -> FineJointErrors:
        """Tables over the range (R, n) joint variables ``theta`` cover (the identification data's)."""
        theta = torch.as_tensor(theta, dtype=torch.float64)
        lo, hi = theta.min(0).values, theta.max(0).values
        hi = torch.maximum(hi, lo + 1e-6)
        return cls(lo.cpu(), hi.cpu(), spacing, joints, joint_names, prior_sigma).to(theta.device)

    @property
    def n(self) -> int:
        return self.values.shape[0]

    def knots(self, i: int) -> torch.Tensor:
        """(counts_i,) knot positions (rad) of joint i."""
        k = torch.arange(int(self.counts[i]), dtype=self.step.dtype, device=self.step.device)
        return self.lower[i] + k * self.step[i]

    def weights(self, theta: torch.Tensor):
        """Interpolation weights (B, n, K) and their θ-derivatives (B, n, K) at joint variables (B, n)."""
        return hat_weights(theta, self.lower, self.step, self.counts, self.values.shape[1])

    def forward(self, theta: torch.Tensor) -> torch.Tensor:
        """Δθ (B, n) at joint variables θ (B, n), rad."""
        w, _ = self.weights(theta)
        return (w * (self.values * self.mask)).sum(-1)

    def slope(self, theta: torch.Tensor) -> torch.Tensor:
        """dΔθ_i/dθ_i (B, n) (zero where the end value is held)."""
        _, dw = self.weights(theta)
        return (dw * (self.values * self.mask)).sum(-1)

    def entry_names(self) -> list[str]:
        n, K = self.values.shape
        return [f"{self.joint_names[i]}.fine.k{k}" for i in range(n) for k in range(K)]

    def param_groups(self, prefix: str = "fine") -> list[ParamGroup]:
        """``values``: angles (rad), prior :data:`DEFAULT_PRIOR` each, role 'fine' (the joint priors of
        :class:`~torchcal.identify.Prior` do not override it), only each joint's knots in the mask."""
        k = self.values.numel()
        return [ParamGroup(f"{prefix}.values", "fine", self.entry_names(), [ANGLE] * k,
                           torch.full((k,), self.prior, dtype=torch.float64), self.mask.clone())]

    def spec(self) -> dict[str, Any]:
        """Structure for :meth:`RobotModel.spec` (the table values live in the state dict)."""
        return {"lower": self.lower.tolist(), "upper": self.upper.tolist(), "spacing": self.spacing.tolist(),
                "joints": self.joints.tolist(), "prior_sigma": self.prior}


def build_fine(robot, option) -> FineJointErrors | None:
    """The RobotModel ``fine=`` argument -> module or None.

    option: None/False (off); a :class:`FineJointErrors`; or a dict of its
    keywords (lower, upper, spacing, joints, prior_sigma), as :meth:`FineJointErrors.spec` writes.
    """
    if option is None or option is False:
        return None
    if isinstance(option, FineJointErrors):
        return option
    if isinstance(option, dict):
        kw = dict(option)
        missing = [k for k in ("lower", "upper") if k not in kw]
        if missing:
            raise ValueError(f"fine joint errors: missing {missing} (rad, the range each table covers)")
        names = list(robot.chain.joint_names) if robot is not None else None
        return FineJointErrors(kw.pop("lower"), kw.pop("upper"), joint_names=names, **kw)
    raise ValueError(f"fine joint errors: expected None, False, a FineJointErrors or a dict, got {type(option).__name__}")


class SmoothnessPenalty:
    """Second-difference smoothness of the fine tables, a ParamBlock (:mod:`torchcal.identify.blocks`).

    r_ik = (v_i,k-1 - 2 v_i,k + v_i,k+1) / sigma_i for every interior knot of
    every joint with a table: a Gaussian prior on the table's curvature, sigma_i
    (rad) the plausible second difference per knot of joint i (small: smooth,
    large: free). Its null space is the constant and the linear trend, which
    the geometric terms own. Entries pinned by the gauge enter at their
    current value.

    fine: the model's :class:`FineJointErrors`; sigma: float or (n,) rad
    (inf switches a joint's penalty off).

    Example:
        >>> import torch
        >>> fe = FineJointErrors(torch.zeros(1), torch.ones(1), spacing=0.25)
        >>> SmoothnessPenalty(fe, 1e-4).rows
        3
    """

    def __init__(self, fine: FineJointErrors, sigma):
        n, K = fine.values.shape
        sigma = torch.as_tensor(sigma, dtype=torch.float64).expand(n)
        names = fine.entry_names()
        rows, cols, vals = [], [], []
        r = 0
        for i in fine.joints.tolist():
            s = float(sigma[i])
            if not math.isfinite(s):
                continue
            for k in range(1, int(fine.counts[i]) - 1):
                for dk, c in ((-1, 1.0), (0, -2.0), (1, 1.0)):
                    rows.append(r)
                    cols.append(i * K + k + dk)
                    vals.append(c / s)
                r += 1
        self.rows = r
        self.fine = fine
        self.names = names
        D = torch.zeros(r, n * K, dtype=torch.float64)
        if r:
            D[torch.tensor(rows), torch.tensor(cols)] = torch.tensor(vals, dtype=torch.float64)
        self.D = D
        self._cache = None

    def _bind(self, layout):
        key = (id(layout), tuple(layout.names()))
        if self._cache is None or self._cache[0] != key:
            where = {nm: j for j, nm in enumerate(layout.names())}
            idx_p = [k for k, nm in enumerate(self.names) if nm in where]
            idx_x = [where[self.names[k]] for k in idx_p]
            self._cache = (key, torch.tensor(idx_p, dtype=torch.long), torch.tensor(idx_x, dtype=torch.long))
        return self._cache[1], self._cache[2]

    def linearize(self, x: torch.Tensor, layout) -> tuple[torch.Tensor, torch.Tensor]:
        """x: (P,) free values -> r (rows,), dr/dx (rows, P)."""
        idx_p, idx_x = self._bind(layout)
        idx_p, idx_x = idx_p.to(x.device), idx_x.to(x.device)
        full = self.fine.values.detach().flatten().to(x)
        full = full.index_put((idx_p,), x[idx_x])
        D = self.D.to(x)
        J = torch.zeros(self.rows, x.numel(), dtype=x.dtype, device=x.device)
        J[:, idx_x] = D[:, idx_p]
        return D @ full, J
