"""Named buffers that outlive one iteration of a batched solve (:class:`Workspace`)."""

from __future__ import annotations

import math

import torch

from ..core import hugepages


class Workspace:
    """Buffers that outlive one iteration, by name: a batched solve's large temporaries (the trial
    linearizations, the steps' gathered inputs, the per-pose Gram blocks and their products, the normal
    matrix and its factor) are taken from here instead of allocated anew in every iteration. glibc maps a
    block above 32 MB afresh at every allocation (the fleet's Gram blocks are 50 MB for 24 FANUC units) and
    the kernel hands out zeroed pages one fault at a time: a 100-FANUC solve took 1.2-2.9e5 page faults and
    0.5-1.4 s of system time, 1.1-1.5e5 and 0.45-0.7 s with this (what remains is the first linearization
    and its concatenation). What is taken under a name is valid until the next take of that name, so it
    must not outlive the step or iteration that took it. Large buffers are backed by huge pages where the
    system allows (:mod:`torchcal.core.hugepages`).
    """

    def __init__(self):
        self._buf: dict[str, torch.Tensor] = {}

    def take(self, name: str, shape, like: torch.Tensor) -> torch.Tensor:
        """An uninitialized tensor of ``shape`` with ``like``'s dtype and device (a view of the named buffer,
        which grows when it is too small)."""
        n = math.prod(shape)
        b = self._buf.get(name)
        if b is None or b.numel() < n or b.dtype != like.dtype or b.device != like.device:
            b = self._buf[name] = hugepages.empty(n, like)
        return b[:n].view(shape)


def consecutive(ic: torch.Tensor) -> slice | None:
    """The slice where the host index ic (k,) is a run of consecutive entries, else None."""
    if ic.numel() and int(ic[-1]) - int(ic[0]) + 1 == ic.numel():
        return slice(int(ic[0]), int(ic[-1]) + 1)
    return None


def take_entries(t: torch.Tensor, ic: torch.Tensor, dim: int = 0, ws: Workspace | None = None,
                 name: str | None = None) -> torch.Tensor:
    """t's entries ic (a host index) along ``dim``: a view where ic is a run of consecutive entries (no copy of a
    solve's large per-model tensors), else a copy, into ``ws``'s buffer ``name`` where both are given."""
    sl = consecutive(ic)
    if sl is not None:
        return t[(slice(None),) * dim + (sl,)]
    idx = ic.to(t.device, non_blocking=True)
    if ws is None or name is None:
        return torch.index_select(t, dim, idx)
    shape = (*t.shape[:dim], ic.numel(), *t.shape[dim + 1:])
    return torch.index_select(t, dim, idx, out=ws.take(name, shape, t))


__all__ = ["Workspace", "consecutive", "take_entries"]
