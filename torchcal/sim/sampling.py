"""Measurement pose sequences: low-discrepancy commands and approach directions.

Paper II (5.2) measures over the visible joint space with a quasi-random
(Niederreiter) sequence because it leaves smaller gaps and less clustering
than pseudo-random draws, especially for small sample sizes. Backlash (13)-(14)
depends on each joint's approach direction, which follows from the order in
which the robot visits the commands.
"""

from __future__ import annotations

import warnings

import numpy as np
import torch


def quasi_random_commands(limits, count: int, seed: int, skip: int = 0, shuffle: bool = True) -> torch.Tensor:
    """Low-discrepancy controller commands inside the limit box.

    limits: (n, 2) controller range [lower, upper] per joint, SI (rad / m);
    count: number of commands; seed: scrambling seed; skip: points of the
    sequence to pass over first (draw disjoint identification and validation
    sets from one seed with ``skip``); shuffle: visit the points in a seeded
    random order instead of the sequence's own.
    -> (count, n) float64 on ``limits``' device.

    Why shuffle: consecutive points of a (t, s)-sequence fall into opposite
    halves of every coordinate (x_2k and x_2k+1 always straddle the middle),
    so in sequence order a joint's approach direction is almost a function of
    its position: s_i = sign(q_i - mid_i) (measured on the FANUC, 250 poses:
    corr(s_i, q_i) up to 0.85). Backlash b_i(q) s_i and the plain error term
    e_i(q) are then confounded. A random visiting order weakens this but does
    not remove it: whatever the order, a high position is more often reached
    from below (corr ~0.6 per joint). :func:`torchcal.analysis.planning.plan_poses`
    chooses the order itself and gets the correlation down to chance (~0.07);
    use it to plan a measurement session. The sequence order stays available
    (``shuffle=False``) because it is what users with a Sobol or Niederreiter
    pose list measure, and the experiments are judged on it.

    The paper uses a Niederreiter sequence; scipy has none, so this uses a
    scrambled Sobol sequence (:class:`scipy.stats.qmc.Sobol`), the same family
    of digital (t, s)-sequences in base 2, with the same low-discrepancy
    property. Scrambling (seeded) keeps it low-discrepancy and removes the
    unscrambled sequence's first point at the box corner.
    """
    lim = torch.as_tensor(limits, dtype=torch.float64)
    if lim.ndim != 2 or lim.shape[1] != 2:
        raise ValueError(f"quasi_random_commands: limits must have shape (n, 2), got {tuple(lim.shape)}")
    bad = ~(lim[:, 0] < lim[:, 1])
    if bad.any():
        raise ValueError(f"quasi_random_commands: joint {int(bad.nonzero()[0]) + 1} lower limit is not below its upper limit")
    if count < 0 or skip < 0:
        raise ValueError(f"quasi_random_commands: count ({count}) and skip ({skip}) must be >= 0")
    from scipy.stats import qmc  # scipy.stats takes ~1-2 s to import: only where Sobol points are drawn

    sampler = qmc.Sobol(d=lim.shape[0], scramble=True, seed=np.random.default_rng(seed))
    with warnings.catch_warnings():
        # Sobol's balance is best at powers of two; the paper's set sizes (250, 300) are not, which is fine here
        warnings.simplefilter("ignore", UserWarning)
        if skip:
            sampler.fast_forward(skip)
        u = torch.from_numpy(sampler.random(count)).to(dtype=torch.float64)
    if shuffle:
        u = u[torch.randperm(count, generator=torch.Generator().manual_seed(int(seed) + 7 * int(skip) + 1))]
    u = u.to(lim.device)
    return lim[:, 0] + u * (lim[:, 1] - lim[:, 0])


def approach_directions(q: torch.Tensor, start: torch.Tensor | None = None) -> torch.Tensor:
    """Approach direction of each joint when the robot visits the commands in order.

    q: (N, n) commands; start: (n,) command the robot comes from, or None.
    -> (N, n) in {-1, +1}, same dtype/device as q: the sign of each joint's move
    from the previous command (row 0: from ``start``). A joint that does not
    move keeps the direction of its last move, because the gear flanks stay in
    contact on the side they were driven against; before any move (and for
    row 0 without ``start``) the direction is +1.
    """
    if q.ndim != 2:
        raise ValueError(f"approach_directions: q must have shape (N, n), got {tuple(q.shape)}")
    N, n = q.shape
    prev = q[:1] if start is None else torch.as_tensor(start, dtype=q.dtype, device=q.device).reshape(1, n)
    step = torch.sign(torch.diff(torch.cat([prev, q]), dim=0))
    # forward-fill zero moves with the last non-zero sign, seeded by a +1 row; no loop over poses
    s = torch.cat([torch.ones(1, n, dtype=q.dtype, device=q.device), step])
    idx = torch.arange(N + 1, device=q.device)[:, None].expand(N + 1, n)
    last = torch.where(s != 0, idx, torch.zeros_like(idx)).cummax(0).values
    return s.gather(0, last)[1:]
