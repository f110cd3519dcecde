"""Choosing the Chebyshev order: Paper II section 5.5 / Figure 11, automated and per joint.

The paper fits orders 1-10 and keeps the one with the smallest mean residual
on a separate validation set. We do the same, then refine the order of each
joint by coordinate descent (a joint whose errors are simple needs fewer
terms, and every unneeded term adds estimation noise). Without a validation
set the score is the K-fold cross-validated mean residual on the
identification data, folds drawn by pose so that the tool configurations of
one pose never straddle training and test. Residuals are always judged with
the joint errors set to zero: with fitted joint errors any model looks good.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Callable, Iterable, Sequence

import torch

from ..measurements import Measurements
from .fit import fit
from .problem import NoiseModel, Prior


@dataclass
class OrderSelection:
    """Outcome of :func:`select_orders`.

    orders: chosen order per joint; score: its mean residual (m); criterion:
    'validation' or 'cv-<K>'; table: one row per evaluated candidate
    (orders, score, stage), in evaluation order.
    """

    orders: list[int]
    score: float
    criterion: str
    table: list[dict] = field(default_factory=list)

    def uniform_scores(self) -> dict[int, float]:
        """Mean residual of each uniform order of the first stage (Figure 11's validation curve)."""
        return {r["orders"][0]: r["score"] for r in self.table if r["stage"] == "uniform"}


def _mean_residual(model, data: Measurements) -> float:
    with torch.no_grad():
        p = model.points(data.q, data.tool, data.direction if data.has_direction else None)
    return float((p - data.xyz).norm(dim=1).mean())


def pose_folds(data: Measurements, folds: int, seed: int) -> list[torch.Tensor]:
    """Split the pose ids into ``folds`` shuffled groups (seeded); returns pose-id tensors."""
    ids = torch.unique(data.pose).cpu()
    g = torch.Generator().manual_seed(seed)
    ids = ids[torch.randperm(ids.numel(), generator=g)]
    return [chunk for chunk in torch.tensor_split(ids, folds)]


def score_orders(
    make_model: Callable[[Sequence[int]], torch.nn.Module],
    orders: Sequence[int],
    data: Measurements,
    validation: Measurements | None,
    noise: NoiseModel,
    prior: Prior | None,
    folds: int = 5,
    seed: int = 0,
    **fit_options,
) -> float:
    """Mean residual (m) of a model with these per-joint orders: on ``validation`` if given, else K-fold CV."""
    if validation is not None:
        model = make_model(orders)
        fit(model, data, noise, prior, **fit_options)
        return _mean_residual(model, validation)
    total, count = 0.0, 0
    for test_ids in pose_folds(data, folds, seed):
        test = torch.isin(data.pose, test_ids.to(data.pose.device))
        model = make_model(orders)
        fit(model, data.subset(~test), noise, prior, **fit_options)
        held = data.subset(test)
        total += _mean_residual(model, held) * len(held)
        count += len(held)
    return total / count


def select_orders(
    make_model: Callable[[Sequence[int]], torch.nn.Module],
    data: Measurements,
    validation: Measurements | None = None,
    noise: NoiseModel | None = None,
    prior: Prior | None = Prior(),
    candidates: Iterable[int] = range(0, 11),
    folds: int = 5,
    seed: int = 0,
    per_joint: bool = True,
    max_passes: int = 2,
    joint_window: int | None = None,
    progress: Callable[[str], None] | None = None,
    **fit_options,
) -> OrderSelection:
    """Pick the Chebyshev order of every joint by validation (Figure 11), then refine per joint.

    make_model(orders) must return a fresh, all-zero model with the given
    per-joint orders. Stage 1 scores every uniform order in ``candidates``;
    stage 2 (per_joint) visits the joints in turn and moves each one's order
    through ``candidates`` while the others stay, keeping any improvement,
    for up to ``max_passes`` passes. joint_window: in stage 2 try only the
    candidates within this distance of the joint's current order (cross-
    validation costs ``folds`` fits per trial; the validation curve of
    Figure 11 is smooth in the order, so far jumps rarely win).
    """
    noise = noise or NoiseModel.paper2()
    candidates = sorted(set(int(c) for c in candidates))
    n = data.n_joints
    table: list[dict] = []
    cache: dict[tuple, float] = {}

    def score(orders, stage):
        key = tuple(int(o) for o in orders)
        if key not in cache:
            cache[key] = score_orders(make_model, key, data, validation, noise, prior, folds, seed, **fit_options)
            table.append({"orders": list(key), "score": cache[key], "stage": stage})
            if progress is not None:
                progress(f"{stage}: orders {list(key)} -> {cache[key] * 1e3:.4f} mm")
        return cache[key]

    best = min(([m] * n for m in candidates), key=lambda o: score(o, "uniform"))
    best_score = cache[tuple(best)]
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
                    if s < best_score:
                        best, best_score, improved = trial, s, True
            if not improved:
                break
    criterion = "validation" if validation is not None else f"cv-{folds}"
    return OrderSelection(orders=list(best), score=best_score, criterion=criterion, table=table)
