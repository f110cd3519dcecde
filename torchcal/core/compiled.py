"""numba's compiled kernels: whether this machine's cache holds them, and one notice before a cold compile.

Why this module exists. torchcal's compiled passes (the fleet's rows, the
compensation's flange, damped, targets and 3-DOF position passes) are numba functions cached
on disk (``cache=True``, next to the source or in numba's user-wide cache
directory). A process that finds them there loads them in ~0.5 s; one that
does not compiles them first, the first time a fresh install (or a new CPU,
numba or source) runs them: ~45 s for a fleet, ~3 min for the first
compensate() (flange, targets and damped families; ~2.5 min of it the targets
pass) on a 2-core machine. Without a word that looks like a hang, so the
first cold use in a process says what is happening and how to do it ahead of
time (``torchcal compile``, :mod:`torchcal.app.compile`).

The test reads numba's cache index as numba's own loader does (the source
stamp, the CPU's magic tuple, the bytecode hash); where numba's internals
differ from what this expects it answers None and nothing is said.
"""

from __future__ import annotations

import logging

log = logging.getLogger("torchcal")

FAMILIES = {
    "fleet": ("torchcal.identify.fleet_kernel", ("linearize_rows", "schur_rows", "apply_rows", "cholesky_rows",
                                                  "cholesky_solve_rows", "gather_rows", "gradient_rows"), "about 45 s"),
    "flange": ("torchcal.compensate.fused", ("flange_soa",), "about 15 s"),
    "damped": ("torchcal.compensate.fused_damped", ("damped_soa",), "about 35 s"),
    "targets": ("torchcal.compensate.fused_targets", ("targets_soa",), "about 2.5 min"),
    "position": ("torchcal.compensate.fused_position", ("position_soa",), "about 1 min"),
}
"""Kernel families: the module, its cached entry points, and the cold compile's time on one core of a 2-core
AMD EPYC VM (stop 28: 43, 15, 35 and 140 s; position: ~95 s beside other processes). ``torchcal compile`` builds them one family per process."""

_NOTICED: set[str] = set()


def cached(dispatcher, on_disk: bool = False) -> bool | None:
    """True where numba's cache holds machine code of ``dispatcher`` (a ``numba.njit(cache=True)`` function) for
    this source and this CPU (or, unless ``on_disk``, this process has it already); False where the next call
    compiles; None where it cannot tell (numba's internals moved, or its cache directory cannot be read)."""
    try:
        if dispatcher.overloads and not on_disk:  # compiled or loaded in this process already
            return True
        cache = dispatcher._cache
        index = cache._cache_file._load_index()  # {} where missing, of another numba version, or stale
        codegen = dispatcher.targetctx.codegen()
        return any(key == cache._index_key(key[0], codegen) for key in index)
    except Exception:  # numba's internals moved: say nothing rather than something wrong
        return None


def cold(family: str, unknown: bool = False, on_disk: bool = False) -> list[str]:
    """The entry points of ``family`` (a key of :data:`FAMILIES`) the next call compiles (empty: all cached, or
    numba missing). unknown: also those whose state cannot be told (:func:`cached` None); on_disk: as
    :func:`cached`'s."""
    import importlib

    module, names, _ = FAMILIES[family]
    mod = importlib.import_module(module)
    if not getattr(mod, "HAVE_NUMBA", False):
        return []
    return [nm for nm in names if cached(getattr(mod, nm), on_disk) in ((False, None) if unknown else (False,))]


def quiet() -> None:
    """No notices in this process (``torchcal compile``'s workers: the command itself reports each family)."""
    _NOTICED.update(FAMILIES)


def notice(family: str) -> None:
    """Before ``family``'s kernels first run in this process: a warning where they are not in the cache (once
    per family and process; a compile of minutes must not look like a hang)."""
    if family in _NOTICED:
        return
    _NOTICED.add(family)
    missing = cold(family)
    if missing:
        text = (f"compiling torchcal's {family} kernels for this CPU ({', '.join(missing)}) into numba's cache: once "
                f"per install, {FAMILIES[family][2]} on a 2-core machine; later runs load them in ~0.5 s. `torchcal "
                "compile` builds every family ahead of time, side by side (TORCHCAL_NO_NUMBA=1 runs the torch forms "
                "instead: no compile, slower per pose)")
        log.warning(text)
        from . import progress

        progress.note(text)  # on the console too, where a front end shows progress: a bar that stalls is no hang


__all__ = ["FAMILIES", "cached", "cold", "notice", "quiet"]
