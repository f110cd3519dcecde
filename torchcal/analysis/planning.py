"""Plan identification poses: quasi-random, reachable, visible, and in a backlash-friendly order.

Paper II (5.2) measures quasi-random (Niederreiter) commands over the visible
joint space. The order in which the robot visits them fixes each joint's
approach direction s_i = sign(q_i,k - q_i,k-1), which enters the backlash term
s_i * Δq_ib(q_i) (13)-(14). In the sequence's own order s_i is nearly a
function of q_i (consecutive points fall into opposite halves of every
coordinate) and backlash is confounded with the position errors; a plain
random shuffle still leaves corr(s_i, q_i) ≈ 0.58 (a high position is more
likely approached from below: E[s | q] = 2u - 1 for a quantile u).
:func:`plan_poses` therefore builds the visiting order greedily: from the
remaining poses it takes next the one whose approach directions best cancel
the running direction x position moments of every joint (Chebyshev c_0..c_3
of the normalized position and a per-bin direction count, the quantities
:func:`~torchcal.analysis.confounding.backlash_confounding` and
:class:`~torchcal.core.coverage.DirectionCoverage` look at), starting
from a seeded random pose. On the FANUC with 250 poses this leaves both
approach directions in every position bin of every joint and max_i
|corr(s_i, q_i)| ≈ 0.08-0.10, R² ≈ 0.05 (sequence order: 0.85 / 0.82;
shuffled: 0.69 / 0.49), about what directions drawn by coin flip,
independent of position, would show by chance (0.063 standard deviation).

Reachability is deliberately simple (nominal kinematics, no collision model):
a command box inside the controller limits, the flange above a plane of the
base frame and outside a sphere around the base origin. Visibility from a
laser tracker is approximated by the incidence angle between the flange z axis
(where a retroreflector on the tool face points) and the line from the flange
to the tracker; poses beyond ``max_incidence`` are dropped. The arm itself
blocking the beam is not modelled.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np
import torch

from ..core.exceptions import TorchcalError
from ..core.progress import task as progress_task
from .confounding import direction_position_dependence
from ..core.coverage import DirectionCoverage
from ..core.basis import chebyshev, normalize
from ..sim.sampling import approach_directions, quasi_random_commands

MAX_POSES = 100_000
"""Largest pose plan: candidate draws (2 x count, ~2 kB each) and the decorrelating order (O(N^2)) stay tractable."""


class PlanningError(TorchcalError, ValueError):
    """Bad planning inputs (order, tracker, count) or too few reachable, visible poses."""


ORDERS = ("decorrelate", "shuffle", "sequence")
"""Visiting orders: greedy decorrelation (default), a seeded random shuffle, the Sobol sequence's own."""

MOMENT_ORDER = 3
"""Chebyshev order of the direction x position moments the ``decorrelate`` order balances."""

CHEBYSHEV_WEIGHTS = torch.tensor([1.0, 4.0, 1.0, 1.0], dtype=torch.float64)
BIN_WEIGHT = 0.5
"""Weights of the balanced moments: c_1 (the linear correlation) counts most. Tuned on the FANUC
(250 poses, seeds 0-3): max |corr(s_i, q_i)| 0.08-0.10 with these against 0.16 with unit weights."""


@dataclass
class PosePlan:
    """Planned identification poses in visiting order.

    q: (N, n) controller commands (rad / m); directions: (N, n) approach
    directions when visited in order (from ``start``, or +1 for the first row
    without one); limits: (n, 2) the command box sampled; flange: (N, 3)
    nominal flange positions (m, base frame); stats: what was drawn and
    rejected and, per joint, corr(s, q), the R² of s on a cubic Chebyshev basis
    of q, and the one-sided position bins (lists, JSON-able).
    """

    q: torch.Tensor
    directions: torch.Tensor
    limits: torch.Tensor
    flange: torch.Tensor
    order: str
    seed: int
    start: torch.Tensor | None = None
    stats: dict = field(default_factory=dict)

    def __len__(self) -> int:
        return self.q.shape[0]

    def measurements(self, tools: int = 1):
        """The plan as :class:`~torchcal.core.measurements.Measurements` (xyz NaN), each pose with ``tools`` tool rows."""
        from ..core.measurements import Measurements

        N = self.q.shape[0]
        T = int(tools)
        m = Measurements.from_tensors(self.q.repeat(T, 1), torch.arange(T).repeat_interleave(N),
                                      direction=self.directions.repeat(T, 1), pose=torch.arange(N).repeat(T),
                                      source=f"plan_poses(order={self.order}, seed={self.seed})")
        return m

    def coverage(self, bins: int = 8) -> DirectionCoverage:
        """Which approach directions each joint's position bins get."""
        return DirectionCoverage.from_data(self.q, self.directions, self.limits, bins)

    def frame(self, robot):
        """pandas DataFrame ``pose, q1..qN`` in file units (deg, mm for prismatic joints)."""
        import pandas as pd

        from ..io.csv import joint_columns, joints_to_file

        q = joints_to_file(self.q, robot)
        cols = {"pose": np.arange(len(self))}
        for i, c in enumerate(joint_columns(q.shape[1])):
            cols[c] = q[:, i]
        return pd.DataFrame(cols)

    def to_csv(self, path, robot):
        """Write ``pose, q1..qN`` (deg / mm) in visiting order; returns the path."""
        from ..io.csv import write_table

        return write_table(path, self.frame(robot))

    def table(self, names: list[str] | None = None) -> list[dict]:
        """Per joint: corr(s, q), R² of s on position, one-sided bins."""
        st = self.stats
        n = self.q.shape[1]
        names = names or [f"J{j + 1}" for j in range(n)]
        return [{"joint": names[j], "corr": st["corr"][j], "r2": st["r2"][j], "one_sided_bins": st["one_sided_bins"][j]}
                for j in range(n)]


# ------------------------------------------------------------------ ordering
def _features(q: torch.Tensor, limits: torch.Tensor, bins: int) -> np.ndarray:
    """(N, n, F) position features whose direction-weighted sums the decorrelating order balances."""
    lam = normalize(q, limits[:, 0], limits[:, 1]).clamp(-1.0, 1.0)
    cheb = chebyshev(lam, MOMENT_ORDER) * CHEBYSHEV_WEIGHTS.to(q.dtype)     # (N, n, 4)
    b = ((lam + 1.0) * 0.5 * bins).floor().clamp(0, bins - 1).long()
    onehot = torch.nn.functional.one_hot(b, bins).to(q.dtype) * BIN_WEIGHT  # (N, n, bins)
    return torch.cat([cheb, onehot], -1).cpu().numpy()


def decorrelating_order(q: torch.Tensor, limits: torch.Tensor, seed: int = 0, start: torch.Tensor | None = None,
                        bins: int = 8, candidates: int = 1) -> torch.Tensor:
    """A visiting order (N,) long in which each joint's approach direction is nearly independent of its position.

    Greedy (herding-like): keep the running sums M_j = Σ_k s_kj φ(q_kj) of the
    direction-weighted position features φ (Chebyshev c_0..c_3 and per-bin
    indicators, ``bins`` over ``limits``); next, visit the remaining pose that
    makes Σ_j |M_j|² smallest (or one drawn at random, seeded, among the
    ``candidates`` best: more variety, somewhat higher correlation); the first
    pose is a seeded random draw. O(N² n) work, vectorized
    per step. start: (n,) the command the robot comes from (None: the first row's
    direction is +1, as :func:`approach_directions` has it).
    """
    N = q.shape[0]
    if N == 0:
        return torch.zeros(0, dtype=torch.long)
    qn = q.detach().to("cpu", torch.float64).numpy()
    phi = _features(q.detach().to("cpu", torch.float64), limits.detach().to("cpu", torch.float64), bins)  # (N, n, F)
    rng = np.random.default_rng(seed)
    remaining = np.ones(N, dtype=bool)
    M = np.zeros(phi.shape[1:])
    order = np.empty(N, dtype=np.int64)
    last = None if start is None else np.asarray(torch.as_tensor(start, dtype=torch.float64).cpu(), dtype=np.float64)
    s_last = np.ones(qn.shape[1])
    with progress_task("planning poses: decorrelating visiting order", total=N) as t:
        for k in range(N):
            idx = np.flatnonzero(remaining)
            if last is None:
                s = np.ones((idx.size, qn.shape[1]))
            else:
                step = np.sign(qn[idx] - last)
                s = np.where(step == 0, s_last, step)
            cost = ((M[None] + s[..., None] * phi[idx]) ** 2).sum((1, 2))
            if k == 0 and last is None:
                pick = int(rng.integers(idx.size))     # every first pose costs the same: start anywhere
            else:
                best = np.argsort(cost, kind="stable")[: max(1, int(candidates))]
                pick = int(best[rng.integers(best.size)])
            i = idx[pick]
            order[k] = i
            M = M + s[pick][:, None] * phi[i]
            s_last = s[pick]
            last = qn[i]
            remaining[i] = False
            t.advance()
    return torch.from_numpy(order)


# ------------------------------------------------------------------ sampling
def _parse_tracker(tracker) -> torch.Tensor | None:
    if tracker is None:
        return None
    t = torch.as_tensor(tracker, dtype=torch.float64).reshape(-1)
    if t.numel() != 3 or not bool(torch.isfinite(t).all()):
        raise PlanningError(f"plan_poses: tracker must be 3 finite numbers (x, y, z in m), got {tracker!r}")
    return t


def _carried_base(chain, theta: torch.Tensor) -> torch.Tensor:
    """(B, 3) how far the joints before the first revolute one (a rail, a gantry) carry the arm's base from where it
    stands with them at zero; zeros for a fixed base. The keep-out sphere around the base moves with it: around
    the rail's origin, 17 of 300 planned poses put the flange inside the arm's own column."""
    lead = 0
    while lead < chain.prismatic.numel() and bool(chain.prismatic[lead]):
        lead += 1
    out = torch.zeros(theta.shape[0], 3, dtype=torch.float64)
    if lead == 0 or lead == chain.prismatic.numel():
        return out
    from ..kinematics.fk import chain_frames

    home = torch.zeros_like(theta)
    home[:, lead:] = theta[:, lead:]
    at = chain_frames(chain.origins, chain.axes, chain.prismatic, theta)[1][:, lead]
    at0 = chain_frames(chain.origins, chain.axes, chain.prismatic, home)[1][:, lead]
    return (at - at0).to("cpu", torch.float64)


def plan_poses(
    robot,
    count: int,
    seed: int = 0,
    tracker=None,
    min_tool_distance: float = 0.2,
    min_height: float = 0.0,
    max_incidence_deg: float = 60.0,
    order: str = "decorrelate",
    margin: float = 0.0,
    start=None,
    bins: int = 8,
    max_draws: int | None = None,
) -> PosePlan:
    """Quasi-random, reachable (and visible) commands in a backlash-decorrelating visiting order.

    robot: :class:`torchcal.kinematics.Robot`; count: poses to plan; seed:
    scrambling of the Sobol sequence and the order's random draws (same seed,
    same plan); tracker: (3,) tracker position in the robot base frame, **m**
    (the CLI takes mm), or None for no visibility test; min_tool_distance:
    radius (m) of a keep-out sphere around the base origin the flange must be
    outside of; min_height: lowest flange z (m) in the base frame (for a robot
    whose base frame sits at the shoulder, like the FANUC's DH base, lower it
    to reach below the shoulder); max_incidence_deg: largest angle between the
    flange z axis and the line from the flange to the tracker; order:
    'decorrelate' (default, :func:`decorrelating_order`), 'shuffle' (seeded
    random) or 'sequence' (the Sobol order, for comparison: confounds
    backlash); margin: fraction of each joint's range kept free at both ends;
    start: (n,) command the robot starts from (None: the first row's direction
    is +1); bins: position bins for the balance and the stats; max_draws:
    candidates drawn at most (default 64 x count).

    Sobol points are drawn in growing batches, filtered, and the first
    ``count`` kept (a prefix of a filtered low-discrepancy sequence). Raises
    :class:`PlanningError` (a ValueError) on bad arguments or when too few
    candidates pass the filters. ``stats['sequence']`` has the same per-joint
    numbers for the poses in their Sobol order, for comparison.

    Example:
        >>> import torchcal
        >>> plan = plan_poses(torchcal.load_robot("abb_irb120"), 60, seed=1)
        >>> plan.q.shape, plan.directions.shape
        (torch.Size([60, 6]), torch.Size([60, 6]))
    """
    if order not in ORDERS:
        raise PlanningError(f"plan_poses: order must be one of {ORDERS}, got {order!r}")
    if count < 1:
        raise PlanningError(f"plan_poses: count must be >= 1, got {count}")
    if count > MAX_POSES:  # checked before anything is allocated: the candidate draws scale with count
        raise PlanningError(f"plan_poses: count {count} is more than {MAX_POSES} poses (a measurement session is "
                            f"hundreds to a few thousand; larger plans exhaust memory and the O(N^2) ordering)")
    if not 0.0 <= margin < 0.5:
        raise PlanningError(f"plan_poses: margin must be in [0, 0.5), got {margin}")
    # NaN compares false everywhere: a NaN incidence bound switched the visibility test off silently
    if not (math.isfinite(min_tool_distance) and min_tool_distance >= 0.0):
        raise PlanningError(f"plan_poses: min_tool_distance must be a distance >= 0, got {min_tool_distance}")
    if not math.isfinite(min_height):
        raise PlanningError(f"plan_poses: min_height must be a finite height, got {min_height}")
    if not 0.0 < max_incidence_deg <= 180.0:
        raise PlanningError(f"plan_poses: max_incidence_deg must be in (0, 180], got {max_incidence_deg}")
    lim = robot.joint_map.limits.detach().to("cpu", torch.float64)
    width = lim[:, 1] - lim[:, 0]
    box = torch.stack([lim[:, 0] + margin * width, lim[:, 1] - margin * width], 1)
    trk = _parse_tracker(tracker)
    cos_max = math.cos(math.radians(max_incidence_deg))
    max_draws = int(max_draws) if max_draws is not None else 64 * count

    kept_q, kept_p = [], []
    drawn, kept = 0, 0
    rejected = {"below_plane": 0, "near_base": 0, "not_visible": 0}
    batch = max(2 * count, 64)
    chain = robot.chain
    dtype = chain.origins.dtype if hasattr(chain, "origins") else torch.float64
    device = chain.origins.device if hasattr(chain, "origins") else torch.device("cpu")
    with progress_task("planning poses: reachable and visible candidates", total=count) as t:
        while kept < count and drawn < max_draws:
            m = min(batch, max_draws - drawn)
            qc = quasi_random_commands(box, m, seed, skip=drawn, shuffle=False)  # a prefix of one Sobol sequence
            with torch.no_grad():
                F = chain.fk(robot.joint_map.to_joint(qc.to(device, dtype))).to("cpu", torch.float64)
            p, z_axis = F[:, :3, 3], F[:, :3, 2]
            below = p[:, 2] < min_height
            near = (p - _carried_base(chain, robot.joint_map.to_joint(qc.to(device, dtype)))).norm(dim=1) < min_tool_distance
            ok = ~below & ~near
            hidden = torch.zeros_like(ok)
            if trk is not None:
                los = trk - p
                cos = (los * z_axis).sum(1) / los.norm(dim=1).clamp(min=1e-12)
                hidden = cos < cos_max
                ok &= ~hidden
            rejected["below_plane"] += int(below.sum())
            rejected["near_base"] += int((near & ~below).sum())
            rejected["not_visible"] += int((hidden & ~below & ~near).sum())
            kept_q.append(qc[ok])
            kept_p.append(p[ok])
            kept += int(ok.sum())
            drawn += m
            batch *= 2
            t.advance(min(kept, count) - t.completed, note=f"{drawn} drawn")
    q = torch.cat(kept_q)[:count]
    flange = torch.cat(kept_p)[:count]
    if q.shape[0] < count:
        raise PlanningError(f"plan_poses: only {q.shape[0]} of {drawn} candidate poses are reachable and visible, "
                         f"{count} wanted (rejected: {rejected}); relax min_height / min_tool_distance / "
                         f"max_incidence_deg or move the tracker")
    return ordered_plan(q, flange, box, order, seed, start, bins, {"drawn": drawn, "rejected": rejected})


def ordered_plan(q: torch.Tensor, flange: torch.Tensor, box: torch.Tensor, order: str = "decorrelate", seed: int = 0,
                 start=None, bins: int = 8, stats: dict | None = None) -> PosePlan:
    """Chosen commands q (N, n) (flange positions (N, 3), sampled box (n, 2)) put in visiting ``order``
    (:func:`plan_poses`' orders), with their approach directions and direction statistics (``stats``: more
    entries for the plan's stats, e.g. what was drawn and rejected). -> :class:`PosePlan`."""
    if order not in ORDERS:
        raise PlanningError(f"plan_poses: order must be one of {ORDERS}, got {order!r}")
    count = q.shape[0]
    start_t = None if start is None else torch.as_tensor(start, dtype=torch.float64).reshape(-1)
    if order == "decorrelate":
        perm = decorrelating_order(q, box, seed, start_t, bins)
    elif order == "shuffle":
        perm = torch.randperm(count, generator=torch.Generator().manual_seed(int(seed) + 1))
    else:
        perm = torch.arange(count)
    seq = direction_stats(q, approach_directions(q, start_t), box, bins)
    q, flange = q[perm], flange[perm]
    s = approach_directions(q, start_t)
    out = direction_stats(q, s, box, bins)
    out.update({**(stats or {}), "order": order, "seed": int(seed),
                "sequence": {k: seq[k] for k in ("corr", "r2", "one_sided_bins", "max_abs_corr", "max_r2")}})
    return PosePlan(q, s, box, flange, order, int(seed), start_t, out)


def direction_stats(q: torch.Tensor, directions: torch.Tensor, limits: torch.Tensor, bins: int = 8) -> dict:
    """Per joint corr(s, q), R² of s on a cubic Chebyshev basis of q, and one-sided position bins (lists)."""
    _, corr, r2, plus = direction_position_dependence(q, directions, limits, order=3)
    seen = DirectionCoverage.from_data(q, directions, limits, bins).seen()
    one_sided = (seen.any(-1) & ~seen.all(-1)).sum(1)
    return {
        "corr": [float(c) for c in corr],
        "r2": [float(r) for r in r2],
        "plus_fraction": [float(x) for x in plus],
        "one_sided_bins": [int(x) for x in one_sided],
        "bins": int(bins),
        "max_abs_corr": float(corr.abs().nan_to_num(1.0).max()),
        "max_r2": float(r2.nan_to_num(1.0).max()),
        "travel": [float(x) for x in torch.diff(q, dim=0).abs().sum(0)] if q.shape[0] > 1 else [0.0] * q.shape[1],
    }

