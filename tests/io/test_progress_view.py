"""The CLI's progress front end: plain lines (k/N, elapsed, ETA) off a terminal, a heartbeat, run.log, bars on a terminal."""

import io
import logging
import re
import threading
import time

import pytest
from rich.console import Console

from torchcal.core import progress
from torchcal.io import progress_view
from torchcal.io.progress_view import ProgressView, describe, format_duration, showing
from torchcal.io.rundir import run_log
from torchcal.app.fit import Progress


def plain_console(out):
    """What a redirected stderr looks like to rich: not a terminal."""
    return Console(file=out, width=200, force_terminal=False, highlight=False, log_path=False)


class Lines(logging.Handler):
    def __init__(self):
        super().__init__(logging.INFO)
        self.lines = []

    def emit(self, record):
        self.lines.append(record.getMessage())


@pytest.fixture
def logged():
    """The lines the view sends to the 'torchcal' logger (what run.log receives)."""
    logger = logging.getLogger("torchcal")
    handler, old = Lines(), logger.level
    logger.addHandler(handler)
    logger.setLevel(logging.INFO)
    yield handler.lines
    logger.removeHandler(handler)
    logger.setLevel(old)


def wait_for(predicate, timeout=3.0):
    t0 = time.perf_counter()
    while not predicate():
        if time.perf_counter() - t0 > timeout:
            return False
        time.sleep(0.01)
    return True


def test_format_and_describe():
    assert [format_duration(x) for x in (0.04, 12.34, 61, 245, 3720, None)] == [
        "0.0 s", "12.3 s", "1 min 01 s", "4 min 05 s", "1 h 02 min", "?"]
    outer = progress.Task("choosing orders", started=time.perf_counter() - 30.0)
    inner = progress.Task("candidate orders", total=4, completed=1, note="orders [2, 2]", parent=outer,
                          started=time.perf_counter() - 10.0)
    line = describe(inner)
    # k/N, elapsed and ETA of the counting task (10 s for 1 of 4 -> 30 s left), the chain, the note
    assert re.fullmatch(r"choosing orders > candidate orders: 1/4, elapsed 10\.0 s, ETA 30\.0 s \[orders \[2, 2\]\]", line), line
    leaf = progress.Task("LM", note="iteration 3", parent=inner)
    assert describe(leaf).startswith("choosing orders > candidate orders > LM: 1/4, elapsed 10.0 s, ETA 30.0 s")
    assert describe(leaf).endswith("[iteration 3]")
    # no total anywhere: the stage's elapsed time, no ETA
    assert re.fullmatch(r"choosing orders: elapsed 30\.0 s", describe(outer))
    inner.completed = 4
    assert re.fullmatch(r"choosing orders > candidate orders: 4/4, done in 10\.0 s", describe(inner, final=True))


def test_plain_lines_have_count_elapsed_and_eta():
    out = io.StringIO()
    with ProgressView(plain_console(out), logger=None, delay=0.0, min_interval=0.0, heartbeat=60.0) as view:
        assert not view.bars
        with progress.task("candidate orders", total=4) as t:
            for k in range(3):
                time.sleep(0.02)
                t.advance(note=f"order {k}")
    text = out.getvalue()
    lines = [l for l in text.splitlines() if "candidate orders" in l]
    assert len(lines) == 3, text
    for k, line in enumerate(lines):
        assert re.search(rf"candidate orders: {k + 1}/4, elapsed \d+\.\d s, ETA \d+\.\d s \[order {k}\]", line), line


def test_lines_are_rate_limited_and_short_stages_quiet():
    out = io.StringIO()
    with ProgressView(plain_console(out), logger=None, delay=0.0, min_interval=30.0, heartbeat=60.0):
        with progress.task("fast loop", total=50) as t:
            for _ in range(50):
                t.advance()
    assert out.getvalue().count("fast loop") == 1  # the first advance only: at most one line a min_interval
    out = io.StringIO()
    with ProgressView(plain_console(out), logger=None, delay=30.0, min_interval=0.0, heartbeat=60.0):
        with progress.task("short stage", total=5) as t:
            for _ in range(5):
                t.advance()
    assert out.getvalue() == ""  # shorter than the delay: nothing


def test_heartbeat_reports_a_stage_that_does_not_advance_and_stops_with_the_block(logged):
    out = io.StringIO()
    with ProgressView(plain_console(out), delay=0.0, min_interval=0.0, heartbeat=0.05) as view:
        with progress.task("one long fit"):
            assert wait_for(lambda: out.getvalue().count("one long fit: elapsed") >= 2), out.getvalue()
        thread = view._thread
    assert thread is not None and not thread.is_alive()  # stopped (and joined) when the block ended
    after = out.getvalue()
    time.sleep(0.2)  # four heartbeats
    assert out.getvalue() == after  # nothing printed after the block
    assert [l for l in logged if l.startswith("one long fit: elapsed")]  # the same lines in the log


def test_heartbeat_is_quiet_between_tasks():
    out = io.StringIO()
    with ProgressView(plain_console(out), logger=None, delay=0.0, min_interval=0.0, heartbeat=0.03):
        with progress.task("stage"):
            pass
        time.sleep(0.15)  # no task running: no heartbeat
    assert out.getvalue() == ""


def test_run_log_gets_the_pipeline_stages_and_library_tasks(tmp_path):
    """A pipeline step around a fake library loop (as order selection reports it): lines on the console, in run.log."""
    out = io.StringIO()
    console = plain_console(out)
    with run_log(tmp_path), ProgressView(console, delay=0.0, min_interval=0.0, heartbeat=0.05):
        p = Progress(console)
        with p.step("choosing Chebyshev orders"):
            with progress.task("candidate orders", total=3) as t:
                for k in range(3):
                    p.update(f"uniform: orders {[k] * 6} -> 0.0{k} mm")
                    time.sleep(0.02)
                    t.advance()
            # a long step that reports nothing: the heartbeat covers it
            assert wait_for(lambda: out.getvalue().count("choosing Chebyshev orders: elapsed") >= 1), out.getvalue()
        p.info("orders chosen")
    log = (tmp_path / "run.log").read_text()
    for text in (log, out.getvalue()):
        assert re.search(r"choosing Chebyshev orders > candidate orders: [123]/3, elapsed \d+\.\d s", text), text
        assert "candidate orders: 3/3, done in" in text  # the inner loop's last line
        # the stage's note, set while the loop inside it runs, shows with the loop's count
        assert re.search(r"choosing Chebyshev orders > candidate orders: 0/3, elapsed \d+\.\d s, ETA \? "
                         r"\[uniform: orders \[0, 0, 0, 0, 0, 0\] -> 0\.00 mm\]", text), text
        assert re.search(r"choosing Chebyshev orders: elapsed \d+\.\d s", text)  # heartbeat
        assert "choosing Chebyshev orders done in" in text and "orders chosen" in text
    assert re.search(r"INFO choosing Chebyshev orders > candidate orders: \d/3, elapsed .*ETA", log), log


def test_lines_never_interleave_with_the_pipelines_own(tmp_path):
    """Heartbeat lines and the pipeline's lines from two threads: every line whole (one lock)."""
    out = io.StringIO()
    console = plain_console(out)
    with ProgressView(console, logger=None, delay=0.0, min_interval=0.0, heartbeat=0.001):
        p = Progress(console)
        with progress.task("busy stage"):
            for k in range(300):
                p.info(f"pipeline line {k}")
    lines = out.getvalue().splitlines()
    assert sum("busy stage: elapsed" in l for l in lines) > 0
    assert all(("pipeline line" in l) != ("busy stage" in l) for l in lines), "a line mixes two messages"


def test_terminal_renders_bars_and_logs_plain_lines(logged):
    out = io.StringIO()
    console = Console(file=out, width=100, force_terminal=True)
    with ProgressView(console, delay=0.0, min_interval=0.0, heartbeat=60.0) as view:
        assert view.bars
        with progress.task("identifying the model"):
            with progress.task("candidate orders", total=3) as t:
                t.advance(note="orders [1, 1]")
                view._bar.refresh()
                t.advance()
            view._bar.refresh()
    text = out.getvalue()
    assert "identifying the model" in text and "candidate orders" in text and "orders [1, 1]" in text
    assert "\x1b[" in text  # drawn with terminal control codes, not as plain lines
    assert not re.search(r"candidate orders: \d/3, elapsed", text)
    assert any(re.search(r"candidate orders: 1/3, elapsed .*ETA", l) for l in logged)  # run.log still has lines


def test_showing_reuses_the_installed_view_and_respects_other_reporters():
    with ProgressView(None, logger=None) as outer:
        with showing(plain_console(io.StringIO())) as view:
            assert view is outer
    with progress.reporting(progress.Reporter()):
        with showing(None) as view:
            assert view is None
    with showing(None, logger=None) as view:
        assert isinstance(view, ProgressView) and progress_view.current_view() is view
    assert view.closed and progress_view.current_view() is None


def test_no_output_after_close_even_if_tasks_go_on():
    out = io.StringIO()
    view = ProgressView(plain_console(out), logger=None, delay=0.0, min_interval=0.0, heartbeat=0.02)
    with view:
        t_cm = progress.task("left running", total=10)
        t = t_cm.__enter__()
    # the block ended while the task still runs (e.g. an interrupt unwinding): nothing more, no thread left
    n = len(out.getvalue())
    t.advance()
    time.sleep(0.1)
    assert len(out.getvalue()) == n
    assert not any(th.name == "torchcal-progress-heartbeat" and th.is_alive() for th in threading.enumerate())
    t_cm.__exit__(None, None, None)
