"""Which approach directions the identification data covered, per joint and position bin.

Paper II models backlash as s_i * Δq_ib(q_i) added to eps_z (13)-(14), s_i = ±1
the direction joint i approached its command from. A model fitted on data in
which joint i was only ever approached from below near some position has seen
nothing of the other flank there: its backlash term for the other direction
is an extrapolation (and, when the direction pattern was confounded with
position, simply wrong by tenths of a millimetre). :class:`DirectionCoverage`
records, per joint and per position bin over the joint limits, how many rows
of the identification data approached from each direction, so that a later
query (compensation, prediction) can be flagged when one of its joints comes
from a direction never seen at that position.
"""

from __future__ import annotations

from dataclasses import dataclass

import torch

_FORMAT = "torchcal.DirectionCoverage/1"


def _as_2d(name: str, t, n: int | None = None) -> torch.Tensor:
    t = torch.as_tensor(t)
    if t.ndim == 1:
        t = t.reshape(1, -1)
    if t.ndim != 2:
        raise ValueError(f"DirectionCoverage: {name} must have shape (B, n), got {tuple(t.shape)}")
    if n is not None and t.shape[1] != n:
        raise ValueError(f"DirectionCoverage: {name} has {t.shape[1]} joints, the coverage has {n}")
    return t


def _check_directions(direction: torch.Tensor) -> None:
    bad = ~((direction == 1) | (direction == -1) | (direction == 0))
    if bad.any():
        i, j = (int(x) for x in bad.nonzero()[0])
        raise ValueError(f"DirectionCoverage: direction of row {i}, joint {j + 1} is {float(direction[i, j])}, "
                         "expected -1, 0 or +1")


@dataclass
class DirectionCoverage:
    """Counts of identification rows per (joint, position bin, approach direction).

    limits: (n, 2) float64 [lower, upper] per joint (rad / m), the range split
    into ``bins`` equal bins; counts: (n, bins, 3) int64, last axis the
    direction -1, 0 (unknown), +1. Positions outside the limits fall into the
    first / last bin. Build with :meth:`from_data`; query with
    :meth:`outside_joints` / :meth:`outside` (batched, on the query's device).
    """

    limits: torch.Tensor
    counts: torch.Tensor

    def __post_init__(self):
        self.limits = torch.as_tensor(self.limits, dtype=torch.float64)
        self.counts = torch.as_tensor(self.counts, dtype=torch.long)
        if self.limits.ndim != 2 or self.limits.shape[1] != 2:
            raise ValueError(f"DirectionCoverage: limits must have shape (n, 2), got {tuple(self.limits.shape)}")
        n = self.limits.shape[0]
        if self.counts.ndim != 3 or self.counts.shape[0] != n or self.counts.shape[2] != 3 or self.counts.shape[1] < 1:
            raise ValueError(f"DirectionCoverage: counts must have shape ({n}, bins, 3), got {tuple(self.counts.shape)}")
        if not bool(torch.isfinite(self.limits).all()) or not bool((self.limits[:, 0] < self.limits[:, 1]).all()):
            raise ValueError("DirectionCoverage: limits must be finite with lower < upper for every joint")

    # ------------------------------------------------------------------ build
    @classmethod
    def from_data(cls, q, direction, limits, bins: int = 8) -> "DirectionCoverage":
        """Record which directions the data approached each joint's position bins from.

        q: (R, n) commands (rad / m); direction: (R, n) in {-1, 0, +1};
        limits: (n, 2); bins: bins per joint over [lower, upper].
        """
        if int(bins) < 1:
            raise ValueError(f"DirectionCoverage: bins must be >= 1, got {bins}")
        lim = torch.as_tensor(limits, dtype=torch.float64)
        cov = cls(lim.cpu(), torch.zeros(lim.shape[0] if lim.ndim == 2 else 0, int(bins), 3, dtype=torch.long))
        q = _as_2d("q", q, cov.n_joints)
        direction = _as_2d("direction", direction, cov.n_joints).to(q.device)
        if direction.shape[0] != q.shape[0]:
            raise ValueError(f"DirectionCoverage: direction has {direction.shape[0]} rows, q has {q.shape[0]}")
        _check_directions(direction)
        cov.counts = cov._count(q, direction).cpu()
        return cov

    def _count(self, q: torch.Tensor, direction: torch.Tensor) -> torch.Tensor:
        n, bins = self.n_joints, self.bins
        b = self.bin_index(q)                                           # (R, n)
        d = direction.to(torch.long) + 1                                # 0, 1, 2
        j = torch.arange(n, device=q.device).expand_as(b)
        flat = (j * bins + b) * 3 + d
        return torch.bincount(flat.reshape(-1), minlength=n * bins * 3).reshape(n, bins, 3)

    def update(self, q, direction) -> "DirectionCoverage":
        """A new coverage with the rows (q, direction) added to these counts."""
        q = _as_2d("q", q, self.n_joints)
        direction = _as_2d("direction", direction, self.n_joints).to(q.device)
        _check_directions(direction)
        return DirectionCoverage(self.limits.clone(), self.counts + self._count(q, direction).cpu())

    # ------------------------------------------------------------------ properties
    @property
    def n_joints(self) -> int:
        return self.limits.shape[0]

    @property
    def bins(self) -> int:
        return self.counts.shape[1]

    @property
    def n_rows(self) -> int:
        """Number of rows recorded (every row counts once per joint)."""
        return int(self.counts[0].sum()) if self.n_joints else 0

    @property
    def has_directions(self) -> torch.Tensor:
        """(n,) bool: whether the data had any known (±1) direction for each joint."""
        return (self.counts[:, :, 0] + self.counts[:, :, 2]).sum(1) > 0

    def seen(self) -> torch.Tensor:
        """(n, bins, 2) bool: direction -1 / +1 seen in each joint's bin."""
        return self.counts[:, :, [0, 2]] > 0

    def both_fraction(self) -> torch.Tensor:
        """(n,) float64: fraction of each joint's bins that were approached from both directions."""
        return self.seen().all(-1).to(torch.float64).mean(1)

    def edges(self) -> torch.Tensor:
        """(n, bins + 1) bin edges per joint."""
        t = torch.linspace(0.0, 1.0, self.bins + 1, dtype=torch.float64)
        return self.limits[:, :1] + t * (self.limits[:, 1:] - self.limits[:, :1])

    # ------------------------------------------------------------------ query
    def bin_index(self, q) -> torch.Tensor:
        """(B, n) long bin of each joint's position, clamped to [0, bins - 1]; on q's device."""
        q = _as_2d("q", q, self.n_joints)
        lim = self.limits.to(device=q.device)
        u = (q.to(torch.float64) - lim[:, 0]) / (lim[:, 1] - lim[:, 0])
        u = torch.nan_to_num(u, nan=0.0)
        return (u * self.bins).floor().clamp(0, self.bins - 1).long()

    def counts_at(self, q, direction) -> torch.Tensor:
        """(B, n) long: identification rows at each joint's bin with the query's direction
        (for direction 0: all rows of that bin)."""
        q = _as_2d("q", q, self.n_joints)
        direction = _as_2d("direction", direction, self.n_joints).to(q.device)
        if direction.shape[0] != q.shape[0]:
            raise ValueError(f"DirectionCoverage: direction has {direction.shape[0]} rows, q has {q.shape[0]}")
        _check_directions(direction)
        counts = self.counts.to(q.device)
        b = self.bin_index(q)
        j = torch.arange(self.n_joints, device=q.device).expand_as(b)
        per_bin = counts[j, b]                                          # (B, n, 3)
        d = direction.to(torch.long)
        same = per_bin.gather(-1, (d + 1).unsqueeze(-1)).squeeze(-1)
        return torch.where(d == 0, per_bin.sum(-1), same)

    def outside_joints(self, q, direction, min_count: int = 1) -> torch.Tensor:
        """(B, n) bool: the joint's direction (±1) at its position bin was seen in fewer than
        ``min_count`` identification rows (default: never). Direction 0 (unknown) is never outside.

        Note that for data without directions (all 0) every known query direction is outside:
        the fit had nothing to identify backlash from.
        """
        q = _as_2d("q", q, self.n_joints)
        direction = _as_2d("direction", direction, self.n_joints).to(q.device)
        n_seen = self.counts_at(q, direction)
        return (direction != 0) & (n_seen < int(min_count))

    def outside(self, q, direction, min_count: int = 1) -> torch.Tensor:
        """(B,) bool: any joint :meth:`outside_joints`."""
        return self.outside_joints(q, direction, min_count).any(-1)

    # ------------------------------------------------------------------ I/O
    def to_dict(self) -> dict:
        """JSON-able dict (plain lists and ints), inverse of :meth:`from_dict`."""
        return {
            "format": _FORMAT,
            "bins": self.bins,
            "limits": self.limits.cpu().tolist(),
            "directions": [-1, 0, 1],
            "counts": self.counts.cpu().tolist(),
        }

    @classmethod
    def from_dict(cls, d: dict) -> "DirectionCoverage":
        fmt = d.get("format", _FORMAT)
        if fmt != _FORMAT:
            raise ValueError(f"DirectionCoverage.from_dict: unknown format {fmt!r}, expected {_FORMAT!r}")
        cov = cls(torch.tensor(d["limits"], dtype=torch.float64), torch.tensor(d["counts"], dtype=torch.long))
        if "bins" in d and int(d["bins"]) != cov.bins:
            raise ValueError(f"DirectionCoverage.from_dict: bins={d['bins']} but counts have {cov.bins} bins")
        return cov

    def to(self, device) -> "DirectionCoverage":
        """Counts and limits moved to ``device`` (queries work from any device regardless)."""
        return DirectionCoverage(self.limits.to(device), self.counts.to(device))

    def table(self, names: list[str] | None = None) -> list[dict]:
        """One row per joint: bins seen from -1 only / +1 only / both / neither."""
        seen = self.seen().cpu()
        rows = []
        for j in range(self.n_joints):
            neg, pos = seen[j, :, 0], seen[j, :, 1]
            rows.append({
                "joint": names[j] if names else f"J{j + 1}",
                "bins": self.bins,
                "both": int((neg & pos).sum()),
                "minus_only": int((neg & ~pos).sum()),
                "plus_only": int((pos & ~neg).sum()),
                "none": int((~neg & ~pos).sum()),
            })
        return rows
