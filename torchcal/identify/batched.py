"""Many models of one machine fitted in one solve: the model batch dimension of identification.

A sweep (Figure 11: orders x data sets), a noise study, or a fleet of units
fits M models that share their structure up to which terms they carry.
:func:`fit_batch` stacks them along a leading model axis: one *superset*
model carries every term; each model is a mask over its free entries (its own
gauge pins included) and, optionally, a subset of the data rows and its own
noise. Every Levenberg-Marquardt iteration linearizes all active models at
once (``torch.func.vmap`` over the model axis of the closed-form Jacobians),
eliminates each row's joint errors by the Schur complement batched over
models, and accepts or rejects each model's step on its own: each model has
its own damping and its own convergence, and a converged model leaves the
active set, so it stops costing work.

The algorithm per model is :func:`torchcal.identify.lm.levenberg_marquardt`'s
(Nielsen's damping on Marquardt's scaling, the same stopping tests; every
iteration makes one attempt per model and linearizes the trial point, so a
rejected step costs an iteration instead of an inner loop).
"""

from __future__ import annotations

import time
from contextlib import nullcontext
from dataclasses import dataclass, field
from typing import Sequence

import torch
from torch.func import functional_call, vmap

from ..core import hugepages
from ..core.exceptions import TorchcalError
from ..core.measurements import Measurements
from ..core.progress import task
from ..core.threads import limit_threads, threads_for_work
from .candidates import structure_mask
from .gauge import dependent_columns_masked, gauge_basis, gauge_priority
from .lm import GEODESIC_H, MU0, acceleration_kept, second_directional
from .problem import CalibrationProblem, NoiseModel, Prior, _prefixed
from .result import FitResult
from .schur import schur_steps
from .workspace import consecutive, take_entries


@dataclass
class BatchedFitResult:
    """Outcome of :func:`fit_batch`: one :class:`FitResult` per model (``results``) and the batch's totals.

    x: (M, P) every model's free values in the superset's layout (entries a
    model lacks are zero); keep: (M, P) which entries each model carries;
    iterations: batched iterations run; time: seconds for the whole batch.
    """

    results: list[FitResult]
    x: torch.Tensor
    keep: torch.Tensor
    iterations: int
    time: float
    names: list[str] = field(default_factory=list)

    @property
    def success(self) -> torch.Tensor:
        return torch.tensor([r.success for r in self.results])

    @property
    def fun(self) -> torch.Tensor:
        return torch.tensor([r.fun for r in self.results], dtype=torch.float64)


class Cancelled(TorchcalError, RuntimeError):
    """A batched solve stopped by its ``cancel`` event (another part of the work failed or was interrupted)."""


class _Predict(torch.nn.Module):
    """instrument.predict_jacobians(model, ...) as a module whose parameters are the model's (functional_call)."""

    def __init__(self, model, instrument):
        super().__init__()
        self.model = model
        self.instrument = instrument

    def forward(self, q, tool, direction, v):
        out = self.instrument.predict_jacobians(self.model, q, tool, direction, v)
        if out is None:
            raise ValueError(f"fit_batch needs closed-form Jacobians: {type(self.instrument).__name__} gives none "
                             f"for {type(self.model).__name__}")
        return out


class BatchedProblem:
    """The implicit-loop MLE of :class:`CalibrationProblem` for M models stacked on a leading axis.

    superset: a model carrying every term of every model (its values are not
    used); models: M models of the same factory (their current values start
    the fit); data: the rows they share; rows: (M, R) bool, the rows each model
    fits (None: all); noise: one :class:`NoiseModel` or M of them (sigma_m and
    joint variances per model); prior, fixed, gauge: as for :func:`torchcal.fit`
    (gauge pinned per model, judged at the zero-error model on its own rows).
    """

    def __init__(self, superset, models: Sequence[torch.nn.Module], data: Measurements, noise, prior: Prior | None = Prior(),
                 rows: torch.Tensor | None = None, fixed=(), gauge: bool = True, instrument=None):
        from .fit import resolve_noise

        M = len(models)
        if M == 0:
            raise ValueError("fit_batch: no models")
        noises = list(noise) if isinstance(noise, (list, tuple)) else [noise] * M
        if len(noises) != M:
            raise ValueError(f"fit_batch: {len(noises)} noise models for {M} models")
        noises = [resolve_noise(models[m], nz) for m, nz in enumerate(noises)]
        self.superset, self.models = superset, list(models)
        self.problem = CalibrationProblem(superset, data, noises[0], prior, fixed, instrument)
        p = self.problem
        self.layout, self.instrument, self.data = p.layout, p.instrument, p.data
        dev = superset.device
        R, n = self.data.q.shape
        self.M, self.R, self.n, self.d = M, R, n, p.dim
        rows = torch.ones(M, R, dtype=torch.bool, device=dev) if rows is None else torch.as_tensor(rows).to(dev)
        if rows.shape != (M, R):
            raise ValueError(f"fit_batch: rows must be an ({M}, {R}) bool mask, got {tuple(rows.shape)}")
        self._set_weights(noises, [self.data.direction] * M, rows, "fit_batch: every model")
        keep = torch.stack([structure_mask(superset, m, self.layout) for m in models]).to(dev)
        if gauge:
            keep = keep & ~self._pins(keep)
        self.keep = keep
        self._f = self._kf = None

    def _set_weights(self, noises, directions, rows: torch.Tensor, who: str) -> None:
        """Per-model whitening scale (the shared instrument whitens with the first model's sigma), joint-error
        weights (M, R, n) from each model's noise and rows' directions, the row mask, the prior."""
        p, dev, dt = self.problem, rows.device, torch.float64
        self.rows = rows
        sig0 = noises[0].sigma_m
        self.scale = torch.tensor([sig0 / nz.sigma_m for nz in noises], dtype=dt, device=dev)[:, None] * rows.to(dt)
        # one evaluation per distinct noise model over its models' rows (a fleet shares one: a GPU waits on
        # every copy of a noise model's variances to it)
        w_v = torch.empty(len(noises), *directions[0].shape, dtype=dt, device=dev)
        for nz in {id(nz): nz for nz in noises}.values():
            idx = [m for m, other in enumerate(noises) if other is nz]
            value = 1.0 / nz.joint_variance(torch.stack([directions[m] for m in idx]).to(dev))
            w_v[slice(None) if len(idx) == len(noises) else idx] = value
        if not bool(torch.isfinite(w_v).all()):
            raise ValueError(f"{who} needs positive joint variances (noise.joint_var_fwd / _bwd)")
        self.w_v = w_v
        self.w_v_cost = w_v * rows[..., None].to(dt)
        self.lam = p.prior_precision.to(dev)
        self.mean = p.prior_mean.to(dev)

    def _pins(self, keep: torch.Tensor) -> torch.Tensor:
        """(M, P) entries each model's own cold fit would pin (fix_gauge on its rows, at the zero-error model)."""
        x0 = torch.zeros(self.layout.size, dtype=torch.float64, device=self.keep_device)
        _, A0, _ = self.problem.linearize(x0, torch.zeros_like(self.data.q))
        order = gauge_priority(self.layout.roles())
        pins = torch.zeros_like(keep)
        for pattern in torch.unique(self.rows, dim=0):
            members = (self.rows == pattern).all(1)
            A = A0[pattern].reshape(-1, A0.shape[-1])
            pins[members] = dependent_columns_masked(gauge_basis(A, order), keep[members])
        return pins

    @property
    def keep_device(self):
        return self.rows.device

    def _stacked(self) -> list | None:
        """Per layout entry, the M models' parameters of that name, where every model has it with the superset's
        shape on its device (a fleet, a noise study); None otherwise (models of several structures)."""
        out = []
        owns = [dict(m.named_parameters()) for m in self.models]
        for name, p, _ in self.layout.entries:
            ps = [own.get(name) for own in owns]
            if any(q is None or q.shape != p.shape or q.device != p.device for q in ps):
                return None
            out.append(ps)
        return out

    def start(self) -> torch.Tensor:
        """(M, P) each model's current values in the superset's layout (entries it lacks: zero). Reads the
        models only (the superset may be one of them)."""
        stacks = self._stacked()
        if stacks is not None:  # one gather per entry for all models (a GPU waits on every boolean mask)
            cols = []
            for ps, idx in zip(stacks, self.layout._flat_index()):
                flat = torch.stack([q.detach() for q in ps]).flatten(1)
                cols.append(flat if idx is None else flat.index_select(1, idx.to(flat.device)))
            return torch.cat(cols, 1).to(self.lam) * self.keep.to(self.lam)
        out = []
        for m in self.models:
            own = dict(m.named_parameters())
            cols = []
            for name, p, msk in self.layout.entries:
                full = torch.zeros(p.shape, dtype=p.dtype, device=p.device)
                q = own.get(name)
                if q is not None and q.ndim == p.ndim:
                    full[tuple(slice(0, min(a, b)) for a, b in zip(p.shape, q.shape))] = \
                        q.detach()[tuple(slice(0, min(a, b)) for a, b in zip(p.shape, q.shape))]
                cols.append(full[msk])
            out.append(torch.cat(cols))
        return torch.stack(out).to(self.lam) * self.keep.to(self.lam)

    @torch.no_grad()
    def write(self, X: torch.Tensor) -> None:
        """Write row m of X (M, P) into model m: its free entries in the superset's layout (entries it lacks
        are dropped; fixed groups keep their values). Reads nothing from the superset, which may be a model."""
        Xc = X.detach().clone()
        stacks = self._stacked()
        if stacks is not None:  # every model's entry from one scatter, then one copy per model and entry
            i = 0
            for ps, idx in zip(stacks, self.layout._flat_index()):
                flat = torch.stack([q.detach() for q in ps]).flatten(1)
                k = flat.shape[1] if idx is None else idx.numel()
                vals = Xc[:, i:i + k].to(flat)
                flat = vals if idx is None else flat.index_copy_(1, idx.to(flat.device), vals)
                for q, row in zip(ps, flat):
                    q.copy_(row.view_as(q))
                i += k
            return
        for m, model in enumerate(self.models):
            own = dict(model.named_parameters())
            i = 0
            for name, p, msk in self.layout.entries:
                k = int(msk.sum())
                q = own.get(name)
                if q is not None and q.ndim == p.ndim:
                    sl = tuple(slice(0, min(a, b)) for a, b in zip(p.shape, q.shape))
                    full = torch.zeros(p.shape, dtype=q.dtype, device=q.device)
                    full[sl] = q.detach()[sl]
                    full[msk] = Xc[m, i:i + k].to(q)
                    q[sl] = full[sl]
                i += k

    # ------------------------------------------------------------------ linearization
    def _params(self, X: torch.Tensor) -> dict:
        """{name: (m, *shape)} the superset's parameters with the free entries of every model from X (m, P)."""
        out, i = {}, 0
        for (name, p, msk), idx in zip(self.layout.entries, self.layout._flat_index()):
            k = int(msk.sum())
            flat = p.detach().flatten().expand(X.shape[0], -1).clone()
            cols = torch.arange(flat.shape[1], device=flat.device) if idx is None else idx.to(flat.device)
            flat[:, cols] = X[:, i:i + k].to(flat)
            out[name] = flat.reshape(X.shape[0], *p.shape)
            i += k
        return out

    @torch.no_grad()
    def linearize(self, X: torch.Tensor, V: torch.Tensor, which: torch.Tensor):
        """Whitened residual f (m, R, d), parameter Jacobian A (m, R, d, P) and joint-error Jacobian C
        (m, R, d, n) of the models ``which`` (m,) at X (m, P), V (m, R, n); rows a model does not fit are zero."""
        wrapper = _Predict(self.superset, self.instrument)
        data, inst, layout, R = self.data, self.instrument, self.layout, self.R
        direction = data.direction if data.has_direction else None

        def one(params, v):
            pred, J = functional_call(wrapper, _prefixed(params), (data.q, data.tool, direction, v))
            f = inst.whiten(inst.residual(pred, inst.observed))
            A = inst.whiten(layout.flatten_jacobian(J, R))
            C = inst.whiten(J["v"])
            return f, A, C

        f, A, C = vmap(one)(self._params(X), V)
        s = self.scale[which][:, :, None]
        kf = self.keep[which].to(A)
        return f * s, A * s[..., None] * kf[:, None, None, :], C * s[..., None]

    def cost_from(self, f, X, V, which) -> torch.Tensor:
        """(m,) V of each model from its whitened residual."""
        dx = X - self.mean
        return (f * f).sum((1, 2)) + (self.w_v_cost[which] * V * V).sum((1, 2)) + (self.lam * dx * dx * self.keep[which]).sum(1)

    def step(self, lin, V, dX, mu, which, again: bool = False):
        """Damped Gauss-Newton steps of the models ``which`` from their linearizations ``lin`` (f, A, C) at
        joint errors V, prior offsets dX = X - mean, dampings mu. -> db (m, P), dv (m, R, n), predicted
        linearized residual (m, R, d) (, with ``again``, the system to solve again: :func:`schur_steps`)."""
        f, A, C = lin
        return schur_steps(f, A, C, self.w_v[which], V, self.lam, dX, mu, self.keep[which], again=again)


def fit_batch(superset, models: Sequence[torch.nn.Module], data: Measurements, noise: NoiseModel | Sequence | None = None,
              prior: Prior | None = Prior(), rows: torch.Tensor | None = None, fixed=(), gauge: bool = True,
              max_iter: int = 100, ftol: float = 1e-8, xtol: float = 1e-10, mu0: float = MU0, chunk: int = 8) -> BatchedFitResult:
    """Fit M models of one machine in one batched Levenberg-Marquardt solve; each model is updated in place.

    superset: a model of the same factory carrying every term any model carries
    (e.g. the largest orders); models: the M models, starting from their
    current values (warm-start them with
    :func:`~torchcal.identify.layout.copy_overlap`); data: the rows they share;
    rows: (M, R) bool, the rows each model fits (data subsets; None: all);
    noise: one :class:`NoiseModel` (None: the robot's) or M of them; prior,
    fixed, gauge, max_iter, ftol, xtol, mu0: as for :func:`torchcal.fit` with
    ``method='lm'`` (gauge pinned per model as its own fit would). chunk:
    models linearized together (memory: chunk x R x d x P doubles).
    -> :class:`BatchedFitResult` with one :class:`FitResult` per model.

    Example:
        >>> import torch, torchcal
        >>> robot = torchcal.load_robot("fanuc_lrmate200i")
        >>> tools = torch.tensor([[0.033, 0.058, 0.161], [0.057, -0.034, 0.161]], dtype=torch.float64)
        >>> truth = torchcal.TruthRobot.fanuc_paper2(robot, tools, 0)
        >>> q = torchcal.sim.quasi_random_commands(robot.joint_map.limits, 40, 0)
        >>> data = torchcal.simulate(truth, q, [0, 1], torchcal.NoiseModel.from_robot(robot), 0)
        >>> models = [torchcal.RobotModel(robot, tools, orders=o) for o in (1, 2, 3)]
        >>> out = fit_batch(torchcal.RobotModel(robot, tools, orders=3), models, data)
        >>> [bool(r.success) for r in out.results], bool(out.results[2].fun < out.results[0].fun)
        ([True, True, True], True)
    """
    t0 = time.perf_counter()
    bp = BatchedProblem(superset, models, data, noise, prior, rows, fixed, gauge)
    return solve_batched(bp, max_iter, ftol, xtol, mu0, chunk, t0=t0)


def solve_batched(bp, max_iter: int = 100, ftol: float = 1e-8, xtol: float = 1e-10, mu0: float = MU0,
                  chunk: int = 8, label: str = "fitting models together", t0: float | None = None,
                  threads: int | None = None, bar=None, cancel=None, accelerate: bool | None = None) -> BatchedFitResult:
    """Levenberg-Marquardt on every model of ``bp`` at once, each with its own damping and convergence; writes
    the solutions into ``bp.models``. -> :class:`BatchedFitResult`.

    bp: a :class:`BatchedProblem` (models sharing the data) or anything with its surface
    (``M, R, n, d, layout, models, keep, w_v, lam, mean``, ``start()``, ``write(X)``,
    ``linearize(X, V, which)``, ``cost_from(f, X, V, which)``; optionally ``step(lin, V, dX, mu, which, again)``,
    ``residual(X, V, which)`` (a trial point's residual alone) and ``accelerate``), e.g. a fleet's units each with
    their own data (:class:`torchcal.identify.fleet.FleetProblem`).
    threads: the solve's CPU threads (None: by the work's size, :func:`~torchcal.core.threads.threads_for`);
    bar: a progress task to advance by the models finished (None: the solve's own, named ``label``).
    cancel: a :class:`threading.Event`; once set, the solve raises :class:`Cancelled` at its next iteration.
    accelerate: geodesic acceleration (Transtrum & Sethna 2012; :func:`~torchcal.identify.lm.second_directional`):
    each step delta becomes delta + a / 2, a from the second directional derivative of the residual along delta
    (one extra residual at x + 0.1 delta, the step's own factor solved again), where 2 |a| <= 0.75 |delta|.
    Where the residual curves along the steps, a unit reaches the stopping test in fewer iterations (100 FANUCs:
    383 unit iterations instead of 564). None: ``bp.accelerate`` (False where the problem says nothing).
    """
    t0 = time.perf_counter() if t0 is None else t0
    models = bp.models
    M, R, n, P = bp.M, bp.R, bp.n, bp.layout.size
    X = bp.start()
    V = torch.zeros(M, R, n, dtype=X.dtype, device=X.device)
    work = chunk * R * bp.d * P * P
    mu = torch.full((M,), float(mu0), dtype=X.dtype, device=X.device)
    nu = torch.full_like(mu, 2.0)
    nit = torch.zeros(M, dtype=torch.long)
    nfev = torch.ones(M, dtype=torch.long)
    success = torch.zeros(M, dtype=torch.bool)
    message = ["maximum number of iterations reached"] * M
    history: list[list[float]] = [[] for _ in range(M)]
    idx_all = torch.arange(M, device=X.device)

    # a problem with a workspace (the fleet's) lends the trial linearizations and the steps' gathered inputs
    # from it: they live only within an iteration, and fresh 10-100 MB blocks cost their page faults every time
    ws = getattr(bp, "workspace", None)

    def lin_chunks(which, Xw, Vw, reuse=False):
        """[(start, stop, linearization)] of the models ``which`` in chunks (positions in ``which``); reuse: the
        workspace's slot per chunk (consumed before the next call)."""
        opt = (lambda c: {"slot": c // chunk}) if reuse and ws is not None else (lambda c: {})
        return [(c, min(c + chunk, which.numel()),
                 bp.linearize(Xw[c:c + chunk], Vw[c:c + chunk], which[c:c + chunk], **opt(c)))
                for c in range(0, which.numel(), chunk)]

    # which models are active, accepted, converged: decided on the host from one transfer per decision, and
    # every index into the models' tensors kept on the host too (a GPU waits on each value it hands back)
    def on(ic: torch.Tensor) -> torch.Tensor:
        """A host index tensor on the models' device."""
        return ic.to(X.device, non_blocking=True)

    accelerate = bool(getattr(bp, "accelerate", False)) if accelerate is None else bool(accelerate)

    def step(lin, Vw, dX, muw, which):
        if hasattr(bp, "step"):
            return bp.step(lin, Vw, dX, muw, which, again=accelerate)
        f, A, C = lin
        return schur_steps(f, A, C, bp.w_v[which], Vw, bp.lam, dX, muw, bp.keep[which], again=accelerate)

    def flat_test(predicted, which):
        """The Gauss-Newton model at the current point sees less to gain than the stopping test accepts
        (judged only on a step right after an accepted one, as the single-model solver does: after a
        rejection the damping is raised and a small prediction says nothing); such a model stops here,
        without paying a linearization to confirm it."""
        return fresh[which] & (~first[which]) & (predicted >= 0) & (predicted <= 0.1 * ftol * cost[which])

    def step_chunk(c, wc, w):
        """(db, dv, linearized residual, predicted cost reduction (judged on db alone), the acceleration to add
        to db) of the active models c:c+chunk."""
        wcc, ww = wc[c:c + chunk], w[c:c + chunk]
        lin_c = [take_entries(t, wcc, 0, ws, f"step{k}") for k, t in enumerate(lin)]
        out = step(lin_c, V[ww], X[ww] - bp.mean, mu[ww], ww)
        db, dv, lres = out[:3]
        predicted = cost[ww] - bp.cost_from(lres, X[ww] + db, V[ww] + dv, ww)
        if not accelerate:
            return db, dv, lres, predicted, None
        # before the next chunk's step: the system may share the workspace's buffers
        resolve = out[3]
        go = ~flat_test(predicted, ww)  # a model that stops here takes no trial point
        goc = on(go.cpu().nonzero()[:, 0])
        r = torch.zeros_like(lres)
        if goc.numel():
            Xh, Vh = X[ww[goc]] + GEODESIC_H * db[goc], V[ww[goc]] + GEODESIC_H * dv[goc]
            slot = {"slot": "h"} if ws is not None else {}
            f_h = bp.residual(Xh, Vh, ww[goc], **slot) if hasattr(bp, "residual") else \
                bp.linearize(Xh, Vh, ww[goc], **slot)[0]
            r[goc] = second_directional(lin_c[0][goc], f_h, lres[goc])
        a = resolve(r)
        kept = go & acceleration_kept(a, db, resolve.scale)
        return db, dv, lres, predicted, torch.where(kept[:, None], 0.5 * a, torch.zeros_like(a))

    with (limit_threads(threads) if threads else threads_for_work(work)), \
            (nullcontext(bar) if bar is not None else task(label, total=M)) as bar:
        # f first; the rest is whatever bp's step reads (A, C or factors)
        # the current linearizations, walked by every iteration: on huge pages where the system allows
        lin = [torch.cat(t, out=hugepages.empty((sum(p.shape[0] for p in t), *t[0].shape[1:]), t[0]))
               for t in zip(*(out for _, _, out in lin_chunks(idx_all, X, V)))]
        cost = bp.cost_from(lin[0], X, V, idx_all)
        for m, c in enumerate(cost.tolist()):  # one transfer, not one host sync per model (a GPU waits on each)
            history[m].append(c)
        active = torch.ones(M, dtype=torch.bool)  # on the host
        first = torch.ones(M, dtype=torch.bool, device=X.device)
        fresh = torch.ones(M, dtype=torch.bool, device=X.device)  # the last step was accepted
        it = 0
        while bool(active.any()) and it < max_iter:
            if cancel is not None and cancel.is_set():
                raise Cancelled(f"{label}: cancelled after {it} iterations")
            it += 1
            wc = active.nonzero()[:, 0]
            w = on(wc)
            # steps of the active models, in chunks (memory); a chunk's linearizations are views where its models
            # are consecutive, else copies into the workspace
            steps = [step_chunk(c, wc, w) for c in range(0, w.numel(), chunk)]
            db, dv, predicted = (torch.cat([s[k] for s in steps]) for k in (0, 1, 3))
            Xn, Vn = X[w] + db, V[w] + dv
            flat = flat_test(predicted, w)
            if accelerate:
                Xn = Xn + torch.cat([s[4] for s in steps])
            flat_c = flat.cpu()
            needc = (~flat_c).nonzero()[:, 0]
            need, wlc = on(needc), wc[needc]
            wl = on(wlc)
            new_cost = cost[w].clone()
            lin_n = lin_chunks(wl, Xn[need], Vn[need], reuse=True) if needc.numel() else []
            nfev[wlc] += 1
            for a, b, out in lin_n:
                new_cost[need[a:b]] = bp.cost_from(out[0], Xn[need[a:b]], Vn[need[a:b]], wl[a:b])
            actual = cost[w] - new_cost
            ok = (actual > 0) & (predicted > 0) & ~flat
            rho = actual / predicted.clamp(min=1e-300)
            mu[w] = torch.where(ok, mu[w] * torch.clamp(1.0 - (2.0 * rho - 1.0) ** 3, min=1.0 / 3.0), mu[w] * nu[w])
            nu[w] = torch.where(ok, torch.full_like(nu[w], 2.0), nu[w] * 2.0)
            stalled = ~ok & (predicted <= 1e-14 * cost[w].clamp(min=1.0))
            step_small = (db.abs() <= xtol * (X[w].abs() + xtol)).all(1)
            conv_rel = ok & (actual <= ftol * new_cost) & (predicted <= ftol * new_cost * 10)
            done = flat | stalled | conv_rel | (ok & step_small)
            fresh[w] = ok
            first[w] = False
            # the per-model bookkeeping from one transfer
            pack = torch.cat([torch.stack([ok, done, stalled, conv_rel]).to(new_cost), new_cost[None]]).cpu()
            ok_c, done_c, stalled_c, rel_c = pack[:4].bool()
            costs = pack[4].tolist()
            # accept: the trial point and its linearization become the current ones
            okp = ok_c.nonzero()[:, 0]
            if okp.numel():
                okw, okp_d = on(wc[okp]), on(okp)
                X.index_copy_(0, okw, Xn.index_select(0, okp_d))
                V.index_copy_(0, okw, Vn.index_select(0, okp_d))
                cost.index_copy_(0, okw, new_cost.index_select(0, okp_d))
            okl = ok_c[needc]
            for a, b, out in lin_n:
                sel = okl[a:b]
                if bool(sel.all()):
                    dst = consecutive(wlc[a:b])
                    for t, tn in zip(lin, out):
                        t[dst].copy_(tn) if dst is not None else t.index_copy_(0, on(wlc[a:b]), tn)
                elif bool(sel.any()):
                    src, dst = on(sel.nonzero()[:, 0]), on(wlc[a:b][sel])
                    for t, tn in zip(lin, out):
                        t.index_copy_(0, dst, tn.index_select(0, src))
            nit[wc] += 1
            for j, m in enumerate(wc.tolist()):
                if ok_c[j]:
                    history[m].append(costs[j])
                if done_c[j]:
                    success[m] = True
                    message[m] = ("converged: the predicted cost reduction is below ftol" if flat_c[j] else
                                  "converged: no step lowers the cost further" if stalled_c[j] else
                                  "converged: relative cost reduction below ftol" if rel_c[j] else
                                  "converged: parameter step below xtol")
            active[wc] = ~done_c
            bar.advance(int(done_c.sum()), note=f"iteration {it}, {int(active.sum())} model{'' if int(active.sum()) == 1 else 's'} active")
    elapsed = time.perf_counter() - t0
    names = bp.layout.names()
    results = []
    bp.write(X)
    keep_c = bp.keep.cpu()
    xs = torch.split(X[bp.keep].detach().clone(), keep_c.sum(1).tolist())  # one transfer of the masks' counts
    V = V.detach()
    costs = cost.tolist()
    for m, model in enumerate(models):
        kn = [nm for nm, k in zip(names, keep_c[m].tolist()) if k]
        results.append(FitResult(x=xs[m], v=V[m], success=bool(success[m]), message=message[m], nit=int(nit[m]),
                                 nfev=int(nfev[m]), fun=costs[m], grad_norm=float("nan"), time=elapsed / M,
                                 method="lm-batched", history=history[m], names=kn))
    return BatchedFitResult(results=results, x=X.detach().clone(), keep=bp.keep.clone(), iterations=it, time=elapsed,
                            names=names)
