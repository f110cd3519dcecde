"""Many candidate models scored from ONE linearization: the model batch dimension of model selection.

Choosing orders (Paper II 5.5, Figure 11) compares dozens of models of one
machine that differ only in which error terms they carry: every candidate is
a sub-model of one *superset* (the largest order of every term). Fitting each
from scratch repeats the same work: the error model is nearly linear in its
parameters (errors are ~1e-3 of the nominal geometry), so the superset's
Jacobian at one fitted point describes every candidate around it.

:class:`SharedLinearization` linearizes the superset once, at a fitted point,
with the joint errors of every row marginalized (as :func:`loo_residuals`
does): whitened residual ``f~`` (R, d) and Jacobian ``A~`` (R, d, P) with
``S = A~^T A~`` formed once. A candidate is a mask over the P free entries;
for all candidates at once (batched over the model dimension M):

- its fit is one Gauss-Newton solve from the shared point, the dropped
  entries set to zero: ``(S_kk + Λ_k) db = -(A~_k^T f~_0 + Λ_k (x_0 - x̄))``;
  second-order accurate in the distance between candidate optima (µm-level
  parameter differences: on the FANUC the scores of orders 4-8 agree with
  separate fits to 1e-5 mm);
- its leave-one-pose-out residuals are the PRESS formula on that solve
  (the pose blocks ``H_ii = A~_i S^-1 A~_i^T`` from one triangular solve);
- its validation residuals are the validation rows' linearization at the
  same point, evaluated at the candidate's parameters.

Candidates that score close to each other are then told apart by the same
paired-difference rule as before (:func:`torchcal.identify.order.select_orders`);
the chosen model is fitted exactly afterwards by the caller.
"""

from __future__ import annotations

from typing import Sequence

import torch

from ..core.measurements import Measurements
from ..core.threads import threads_for_work
from .gauge import dependent_columns_masked, gauge_basis, gauge_priority
from .layout import copy_overlap  # noqa: F401  (re-exported: the warm start between candidates)
from .problem import CalibrationProblem, NoiseModel, Prior

CHUNK = 8
"""Candidates per batched PRESS evaluation (memory: CHUNK x P x R d doubles)."""

SEARCH_FTOL = 1e-4
"""Relative cost reduction at which :class:`StructureSearch`'s own fits stop (their points are where the
candidates are linearized; the scores are solves from there, insensitive to the last iterations' creep)."""


def structure_mask(superset: torch.nn.Module, candidate: torch.nn.Module, layout) -> torch.Tensor:
    """(P,) bool over ``layout``'s free entries (a layout of ``superset``): the entries ``candidate`` carries.

    Both models come from one factory with different orders; each parameter of
    the candidate has the superset's shape or a smaller one along trailing
    axes (fewer Chebyshev coefficients), aligned at index 0. Parameters the
    candidate lacks are not carried.
    """
    groups = {g.name: g.mask for g in _groups(candidate)}
    out = []
    for name, p, m in layout.entries:
        cm = groups.get(name)
        full = torch.zeros(p.shape, dtype=torch.bool)
        if cm is not None:
            if cm.ndim != p.ndim or any(a > b for a, b in zip(cm.shape, p.shape)):
                raise ValueError(f"candidate parameter '{name}' {tuple(cm.shape)} is not inside the superset's "
                                 f"{tuple(p.shape)}: build the superset with the largest order of every term")
            full[tuple(slice(0, s) for s in cm.shape)] = cm.cpu()
        out.append(full.to(m.device)[m])
    return torch.cat(out) if out else torch.zeros(0, dtype=torch.bool)


def _groups(model):
    from .layout import parameter_groups

    return parameter_groups(model)


class SharedLinearization:
    """The superset model linearized once at its fitted point; scores sub-models without refitting them.

    model: the superset (fitted: its current parameters are the linearization
    point); data: its identification rows; v: (R, n) the fitted joint errors
    (None: zero); validation: optional rows to score candidates on (the
    Figure 11 criterion) instead of leave-one-pose-out; fixed, gauge: as given
    to :func:`torchcal.fit`, so that the same entries are free; refine: chord
    steps after the one-step solve, each from the candidate's exact residual
    (one forward pass) with the shared Jacobian, for candidates far from the
    shared point (a low order against a large over-fitted one on few poses was
    off by 10-20 % in one step). The searches re-centre on their incumbent
    instead and score only its neighbours, which one step gets to ~0.1 %.

    Example:
        >>> import torch, torchcal
        >>> robot = torchcal.load_robot("fanuc_lrmate200i")
        >>> tools = torch.tensor([[0.033, 0.058, 0.161], [0.057, -0.034, 0.161]], dtype=torch.float64)
        >>> truth = torchcal.TruthRobot.fanuc_paper2(robot, tools, 0)
        >>> q = torchcal.sim.quasi_random_commands(robot.joint_map.limits, 60, 0)
        >>> data = torchcal.simulate(truth, q, [0, 1], torchcal.NoiseModel.from_robot(robot), 0)
        >>> sup = torchcal.RobotModel(robot, tools, orders=3)
        >>> r = torchcal.fit(sup, data)
        >>> lin = SharedLinearization(sup, data, v=r.v)
        >>> keep = lin.masks([torchcal.RobotModel(robot, tools, orders=o) for o in (1, 3)])
        >>> err = lin.loo_errors(keep)               # (2 candidates, 120 rows), m
        >>> tuple(err.shape), bool(err[1].mean() < err[0].mean())
        ((2, 120), True)
    """

    def __init__(self, model, data: Measurements, noise: NoiseModel | None = None, prior: Prior | None = Prior(),
                 v: torch.Tensor | None = None, validation: Measurements | None = None, fixed=(), gauge: bool = True,
                 refine: int = 0, pins: dict | None = None, instrument=None, validation_instrument=None):
        from .fit import resolve_noise

        self.model = model
        noise = resolve_noise(model, noise)
        problem = CalibrationProblem(model, data, noise, prior, fixed, instrument)
        # held-out errors: |raw residual| (m) for point targets, as the order search always judged them; the
        # whitened norm for any other instrument (position and angles on their own noise scales)
        self.raw_scores = problem.instrument.dim == 3 and type(problem.instrument).__name__ == "PointTargets"
        # no gauge fixing of the superset: what a candidate must pin depends on the columns IT carries
        # (an entry redundant beside the superset's extra terms may be free without them); masks() pins per candidate
        self.gauge = bool(gauge)
        self.problem = problem
        self.layout = problem.layout
        x = self.layout.get().to(model.device)
        v = problem.v_zero() if v is None else v.to(x)
        with torch.no_grad():
            # what each structure pins is judged at the zero-error model, the same for every linearization
            # point (cached across them in ``pins``): a candidate then pins exactly what its own cold fit
            # pins (fix_gauge), whereas near-dependent columns flip with the point
            self._pins: dict = {} if pins is None else pins
            if gauge and "basis" not in self._pins:
                A0 = problem.linearize(torch.zeros_like(x), torch.zeros_like(v))[1]
                self._pins["basis"] = gauge_basis(A0.reshape(-1, A0.shape[-1]), gauge_priority(self.layout.roles()))
            f, A, C = problem.linearize(x, v)
        R, d, P = A.shape
        eye = torch.eye(d, dtype=f.dtype, device=f.device)
        # joint errors marginalized per row: cov of the zero-v residual g = f - C v is I + C W_v^-1 C^T = L L^T
        g = f - (C @ v[..., None])[..., 0]
        cov = eye + C @ (C / problem.w_v[:, None, :]).transpose(1, 2)
        L = torch.linalg.cholesky(cov)
        Li = torch.linalg.solve_triangular(L, eye.expand(R, d, d), upper=False)
        self.x, self.A, self.g, self.L, self.Li = x, A, g, L, Li
        self.refine = int(refine)
        self.At = Li @ A  # (R, d, P)
        self.ft = (Li @ g[..., None])[..., 0]  # (R, d)
        Af = self.At.reshape(R * d, P)
        self.S = Af.T @ Af  # shared by every candidate
        self.lam, self.mean = problem.prior_precision, problem.prior_mean
        self.pose = problem.data.pose
        self.validation = None
        if validation is not None:
            vp = CalibrationProblem(model, validation, noise, None, fixed, validation_instrument)
            vp.layout = self.layout  # the same free entries, same order
            self.validation = vp
            if self.refine == 0:  # the validation rows linearized at the same point, consistent with the solve
                fv, Av, _ = vp.linearize(x, vp.v_zero())
                self._val_lin = (vp.instrument.unwhiten(fv), vp.instrument.unwhiten(Av)) if self.raw_scores else (fv, Av)
                self.layout.set(x)
        self._blocks = None

    @property
    def size(self) -> int:
        """P: free entries of the superset (no gauge fixing: each candidate pins its own, see :meth:`masks`)."""
        return self.layout.size

    def masks(self, candidates: Sequence[torch.nn.Module]) -> torch.Tensor:
        """(M, P) bool keep-masks of candidate models (same factory, smaller orders): :func:`structure_mask`,
        less the entries each candidate's own gauge fixing would pin (:func:`~torchcal.identify.gauge.fix_gauge`,
        judged on its own columns of the shared Jacobian)."""
        keep = torch.stack([structure_mask(self.model, c, self.layout) for c in candidates]).to(self.x.device)
        if self.gauge and keep.shape[1]:
            key = [bytes(k.cpu().numpy().tobytes()) for k in keep]
            todo = [i for i, k in enumerate(key) if k not in self._pins]
            if todo:
                dep = dependent_columns_masked(self._pins["basis"], keep[todo])
                for i, d in zip(todo, dep):
                    self._pins[key[i]] = d
            keep = keep & ~torch.stack([self._pins[k] for k in key]).to(keep.device)
        return keep

    # ------------------------------------------------------------------ views
    def _view(self, keep: torch.Tensor) -> "_View":
        """The columns some candidate of ``keep`` (M, P) carries: every solve of the batch happens there."""
        u = keep.any(0)
        if bool(u.all()):
            idx = None
        else:
            idx = u.nonzero()[:, 0]
        return _View(self, idx)

    # ------------------------------------------------------------------ solves
    def solve(self, keep: torch.Tensor) -> torch.Tensor:
        """(M, P) keep-masks -> (M, P) each candidate's parameters (one Gauss-Newton solve from the shared
        point, then ``refine`` chord steps)."""
        view = self._view(keep)
        k = view.cols(keep)
        kf, x0, ft0, Ls = view.systems(k)
        xv, _ = view.refined(kf, x0, ft0, Ls)
        return view.full(xv)

    @torch.no_grad()
    def residuals_at(self, X: torch.Tensor) -> torch.Tensor:
        """(M, P) parameter vectors -> (M, R, d) exact whitened residuals with the joint errors at zero."""
        v = torch.zeros_like(self.problem.data.q)
        try:
            return torch.stack([self.problem.whitened_residual(x, v) for x in X])
        finally:
            self.layout.set(self.x)  # the model keeps the shared point

    # ------------------------------------------------------------------ scores
    @torch.no_grad()
    def validation_errors(self, keep: torch.Tensor) -> torch.Tensor:
        """(M, R_val) |validation residual| (m) of each candidate's solve, joint errors zero (linearized at the
        shared point like the solve; with ``refine`` an exact forward pass at the refined solve)."""
        if self.validation is None:
            raise ValueError("SharedLinearization was built without validation rows")
        vp = self.validation
        v = torch.zeros_like(vp.data.q)
        X = self.solve(keep)
        if self.refine == 0:
            fv, Av = self._val_lin
            return (fv + torch.einsum("rdp,mp->mrd", Av, X - self.x)).norm(dim=-1)
        back = vp.instrument.unwhiten if self.raw_scores else (lambda t: t)
        try:
            return torch.stack([back(vp.whitened_residual(x, v)).norm(dim=-1) for x in X])
        finally:
            self.layout.set(self.x)

    def _pose_index(self):
        """The row -> (pose slot, position in the pose's block) map, built once."""
        if self._blocks is None:
            R = self.At.shape[0]
            ids, slot = torch.unique(self.pose, return_inverse=True)
            N = ids.numel()
            order = torch.argsort(slot, stable=True)
            counts = torch.bincount(slot, minlength=N)
            k = int(counts.max())
            start = torch.cumsum(counts, 0) - counts
            within = torch.arange(R, device=slot.device) - start[slot[order]]
            pos = torch.empty_like(within)
            pos[order] = within
            self._blocks = (N, k, slot, pos)
        return self._blocks

    def loo_errors(self, keep: torch.Tensor, chunk: int = CHUNK) -> torch.Tensor:
        """(M, R) leave-one-pose-out errors (m) of each candidate, joint errors zero (as :func:`loo_residuals`).

        Dropping pose i from candidate c's fit moves its parameters by
        db_i = S_c^-1 A~_i^T (I - H_ii)^-1 f~_i with H_ii = A~_i S_c^-1 A~_i^T
        (Sherman-Morrison-Woodbury); the held-out error of its rows is
        |L_i (f~_i + H_ii (I - H_ii)^-1 f~_i)| = |L_i (I - H_ii)^-1 f~_i|. A pose
        that alone determines some direction (H_ii -> I) gets +inf.
        """
        view = self._view(keep)
        k = view.cols(keep)
        N, kb, _, _ = self._pose_index()
        work = chunk * view.P ** 2 * N * kb * self.At.shape[1]
        with threads_for_work(work):
            return torch.cat([view.loo(k[c0:c0 + chunk]) for c0 in range(0, k.shape[0], chunk)])

    def errors(self, keep: torch.Tensor) -> torch.Tensor:
        """(M, rows) held-out errors (m): on the validation rows if given, else leave-one-pose-out."""
        return self.validation_errors(keep) if self.validation is not None else self.loo_errors(keep)


class _View:
    """A :class:`SharedLinearization` restricted to some of its columns (idx None: all of them)."""

    def __init__(self, lin: SharedLinearization, idx: torch.Tensor | None):
        self.lin, self.idx = lin, idx
        if idx is None:
            self.At, self.S, self.x, self.lam, self.mean = lin.At, lin.S, lin.x, lin.lam, lin.mean
            self.ft = lin.ft
        else:
            self.At = lin.At[..., idx]
            self.S = lin.S[idx][:, idx]
            self.x, self.lam, self.mean = lin.x[idx], lin.lam[idx], lin.mean[idx]
            # no candidate of the batch carries the other columns: they go to zero in all of them
            out = torch.ones(lin.x.numel(), dtype=torch.bool, device=idx.device)
            out[idx] = False
            self.ft = lin.ft - torch.einsum("rdp,p->rd", lin.At[..., out], lin.x[out])
        self.P = self.x.numel()

    def cols(self, keep: torch.Tensor) -> torch.Tensor:
        return keep if self.idx is None else keep[:, self.idx]

    def full(self, xv: torch.Tensor) -> torch.Tensor:
        """(M, P_view) -> (M, P): the columns outside the view, which no candidate carries, at zero."""
        if self.idx is None:
            return xv
        out = xv.new_zeros(xv.shape[0], self.lin.x.numel())
        out[:, self.idx] = xv
        return out

    def refined(self, kf, x0, ft0, Ls):
        """The one-step solve and ``refine`` chord steps -> (x (M, P_view), fitted whitened residual (M, R, d))."""
        db = self.step(kf, x0, ft0, Ls)
        xv = x0 + db
        ft = ft0 + torch.einsum("rdp,mp->mrd", self.At, db)
        for _ in range(self.lin.refine):
            g = self.lin.residuals_at(self.full(xv))  # exact at zero joint errors
            ft_exact = (self.lin.Li @ g[..., None])[..., 0]
            db = self.step(kf, xv, ft_exact, Ls)
            xv = xv + db
            ft = ft_exact + torch.einsum("rdp,mp->mrd", self.At, db)
        return xv, ft

    def systems(self, keep: torch.Tensor):
        """Per candidate: the start x0 (entries it lacks at zero), its whitened residual there, S_c's Cholesky."""
        kf = keep.to(self.x)  # (M, P)
        x0 = self.x * kf
        dx0 = x0 - self.x  # (M, P): the dropped entries go to zero
        ft0 = self.ft + torch.einsum("rdp,mp->mrd", self.At, dx0)  # (M, R, d)
        # dropped entries: a unit diagonal and a zero row/column keep the system positive definite and their step 0
        S = self.S * (kf[:, :, None] * kf[:, None, :]) + torch.diag_embed(torch.where(keep, self.lam, torch.ones_like(self.lam)))
        Ls, info = torch.linalg.cholesky_ex(S)
        if bool((info != 0).any()):  # no prior and a direction the data leave free: a nudge (as loo_residuals)
            S = S + torch.eye(S.shape[-1], dtype=S.dtype, device=S.device) * 1e-12 * S.diagonal(dim1=1, dim2=2).abs().amax(-1)[:, None, None]
            Ls = torch.linalg.cholesky(S)
        return kf, x0, ft0, Ls

    def step(self, kf, x0, ft0, Ls):
        rhs = -(torch.einsum("rdp,mrd->mp", self.At, ft0) + self.lam * (x0 - self.mean)) * kf
        return torch.cholesky_solve(rhs[..., None], Ls)[..., 0]

    def loo(self, keep: torch.Tensor) -> torch.Tensor:
        lin = self.lin
        R, d, P = self.At.shape
        N, k, slot, pos = lin._pose_index()
        kf, x0, ft0, Ls = self.systems(keep)
        _, ftc = self.refined(kf, x0, ft0, Ls)  # (M, R, d) fitted whitened residual
        M = keep.shape[0]
        fb = ftc.new_zeros(M, N, k, d)
        fb[:, slot, pos] = ftc
        fb = fb.reshape(M, N, k * d)
        Ab = self.At.new_zeros(N, k, d, P)
        Ab[slot, pos] = self.At
        # Z = Ls^-1 (A~ masked)^T for every pose at once; H_ii = Z_i^T Z_i
        rhs = (Ab.reshape(N * k * d, P).T[None] * kf[:, :, None])  # (M, P, N k d)
        Z = torch.linalg.solve_triangular(Ls, rhs, upper=False).reshape(M, P, N, k * d).permute(0, 2, 1, 3)
        H = Z.transpose(-1, -2) @ Z  # (M, N, dk, dk)
        eye = torch.eye(k * d, dtype=H.dtype, device=H.device)
        sol, info = torch.linalg.solve_ex(eye - H, fb[..., None])
        sol = sol[..., 0]  # (M, N, dk) = (I - H_ii)^-1 f~_i: the whitened held-out residual
        bad = (info != 0) | ~torch.isfinite(sol).all(-1)
        sol = torch.where(bad[..., None], torch.zeros_like(sol), sol)
        e_t = sol.reshape(M, N, k, d)[:, slot, pos]  # back to rows (M, R, d), whitened by L^-1
        e = (lin.L @ e_t[..., None])[..., 0]
        e = (lin.problem.instrument.unwhiten(e) if lin.raw_scores else e).norm(dim=-1)
        return torch.where(bad[:, slot], torch.full_like(e, float("inf")), e)


class StructureSearch:
    """Scores candidate structures (order tuples) from a :class:`SharedLinearization`, batched.

    make_superset(): the model carrying every candidate's terms; make(key): a
    fresh candidate model for a structure key (a tuple); data, validation,
    noise, prior, fit_options: as for :func:`torchcal.fit`; center: the
    candidate fitted first (exactly, warm-started from ``warm`` if given) and
    linearized at (its unused terms zero). :meth:`recenter` does the same for
    another candidate, so that the candidates near an incumbent are scored from
    a point next to them: the one-step scores are second-order accurate in the
    distance to that point, exact enough for neighbours and only roughly right
    for far ones (a low order against an over-fitted high one). Errors are
    cached per linearization (an ``epoch``).
    """

    def __init__(self, make_superset, make, data: Measurements, validation: Measurements | None, noise, prior,
                 fit_options: dict, center, warm: torch.nn.Module | None = None, validation_instrument=None):
        from .fit import fit

        self._fit = fit
        self.make, self.data, self.validation = make, data, validation
        self.noise, self.prior, self.fit_options = noise, prior, dict(fit_options)
        self.fit_options.pop("callback", None)
        # the search's own fits only place a linearization point (each score is a solve from it): they stop
        # where the last iterations would only creep along near-redundant directions
        if self.fit_options.get("method", "lm") == "lm":
            self.fit_options["ftol"] = max(float(self.fit_options.get("ftol", 0.0)), SEARCH_FTOL)
        self.superset = make_superset()
        self.fits = 0
        self.epoch = -1
        self.center = None
        self.validation_instrument = validation_instrument
        self._pins: dict = {}
        if warm is not None:
            copy_overlap(warm, self.superset)
        self._fit_at(tuple(int(x) for x in center))

    def _fit_at(self, key: tuple) -> None:
        """Fit candidate ``key`` warm-started from the superset's current values (the gauge of a cold fit) and
        re-linearize the superset there."""
        cand = self.make(key)
        r = self._fit(cand, self.data, self.noise, self.prior, warm=self.superset, **self.fit_options)
        self.fits += 1
        copy_overlap(cand, self.superset)
        self.center = key
        self.lin = SharedLinearization(self.superset, self.data, self.noise, self.prior, v=r.v,
                                       validation=self.validation, fixed=self.fit_options.get("fixed", ()),
                                       gauge=self.fit_options.get("gauge", True), pins=self._pins,
                                       instrument=self.fit_options.get("instrument"),
                                       validation_instrument=self.validation_instrument)
        self._cache: dict[tuple, torch.Tensor] = {}
        self.epoch += 1

    def errors(self, keys) -> dict[tuple, torch.Tensor]:
        """{key: (rows,) held-out errors (m)} for every key, the new ones computed in one batch."""
        keys = [tuple(int(x) for x in k) for k in keys]
        new = [k for k in dict.fromkeys(keys) if k not in self._cache]
        if new:
            keep = self.lin.masks([self.make(k) for k in new])
            for k, e in zip(new, self.lin.errors(keep)):
                self._cache[k] = e
        return {k: self._cache[k] for k in keys}

    def recenter(self, key) -> None:
        """Fit candidate ``key`` exactly (warm-started from its solve) and re-linearize the superset there."""
        key = tuple(int(x) for x in key)
        if key == self.center:
            return
        keep = self.lin.masks([self.make(key)])
        self.lin.layout.set(self.lin.solve(keep)[0])  # the superset now holds the candidate's solve
        self._fit_at(key)
