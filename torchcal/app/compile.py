"""``torchcal compile``: numba's compiled kernels built into its cache ahead of the first run that needs them.

Why this module exists. A fresh install (or a new CPU, a new numba, a changed
source) compiles each kernel family on its first use: the fleet's rows, the
compensation's flange, damped and targets passes, minutes in all on a 2-core
machine, inside whatever command first needs them. Here each family is
compiled by running a tiny problem through the same public path, one family
per process, so the families compile side by side (numba compiles on one
thread) and a plant's deployment script, a Docker build or CI can do it once,
up front. Families already in the cache are only reported.
"""

from __future__ import annotations

import os
import time
from concurrent.futures import ProcessPoolExecutor, as_completed
from dataclasses import dataclass
from multiprocessing import get_context

from ..core.compiled import FAMILIES, cold, quiet

ORDER = ("targets", "position", "fleet", "damped", "flange")
"""Families in the order they start, the longest compile first (stop 28: targets 140 s, fleet 43 s, damped 35 s,
flange 15 s on one core; the 3-DOF position pass ~95 s beside other processes): on two processes the targets pass
compiles on one while the others follow each other on the second."""


@dataclass
class Compiled:
    """One family's outcome: what was missing from the cache before, the seconds its process took, and an error
    message where the warm-up failed (None: the family is in the cache now)."""

    family: str
    missing: list
    seconds: float
    error: str | None = None


def _model():
    import torch

    import torchcal

    robot = torchcal.load_robot("fanuc_lrmate200i")
    tools = torch.tensor([[0.033, 0.058, 0.161], [0.057, -0.034, 0.161], [-0.034, -0.057, 0.161]], dtype=torch.float64)
    return robot, tools, torchcal.RobotModel(robot, tools, orders=4, backlash=True)


def _commands(robot, B: int):
    import torchcal.sim

    return torchcal.sim.quasi_random_commands(robot.joint_map.limits, B, 0)


def _warm_fleet():
    """fit_fleet's factored solve on two units of a few poses: every kernel of :mod:`torchcal.identify.fleet_kernel`
    that a fleet runs (one iteration is enough: the kernels' types do not depend on the sizes)."""
    import torch

    from ..core.measurements import Measurements
    from ..identify.fleet import fit_fleet

    robot, tools, model = _model()
    q = _commands(robot, 12)
    T = tools.shape[0]
    qr, tool = q.repeat(T, 1), torch.arange(T).repeat_interleave(q.shape[0])
    with torch.no_grad():
        xyz = model(qr, tool)
    # opposite approach directions: two programs, so the step is each unit's own (one program's first step is
    # shared and factors by torch: cholesky_rows would stay cold)
    units = [Measurements.from_tensors(qr, tool, xyz + 1e-4 * k, direction=torch.ones_like(qr) * (1 - 2 * k))
             for k in range(2)]
    fit_fleet(lambda: _model()[2], units, max_iter=1, structured=True)


def _warm_flange():
    """The compiled flange (:func:`torchcal.compensate.fused.flange_soa`): poses and Jacobians."""
    from ..compensate.kernel import FlangeKernel

    robot, _, model = _model()
    k = FlangeKernel(model, fused=True)
    qT = _commands(robot, 16).T.contiguous()
    k.flange(qT)
    k.flange_jacobian(qT)


def _warm_damped():
    """The compiled damped least squares (:func:`torchcal.compensate.fused_damped.damped_soa`), as the
    controller's nominal IK runs it."""
    import torch

    from ..compensate.damped import damped_least_squares

    robot, _, model = _model()
    q = _commands(robot, 16)
    with torch.no_grad():
        target = model.nominal_flange(q)
    damped_least_squares(model, q, target)


def _warm_targets():
    """The compiled targets pass (:func:`torchcal.compensate.fused_targets.targets_soa`) alone: compensate()'s
    pass over commands, set up as :func:`torchcal.compensate.newton.compiled_pass_setup` does (no flange call
    before it, so that the flange's family compiles in its own process)."""
    from ..compensate.fused_targets import solve_commands
    from ..compensate.newton import compiled_pass_setup

    robot, _, model = _model()
    q = _commands(robot, 16)
    fused, opts = compiled_pass_setup(model, q, {})
    solve_commands(fused, q, None, **opts)


def _warm_position():
    """The compiled 3-DOF pass (:func:`torchcal.compensate.fused_position.position_soa`) alone, as compensate()
    with ``position_only`` runs it (set up as :func:`_warm_targets`)."""
    from ..compensate.fused_position import solve_positions
    from ..compensate.newton import compiled_pass_setup

    robot, tools, model = _model()
    q = _commands(robot, 16)
    fused, opts = compiled_pass_setup(model, q, {})
    solve_positions(fused, q, None, tools[0].expand(16, 3), **opts)


WARM = {"fleet": _warm_fleet, "flange": _warm_flange, "damped": _warm_damped, "targets": _warm_targets,
        "position": _warm_position}


def _run(family: str) -> Compiled:
    """One family in this (worker) process: its warm-up, timed; the error's message where it fails."""
    import torch

    torch.set_num_threads(1)  # the workers run side by side; numba compiles on one thread anyway
    quiet()  # the command reports each family; a worker's own notice would repeat it
    t = time.perf_counter()
    missing = cold(family, unknown=True)
    try:
        WARM[family]()
    except Exception as exc:  # reported per family: the others still compile
        return Compiled(family, missing, time.perf_counter() - t, f"{type(exc).__name__}: {exc}")
    # read back from the disk: this process holds the code either way, the next one only what numba saved
    left = cold(family, unknown=True, on_disk=True)
    err = (f"not in numba's cache after the warm-up, or the cache cannot be read: {', '.join(left)} (can this "
           f"user write numba's cache directory? NUMBA_CACHE_DIR chooses another)") if left else None
    return Compiled(family, missing, time.perf_counter() - t, err)


def compile_kernels(families=None, jobs: int | None = None, force: bool = False, progress=None) -> list[Compiled]:
    """Compile the kernel families (None: every one of :data:`torchcal.core.compiled.FAMILIES`) into numba's cache,
    ``jobs`` processes side by side (None: the CPUs this process may use, at most one per family). force: run
    families already in the cache too (their processes only load them). progress: called with each
    :class:`Compiled` as it ends. -> one :class:`Compiled` per family, in :data:`ORDER`.

    Example:
        >>> from torchcal.app.compile import compile_kernels
        >>> [c.family for c in compile_kernels(["damped"], jobs=1)]  # doctest: +SKIP
        ['damped']
    """
    from ..compensate import fused

    names = list(ORDER if families is None else families)
    unknown = [f for f in names if f not in FAMILIES]
    if unknown:
        raise ValueError(f"compile_kernels: unknown kernel families {unknown}; known: {', '.join(ORDER)}")
    if not fused.HAVE_NUMBA:
        raise RuntimeError("compile_kernels: numba is not importable here (or TORCHCAL_NO_NUMBA is set), so the torch "
                           "forms run instead")
    out = {f: Compiled(f, [], 0.0) for f in names}
    todo = [f for f in ORDER if f in names and (force or cold(f, unknown=True))]
    if todo:
        cpus = len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else (os.cpu_count() or 1)
        workers = max(1, min(len(todo), cpus if jobs is None else int(jobs)))
        # spawn: a fresh interpreter per worker (torch's threads and fork do not mix)
        with ProcessPoolExecutor(max_workers=workers, mp_context=get_context("spawn")) as pool:
            futures = {pool.submit(_run, f): f for f in todo}
            for fut in as_completed(futures):
                try:
                    res = fut.result()
                except Exception as exc:  # the worker died (memory, a signal): the family is reported, not lost
                    res = Compiled(futures[fut], [], 0.0, f"its process failed: {type(exc).__name__}: {exc}")
                out[res.family] = res
                if progress is not None:
                    progress(res)
    return [out[f] for f in ORDER if f in out]


__all__ = ["Compiled", "ORDER", "WARM", "compile_kernels"]
