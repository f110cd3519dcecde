"""Online adaptive identification (Paper III (31)-(33)): a first model, then one update per batch of new poses.

Why one module: Paper III (31)-(33) in its information form and its literal form, with the state they carry between updates; the two forms are one algorithm and are checked against each other.

The first batch is identified with (31): joint errors v_k of every row, the
error parameters b, and the parameter prior. Each later batch of M rows
warm-starts from the previous parameters b_N* and never re-solves the earlier
rows' joint errors. What stands in for the earlier rows is the strategy:

- ``"information"`` (default): after each update, the new rows are linearized
  at the solution and their joint errors eliminated per row (the Schur
  complement that LM forms, :func:`marginal_information`); the resulting
  quadratic in b (information H, linear term g) is added to the carried one.
  The next update solves the new rows + the carried quadratic
  (:class:`InformationBlock`) + the prior: an information-form recursive least
  squares. Nothing of the earlier rows is re-evaluated, and the carried
  quadratic holds measurement information only, so the prior enters each
  objective exactly once. For a model linear in (b, v) this reproduces the
  all-rows fit exactly; for a robot it is exact up to the change of the
  earlier rows' Jacobians between linearization points.
- ``"literal"``: (33) as printed: every earlier row is kept, its joint error
  frozen at the value identified with it, and weighted by the measurement
  covariance alone (its v^T Sigma_v^-1 v term is a constant and drops out);
  all rows are refitted each batch. The frozen rows look more certain than
  they are (the joint-error uncertainty they carried is gone), which biases b
  towards them.

Which reading of (33): the paper drops v_1..v_N from the unknowns but keeps
e_1..e_N in the sum, i.e. e_k evaluated with the identified v_k*. That is the
literal strategy; the information strategy is what the same idea gives when
the earlier rows' joint errors are marginalized instead of frozen.

The carried information is indexed by parameter entry names
(:meth:`ParameterLayout.names`), so the gauge fixing of a later update (which
may pin other entries) cannot misalign it.

A warm update is solved on ONE linearization of its new rows (:func:`one_step`):
Gauss-Newton with the Jacobians frozen there (a chord iteration, each further
step a residual, not a linearization), until the decrease the next step
predicts is under ``warm_tol`` s^2. The rows' information is then carried at
that point (its residual, the frozen Jacobians). Where a step does not lower
the cost or no stop comes within a few steps, LM runs and stops once its
Gauss-Newton model predicts less than ``warm_tol`` s^2 of further decrease (see
:meth:`OnlineCalibration._solve`).

Measured (Paper III 5.5's protocol, order 3, N = 50 -> 250 by 25, 300
validation poses, default settings; experiments/paper3_sts, 2026-11-28):
simulated FANUC + STS on six seeds, every warm update one linearization and
one or two steps, the information strategy within 0.5-1.1 % (position) and 0.2-1.1 %
(angle) of the non-adaptive models at every N (with LM's updates, two or
three linearizations each: 0.4-1.9 % and 0.4-1.7 %), and the whole adaptive
sequence 23.5-28.7 % and 23.9-27.0 % of the non-adaptive sequence's CPU time
(two passes, one quiet run a seed; the target is 25 %; 39.5-43.5 % with LM's
updates). Point targets (3 tools,
measured when written, with LM updates): within 3.3 % on five seeds and 6.0 %
at N = 75 on the sixth (1.8 % from N = 100 on), the literal one 1.24-1.40x
above. Where the information strategy falls short it is at small N: the first
model's weakly determined combinations sit far (0.05 rad) from where more data
puts them, and the first batch's quadratic, taken there, misses the curvature
between. The order of the rows matters the same way: batches clustered in one
region of the workspace (rows sorted by joint 1) ended 5-6 % off the all-rows
fit in an independent check, random orders within 0.5 %.
"""

from __future__ import annotations

import logging
import time
from dataclasses import dataclass, field, replace

import torch

from ..measure import Instrument, PointTargets
from ..measure.base import concat
from ..core.measurements import Measurements
from ..core.progress import task as progress_task
from .fit import SOLVERS, fit, resolve_noise
from .gauge import fix_gauge
from .layout import ParameterLayout
from .lm import _blocks, _schur_factor, _schur_solve
from .problem import CalibrationProblem, NoiseModel, Prior, default_instrument
from .result import FitResult

log = logging.getLogger("torchcal")

STRATEGIES = ("information", "literal")
WARM_TOL = 1.0  # see OnlineCalibration._solve
STATE_FORMAT = "torchcal.OnlineCalibration"
STATE_VERSION = 1


def marginal_information(f: torch.Tensor, A: torch.Tensor, C: torch.Tensor, w_v: torch.Tensor,
                         v: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """The rows' quadratic in the parameter step db with each row's joint errors eliminated.

    sum_r min_dv_r |f_r + A_r db + C_r dv_r|^2 + (v_r + dv_r)^T W_r (v_r + dv_r) = c + 2 g^T db + db^T H db,

    H = sum_r A_r^T (I - C_r H_vv,r^-1 C_r^T) A_r,  g = sum_r A_r^T (f_r - C_r H_vv,r^-1 (C_r^T f_r + W_r v_r)),
    H_vv,r = C_r^T C_r + W_r: exactly the Schur complement of LM's normal equations
    (:mod:`torchcal.identify.lm`) without damping or prior. Rows with C_r = 0 (joint
    errors frozen or not estimated) give A_r^T A_r and A_r^T f_r.

    f: (R, d) whitened residual; A: (R, d, P), C: (R, d, n) whitened Jacobians;
    w_v: (R, n) joint-error precisions W_r (diagonal); v: (R, n) joint errors.
    -> H (P, P), g (P,).

    Example:
        >>> import torch
        >>> f, A = torch.ones(2, 1, dtype=torch.float64), torch.ones(2, 1, 1, dtype=torch.float64)
        >>> C, w_v, v = torch.zeros(2, 1, 1, dtype=torch.float64), torch.ones(2, 1, dtype=torch.float64), torch.zeros(2, 1)
        >>> H, g = marginal_information(f, A, C, w_v, v.double())  # C = 0: plain A^T A and A^T f
        >>> H.tolist(), g.tolist()
        ([[2.0]], [2.0])
    """
    R, d, P = A.shape
    Ct = C.transpose(1, 2)  # (R, n, d)
    L = torch.linalg.cholesky(Ct @ C + torch.diag_embed(w_v))
    n = C.shape[-1]
    eye = torch.eye(n, dtype=A.dtype, device=A.device).expand(R, n, n)
    Li = torch.linalg.solve_triangular(L, eye, upper=False)  # L^-1 (R, n, n)
    W = Li @ Ct  # (R, n, d)
    M = torch.eye(d, dtype=A.dtype, device=A.device) - W.transpose(1, 2) @ W  # I - C H_vv^-1 C^T
    Af = A.reshape(R * d, P)
    H = Af.T @ (M @ A).reshape(R * d, P)
    z = Li @ ((Ct @ f[..., None])[..., 0] + w_v * v)[..., None]  # L^-1 (C^T f + W v), (R, n, 1)
    e = f - (W.transpose(1, 2) @ z)[..., 0]  # f - C H_vv^-1 (C^T f + W v), (R, d)
    g = Af.T @ e.reshape(-1)
    return 0.5 * (H + H.T), g


class InformationBlock:
    """A carried quadratic Q(x) = (x - x_ref)^T H (x - x_ref) + 2 g^T (x - x_ref) on named entries (a ParamBlock).

    names: k entry names (:meth:`ParameterLayout.names`); H: (k, k) information
    (symmetric positive semi-definite, SI: 1/rad^2, 1/m^2, ...); g: (k,) linear
    term at x_ref; x_ref: (k,) the linearization point, SI. Written as residuals
    r = J (x - x_ref) + r0 with J = Lambda^1/2 U^T from H = U Lambda U^T (directions
    with eigenvalue below ``rtol`` of the largest carry no information and are
    dropped; g lies in the span of the others), so J^T J = H, J^T r = H (x - x_ref) + g
    and |r|^2 = Q(x) + const. Entries the layout does not have free (pinned by the
    gauge, held fixed) enter at their current model value, as constants.

    Example:
        >>> import torch
        >>> b = InformationBlock(["base.eps_x"], 4 * torch.eye(1), torch.zeros(1), torch.ones(1))
        >>> b.quadratic(torch.tensor([3.0], dtype=torch.float64)).item()  # (3 - 1) * 4 * (3 - 1)
        16.0
    """

    linear_residual = True
    """Q is a quadratic in x (a linear residual): a Gauss-Newton model of it is Q itself."""

    def __init__(self, names, H: torch.Tensor, g: torch.Tensor, x_ref: torch.Tensor, rtol: float = 1e-13):
        self.names = list(names)
        k = len(self.names)
        self.H = torch.as_tensor(H, dtype=torch.float64)
        self.g = torch.as_tensor(g, dtype=torch.float64).reshape(-1)
        self.x_ref = torch.as_tensor(x_ref, dtype=torch.float64).reshape(-1)
        if self.H.shape != (k, k) or self.g.shape != (k,) or self.x_ref.shape != (k,):
            raise ValueError(f"InformationBlock: {k} names, H {tuple(self.H.shape)}, g {tuple(self.g.shape)}, "
                             f"x_ref {tuple(self.x_ref.shape)}")
        if len(set(self.names)) != k:
            raise ValueError("InformationBlock: names repeat")
        self.rtol = rtol
        self._residual_form: tuple | None = None
        self._cache: tuple | None = None

    def _factor(self) -> tuple[torch.Tensor, torch.Tensor]:
        """(J (k', k), r0 (k',)) of the residual form, computed when first needed (one eigendecomposition)."""
        if self._residual_form is None:
            lam, U = torch.linalg.eigh(0.5 * (self.H + self.H.T))
            keep = lam > self.rtol * max(float(lam.max()), 0.0) if len(self.names) else lam > 0
            lam, U = lam[keep], U[:, keep]
            self._residual_form = (lam.sqrt()[:, None] * U.T, (U.T @ self.g) / lam.sqrt())
        return self._residual_form

    @property
    def J(self) -> torch.Tensor:
        return self._factor()[0]

    @property
    def r0(self) -> torch.Tensor:
        return self._factor()[1]

    def quadratic(self, x_named: torch.Tensor) -> torch.Tensor:
        """Q at values (k,) of the block's own entries (in ``names`` order)."""
        d = x_named - self.x_ref.to(x_named)
        return d @ (self.H.to(x_named) @ d) + 2 * self.g.to(x_named) @ d

    def _bind(self, layout: ParameterLayout, like: torch.Tensor):
        if self._cache is None or self._cache[0] is not layout:
            free = {n: i for i, n in enumerate(layout.names())}
            pos = torch.tensor([free.get(n, -1) for n in self.names], dtype=torch.long)
            is_free = pos >= 0
            if bool(is_free.all()):  # the usual case (the gauge pinned as before): no entry needs the model's value
                base = torch.zeros(len(self.names), dtype=torch.float64)
            else:
                full = ParameterLayout(layout.model, (), None, layout._all_groups)
                values = dict(zip(full.names(), full.get().tolist()))
                missing = [n for n in self.names if n not in values]
                if missing:
                    raise ValueError(f"InformationBlock: {missing[:5]} are not parameter entries of the model")
                base = torch.tensor([values[n] for n in self.names], dtype=torch.float64)  # pinned entries: constants
            self._cache = (layout, pos, is_free, base, {})
        _, pos, is_free, base, _ = self._cache
        dev = like.device
        return pos.to(dev), is_free.to(dev), base.to(like)

    def _layout_matrix(self, key: str, layout: ParameterLayout, like: torch.Tensor) -> torch.Tensor:
        """J (k', P) or H (P, P) scattered onto the layout's free entries, cached per layout."""
        pos, is_free, _ = self._bind(layout, torch.empty(0, dtype=torch.float64))
        store = self._cache[4]
        if key not in store:
            P = layout.size
            cols = pos[is_free]
            if key == "H" and len(self.names) == P and bool(is_free.all()) and torch.equal(cols, torch.arange(P)):
                store[key] = 0.5 * (self.H + self.H.T)  # the layout's own order (the usual case): no scatter
                return store[key].to(like)
            if key == "J":
                M = torch.zeros(self.J.shape[0], P, dtype=torch.float64)
                M[:, cols] = self.J[:, is_free]
            else:
                M = torch.zeros(P, P, dtype=torch.float64)
                Hs = 0.5 * (self.H + self.H.T)
                M[cols[:, None], cols[None, :]] = Hs[is_free][:, is_free]
            store[key] = M
        return store[key].to(like)

    def named_values(self, x: torch.Tensor, layout: ParameterLayout) -> torch.Tensor:
        """(k,) values of the block's entries: from x (P,) where free in ``layout``, else the model's (differentiable in x)."""
        pos, is_free, base = self._bind(layout, x)
        return base.masked_scatter(is_free, x[pos[is_free]])

    def linearize(self, x: torch.Tensor, layout: ParameterLayout) -> tuple[torch.Tensor, torch.Tensor]:
        xn = self.named_values(x, layout)
        r = self.J.to(x) @ (xn - self.x_ref.to(x)) + self.r0.to(x)
        return r, self._layout_matrix("J", layout, x)

    def normal_equations(self, x: torch.Tensor, layout: ParameterLayout):
        """J^T J (P, P), J^T r (P,) and Q(x) at x, straight from H and g (no residual form, no eigendecomposition).

        The residual form's constant |r0|^2 is left out of the cost: it shifts V, not its minimizer.
        """
        pos, is_free, _ = self._bind(layout, x)
        d = self.named_values(x, layout) - self.x_ref.to(x)
        H = self.H.to(x)
        grad = H @ d + self.g.to(x)
        g = torch.zeros(layout.size, dtype=x.dtype, device=x.device)
        g[pos[is_free]] = grad[is_free]
        return self._layout_matrix("H", layout, x), g, d @ (grad + self.g.to(x))

    def cost(self, x: torch.Tensor, layout: ParameterLayout) -> torch.Tensor:
        """Q(x) (differentiable in x), consistent with :meth:`normal_equations`."""
        return self.quadratic(self.named_values(x, layout))


@dataclass
class OnlineStep:
    """What one :meth:`OnlineCalibration.update` did.

    result: the solver's FitResult (x in its layout, v of the rows it solved
    for: the new rows for 'information', all rows for 'literal'); batch:
    0-based batch index; rows: rows identified so far (all batches); new_rows:
    this batch's rows; seconds: wall time of the whole update (solve and
    information update); strategy; pinned: entries the gauge pinned.
    """

    result: FitResult
    batch: int
    rows: int
    new_rows: int
    seconds: float
    strategy: str
    pinned: list[str] = field(default_factory=list)

    def summary(self) -> dict:
        """JSON-ready scalars."""
        return {"batch": self.batch, "rows": self.rows, "new_rows": self.new_rows, "seconds": float(self.seconds),
                "strategy": self.strategy, "iterations": int(self.result.nit), "cost": float(self.result.fun),
                "converged": bool(self.result.success), "pinned": len(self.pinned)}


def cat_measurements(parts: list[Measurements]) -> Measurements:
    """The rows of several Measurements in order (SI tensors concatenated; ``extra`` keys every part has)."""
    parts = list(parts)
    if len(parts) == 1:
        return parts[0]
    n = {p.n_joints for p in parts}
    if len(n) != 1:
        raise ValueError(f"cat_measurements: parts with different joint counts {sorted(n)}")
    keys = set(parts[0].extra).intersection(*(p.extra for p in parts[1:]))
    first = parts[0]
    dev = first.q.device
    return replace(
        first,
        q=torch.cat([p.q.to(dev) for p in parts]), tool=torch.cat([p.tool.to(dev) for p in parts]),
        xyz=torch.cat([p.xyz.to(dev) for p in parts]), direction=torch.cat([p.direction.to(dev) for p in parts]),
        pose=torch.cat([p.pose.to(dev) for p in parts]), rows=torch.cat([p.rows for p in parts]),
        has_direction=all(p.has_direction for p in parts),
        source=" + ".join(dict.fromkeys(p.source for p in parts)),
        extra={k: torch.cat([p.extra[k].to(dev) for p in parts]) for k in sorted(keys)},
    )


class OnlineCalibration:
    """Streamed identification: feed a batch of rows, get the model updated in place (Paper III (31), (33)).

    model: a model :func:`~torchcal.identify.fit` accepts (RobotModel, SensorRig,
    ...), updated in place from its current values; noise: joint variances and
    the default instrument's sigma_m (None: the robot's declared repeatability);
    prior: Gaussian prior on the parameters (Paper III (31)'s Sigma_b), entering
    every objective once; strategy: 'information' (default, see the module) or
    'literal' ((33) as printed); method: 'lm' or 'lbfgs'; fixed: parameter
    groups held fixed; gauge: pin exactly redundant entries (judged by the
    first update and kept, see :meth:`pin`); blocks: further
    parameter-only blocks; warm_mu0: LM's initial damping in the updates after the
    first (warm-started next to the solution; None: the solver's default, or
    give mu0 in fit_options); warm_tol: when the updates after the first stop,
    in units of s^2, the cost per residual entry: an update ends once the
    Gauss-Newton model predicts less than warm_tol * s^2 further decrease, i.e.
    the remaining step is under sqrt(warm_tol) standard errors (None: the
    first update's ftol; an ftol in fit_options applies to every update and
    overrides it); fit_options: solver options (max_iter, ftol, ...).

    Example:
        >>> import torch, torchcal
        >>> robot = torchcal.load_robot("fanuc_lrmate200i")
        >>> tools = torch.tensor([[0.033, 0.058, 0.161], [0.057, -0.034, 0.161], [-0.034, -0.057, 0.161]], dtype=torch.float64)
        >>> truth = torchcal.TruthRobot.fanuc_paper2(robot, tools, 0)
        >>> q = torchcal.sim.quasi_random_commands(robot.joint_map.limits, 40, 0)
        >>> data = torchcal.simulate(truth, q, [0, 1, 2], torchcal.NoiseModel.from_robot(robot), 0)
        >>> online = OnlineCalibration(torchcal.RobotModel(robot, tools, orders=1))
        >>> first = online.update(data.poses_subset(range(30)))            # (31): the first model
        >>> step = online.update(data.poses_subset(range(30, 40)))         # (33): 10 more poses
        >>> step.batch, step.rows, step.new_rows, step.result.success
        (1, 120, 30, True)
    """

    def __init__(self, model, noise: NoiseModel | None = None, prior: Prior | None = Prior(), strategy: str = "information",
                 method: str = "lm", fixed=(), gauge: bool = True, blocks=(), warm_mu0: float | None = 1e-6,
                 warm_tol: float | None = WARM_TOL, **fit_options):
        if strategy not in STRATEGIES:
            raise ValueError(f"unknown online strategy '{strategy}', choose from {list(STRATEGIES)}")
        if method not in SOLVERS:
            raise ValueError(f"unknown solver '{method}', choose from {sorted(SOLVERS)}")
        self.model = model
        self.noise = resolve_noise(model, noise)
        self.prior = prior
        self.strategy = strategy
        self.method = method
        self.fixed = tuple(fixed)
        self.gauge = gauge
        self.blocks = list(blocks)
        self.fit_options = fit_options
        self.warm_mu0 = warm_mu0
        self.warm_tol = warm_tol
        self.batches = 0
        self.rows = 0
        self.pinned: list[str] | None = None  # gauge: fixed by the first update (see pin())
        # information strategy: the carried measurement information, by entry name
        self.names: list[str] = []
        self.H: torch.Tensor | None = None
        self.g: torch.Tensor | None = None
        self.x_ref: torch.Tensor | None = None
        # literal strategy: every row so far, its instrument and its frozen joint errors
        self.data: Measurements | None = None
        self.instrument: Instrument | None = None
        self.v: torch.Tensor | None = None

    # ----------------------------------------------------------------- update
    def update(self, data: Measurements, instrument: Instrument | None = None) -> OnlineStep:
        """Identify with the rows of ``data`` added; the model is updated in place.

        data: the batch's rows (SI); instrument: its measurement model (None:
        point targets on ``data.xyz`` with the noise's sigma_m).
        """
        if len(data) == 0:
            raise ValueError(f"{data.source}: an online update needs at least one row")
        t0 = time.perf_counter()
        data = data.to(self.model.device)
        instrument = (default_instrument(data, self.noise) if instrument is None else instrument).to(self.model.device)
        if len(instrument) != len(data):
            raise ValueError(f"{data.source}: the instrument has {len(instrument)} rows, the data {len(data)}")
        with progress_task(f"online update ({self.strategy}): batch {self.batches + 1}, {len(data)} new rows"):
            if self.strategy == "literal":
                result = self._update_literal(data, instrument)
            else:
                result = self._update_information(data, instrument)
        self._count(data)
        return OnlineStep(result, self.batches - 1, self.rows, len(data), time.perf_counter() - t0, self.strategy,
                          list(result.pinned))

    def absorb(self, data: Measurements, instrument: Instrument | None = None, v: torch.Tensor | None = None,
               pinned=None) -> torch.Tensor:
        """Take rows the model already reflects (e.g. an earlier fit's identification data) as a first batch, unsolved.

        Nothing is fitted: the rows' information at the current parameters joins the carried quadratic
        ('information') or the rows are stored with frozen joint errors ('literal'). v: (R, n) their
        joint errors (None: each row's own optimum at the current parameters, :func:`solve_joint_errors`);
        pinned: the earlier fit's gauge (its pinned entry names), kept by later updates (None: judged on these
        rows as a fit of them judges it, :func:`~torchcal.identify.gauge.fix_gauge`).
        -> the joint errors used (R, n).
        """
        data = data.to(self.model.device)
        instrument = (default_instrument(data, self.noise) if instrument is None else instrument).to(self.model.device)
        if v is None:
            with progress_task(f"online: joint errors of {len(data)} earlier rows"):
                v = solve_joint_errors(self.model, data, self.noise, instrument, self.fixed)
        v = v.to(data.q)
        if pinned is not None:
            self.pin(pinned)
        elif self.gauge and self.pinned is None:
            # judged on these rows (the model's own data) rather than on whatever the first update brings: a
            # first batch of 5 rows pinned 146 of 156 entries, kept in every update after it
            self.pinned = fix_gauge(CalibrationProblem(self.model, data, self.noise, self.prior, self.fixed, instrument))
        if self.strategy == "literal":
            if self.data is None:
                self.data, self.instrument, self.v = data, instrument, v.clone()
            else:
                self.data = cat_measurements([self.data, data])
                self.instrument = concat([self.instrument, instrument])
                self.v = torch.cat([self.v.to(v), v])
        else:
            self._absorb(data, instrument, v)
        # a model fitted on these rows records their directions already (fit() sets model.coverage)
        self._count(data, coverage=getattr(self.model, "coverage", None) is None)
        return v

    def _count(self, data: Measurements, coverage: bool = True) -> None:
        self.batches += 1
        self.rows += len(data)
        if coverage and data.has_direction and getattr(self.model, "command_limits", None) is not None:
            # the directions every row so far came from (what fit() records for one batch)
            from ..core.coverage import DirectionCoverage

            cov = getattr(self.model, "coverage", None)
            self.model.coverage = (DirectionCoverage.from_data(data.q, data.direction, self.model.command_limits)
                                   if cov is None else cov.update(data.q, data.direction))
        if hasattr(self.model, "record_data_span"):  # the range every row so far covered
            self.model.record_data_span(data.q)

    def _solve(self, data: Measurements, instrument: Instrument, blocks, fixed_rows=None, v0=None) -> FitResult:
        """One identification, the gauge pinned as in the first update (see :meth:`pin`)."""
        full, pinned = self._layouts()
        problem = _RememberingProblem(self.model, data, self.noise, self.prior, self.fixed, instrument, blocks,
                                      fixed_rows, v0, layout=full)
        self._last_problem = problem
        if self.gauge:
            if self.pinned is None:
                self.pinned = fix_gauge(problem)
                if 2 * len(self.pinned) > full.size:
                    # what a few rows leave undetermined is pinned for good: later batches cannot free it
                    log.warning("online calibration: the first batch (%d rows) leaves %d of %d parameter entries "
                                "undetermined, and they stay pinned in every later update; begin with more rows, or "
                                "absorb() a fitted model's rows first", len(data), len(self.pinned), full.size)
            else:
                if pinned is None:
                    keep = set(self.pinned)
                    pinned = full.without(torch.tensor([n in keep for n in full.names()], dtype=torch.bool))
                    self._layout_cache = self._layout_cache[:2] + (pinned,)
                problem.set_layout(pinned)
        options = dict(self.fit_options)
        if self.method == "lm" and self.batches > 0 and self.warm_mu0 is not None:
            # warm start: the previous model is next to the solution, so begin near Gauss-Newton. LM's cold
            # default (1e-4 of the diagonal) damps the weakly determined combinations, and Nielsen's rule
            # lowers it at most 3x per iteration: measured 9-22 iterations per 25-pose update, 5-13 with 1e-6
            options.setdefault("mu0", self.warm_mu0)
        if self.batches > 0 and self.warm_tol is not None:
            # A warm update need not reach the optimum to solver precision: the carried quadratic is the Taylor
            # expansion at wherever the update stops (its gradient g included), so the next update carries on
            # from there, as an incremental smoother relinearizes once per batch. What is left undone must
            # only be small against the estimate's own uncertainty: a Gauss-Newton decrease of warm_tol * s^2
            # is a step of sqrt(warm_tol) standard errors (s^2 = cost per residual entry: the residuals here
            # are mostly model error, not the tracker's noise, so chi-square units would be far too strict).
            # LM's test is ftol * cost, hence ftol = warm_tol / entries of the rows this solve sees.
            entries = max(len(instrument) * max(int(instrument.dim), 1), 1)
            options.setdefault("ftol", self.warm_tol / entries)
        result, self._step_information = None, None
        if self.method == "lm" and self.batches > 0 and self.warm_tol is not None and "ftol" in options:
            step = one_step(problem, options["ftol"])
            if step is not None:
                result, self._step_information = step
                if options.get("callback") is not None:  # as LM calls it after its iteration
                    options["callback"](1, result.fun)
        if result is None:
            result = SOLVERS[self.method](problem, **options)
        result.pinned = list(self.pinned or [])
        return result

    def _layouts(self):
        """(every entry not held fixed, the same with the pinned entries held or None), kept while the model's
        parameters, the fixed groups and the pinned names stay what they were: a batch of a few rows costs
        little more to solve than to set up, and these were a tenth of an update."""
        key = (self.fixed, tuple(self.pinned or ()),
               tuple((n, id(p), p.device, p.dtype) for n, p in self.model.named_parameters()),
               # the masks that declare which entries exist are buffers: an edit (or a load_state_dict) bumps them
               tuple((n, b.data_ptr(), b._version) for n, b in self.model.named_buffers()))
        cache = getattr(self, "_layout_cache", None)
        if cache is None or cache[0] != key:
            cache = self._layout_cache = (key, ParameterLayout(self.model, self.fixed), None)
        return cache[1], cache[2]

    def pin(self, names) -> None:
        """Hold these entries (names as :meth:`ParameterLayout.names`) at their value in every later update.

        By default the first update fixes the gauge as :func:`~torchcal.identify.fit` does (on the first
        batch's Jacobian at the model's starting values, as every from-scratch fit of the non-adaptive
        baseline does) and later updates keep that set: the directions of the exact redundancies move with
        the parameters, so information summed over several linearization points is never exactly singular
        and a fresh judgement would free them (measured: 18 pins at the start, 0 after three updates,
        and the solution drifts along the freed directions). A model that continues an earlier fit
        takes that fit's pinned names here.
        """
        self.pinned = list(names)

    def _update_literal(self, data: Measurements, instrument: Instrument) -> FitResult:
        if self.data is None:
            all_data, all_inst, fixed_rows, v0 = data, instrument, None, None
        else:
            all_data = cat_measurements([self.data, data])
            all_inst = concat([self.instrument, instrument])
            R0 = len(self.data)
            fixed_rows = torch.arange(len(all_data), device=data.q.device) < R0
            v0 = torch.cat([self.v.to(data.q), torch.zeros_like(data.q)])
        result = self._solve(all_data, all_inst, self.blocks, fixed_rows, v0)
        self.data, self.instrument, self.v = all_data, all_inst, result.v.detach().clone()
        return result

    def _update_information(self, data: Measurements, instrument: Instrument) -> FitResult:
        carried = self.information_block()
        result = self._solve(data, instrument, self.blocks + ([carried] if carried is not None else []))
        problem = self._last_problem
        if self._step_information is not None:
            # one_step: the rows' quadratic at its end (x_k, the residual there, the Jacobians of its one
            # linearization), where the next update starts
            xk, H_new, g_new = self._step_information
            self._merge(problem.layout.names(), H_new, g_new, xk)
            return result
        last = problem.last_linearization(result.x, result.v)
        if last is None:  # the solver did not end on a linearization at its solution (e.g. L-BFGS)
            self._absorb(data, instrument, result.v)
        else:
            # LM's own linearization at the solution: the entries it left free are all later updates move
            f, A, C = last
            H_new, g_new = marginal_information(f, A, C, problem.w_v, result.v.to(f))
            self._merge(problem.layout.names(), H_new, g_new, result.x)
        return result

    @torch.no_grad()
    def _absorb(self, data: Measurements, instrument: Instrument, v: torch.Tensor) -> None:
        """Add the rows' marginal information at the current parameters to the carried quadratic."""
        p = CalibrationProblem(self.model, data, self.noise, None, self.fixed, instrument)  # every free entry, no gauge
        x = p.layout.get().to(self.model.device)
        f, A, C = p.linearize(x, v.to(x))
        H_new, g_new = marginal_information(f, A, C, p.w_v, v.to(x))
        self._merge(p.layout.names(), H_new, g_new, x)

    @torch.no_grad()
    def _merge(self, names: list[str], H_new: torch.Tensor, g_new: torch.Tensor, x: torch.Tensor) -> None:
        """carried := carried re-centred at x (exact: it is a quadratic) + the new rows' (H_new, g_new) at x.

        Works on the union of both name sets: an entry only the carried quadratic has (pinned in this
        update) keeps its value, read from the model.
        """
        H_new, g_new, x = H_new.detach().cpu(), g_new.detach().cpu(), x.detach().cpu().to(torch.float64)
        if self.H is None:
            self.names, self.H, self.g, self.x_ref = list(names), H_new, g_new, x
            return
        if list(names) == self.names:  # the usual case (the same entries free as before): no re-indexing
            H = H_new + self.H
            self.g = g_new + self.g + self.H @ (x - self.x_ref)
            self.H, self.x_ref = 0.5 * (H + H.T), x
            return
        known = set(names)
        extra = [n for n in self.names if n not in known]
        if extra:
            full = ParameterLayout(self.model)
            values = dict(zip(full.names(), full.get().detach().cpu().tolist()))
            missing = [n for n in extra if n not in values]
            if missing:
                raise ValueError(f"OnlineCalibration: carried information on {missing[:5]}, which the model does not have")
            x = torch.cat([x, torch.tensor([values[n] for n in extra], dtype=torch.float64)])
        union = list(names) + extra
        k, U = len(names), len(union)
        where = {n: i for i, n in enumerate(union)}
        idx = torch.tensor([where[n] for n in self.names], dtype=torch.long)
        H = torch.zeros(U, U, dtype=torch.float64)
        g = torch.zeros(U, dtype=torch.float64)
        H[:k, :k] = H_new
        g[:k] = g_new
        H[idx[:, None], idx[None, :]] += self.H
        g[idx] += self.g + self.H @ (x[idx] - self.x_ref)
        self.names, self.H, self.g, self.x_ref = union, 0.5 * (H + H.T), g, x

    def information_block(self) -> InformationBlock | None:
        """The earlier rows' carried quadratic as a parameter block (None before the first update or for 'literal')."""
        if self.H is None:
            return None
        return InformationBlock(self.names, self.H, self.g, self.x_ref)

    # ------------------------------------------------------------------ state
    def state_dict(self) -> dict:
        """Everything a later update needs, as tensors and plain values (``torch.save`` / ``weights_only`` loadable).

        x: the model's declared entries by name (SI; held-fixed groups too); names, H, g, x_ref: the carried
        information; batches, rows; strategy; literal: the stored rows, their frozen
        joint errors and (point targets only) their instrument.
        """
        full = ParameterLayout(self.model)  # every entry, held-fixed groups too
        state = {"format": STATE_FORMAT, "version": STATE_VERSION, "strategy": self.strategy, "batches": self.batches,
                 "rows": self.rows, "pinned": None if self.pinned is None else list(self.pinned),
                 "x_names": full.names(), "x": full.get().detach().cpu().clone(),
                 "names": list(self.names), "H": None if self.H is None else self.H.clone(),
                 "g": None if self.g is None else self.g.clone(), "x_ref": None if self.x_ref is None else self.x_ref.clone(),
                 "literal": None}
        if self.data is not None:
            state["literal"] = {"data": _measurements_state(self.data), "v": self.v.detach().cpu().clone(),
                                "instrument": _instrument_state(self.instrument)}
        return state

    def load_state_dict(self, state: dict, instrument: Instrument | None = None) -> None:
        """Restore :meth:`state_dict`: the model's values, the carried information or stored rows, the counts.

        instrument: the literal strategy's stored instrument where the state could
        not hold it (other than point targets).
        """
        if not isinstance(state, dict) or state.get("format") != STATE_FORMAT:
            raise ValueError("OnlineCalibration.load_state_dict: not an online-calibration state")
        if state.get("version", 0) > STATE_VERSION:
            raise ValueError(f"OnlineCalibration.load_state_dict: state version {state['version']} is newer than this torchcal's")
        if state["strategy"] != self.strategy:
            raise ValueError(f"OnlineCalibration.load_state_dict: the state is for strategy '{state['strategy']}', "
                             f"this calibration uses '{self.strategy}'")
        full = ParameterLayout(self.model)  # every entry, held-fixed groups too
        where = {n: i for i, n in enumerate(state["x_names"])}
        names = full.names()
        missing = [n for n in names if n not in where]
        if missing:
            raise ValueError(f"OnlineCalibration.load_state_dict: the state has no value for {missing[:5]}")
        x = state["x"].to(torch.float64)[torch.tensor([where[n] for n in names], dtype=torch.long)]
        full.set(x.to(self.model.device))
        self.batches, self.rows = int(state["batches"]), int(state["rows"])
        self.pinned = None if state.get("pinned") is None else list(state["pinned"])
        self.names = list(state["names"])
        self.H, self.g, self.x_ref = state["H"], state["g"], state["x_ref"]
        lit = state.get("literal")
        if lit is None:
            self.data = self.instrument = self.v = None
            return
        self.data = measurements_from_state(lit["data"])
        inst = _instrument_from_state(lit["instrument"]) if lit["instrument"] is not None else instrument
        if inst is None:
            raise ValueError("OnlineCalibration.load_state_dict: the literal strategy's instrument was not stored "
                             "(not point targets); pass instrument=")
        self.instrument, self.v = inst, lit["v"]


_MEAS_TENSORS = ("q", "tool", "xyz", "direction", "pose", "rows")


class _RememberingProblem(CalibrationProblem):
    """A CalibrationProblem that keeps its latest linearization, so the information of the rows at the
    solver's solution costs no further kinematics pass."""

    _last = None

    def linearize(self, x, v, jacobian=None):
        out = super().linearize(x, v, jacobian)
        self._last = (x.detach().clone(), v.detach().clone(), out)
        return out

    def last_linearization(self, x, v):
        """(f, A, C) of the latest linearization if it was at exactly (x, v), else None."""
        if self._last is None:
            return None
        lx, lv, out = self._last
        same = lx.shape == x.shape and lv.shape == v.shape and torch.equal(lx, x.to(lx)) and torch.equal(lv, v.to(lv))
        return out if same else None


ONE_STEP = "converged: Gauss-Newton on one linearization (chord), the remaining decrease below warm_tol s^2"
CHORD_ITERATIONS = 6
"""At most this many steps on a warm update's one linearization before LM takes over (measured: 1-3)."""


@torch.no_grad()
def one_step(problem: CalibrationProblem, ftol: float):
    """A warm update solved on ONE linearization: Gauss-Newton with the Jacobians frozen at the start (a chord
    iteration), each step costing a residual instead of a linearization.

    From the model's values x0: one linearization (f0, A, C) and its factorization; then steps from the
    residual f_k at x_k with those Jacobians, until the decrease the next such step predicts is at most
    ftol * |f_k|^2 (ftol = warm_tol / entries: warm_tol s^2, s^2 the rows' misfit per entry, LM's stopping
    tolerance). The model's nonlinearity over the steps shows in f_k, so the predicted remaining decrease is
    the chord's estimate of what a fresh linearization would still find (measured on the STS stream of
    experiments/paper3_sts: the first update after the cold fit 78 s^2 before its second step, later ones
    0.1-2.5 s^2 after the first). Most updates stop after one step: one linearization and one residual, where
    LM pays a second linearization to learn that it may stop.

    -> (FitResult (message :data:`ONE_STEP`; the model set to the last x_k; grad_norm NaN: the exact gradient
    there needs a linearization), (x_k (P,), H (P, P), g (P,)): the rows' quadratic at x_k with their joint
    errors eliminated, H from the frozen Jacobians and g from the residual at x_k (what
    :func:`marginal_information` gives with those), from the same factorization), or None with the model at
    x0 when a step did not lower V, no stop came within :data:`CHORD_ITERATIONS` steps, or a joint error is
    held (then the factorization is not the rows' information); the caller then runs the solver.
    """
    t0 = time.perf_counter()
    layout = problem.layout
    x0 = layout.get().to(problem.model.device)
    v = problem.v_zero()
    if problem.v_free is not None and not bool(problem.v_free.all()) and problem.estimate_v:
        return None
    f, A, C = problem.linearize(x0, v)
    H_blk, g_blk, c_blk = _blocks(problem, x0)
    factor = _schur_factor(A, C, problem.w_v, problem.prior_precision, 0.0, H_blk)
    quadratic_blocks = H_blk is not None and all(getattr(b, "linear_residual", False) is True for b in problem.blocks)
    x, cost = x0, float(problem.cost_from(f, x0, v, c_blk))
    history = [cost]
    for k in range(CHORD_ITERATIONS + 1):
        db, dv, _, (H_rows, g_rows) = _schur_solve(factor, f, v, problem.prior_precision, x - problem.prior_mean,
                                                   g_blk, problem.v_free, rows_information=True)
        lin = f + (A @ db[:, None])[..., 0] + (C @ dv[..., None])[..., 0]
        lin_blk = None if H_blk is None else c_blk + 2 * (g_blk @ db) + db @ (H_blk @ db)
        predicted = cost - float(problem.cost_from(lin, x + db, v + dv, lin_blk))
        if k > 0 and predicted <= ftol * float((f * f).sum()):
            result = FitResult(x=x.detach().clone(), v=v.detach().clone(), success=True, message=ONE_STEP, nit=k,
                               nfev=k + 1, fun=cost, grad_norm=float("nan"), time=time.perf_counter() - t0,
                               method="lm", history=history, names=layout.names())
            return result, (x.detach().clone(), H_rows, g_rows)
        if k == CHORD_ITERATIONS:
            break
        x1, v1 = x + db, v + dv
        f1 = problem.residual(x1, v1)
        if quadratic_blocks:  # their J^T r and cost at x1 follow from x's exactly
            g1, c1 = g_blk + H_blk @ db, lin_blk
        else:
            _, g1, c1 = _blocks(problem, x1)
        new_cost = float(problem.cost_from(f1, x1, v1, c1))
        if not new_cost < cost:
            break
        x, v, f, cost, g_blk, c_blk = x1, v1, f1, new_cost, g1, c1
        history.append(cost)
    layout.set(x0)
    return None


@torch.no_grad()
def solve_joint_errors(model, data: Measurements, noise: NoiseModel, instrument: Instrument | None = None, fixed=(),
                       iterations: int = 20, tol: float = 1e-15) -> torch.Tensor:
    """Each row's joint errors v_r (R, n) minimizing its term of (31) at the model's current parameters.

    Gauss-Newton on v alone, all rows at once (each row's n x n system); stops when
    no joint error moves by more than ``tol`` (rad / m).
    """
    p = CalibrationProblem(model, data, noise, None, fixed, instrument)
    x = p.layout.get().to(data.q.device)
    v = torch.zeros_like(p.data.q)
    if not p.estimate_v:
        return v
    for _ in range(iterations):
        f, _, C = p.linearize(x, v)
        Ct = C.transpose(1, 2)
        dv = -torch.linalg.solve(Ct @ C + torch.diag_embed(p.w_v), ((Ct @ f[..., None])[..., 0] + p.w_v * v)[..., None])[..., 0]
        v = v + dv
        if float(dv.abs().max()) <= tol:
            break
    return v


def _measurements_state(data: Measurements) -> dict:
    out = {k: getattr(data, k).detach().cpu().clone() for k in _MEAS_TENSORS}
    out.update(has_direction=bool(data.has_direction), source=str(data.source),
               extra={k: v.detach().cpu().clone() for k, v in data.extra.items()})
    return out


def measurements_from_state(s: dict) -> Measurements:
    return Measurements(**{k: s[k] for k in _MEAS_TENSORS}, has_direction=bool(s["has_direction"]),
                        source=s["source"], extra=dict(s["extra"]))


def _instrument_state(inst: Instrument) -> dict | None:
    if type(inst) is not PointTargets:
        return None
    w = inst.weight
    return {"kind": "points", "observed": inst.observed.detach().cpu().clone(),
            "sigma": getattr(w, "sigma", None), "cov": None if getattr(w, "sigma", None) is not None else w.cov.cpu().clone()}


def _instrument_from_state(s: dict) -> Instrument:
    if s.get("kind") != "points":
        raise ValueError(f"OnlineCalibration: unknown stored instrument kind {s.get('kind')!r}")
    return PointTargets(s["observed"], sigma=s["sigma"]) if s["sigma"] is not None else PointTargets(s["observed"], cov=s["cov"])


def batch_refit(make_model, data: Measurements, noise: NoiseModel | None = None, prior: Prior | None = Prior(),
                instrument: Instrument | None = None, method: str = "lm", **fit_options):
    """The non-adaptive baseline ((31) on every row so far): a fresh model from ``make_model()``, fitted from scratch.

    -> (model, FitResult).
    """
    model = make_model()
    return model, fit(model, data, noise, prior, method, instrument=instrument, **fit_options)


__all__ = [
    "STRATEGIES",
    "InformationBlock",
    "OnlineCalibration",
    "OnlineStep",
    "batch_refit",
    "cat_measurements",
    "marginal_information",
    "solve_joint_errors",
]
