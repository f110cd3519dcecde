"""Where the independent cells of a fleet or a sweep run: this process, or Ray tasks.

An engine runs ``fn(*args)`` for every cell and hands back, per cell, what it
returned or the exception it raised: a cell that fails is the caller's to
report, and never stops the others. ``local`` runs the cells one after the
other in this process; ``ray`` sends each to a Ray task (a local Ray started
for the call, the cluster at ``address``, or the Ray already initialized by
the caller), with Ray's own scheduling and transport and no retries (a cell
that failed once fails the same way again: its reason is what the user needs).

Both engines run the same function on the same arguments, so the callers
make a Ray run compute what a local run computes: they pass every cell the
CPU thread count of its solve (a different count sums in another order, and a
Ray worker starts with one thread).
"""

from __future__ import annotations

from collections.abc import Callable, Sequence

from ..core.exceptions import ConfigError, TorchcalError

ENGINES = ("local", "ray")
"""``fleet.engine`` / ``sweep.engine``: where the cells are fitted."""


class Interrupted(TorchcalError):
    """What a cell that had not finished when the run was interrupted (Ctrl-C) hands back: the cells done by then
    are kept, and the caller writes them before it lets the interrupt end the run."""


def check_engine(engine: str, where: str) -> None:
    """Refuse (:class:`ConfigError` naming ``where``) an unknown engine, or ``ray`` where Ray is not installed:
    checked before a run directory is made, so that a missing extra leaves nothing behind."""
    if engine not in ENGINES:
        raise ConfigError(f"{where}: must be one of {', '.join(ENGINES)}, got {engine!r}")
    if engine == "ray":
        import importlib.util
        import sys

        if "ray" not in sys.modules and importlib.util.find_spec("ray") is None:
            raise ConfigError(f"{where}: ray needs Ray installed (pip install 'torchcal[ray]')")


def run_cells(fn: Callable, args: Sequence[tuple], engine: str = "local", address: str | None = None,
              where: str = "key 'engine'", on_done: Callable[[int, object], None] | None = None) -> list:
    """``fn(*a)`` for every ``a`` in ``args`` on ``engine`` -> per cell its result or the exception it raised.

    fn: a module-level function (Ray pickles it by reference); args: one tuple per cell, picklable;
    address: engine ray: the cluster (None: the Ray this process has initialized, else a local one started
    for the call, or RAY_ADDRESS); where: the config file and key named when Ray is missing; on_done(i, result or
    exception): called as each cell finishes (the progress bar), in the order they finish. Ctrl-C: the cells
    not finished by then hand back :class:`Interrupted` (Ray's are cancelled) and the finished ones their results.

    Example:
        >>> run_cells(divmod, [(7, 2), (1, 0)])[0]
        (3, 1)
    """
    check_engine(engine, where)
    done = on_done or (lambda i, r: None)
    if engine == "local":
        out: list = []
        try:
            for i, a in enumerate(args):
                try:
                    out.append(fn(*a))
                except Exception as exc:  # a failing cell is reported by the caller; the others go on
                    out.append(exc)
                done(i, out[-1])
        except KeyboardInterrupt:
            out += [_interrupted() for _ in range(len(args) - len(out))]
        return out
    try:
        import ray
    except ImportError:
        raise ConfigError(f"{where}: ray needs Ray installed (pip install 'torchcal[ray]')") from None
    started = not ray.is_initialized()
    if started:
        _check_reachable(address, where)
        try:
            ray.init(address=address, include_dashboard=False, log_to_driver=False)
        except KeyboardInterrupt:  # Ctrl-C while Ray starts: no cell ran; the caller still writes its summary
            if ray.is_initialized():
                ray.shutdown()
            return [_interrupted() for _ in args]
        except Exception as exc:  # an unreachable cluster: one line naming it, before any cell is sent
            raise ConfigError(f"{where}: cannot start or reach Ray"
                              + (f" at {address}" if address else "") + f": {type(exc).__name__}: {exc}") from None
    try:
        task = ray.remote(max_retries=0, num_cpus=1)(fn)
        refs = []
        try:
            for a in args:
                refs.append(task.remote(*a))
        except KeyboardInterrupt:  # Ctrl-C while the cells are sent: none has been waited for
            for ref in refs:
                ray.cancel(ref, force=True)
            return [_interrupted() for _ in args]
        place = {ref: i for i, ref in enumerate(refs)}
        out = [None] * len(refs)
        pending = list(refs)
        try:
            while pending:
                ready, pending = ray.wait(pending, num_returns=1)
                i = place[ready[0]]
                try:
                    out[i] = ray.get(ready[0])
                except Exception as exc:  # a cell that failed on its worker: its own exception where Ray kept it
                    out[i] = task_error(exc)
                done(i, out[i])
        except KeyboardInterrupt:
            for ref in pending:
                ray.cancel(ref, force=True)
            out = [_interrupted() if r is None else r for r in out]
        return out
    finally:
        if started:
            ray.shutdown()


REACH_TIMEOUT_S = 5.0
"""Seconds to wait for a cluster's address to accept a connection before Ray is asked (ray.init retries an
unreachable GCS for minutes, printing its own errors, while nothing else moves)."""


def _check_reachable(address: str | None, where: str) -> None:
    """A ConfigError naming ``address`` ('host:port' or 'ray://host:port') when nothing accepts a TCP connection
    there within :data:`REACH_TIMEOUT_S`; None, 'auto' and 'local' are Ray's to resolve."""
    if not address or address in ("auto", "local"):
        return
    import socket

    hostport = address.split("://", 1)[-1].rstrip("/")
    host, _, port = hostport.rpartition(":")
    if not host or not port.isdigit():
        raise ConfigError(f"{where}: Ray address '{address}' is not host:port (or ray://host:port)")
    try:
        socket.create_connection((host.strip("[]"), int(port)), timeout=REACH_TIMEOUT_S).close()
    except OSError as exc:
        raise ConfigError(f"{where}: cannot reach the Ray cluster at {address}: {exc} (is it running, and is the "
                          "port open from here?)") from None


def _interrupted() -> Interrupted:
    return Interrupted("interrupted (Ctrl-C) before this cell finished")


def interrupted(results: list) -> bool:
    """Whether :func:`run_cells` was interrupted (some cell handed back :class:`Interrupted`)."""
    return any(isinstance(r, Interrupted) for r in results)


def task_error(exc: Exception) -> Exception:
    """The exception a Ray task raised, unwrapped from Ray's RayTaskError where Ray kept it (its message would
    otherwise carry the worker's whole traceback); anything else (a worker that died) as Ray raised it."""
    cause = getattr(exc, "cause", None)
    return cause if isinstance(cause, Exception) else exc


__all__ = ["ENGINES", "Interrupted", "check_engine", "interrupted", "run_cells", "task_error"]
