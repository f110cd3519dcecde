"""Engines: a cell that fails or is interrupted is handed back as such, and the finished ones are kept."""

from __future__ import annotations

import importlib.util
import sys
import types

import pytest

from torchcal.app.engines import Interrupted, interrupted, run_cells
from torchcal.core.exceptions import ConfigError


def _cell(k: int) -> int:
    if k == 2:
        raise ValueError("cell 2 is broken")
    if k == 4:
        raise KeyboardInterrupt
    return k * k


def test_local_engine_reports_failures_and_keeps_cells_done_before_ctrl_c():
    seen = []
    out = run_cells(_cell, [(k,) for k in range(6)], on_done=lambda i, r: seen.append(i))
    assert out[:2] == [0, 1] and out[3] == 9
    assert isinstance(out[2], ValueError) and "broken" in str(out[2])
    assert all(isinstance(r, Interrupted) for r in out[4:]) and interrupted(out)
    assert seen == [0, 1, 2, 3]  # the interrupted ones never finished
    assert not interrupted(run_cells(_cell, [(0,), (1,)]))


def test_unknown_engine_and_unreachable_ray_name_the_key(monkeypatch):
    with pytest.raises(ConfigError, match="fleet.yaml: key 'fleet.engine': must be one of local, ray"):
        run_cells(_cell, [(0,)], "spark", where="fleet.yaml: key 'fleet.engine'")
    fake = types.ModuleType("ray")
    fake.is_initialized = lambda: False

    def init(**kw):
        raise ConnectionError(f"Failed to connect to Ray cluster at {kw['address']}")

    fake.init = init
    monkeypatch.setitem(sys.modules, "ray", fake)
    import torchcal.app.engines as engines

    with monkeypatch.context() as m:  # an address that accepts connections, where Ray itself then fails
        m.setattr(engines, "_check_reachable", lambda address, where: None)
        with pytest.raises(ConfigError, match="cannot start or reach Ray at 10.0.0.9:6379: ConnectionError"):
            run_cells(_cell, [(0,)], "ray", "10.0.0.9:6379", where="fleet.yaml: key 'fleet.engine'")


def test_an_unreachable_ray_address_fails_at_once_without_asking_ray(monkeypatch):
    """ray.init retries an unreachable cluster for minutes: the address is tried first and named."""
    import socket
    import time

    fake = types.ModuleType("ray")
    fake.is_initialized = lambda: False
    asked = []
    fake.init = lambda **kw: asked.append(kw)
    monkeypatch.setitem(sys.modules, "ray", fake)
    with socket.socket() as sk:  # a port nothing listens on
        sk.bind(("127.0.0.1", 0))
        port = sk.getsockname()[1]
    t0 = time.perf_counter()
    for address in (f"127.0.0.1:{port}", f"ray://127.0.0.1:{port}"):
        with pytest.raises(ConfigError, match=f"key 'fleet.engine': cannot reach the Ray cluster at {address}"):
            run_cells(_cell, [(0,)], "ray", address, where="key 'fleet.engine'")
    assert time.perf_counter() - t0 < 10.0 and not asked
    with pytest.raises(ConfigError, match="'headnode' is not host:port"):
        run_cells(_cell, [(0,)], "ray", "headnode", where="key 'fleet.engine'")


@pytest.mark.skipif(importlib.util.find_spec("ray") is None, reason="Ray not installed (pip install 'torchcal[ray]')")
def test_ray_engine_unwraps_a_cells_own_error():
    """A cell that raised on its worker comes back as its own exception (Ray wraps it with the worker's traceback)."""
    import statistics

    import ray

    ray.init(num_cpus=2, include_dashboard=False, log_to_driver=False)
    try:  # a function the workers can import (this test module is not on their path)
        out = run_cells(statistics.mean, [([1, 1],), ([],), ([3, 5],)], "ray")
    finally:
        ray.shutdown()
    assert out[0] == 1 and out[2] == 4
    assert type(out[1]) is statistics.StatisticsError and "at least one data point" in str(out[1])


def test_ctrl_c_while_ray_starts_or_cells_are_sent_hands_back_every_cell_interrupted(monkeypatch):
    """Interrupted before any cell ran (Ray starting, or the cells being sent): every cell comes back Interrupted,
    so a fleet or sweep still writes its summary (the interrupt used to escape with nothing written), and what was
    sent is cancelled."""
    import torchcal.app.engines as engines

    monkeypatch.setattr(engines, "_check_reachable", lambda address, where: None)
    fake = types.ModuleType("ray")
    state = {"up": False, "shut": 0, "cancelled": []}
    fake.is_initialized = lambda: state["up"]

    def init(**kw):
        state["up"] = True  # half started, then Ctrl-C
        raise KeyboardInterrupt

    def shutdown():
        state["up"], state["shut"] = False, state["shut"] + 1

    fake.init, fake.shutdown = init, shutdown
    monkeypatch.setitem(sys.modules, "ray", fake)
    out = run_cells(_cell, [(0,), (1,), (3,)], "ray")
    assert len(out) == 3 and all(isinstance(r, Interrupted) for r in out) and interrupted(out)
    assert state["shut"] == 1 and not state["up"]

    sent = []

    class _Task:
        def remote(self, *a):
            if len(sent) == 2:
                raise KeyboardInterrupt
            sent.append(a)
            return f"ref{len(sent)}"

    fake.init = lambda **kw: state.update(up=True)
    fake.remote = lambda **kw: (lambda fn: _Task())
    fake.cancel = lambda ref, force: state["cancelled"].append(ref)
    out = run_cells(_cell, [(0,), (1,), (3,)], "ray")
    assert all(isinstance(r, Interrupted) for r in out) and state["cancelled"] == ["ref1", "ref2"]
    assert state["shut"] == 2  # the Ray this call started is shut down
