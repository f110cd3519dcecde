"""Transparent huge pages for the large CPU buffers that a batched solve keeps for its whole run.

Why: a fleet solve walks ~1-3 MB of Jacobian factors and Gram blocks per unit in every iteration, hundreds of MB
in all, and writes the Gram blocks pair by pair, a page apart. On 4 KiB pages that costs a TLB miss on most
of those writes and a page fault on every first touch (a 100-FANUC solve took ~1.5e5 of them). With the buffers'
2 MiB-aligned interiors advised MADV_HUGEPAGE, Linux backs them with 2 MiB pages where its transparent huge
pages are enabled (``always`` or ``madvise``, the usual default); elsewhere, and off Linux, nothing changes.
The advice changes only how memory is backed, never what it holds.
"""

from __future__ import annotations

import ctypes
import ctypes.util
import mmap
import sys

import torch

_HUGE = 2 << 20
"""The huge page size the advice is aligned to (x86-64 and most aarch64 kernels)."""

MIN_BYTES = 2 * _HUGE
"""Buffers below this are left alone: too small to hold a whole aligned huge page worth advising."""

_madvise = None
if sys.platform.startswith("linux") and hasattr(mmap, "MADV_HUGEPAGE"):
    try:
        _libc = ctypes.CDLL(ctypes.util.find_library("c") or "libc.so.6", use_errno=True)
        _madvise = _libc.madvise
        _madvise.argtypes = (ctypes.c_void_p, ctypes.c_size_t, ctypes.c_int)
        _madvise.restype = ctypes.c_int
    except (OSError, AttributeError):  # pragma: no cover  (no libc to load: leave the pages as they are)
        _madvise = None


def advise(t: torch.Tensor) -> bool:
    """Advise the 2 MiB-aligned interior of CPU tensor ``t``'s memory MADV_HUGEPAGE (best before its first
    write: pages touched already stay small until the kernel collapses them). -> whether advice was given."""
    if _madvise is None or t.device.type != "cpu" or t.numel() * t.element_size() < MIN_BYTES:
        return False
    start = t.data_ptr()
    end = start + t.numel() * t.element_size()
    a0 = (start + _HUGE - 1) & ~(_HUGE - 1)
    a1 = end & ~(_HUGE - 1)
    return a1 > a0 and _madvise(a0, a1 - a0, mmap.MADV_HUGEPAGE) == 0


def empty(shape, like: torch.Tensor) -> torch.Tensor:
    """An uninitialized tensor of ``shape`` with ``like``'s dtype and device; a large CPU one advised huge pages
    (:func:`advise`) before anything touches it."""
    t = like.new_empty(shape)
    advise(t)
    return t


__all__ = ["MIN_BYTES", "advise", "empty"]
