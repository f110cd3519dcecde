"""A fleet: many units of one robot type, each with its own measurements, fitted in one batched solve.

A plant calibrates every unit of a type with the same measurement program;
each fit is small and there are many. :func:`fit_fleet` stacks the units along
the model axis of :func:`~torchcal.identify.batched.solve_batched` (the model
batch dimension): every unit has its own data rows (padded to the longest
unit, the padding masked out), its own noise, its own damping and its own
convergence, and a converged unit stops costing work. On the CPU the units
are split into streams, one per usable CPU, each solved alone on one thread
beside the others (:func:`fit_fleet`). Each unit's result is its own
maximum-likelihood fit (Paper II (26)); nothing is shared between
units but the model's structure and the gauge (the redundant constants of
Paper II (18), which no data set can determine, judged on the pooled rows
of the first units). For a RobotModel the Jacobian is never formed: its
Khatri-Rao factors (twist Jacobian columns times Chebyshev basis values,
:mod:`.structured`, compiled per row by :mod:`.fleet_kernel`) give the
normal matrix as per-pose Gram matrices contracted with the basis, ~10x
fewer flops than the dense product and a tenth of the memory traffic.

:func:`~.fleet_prior.fleet_prior` (:mod:`.fleet_prior`) turns the fitted fleet into a Gaussian prior (mean
and spread of every parameter over the units) for a new unit measured with few poses;
:func:`~.fleet_outliers.parameter_outliers` (:mod:`.fleet_outliers`) flags units whose parameters lie far from
the fleet's (a damaged gearbox, a bad measurement); :mod:`.fleet_change` compares a unit with its earlier
calibration (a crash, a gearbox swap).
"""

from __future__ import annotations

import copy
import time
from contextlib import nullcontext
from dataclasses import dataclass
from typing import Callable, Sequence

import torch
from torch.func import functional_call, vmap

from ..core.measurements import Measurements
from ..core.replicate import replicate
from ..core.threads import limit_threads
from .batched import BatchedFitResult, BatchedProblem, _Predict, solve_batched
from .gauge import dependent_columns_masked, gauge_basis, gauge_priority
from .lm import MU0
from .fleet_prior import fleet_prior  # noqa: F401  (re-exported: the fleet's API in one place)
from .fleet_outliers import (OUTLIER_MIN_RATIO, FeatureScores, Outlier, feature_scores, joint_features,
                             parameter_outliers)  # the fleet's API too (__all__)
from .problem import CalibrationProblem, Prior, _prefixed
from .schur import schur_steps
from . import fleet_kernel
from .fleet_kernel import factored_linearization_fused
from ..models.jacobian import chebyshev_design
from .streams import STREAM_MIN_UNITS, fleet_streams, solve_streams
from .structured import (RobotStructure, dense_jacobian, factored_linearization, factored_residual, pair_basis,
                         pose_groups, regrouped, slots_of, structured_steps)
from .workspace import Workspace, take_entries

UNIT_PAIRS_BYTES = 2 << 30  # the most memory each unit's own pair products may hold between steps


def stack_units(units: Sequence[Measurements]) -> dict:
    """Pad the units' rows to the longest and stack them on a leading unit axis.

    -> dict with q (M, R, n), tool (M, R) long, direction (M, R, n), xyz (M, R, 3),
    rows (M, R) bool (the real rows); a padding row repeats its unit's first
    row (finite predictions), masked out of every cost and Jacobian.
    """
    if not units:
        raise ValueError("fleet: no units")
    n = units[0].q.shape[1]
    for k, u in enumerate(units):
        if u.q.shape[1] != n:
            raise ValueError(f"fleet: unit {k} ({u.source or 'data'}) has {u.q.shape[1]} joints, unit 0 has {n}")
        if len(u) == 0:
            raise ValueError(f"fleet: unit {k} ({u.source or 'data'}) has no rows")
    if len({bool(u.has_direction) for u in units}) > 1:
        raise ValueError("fleet: some units have approach directions (dir columns) and some do not")
    R = max(len(u) for u in units)

    def pad(t: torch.Tensor) -> torch.Tensor:
        extra = R - t.shape[0]
        return t if extra == 0 else torch.cat([t, t[:1].expand(extra, *t.shape[1:])])

    xyz = torch.stack([pad(u.xyz) for u in units])
    if bool(torch.isnan(xyz).any()):  # one test for the fleet (a GPU waits on each)
        k, r = (int(i) for i in torch.isnan(xyz).any(2).nonzero()[0])
        u = units[k]
        raise ValueError(f"fleet: unit {k} ({u.source or 'data'}), data row {int(u.rows[r])}: no measured x, y, z")
    return {
        "q": torch.stack([pad(u.q) for u in units]),
        "tool": torch.stack([pad(u.tool) for u in units]),
        "direction": torch.stack([pad(u.direction) for u in units]),
        "xyz": xyz,
        "rows": torch.stack([torch.arange(R, device=u.q.device) < len(u) for u in units]),
        "has_direction": bool(units[0].has_direction),
    }


class FleetProblem(BatchedProblem):
    """The implicit-loop MLE of M units, each its own model and its own data, stacked on a leading axis.

    make: () -> a fresh model of the type (called once: the superset, and every
    unit's model a copy of it); units: M :class:`Measurements` (tracker points,
    SI); noise: one :class:`NoiseModel` or M of them; prior, fixed, gauge: as
    for :func:`torchcal.fit`. gauge_units: how many units' rows are pooled to
    judge the gauge (the structural redundancy is the same for every unit; None: the first units whose
    rows hold 4x as many residuals as there are parameters, one FANUC unit of 250 x 3 poses).
    models: the units' models (None: copies of the superset); each starts from its own current values (a fresh
    model: zero error; a model loaded with a fleet mean starts there). structured: the factored Jacobian where the model has one (else
    dense A by ``vmap``); dense_normal: with the factored Jacobian, the normal matrix from the dense A it
    expands to (one large product, what a GPU is fast at) instead of per-pose Gram blocks.
    On the CPU each unit's rows are held pose by pose (``units``, ``stack`` and everything per row:
    :func:`pose_groups`); ``row_order[m]`` gives, for each of them, its row in the unit's data (:func:`fit_fleet`
    maps the joint errors of its results back). Elsewhere the rows keep the data's order (row_order None).
    """

    def __init__(self, make: Callable[[], torch.nn.Module], units: Sequence[Measurements], noise=None,
                 prior: Prior | None = Prior(), fixed=(), gauge: bool = True, gauge_units: int | None = None,
                 models: Sequence[torch.nn.Module] | None = None, structured: bool = True, dense_normal: bool = False):
        from .fit import resolve_noise

        M = len(units)
        if M == 0:
            raise ValueError("fit_fleet: no units")
        superset = make()
        # every unit's model a copy of one fresh model of the type: what make() would give, without building
        # each again (on a GPU, make() copies every tensor from the host, and the host waits on each)
        models = [replicate(superset) for _ in range(M)] if models is None else list(models)
        if len(models) != M:
            raise ValueError(f"fit_fleet: {len(models)} models for {M} units")
        dev = superset.device
        # each unit's rows pose by pose, as the factored kernels walk them (structured.slots_of): in the data's
        # order (tool-major) a pose's rows lie far apart, and the kernels' reads jumped by a row's 1.4 kB of
        # factors at every row (the final per-row pass ran 3x slower); row_order maps back (FitResult.v). A GPU's
        # dense form reads no pose's rows together: there the grouping (a host copy of every unit's commands)
        # and the units' reordering (gathers and host syncs per unit) are skipped (100 FANUCs on an H200: the
        # GPU solve took 0.36 s with them, 0.21 s without, on two hosts, not side by side)
        def grouped(us):
            return pose_groups([u.q for u in us], [u.direction if u.has_direction else None for u in us])

        groups, self.row_order = None, None
        if dev.type == "cpu":
            groups = grouped(units)
            self.row_order = [order for _, order, _ in groups]
            units = [u.subset(o).to(dev) for u, o in zip(units, self.row_order)]
        else:
            units = [u.to(dev) for u in units]
        noises = list(noise) if isinstance(noise, (list, tuple)) else [noise] * M
        if len(noises) != M:
            raise ValueError(f"fit_fleet: {len(noises)} noise models for {M} units")
        resolved = {id(nz): resolve_noise(superset, nz) for nz in noises}  # a shared noise model stays shared
        noises = [resolved[id(nz)] for nz in noises]
        self.superset, self.models, self.units = superset, models, units
        self.problem = CalibrationProblem(superset, units[0], noises[0], prior, fixed)
        p = self.problem
        weight = getattr(p.instrument, "weight", None)
        if getattr(weight, "sigma", None) is None:
            raise ValueError("fit_fleet: every unit needs an isotropic tracker sigma (noise.sigma_m); per-row "
                             "covariances are not stacked")
        self.layout, self.instrument, self.data = p.layout, p.instrument, p.data
        st = stack_units(units)
        self.stack = st
        M, R, n = st["q"].shape
        self.M, self.R, self.n, self.d = M, R, n, p.dim
        self._set_weights(noises, list(st["direction"]), st["rows"], "fit_fleet: every unit")
        keep = torch.ones(M, self.layout.size, dtype=torch.bool, device=dev)
        if gauge:
            keep = keep & ~self._pins(keep, noises[0], prior, fixed, gauge_units)
        self.keep = keep
        # geodesic acceleration (solve_batched): measured on the CPU only, so off elsewhere until it is
        self.accelerate = dev.type == "cpu"
        # the factored Jacobian (torchcal.identify.structured) where the model has one, else dense A
        self.structure = None
        self.dense_normal = False
        if structured and RobotStructure.supports(superset, p.instrument, self.layout):
            self.structure = RobotStructure(superset, self.layout)
            self.dense_normal = bool(dense_normal)
            self.workspace = Workspace()  # the solver's large temporaries, reused from one iteration to the next
            if not self.dense_normal:  # the per-pose Gram blocks' poses and basis values
                if groups is None:  # (off the CPU, in the data's order)
                    groups = grouped(units)
                self.slots = slots_of([tuple(t.to(dev) for t in g)
                                       for g in (groups if self.row_order is None else regrouped(groups))], R)
                self.phi_p, self.pp = self._pose_basis()
                self.unit_pp = None  # each unit's own pair products, formed at the first step (_pair_products)
            self.one_program = self._one_program()

    def _one_program(self) -> bool:
        """Whether every unit ran the same program: the same commands, tools, directions, rows, weights and kept
        entries. At a common start (a fresh fleet: every unit at zero error) such units share one linearization
        but for their residuals, so one normal matrix serves their first step (:meth:`step`)."""
        st = self.stack

        def same(t):
            return bool((t == t[:1]).all())

        slots = getattr(self, "slots", st["rows"])
        return all(same(t) for t in (st["q"], st["tool"], st["direction"], st["rows"], self.scale, self.w_v,
                                     self.keep, slots))

    def subset(self, idx: Sequence[int]) -> "FleetProblem":
        """The problem of the units ``idx`` alone: the same structure, gauge, padding and pose basis (so each unit's
        arithmetic is the one it has in the whole fleet), its own models and workspace. For a solve of its own
        beside the others' (:func:`fit_fleet`'s streams)."""
        sub = copy.copy(self)
        ix = torch.as_tensor(list(idx), dtype=torch.long, device=self.keep.device)
        sub.models, sub.units = [self.models[i] for i in idx], [self.units[i] for i in idx]
        sub.row_order = None if self.row_order is None else [self.row_order[i] for i in idx]
        sub.stack = {k: (v[ix] if torch.is_tensor(v) else v) for k, v in self.stack.items()}
        sub.unit_pp = None  # formed for its own units at its first step
        for name in ("rows", "scale", "w_v", "w_v_cost", "keep", "slots", "phi_p"):
            if getattr(self, name, None) is not None:
                setattr(sub, name, getattr(self, name)[ix])
        sub.M = len(idx)
        if hasattr(self, "workspace"):
            sub.workspace = Workspace()
        return sub

    def in_data_order(self, results) -> None:
        """Put the joint errors ``v`` of the units' :class:`FitResult` s (held pose by pose) back in each unit's
        data order, in place (padding rows stay last)."""
        for r, order in zip(results, self.row_order or []):
            v = r.v.clone()
            v[order.to(v.device)] = r.v[:order.numel()]
            r.v = v

    def _common(self, X: torch.Tensor, V: torch.Tensor) -> bool:
        """Whether units of one program stand at one point (X (m, P), V (m, R, n)): then their linearizations
        and normal matrices are one unit's, their residuals apart."""
        return self.one_program and X.shape[0] > 1 and bool((X == X[:1]).all()) and bool((V == V[:1]).all())

    def _pins(self, keep, noise, prior, fixed, gauge_units) -> torch.Tensor:
        """(M, P) the gauge pins judged at the zero-error model on the pooled rows of the first units.

        Judged on the host wherever the fleet is: the greedy test walks the columns in blocks, each a few
        small products and a QR (on a GPU, tiny kernels and a sync per block)."""
        cpu = torch.device("cpu")
        if self.superset.device == cpu:
            return self._pins_on_host(self.superset, keep, noise, prior, fixed, gauge_units)
        # one host thread: beside a GPU the host only feeds it, and a parallel region on a host whose other core
        # is busy waits for its descheduled thread
        with limit_threads(1):
            return self._pins_on_host(replicate(self.superset).to(cpu), keep, noise, prior, fixed, gauge_units)

    def _pins_on_host(self, judge, keep, noise, prior, fixed, gauge_units) -> torch.Tensor:
        cpu = torch.device("cpu")
        x0 = torch.zeros(self.layout.size, dtype=torch.float64)
        blocks = []
        if gauge_units is None:  # the first units until their rows (x d) are 4x the parameters: data enough
            rows = torch.cumsum(torch.tensor([len(u) * self.d for u in self.units]), 0)
            gauge_units = int((rows < 4 * self.layout.size).sum()) + 1
        for u in self.units[:max(1, int(gauge_units))]:
            prob = CalibrationProblem(judge, u.to(cpu), noise, prior, fixed)
            blocks.append(prob.linearize(x0, torch.zeros_like(prob.data.q))[1].reshape(-1, self.layout.size))
        basis = gauge_basis(torch.cat(blocks), gauge_priority(self.layout.roles()))
        # every unit carries the same terms (one model type): judge each distinct column subset once
        subsets, inverse = torch.unique(keep, dim=0, return_inverse=True)
        return dependent_columns_masked(basis, subsets)[inverse]

    @torch.no_grad()
    def _pose_basis(self):
        """Every pose's basis values at its command (M, Pp, n, K) (the normal matrix's; the rows' own, with their
        joint errors, enter every exact product), and their pair products (:func:`pair_basis`) where every unit
        has the same poses, else None."""
        je, st = self.superset.joint_errors, self.structure
        first = self.slots[..., 0].clamp(max=self.R - 1)  # a pose's first row (empty poses: any; they weigh 0)
        q = torch.gather(self.stack["q"], 1, first[..., None].expand(-1, -1, self.n))
        u = self.superset.error_variables(q.reshape(-1, self.n))
        basis, _ = chebyshev_design(je.normalized(u), st.K, 2.0 / (je.ranges[:, 1] - je.ranges[:, 0]))
        phi = basis.reshape(self.M, -1, self.n, st.K)
        shared = bool((phi == phi[:1]).all()) and bool((self.slots < self.R).sum(-1).eq((self.slots[:1] < self.R).sum(-1)).all())
        return phi, (pair_basis(phi[0], self.n).contiguous() if shared else None)

    @torch.no_grad()
    def linearize(self, X: torch.Tensor, V: torch.Tensor, which: torch.Tensor, slot: int | str | None = None):
        """Whitened residual f (m, R, d), parameter Jacobian A (m, R, d, P) and joint-error Jacobian C
        (m, R, d, n) of the units ``which`` (m,) at X (m, P), V (m, R, n), each on its own rows (factored where
        the model allows: f, C, E, Phi, Phi_p). slot: the compiled factored outputs are written into the
        problem's workspace under this slot, valid until the next call with the same slot (the solver's
        chunks, whose linearizations it copies or drops within the iteration); None: allocated."""
        inst, layout, R, st = self.instrument, self.layout, self.R, self.stack
        w = which.to(st["q"].device)
        q, tool, obs = st["q"][w], st["tool"][w], st["xyz"][w]
        if self.structure is not None:
            if slot is None and self._common(X, V):  # a fresh fleet's start: one unit's, each its own residual
                one = self._factored(X[:1], V[:1], w[:1], q[:1], tool[:1], obs[:1])
                s = (self.scale[w] / self.instrument.weight.sigma)[..., None]
                f = one[0] + (obs[:1] - obs) * s  # the residual is (prediction - observation), whitened
                rest = [t.expand(len(w), *t.shape[1:]) for t in one[1:4]]
                return (f, *rest) if self.dense_normal else (f, *rest, self.phi_p[w])
            return self._factored(X, V, w, q, tool, obs, slot)
        wrapper = _Predict(self.superset, self.instrument)

        if st["has_direction"]:
            def one(params, q, tool, direction, obs, v):
                pred, J = functional_call(wrapper, _prefixed(params), (q, tool, direction, v))
                return inst.whiten(inst.residual(pred, obs)), inst.whiten(layout.flatten_jacobian(J, R)), inst.whiten(J["v"])

            f, A, C = vmap(one)(self._params(X), q, tool, st["direction"][w], obs, V)
        else:
            def one(params, q, tool, obs, v):
                pred, J = functional_call(wrapper, _prefixed(params), (q, tool, None, v))
                return inst.whiten(inst.residual(pred, obs)), inst.whiten(layout.flatten_jacobian(J, R)), inst.whiten(J["v"])

            f, A, C = vmap(one)(self._params(X), q, tool, obs, V)
        s = self.scale[which][:, :, None]
        kf = self.keep[which].to(A)
        return f * s, A * s[..., None] * kf[:, None, None, :], C * s[..., None]

    @torch.no_grad()
    def residual(self, X: torch.Tensor, V: torch.Tensor, which: torch.Tensor, slot: int | str | None = None):
        """The whitened residual f (m, R, d) alone of the units ``which`` at X (m, P), V (m, R, n), for a point
        whose Jacobian no step reads (the factored forms skip it; the dense one: :meth:`linearize`'s first part)."""
        st, w = self.stack, which.to(self.stack["q"].device)
        if self.structure is None:
            return self.linearize(X, V, which, slot)[0]
        return self._factored(X, V, w, st["q"][w], st["tool"][w], st["xyz"][w], slot, jac=False)

    def _factored(self, X, V, w, q, tool, obs, slot=None, jac=True):
        """Whitened residual f (m, R, d), joint-error Jacobian C (m, R, d, n) and the factored parameter
        Jacobian (E (m, R, d, Q), Phi (m, R, n, K), each pose's Phi_p (m, Pp, n, K) at its command) of the units w
        (jac False: f alone)."""
        st = self.stack
        direction = st["direction"][w] if st["has_direction"] else None
        s = self.scale[w] / self.instrument.weight.sigma
        if fleet_kernel.available(q.device):  # whitened in the kernel: a pass over E the less
            out = None if slot is None else (lambda name, shape, like: self.workspace.take(f"lin{slot}.{name}", shape, like))
            lin = factored_linearization_fused(self.superset, self.structure, self._params(X), q, tool, direction, V,
                                               obs, scale=s, out=out, jac=jac)
            return lin if not jac or self.dense_normal else (*lin, self.phi_p[w])
        if not jac:  # the forward half alone (a GPU's geodesic acceleration)
            raw = factored_residual(self.superset, self.structure, self._params(X), q, tool, direction, V, obs)
            return raw * s[..., None]
        raw, Jv, E, Phi = factored_linearization(self.superset, self.structure, self._params(X), q, tool, direction, V,
                                                 obs)
        s = s[:, :, None]
        out = raw * s, Jv * s[..., None], E * s[..., None], Phi
        return out if self.dense_normal else (*out, self.phi_p[w])

    def step(self, lin, V, dX, mu, which, again: bool = False):
        """Damped Gauss-Newton steps of the units ``which`` (factored where the model allows, else dense)."""
        if self.structure is None:
            return super().step(lin, V, dX, mu, which, again)
        if self.dense_normal:
            f, C, E, Phi = lin
            A = dense_jacobian(E, Phi, self.structure) * self.keep[which].to(E)[:, None, None, :]
            return schur_steps(f, A, C, self.w_v[which], V, self.lam, dX, mu, self.keep[which], again=again)
        # one program at a common point (the first step of a fresh fleet): one normal matrix for every unit
        shared = self._common(dX, V) and bool((mu == mu[:1]).all())
        return structured_steps(lin, self.structure, self.slots[which], self.w_v[which], V, self.lam, dX, mu,
                                self.keep[which], pp=self._pair_products(which), ws=self.workspace, shared=shared,
                                again=again)

    def _pair_products(self, which: torch.Tensor) -> torch.Tensor | None:
        """The pair products (:func:`pair_basis`) for a step of the units ``which``: the shared ones where every
        unit has the same poses, else the units' own (npair, m, Pp, K K), formed once (they hang on the commands
        alone; 2 MB a FANUC unit) while all of them take at most UNIT_PAIRS_BYTES, else None (each step forms
        its units')."""
        if self.pp is not None:
            return self.pp
        if self.unit_pp is None:
            Pp, K = self.phi_p.shape[1], self.structure.K
            size = self.n * (self.n + 1) // 2 * self.M * Pp * K * K * self.phi_p.element_size()
            self.unit_pp = pair_basis(self.phi_p, self.n) if size <= UNIT_PAIRS_BYTES else False
        if self.unit_pp is False:
            return None
        return take_entries(self.unit_pp, which.cpu(), 1, self.workspace, "unit_pp")


@dataclass
class FleetFit:
    """Outcome of :func:`fit_fleet`: the fitted models (one per unit, in order) and the batched solve."""

    models: list
    batch: BatchedFitResult
    layout: object = None  # the full ParameterLayout of the type's model (before gauge fixing)

    @property
    def results(self):
        return self.batch.results


FLEET_FTOL = 1e-4
"""The relative cost reduction at which a fleet's units stop (:func:`fit_fleet`'s default; ``torchcal.fit``'s is
1e-8). After ~4 iterations from zero a unit's cost is within ~1e-6 of its optimum, and the iterations to 1e-8
move no prediction that matters: on 100 simulated FANUCs (experiments/fleet/run.py's fleet, order 6 + backlash)
every unit's validation residual stayed within 0.023 % of its separate fit at 1e-8, its model error within 0.08 %,
the same five units flagged, in 553 unit iterations instead of 771 (1e-5: 641 and 0.012 %; 1e-6: 687; all
before geodesic acceleration, which brings 1e-4 to 380 unit iterations and 0.017 %). The issue's bound is 1 %."""


def fit_fleet(make: Callable[[], torch.nn.Module], units: Sequence[Measurements], noise=None,
              prior: Prior | None = Prior(), fixed=(), gauge: bool = True, max_iter: int = 100, ftol: float = FLEET_FTOL,
              xtol: float = 1e-10, mu0: float = MU0, chunk: int | None = None, gauge_units: int | None = None,
              structured: bool | None = None, streams: int | None = None, accelerate: bool | None = None) -> FleetFit:
    """Fit one model per unit, every unit on its own data, in one batched Levenberg-Marquardt solve (on the CPU,
    one per stream).

    make: () -> a fresh model of the robot type (e.g. ``lambda: RobotModel(robot,
    tools, orders=6, backlash=True)``); units: (M,) :class:`Measurements`, one
    per unit (tracker points, SI; any number of rows each); noise: one
    :class:`NoiseModel` (None: the robot's) or M of them; prior, fixed, gauge,
    max_iter, xtol, mu0: as for :func:`torchcal.fit` (``method='lm'``); ftol: as there, by default
    :data:`FLEET_FTOL` (1e-4: a unit lands within a few hundredths of a percent of its own fit's residuals; 1e-8
    for the fit's own stopping point);
    chunk: units linearized together (None: as many as ~190 MB of factors and temporaries hold on the CPU,
    a quarter of the free memory on a GPU). structured: True, the factored Jacobian and normal matrix
    (:mod:`.structured`) where the model allows (a RobotModel without compliance and fine tables, isotropic
    point targets); False: dense A by ``vmap`` of the model's Jacobians; None (default): True on the CPU, and
    on a GPU the factored Jacobian expanded to dense A, whose normal matrix is one large product (what a GPU
    is fast at; the per-pose Gram blocks are many small ones).
    streams: independent solves run side by side in threads, each over a contiguous share of the units on one
    thread (None: :func:`fleet_streams`, one per CPU thread the solve may use on the CPU's compiled factored
    path, else 1). The split depends only on the unit count and ``streams``, so a run is reproducible bit for
    bit wherever it runs with the same thread count; a different split moves results by rounding (~1e-10)
    only. While the streams run, torch's intra-op threads are set to 1 (a process-wide setting).
    accelerate: geodesic acceleration of every step (:func:`~.batched.solve_batched`); None: where measured to
    pay (the CPU), off elsewhere (a GPU: not measured yet; ``bench/gpu.py --accelerate`` times both).
    Each unit's result is its own fit's (the same optimum, up to the stopping
    tolerance ``ftol``). -> :class:`FleetFit` (each unit's model fitted in place).

    Example:
        >>> import torch, torchcal
        >>> robot = torchcal.load_robot("fanuc_lrmate200i")
        >>> tools = torch.tensor([[0.033, 0.058, 0.161], [0.057, -0.034, 0.161]], dtype=torch.float64)
        >>> q = torchcal.sim.quasi_random_commands(robot.joint_map.limits, 40, 0)
        >>> noise = torchcal.NoiseModel.from_robot(robot)
        >>> units = [torchcal.simulate(torchcal.TruthRobot.fanuc_paper2(robot, tools, s), q, [0, 1], noise, s)
        ...          for s in range(3)]
        >>> out = fit_fleet(lambda: torchcal.RobotModel(robot, tools, orders=1), units)
        >>> [r.success for r in out.results]
        [True, True, True]
    """
    t0 = time.perf_counter()
    on_cpu = not units or units[0].xyz.device.type == "cpu"
    # the setup's ops are small (stacking, the gauge's QR on one unit's rows, the pose basis): one thread, which
    # beside a CPU-bound neighbour took 0.13-0.19 s against 0.21-0.48 s on two (100 FANUCs; quiet 0.19 / 0.17 s)
    with limit_threads(1) if on_cpu else nullcontext():
        fp = FleetProblem(make, units, noise, prior, fixed, gauge, gauge_units, structured=structured is not False,
                          dense_normal=not on_cpu if structured is None else False)
    fp.accelerate = fp.accelerate if accelerate is None else bool(accelerate)
    k = fleet_streams(fp) if streams is None else max(1, min(int(streams), fp.M))
    if chunk is None:
        if fp.structure is not None and not fp.dense_normal:  # factors, per-pose Gram blocks, temporaries
            per_unit = 8 * fp.R * (4 * fp.d * (fp.structure.ne + fp.structure.Nd) + 2 * fp.structure.size)
        else:  # A, M A and the step's other temporaries, roughly
            per_unit = 8 * fp.R * fp.d * fp.layout.size * 4
        if on_cpu:  # bytes; 24 FANUC units (7.8 MB each): with the step's buffers reused (Workspace), 16-50 ran
            budget = 1.9e8  # alike and 7-10 units 7-12 % slower (100 FANUCs, 2 cores, side by side)
        elif units[0].xyz.device.type == "cuda":  # every unit in one chunk where a quarter of the free memory
            budget = max(1e9, 0.25 * torch.cuda.mem_get_info(units[0].xyz.device)[0])  # holds them: fewer launches
        else:
            budget = 1e9
        # streams side by side share the budget (each has its own workspace), down to 8 units a chunk
        chunk = max(1, min(-(-fp.M // k), max(int(budget / k // per_unit), 8 if k > 1 else 1)))
    label = "fitting the fleet's units together"
    if k == 1:
        batch = solve_batched(fp, max_iter, ftol, xtol, mu0, chunk, label=label, t0=t0)
    else:
        batch = solve_streams(fp, k, max_iter, ftol, xtol, mu0, chunk, label, t0)
    fp.in_data_order(batch.results)
    for model, unit in zip(fp.models, units):  # what each unit's predict / compensate judge extrapolation by
        if hasattr(model, "record_data_span"):
            model.record_data_span(unit.q)
    return FleetFit(fp.models, batch, fp.layout)


__all__ = ["FLEET_FTOL", "FeatureScores", "FleetFit", "FleetProblem", "OUTLIER_MIN_RATIO", "Outlier", "STREAM_MIN_UNITS",
           "feature_scores", "fit_fleet", "fleet_prior", "fleet_streams", "joint_features", "parameter_outliers",
           "stack_units"]
