"""Progress of long stages, reported by the library and shown by whoever runs it.

The library marks its long loops with :func:`task` (a name, a total, one
:meth:`Task.advance` per finished item); it never prints. A front end
installs a :class:`Reporter` for a block with :func:`reporting` and decides
how to show it: the CLI shows a bar on a terminal and plain lines (stage,
k/N, elapsed, ETA) elsewhere, and writes the same lines to ``run.log``.
Without a reporter a task costs a few attribute updates.

Example:
    >>> from torchcal.core import progress
    >>> seen = []
    >>> class Keep(progress.Reporter):
    ...     def update(self, task):
    ...         seen.append((task.name, task.completed, task.total))
    >>> with progress.reporting(Keep()):
    ...     with progress.task("candidate orders", total=2) as t:
    ...         t.advance()
    ...         t.advance()
    >>> seen[-1]
    ('candidate orders', 2, 2)
"""

from __future__ import annotations

import time
from contextlib import contextmanager
from contextvars import ContextVar
from dataclasses import dataclass, field


@dataclass
class Task:
    """One long stage: ``completed`` of ``total`` items (total None: unknown), a free-text ``note``."""

    name: str
    total: int | None = None
    completed: int = 0
    note: str = ""
    started: float = field(default_factory=time.perf_counter)
    parent: "Task | None" = None
    _reporter: "Reporter | None" = field(default=None, repr=False)

    @property
    def elapsed(self) -> float:
        return time.perf_counter() - self.started

    @property
    def eta(self) -> float | None:
        """Seconds left at the rate so far (None until an item finished or without a total)."""
        if self.total is None or self.completed <= 0:
            return None
        return self.elapsed / self.completed * max(self.total - self.completed, 0)

    def advance(self, n: int = 1, note: str | None = None) -> None:
        self.completed += n
        if note is not None:
            self.note = note
        if self._reporter is not None:
            self._reporter.update(self)

    def set_total(self, total: int | None) -> None:
        self.total = total
        if self._reporter is not None:
            self._reporter.update(self)

    def set_note(self, note: str) -> None:
        self.note = note
        if self._reporter is not None:
            self._reporter.update(self)


class Reporter:
    """Receives task events; subclass and override what you show. All methods default to nothing."""

    def start(self, task: Task) -> None:
        pass

    def update(self, task: Task) -> None:
        pass

    def end(self, task: Task) -> None:
        pass


_REPORTER: ContextVar[Reporter | None] = ContextVar("torchcal_progress_reporter", default=None)
_CURRENT: ContextVar[Task | None] = ContextVar("torchcal_progress_task", default=None)


@contextmanager
def reporting(reporter: Reporter | None):
    """Send the progress of every task started in the block to ``reporter`` (None: nowhere)."""
    token = _REPORTER.set(reporter)
    try:
        yield reporter
    finally:
        _REPORTER.reset(token)


def note(text: str) -> None:
    """A line for whoever watches (a cold compile that stalls a bar for a minute): handed to the installed
    reporter's ``note(text)`` where it has one, else nowhere (the caller logs its own lines)."""
    say = getattr(_REPORTER.get(), "note", None)
    if callable(say):
        say(text)


@contextmanager
def task(name: str, total: int | None = None):
    """A long stage of ``total`` items; yields the :class:`Task` to advance. Nested tasks know their parent."""
    rep = _REPORTER.get()
    t = Task(name, total, parent=_CURRENT.get(), _reporter=rep)
    token = _CURRENT.set(t)
    if rep is not None:
        rep.start(t)
    try:
        yield t
    finally:
        _CURRENT.reset(token)
        if rep is not None:
            rep.end(t)
