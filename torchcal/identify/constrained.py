"""Paper I's slope constraint: the constrained MLE, the constraint sweep and the choice of c.

Why one module: Paper I's slope constraint (31) as one method: the penalty block, the constrained fit, the constraint sweep and its knee (3.4, Figure 14), auto_constraint.

Paper I (Ma, Bristow, Landers) identifies the axis perturbation model by the
implicit-loop MLE (11)-(12) SUBJECT TO a bound on the tool-tip modeled-error
slope over the whole axis space:

    min  sum_k v_k^T S_v^-1 v_k + xi_k^T S_xi^-1 xi_k            (11)-(12)
    s.t. |hbar_i(q)|_2 <= c   for every axis i and every q       (31)

hbar_i (29)-(30) is the slope of the modeled tool-tip error along axis i,
scaled to half the axis range (m per half axis motion; Paper I picks c = 0.4
mm), computed in :mod:`torchcal.identify.slope` (closed form for machines,
autograd for robots). "Every q" is a dense, seeded quasi-random point set over
the WHOLE command box plus its faces and corners (:func:`slope_points`), where
nothing was measured too; the result reports the slope at fresh points the
constraint never saw.

Where things are:

- :func:`fit_constrained`: the constrained MLE. Default solver 'sqp': a
  Levenberg-Marquardt whose every step minimizes the damped Gauss-Newton model
  (axis errors eliminated per row, as in :mod:`torchcal.identify.lm`) subject
  to the linearized bound, exactly (:func:`solve_qp`, least-distance
  programming by one NNLS), with an l1 merit line search; the bound is imposed
  at c (1 - 0.02) so that it also holds between the points; fresh points that
  still exceed c join the point set with the local slope maxima climbed from
  the worst points (:func:`~torchcal.identify.slope.worst_points`). Solver
  'penalty': an augmented-Lagrangian loop around :func:`torchcal.fit` with
  :class:`SlopePenalty` (for L-BFGS or any :func:`torchcal.fit` option; the
  hinge makes LM crawl there: 5-50 s per fit against ~1-4 s);
- :class:`SlopePenalty`: the bound as a parameter-only residual block
  (:mod:`torchcal.identify.blocks`): hinge residuals w max(0, |hbar| - c + s)
  and their Jacobian (closed form for machines), usable in any :func:`torchcal.fit`;
- :func:`constraint_sweep`, :func:`pick_knee`, :func:`auto_constraint`: Paper I
  3.4 and Figure 14: fit the sub-identification set (identification minus the
  BORDER points) for a range of c, read the knee, refit all data with it.

Everything is SI inside: c and slopes in m (per half axis motion); the sweep's
:meth:`SweepResult.table` speaks mm.
"""

from __future__ import annotations

import copy
import logging
import math
import time
import warnings
import weakref
from dataclasses import dataclass, field

import numpy as np
import torch
from torch import nn

from ..core import progress
from ..core.exceptions import TorchcalError
from ..core.measurements import Measurements, pose_first_rows
from ..core.threads import threads_for_work
from .fit import fit, resolve_noise, warns_once
from .layout import ParameterLayout
from .problem import NoiseModel, Prior, row_errors
from .result import FitResult
from .slope import (is_machine_model, cat_contexts, context_rows, functional_slope_norms, machine_slope_norm_jacobian,
                    robot_fast_path, robot_pair_terms, robot_slope_terms, slope_context, slope_model, slope_norms,
                    slope_points, tool_vectors, worst_points)

log = logging.getLogger("torchcal")

DEFAULT_POINTS = 512
"""Quasi-random points inside the command box for the penalty (plus count // 8 on each face and the corners)."""


class ConstraintError(TorchcalError, ValueError):
    """A constrained fit that did not meet its slope bound (infeasible c, or no convergence).

    ``result`` holds the partial :class:`ConstrainedFitResult` (the model is left at its values).
    """

    def __init__(self, message: str, result=None):
        super().__init__(message)
        self.result = result


# ------------------------------------------------------------------ the penalty block
def _as_dict_matmul(layout: ParameterLayout, x: torch.Tensor) -> dict[str, torch.Tensor]:
    """layout.as_dict(x) with a selection matmul instead of masked_scatter (batches under torch.func)."""
    out, i = {}, 0
    for name, p, m in layout.entries:
        k = int(m.sum())
        flat = m.flatten()
        sel = torch.zeros(flat.numel(), k, dtype=p.dtype, device=p.device)
        sel[flat.nonzero()[:, 0], torch.arange(k, device=p.device)] = 1.0
        base = p.detach().flatten() * (~flat).to(p.dtype)
        out[name] = (base + sel @ x[i : i + k].to(p)).reshape(p.shape)
        i += k
    return out


class SlopePenalty:
    """Paper I's bound (31) as a parameter-only residual block (hinge residuals), for :func:`torchcal.fit`.

    model: MachineModel or RobotModel (its parameters are read from x, the
    layout's free vector); points: (M, n) commands, SI, where the bound holds;
    c: bound, m per half axis motion; weight: 1/m, scales the residuals (a
    slope excess of 1/weight m costs as much as one standard deviation of one
    measured coordinate); tools: which tool vectors (see
    :func:`~torchcal.identify.slope.tool_vectors`; None: every nominal tool of
    the model, each bounded); shift: (T, M, n) m, the augmented-Lagrangian shift
    s (multiplier / rho), default zero.

    ``linearize(x, layout)`` returns the ACTIVE hinge residuals
    r = weight * (|hbar_i(q)| - c + s), those > 0, and their Jacobian (k, P):
    the inactive ones are exactly zero with zero Jacobian rows, so they are
    left out (k varies from call to call). Closed form for a MachineModel,
    torch.func otherwise. The last evaluation is cached on x.

    Example:
        >>> import torch, torchcal
        >>> from torchcal.identify.layout import ParameterLayout
        >>> from torchcal.models.machine import MachineModel
        >>> robot = torchcal.load_robot("five_axis_xyzcb")
        >>> model = MachineModel(robot, torch.tensor([[0.0, 0.0, 0.4029]], dtype=torch.float64), orders=2)
        >>> pen = SlopePenalty(model, slope_points(robot.joint_map.limits, 64), c=1e-4, weight=1e4)
        >>> layout = ParameterLayout(model)
        >>> r, J = pen.linearize(layout.get(), layout)   # the nominal model has no slope: nothing active
        >>> r.shape, J.shape
        (torch.Size([0]), torch.Size([0, 82]))
    """

    def __init__(self, model, points: torch.Tensor, c: float, weight: float = 1.0, tools=None,
                 shift: torch.Tensor | None = None):
        if not (c > 0 and math.isfinite(c)):
            raise ValueError(f"SlopePenalty: the bound c must be positive and finite, got {c}")
        self.model = model
        self.points = torch.as_tensor(points).to(dtype=model.dtype, device=model.device)
        if self.points.ndim != 2 or self.points.shape[1] != model.n:
            raise ValueError(f"SlopePenalty: points must have shape (M, {model.n}), got {tuple(self.points.shape)}")
        self.c = float(c)
        self.weight = float(weight)
        self.tools = tool_vectors(model, tools)
        T, M = self.tools.shape[0], self.points.shape[0]
        self.shift = torch.zeros(T, M, model.n, dtype=model.dtype, device=model.device) if shift is None else shift
        if self.shift.shape != (T, M, model.n):
            raise ValueError(f"SlopePenalty: shift must have shape ({T}, {M}, {model.n}), got {tuple(self.shift.shape)}")
        self._cache = self._norms_cache = None
        # the slope at fixed points: what does not depend on the parameters (nominal chain, Chebyshev values,
        # difference stencil, gravity torques) once, not per evaluation
        self._context = _CONTEXTS.get(model, self.points, self.tools)

    def norms(self, x: torch.Tensor, layout: ParameterLayout) -> torch.Tensor:
        """|hbar| (T, M, n) at the free values x (differentiable in x). The last value for an x without
        gradient is kept: a solver that tries x + d and then steps there evaluates once."""
        if x.requires_grad:
            return functional_slope_norms(self.model, layout.as_dict(x), self.points, self.tools, self._context)
        last = self._norms_cache
        if last is not None and last[1] is layout and last[0].shape == x.shape and torch.equal(last[0], x):
            return last[2]
        out = functional_slope_norms(self.model, layout.as_dict(x), self.points, self.tools, self._context)
        self._norms_cache = (x.detach().clone(), layout, out.detach())
        return out

    def linearize(self, x: torch.Tensor, layout: ParameterLayout):
        grad = x.requires_grad
        if not grad and self._cache is not None:
            cx, clayout, r, J = self._cache
            if clayout is layout and cx.shape == x.shape and torch.equal(cx, x):
                return r, J
        with torch.no_grad():
            g = self.norms(x.detach(), layout) - self.c + self.shift
        active = (g > 0).nonzero()  # (k, 3): tool, point, axis
        P = x.numel()
        if active.shape[0] == 0:
            r = x.sum() * 0.0 if grad else x.new_zeros(())
            r, J = r.reshape(1)[:0], x.new_zeros(0, P)
        else:
            J = self._jacobian(x.detach(), layout, active)
            if grad:
                nrm = self._active_norms(x, layout, active)
            else:
                nrm = g[active[:, 0], active[:, 1], active[:, 2]] + self.c - self.shift[active[:, 0], active[:, 1], active[:, 2]]
            r = self.weight * (nrm - self.c + self.shift[active[:, 0], active[:, 1], active[:, 2]])
            J = self.weight * J
        if not grad:
            self._cache = (x.detach().clone(), layout, r, J)
        return r, J

    def _active_norms(self, x, layout, active) -> torch.Tensor:
        """|hbar| of the active entries, differentiable in x (for L-BFGS)."""
        out = x.new_zeros(active.shape[0])
        params = layout.as_dict(x)
        for t in range(self.tools.shape[0]):
            sel = active[:, 0] == t
            if sel.any():
                pts = self.points[active[sel, 1]]
                nrm = functional_slope_norms(self.model, params, pts, self.tools[t : t + 1])[0]
                out = out.masked_scatter(sel, nrm[torch.arange(pts.shape[0]), active[sel, 2]])
        return out

    def _jacobian(self, x, layout, active) -> torch.Tensor:
        """d |hbar| / dx (k, P) of the active entries."""
        k, P = active.shape[0], x.numel()
        J = x.new_zeros(k, P)
        if is_machine_model(self.model):
            params = layout.as_dict(x)
            wrapper = _MachineNormJacobian(self.model)
            from torch.func import functional_call

            for t in range(self.tools.shape[0]):
                sel = (active[:, 0] == t).nonzero()[:, 0]
                if sel.numel() == 0:
                    continue
                rows = active[sel, 1]
                with torch.no_grad():
                    _, Jc = functional_call(wrapper, {f"model.{n}": v for n, v in params.items()},
                                            (self.points[rows], self.tools[t], active[sel, 2],
                                             context_rows(self._context, rows, slice(t, t + 1))))
                groups = {name: x.new_zeros((sel.numel(), 1) + tuple(p.shape)) for name, p, _ in layout.entries}
                groups["axis_errors.coef"] = Jc[:, None]
                J[sel] = layout.flatten_jacobian(groups, sel.numel())[:, 0, :]
            return J
        uniq, inv = torch.unique(active[:, 1], return_inverse=True)
        pts = self.points[uniq]
        if robot_fast_path(self.model):
            from torch.func import functional_call

            params = {f"model.{n}": v for n, v in layout.as_dict(x).items()}
            if self._context is not None:  # the two difference rows of each (point, axis) pair, not all 2 n
                pairs, inv = torch.unique(active[:, 1:], dim=0, return_inverse=True)
                with torch.no_grad():
                    h, dh = functional_call(_RobotPairTerms(self.model, layout), params,
                                            (self._context, pairs[:, 0], pairs[:, 1], self.tools))
                h, dh = h[active[:, 0], inv], dh[active[:, 0], inv]  # (k, 3), (k, 3, P)
            else:
                with torch.no_grad():
                    h, dh = functional_call(_RobotSlopeTerms(self.model, layout), params, (pts, self.tools))
                h = h[active[:, 0], inv, active[:, 2]]  # (k, 3)
                dh = dh[active[:, 0], inv, active[:, 2]]  # (k, 3, P)
            unit = h / h.norm(dim=-1, keepdim=True).clamp_min(1e-300)
            return torch.einsum("kc,kcp->kp", unit, dh)
        from torch.func import jacfwd

        def f(xx):
            nrm = functional_slope_norms(self.model, _as_dict_matmul(layout, xx), pts, self.tools)  # (T, U, n)
            return nrm[active[:, 0], inv, active[:, 2]]

        with warnings.catch_warnings():
            warnings.simplefilter("ignore", UserWarning)  # functorch batching fallbacks: slower, still exact
            return jacfwd(f)(x)


class _ContextCache:
    """The slope context (:func:`~torchcal.identify.slope.slope_context`) of the last point set.

    A fit evaluates the slope at the same points in every iteration and the sweep at the same points,
    grown by refinements, for every c: the context of a set that extends the last one is the last
    context plus that of the new points.
    """

    def __init__(self):
        self.entry = None  # (model weakref, slope reference, points, tools, context)

    def get(self, model, points: torch.Tensor, tools: torch.Tensor):
        e, ref = self.entry, getattr(slope_model(model)[0], "slope_reference", "nominal")
        ctx = None
        if (e is not None and e[0]() is model and e[1] == ref and e[3].shape == tools.shape and torch.equal(e[3], tools)
                and e[2].shape[0] <= points.shape[0] and e[2].device == points.device
                and torch.equal(points[: e[2].shape[0]], e[2])):
            m0 = points.shape[0] - e[2].shape[0]
            if m0 == 0:
                return e[4]
            if e[4] is not None:
                ctx = cat_contexts(e[4], slope_context(model, points[e[2].shape[0]:], tools))
        else:
            ctx = slope_context(model, points, tools)
        self.entry = (weakref.ref(model), ref, points, tools, ctx)
        return ctx


_CONTEXTS = _ContextCache()


class _RobotSlopeTerms(nn.Module):
    def __init__(self, model, layout):
        super().__init__()
        self.model = model
        self.layout = layout

    def forward(self, q, P, context=None):
        return robot_slope_terms(self.model, q, P, self.layout, context=context)


class _RobotPairTerms(nn.Module):
    def __init__(self, model, layout):
        super().__init__()
        self.model = model
        self.layout = layout

    def forward(self, context, point, axis, P):
        return robot_pair_terms(self.model, context, point, axis, P, self.layout)


class _MachineNormJacobian(nn.Module):
    def __init__(self, model):
        super().__init__()
        self.model = model

    def forward(self, q, p, axis, context=None):
        return machine_slope_norm_jacobian(self.model, q, p, axis, context)


# ------------------------------------------------------------------ the constrained fit
@dataclass
class ConstrainedFitResult:
    """Outcome of :func:`fit_constrained`, in the manner of scipy.optimize.OptimizeResult.

    x: free parameters of the last inner fit (its layout, SI); v: (R, n) axis
    errors; success: the bound holds to ``tol`` at the penalty points and to
    ``check_tol`` at the fresh points; message; nit: outer (augmented-Lagrangian)
    iterations; c: the bound, m per half axis motion; max_slope: max |hbar| at
    the penalty points (m); max_slope_check: at fresh points the penalty never
    saw (m); fit: the last inner :class:`FitResult`; points / check_points:
    how many; weight: final penalty weight (1/m, solver 'penalty'); history:
    max |hbar| / c after each outer iteration; time: seconds; penalty_points:
    the final penalty point set (M, n) (the initial one plus the fresh points
    that failed a check), to warm-start a fit at a nearby c.
    """

    x: torch.Tensor
    v: torch.Tensor
    success: bool
    message: str
    nit: int
    c: float
    max_slope: float
    max_slope_check: float
    fit: FitResult | None
    points: int = 0
    check_points: int = 0
    weight: float = 0.0
    history: list[float] = field(default_factory=list)
    time: float = 0.0
    penalty_points: torch.Tensor | None = field(default=None, repr=False)

    def summary(self) -> dict:
        """JSON-ready scalars (slopes and c in mm per half axis motion)."""
        return {"converged": bool(self.success), "message": self.message, "outer_iterations": int(self.nit),
                "c_mm": self.c * 1e3, "max_slope_mm": self.max_slope * 1e3,
                "max_slope_check_mm": self.max_slope_check * 1e3, "points": self.points,
                "check_points": self.check_points, "time_s": self.time,
                "fit": None if self.fit is None else self.fit.summary()}


# ------------------------------------------------------------------ constrained Levenberg-Marquardt (SQP)
def _reduced_system(f, A, C, w_v, v, lam_b, dx, mu, H_blk, g_blk, v_free):
    """The damped Gauss-Newton system of V with every row's axis errors eliminated (as in the LM solver).

    -> S (P, P), rhs (P,) with V(x + db, v + dv(db)) ~ V + dbᵀ S db - 2 rhsᵀ db, and
    back(db) -> dv (R, n). Shapes as in :func:`torchcal.identify.lm._schur_step`.
    """
    R, d, P = A.shape
    n = C.shape[-1]
    Af = A.reshape(R * d, P)
    diag_bb = (A * A).sum((0, 1)) + lam_b
    g_b = Af.T @ f.reshape(-1) + lam_b * dx
    if H_blk is not None:
        diag_bb = diag_bb + torch.diagonal(H_blk)
        g_b = g_b + g_blk
    Ct = C.transpose(1, 2)
    H_vv = Ct @ C + torch.diag_embed(w_v)
    g_v = ((Ct @ f[..., None])[..., 0] + w_v * v) * v_free[:, None].to(f)
    L = torch.linalg.cholesky(H_vv + mu * torch.diag_embed(torch.diagonal(H_vv, dim1=1, dim2=2)))
    Li = torch.linalg.solve_triangular(L, torch.eye(n, dtype=A.dtype, device=A.device).expand(R, n, n), upper=False)
    W = Li @ Ct
    z = Li @ g_v[..., None]
    M = torch.eye(d, dtype=A.dtype, device=A.device) - W.transpose(1, 2) @ W
    S = Af.T @ (M @ A).reshape(R * d, P)
    if H_blk is not None:
        S = S + H_blk
    S = 0.5 * (S + S.T) + torch.diag(lam_b + mu * diag_bb)
    rhs = -(g_b - Af.T @ (W.transpose(1, 2) @ z).reshape(-1))

    def back(db):
        return -(Li.transpose(1, 2) @ (z + W @ (A @ db[:, None])))[..., 0]

    return S, rhs, back


SQP_FTOL_FLOOR = 1e-5
"""The smallest relative change of V the constrained solver stops on. Near the bound every step trades V
against second-order violations of the linearized constraints that the l1 merit then rejects (the Maratos
effect): V moves by ~1e-6 V per step for tens of steps (Paper I, c = 0.4 mm: 3990.82 -> 3990.81 over 25
steps), statistically nothing. An LM tolerance (``solver.ftol``, 1e-8) passed on would run every fit to
``max_iter``."""


class _QPNotConverged(TorchcalError, RuntimeError):
    """NNLS stopped at its iteration limit (degenerate constraints); the caller damps or stops."""


def _ldp_nnls(E: torch.Tensor, f: torch.Tensor) -> tuple[torch.Tensor | None, torch.Tensor]:
    """min |z| s.t. E z >= f (Lawson & Hanson ch. 23) by one NNLS of size (P + 1) x k.

    -> (z (P,) or None when infeasible, (k,) bool: the constraints with a positive multiplier).
    """
    from scipy.optimize import nnls

    P = E.shape[1]
    rows = torch.cat([E, f[:, None]], 1)  # (k, P + 1); the dual: min |rows^T u - e_{P+1}|, u >= 0
    scale = rows.norm(dim=1, keepdim=True).clamp(min=1e-300)
    # identical constraints (a linear table has the same slope everywhere) make NNLS cycle: keep one of each
    _, first = torch.unique(torch.round(rows / scale * 1e9), dim=0, return_inverse=True)
    keep = torch.zeros(first.max() + 1, dtype=torch.long, device=rows.device).scatter_(
        0, first, torch.arange(first.numel(), device=rows.device))
    Mm = (rows[keep] / scale[keep]).T.cpu().numpy()  # column scaling (u >= 0 is invariant): NNLS tolerances are absolute
    e = np.zeros(P + 1)
    e[-1] = 1.0
    try:
        u, _ = nnls(Mm, e, maxiter=100 * (P + 1))
    except RuntimeError as exc:  # not converged: not a proof of infeasibility
        raise _QPNotConverged(str(exc)) from None
    active = torch.zeros(E.shape[0], dtype=torch.bool, device=E.device)
    active[keep[torch.from_numpy(u > 0).to(keep.device)]] = True
    r = torch.from_numpy(Mm @ u - e).to(E)
    if float(r.norm()) < 1e-12 or float(r[-1]) >= -1e-14:
        return None, active
    return -r[:P] / r[P], active


def solve_qp(S: torch.Tensor, rhs: torch.Tensor, G: torch.Tensor, h: torch.Tensor, start: torch.Tensor | None = None,
             chunk: int | None = None, return_active: bool = False):
    """min ½ dbᵀ S db - rhsᵀ db  s.t.  G db <= h, S positive definite.  -> db (P,), or None when infeasible.

    Least-distance programming (Lawson & Hanson, ch. 23): with S = L Lᵀ and
    db = S^-1 rhs + L^-T z the problem is min |z| s.t. E z >= f, solved by
    non-negative least squares (scipy.optimize.nnls) on a working set of the
    constraints: the most violated ones first (``chunk`` at a time, default
    P // 4), then every constraint the solution still violates, until it
    violates none (constraint generation: the working-set problem is a
    relaxation, so its solution, once feasible for all k rows, is the QP's
    solution). ``start``: (k,) bool, constraints to begin with (e.g. those
    active at the previous step). Exact: the solution meets G db <= h to
    round-off. return_active: also return the (k,) bool mask of the
    constraints with a positive multiplier (None when infeasible or
    unconstrained).
    """
    L = torch.linalg.cholesky(S)
    db0 = torch.cholesky_solve(rhs[:, None], L)[:, 0]
    k, P = G.shape
    none = (db0, None) if return_active else db0
    if k == 0:
        return none
    fvec = G @ db0 - h  # G db <= h  <=>  E z >= f with E = -G L^-T, f = G db0 - h, db = db0 + L^-T z
    if bool((fvec <= 0).all()):
        return none
    gn, hn = G.norm(dim=1), h.abs()
    chunk = max(8, P // 4) if chunk is None else int(chunk)
    W = torch.zeros(k, dtype=torch.bool, device=G.device) if start is None else start.clone().to(G.device)
    db, active, solved = db0, W, False
    while True:  # at most k rounds: each adds a constraint or ends
        viol = (G @ db - h) / (gn * float(db.norm()) + hn).clamp(min=1e-300)  # relative; > 0: violated
        bad = (viol > 1e-10) & ~W
        nb = int(bad.sum())
        if solved and nb == 0:
            break
        if nb == 0 and not bool(W.any()):  # violated by round-off only
            return none
        if nb:
            W[torch.where(bad, viol, viol.new_tensor(-math.inf)).topk(min(nb, chunk)).indices] = True
        idx = W.nonzero()[:, 0]
        E = -torch.linalg.solve_triangular(L, G[idx].T, upper=False).T  # (|W|, P)
        z, act = _ldp_nnls(E, fvec[idx])
        if z is None:  # the working set alone admits no step: neither do all constraints
            return (None, None) if return_active else None
        db = db0 + torch.linalg.solve_triangular(L.T, z[:, None], upper=True)[:, 0]
        solved = True
        active = torch.zeros_like(W)
        active[idx[act]] = True
    return (db, active) if return_active else db


def _sqp(problem, pen: SlopePenalty, tol: float, max_iter: int = 40, ftol: float = 1e-5, mu0: float = 1e-4,
         margin: float = 0.3, v_start=None, max_tries: int = 12, damp_tries: int = 3, inner_margin: float = 0.02,
         max_candidates: int | None = None, callback=None) -> FitResult:
    """Minimize V of ``problem`` subject to |hbar| <= c at ``pen``'s points: Levenberg-Marquardt steps whose
    linearized constraints are met exactly (a QP per step, :func:`solve_qp`), accepted on the merit
    V + rho sum max(0, |hbar| / c_in - 1) (l1 exact penalty), rho = 1e3 V_0 (feasibility first), c_in = c (1 - inner_margin)
    (imposed slightly inside, so that the bound also holds between the points). Candidates: entries above
    (1 - margin) c at the first step, (1 - margin / 10) c later, at most ``max_candidates`` (default max(2500, 4 P))
    of the largest (cutting planes). Stops when a step changes V by less than ftol V (1e-5: ~0.02 for Paper I's 590 rows,
    statistically nothing; never below :data:`SQP_FTOL_FLOOR`) with the bound met to tol, or when no damped step
    lowers the merit. Each QP starts from the entries active at the last one (:func:`solve_qp`'s ``start``).
    callback(it, V, violation): called after every accepted step."""
    from .blocks import block_normal_equations

    t0 = time.perf_counter()
    layout = problem.layout
    c = pen.c
    ftol = max(float(ftol), SQP_FTOL_FLOOR)
    max_cand = max(2500, 4 * layout.size) if max_candidates is None else int(max_candidates)
    # imposed slightly inside c: the bound then also holds between the points (checked at fresh ones)
    target = c * (1.0 - inner_margin)
    x = layout.get().to(problem.model.device)
    v = problem.v_zero() if v_start is None else v_start.clone()
    lam_b, w_v, v_free = problem.prior_precision, problem.w_v, problem.v_free
    others = problem.blocks

    def merit_parts(f, x_, v_):
        with torch.no_grad():
            nrm = pen.norms(x_, layout)
        return float(problem.cost_from(f, x_, v_)), nrm

    def violation(nrm_):
        return max(0.0, float(nrm_.max()) / target - 1.0)

    def excess(nrm_):  # l1 merit term: a step may overload an entry outside the cutting planes a little
        return float((nrm_ / target - 1.0).clamp(min=0.0).sum())

    f = problem.residual(x, v)
    V, nrm = merit_parts(f, x, v)
    rho = 1e3 * max(V, 1.0)
    viol = violation(nrm)
    phi = V + rho * excess(nrm)
    history, mu, nu, nfev = [V], mu0, 2.0, 1
    success, message, it = False, "maximum number of iterations reached", 0
    M_pts, n_ax = pen.points.shape

    def keys(entries):  # (k, 3) tool, point, axis -> (k,) one integer per entry
        return (entries[:, 0] * M_pts + entries[:, 1]) * n_ax + entries[:, 2]

    act_keys = None
    # as in the LM solver: while steps pass at once, a trial point is linearized directly (its Jacobians are the
    # next iteration's), one kinematics pass per iteration instead of a residual and a linearization
    trial_linearize, lin_next = True, None
    for it in range(1, max_iter + 1):
        f, A, C = lin_next if lin_next is not None else problem.linearize(x, v)
        lin_next = None
        H_blk = g_blk = None
        if others:
            H_blk, g_blk, _ = block_normal_equations(others, x, layout)
        # wide at the first step (the unconstrained start moves far), narrow once near the bound
        cand = (nrm > (1.0 - margin) * c if it == 1 else nrm > (1.0 - 0.1 * margin) * target).nonzero()
        if cand.shape[0] > max_cand:
            # cutting planes: the most loaded entries now, the others when a step overloads them
            cand = cand[nrm[cand[:, 0], cand[:, 1], cand[:, 2]].topk(max_cand).indices]
        Gc = pen._jacobian(x, layout, cand) if cand.shape[0] else x.new_zeros(0, x.numel())
        hc = target - nrm[cand[:, 0], cand[:, 1], cand[:, 2]]
        accepted = False
        d_full = None

        def qp(S_, rhs_):
            # the QP starts from the entries active at the last solve (the active set changes little from one
            # damping or step to the next): a few NNLS rounds instead of a cold working set
            nonlocal act_keys
            start = torch.isin(keys(cand), act_keys) if act_keys is not None else None
            d, act = solve_qp(S_, rhs_, Gc, hc, start=start, return_active=True)
            if act is not None:
                act_keys = keys(cand[act])
            return d
        for attempt in range(max_tries):
            # first damp (Levenberg-Marquardt), then shorten the last direction: damping alone cannot shrink a
            # step whose linearized constraints must be met in full
            if attempt < damp_tries:
                S, rhs, back = _reduced_system(f, A, C, w_v, v, lam_b, x - problem.prior_mean, mu, H_blk, g_blk,
                                               v_free)
                try:
                    d_full = qp(S, rhs)
                except _QPNotConverged:
                    break
                for _ in range(3):  # entries the step would overload join the QP (linearized at x), re-solve
                    if d_full is None:
                        break
                    with torch.no_grad():
                        n_try = pen.norms(x + d_full, layout)
                    mask = n_try > target * (1.0 - 0.1 * margin)
                    mask[cand[:, 0], cand[:, 1], cand[:, 2]] = False
                    if not mask.any():
                        break
                    extra = mask.nonzero()
                    cand = torch.cat([cand, extra])
                    Gc = torch.cat([Gc, pen._jacobian(x, layout, extra)])
                    hc = torch.cat([hc, target - nrm[extra[:, 0], extra[:, 1], extra[:, 2]]])
                    try:
                        d_full = qp(S, rhs)
                    except _QPNotConverged:
                        d_full = None
                        break
                if d_full is None:
                    if it == 1 and attempt == 0:
                        raise ConstraintError(f"fit_constrained: the linearized slope bound c = {c * 1e3:.4g} mm "
                                              f"cannot be met by the free parameters (infeasible; are parameters "
                                              f"that carry slope held fixed?)")
                    break
                alpha = 1.0
            else:
                alpha = 0.5 ** (attempt - damp_tries + 1)
            db = alpha * d_full
            dv = back(db)
            x_new, v_new = x + db, v + dv
            lin_new = problem.linearize(x_new, v_new) if trial_linearize and attempt == 0 else None
            f_new = lin_new[0] if lin_new is not None else problem.residual(x_new, v_new)
            nfev += 1
            V_new, nrm_new = merit_parts(f_new, x_new, v_new)
            viol_new = violation(nrm_new)
            phi_new = V_new + rho * excess(nrm_new)
            log.debug("sqp it %d: mu %.3g, step %.3g, V %.6g -> %.6g, violation %.4g -> %.4g, %d candidates", it, mu,
                      alpha, V, V_new, viol, viol_new, Gc.shape[0])
            if phi_new < phi:
                accepted = True
                if attempt == 0:
                    mu, nu = max(mu / 3.0, 1e-12), 2.0
                lin_next, trial_linearize = lin_new, attempt == 0
                break
            if attempt < damp_tries - 1:
                mu *= nu
                nu *= 2.0
        if not accepted:
            layout.set(x)
            success = viol <= tol
            message = "converged: no step lowers the merit further" if success else \
                f"stalled with the bound violated by {viol:.3g} c"
            break
        dV = abs(V_new - V)
        x, v, V, nrm, viol, phi = x_new, v_new, V_new, nrm_new, viol_new, phi_new
        history.append(V)
        if callback is not None:
            callback(it, V, viol)
        if dV <= ftol * V and viol <= tol:
            success, message = True, "converged: relative cost change below ftol, bound met"
            break
    layout.set(x)
    return FitResult(x=x.detach().clone(), v=v.detach().clone(), success=success, message=message, nit=it, nfev=nfev,
                     fun=V, grad_norm=float("nan"), time=time.perf_counter() - t0, method="sqp", history=history,
                     names=layout.names())


def _points(model, points, seed: int) -> torch.Tensor:
    if points is None:
        points = DEFAULT_POINTS
    if isinstance(points, int):
        return slope_points(model.command_limits, points, seed)
    pts = torch.as_tensor(points).to(dtype=model.dtype, device=model.device)
    if pts.ndim != 2 or pts.shape[1] != model.n:
        raise ValueError(f"fit_constrained: points must be a count or an (M, {model.n}) tensor, got {tuple(pts.shape)}")
    return pts


@warns_once
def fit_constrained(model, data: Measurements, c: float, noise: NoiseModel | None = None, prior: Prior | None = Prior(),
                    points=None, tol: float = 1e-2, check_tol: float = 5e-2, tools=None, check_points=None,
                    seed: int = 0, solver: str = "sqp", refine: int = 3, blocks=(), raise_on_failure: bool = True,
                    weight: float | None = None, max_outer: int = 30, worst: int = 32, give_up=None,
                    **fit_options) -> ConstrainedFitResult:
    """The constrained MLE of Paper I: (11)-(12) subject to |hbar_i(q)| <= c (31) over the whole axis space.

    model: MachineModel or RobotModel, updated in place from its current values
    (warm start); data: identification rows; c: bound in m per half axis
    motion (Paper I: 0.4 mm = 4e-4; ``math.inf`` or None: unconstrained, a plain
    :func:`torchcal.fit`); noise, prior, blocks: as for :func:`torchcal.fit`;
    points: where the bound is imposed: None (512 quasi-random points + faces +
    corners, :func:`slope_points`), a count, or (M, n) commands; check_points:
    fresh points to verify it (default: a disjoint seeded set of the same
    kind); tools: which tool vectors are bounded (None: every nominal tool);
    tol: the bound must hold to c (1 + tol) at the penalty points, check_tol:
    to c (1 + check_tol) at the fresh ones (where it does not, the violating
    fresh points join the penalty set, together with the local maxima of the
    slope climbed from the ``worst`` worst fresh and penalty points
    (:func:`~torchcal.identify.slope.worst_points`), and a new fresh set is
    drawn, at most ``refine`` times). give_up: optional callable(model) ->
    bool, asked when the bound holds at the penalty points but not at the
    fresh ones: True ends the fit there without refining (the constraint
    sweep's past-the-knee test: more points only add constraints, so a fit
    already past the knee stays past it).

    solver: 'sqp' (default): Levenberg-Marquardt whose every step solves the
    damped Gauss-Newton model (axis errors eliminated per row, as in
    :mod:`torchcal.identify.lm`) subject to the linearized bound at the
    candidate entries, exactly (a QP, :func:`solve_qp`), steps accepted on the
    merit V + rho max violation: a few seconds for Paper I's 590 rows, 6th
    order. fit_options: fixed, gauge, instrument, fixed_rows, v0, max_iter,
    ftol, mu0. 'penalty': an augmented-Lagrangian loop of :func:`torchcal.fit`
    runs with a :class:`SlopePenalty` block (weight w, default 1 / (0.01 c);
    shift s <- max(0, s + |hbar| - c); w <- 4 w where the violation did not
    halve; at most max_outer runs), for method='lbfgs' or any other solver
    option of :func:`torchcal.fit` (slower: the hinge makes LM crawl).

    Raises :class:`ConstraintError` (with ``.result``, the model left at its
    last values) when the bound is not met (infeasible c or no convergence);
    raise_on_failure=False returns the result with success False instead;
    ValueError for c <= 0.

    Example:
        >>> import torch, torchcal
        >>> import torchcal.sim
        >>> from torchcal.models.machine import MachineModel
        >>> robot = torchcal.load_robot("five_axis_xyzcb")
        >>> tools = torch.tensor([[0.0, 0.0, 0.4029], [0.0, 0.0, 0.5009]], dtype=torch.float64)
        >>> truth = MachineModel(robot, tools, orders=2)
        >>> with torch.no_grad():
        ...     _ = truth.axis_errors.coef[2, 4, 2].fill_(2e-4)          # Z error quadratic in B
        >>> q = torchcal.sim.quasi_random_commands(robot.joint_map.limits, 40, 0).repeat(2, 1)
        >>> tool = torch.arange(2).repeat_interleave(40)
        >>> data = torchcal.Measurements.from_tensors(q, tool, truth.points(q, tool).detach())
        >>> model = MachineModel(robot, tools, orders=2)
        >>> res = fit_constrained(model, data, c=2e-4, points=64)   # the truth's slope reaches 0.4 mm
        >>> res.success, res.max_slope_check <= 2e-4 * 1.05
        (True, True)
    """
    # small solves run on one thread (torchcal.core.threads): the slope evaluations and QPs are many small steps
    c_text = "inf" if c is None or math.isinf(float(c)) else f"{float(c) * 1e3:.4g} mm"
    with threads_for_work(_work(model, data, fit_options.get("instrument"))), \
            progress.task(f"constrained fit (c = {c_text})") as task:
        return _fit_constrained(model, data, c, noise, prior, points, tol, check_tol, tools, check_points, seed, solver,
                                refine, blocks, raise_on_failure, weight, max_outer, worst, task, give_up, **fit_options)


def _work(model, data: Measurements, instrument=None) -> float:
    """Flops of one Gauss-Newton iteration, as :func:`torchcal.identify.fit.problem_work` (parameters counted
    before masking and gauge fixing: an upper bound)."""
    P = sum(p.numel() for p in model.parameters())
    return float(len(data) * int(getattr(instrument, "dim", 3)) * P * P)


def _fit_constrained(model, data, c, noise, prior, points, tol, check_tol, tools, check_points, seed, solver, refine,
                     blocks, raise_on_failure, weight, max_outer, worst, task, give_up=None,
                     **fit_options) -> ConstrainedFitResult:
    t0 = time.perf_counter()

    def on_step(label):  # the solver's iterations as progress (a front end shows one line per few seconds)
        def callback(it, V, viol):
            task.advance(note=f"{label}: iteration {it}, cost {V:.6g}, bound exceeded by {100 * viol:.2g} %")
        return callback

    if solver not in ("sqp", "penalty"):
        raise ValueError(f"fit_constrained: solver must be 'sqp' or 'penalty', got {solver!r}")
    noise = resolve_noise(model, noise)
    pts = _points(model, points, seed)
    chk_count = points if isinstance(points, int) else DEFAULT_POINTS
    chk_seed = seed + 1
    chk = _points(model, chk_count if check_points is None else check_points, chk_seed)
    if c is None or math.isinf(float(c)) and float(c) > 0:
        task.set_note("unconstrained fit")
        res = fit(model, data, noise, prior, blocks=blocks, **fit_options)
        return ConstrainedFitResult(res.x, res.v, res.success, "unconstrained (c = inf): " + res.message, 0, math.inf,
                                    max_slope_of(model, pts, tools), max_slope_of(model, chk, tools), res,
                                    pts.shape[0], chk.shape[0], 0.0, [], time.perf_counter() - t0, pts)
    c = float(c)
    if not (c > 0 and math.isfinite(c)):
        raise ValueError(f"fit_constrained: the slope bound c must be positive (m per half axis motion), got {c}")
    P = tool_vectors(model, tools)
    T = P.shape[0]
    if solver == "sqp" and fit_options.get("method", "lm") != "lm":
        solver = "penalty"
    fit_options.pop("method", None) if solver == "sqp" else None
    v0 = fit_options.pop("v0", None)
    history: list[float] = []
    res: FitResult | None = None
    refinements, it, success = 0, 0, False
    message = "maximum number of outer iterations reached"
    m_pen = m_chk = math.nan
    w = float(weight) if weight is not None else 1.0 / (0.01 * c)
    shift = torch.zeros(T, pts.shape[0], model.n, dtype=model.dtype, device=model.device)
    problem = None
    if solver == "sqp":
        from .gauge import fix_gauge
        from .problem import CalibrationProblem

        sqp_keys = ("max_iter", "ftol", "mu0", "margin", "inner_margin", "max_tries", "max_candidates")
        sqp_opts = {k: fit_options.pop(k) for k in sqp_keys if k in fit_options}
        gauge = fit_options.pop("gauge", True)
        problem = CalibrationProblem(model, data, noise, prior, fit_options.pop("fixed", ()),
                                     fit_options.pop("instrument", None), blocks, fit_options.pop("fixed_rows", None), v0)
        if fit_options:
            raise TypeError(f"fit_constrained(solver='sqp'): unknown options {sorted(fit_options)}")
        pinned = fix_gauge(problem) if gauge else []
        max_outer = refine + 1
        cur = max_slope_of(model, pts, P, context=_CONTEXTS.get(model, pts, P))
        if cur < 0.5 * c:
            # far inside the bound (e.g. a fresh, all-zero model): the norms' linearization means little there, so
            # start from the unconstrained optimum, whose slopes the bound then pulls down
            from .lm import levenberg_marquardt

            task.set_note("unconstrained start")
            res = levenberg_marquardt(problem, **{k: v for k, v in sqp_opts.items() if k in ("ftol", "mu0")})
            cur = max_slope_of(model, pts, P, context=_CONTEXTS.get(model, pts, P))
        # continuation: a bound far below the current slopes is approached through intermediate bounds (one
        # linearization cannot pull thousands of entries down by a factor of 10 at once)
        while cur > 3.0 * c:
            c_mid = max(c, cur / 2.5)
            try:
                step = _sqp(problem, SlopePenalty(model, pts, c_mid, 1.0, P), tol,
                            v_start=None if res is None else res.v, callback=on_step(f"on the way, c = {c_mid * 1e3:.4g} mm"),
                            **sqp_opts)
            except ConstraintError:
                break
            res = step
            new = max_slope_of(model, pts, P, context=_CONTEXTS.get(model, pts, P))
            log.debug("fit_constrained: continuation bound %.4g mm -> max slope %.4g mm", c_mid * 1e3, new * 1e3)
            if new > 0.9 * cur:
                break
            cur = new
    viol_prev = math.inf
    for it in range(1, max_outer + 1):
        if solver == "sqp":
            pen = SlopePenalty(model, pts, c, 1.0, P)
            try:
                res = _sqp(problem, pen, tol, v_start=None if res is None else res.v,
                           callback=on_step(f"{pts.shape[0]} points" + (f", refinement {refinements}" if refinements else "")),
                           **sqp_opts)
            except ConstraintError as exc:
                message = str(exc)
                break
            res.pinned = pinned
        else:
            pen = SlopePenalty(model, pts, c, w, P, shift)
            res = fit(model, data, noise, prior, blocks=[pen, *blocks], v0=v0, **fit_options)
            v0 = res.v
        with torch.no_grad():
            nrm = slope_norms(model, pts, P, context=_CONTEXTS.get(model, pts, P))  # (T, M, n)
        m_pen = float(nrm.max())
        viol = m_pen / c - 1.0
        history.append(m_pen / c)
        log.debug("fit_constrained c=%.4g mm: outer %d, max slope %.5g mm, %d points, inner: %d iterations, %.2f s, %s",
                  c * 1e3, it, m_pen * 1e3, pts.shape[0], res.nit, res.time, res.message)
        if viol <= tol:
            task.set_note(f"checking the bound at {chk.shape[0]} fresh points")
            with torch.no_grad():
                nchk = slope_norms(model, chk, P)
            m_chk = float(nchk.max())
            if m_chk <= c * (1.0 + check_tol):
                success, message = True, (f"bound met: max slope {m_pen / c:.4f} c at {pts.shape[0]} penalty points, "
                                          f"{m_chk / c:.4f} c at {chk.shape[0]} fresh points ({res.message})")
                break
            if refinements >= refine:
                message = (f"bound met at the penalty points but not at fresh points ({m_chk / c:.4f} c) after "
                           f"{refinements} refinements of the point set")
                break
            if give_up is not None and give_up(model):
                success, message = True, (f"bound met at {pts.shape[0]} penalty points ({m_pen / c:.4f} c), not refined "
                                          f"at the fresh points ({m_chk / c:.4f} c): past the constraint sweep's knee")
                break
            # the fresh points where the bound fails join the penalty set, with the local maxima of the slope
            # climbed from the worst of them and of the penalty points; a new fresh set checks again
            bad = (nchk > c).any(0).any(-1)
            top = torch.cat([chk[nchk.amax(dim=(0, 2)).topk(min(worst, chk.shape[0])).indices],
                             pts[nrm.amax(dim=(0, 2)).topk(min(worst, pts.shape[0])).indices]])
            task.set_note(f"{int(bad.sum())} fresh points exceed c: climbing to the slope's local maxima")
            new = torch.cat([chk[bad], worst_points(model, top, P)]) if worst > 0 else chk[bad]
            pts = torch.cat([pts, new])
            shift = torch.cat([shift, torch.zeros(T, new.shape[0], model.n, dtype=shift.dtype, device=shift.device)], 1)
            refinements += 1
            if check_points is None:
                chk = _points(model, chk_count, chk_seed + 100 * refinements)
            viol_prev = math.inf
            continue
        if solver == "sqp":
            message = f"the constrained solver stopped with the bound violated ({res.message})"
            break
        shift = (shift + nrm - c).clamp(min=0.0)
        if viol > 0.5 * viol_prev:
            w *= 4.0
        viol_prev = viol
    if res is None:  # infeasible before any step: the partial result is the model as it was
        x0 = problem.layout.get() if problem is not None else torch.zeros(0, dtype=model.dtype)
        m_pen = max_slope_of(model, pts, P)
        out = ConstrainedFitResult(x0, torch.zeros_like(data.q), False, message, it, c, m_pen, max_slope_of(model, chk, P),
                                   None, pts.shape[0], chk.shape[0], 0.0, history, time.perf_counter() - t0, pts)
        if raise_on_failure:
            raise ConstraintError(message, out)
        return out
    if math.isnan(m_chk):
        m_chk = max_slope_of(model, chk, P)
    out = ConstrainedFitResult(res.x, res.v, success, message, it, c, m_pen, m_chk, res, pts.shape[0], chk.shape[0],
                               w if solver == "penalty" else 0.0, history, time.perf_counter() - t0, pts)
    if not success and raise_on_failure:
        raise ConstraintError(f"fit_constrained: slope bound c = {c * 1e3:.4g} mm per half axis motion not met: "
                              f"{message} (max slope {m_pen * 1e3:.4g} mm at the penalty points, {m_chk * 1e3:.4g} mm at "
                              f"fresh points, {it} outer iterations)", out)
    return out


def max_slope_of(model, points: torch.Tensor, tools=None, context: dict | None = None) -> float:
    """max |hbar| (m per half axis motion) over points (M, n), axes and tools (context: see
    :func:`~torchcal.identify.slope.slope_norms`)."""
    with torch.no_grad():
        return float(slope_norms(model, points, tools, context).max())


# ------------------------------------------------------------------ Paper I 3.4: the constraint sweep
@dataclass
class SweepResult:
    """Figure 14: per constraint value, residuals of the sub-identification and boundary (constraint validation) sets.

    c: (K,) bounds, m per half axis motion, descending, c[0] = inf (unconstrained);
    sub_mean, sub_max, boundary_mean, boundary_max: (K,) residual statistics, m
    (row norms of model minus measurement, axis errors zero; a sensor rig's: of
    the sensor origin's position); max_slope: (K,)
    max |hbar| at fresh points, m; success: per c, whether the bound was met;
    time: seconds per c.
    """

    c: torch.Tensor
    sub_mean: torch.Tensor
    sub_max: torch.Tensor
    boundary_mean: torch.Tensor
    boundary_max: torch.Tensor
    max_slope: torch.Tensor
    success: list[bool]
    time: list[float]
    states: list = field(default_factory=list, repr=False)
    """Per c: (the model's state dict, its penalty points) after that fit: a warm start for the final fit."""

    def table(self) -> list[dict]:
        """Rows in mm (c, residuals, max slope), for printing or JSON."""
        out = []
        for k in range(self.c.numel()):
            out.append({"c_mm": float(self.c[k]) * 1e3, "sub_mean_mm": float(self.sub_mean[k]) * 1e3,
                        "sub_max_mm": float(self.sub_max[k]) * 1e3, "boundary_mean_mm": float(self.boundary_mean[k]) * 1e3,
                        "boundary_max_mm": float(self.boundary_max[k]) * 1e3, "max_slope_mm": float(self.max_slope[k]) * 1e3,
                        "success": bool(self.success[k]), "time_s": self.time[k]})
        return out


def _factory(make_model):
    if isinstance(make_model, nn.Module):
        return lambda: copy.deepcopy(make_model)
    if not callable(make_model):
        raise TypeError("make_model must be a model (copied) or a callable returning a fresh model")
    return make_model


def _row_mask(index, rows: int, device) -> torch.Tensor:
    idx = torch.as_tensor(index)
    if idx.dtype == torch.bool:
        if idx.shape != (rows,):
            raise ValueError(f"boundary_index: a bool mask must have shape ({rows},), got {tuple(idx.shape)}")
        return idx.to(device)
    mask = torch.zeros(rows, dtype=torch.bool, device=device)
    idx = idx.reshape(-1).long()
    if idx.numel() and (idx.min() < 0 or idx.max() >= rows):
        raise ValueError(f"boundary_index: row indices must be in 0..{rows - 1}")
    mask[idx.to(device)] = True
    return mask


def _stats(model, data: Measurements):
    e = row_errors(model, data)
    return float(e.mean()), float(e.max())


@warns_once
def constraint_sweep(make_model, data: Measurements, boundary_index, c_values=None, noise: NoiseModel | None = None,
                     prior: Prior | None = Prior(), n_values: int = 8, span: float = 20.0,
                     stop_tol_mm: float | None = None, stop_mean_tol_mm: float | None = None, **options) -> SweepResult:
    """Paper I 3.4 / Figure 14: fit the sub-identification set for each c, score the boundary points.

    make_model: a callable returning a fresh (zero) model, or a model (deep-copied);
    data: the identification rows; boundary_index: the BORDER rows ((k,) row
    indices or an (R,) bool mask; every row of a boundary pose, all its tools),
    held out: the fits use the other rows (the sub-identification set);
    c_values: bounds (m per half axis motion), swept from large to small, each
    fit warm-started from the previous; None: ``n_values`` values spaced
    geometrically from the unconstrained model's max slope down by ``span``.
    The unconstrained fit (c = inf) always comes first. ``options`` go to
    :func:`fit_constrained` (points, tools, tol, method, instrument, ...). A c whose fit
    fails to meet the bound is recorded with success False (its model is still
    scored) and the sweep goes on. stop_tol_mm, stop_mean_tol_mm: stop once a c
    fails the knee test of :func:`pick_knee` with these tolerances (the smaller,
    over-constrained c values are the slowest fits and cannot be the knee);
    None sweeps them all.
    """
    factory = _factory(make_model)
    model = factory()
    mask = _row_mask(boundary_index, len(data), data.q.device)
    if not mask.any() or mask.all():
        raise ValueError("constraint_sweep: the boundary set must be a proper, non-empty subset of the rows")
    sub, bnd = data.subset(~mask), data.subset(mask)
    if options.get("instrument") is not None:  # an instrument holds its rows: the fits see the sub set's
        options = {**options, "instrument": options["instrument"].subset(~mask)}
    noise = resolve_noise(model, noise)
    rows = {k: [] for k in ("c", "sub_mean", "sub_max", "boundary_mean", "boundary_max", "max_slope", "success", "time")}

    states: list = []

    def record(cv, res, t):
        sm, sx = _stats(model, sub)
        bm, bx = _stats(model, bnd)
        for key, val in (("c", cv), ("sub_mean", sm), ("sub_max", sx), ("boundary_mean", bm), ("boundary_max", bx),
                         ("max_slope", res.max_slope_check), ("success", res.success), ("time", t)):
            rows[key].append(val)
        states.append(({k: t.detach().clone() for k, t in model.state_dict().items()}, res.penalty_points))

    seed = int(options.pop("seed", 0))
    try:
        with progress.task("constraint sweep", total=None if c_values is None else len(c_values) + 1) as task:
            t = time.perf_counter()
            res = fit_constrained(model, sub, math.inf, noise, prior, seed=seed, **options)
            record(math.inf, res, time.perf_counter() - t)
            if c_values is None:
                top = res.max_slope_check
                c_values = [top * span ** (-(k + 1) / n_values) for k in range(n_values)]
                task.set_total(len(c_values) + 1)
            task.advance(note="c = inf (unconstrained)")
            # each c starts from the previous c's parameters and penalty points (they include the fresh points that
            # failed a check there); each gets its own fresh check points (seed)
            carry = dict(options)
            give_up = None
            if stop_tol_mm is not None:
                # a c whose sub-identification mean already rose past the knee test's tolerance is past the knee: its
                # fresh-point refinements (the costliest part of the sweep's slowest fit) could only raise it further
                limit = rows["sub_mean"][0] + (stop_tol_mm / 2 if stop_mean_tol_mm is None else stop_mean_tol_mm) * 1e-3

                def give_up(m):
                    return _stats(m, sub)[0] > limit
            for k, cv in enumerate(sorted((float(c) for c in c_values), reverse=True)):
                t = time.perf_counter()
                try:
                    res = fit_constrained(model, sub, cv, noise, prior, seed=seed + 1000 * (k + 1), give_up=give_up, **carry)
                except ConstraintError as exc:
                    res = exc.result
                    log.warning("constraint sweep: c = %.4g mm: %s", cv * 1e3, exc)
                if res is None:
                    raise ConstraintError(f"constraint sweep: c = {cv * 1e3:.4g} mm: no fit at all", None)
                record(cv, res, time.perf_counter() - t)
                task.advance(note=f"c = {cv * 1e3:.4g} mm: boundary max {rows['boundary_max'][-1] * 1e3:.4f} mm, "
                                  f"sub-identification mean {rows['sub_mean'][-1] * 1e3:.4f} mm")
                if res.penalty_points is not None and not isinstance(options.get("points"), torch.Tensor):
                    carry["points"] = res.penalty_points
                if stop_tol_mm is not None and res.success:
                    if pick_knee(_sweep_result(rows, states), stop_tol_mm, stop_mean_tol_mm) > cv:
                        log.info("constraint sweep: c = %.4g mm is past the knee; smaller c values skipped", cv * 1e3)
                        task.set_total(task.completed)  # done: the rest cannot be the knee
                        break
    except KeyboardInterrupt as exc:  # Ctrl-C: the bounds fitted by then go with it (the caller writes them down)
        if rows["c"]:
            exc.sweep = _sweep_result(rows, states)
        raise
    return _sweep_result(rows, states)


def _sweep_result(rows: dict, states: list) -> SweepResult:
    """The sweep's rows so far as a :class:`SweepResult`."""
    tt = lambda k: torch.tensor(rows[k], dtype=torch.float64)  # noqa: E731
    return SweepResult(tt("c"), tt("sub_mean"), tt("sub_max"), tt("boundary_mean"), tt("boundary_max"), tt("max_slope"),
                       rows["success"], rows["time"], list(states))


def pick_knee(sweep: SweepResult, tol_mm: float = 0.01, mean_tol_mm: float | None = None) -> float:
    """The knee of Figure 14: the smallest c reached, from c = inf down, before the fit gets worse.

    Walking the sweep from large to small c, c qualifies while its boundary max
    residual exceeds the best (smallest) boundary max seen at larger c
    (c = inf included) by at most ``tol_mm`` and its sub-identification mean
    exceeds the unconstrained one by at most ``mean_tol_mm`` (default tol_mm / 2).
    The first c that fails ends the walk; the knee is the last c that
    qualified (inf when none did). A flat boundary max (Paper I: within
    ±0.004 mm from inf to the knee) makes "the lowest max" a coin toss; this
    reading picks where both curves start to rise, as Figure 14 is read
    (c = 0.4 mm there). Bounds whose fit failed are skipped. -> c, m.

    Example:
        >>> inf = float("inf")
        >>> s = SweepResult(torch.tensor([inf, 8e-4, 4e-4, 2e-4]), torch.tensor([38e-6, 39e-6, 41e-6, 80e-6]),
        ...                 torch.zeros(4), torch.zeros(4), torch.tensor([1.9e-3, 0.6e-3, 0.44e-3, 0.9e-3]),
        ...                 torch.zeros(4), [True] * 4, [0.0] * 4)
        >>> round(pick_knee(s) * 1e3, 6)   # mm
        0.4
    """
    tol = tol_mm * 1e-3
    mtol = (tol_mm / 2 if mean_tol_mm is None else mean_tol_mm) * 1e-3
    order = torch.argsort(sweep.c, descending=True).tolist()
    ref_mean = float(sweep.sub_mean[order[0]])
    best_max = float(sweep.boundary_max[order[0]])
    knee = float(sweep.c[order[0]])
    for k in order[1:]:
        if not sweep.success[k]:
            continue
        bx, sm = float(sweep.boundary_max[k]), float(sweep.sub_mean[k])
        if bx > best_max + tol or sm > ref_mean + mtol:
            break
        knee = float(sweep.c[k])
        best_max = min(best_max, bx)
    return knee


@dataclass
class AutoConstraintResult:
    """Outcome of :func:`auto_constraint`: the chosen c (m), the sweep, the final fit and the BORDER rows."""

    c: float
    sweep: SweepResult
    result: ConstrainedFitResult
    boundary_index: torch.Tensor
    model: object = None


def border_rows(data: Measurements, axes, limits: torch.Tensor, k: int = 30, n: int = 10) -> torch.Tensor:
    """Rows of the BORDER poses (Paper I 3.4): boundary points of the identification commands in a 2-axis space.

    axes: the two axis indices (Paper I: B and Z, (4, 2) for XYZCB); limits:
    (n, 2) command range, used to scale both axes to [-1, 1] first; k, n:
    BORDER's neighbour count and number of boundary poses (Paper I: 30, 10).
    Uses :func:`torchcal.analysis.border.border_points` on one point per pose.
    -> (R,) bool, every row (tool) of a boundary pose.
    """
    from ..analysis.border import border_points  # another engineer's module: imported when needed

    poses, first = pose_first_rows(data.pose)
    q = data.q[first][:, list(axes)]
    lim = limits.to(q)[list(axes)]
    pts = 2.0 * (q - lim[:, 0]) / (lim[:, 1] - lim[:, 0]) - 1.0
    idx = border_points(pts, k=k, n=n)
    return torch.isin(data.pose, poses[idx.to(poses.device)])


@warns_once
def auto_constraint(make_model, data: Measurements, boundary_index=None, border_axes=None, border_k: int = 30,
                    border_n: int = 10, c_values=None, tol_mm: float = 0.01, mean_tol_mm: float | None = None,
                    noise: NoiseModel | None = None, prior: Prior | None = Prior(), **options) -> AutoConstraintResult:
    """Paper I 3.4-4.4 in one call: BORDER -> constraint sweep -> knee -> constrained refit on all data.

    make_model: a callable returning a fresh model (or a model, deep-copied);
    data: identification rows; boundary_index: the constraint-validation rows
    (indices or (R,) mask), or None to find them with BORDER in the two-axis
    space ``border_axes`` (Paper I: (B, Z) = (4, 2)), ``border_k`` neighbours,
    ``border_n`` poses; c_values, n_values (in options): see
    :func:`constraint_sweep`; tol_mm, mean_tol_mm: see :func:`pick_knee`.
    The final model is fitted on ALL rows with the chosen c (unconstrained when
    the knee is at inf) and is ``result``'s model, ``AutoConstraintResult.model``
    (``make_model`` is called once; the sweep and the final fit take copies).
    """
    # one fresh model, copied for the sweep and the final fit (a robot with gravity compliance reads its URDF's
    # inertials per construction: seconds)
    probe = _factory(make_model)()

    def factory():
        return copy.deepcopy(probe)

    if boundary_index is None:
        if border_axes is None:
            raise ValueError("auto_constraint: give boundary_index or border_axes (the two axes BORDER works in)")
        boundary_index = border_rows(data, border_axes, probe.command_limits, border_k, border_n)
    mask = _row_mask(boundary_index, len(data), data.q.device)
    sweep = constraint_sweep(factory, data, mask, c_values, noise, prior, stop_tol_mm=tol_mm,
                             stop_mean_tol_mm=mean_tol_mm, **options)
    c = pick_knee(sweep, tol_mm, mean_tol_mm)
    model = factory()
    options.pop("n_values", None)
    options.pop("span", None)
    # the final fit on all rows starts where the sweep's fit at the knee ended (the boundary rows move it a
    # little), with that fit's refined penalty points: no unconstrained start, fewer refinements
    k = next((i for i, cv in enumerate(sweep.c.tolist()) if cv == c), None)
    if k is not None and k < len(sweep.states):
        state, points = sweep.states[k]
        model.load_state_dict(state)
        if points is not None and not isinstance(options.get("points"), torch.Tensor):
            options = {**options, "points": points}
    try:
        result = fit_constrained(model, data, c, noise, prior, **options)
    except KeyboardInterrupt as exc:  # the whole sweep is done: it goes with the interrupt (constraint_sweep's)
        exc.sweep = sweep
        raise
    return AutoConstraintResult(c, sweep, result, mask, model)
