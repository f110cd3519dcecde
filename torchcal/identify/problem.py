"""The implicit-loop maximum-likelihood objective of Paper II (31)-(33), with an optional prior.

    V(v, b) = sum_r |p_r - P(q_r + v_r; b)|^2 / sigma_m^2      measurement errors xi (31)-(32)
            + sum_r v_r^T Sigma_v(s_r)^-1 v_r                  joint positioning errors (32)
            + (b - b_0)^T Sigma_b^-1 (b - b_0)                 prior (Paper III (31))

with one joint-error vector v_r per measured row (pose x tool configuration),
Sigma_v from the forward/backward joint variances of Table 5 chosen by each
joint's approach direction, and the prior fixing the gauge: constant terms of
neighbouring E_i are redundant (only combinations are identifiable), and a weak
prior picks the smallest-norm member of each redundant family instead of
letting the solver wander. Everything is whitened so that V is a plain sum of
squares.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import torch

from .. import units
from ..measurements import Measurements
from .layout import ParameterLayout

# Paper II, Table 5: joint variances of the FANUC LR Mate 200i, deg^2, forward / backward
PAPER2_JOINT_VAR_FWD = (3.6e-6, 3.6e-7, 8.4e-6, 3.0e-5, 2.7e-5, 5.6e-4)
PAPER2_JOINT_VAR_BWD = (2.6e-6, 2.5e-7, 2.0e-6, 1.4e-5, 5.6e-5, 3.6e-4)


@dataclass
class NoiseModel:
    """Measurement and joint-repeatability noise, SI.

    sigma_m: tracker standard deviation per axis (m); joint_var_fwd / _bwd:
    (n,) joint variances (rad^2 / m^2) for forward / backward approach.
    """

    sigma_m: float
    joint_var_fwd: torch.Tensor
    joint_var_bwd: torch.Tensor

    @classmethod
    def from_file_units(cls, sigma_m_mm: float, var_fwd_deg2, var_bwd_deg2, prismatic=None) -> "NoiseModel":
        """Build from mm and deg^2 (mm^2 for prismatic joints), the config units."""
        fwd = torch.as_tensor(var_fwd_deg2, dtype=torch.float64)
        bwd = torch.as_tensor(var_bwd_deg2, dtype=torch.float64)
        prismatic = torch.zeros(fwd.shape[0], dtype=torch.bool) if prismatic is None else torch.as_tensor(prismatic)
        scale2 = units.joint_scale(prismatic) ** 2
        return cls(units.mm_to_m(float(sigma_m_mm)), fwd * scale2, bwd * scale2)

    @classmethod
    def paper2(cls) -> "NoiseModel":
        """sigma_m = 0.005 mm and the joint variances of Table 5."""
        return cls.from_file_units(0.005, PAPER2_JOINT_VAR_FWD, PAPER2_JOINT_VAR_BWD)

    def joint_variance(self, direction: torch.Tensor) -> torch.Tensor:
        """(R, n) variance of each row's joint error: forward, backward, or their mean where unknown."""
        fwd = self.joint_var_fwd.to(direction)
        bwd = self.joint_var_bwd.to(direction)
        return torch.where(direction > 0, fwd, torch.where(direction < 0, bwd, 0.5 * (fwd + bwd)))


@dataclass
class Prior:
    """Gaussian prior on the error parameters, centred on zero (no error).

    rotation / translation: sigma of the joint error terms (rad / m);
    frame_rotation / frame_translation: sigma of the base frame and tool
    corrections; compliance: sigma of the gravity compliance coefficients
    (``compliance.coef``, rad per unit configuration function: per unit sin/cos
    in 'functions' mode, rad/(N·m) in 'gravity' mode). Besides the exact
    redundancies that :mod:`.gauge` pins, an
    order-m model has near-redundant directions (a constant error after joint
    i is a sin/cos of q_i before it, which a Chebyshev series reproduces to
    ~1e-6): the data cannot place the model along them, the prior does. The
    defaults are ~1e-5 of the data's information on well-determined
    combinations and about 20x the paper's largest constant errors.
    """

    rotation: float = 1e-2
    translation: float = 1e-3
    frame_rotation: float = 0.1
    frame_translation: float = 1e-2
    mean: torch.Tensor | None = field(default=None, repr=False)
    compliance: float = 1e-2

    def precision(self, layout: ParameterLayout) -> torch.Tensor:
        """(P,) inverse variances in layout order."""
        rot = layout.is_rotation()
        frame = torch.tensor([n.startswith(("base.", "tool")) for n in layout.names()], dtype=torch.bool)
        comp = torch.tensor([n.startswith("compliance.") for n in layout.names()], dtype=torch.bool)
        sigma = torch.where(
            frame,
            torch.where(rot, self.frame_rotation, self.frame_translation),
            torch.where(rot, self.rotation, self.translation),
        ).to(torch.float64)
        sigma = torch.where(comp, torch.tensor(self.compliance, dtype=torch.float64), sigma)
        return 1.0 / sigma**2


class CalibrationProblem:
    """Whitened residuals and Jacobians of V for one model and one data set.

    model: a :class:`torchcal.model.RobotModel` (or anything with ``points`` and
    ``point_jacobians``); data: identification measurements; fixed: parameter
    names held fixed; prior: None for none (then redundant combinations are
    left to the solver's damping).
    """

    def __init__(self, model, data: Measurements, noise: NoiseModel, prior: Prior | None = Prior(), fixed=()):
        if torch.isnan(data.xyz).any():
            raise ValueError(f"{data.source}: identification data has rows without a measured x, y, z")
        self.model = model
        self.data = data.to(model.device)
        self.noise = noise
        self.layout = ParameterLayout(model, fixed)
        self.direction = self.data.direction if data.has_direction else None
        var = noise.joint_variance(self.data.direction)
        self.estimate_v = bool((var > 0).all())
        # without joint variances the joint errors are not estimated: unit weight and a zero Jacobian keep v at 0
        self.w_v = 1.0 / var if self.estimate_v else torch.ones_like(var)
        self.inv_sigma_m = 1.0 / noise.sigma_m
        if prior is None:
            self.prior_precision = torch.zeros(self.layout.size, dtype=torch.float64, device=model.device)
            self.prior_mean = torch.zeros(self.layout.size, dtype=torch.float64, device=model.device)
        else:
            self.prior_precision = prior.precision(self.layout).to(model.device)
            self.prior_mean = (prior.mean if prior.mean is not None else torch.zeros(self.layout.size, dtype=torch.float64)).to(model.device)

    def set_layout(self, layout: ParameterLayout) -> None:
        """Switch to another view of the free parameters (prior re-indexed to match)."""
        keep = self._entry_keep(layout)
        self.prior_precision = self.prior_precision[keep]
        self.prior_mean = self.prior_mean[keep]
        self.layout = layout

    def _entry_keep(self, new: ParameterLayout) -> torch.Tensor:
        """(P_old,) bool: which of the current free entries stay free in ``new``."""
        new_masks = {name: m for name, _, m in new.entries}
        keep = []
        for name, _, m in self.layout.entries:
            nm = new_masks.get(name)
            # a group the new layout pins entirely is absent from it: none of its entries stay
            keep.append(torch.zeros_like(m[m]) if nm is None else nm[m])
        return torch.cat(keep).to(self.prior_precision.device) if keep else torch.zeros(0, dtype=torch.bool)

    @property
    def rows(self) -> int:
        return len(self.data)

    def v_zero(self) -> torch.Tensor:
        return torch.zeros_like(self.data.q)

    @torch.no_grad()
    def residual(self, x: torch.Tensor, v: torch.Tensor) -> torch.Tensor:
        """Whitened measurement residual (R, 3) = (P(q + v) - p) / sigma_m at parameters x."""
        self.layout.set(x)
        p = self.model.points(self.data.q, self.data.tool, self.direction, v)
        return (p - self.data.xyz) * self.inv_sigma_m

    def cost_from(self, f: torch.Tensor, x: torch.Tensor, v: torch.Tensor) -> torch.Tensor:
        """V from a whitened residual and the current x, v."""
        dx = x - self.prior_mean
        return (f * f).sum() + (self.w_v * v * v).sum() + (self.prior_precision * dx * dx).sum()

    def cost(self, x: torch.Tensor, v: torch.Tensor) -> torch.Tensor:
        return self.cost_from(self.residual(x, v), x, v)

    @torch.no_grad()
    def linearize(self, x: torch.Tensor, v: torch.Tensor):
        """Whitened residual f (R, 3), parameter Jacobian A (R, 3, P) and joint-error Jacobian C (R, 3, n)."""
        self.layout.set(x)
        p, J = self.model.point_jacobians(self.data.q, self.data.tool, self.direction, v)
        f = (p - self.data.xyz) * self.inv_sigma_m
        A = self.layout.flatten_jacobian(J, self.rows) * self.inv_sigma_m
        C = J["v"] * self.inv_sigma_m if self.estimate_v else torch.zeros_like(J["v"])
        return f, A, C
