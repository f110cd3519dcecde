"""A fleet solved as independent streams side by side (torchcal.identify.fleet.fit_fleet's streams)."""

from __future__ import annotations

import threading

import pytest
import torch

import torchcal
import torchcal.sim
from torchcal.core import progress, threads
from torchcal.identify import streams as streams_mod
from torchcal.identify import fleet_kernel
from torchcal.identify.fleet import FleetProblem, fit_fleet, fleet_streams
from torchcal.sim.fleet import fleet_truths

TOOLS = torch.tensor([[0.033, 0.058, 0.161], [0.057, -0.034, 0.161]], dtype=torch.float64)

pytestmark = pytest.mark.skipif(not fleet_kernel.available("cpu"), reason="streams run on the compiled kernels")


@pytest.fixture(scope="module")
def fleet():
    robot = torchcal.load_robot("fanuc_lrmate200i")
    noise = torchcal.NoiseModel.from_robot(robot)
    truths = fleet_truths(robot, TOOLS, 7, 2, [3]).truths
    q = torchcal.sim.quasi_random_commands(robot.joint_map.limits, 40, 5)
    g = torch.Generator().manual_seed(5)
    dirs = torch.where(torch.rand(q.shape, generator=g, dtype=torch.float64) > 0.5, 1.0, -1.0)
    units = [torchcal.simulate(t, q, [0, 1], noise, 50 + k, directions=dirs) for k, t in enumerate(truths)]

    def make():
        return torchcal.RobotModel(robot, TOOLS, orders=2, backlash=True)

    return make, units, noise


def test_streams_land_where_one_solve_lands_and_repeat_bit_for_bit(fleet, monkeypatch):
    """Three streams (7 units: shares of 2, 3, 2) reach every unit's optimum of the single solve, in the same
    iterations, each stream on its own thread with one torch thread; a second run is identical bit for bit."""
    make, units, noise = fleet
    one = fit_fleet(make, units, noise, streams=1)
    seen = []
    real = streams_mod.solve_batched

    def spy(bp, *a, **k):
        seen.append((bp.M, threading.current_thread().name, torch.get_num_threads()))
        return real(bp, *a, **k)

    monkeypatch.setattr(streams_mod, "solve_batched", spy)
    three = fit_fleet(make, units, noise, streams=3)
    again = fit_fleet(make, units, noise, streams=3)
    assert sorted(m for m, _, _ in seen[:3]) == [2, 2, 3]
    assert len({name for _, name, _ in seen[:3]}) == 3 and all(name.startswith("torchcal-fleet") for _, name, _ in seen)
    assert all(t == 1 for _, _, t in seen)
    assert torch.equal(three.batch.x, again.batch.x)
    assert [r.nit for r in three.results] == [r.nit for r in again.results]
    scale = one.batch.x.abs().amax(1, keepdim=True)
    assert float(((three.batch.x - one.batch.x).abs() / scale).max()) < 1e-7
    assert float(((three.batch.fun - one.batch.fun) / one.batch.fun).abs().max()) < 1e-9
    assert [r.nit for r in three.results] == [r.nit for r in one.results]
    assert all(r.success for r in three.results)
    # every unit's model holds its own fit: the stream wrote it, in the fleet's order
    for m, r in zip(three.models, three.results):
        assert torch.equal(FleetProblem(make, [units[0]], noise, models=[m]).start()[0][three.batch.keep[0]], r.x)


def test_the_streams_share_one_progress_task(fleet):
    """Every unit is counted once on the fleet's task, whichever stream finished it, and each note names its
    stream."""
    make, units, noise = fleet
    done, notes = [], set()

    class Keep(progress.Reporter):
        def update(self, task):
            notes.add(task.note.split(":")[0])

        def end(self, task):
            done.append((task.name, task.completed, task.total))

    with progress.reporting(Keep()):
        fit_fleet(make, units, noise, streams=2)
    assert ("fitting the fleet's units together", len(units), len(units)) in done
    assert notes == {"stream 1/2", "stream 2/2"}


def test_how_many_streams(fleet, monkeypatch):
    """One per thread the solve may use, at least STREAM_MIN_UNITS (4) units each, on the CPU's compiled factored
    path only."""
    make, units, noise = fleet
    fp = FleetProblem(make, units * 3, noise)  # 21 units
    old = threads.get_override()
    try:
        threads.set_threads(8)
        assert fleet_streams(fp) == 5  # 21 // 4
        threads.set_threads(1)
        assert fleet_streams(fp) == 1
        threads.set_threads(2)
        assert fleet_streams(fp) == 2
        assert fleet_streams(FleetProblem(make, units, noise)) == 1  # 7 units: one share of 4 and 3 would not do
        assert fleet_streams(FleetProblem(make, units + units[:1], noise)) == 2  # 8 units
        assert fleet_streams(FleetProblem(make, units * 3, noise, dense_normal=True)) == 1
        monkeypatch.setattr(fleet_kernel, "available", lambda device: False)
        assert fleet_streams(fp) == 1
    finally:
        threads.set_threads(old)


def _recording(real, outcomes, before=None):
    """solve_batched that records how each stream ended ('done' or the exception's type name)."""

    def run(bp, *a, **k):
        try:
            if before is not None:
                before(bp)
            out = real(bp, *a, **k)
        except BaseException as exc:
            outcomes.append((bp.M, type(exc).__name__))
            raise
        outcomes.append((bp.M, "done"))
        return out

    return run


def test_a_failing_stream_is_raised_and_stops_the_others(fleet, monkeypatch):
    """A stream that fails raises its error from fit_fleet, as one solve would, and the other streams stop at
    their next iteration (Cancelled) instead of finishing work whose result is lost."""
    import time

    make, units, noise = fleet
    outcomes = []
    started = threading.Barrier(3)

    def before(bp):
        started.wait(timeout=30)
        if bp.M == 3:
            raise FloatingPointError("stream broke")
        time.sleep(0.2)  # the failure is surely seen before the healthy streams' first iteration

    monkeypatch.setattr(streams_mod, "solve_batched", _recording(streams_mod.solve_batched, outcomes, before))
    with pytest.raises(FloatingPointError, match="stream broke"):
        fit_fleet(make, units, noise, streams=3)
    assert sorted(outcomes) == [(2, "Cancelled"), (2, "Cancelled"), (3, "FloatingPointError")]


def test_an_interrupt_stops_every_stream(fleet, monkeypatch):
    """Ctrl-C while the streams run (KeyboardInterrupt in the waiting thread) stops them all and propagates."""
    make, units, noise = fleet
    outcomes = []
    monkeypatch.setattr(streams_mod, "solve_batched", _recording(streams_mod.solve_batched, outcomes))

    def interrupted(*a, **k):
        raise KeyboardInterrupt

    monkeypatch.setattr(streams_mod, "wait", interrupted)
    with pytest.raises(KeyboardInterrupt):
        fit_fleet(make, units, noise, streams=2)
    assert sorted(outcomes) == [(3, "Cancelled"), (4, "Cancelled")]
