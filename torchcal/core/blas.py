"""Batched matrix products of CPU tensors through numpy's BLAS where torch's is the slower one (:func:`bmm`).

Why this module exists. torch's CPU wheels link Intel's MKL, which on other vendors' CPUs takes a generic code
path; numpy's wheels link OpenBLAS, which picks its kernels by the CPU's features. On this project's 2-core AMD
EPYC machines (2026-11-27, one thread, side by side in one process):

- the fleet's per-unit contraction, 21 x 33 products (49 x 250) @ (250 x 49): 6.3-6.7 GFMA/s in torch, 8.2-10.1
  through numpy (4.7 against 8.6 in a slow phase of the machine);
- its one-program form, 21 products (49 x 250) @ (250 x 1617): 8.0-11.1 against 12.6-15.2.

The choice is fixed per machine, by the CPU's vendor (numpy's BLAS where torch's is MKL and the CPU is not
Intel's), not timed: every run and every Ray worker on a machine computes the same bits. ``TORCHCAL_BLAS=numpy``
or ``torch`` overrides it. numpy's OpenBLAS keeps a thread pool of its own, which
:func:`torchcal.core.threads.limit_threads` holds to the solve's count through threadpoolctl (:func:`limit`).
"""

from __future__ import annotations

import functools
import os
from contextlib import nullcontext

import numpy as np
import torch

ENV = "TORCHCAL_BLAS"


def cpu_info(key: str) -> str:
    """A field of the first CPU in /proc/cpuinfo (``vendor_id``, ``model name``), '' where it cannot be read."""
    try:
        with open("/proc/cpuinfo") as f:
            for line in f:
                if line.startswith(key):
                    return line.split(":", 1)[1].strip()
    except OSError:
        pass
    return ""


def _vendor() -> str:
    """The CPU's vendor string (``GenuineIntel``, ``AuthenticAMD``, ...), '' where it cannot be read."""
    return cpu_info("vendor_id")


@functools.cache
def numpy_blas() -> bool:
    """Whether CPU products go through numpy's BLAS (see the module docstring)."""
    choice = os.environ.get(ENV, "").strip().lower()
    if choice in ("numpy", "torch"):
        return choice == "numpy"
    if choice:
        raise ValueError(f"{ENV}={choice!r}: expected 'numpy' or 'torch'")
    vendor = _vendor()
    return bool(vendor) and vendor != "GenuineIntel" and torch.backends.mkl.is_available()


def bmm(a: torch.Tensor, b: torch.Tensor, out: torch.Tensor) -> torch.Tensor:
    """``torch.bmm(a, b, out=out)``: (B, m, k) @ (B, k, n) -> out (B, m, n), any strides where each matrix has a
    unit stride in one dimension (views, as the fleet's contraction reads and writes). On the CPU through numpy's
    BLAS where :func:`numpy_blas`, else torch's. No autograd: for data, not for parameters."""
    if out.device.type == "cpu" and numpy_blas():
        np.matmul(a.detach().numpy(), b.detach().numpy(), out=out.detach().numpy())
        return out
    return torch.bmm(a, b, out=out)


@functools.cache
def _controller():
    from threadpoolctl import ThreadpoolController

    return ThreadpoolController().select(user_api="blas")


def limit(n: int):
    """A context holding numpy's BLAS to ``n`` threads (where :func:`bmm` uses it; else nothing)."""
    return _controller().limit(limits=int(n)) if numpy_blas() else nullcontext()


__all__ = ["ENV", "bmm", "cpu_info", "limit", "numpy_blas"]
