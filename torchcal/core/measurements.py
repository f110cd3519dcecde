"""A set of position measurements, in SI, ready for identification or evaluation.

One row per measured point: pose id, tool index, controller command q, approach
direction s (0 where unknown), measured xyz in the measurement frame. The CSV
contract (mm, deg) is read and written by :mod:`torchcal.io.csv`.
"""

from __future__ import annotations

from dataclasses import dataclass, field, replace

import torch

from .exceptions import InputError


@dataclass
class Measurements:
    """Rows of (pose, tool, q, direction, xyz); SI units, float64.

    q: (R, n) controller commands (rad / m); tool: (R,) long; xyz: (R, 3) m
    (NaN where only predicting); direction: (R, n) in {-1, 0, +1};
    pose: (R,) long; rows: (R,) row numbers in the source file (1-based data
    rows, for messages); source: file name or description.

    Example:
        >>> import torch
        >>> m = Measurements.from_tensors(torch.zeros(4, 6), tool=0, direction=torch.ones(4, 6))
        >>> len(m), m.n_joints, m.has_direction, bool(m.xyz.isnan().all())
        (4, 6, True, True)
    """

    q: torch.Tensor
    tool: torch.Tensor
    xyz: torch.Tensor
    direction: torch.Tensor
    pose: torch.Tensor
    rows: torch.Tensor
    has_direction: bool = False
    source: str = ""
    extra: dict = field(default_factory=dict)

    def __post_init__(self):
        R = self.q.shape[0]
        for name in ("tool", "xyz", "direction", "pose", "rows"):
            t = getattr(self, name)
            if t.shape[0] != R:
                raise InputError(f"Measurements.{name} has {t.shape[0]} rows, q has {R}")

    def __len__(self) -> int:
        return self.q.shape[0]

    def __repr__(self) -> str:
        # a summary: the dataclass's repr printed every tensor in full (thousands of rows in a notebook)
        tools = sorted(torch.unique(self.tool).tolist()) if len(self) else []
        return (f"Measurements({len(self)} rows, {self.n_poses if len(self) else 0} poses, {self.n_joints} joints, "
                f"tools {tools}, directions {'yes' if self.has_direction else 'no'}, {self.q.dtype}, {self.q.device}"
                + (f", source {self.source!r}" if self.source else "")
                + (f", extra {sorted(self.extra)}" if self.extra else "") + ")")

    @property
    def n_joints(self) -> int:
        return self.q.shape[1]

    @property
    def n_poses(self) -> int:
        return int(torch.unique(self.pose).numel())

    @classmethod
    def from_tensors(cls, q, tool, xyz=None, direction=None, pose=None, source: str = "") -> "Measurements":
        """Build from plain tensors; missing pose ids / directions get defaults."""
        q = torch.as_tensor(q, dtype=torch.float64)
        if q.ndim != 2:
            raise InputError(f"Measurements.from_tensors: q must be (R, n) commands, got shape {tuple(q.shape)}")
        R = q.shape[0]
        tool = torch.as_tensor(tool)
        if tool.is_floating_point() and not bool((tool == tool.round()).all()):
            raise InputError("Measurements.from_tensors: tool must hold integer tool indices")
        tool = tool.to(torch.long)
        if tool.ndim > 1 or (tool.ndim == 1 and tool.shape[0] not in (1, R)):
            raise InputError(f"Measurements.from_tensors: tool must be one index or ({R},) indices, got shape "
                             f"{tuple(tool.shape)}")
        tool = tool.expand(R).clone()
        if R and int(tool.min()) < 0:
            raise InputError(f"Measurements.from_tensors: tool indices must be >= 0, got {int(tool.min())}")
        xyz = torch.full((R, 3), float("nan"), dtype=torch.float64) if xyz is None else torch.as_tensor(xyz, dtype=torch.float64)
        if xyz.ndim != 2 or xyz.shape[1] != 3:
            raise InputError(f"Measurements.from_tensors: xyz must be ({R}, 3) points, got shape {tuple(xyz.shape)}")
        has_dir = direction is not None
        direction = torch.zeros_like(q) if direction is None else torch.as_tensor(direction, dtype=torch.float64)
        if direction.shape != q.shape:
            raise InputError(f"Measurements.from_tensors: direction must have q's shape {tuple(q.shape)}, got "
                             f"{tuple(direction.shape)}")
        bad = first_invalid_direction(direction)
        if bad is not None:
            raise InputError(f"Measurements.from_tensors: direction must be -1, 0 or +1, got "
                             f"{float(direction[bad])} at row {bad[0]}, joint {bad[1] + 1}")
        pose = torch.arange(R) if pose is None else torch.as_tensor(pose, dtype=torch.long)
        return cls(q, tool, xyz.to(q.device), direction.to(q.device), pose.to(q.device), torch.arange(1, R + 1), has_dir, source)

    def to(self, device) -> "Measurements":
        return replace(self, q=self.q.to(device), tool=self.tool.to(device), xyz=self.xyz.to(device),
                       direction=self.direction.to(device), pose=self.pose.to(device))

    def subset(self, index) -> "Measurements":
        """Rows selected by a bool mask or an index tensor."""
        index = torch.as_tensor(index)
        if index.dtype == torch.bool:
            index = index.nonzero()[:, 0]
        index = index.to(self.q.device)
        return replace(self, q=self.q[index], tool=self.tool[index], xyz=self.xyz[index],
                       direction=self.direction[index], pose=self.pose[index], rows=self.rows[index.cpu()],
                       extra={k: v[index.to(v.device)] for k, v in self.extra.items()})

    def poses_subset(self, pose_ids) -> "Measurements":
        """All rows whose pose id is in pose_ids."""
        ids = torch.as_tensor(pose_ids, dtype=torch.long, device=self.pose.device)
        return self.subset(torch.isin(self.pose, ids))


def pose_first_rows(pose: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """The distinct pose ids (N,) of ``pose`` (R,), sorted, and each one's first row (N,) long: one row per
    pose (its commands), in the order of the ids."""
    poses, inv = torch.unique(pose, return_inverse=True)
    first = torch.full((poses.numel(),), pose.numel(), dtype=torch.long, device=pose.device)
    first = first.scatter_reduce(0, inv, torch.arange(pose.numel(), device=pose.device), reduce="amin")
    return poses, first


def first_invalid_direction(direction: torch.Tensor) -> tuple[int, int] | None:
    """(pose, joint index) of the first approach direction that is not -1, 0 or +1, or None.  direction: (B, n)."""
    bad = ~((direction == 1) | (direction == -1) | (direction == 0))
    if not bad.any():
        return None
    i, j = (int(x) for x in bad.nonzero()[0])
    return i, j
