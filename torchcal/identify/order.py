"""Choosing the Chebyshev order: Paper II section 5.5 / Figure 11, automated and per joint.

The paper fits orders 1-10 and keeps the one with the smallest mean residual
on a separate validation set. We do the same, then refine the order of each
joint by coordinate descent (a joint whose errors are simple needs fewer
terms, and every unneeded term adds estimation noise). Without a validation
set the score is the K-fold cross-validated mean residual on the
identification data, folds drawn by pose so that the tool configurations of
one pose never straddle training and test, or (the default in configs) the
leave-one-pose-out residual, computed from the single fit on all the data
(:func:`loo_residuals`): K-fold CV trains on (K-1)/K of the poses and so
favours orders that suit a smaller data set (5-fold on 250 poses picked
orders 4-5 where 6 is best). Residuals are always judged with the joint
errors set to zero: with fitted joint errors any model looks good.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Callable, Iterable, Sequence

import torch

from ..core.measurements import Measurements
from ..core.progress import task
from .candidates import StructureSearch
from .fit import fit, resolve_noise, warns_once
from .gauge import fix_gauge
from .problem import CalibrationProblem, NoiseModel, Prior, row_errors


@dataclass
class OrderSelection:
    """Outcome of :func:`select_orders`.

    orders: chosen order per joint; score: its mean residual (m); criterion:
    'validation', 'loo' or 'cv-<K>'; table: one row per evaluated candidate
    (orders, score, stage), in evaluation order.
    """

    orders: list[int]
    score: float
    criterion: str
    table: list[dict] = field(default_factory=list)
    fitted: torch.nn.Module | None = field(default=None, repr=False)
    """A model holding the chosen candidate's fit (the search's superset, unused terms zero): a warm start."""

    def uniform_scores(self) -> dict[int, float]:
        """Mean residual of each uniform order of the first stage (Figure 11's validation curve)."""
        return {r["orders"][0]: r["score"] for r in self.table if r["stage"] == "uniform"}


def _row_errors(model, data: Measurements) -> torch.Tensor:
    """(R,) |predicted - measured| with the joint errors at zero (m), through the problem's residual."""
    return row_errors(model, data)


def _mean_residual(model, data: Measurements) -> float:
    return float(_row_errors(model, data).mean())


def pose_folds(data: Measurements, folds: int, seed: int) -> list[torch.Tensor]:
    """Split the pose ids into ``folds`` shuffled groups (seeded); returns pose-id tensors."""
    ids = torch.unique(data.pose).cpu()
    g = torch.Generator().manual_seed(seed)
    ids = ids[torch.randperm(ids.numel(), generator=g)]
    return [chunk for chunk in torch.tensor_split(ids, folds)]


@torch.no_grad()
def loo_residuals(model, data: Measurements, noise: NoiseModel, prior: Prior | None, v: torch.Tensor | None = None,
                  fixed=(), gauge: bool = True) -> torch.Tensor:
    """Leave-one-pose-out prediction errors of a fitted model, from one linearization.  -> (R,) m.

    model: fitted to ``data`` (the MLE optimum); v: (R, n) its fitted joint
    errors (None: zero). For every pose i this predicts the error of its rows
    (joint errors zero, as for validation) under the model fitted to all
    *other* poses, by one Gauss-Newton step from the optimum (exact for a
    linear model, the classic PRESS residual). Per row the joint errors are
    eliminated: the row's whitened residual g = f - C v (at zero joint error)
    has covariance I + C W_v^-1 C^T = L L^T, so f~ = L^-1 g, A~ = L^-1 A. With
    S = sum A~^T A~ + Lambda_prior and the pose's blocks A~_i, f~_i,
    H_ii = A~_i S^-1 A~_i^T, dropping pose i moves the parameters by
    db_i = S^-1 A~_i^T (I - H_ii)^-1 f~_i (Sherman-Morrison-Woodbury), and the
    held-out error is sigma_m (g_i + A_i db_i). fixed, gauge: as given to
    :func:`fit`, so that the same parameters are free.
    """
    problem = CalibrationProblem(model, data, resolve_noise(model, noise), prior, fixed)
    if gauge:
        fix_gauge(problem)
    x = problem.layout.get().to(problem.model.device)
    v = problem.v_zero() if v is None else v.to(x)
    f, A, C = problem.linearize(x, v)
    R, d, P = A.shape
    g = f - (C @ v[..., None])[..., 0]
    cov = torch.eye(d, dtype=f.dtype, device=f.device) + C @ (C / problem.w_v[:, None, :]).transpose(1, 2)
    L = torch.linalg.cholesky(cov)
    Li = torch.linalg.solve_triangular(L, torch.eye(d, dtype=f.dtype, device=f.device).expand(R, d, d), upper=False)
    At = Li @ A  # (R, d, P)
    ft = (Li @ g[..., None])[..., 0]  # (R, d)
    Af = At.reshape(R * d, P)
    S = Af.T @ Af + torch.diag(problem.prior_precision)
    Ls, info = torch.linalg.cholesky_ex(S)
    if int(info) != 0:  # no prior and a direction the data leave free: the fit's damping chose it, a nudge here
        S = S + torch.eye(P, dtype=S.dtype, device=S.device) * 1e-12 * S.diagonal().abs().max()
        Ls = torch.linalg.cholesky(S)
    # pose blocks, padded to the largest number of rows per pose (padding rows are zero)
    pose = problem.data.pose
    ids, slot_of = torch.unique(pose, return_inverse=True)
    N = ids.numel()
    order = torch.argsort(slot_of, stable=True)
    counts = torch.bincount(slot_of, minlength=N)
    k = int(counts.max())
    start = torch.cumsum(counts, 0) - counts
    within = torch.arange(R, device=pose.device) - start[slot_of[order]]
    Ab = torch.zeros(N, k, d, P, dtype=A.dtype, device=A.device)
    fb = torch.zeros(N, k, d, dtype=A.dtype, device=A.device)
    Ab[slot_of[order], within] = At[order]
    fb[slot_of[order], within] = ft[order]
    Ab, fb = Ab.reshape(N, d * k, P), fb.reshape(N, d * k)
    SiAT = torch.cholesky_solve(Ab.permute(2, 0, 1).reshape(P, N * d * k), Ls).reshape(P, N, d * k).permute(1, 0, 2)  # S^-1 A~_i^T
    H = Ab @ SiAT  # (N, dk, dk)
    eye = torch.eye(d * k, dtype=A.dtype, device=A.device)
    # a pose that alone determines some direction has H_ii -> I: its held-out error is unbounded, say so
    sol, info = torch.linalg.solve_ex(eye - H, fb[..., None])
    bad = (info != 0) | ~torch.isfinite(sol).all(-1).all(-1)
    sol = torch.where(bad[:, None, None], torch.zeros_like(sol), sol)
    db = (SiAT @ sol)[..., 0]  # (N, P)
    e = problem.instrument.unwhiten(g + (A @ db[slot_of][..., None])[..., 0]).norm(dim=-1)
    return torch.where(bad[slot_of], torch.full_like(e, float("inf")), e)


@warns_once
def held_out_errors(
    make_model: Callable[[Sequence[int]], torch.nn.Module],
    orders: Sequence[int],
    data: Measurements,
    validation: Measurements | None,
    noise: NoiseModel,
    prior: Prior | None,
    folds: int = 0,
    seed: int = 0,
    **fit_options,
) -> torch.Tensor:
    """Held-out error (m) of every row of ``validation`` (if given) or ``data``, for a model with these orders.

    On ``validation`` if given; else the leave-one-pose-out errors (folds=0,
    :func:`loo_residuals`); else K-fold cross-validation by pose (each row
    predicted by the fit on the folds without it). -> (R,).
    """
    if validation is not None or folds == 0:
        model = make_model(orders)
        noise = resolve_noise(model, noise)
        r = fit(model, data, noise, prior, **fit_options)
        if validation is not None:
            return _row_errors(model, validation)
        return loo_residuals(model, data, noise, prior, r.v, fit_options.get("fixed", ()), fit_options.get("gauge", True))
    err = torch.empty(len(data), dtype=data.xyz.dtype, device=data.xyz.device)
    for test_ids in pose_folds(data, folds, seed):
        test = torch.isin(data.pose, test_ids.to(data.pose.device))
        model = make_model(orders)
        fit(model, data.subset(~test), noise, prior, **fit_options)
        err[test] = _row_errors(model, data.subset(test))
    return err


def score_orders(make_model, orders, data, validation, noise, prior, folds: int = 0, seed: int = 0, **fit_options) -> float:
    """Mean held-out residual (m) of :func:`held_out_errors`."""
    return float(held_out_errors(make_model, orders, data, validation, noise, prior, folds, seed, **fit_options).mean())


def paired_improvement(err_a: torch.Tensor, err_b: torch.Tensor, pose: torch.Tensor) -> tuple[float, float]:
    """How much lower b's mean held-out error is than a's, and the standard error of that (m).

    Both are errors of the same rows; the difference is averaged per pose
    first (the rows of one pose share its joint errors), so the standard
    error is that of a mean over independent poses.
    """
    _, slot = torch.unique(pose, return_inverse=True)
    N = int(slot.max()) + 1
    d = torch.zeros(N, dtype=err_a.dtype, device=err_a.device).index_add_(0, slot, err_a - err_b)
    d = d / torch.bincount(slot, minlength=N).to(d)
    return float(d.mean()), float(d.std() / N**0.5) if N > 1 else float("inf")


class SearchScores:
    """Scores of structures in a :class:`StructureSearch`'s current linearization, for a coordinate search.

    Calling it with keys and a stage name gives their held-out errors; each
    (epoch, key) goes into ``table`` (and to ``progress``) once. ``better``:
    a trial beats the incumbent by more than ``margin`` standard errors of the
    paired per-pose improvement.
    """

    def __init__(self, search, table: list, pose: torch.Tensor, margin: float, progress, what: str):
        self.search, self.table, self.pose, self.margin, self.progress, self.what = search, table, pose, margin, progress, what
        self.seen: set = set()

    def __call__(self, keys, stage: str) -> dict:
        search = self.search
        errs = search.errors(keys)
        for k in keys:
            if (search.epoch, k) not in self.seen:
                self.seen.add((search.epoch, k))
                self.table.append({"orders": list(k), "score": float(errs[k].mean()), "stage": stage, "epoch": search.epoch})
                if self.progress is not None:
                    self.progress(f"{stage}: {self.what} {list(k)} -> {self.table[-1]['score'] * 1e3:.4f} mm")
        return errs

    def better(self, errs, trial, incumbent) -> bool:
        gain, se = paired_improvement(errs[incumbent], errs[trial], self.pose)
        return gain > self.margin * se


@warns_once
def select_orders(
    make_model: Callable[[Sequence[int]], torch.nn.Module],
    data: Measurements,
    validation: Measurements | None = None,
    noise: NoiseModel | None = None,
    prior: Prior | None = Prior(),
    candidates: Iterable[int] = range(0, 11),
    folds: int = 0,
    seed: int = 0,
    per_joint: bool = True,
    max_passes: int = 2,
    joint_window: int | None = None,
    margin: float = 1.0,
    progress: Callable[[str], None] | None = None,
    validation_instrument=None,
    **fit_options,
) -> OrderSelection:
    """Pick the Chebyshev order of every joint by validation (Figure 11), then refine per joint.

    make_model(orders) must return a fresh, all-zero model with the given
    per-joint orders. Stage 1 scores every uniform order in ``candidates``;
    stage 2 (per_joint) visits the joints in turn and moves each one's order
    through ``candidates`` while the others stay, for up to ``max_passes``
    passes, keeping a change only when it lowers the held-out error by more
    than ``margin`` standard errors of the paired difference (per pose):
    dozens of trials differ by a few tenths of a per cent, and taking every
    such "improvement" fits the noise of the criterion (measured on the FANUC
    case: it took the validation ratio from 1.09 to 1.13). joint_window: in
    stage 2 try only the candidates within this distance of the joint's
    current order (the validation curve of Figure 11 is smooth in the order,
    so far jumps rarely win). folds: 0 for the leave-one-pose-out criterion,
    K for K-fold cross-validation (K fits per trial); ignored when
    ``validation`` is given.

    With the validation or leave-one-pose-out criterion the candidates are not
    fitted one by one: the model with the largest order of every joint is fitted
    once and every candidate is scored from its linearization, in batches
    (:class:`~torchcal.identify.candidates.StructureSearch`); the incumbent is
    refitted exactly after stage 1 and after every pass that changed it, and the
    candidates near it are scored from there. ``table`` records those scores.
    An ``instrument`` in ``fit_options`` (a 6-DOF sensor, Paper III) is used
    throughout, ``validation_instrument`` for the validation rows; held-out
    errors are then whitened residual norms (position and angles on their
    noise scales) instead of metres.
    """
    if folds and validation is None:
        return _select_orders_refit(make_model, data, validation, noise, prior, candidates, folds, seed, per_joint,
                                    max_passes, joint_window, margin, progress, **fit_options)
    candidates = sorted(set(int(c) for c in candidates))
    n = data.n_joints
    if noise is None:
        noise = resolve_noise(make_model([candidates[0]] * n), None)
    pose = (validation if validation is not None else data).pose
    table: list[dict] = []
    uniform = [(m,) * n for m in candidates]
    with task("choosing orders: first fit", total=None) as t:
        center = uniform[len(uniform) // 2]
        search = StructureSearch(lambda: make_model([candidates[-1]] * n), make_model, data, validation, noise, prior,
                                 fit_options, center=center, validation_instrument=validation_instrument)
        t.advance()

    scores = SearchScores(search, table, pose, margin, progress, "orders")
    better = scores.better

    with task("choosing orders: uniform candidates", total=len(uniform)) as t:
        errs = scores(uniform, "uniform")
        t.advance(len(uniform))
        best = min(uniform, key=lambda k: float(errs[k].mean()))
        # the scores are exact next to the linearization point: move there until the best stays put
        for _ in range(3):
            if best == search.center:
                break
            search.recenter(best)
            near = [k for k in uniform if abs(k[0] - best[0]) <= 2]
            errs = scores(near, "uniform recentred")
            best = min(near, key=lambda k: float(errs[k].mean()))
    best_score = float(scores([best], "uniform")[best].mean())
    if per_joint:
        passes = max_passes * n
        with task("choosing orders: per joint", total=passes) as t:
            for _ in range(max_passes):
                improved = False
                for j in range(n):
                    trials = []
                    for m in candidates:
                        if m == best[j] or (joint_window is not None and abs(m - best[j]) > joint_window):
                            continue
                        trials.append(best[:j] + (m,) + best[j + 1:])
                    errs = scores([best] + trials, f"joint{j + 1}")
                    # the trials of joint j differ from the incumbent in joint j only: whichever of them is
                    # accepted, the next trial is the same model, so the batch gives the sequential answer
                    for trial in trials:
                        s = float(errs[trial].mean())
                        if s < best_score and better(errs, trial, best):
                            best, best_score, improved = trial, s, True
                    t.advance(note=f"orders {list(best)}")
                if not improved:
                    break
                search.recenter(best)
                best_score = float(scores([best], "recentred")[best].mean())
    criterion = "validation" if validation is not None else "loo"
    return OrderSelection(orders=list(best), score=best_score, criterion=criterion, table=table, fitted=search.superset)


def _select_orders_refit(make_model, data, validation, noise, prior, candidates, folds, seed, per_joint, max_passes,
                         joint_window, margin, progress, **fit_options) -> OrderSelection:
    """:func:`select_orders` by refitting every candidate: the K-fold cross-validation criterion (K fits a trial)."""
    candidates = sorted(set(int(c) for c in candidates))
    if noise is None:
        noise = resolve_noise(make_model([candidates[0]] * data.n_joints), None)
    n = data.n_joints
    table: list[dict] = []
    errors: dict[tuple, torch.Tensor] = {}  # held-out error per row of each candidate tried
    pose = (validation if validation is not None else data).pose  # the rows those errors belong to

    def score(orders, stage):
        key = tuple(int(o) for o in orders)
        if key not in errors:
            errors[key] = held_out_errors(make_model, key, data, validation, noise, prior, folds, seed, **fit_options)
            table.append({"orders": list(key), "score": float(errors[key].mean()), "stage": stage})
            if progress is not None:
                progress(f"{stage}: orders {list(key)} -> {table[-1]['score'] * 1e3:.4f} mm")
        return float(errors[key].mean())

    def better(trial, incumbent) -> bool:
        gain, se = paired_improvement(errors[tuple(incumbent)], errors[tuple(trial)], pose)
        return gain > margin * se

    best = min(([m] * n for m in candidates), key=lambda o: score(o, "uniform"))
    best_score = score(best, "uniform")
    if per_joint:
        for _ in range(max_passes):
            improved = False
            for j in range(n):
                for m in candidates:
                    if m == best[j] or (joint_window is not None and abs(m - best[j]) > joint_window):
                        continue
                    trial = list(best)
                    trial[j] = m
                    s = score(trial, f"joint{j + 1}")
                    if s < best_score and better(trial, best):
                        best, best_score, improved = trial, s, True
            if not improved:
                break
    criterion = "validation" if validation is not None else ("loo" if folds == 0 else f"cv-{folds}")
    return OrderSelection(orders=list(best), score=best_score, criterion=criterion, table=table)
