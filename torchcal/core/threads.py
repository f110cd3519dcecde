"""CPU threads: how many this process may really use, and how many a piece of work should get.

Why this module exists. On a 2-core machine with one other CPU-bound
process, a fit on torch's default two threads ran 3-9x slower than on one
thread, while one thread lost almost nothing. The cause is OpenMP's
spin-waiting: torch (and numba's ``omp`` layer, a second libgomp of its own)
ends every parallel region at a barrier, and GNU OpenMP, unless told
otherwise, lets a thread that arrives early spin for ~300 000 iterations
before it sleeps. With one core taken by the neighbour, the spinning thread
burns the time slice that the thread it waits for needs; an LM fit runs
thousands of small parallel regions, each paying a scheduler quantum.
Measured (2 cores, one competitor, FANUC order 6, 250 x 3): 2 threads 3.5-4.6 s,
2 threads with ``OMP_WAIT_POLICY=PASSIVE`` 1.5 s, 1 thread 1.7 s, quiet 1.4 s.

So torchcal does two things:

1. :func:`configure_openmp` (run by ``import torchcal``) sets
   ``OMP_WAIT_POLICY=PASSIVE`` (waiting threads sleep at once) unless the
   user set it. GNU OpenMP reads it when the library loads, so it takes
   effect for torch only when ``torchcal`` is imported before ``torch``
   (the CLI and the experiments do); numba's runtime loads later and always
   sees it.
2. Work is given threads by its size (:func:`threads_for`): a parallel region
   costs a wake-up and a barrier, which small solves cannot win back, so
   they run on one thread whatever the wait policy; large batches (10^5
   compensated poses) spread over the CPUs this process may use
   (:func:`usable_cpus`: its affinity mask and its cgroup CPU quota, which
   ``os.cpu_count()`` and torch's default both ignore). ``threads:`` in a
   config, or :func:`set_threads`, overrides the choice.

Within one solve torch and numba never run at the same time (the compiled
kernels are called between torch ops), and both get the same count from
:func:`limit_threads`, so they do not oversubscribe each other. A fleet's
streams (:func:`torchcal.identify.fleet.fit_fleet`) run side by side, one per
usable CPU, each on one thread of both.
"""

from __future__ import annotations

import math
import os
import sys
from contextlib import contextmanager

WAIT_POLICY = "OMP_WAIT_POLICY"

SERIAL_WORK = 3e8
"""Floating-point operations per call below which one thread is faster than a pool (see module docstring).

A Schur-complement LM iteration of the FANUC order-6 fit (2 250 residuals x 285
parameters) is ~2e8 flops: measured quiet, one thread is as fast as two."""

_override: int | None = None


def configure_openmp() -> bool:
    """Ask OpenMP runtimes loaded from now on to sleep rather than spin while they wait.

    Sets ``OMP_WAIT_POLICY=PASSIVE`` unless it is already set. -> True where
    torch's own runtime will see it (torch not imported yet, or the policy
    was already passive), False where torch loaded first: then only the
    thread choice by work size protects small solves.
    """
    torch_loaded = "torch" in sys.modules
    already_passive = os.environ.get(WAIT_POLICY, "").strip().upper() == "PASSIVE"
    os.environ.setdefault(WAIT_POLICY, "PASSIVE")
    return already_passive or not torch_loaded


def _cgroup_quota() -> float | None:
    """CPUs allowed by the cgroup's CPU quota (v2 ``cpu.max`` or v1 ``cfs_quota_us``), None if unlimited."""
    try:
        with open("/sys/fs/cgroup/cpu.max") as f:
            quota, period = f.read().split()[:2]
        if quota != "max":
            return float(quota) / float(period)
        return None
    except (OSError, ValueError):
        pass
    try:
        with open("/sys/fs/cgroup/cpu/cpu.cfs_quota_us") as f:
            quota = float(f.read())
        with open("/sys/fs/cgroup/cpu/cpu.cfs_period_us") as f:
            period = float(f.read())
        return quota / period if quota > 0 and period > 0 else None
    except (OSError, ValueError):
        return None


def usable_cpus() -> int:
    """CPUs this process may run on: its affinity mask, capped by its cgroup's CPU quota (at least 1)."""
    try:
        n = len(os.sched_getaffinity(0))
    except (AttributeError, OSError):  # not Linux
        n = os.cpu_count() or 1
    quota = _cgroup_quota()
    if quota is not None:
        n = min(n, max(1, math.floor(quota)))
    return max(1, n)


def set_threads(n: int | None) -> None:
    """Fix the thread count of every torchcal call from now on (None: choose by work size again)."""
    global _override
    if n is not None and int(n) < 1:
        raise ValueError(f"threads must be at least 1 (or None to choose by work size), got {n}")
    _override = None if n is None else int(n)


def get_override() -> int | None:
    """The count fixed by :func:`set_threads` (a config's ``threads:``), or None."""
    return _override


def threads_for(work: float) -> int:
    """Threads for a call doing about ``work`` floating-point operations per parallel step.

    The override (:func:`set_threads`) wins; else 1 below :data:`SERIAL_WORK`,
    and :func:`usable_cpus` above it.
    """
    if _override is not None:
        return _override
    if work < SERIAL_WORK:
        return 1
    return usable_cpus()


@contextmanager
def limit_threads(n: int):
    """Run a block with ``n`` intra-op threads in torch (and its BLAS), in numba, and in numpy's BLAS where
    torchcal's products use it (:mod:`torchcal.core.blas`); restore afterwards."""
    import torch

    from . import blas

    n = max(1, int(n))
    old = torch.get_num_threads()
    numba = sys.modules.get("numba")
    old_nb = None
    if old != n:
        torch.set_num_threads(n)
    if numba is not None:
        try:
            old_nb = numba.get_num_threads()
            numba.set_num_threads(min(n, numba.config.NUMBA_NUM_THREADS))
        except Exception:  # numba without a threading layer: nothing to limit
            old_nb = None
    try:
        with blas.limit(n):
            yield n
    finally:
        if old != n:
            torch.set_num_threads(old)
        if old_nb is not None:
            numba.set_num_threads(old_nb)


@contextmanager
def threads_for_work(work: float):
    """:func:`limit_threads` with :func:`threads_for` ``(work)``."""
    with limit_threads(threads_for(work)) as n:
        yield n
