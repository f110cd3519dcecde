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
from ..measurements import Measurements
from .order import OrderSelection, held_out_errors, paired_improvement
from .problem import NoiseModel, Prior


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
    ``orders`` are the backlash orders.

    Example:
        >>> # sel = select_backlash_orders(lambda o, b: RobotModel(robot, tools, o, backlash=b), [6] * 6, data)
        >>> # model = RobotModel(robot, tools, [6] * 6, backlash=sel.orders)
    """
    if not data.has_direction:
        raise ValueError(f"{data.source}: backlash orders need approach directions (dir1..dirN) in the data")
    candidates = sorted(set(int(c) for c in candidates) | {int(start)})
    n = data.n_joints
    orders = [int(o) for o in orders]
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
