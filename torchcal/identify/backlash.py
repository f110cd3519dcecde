"""Choosing the order of the backlash series, after the joint orders (``model.order: auto``).

Backlash (Paper II (13)-(14)) is ``s_i Δq_ib(q_i)`` on eps_z. Its order is
chosen apart from eps_z's because the two play different parts: eps_z's series
describes how the joint's angle error varies with position, the backlash
series how the *difference between approach directions* varies with it, and
the data say much less about the second. Poses visited in a quasi-random
sequence's own order make each joint's direction nearly a function of its
position; a backlash series as rich as eps_z's then describes position errors
as direction errors, which held-out residuals on data of the same pattern
cannot reveal (both sides are confounded alike). So the search starts from the
low default order and accepts a change only where it lowers the held-out
error by more than ``margin`` standard errors of the paired per-pose
difference, the same rule as the joint orders (:func:`select_orders`).
"""

from __future__ import annotations

from typing import Callable, Iterable, Sequence

import torch

from ..error_models.joint import DEFAULT_BACKLASH_ORDER
from ..core.measurements import Measurements
from ..core.progress import task
from .candidates import StructureSearch
from .order import OrderSelection, SearchScores, held_out_errors, paired_improvement
from .problem import NoiseModel, Prior


UNCONFOUNDED_R2 = 0.1
"""A joint whose approach direction is explained by its position to less than this R² (data only,
:func:`~torchcal.analysis.confounding.direction_position_dependence`) counts as unconfounded: random
approach directions give R² ~0.01, a plain shuffle ~1/3, sequence order 0.3-0.9."""

UNCONFOUNDED_BACKLASH_CAP = 3
"""The backlash order an unconfounded joint gets at most. Measured on the simulated FANUC (250 x 3, random
approach directions, seeds 0-2), model error at random-direction poses, order-6 model: backlash order 2
0.0155 / 0.0160 / 0.0159 mm, 3 0.0152 / 0.0159 / 0.0159, 6 0.0161 / 0.0162 / 0.0163 (up to 1.06x the best);
order-3 model: 2 and 3 within 0.3 %. Backlash varies smoothly along the range (Paper II Fig. 3)."""


def default_backlash_orders(orders: Sequence[int], q: torch.Tensor, direction: torch.Tensor, limits: torch.Tensor,
                            r2_max: float = UNCONFOUNDED_R2, cap: int = UNCONFOUNDED_BACKLASH_CAP) -> tuple[list[int], list[float]]:
    """The backlash order of every joint when backlash is switched on without one, from the data.

    Where a joint's approach direction does not follow its position (R² of
    direction on position below ``r2_max``), the backlash series is
    identifiable and takes the joint's own order (at most ``cap``); where it
    does, it keeps the low :data:`DEFAULT_BACKLASH_ORDER` (a rich series would
    describe position errors as direction errors). A joint whose direction
    never changes keeps the default too (its backlash is not identifiable at
    all; the fit warns). orders: (n,) joint orders; q, direction: (R, n) the
    identification rows; limits: (n, 2). -> (backlash orders, R² per joint).

    Example:
        >>> import torch
        >>> q = torch.linspace(-1, 1, 200, dtype=torch.float64)[:, None].repeat(1, 2)
        >>> s = torch.stack([torch.sign(torch.sin(torch.arange(200.0) * 2.1)), torch.sign(q[:, 1] + 1e-9)], 1)
        >>> default_backlash_orders([6, 6], q, s.to(q), torch.tensor([[-1.0, 1.0], [-1.0, 1.0]]))[0]
        [3, 2]
    """
    from ..analysis.confounding import direction_position_dependence

    rows, _, r2, _ = direction_position_dependence(q, direction, limits)
    out = []
    for j, o in enumerate(orders):
        ok = bool(rows[j] > 0) and bool(torch.isfinite(r2[j])) and float(r2[j]) < r2_max
        out.append(min(int(o), int(cap)) if ok else DEFAULT_BACKLASH_ORDER)
    return out, [float(x) for x in r2.tolist()]


def select_backlash_orders(
    make_model: Callable[[Sequence[int], Sequence[int]], torch.nn.Module],
    orders: Sequence[int],
    data: Measurements,
    validation: Measurements | None = None,
    noise: NoiseModel | None = None,
    prior: Prior | None = Prior(),
    candidates: Iterable[int] = (-1, 0, 1, 2, 3),
    start: int = DEFAULT_BACKLASH_ORDER,
    per_joint: bool = True,
    margin: float = 1.0,
    folds: int = 0,
    seed: int = 0,
    progress: Callable[[str], None] | None = None,
    warm: torch.nn.Module | None = None,
    validation_instrument=None,
    **fit_options,
) -> OrderSelection:
    """Pick the backlash order of every joint for fixed joint orders.

    make_model(orders, backlash_orders) must return a fresh all-zero model;
    orders: the joint orders (e.g. from :func:`select_orders`); candidates:
    backlash orders to try (-1 switches a joint's backlash off); start: the
    order every joint starts from. Stage 1 tries each candidate for all joints
    at once, stage 2 (per_joint) each joint in turn; a change is kept only when
    its held-out error beats the incumbent's by more than ``margin`` paired
    standard errors. Scores as :func:`held_out_errors` (validation set,
    leave-one-pose-out or K-fold CV). -> :class:`OrderSelection` whose
    ``orders`` are the backlash orders. With the validation or
    leave-one-pose-out criterion every candidate is scored from one
    linearization of the model with the largest backlash order
    (:class:`~torchcal.identify.candidates.StructureSearch`), warm-started from
    ``warm`` (e.g. the model of the joint-order search) where given.

    Example:
        >>> # sel = select_backlash_orders(lambda o, b: RobotModel(robot, tools, o, backlash=b), [6] * 6, data)
        >>> # model = RobotModel(robot, tools, [6] * 6, backlash=sel.orders)
    """
    if not data.has_direction:
        raise ValueError(f"{data.source}: backlash orders need approach directions (dir1..dirN) in the data")
    candidates = sorted(set(int(c) for c in candidates) | {int(start)})
    n = data.n_joints
    orders = [int(o) for o in orders]
    if folds and validation is None:
        return _select_backlash_refit(make_model, orders, data, validation, noise, prior, candidates, start, per_joint,
                                      margin, folds, seed, progress, **fit_options)
    pose = (validation if validation is not None else data).pose
    table: list[dict] = []
    top = max(candidates)
    with task("choosing backlash orders: first fit", total=None) as t:
        search = StructureSearch(lambda: make_model(orders, [top] * n), lambda k: make_model(orders, list(k)), data,
                                 validation, noise, prior, fit_options, center=(int(start),) * n, warm=warm,
                                 validation_instrument=validation_instrument)
        t.advance()

    scores = SearchScores(search, table, pose, margin, progress, "backlash orders")
    better = scores.better

    best = (int(start),) * n
    uniform = [(m,) * n for m in candidates]
    with task("choosing backlash orders: uniform candidates", total=len(uniform)) as t:
        errs = scores([best] + uniform, "backlash uniform")
        best_score = float(errs[best].mean())
        for trial in uniform:
            s = float(errs[trial].mean())
            if s < best_score and better(errs, trial, best):
                best, best_score = trial, s
        t.advance(len(uniform))
    if per_joint:
        search.recenter(best)
        best_score = float(scores([best], "backlash recentred")[best].mean())
        with task("choosing backlash orders: per joint", total=n) as t:
            for j in range(n):
                trials = [best[:j] + (m,) + best[j + 1:] for m in candidates if m != best[j]]
                errs = scores([best] + trials, f"backlash joint{j + 1}")
                for trial in trials:  # trials differ in joint j only: the batch gives the sequential answer
                    s = float(errs[trial].mean())
                    if s < best_score and better(errs, trial, best):
                        best, best_score = trial, s
                t.advance(note=f"backlash orders {list(best)}")
    criterion = "validation" if validation is not None else "loo"
    return OrderSelection(orders=list(best), score=best_score, criterion=criterion, table=table, fitted=search.superset)


def _select_backlash_refit(make_model, orders, data, validation, noise, prior, candidates, start, per_joint, margin,
                           folds, seed, progress, **fit_options) -> OrderSelection:
    """:func:`select_backlash_orders` by refitting every candidate: the K-fold cross-validation criterion."""
    n = data.n_joints
    pose = (validation if validation is not None else data).pose
    errors: dict[tuple, torch.Tensor] = {}
    table: list[dict] = []

    def score(b, stage) -> float:
        key = tuple(int(x) for x in b)
        if key not in errors:
            errors[key] = held_out_errors(lambda k: make_model(orders, list(k)), key, data, validation, noise, prior,
                                          folds, seed, **fit_options)
            table.append({"orders": list(key), "score": float(errors[key].mean()), "stage": stage})
            if progress is not None:
                progress(f"{stage}: backlash orders {list(key)} -> {table[-1]['score'] * 1e3:.4f} mm")
        return float(errors[key].mean())

    def better(trial, incumbent) -> bool:
        gain, se = paired_improvement(errors[tuple(incumbent)], errors[tuple(trial)], pose)
        return gain > margin * se

    best = [int(start)] * n
    best_score = score(best, "backlash uniform")
    for m in candidates:
        trial = [m] * n
        s = score(trial, "backlash uniform")
        if s < best_score and better(trial, best):
            best, best_score = trial, s
    if per_joint:
        for j in range(n):
            for m in candidates:
                if m == best[j]:
                    continue
                trial = list(best)
                trial[j] = m
                s = score(trial, f"backlash joint{j + 1}")
                if s < best_score and better(trial, best):
                    best, best_score = trial, s
    criterion = "validation" if validation is not None else ("loo" if folds == 0 else f"cv-{folds}")
    return OrderSelection(orders=best, score=best_score, criterion=criterion, table=table)
