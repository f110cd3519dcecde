"""The implicit-loop maximum-likelihood objective of Paper II (31)-(33), for any instrument.

    V(v, b) = sum_r |S_r (h(q_r + v_r; b) - y_r)|^2            instrument residuals, d per row (31)-(32)
            + sum_r v_r^T Sigma_v(s_r)^-1 v_r                  joint positioning errors (32)
            + (b - b_0)^T Sigma_b^-1 (b - b_0)                 prior (Paper III (31))
            + sum_blocks |r_k(b)|^2                            parameter-only blocks (full-covariance prior, ...)

with one joint-error vector v_r per measured row (pose x tool configuration),
h what the instrument reports for the modeled robot (:mod:`torchcal.measure`;
tool points in the measurement frame for Paper II, d = 3), S_r its per-row
whitening, Sigma_v from the forward/backward joint variances chosen by each
joint's approach direction, and the prior fixing the gauge: constant terms of
neighbouring E_i are redundant (only combinations are identifiable), and a weak
prior picks the smallest-norm member of each redundant family instead of
letting the solver wander. Everything is whitened so that V is a plain sum of
squares. All residuals go through one function (:func:`raw_residual`).
"""

from __future__ import annotations

import logging
from dataclasses import dataclass, field

import torch

from ..core.exceptions import InputError
from torch.func import functional_call

from ..core import units
from ..measure import Instrument, PointTargets, row_jacobians
from ..core.measurements import Measurements
from .blocks import block_cost
from .layout import ParameterLayout

log = logging.getLogger("torchcal")

# Paper II, Table 5: joint variances of the FANUC LR Mate 200i, deg^2, forward / backward
PAPER2_JOINT_VAR_FWD = (3.6e-6, 3.6e-7, 8.4e-6, 3.0e-5, 2.7e-5, 5.6e-4)
PAPER2_JOINT_VAR_BWD = (2.6e-6, 2.5e-7, 2.0e-6, 1.4e-5, 5.6e-5, 3.6e-4)


@dataclass
class NoiseModel:
    """Measurement and joint-repeatability noise, SI.

    sigma_m: tracker standard deviation per axis (m); joint_var_fwd / _bwd:
    (n,) joint variances (rad^2 / m^2) for forward / backward approach;
    source: where the joint variances come from (logged by :func:`fit`).

    Example:
        >>> import torchcal
        >>> noise = NoiseModel.from_robot(torchcal.load_robot("abb_irb120"))  # its YAML's repeatability
        >>> round(noise.sigma_m * 1e3, 3), tuple(noise.joint_var_fwd.shape)
        (0.005, (6,))
    """

    sigma_m: float
    joint_var_fwd: torch.Tensor
    joint_var_bwd: torch.Tensor
    source: str = ""

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
        """sigma_m = 0.005 mm and the joint variances of Table 5 (FANUC LR Mate 200i): for explicit use."""
        out = cls.from_file_units(0.005, PAPER2_JOINT_VAR_FWD, PAPER2_JOINT_VAR_BWD)
        out.source = "Paper II, Table 5 (NoiseModel.paper2)"
        return out

    @classmethod
    def from_robot(cls, robot, sigma_m: float = 5e-6) -> "NoiseModel":
        """sigma_m (m) and the joint variances of ``robot.repeatability`` (its YAML's ``repeatability:``).

        Raises :class:`~torchcal.kinematics.URDFError` (a ValueError) naming the robot when it declares none.
        """
        rep = getattr(robot, "repeatability", None)
        if rep is None:
            from ..kinematics.urdf import URDFError

            name = getattr(robot, "name", repr(robot))
            src = getattr(robot, "source", "")
            raise URDFError(f"robot '{name}'{f' ({src})' if src else ''} declares no joint repeatability: add a "
                             f"'repeatability:' section (joint_var_fwd, joint_var_bwd in deg², source) to its YAML, "
                             f"or pass noise=NoiseModel(...) explicitly")
        return cls(float(sigma_m), rep.var_fwd.clone(), rep.var_bwd.clone(), rep.source or getattr(robot, "name", ""))

    def joint_variance(self, direction: torch.Tensor) -> torch.Tensor:
        """(R, n) variance of each row's joint error: forward, backward, or their mean where unknown."""
        fwd = self.joint_var_fwd.to(direction)
        bwd = self.joint_var_bwd.to(direction)
        return torch.where(direction > 0, fwd, torch.where(direction < 0, bwd, 0.5 * (fwd + bwd)))


@dataclass
class Prior:
    """Gaussian prior on the error parameters, centred on ``mean`` (default zero: no error).

    Each entry's sigma is its module's declared prior (:class:`torchcal.core.params.ParamGroup`),
    overridden by role and kind where a field here is set (None keeps the
    declaration): role 'joint' takes rotation (angles, rad) / translation
    (lengths, m); 'backlash' takes backlash (rad, every coefficient; None keeps
    the declared wide c0 and tight c1.., see
    :data:`torchcal.error_models.joint.BACKLASH_VARIATION_SIGMA`); 'frame' / 'tool' take frame_rotation /
    frame_translation; 'compliance' takes compliance (``compliance.coef``, rad
    per unit configuration function: per unit sin/cos in 'functions' mode,
    rad/(N·m) in 'gravity' mode). Nothing is read from parameter names.
    Besides the exact redundancies that :mod:`.gauge` pins, an
    order-m model has near-redundant directions (a constant error after joint
    i is a sin/cos of q_i before it, which a Chebyshev series reproduces to
    ~1e-6): the data cannot place the model along them, the prior does. The
    defaults are ~1e-5 of the data's information on well-determined
    combinations and about 20x the paper's largest constant errors.
    mean, std: (P,) in the order of the full layout (before gauge fixing), SI
    (std, when given, is every entry's sigma: e.g. a fleet's spread,
    :func:`torchcal.identify.fleet.fleet_prior`).

    Example:
        >>> Prior(rotation=None).rotation is None  # None: every joint angle term keeps its module's declared sigma
        True
        >>> Prior(backlash=1e-3).backlash  # one sigma (rad) for every backlash coefficient
        0.001
    """

    rotation: float | None = 1e-2
    translation: float | None = 1e-3
    frame_rotation: float | None = 0.1
    frame_translation: float | None = 1e-2
    mean: torch.Tensor | None = field(default=None, repr=False)
    compliance: float | None = 1e-2
    backlash: float | None = None
    std: torch.Tensor | None = field(default=None, repr=False)

    def sigma(self, layout: ParameterLayout) -> torch.Tensor:
        """(P,) prior standard deviations in layout order (declared, then overridden by role + kind; ``std``,
        when given, replaces them all)."""
        if self.std is not None:
            std = torch.as_tensor(self.std, dtype=torch.float64).reshape(-1)
            if std.numel() != layout.size:
                raise ValueError(f"Prior.std has {std.numel()} entries, the model's layout {layout.size}")
            if not bool((std > 0).all()):
                raise ValueError("Prior.std: every standard deviation must be positive")
            return std.cpu()
        # per layout (its entries never change) and setting: an online calibration asks once per batch
        key = (self.rotation, self.translation, self.frame_rotation, self.frame_translation, self.compliance,
               self.backlash)
        cache = layout.__dict__.setdefault("_prior_sigma", {})
        if key not in cache:
            cache[key] = self._sigma(layout)
        return cache[key].clone()

    def _sigma(self, layout: ParameterLayout) -> torch.Tensor:
        sigma = layout.prior_sigma().tolist()
        for i, (role, kind) in enumerate(zip(layout.roles(), layout.kinds())):
            if role == "joint":
                o = {"angle": self.rotation, "length": self.translation}.get(kind)
            elif role == "backlash":
                o = self.backlash
            elif role in ("frame", "tool"):
                o = {"angle": self.frame_rotation, "length": self.frame_translation}.get(kind)
            elif role == "compliance":
                o = self.compliance
            else:
                o = None
            if o is not None:
                sigma[i] = float(o)
        return torch.tensor(sigma, dtype=torch.float64)

    def precision(self, layout: ParameterLayout) -> torch.Tensor:
        """(P,) inverse variances in layout order."""
        return 1.0 / self.sigma(layout) ** 2


def raw_residual(model, instrument: Instrument, q, tool, direction, v, observed, params=None) -> torch.Tensor:
    """THE residual: what ``instrument`` reports for ``model`` minus what it reported.  -> (B, d), unwhitened.

    q: (B, n); tool: (B,); direction: (B, n) or None; v: (B, n) or None;
    observed: (B, d); params: optional {name: tensor} replacing model
    parameters (functional, differentiable).
    """
    if params:
        pred = functional_call(_InstrumentPredict(model, instrument), _prefixed(params), (q, tool, direction, v))
    else:
        pred = instrument.predict(model, q, tool, direction, v)
    return instrument.residual(pred, observed)


class _InstrumentPredict(torch.nn.Module):
    """instrument.predict(model, ...) as a module whose parameters are the model's (for functional_call)."""

    def __init__(self, model, instrument):
        super().__init__()
        self.model = model
        self.instrument = instrument

    def forward(self, q, tool, direction, v):
        return self.instrument.predict(self.model, q, tool, direction, v)


def _prefixed(params: dict) -> dict:
    return {f"model.{k}": t for k, t in params.items()}


def default_instrument(data: Measurements, noise: NoiseModel) -> PointTargets:
    """Paper II's instrument: the tracker points of ``data``, isotropic sigma_m."""
    return PointTargets.from_measurements(data, noise.sigma_m)


def row_errors(model, data: Measurements, instrument: Instrument | None = None, v=None) -> torch.Tensor:
    """(R,) norm of each row's raw residual (m for point targets), joint errors v (default zero)."""
    if instrument is None:
        if torch.isnan(data.xyz).any():
            raise InputError(f"{data.source or 'the measurements'}: data has rows without a measured x, y, z")
        instrument = PointTargets(data.xyz, sigma=1.0)
    with torch.no_grad():
        r = raw_residual(model, instrument, data.q, data.tool, data.direction if data.has_direction else None, v,
                         instrument.observed)
    return r.norm(dim=-1)


class CalibrationProblem:
    """Whitened residuals and Jacobians of V for one model, one instrument and one data set.

    model: a :class:`torchcal.models.robot.RobotModel` (or any module the instrument
    can predict from, its parameters declared, see
    :func:`~torchcal.identify.layout.parameter_groups`); data: identification
    rows (q, tool, direction, pose); noise: joint variances (and sigma_m for
    the default instrument); prior: diagonal prior (None for none: then
    redundant combinations are left to the solver's damping); fixed:
    parameter names held fixed; instrument: the measurement model (default:
    :class:`~torchcal.measure.PointTargets` on ``data.xyz`` with sigma_m);
    blocks: parameter-only residual blocks (:mod:`.blocks`); fixed_rows: (R,)
    bool, rows whose joint errors are held at v0 (R, n) rather than solved for.
    jacobian: 'auto' (closed form where the instrument/model give it, else
    autograd), 'closed' or 'autodiff'; layout: this model's ParameterLayout with
    ``fixed`` held when the caller has built it (an online calibration builds a
    problem per batch), else built here.
    """

    def __init__(self, model, data: Measurements, noise: NoiseModel, prior: Prior | None = Prior(), fixed=(),
                 instrument: Instrument | None = None, blocks=(), fixed_rows: torch.Tensor | None = None,
                 v0: torch.Tensor | None = None, jacobian: str = "auto", layout: ParameterLayout | None = None):
        if jacobian not in ("auto", "closed", "autodiff"):
            raise ValueError(f"jacobian must be 'auto', 'closed' or 'autodiff', got {jacobian!r}")
        device = model.device
        self.model = model
        self.data = data.to(device)
        self.noise = noise
        if instrument is None:
            instrument = default_instrument(data, noise)
        if len(instrument) != len(data):
            raise ValueError(f"{data.source}: the instrument has {len(instrument)} rows, the data {len(data)}")
        if own := instrument.own_parameters():  # an instrument's station or scale left unestimated, silently
            log.warning("the instrument %s holds parameters (%s) that the fit does not estimate: it estimates the "
                        "model's only (put them on the model, e.g. as its measurement frame, or fix them)",
                        type(instrument).__name__, ", ".join(own))
        self.instrument = instrument.to(device)
        self.observed = self.instrument.observed
        self.blocks = list(blocks)
        self.jacobian = jacobian
        if layout is not None and (layout.model is not model or layout.fixed != ParameterLayout.fixed_names(fixed)):
            raise ValueError("CalibrationProblem: the layout given is not this model's with these groups fixed")
        self.layout = ParameterLayout(model, fixed) if layout is None else layout
        self.direction = self.data.direction if data.has_direction else None
        R, n = self.data.q.shape
        var = noise.joint_variance(self.data.direction)
        self.estimate_v = bool((var > 0).all())
        # without joint variances the joint errors are not estimated: unit weight and a zero Jacobian keep v at 0
        self.w_v = 1.0 / var if self.estimate_v else torch.ones_like(var)
        fr = torch.zeros(R, dtype=torch.bool, device=device) if fixed_rows is None else torch.as_tensor(fixed_rows).to(device)
        if fr.shape != (R,) or fr.dtype != torch.bool:
            raise ValueError(f"fixed_rows must be a ({R},) bool mask, got {tuple(fr.shape)} {fr.dtype}")
        self.fixed_rows = fr
        self.v_free = (~fr) & self.estimate_v  # (R,) rows whose joint errors are solved for
        if v0 is None:
            self.v0 = torch.zeros_like(self.data.q)
        else:
            v0 = torch.as_tensor(v0).to(self.data.q)
            if v0.shape != (R, n):
                raise ValueError(f"v0 must have shape ({R}, {n}), got {tuple(v0.shape)}")
            self.v0 = v0.clone()  # the start of every row; fixed rows stay there
        # the v term of V counts only rows whose v is solved for (a fixed row's is a constant)
        self.w_v_cost = self.w_v * self.v_free[:, None].to(self.w_v)
        if prior is None:
            self.prior_precision = torch.zeros(self.layout.size, dtype=torch.float64, device=device)
            self.prior_mean = torch.zeros(self.layout.size, dtype=torch.float64, device=device)
        else:
            self.prior_precision = prior.precision(self.layout).to(device)
            self.prior_mean = (prior.mean if prior.mean is not None else torch.zeros(self.layout.size, dtype=torch.float64)).to(device)

    @property
    def inv_sigma_m(self) -> float:
        """1 / sigma of an isotropic instrument (compatibility; prefer ``instrument.whiten``)."""
        sigma = getattr(self.instrument.weight, "sigma", None)
        if sigma is None:
            raise AttributeError("the instrument's whitening is not isotropic; use problem.instrument.whiten / unwhiten")
        return 1.0 / sigma

    @property
    def dim(self) -> int:
        return self.instrument.dim

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
        """Starting joint errors (R, n): v0 on fixed rows, zero elsewhere."""
        return self.v0.clone()

    # ------------------------------------------------------------ residuals
    def whitened_residual(self, x: torch.Tensor, v: torch.Tensor) -> torch.Tensor:
        """Whitened residual (R, d) at free values x (P,) and joint errors v (R, n); differentiable in both."""
        raw = raw_residual(self.model, self.instrument, self.data.q, self.data.tool, self.direction, v, self.observed,
                           self.layout.as_dict(x))
        return self.instrument.whiten(raw)

    @torch.no_grad()
    def residual(self, x: torch.Tensor, v: torch.Tensor) -> torch.Tensor:
        """Whitened residual (R, d) at parameters x (also written into the model)."""
        self.layout.set(x)
        # x is the model's now: predict from it directly (functional_call's parameter swap, which
        # whitened_residual needs for gradients, is most of a small batch's residual)
        return self.instrument.whiten(raw_residual(self.model, self.instrument, self.data.q, self.data.tool,
                                                   self.direction, v, self.observed))

    def cost_from(self, f: torch.Tensor, x: torch.Tensor, v: torch.Tensor, block_cost_value=None) -> torch.Tensor:
        """V from a whitened residual and the current x, v (blocks evaluated at x unless their cost is given)."""
        dx = x - self.prior_mean
        cost = (f * f).sum() + (self.w_v_cost * v * v).sum() + (self.prior_precision * dx * dx).sum()
        if self.blocks:
            cost = cost + (block_cost(self.blocks, x, self.layout) if block_cost_value is None else block_cost_value)
        return cost

    def cost(self, x: torch.Tensor, v: torch.Tensor) -> torch.Tensor:
        return self.cost_from(self.residual(x, v), x, v)

    @torch.no_grad()
    def linearize(self, x: torch.Tensor, v: torch.Tensor, jacobian: str | None = None):
        """Whitened residual f (R, d), parameter Jacobian A (R, d, P) and joint-error Jacobian C (R, d, n).

        C is zero on rows whose joint errors are not solved for (fixed rows,
        or a noise model without joint variances).
        """
        mode = jacobian or self.jacobian
        self.layout.set(x)
        out = None
        if mode != "autodiff":
            out = self.instrument.predict_jacobians(self.model, self.data.q, self.data.tool, self.direction, v)
            if out is not None and not self.layout.has_jacobians(out[1]):
                out = None
            if out is None and mode == "closed":
                raise ValueError(f"{type(self.instrument).__name__} gives no closed-form Jacobians for every free group "
                                 f"of {type(self.model).__name__}")
        if out is not None:
            pred, J = out
            raw = self.instrument.residual(pred, self.observed)
            Jv = J["v"]
        else:
            raw, J, Jv = self._autodiff(x, v)
        f = self.instrument.whiten(raw)
        A = self.instrument.whiten(self.layout.flatten_jacobian(J, self.rows))
        C = self.instrument.whiten(Jv) * self.v_free[:, None, None].to(Jv)
        return f, A, C

    def _autodiff(self, x: torch.Tensor, v: torch.Tensor):
        """Raw residual (R, d), {group: (R, d, *shape)}, (R, d, n) by torch.func, vmapped over rows."""
        model, instrument = self.model, self.instrument
        wrapper = _InstrumentPredict(model, instrument)

        def fn(params, vr, q, tool, s, y):
            pred = functional_call(wrapper, _prefixed(params), (q, tool, s, vr))
            return instrument.residual(pred, y)

        with torch.enable_grad():
            raw, J, Jv = row_jacobians(fn, self.layout.as_dict(x), v, self.data.q, self.data.tool, self.direction,
                                       self.observed)
        return raw.detach(), {k: t.detach() for k, t in J.items()}, Jv.detach()
