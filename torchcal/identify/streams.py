"""A fleet's units solved as independent streams side by side, one per usable CPU (:func:`solve_streams`).

Beside one CPU-bound process, one solve on two threads gets about one core: its threads meet at barriers at the
end of every parallel region, and the one the scheduler put aside holds up the other. Independent solves, each
on one thread, get their share (two streams 1.23-1.31 cores where one solve on two threads got 1.03).
"""

from __future__ import annotations

import contextvars
import threading
import time
from concurrent.futures import FIRST_EXCEPTION, ThreadPoolExecutor, wait

import torch

from ..core.progress import task
from ..core.threads import limit_threads, threads_for
from . import fleet_kernel
from .batched import BatchedFitResult, Cancelled, solve_batched


def solve_streams(fp, k: int, max_iter, ftol, xtol, mu0, chunk, label, t0) -> BatchedFitResult:
    """:func:`solve_batched` on ``k`` contiguous shares of the units, side by side in threads, each on one thread;
    -> their results merged in the units' order. The first stream's error is raised, the others cancelled."""
    # each stream solves its units alone, on one thread: beside a CPU-bound neighbour the scheduler gives
    # independent threads their share, where one solve's parallel regions wait at every barrier for the thread
    # it has descheduled (two threads of one solve got 1.03 cores, two streams 1.23-1.31; README, Fleets)
    bounds = [round(i * fp.M / k) for i in range(k + 1)]
    fp.layout._flat_index()  # its cache filled once, not by the streams at once
    subs = [fp.subset(range(a, b)) for a, b in zip(bounds[:-1], bounds[1:])]
    cancel = threading.Event()  # a failed stream, or Ctrl-C, stops the others at their next iteration
    with limit_threads(1), task(label, total=fp.M) as bar:
        lock = threading.Lock()
        with ThreadPoolExecutor(k, thread_name_prefix="torchcal-fleet") as ex:
            futures = [ex.submit(contextvars.copy_context().run, solve_batched, s, max_iter, ftol, xtol, mu0, chunk,
                                 label, t0, 1, _StreamTask(bar, lock, f"stream {i + 1}/{k}"), cancel)
                       for i, s in enumerate(subs)]
            try:
                wait(futures, return_when=FIRST_EXCEPTION)
            finally:
                if not all(f.done() and f.exception() is None for f in futures):
                    cancel.set()
            failed = [f.exception() for f in futures if f.exception() is not None]
            first = next((e for e in failed if not isinstance(e, Cancelled)), None)
            if first is not None:
                raise first
            parts = [f.result() for f in futures]
    return BatchedFitResult(results=[r for b in parts for r in b.results], x=torch.cat([b.x for b in parts]),
                            keep=torch.cat([b.keep for b in parts]), iterations=max(b.iterations for b in parts),
                            time=time.perf_counter() - t0, names=parts[0].names)


STREAM_MIN_UNITS = 4
"""The fewest units a stream gets. Two streams against one solve on two threads, 2 cores, medians of 5
(FANUC units of 250 x 3 poses): 8 units 0.36 / 0.34 s quiet, 0.61 / 1.01 s beside a CPU-bound process; 12
units 0.54 / 0.54 s and 0.69 / 1.43 s; 4 units (two streams of 2) 0.22 / 0.19 s and 0.46 / 0.49 s."""


def fleet_streams(fp) -> int:
    """Independent solves a fleet runs side by side: on the CPU's factored path, one per thread the solve may
    use (each on one thread, :func:`~torchcal.core.threads.threads_for` of a large solve), at least
    :data:`STREAM_MIN_UNITS` units each; else 1."""
    if fp.structure is None or fp.dense_normal or fp.keep.device.type != "cpu" or not fleet_kernel.available(fp.keep.device):
        return 1
    return max(1, min(threads_for(float("inf")), fp.M // STREAM_MIN_UNITS))


class _StreamTask:
    """One stream's view of the fleet's progress task: its finished units counted there, its notes prefixed with
    its name (the streams advance one task from their threads, under one lock)."""

    def __init__(self, task, lock, name: str):
        self.task, self.lock, self.name = task, lock, name

    def advance(self, n: int = 1, note: str | None = None) -> None:
        with self.lock:
            self.task.advance(n, None if note is None else f"{self.name}: {note}")


__all__ = ["STREAM_MIN_UNITS", "fleet_streams", "solve_streams"]
