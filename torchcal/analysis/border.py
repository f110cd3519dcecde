"""BORDER: boundary points of a point cloud by reverse k-nearest-neighbour counts, Paper I 3.4.

Paper I picks its constraint validation set with BORDER [26] in the two-axis
BZ space: (1) find the k nearest neighbours (kNN) of every point, (2) count
for every point how many other points have it among *their* k nearest
neighbours (its reverse kNN, RkNN), (3) sort by that count; boundary points
have few RkNN. Tables 1-2 work the method on 8 points with k = 2; the
experiment uses k = 30 and takes the first 10 points.

Choices where the paper is silent (stated here, tested in
``tests/analysis/test_border.py``):

- A point is not its own neighbour; ties in distance are broken by index
  (``torch.topk`` on distances with the diagonal set to +inf).
- Ties in the RkNN count are broken by the mean distance to the k nearest
  neighbours, larger first (a sparser neighbourhood is more "outside"), then by
  index.
- Scaling of the axes. The kNN step needs one distance over axes of different
  units (B in degrees, Z in millimetres). ``scale="range"`` (the default) maps
  every column to [-1, 1] over its range, Paper I (7) (the points' own min/max,
  or ``limits`` when given, e.g. the axis command limits), so a half range of
  B weighs like a half range of Z. ``scale=None`` uses the coordinates as they
  are (the paper's 8-point example); a tensor of d positive numbers divides
  the columns by them.
"""

from __future__ import annotations

import torch

from ..core.exceptions import TorchcalError


class BorderError(TorchcalError, ValueError):
    """Bad input to BORDER (k out of range, wrong shapes, non-finite points)."""


def _check(points: torch.Tensor, k: int) -> torch.Tensor:
    if not isinstance(points, torch.Tensor):
        points = torch.as_tensor(points, dtype=torch.float64)
    if points.ndim != 2:
        raise BorderError(f"BORDER: points must have shape (N, d), got {tuple(points.shape)}")
    N = points.shape[0]
    if not 1 <= int(k) <= N - 1:
        raise BorderError(f"BORDER: k must be in 1..N-1 = 1..{N - 1}, got {k}")
    bad = ~torch.isfinite(points).all(-1)
    if bad.any():
        raise BorderError(f"BORDER: {int(bad.sum())} point(s) are not finite, first at row {int(bad.nonzero()[0])}")
    return points


def knn(points: torch.Tensor, k: int) -> tuple[torch.Tensor, torch.Tensor]:
    """k nearest neighbours of every point (itself excluded), nearest first.

    points: (N, d). Returns (indices (N, k) long, distances (N, k)).

    Example:
        >>> import torch
        >>> idx, dist = knn(torch.tensor([[0.0], [1.0], [3.0]]), 1)
        >>> idx[:, 0].tolist(), dist[:, 0].tolist()
        ([1, 0, 1], [1.0, 1.0, 2.0])
    """
    points = _check(points, k)
    D = torch.cdist(points, points)
    D.fill_diagonal_(float("inf"))
    dist, idx = torch.topk(D, int(k), dim=1, largest=False, sorted=True)
    return idx, dist


def reverse_knn_counts(points: torch.Tensor, k: int) -> torch.Tensor:
    """Number of reverse k-nearest neighbours of every point (BORDER steps 1-2).

    points: (N, d) -> (N,) long; entry n counts the points m != n with n among m's k nearest.

    Example:
        >>> import torch
        >>> reverse_knn_counts(torch.tensor([[0.0], [1.0], [3.0]]), 1).tolist()
        [1, 2, 0]
    """
    idx, _ = knn(points, k)
    return torch.bincount(idx.reshape(-1), minlength=points.shape[0])


def scale_points(points: torch.Tensor, scale="range", limits: torch.Tensor | None = None) -> torch.Tensor:
    """Columns scaled for BORDER's distances: see the module docstring. points (N, d) -> (N, d)."""
    points = torch.as_tensor(points, dtype=torch.float64) if not isinstance(points, torch.Tensor) else points
    if scale is None:
        return points
    if isinstance(scale, str):
        if scale != "range":
            raise BorderError(f"BORDER: scale must be 'range', None or a tensor of {points.shape[-1]} numbers, got {scale!r}")
        if limits is None:
            lo, hi = points.min(0).values, points.max(0).values
        else:
            lim = torch.as_tensor(limits, dtype=points.dtype, device=points.device)
            if lim.shape != (points.shape[1], 2):
                raise BorderError(f"BORDER: limits must have shape ({points.shape[1]}, 2), got {tuple(lim.shape)}")
            lo, hi = lim[:, 0], lim[:, 1]
        span = hi - lo
        if (span <= 0).any():
            raise BorderError(f"BORDER: column {int((span <= 0).nonzero()[0])} has no range to scale by")
        return 2.0 * (points - lo) / span - 1.0
    s = torch.as_tensor(scale, dtype=points.dtype, device=points.device)
    if s.shape != (points.shape[1],) or not (s > 0).all():
        raise BorderError(f"BORDER: a scale tensor must hold {points.shape[1]} positive numbers, got {s.tolist()}")
    return points / s


def border_order(points: torch.Tensor, k: int, scale="range", limits=None) -> tuple[torch.Tensor, torch.Tensor]:
    """All points sorted most-boundary first (BORDER step 3).

    points: (N, d). Returns (order (N,) long, RkNN counts (N,) long of the points in input order).
    Sort key: RkNN count ascending, then mean kNN distance descending, then index.
    """
    p = scale_points(_check(points, k), scale, limits)
    idx, dist = knn(p, k)
    counts = torch.bincount(idx.reshape(-1), minlength=p.shape[0])
    order = torch.argsort(-dist.mean(1), stable=True)
    order = order[torch.argsort(counts[order], stable=True)]
    return order, counts


def border_points(points: torch.Tensor, k: int = 30, n: int = 10, scale="range", limits=None) -> torch.Tensor:
    """Indices of the n most boundary points by BORDER (Paper I 3.4: k = 30, n = 10 in BZ space).

    points: (N, d), typically (N, 2) axis commands of a two-axis space (any
    consistent units; see ``scale``); limits: optional (d, 2) range for
    ``scale="range"``. Returns (n,) long, most boundary first.

    Example:
        >>> import torch
        >>> g = torch.stack(torch.meshgrid(torch.arange(5.0), torch.arange(5.0), indexing="ij"), -1).reshape(-1, 2)
        >>> sorted(border_points(g, k=4, n=4).tolist())    # the four corners of a 5 x 5 grid
        [0, 4, 20, 24]
    """
    if not 0 <= int(n) <= points.shape[0]:
        raise BorderError(f"BORDER: n must be in 0..{points.shape[0]}, got {n}")
    return border_order(points, k, scale, limits)[0][: int(n)]


__all__ = ["BorderError", "border_order", "border_points", "knn", "reverse_knn_counts", "scale_points"]
