"""What a front end shows of :mod:`torchcal.core.progress`: bars on a terminal, plain lines elsewhere, and run.log.

The library marks its long loops as tasks and never prints. A :class:`ProgressView`,
installed around a command (``with ProgressView(console): ...``, or
:func:`showing`), shows every task started in the block, the library's own and
the pipeline's stages alike:

- on a terminal: a rich progress bar per active task (nested tasks indented,
  gone when they end);
- elsewhere (CI, nohup, a scheduler, output redirected to a file): plain lines
  ``stage > inner stage: k/N, elapsed 12.3 s, ETA 40 s [note]``, one when a task
  advanced (at most one a ``min_interval``) and, from a heartbeat thread, one
  every ``heartbeat`` seconds while a task runs even if nothing advanced (a
  single long fit);
- the same lines, in both cases, to the ``torchcal`` logger: ``run.log`` while
  a run directory's log is open (:func:`torchcal.io.rundir.run_log`).

Stages shorter than ``delay`` seconds print nothing. Lines, the heartbeat and
:meth:`ProgressView.message` (the pipeline's own log lines) share one lock, so no
two lines interleave; :meth:`ProgressView.close` (the end of the ``with`` block,
also on Ctrl-C) stops the heartbeat before it returns and nothing is printed
after it.

Example:
    >>> import io
    >>> from rich.console import Console
    >>> from torchcal.core import progress
    >>> out = io.StringIO()
    >>> with ProgressView(Console(file=out, width=120), logger=None, delay=0.0, min_interval=0.0):
    ...     with progress.task("candidate orders", total=4) as t:
    ...         t.advance(note="order 2")
    >>> "candidate orders: 1/4, elapsed" in out.getvalue()
    True
"""

from __future__ import annotations

import logging
import threading
import time
from contextlib import contextmanager

from ..core import progress
from ..core.progress import Reporter, Task

HEARTBEAT_S = 5.0
"""Seconds between two lines while a task runs without advancing."""

MIN_INTERVAL_S = 1.0
"""Fewest seconds between two lines printed because a task advanced."""

DELAY_S = 2.0
"""A stage prints its first line once it has run this long: short stages stay quiet."""


def format_duration(seconds: float | None) -> str:
    """'12.3 s', '4 min 05 s', '1 h 02 min'; '?' for None (unknown).

    Example:
        >>> format_duration(12.34), format_duration(245), format_duration(3720), format_duration(None)
        ('12.3 s', '4 min 05 s', '1 h 02 min', '?')
    """
    if seconds is None or seconds != seconds:
        return "?"
    s = max(float(seconds), 0.0)
    if s < 59.95:
        return f"{s:.1f} s"
    if s < 3600:
        m, r = divmod(int(round(s)), 60)
        return f"{m} min {r:02d} s"
    h, r = divmod(int(round(s)), 3600)
    return f"{h} h {r // 60:02d} min"


def chain_of(task: Task) -> list[Task]:
    """The task and its parents, outermost first."""
    out: list[Task] = []
    t: Task | None = task
    while t is not None and len(out) < 64:
        out.append(t)
        t = t.parent
    return out[::-1]


def _counting(chain: list[Task]) -> Task | None:
    """The outermost task of a chain with a known total: its k/N and ETA stand for the whole stage."""
    return next((t for t in chain if t.total is not None), None)


def describe(task: Task, final: bool = False) -> str:
    """One plain line for ``task`` and its parents: ``outer > inner: k/N, elapsed E, ETA X [note]``.

    k/N, elapsed and ETA are those of the outermost task with a total (other tasks
    with a total show their k/N after their name); without one, the outermost
    task's elapsed time. The note is the innermost non-empty one. final: the line
    for a finished task (``k/N, done in E``).
    """
    chain = chain_of(task)
    counting = _counting(chain)
    head = " > ".join(t.name + (f" {t.completed}/{t.total}" if t.total is not None and t is not counting else "")
                      for t in chain)
    parts = []
    if counting is not None:
        parts.append(f"{counting.completed}/{counting.total}")
    elif chain[-1].completed:
        parts.append(f"{chain[-1].completed}/?")
    ref = counting if counting is not None else chain[0]
    if final:
        parts.append(f"done in {format_duration(ref.elapsed)}")
    else:
        parts.append(f"elapsed {format_duration(ref.elapsed)}")
        if counting is not None and counting.completed < (counting.total or 0):
            parts.append(f"ETA {format_duration(counting.eta)}")
    note = next((t.note for t in reversed(chain) if t.note), "")
    return f"{head}: {', '.join(parts)}" + (f" [{note}]" if note and not final else "")


class ProgressView(Reporter):
    """A :class:`torchcal.core.progress.Reporter` for the CLI: bars on a terminal, lines elsewhere, lines in the log.

    console: a rich Console (None: no screen output, the logger only); bars: draw
    rich bars (default: when the console is a terminal), else plain lines on the
    console; logger: where the plain lines go as well (a name or a Logger; None:
    nowhere), ``torchcal`` by default, which :func:`torchcal.io.rundir.run_log`
    writes to run.log; heartbeat, min_interval, delay: seconds (see the module
    docstring; None: :data:`HEARTBEAT_S`, :data:`MIN_INTERVAL_S`, :data:`DELAY_S`).
    A finished inner task with a total above 1 that printed a line says ``k/N, done in E``
    (a stage, a task without a parent, has its caller's own 'done' line). Use it
    as a context manager: it installs itself for the block
    (:func:`torchcal.core.progress.reporting`) and :meth:`close` s at the end.
    """

    def __init__(self, console=None, *, bars: bool | None = None, logger: logging.Logger | str | None = "torchcal",
                 heartbeat: float | None = None, min_interval: float | None = None, delay: float | None = None):
        self.console = console
        self.bars = bool(console is not None and (bool(getattr(console, "is_terminal", False)) if bars is None else bars))
        self.logger = logging.getLogger(logger) if isinstance(logger, str) else logger
        # None: the module's defaults, read now (a test may shorten them)
        self.heartbeat = float(HEARTBEAT_S if heartbeat is None else heartbeat)
        self.min_interval = float(MIN_INTERVAL_S if min_interval is None else min_interval)
        self.delay = float(DELAY_S if delay is None else delay)
        self._line_console = console if console is not None and not self.bars else None
        self._lines = self._line_console is not None or self.logger is not None
        self._lock = threading.RLock()
        self._active: list[Task] = []
        self._shown: dict[int, Task] = {}  # tasks a line was printed about (their final line is printed too)
        self._last_line = float("-inf")
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None
        self._closed = False
        self._bar = None  # rich.progress.Progress while a task is active on a terminal
        self._bar_ids: dict[int, int] = {}
        self._installed = None

    # ------------------------------------------------------------ lifecycle
    def __enter__(self) -> "ProgressView":
        self._installed = progress.reporting(self)
        self._installed.__enter__()
        return self

    def __exit__(self, *exc) -> None:
        try:
            self.close()
        finally:
            cm, self._installed = self._installed, None
            if cm is not None:
                cm.__exit__(*exc)

    def close(self) -> None:
        """Stop the heartbeat and the bars; nothing is shown after this returns (idempotent)."""
        with self._lock:
            if self._closed:
                return
            self._closed = True
            self._stop.set()
            bar, self._bar = self._bar, None
            thread = self._thread
        if thread is not None and thread is not threading.current_thread():
            thread.join(timeout=5.0)
        if bar is not None:
            bar.stop()

    @property
    def closed(self) -> bool:
        return self._closed

    # ------------------------------------------------------- Reporter events
    def start(self, task: Task) -> None:
        with self._lock:
            if self._closed:
                return
            self._active.append(task)
            if self.bars:
                self._bar_add(task)
            if self._lines and self._thread is None:
                self._thread = threading.Thread(target=self._beat, name="torchcal-progress-heartbeat", daemon=True)
                self._thread.start()

    def update(self, task: Task) -> None:
        with self._lock:
            if self._closed:
                return
            if self.bars:
                self._bar_update(task)
            if not self._lines:
                return
            now = time.perf_counter()
            if now - self._last_line < self.min_interval or now - chain_of(task)[0].started < self.delay:
                return
            shown = self._deepest_under(task)  # a stage's note while a loop inside it runs: show the loop too
            self._emit(describe(shown), shown, now)

    def end(self, task: Task) -> None:
        with self._lock:
            for i in range(len(self._active) - 1, -1, -1):
                if self._active[i] is task:
                    del self._active[i]
                    break
            if self._closed:
                return
            if self.bars:
                self._bar_remove(task)
            shown = self._shown.pop(id(task), None) is task
            # a finished inner loop of several items says so once; a stage (no parent) has its own 'done' line
            if (shown and self._lines and task.total is not None and task.total > 1 and task.parent is not None
                    and _counting(chain_of(task)) is task):
                self._emit(describe(task, final=True), None, time.perf_counter())

    # ------------------------------------------------------------ output
    def message(self, text: str, markup: bool = True) -> None:
        """Print one of the front end's own lines (e.g. the pipeline's log lines) on the console, never in the
        middle of a progress line. Not logged: the caller logs its own lines."""
        if self.console is None:
            return
        with self._lock:
            self.console.log(text, markup=markup)

    def note(self, text: str) -> None:
        """:func:`torchcal.core.progress.note`: a library's line for the console (it logs the line itself)."""
        self.message(text, markup=False)

    def _emit(self, line: str, task: Task | None, now: float) -> None:
        """Print and log one line (the lock is held)."""
        self._last_line = now
        if task is not None:
            for t in chain_of(task):
                self._shown[id(t)] = t
        if self._line_console is not None:
            try:
                self._line_console.log(line, markup=False, highlight=False)
            except Exception:  # a closed or broken stream must not cost the run
                pass
        if self.logger is not None:
            self.logger.info(line)

    def _deepest_under(self, task: Task) -> Task:
        """The most recently started running task inside ``task`` (``task`` itself when none)."""
        for t in reversed(self._active):
            if t is task or any(p is task for p in chain_of(t)):
                return t
        return task

    def _beat(self) -> None:
        """The heartbeat thread: a line for the innermost running task when none was printed for ``heartbeat`` s."""
        tick = max(min(self.heartbeat / 4.0, 0.5), 0.005)
        while not self._stop.wait(tick):
            with self._lock:
                if self._closed:
                    return
                if not self._active:
                    continue
                task = self._active[-1]
                now = time.perf_counter()
                if now - max(self._last_line, chain_of(task)[0].started) >= self.heartbeat:
                    try:
                        self._emit(describe(task), task, now)
                    except Exception:  # the heartbeat must never die of a logging handler's error
                        pass

    # --------------------------------------------------------------- bars
    def _bar_add(self, task: Task) -> None:
        if self._bar is None:
            from rich.progress import BarColumn, Progress, SpinnerColumn, TextColumn, TimeElapsedColumn

            self._bar = Progress(SpinnerColumn(), TextColumn("{task.description}", markup=False), BarColumn(),
                                 TextColumn("{task.fields[count]}"), TimeElapsedColumn(),
                                 TextColumn("{task.fields[eta]}"), TextColumn("{task.fields[note]}", markup=False),
                                 console=self.console, transient=True, refresh_per_second=4)
        if not self._bar.live.is_started:
            self._bar.start()
        depth = len(chain_of(task)) - 1
        self._bar_ids[id(task)] = self._bar.add_task("  " * depth + task.name, total=task.total,
                                                     completed=task.completed, **_bar_fields(task))

    def _bar_update(self, task: Task) -> None:
        tid = self._bar_ids.get(id(task))
        if tid is not None and self._bar is not None:
            self._bar.update(tid, total=task.total, completed=task.completed, **_bar_fields(task))

    def _bar_remove(self, task: Task) -> None:
        tid = self._bar_ids.pop(id(task), None)
        if tid is not None and self._bar is not None:
            self._bar.remove_task(tid)
            if not self._bar_ids:
                self._bar.stop()


def _bar_fields(task: Task) -> dict:
    """The text columns of a task's bar: k/N (k alone without a total), 'ETA ...' once known, the note."""
    count = f"{task.completed}/{task.total}" if task.total is not None else (f"{task.completed}" if task.completed else "")
    eta = task.eta if task.total is not None and task.completed < task.total else None
    return {"count": count, "eta": "" if eta is None else f"ETA {format_duration(eta)}", "note": task.note}


def installed_reporter() -> Reporter | None:
    """The reporter :func:`torchcal.core.progress.reporting` installed for the current context, or None."""
    getter = getattr(progress, "current_reporter", None)  # not in torchcal.core.progress's API (yet): its context variable
    return getter() if getter is not None else progress._REPORTER.get()


def current_view() -> ProgressView | None:
    """The :class:`ProgressView` installed for the current context, or None."""
    rep = installed_reporter()
    return rep if isinstance(rep, ProgressView) else None


@contextmanager
def showing(console=None, **options):
    """A :class:`ProgressView` on ``console`` for the block, unless a reporter is installed already.

    Yields the view in charge: the installed one when it is a ProgressView (the
    CLI's), a new one when there is none (closed at the end), None when the caller
    installed a reporter of its own (it decides what to show).
    """
    rep = installed_reporter()
    if rep is not None:
        yield rep if isinstance(rep, ProgressView) else None
        return
    with ProgressView(console, **options) as view:
        yield view


__all__ = ["DELAY_S", "HEARTBEAT_S", "MIN_INTERVAL_S", "ProgressView", "chain_of", "current_view", "describe",
           "format_duration", "installed_reporter", "showing"]
