"""The damped least squares of :mod:`.damped` on a GPU: fixed-shape iterations replayed as CUDA graphs.

On a GPU one Levenberg-Marquardt iteration of :func:`.damped.damped_least_squares` is ~400 small kernels
(the flange, its Jacobian, the 6 x 6 solves), whatever the row count: the rows handed on by the fast path
(a few per cent of a large batch) leave the GPU idle while the host launches them, and the eager loop
synchronizes once an iteration to drop finished rows. Here the rows keep their places: a finished row is frozen
(every state update masked by ``active``), so every iteration has the same shapes and is captured once as a
CUDA graph and replayed, one launch an iteration. The host asks whether any row is still active once per
window of iterations; the iteration count and the window's progress test live on the device. Each row
follows exactly the eager loop's iteration (the same :func:`.damped.lm_step`); the linear solve is an
unrolled Cholesky (:func:`.damped.spd_solve`) instead of LAPACK's / cuSOLVER's LU, so results agree with the
eager loop to rounding. Measured on an H200 (README, The GPU): the damped path's two calls of a 4·10^6-pose
compensation took 85 + 80 ms against 135 + 134 ms eagerly.
"""

from __future__ import annotations

import warnings

import torch


def _masked(step, S: dict, C: dict, check, active, flags):
    """One iteration of the rows still active, in place: S's tensors and the flags (converged, blocked,
    stationary) keep their storage, which a captured graph needs."""
    N, conv, stall, blocked = step(S, C, check)
    for k, v in N.items():
        torch.where(active.view(-1, *([1] * (v.dim() - 1))), v, S[k], out=S[k])
    done = active & (conv | stall)
    flags["converged"] |= done & conv
    if blocked is not None:
        flags["blocked"] |= done & blocked
        flags["stationary"] |= done & stall & ~conv & ~blocked
    else:
        flags["stationary"] |= done & stall & ~conv
    active &= ~done


def solve_fixed_shape(step, S: dict, C: dict, max_iter: int, window: int, graphs: bool | None = None) -> dict:
    """Run ``max_iter`` iterations of ``step`` (:func:`.damped.lm_step` bound to its options) on every row.

    step(S, C, check_window) -> (new state, conv, stall, blocked); S: the state, (M, ...) tensors; C: the rows'
    constants. graphs: capture and replay a CUDA graph (None: on a CUDA device). -> dict of the final state
    (finished rows frozen where they finished), the converged, blocked, stationary flags (M,), and with graphs
    ``events``: CUDA events before the first (eager) iteration, after it, after the capture and after the
    replays (bench/gpu_compensation_probe.py reads the times between them).
    """
    q = S["q"]
    M, device = q.shape[0], q.device
    graphs = device.type == "cuda" if graphs is None else graphs
    S = {k: v.clone() for k, v in S.items()}
    active = torch.ones(M, dtype=torch.bool, device=device)
    flags = {k: torch.zeros(M, dtype=torch.bool, device=device) for k in ("converged", "blocked", "stationary")}
    if max_iter <= 0:
        return dict(state=S, **flags)
    # the iteration count lives on the device: one graph holds every iteration, the window's progress test too
    count = torch.zeros((), dtype=torch.long, device=device)

    def run():
        _masked(step, S, C, (count + 1) % window == 0, active, flags)
        count.add_(1)

    replay, events = run, None
    if graphs:
        events = [torch.cuda.Event(enable_timing=True) for _ in range(4)]
        events[0].record()
        # the first iteration runs eagerly on a side stream (lazy initialization, cuBLAS workspaces: what a
        # capture must not see for the first time); then the capture
        side = torch.cuda.Stream(device)
        side.wait_stream(torch.cuda.current_stream(device))
        with torch.cuda.stream(side):
            run()
        torch.cuda.current_stream(device).wait_stream(side)
        events[1].record()
        g = torch.cuda.CUDAGraph()
        try:
            with torch.cuda.graph(g):
                run()
            replay = g.replay
        except RuntimeError as exc:
            # a capture this torch / CUDA cannot take (verified on torch 2.11 + CUDA 13 only): nothing recorded
            # ran, so the same iterations go on eagerly, launched one by one
            warnings.warn(f"torchcal: the damped least squares' CUDA graph could not be captured ({exc}); its "
                          "iterations run eagerly (TORCHCAL_CUDA_GRAPHS=0 skips the attempt)", RuntimeWarning,
                          stacklevel=3)
        events[2].record()
    for k in range(1 if graphs else 0, max_iter):
        replay()
        if ((k + 1) % window == 0 or k + 1 == max_iter) and not bool(active.any()):
            break
    if graphs:
        events[3].record()
    return dict(state=S, **flags, events=events)
