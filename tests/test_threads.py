"""Thread policy: usable CPUs, the OpenMP wait policy, work-sized thread counts, and the numba cache."""

from __future__ import annotations

import os
import subprocess
import sys
import textwrap

import pytest
import torch

from torchcal.core import threads


def _run(code: str, env=None) -> str:
    out = subprocess.run([sys.executable, "-c", textwrap.dedent(code)], capture_output=True, text=True, env=env,
                         timeout=300)
    assert out.returncode == 0, out.stderr
    return out.stdout.strip()


def test_usable_cpus_follows_the_affinity_mask():
    if not hasattr(os, "sched_setaffinity"):
        pytest.skip("no affinity API")
    cpu = sorted(os.sched_getaffinity(0))[0]
    code = f"""
        import os
        os.sched_setaffinity(0, {{{cpu}}})
        from torchcal.core.threads import usable_cpus
        print(usable_cpus())
    """
    assert _run(code) == "1"


def test_usable_cpus_never_exceeds_the_affinity_mask():
    assert 1 <= threads.usable_cpus() <= len(os.sched_getaffinity(0))


def test_cgroup_quota_caps_the_count(monkeypatch):
    monkeypatch.setattr(threads, "_cgroup_quota", lambda: 1.5)
    assert threads.usable_cpus() == 1
    monkeypatch.setattr(threads, "_cgroup_quota", lambda: None)
    assert threads.usable_cpus() == len(os.sched_getaffinity(0))


def test_import_torchcal_before_torch_makes_openmp_wait_passively():
    env = {k: v for k, v in os.environ.items() if k != "OMP_WAIT_POLICY"}
    assert _run("import torchcal, os; print(os.environ['OMP_WAIT_POLICY'])", env) == "PASSIVE"
    # a user's own choice is kept
    assert _run("import torchcal, os; print(os.environ['OMP_WAIT_POLICY'])", {**env, "OMP_WAIT_POLICY": "active"}) == "active"
    # and torch loaded first is reported: its runtime has read the environment already
    assert _run("import torch, torchcal.core.threads as t, os; os.environ.pop('OMP_WAIT_POLICY', None); "
                "print(t.configure_openmp())", env) == "False"


def test_threads_for_small_work_is_one_and_override_wins():
    threads.set_threads(None)
    assert threads.threads_for(1e6) == 1
    assert threads.threads_for(1e12) == threads.usable_cpus()
    threads.set_threads(3)
    try:
        assert threads.threads_for(1e6) == 3
    finally:
        threads.set_threads(None)
    with pytest.raises(ValueError):
        threads.set_threads(0)


def test_limit_threads_sets_and_restores_torch_threads():
    old = torch.get_num_threads()
    with threads.limit_threads(1) as n:
        assert n == 1 and torch.get_num_threads() == 1
    assert torch.get_num_threads() == old


def test_fused_kernel_is_loaded_from_numba_cache_in_a_new_process():
    """The compiled compensation kernel must come from numba's on-disk cache in a second process
    (closures were recompiled in every process: 10-26 s per CLI run)."""
    from torchcal.compensate import fused

    if not fused.HAVE_NUMBA:
        pytest.skip("numba not available")
    code = """
        import torch, torchcal
        from torchcal.compensate import compensate, fused, fused_targets, newton
        newton.FUSED_MIN_POSES = 0  # a handful of poses would run on the torch ops
        robot = torchcal.load_robot("fanuc_lrmate200i")
        model = torchcal.RobotModel(robot, torch.zeros(1, 3, dtype=torch.float64), orders=1, backlash=True)
        q = torch.zeros(4, 6, dtype=torch.float64) + 0.3
        compensate(model, q, torch.ones_like(q))  # the compiled pass (fused_targets)
        compensate(model, q, torch.ones_like(q), sigma=True)  # the batched solver on the compiled flange
        k = (fused.flange_soa, fused_targets.targets_soa)
        print(sum(sum(f.stats.cache_misses.values()) for f in k), *(sum(f.stats.cache_hits.values()) for f in k))
    """
    _run(code)  # compiles (and writes the cache) if no earlier process did
    misses, hits_flange, hits_pass = map(int, _run(code).split())
    assert misses == 0 and hits_flange >= 1 and hits_pass >= 1


@pytest.mark.parametrize("code, env, warned", [
    ("import torch, torchcal", {}, True),            # torch's OpenMP loaded first: it will spin, said once
    ("import torchcal, torch", {}, False),           # the order the README gives: nothing to say
    ("import torch, torchcal", {"OMP_WAIT_POLICY": "ACTIVE"}, False),  # the user's own choice
])
def test_importing_torch_first_is_said(code, env, warned):
    import os
    import subprocess
    import sys

    base = {k: v for k, v in os.environ.items() if k != "OMP_WAIT_POLICY"}
    r = subprocess.run([sys.executable, "-c", code], env={**base, **env}, capture_output=True, text=True, timeout=120)
    assert r.returncode == 0, r.stderr
    assert ("torch was imported before torchcal" in r.stderr) == warned, r.stderr
