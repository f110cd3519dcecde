"""numba's cache as torchcal reads it (torchcal.core.compiled) and `torchcal compile` (torchcal.app.compile).

Each cache check runs in a fresh interpreter with its own NUMBA_CACHE_DIR: numba reads that directory when a
cached function is created, so a process can only be asked about a cache it started with."""

from __future__ import annotations

import os
import subprocess
import sys
import textwrap

import pytest
from typer.testing import CliRunner

from torchcal.app.compile import compile_kernels
from torchcal.cli import app
from torchcal.compensate import fused

pytestmark = pytest.mark.skipif(not fused.HAVE_NUMBA, reason="numba's cache needs numba")

KERNEL = """
import numba

HAVE_NUMBA = True


@numba.njit(cache=True)
def k(x):
    return x + {add}


@numba.njit  # not cached: the process has it, the disk never will
def j(x):
    return x - 1
"""


def _python(code: str, cache, path, timeout=300) -> subprocess.CompletedProcess:
    env = dict(os.environ, NUMBA_CACHE_DIR=str(cache), PYTHONPATH=os.pathsep.join([str(path), os.environ.get("PYTHONPATH", "")]))
    return subprocess.run([sys.executable, "-c", textwrap.dedent(code)], env=env, capture_output=True, text=True,
                          timeout=timeout)


PROBE = """
import logging, sys
logging.basicConfig(stream=sys.stderr, level=logging.WARNING, format="%(message)s")
from torchcal.core import compiled
import kmod
compiled.FAMILIES["probe"] = ("kmod", ("k",), "a moment")
print("before", compiled.cold("probe"), compiled.cached(kmod.k))
compiled.notice("probe")
compiled.notice("probe")  # once a process
print("value", kmod.k(1.0))
print("after", compiled.cold("probe"), compiled.cached(kmod.k))
print("on disk", compiled.cached(kmod.k, on_disk=True))
kmod.j(1.0)
print("uncached", compiled.cached(kmod.j), compiled.cached(kmod.j, on_disk=True))
"""


def test_a_kernel_is_cold_until_compiled_then_cached_across_processes_until_its_source_changes(tmp_path):
    cache, src = tmp_path / "cache", tmp_path / "src"
    src.mkdir()
    (src / "kmod.py").write_text(KERNEL.format(add=1))
    first = _python(PROBE, cache, src)
    assert first.returncode == 0, first.stderr
    assert "before ['k'] False" in first.stdout and "value 2.0" in first.stdout and "after [] True" in first.stdout
    assert "on disk True" in first.stdout  # numba wrote it
    assert "uncached True None" in first.stdout  # in this process, but nothing on disk to read back
    assert first.stderr.count("compiling torchcal's probe kernels for this CPU (k)") == 1, first.stderr
    # a new process finds the machine code on disk before any call, and says nothing
    second = _python(PROBE, cache, src)
    assert second.returncode == 0, second.stderr
    assert "before [] True" in second.stdout and "compiling" not in second.stderr
    # a changed source makes the cached code stale: cold again (numba's own stamp test)
    (src / "kmod.py").write_text(KERNEL.format(add=2) + "\n# changed\n")
    third = _python(PROBE, cache, src)
    assert "before ['k'] False" in third.stdout and "value 3.0" in third.stdout, third.stdout + third.stderr


def test_compile_builds_a_family_into_an_empty_cache_in_a_worker_process(tmp_path):
    """The warm-up of the flange family (the quickest to compile) runs in a spawned worker and leaves the kernel in
    the cache the calling process reads: before it, the family is cold; after it, it is not, and a second call
    only reports it."""
    out = _python("""
        from torchcal.app.compile import compile_kernels
        from torchcal.core.compiled import cold
        print("before", cold("flange"))
        first = compile_kernels(["flange"], jobs=1)
        print("first", [(c.family, c.missing, c.error) for c in first])
        print("after", cold("flange"))
        again = compile_kernels(["flange"], jobs=1)
        print("again", [(c.family, c.missing, c.error, c.seconds) for c in again])
    """, tmp_path / "cache", tmp_path, timeout=600)
    assert out.returncode == 0, out.stderr
    assert "before ['flange_soa']" in out.stdout
    assert "first [('flange', ['flange_soa'], None)]" in out.stdout
    assert "after []" in out.stdout
    assert "again [('flange', [], None, 0.0)]" in out.stdout  # nothing to do: no worker started
    assert "compiling torchcal's" not in out.stderr  # the workers stay quiet: the caller reports


def test_unknown_families_are_refused_by_name():
    with pytest.raises(ValueError, match="bogus.*known: targets, position, fleet, damped, flange"):
        compile_kernels(["fleet", "bogus"])
    res = CliRunner().invoke(app, ["compile", "--only", "fleet,bogus"])
    assert res.exit_code == 2
    assert "unknown kernel families bogus" in res.output and "known: targets, position, fleet, damped, flange" in res.output
    res = CliRunner().invoke(app, ["compile", "--jobs", "0"])
    assert res.exit_code == 2 and "--jobs 0" in res.output


def test_without_numba_there_is_nothing_to_compile_and_nothing_is_wrong(monkeypatch):
    monkeypatch.setattr(fused, "HAVE_NUMBA", False)
    with pytest.raises(RuntimeError, match="TORCHCAL_NO_NUMBA"):
        compile_kernels()
    res = CliRunner().invoke(app, ["compile"])
    assert res.exit_code == 0 and "nothing to compile" in res.output and "torch forms run instead" in res.output


def test_the_cold_compile_notice_reaches_the_console_of_a_front_end(monkeypatch):
    """The notice is logged (run.log) and handed to the installed progress reporter (the CLI's console), once."""
    import io

    from rich.console import Console

    from torchcal.core import compiled, progress
    from torchcal.io.progress_view import ProgressView

    monkeypatch.setitem(compiled.FAMILIES, "probe2", ("kmod", ("k",), "a moment"))
    monkeypatch.setattr(compiled, "cold", lambda family: ["k"])
    monkeypatch.setattr(compiled, "_NOTICED", set())
    out = io.StringIO()
    view = ProgressView(Console(file=out, width=300), bars=False, logger=None)
    with progress.reporting(view):
        compiled.notice("probe2")
        compiled.notice("probe2")
    assert out.getvalue().count("compiling torchcal's probe2 kernels for this CPU (k)") == 1, out.getvalue()
