"""What produced a run: versions.json's record (package versions, git commit and a hash of torchcal's own source,
the CPU, threads and the environment that sets them, the command line) and the files' sha256. Split from
:mod:`torchcal.io.rundir`, which re-exports these names and writes a deliverable's provenance sidecar from them."""

from __future__ import annotations

import functools
import platform
import subprocess
import sys
from datetime import datetime
from importlib import metadata
from pathlib import Path

import torch


def _version(dist: str) -> str | None:
    try:
        return metadata.version(dist)
    except metadata.PackageNotFoundError:
        return None


def git_commit(folder=None) -> dict | None:
    """{'commit', 'dirty'} of the git checkout holding ``folder`` (default: torchcal's source), or None."""
    folder = Path(folder or Path(__file__).resolve().parent.parent)
    try:
        commit = subprocess.run(["git", "-C", str(folder), "rev-parse", "HEAD"], capture_output=True, text=True, timeout=5)
        if commit.returncode != 0:
            return None
        status = subprocess.run(["git", "-C", str(folder), "status", "--porcelain", "--untracked-files=no"],
                                capture_output=True, text=True, timeout=10)
        return {"commit": commit.stdout.strip(), "dirty": bool(status.stdout.strip()) if status.returncode == 0 else None}
    except (OSError, subprocess.SubprocessError):
        return None


THREAD_ENV = ("OMP_NUM_THREADS", "MKL_NUM_THREADS", "OPENBLAS_NUM_THREADS", "NUMBA_NUM_THREADS", "OMP_WAIT_POLICY",
              "TORCHCAL_BLAS", "CUDA_VISIBLE_DEVICES")
"""Environment variables that change a run's last bits (thread counts, the BLAS a product goes through) or its
device: recorded when set (OMP_NUM_THREADS=1 alone changed 42 values of a metrics.json)."""


def collect_versions(device=None) -> dict:
    """What produced a run: interpreter, platform, package versions, git commit and a hash of torchcal's own
    source, compute device and CPU, the threads and the environment that choose them, the command line."""
    import os
    import shlex

    from ..core.blas import numpy_blas

    dev = torch.device(device or "cpu")
    try:
        cpus = len(os.sched_getaffinity(0))
    except (AttributeError, OSError):
        cpus = os.cpu_count()
    return {**_process_versions(), "device": str(dev),
            "device_name": torch.cuda.get_device_name(dev) if dev.type == "cuda" else _cpu_name(),
            "host": platform.node(), "cpus_available": cpus, "torch_threads": torch.get_num_threads(),
            "cpu_products": _cpu_products(numpy_blas),
            "environment": {k: os.environ[k] for k in THREAD_ENV if k in os.environ},
            "command": shlex.join(sys.argv),
            "created": datetime.now().astimezone().isoformat(timespec="seconds")}


def _cpu_products(numpy_blas) -> str:
    try:
        return "numpy BLAS" if numpy_blas() else "torch"
    except ValueError as exc:  # a bad TORCHCAL_BLAS: the run that uses it says so; the record says what was set
        return f"unknown ({exc})"


@functools.cache
def _cpu_name() -> str:
    """The CPU's model name, else what platform knows (read once a process: a fleet writes a record per unit)."""
    from ..core.blas import cpu_info

    return cpu_info("model name") or platform.processor() or platform.machine()


def file_sha256(path) -> str:
    """sha256 (hex) of a file's bytes."""
    import hashlib

    h = hashlib.sha256()
    with open(path, "rb") as fh:
        for block in iter(lambda: fh.read(1 << 20), b""):
            h.update(block)
    return h.hexdigest()


@functools.cache
def source_sha256() -> str:
    """sha256 over torchcal's own source files (paths and contents): which code ran, where a plain install has no
    git checkout and the version string is the same for every commit. Once a process, as :func:`_process_versions`:
    what was imported is what runs (the report read every source file again per page)."""
    import hashlib

    root = Path(__file__).resolve().parent.parent
    h = hashlib.sha256()
    for p in sorted(root.rglob("*.py")):
        h.update(p.relative_to(root).as_posix().encode())
        h.update(p.read_bytes())
    return h.hexdigest()


@functools.cache
def _process_versions() -> dict:
    """collect_versions' part that is fixed once a process has imported its packages: read once, as a fleet writes
    one versions.json per unit (reading the package metadata and asking git took 80 ms a unit, 8 s of a 100-unit
    run; what was imported is what ran, whatever is installed or committed since)."""
    return {
        "python": sys.version.split()[0],
        "platform": platform.platform(),
        "torchcal": _version("torchcal"),
        "torch": torch.__version__,
        "numpy": _version("numpy"),
        "scipy": _version("scipy"),
        "pandas": _version("pandas"),
        "omegaconf": _version("omegaconf"),
        "pytorch_kinematics": _version("pytorch-kinematics") or _version("pytorch_kinematics"),
        "yourdfpy": _version("yourdfpy"),
        # the compiled kernels and the distributed engine change results' last bits and timings (None: not installed)
        "numba": _version("numba"),
        "ray": _version("ray"),
        "git": git_commit(),
        "torchcal_source": str(Path(__file__).resolve().parent.parent),
        "torchcal_source_sha256": source_sha256(),
    }
