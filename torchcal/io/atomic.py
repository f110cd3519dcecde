"""Writing outputs safely: whole files or nothing, and never over an input or (without --force) an earlier result.

Every file torchcal writes goes through :func:`atomic_path`: the content goes to a
hidden temporary file in the target's own folder (the same filesystem, so the
final ``os.replace`` is atomic) and only a complete file replaces the target. A
write that fails (read-only or full filesystem, Ctrl-C, a crash) leaves the
earlier file as it was and no temporary behind; an OS failure becomes one
:class:`WriteError` naming the path and the operating system's reason.

:func:`check_output` is the command line's overwrite policy: an output that is
also an input is refused, an existing one needs ``--force``.
"""

from __future__ import annotations

import os
import secrets
from contextlib import contextmanager
from pathlib import Path

from ..core.exceptions import TorchcalError


class WriteError(TorchcalError, ValueError):
    """An output that could not be written (read-only or full filesystem, ...); names the path and the OS reason."""


class OutputExistsError(TorchcalError, ValueError):
    """An output that exists already (no --force) or that is also an input; names the file."""


def _reason(exc: BaseException) -> str:
    if isinstance(exc, OSError) and exc.strerror:
        return exc.strerror
    return f"{type(exc).__name__}: {exc}"


@contextmanager
def atomic_path(path):
    """Yield a temporary path beside ``path``; when the block ends normally it replaces ``path`` in one step.

    The temporary keeps ``path``'s suffix (writers that pick a format from it, e.g.
    matplotlib, still work). Creates the folder. On any failure the temporary is
    removed and ``path`` is untouched; OSError / RuntimeError (torch.save reports a
    full disk as ``RuntimeError``) become :class:`WriteError`.
    """
    path = Path(path)
    tmp = None
    try:
        path.parent.mkdir(parents=True, exist_ok=True)
        tmp = path.with_name(f".{path.stem}.{secrets.token_hex(4)}.tmp{path.suffix}")
        # O_EXCL: never reuse someone else's file; mode 0o666 lets the umask decide, as a plain open() would
        os.close(os.open(tmp, os.O_WRONLY | os.O_CREAT | os.O_EXCL, 0o666))
        yield tmp
        os.replace(tmp, path)
        tmp = None
    except BaseException as exc:
        if tmp is not None:
            try:
                tmp.unlink(missing_ok=True)
            except OSError:
                pass
        if isinstance(exc, (OSError, RuntimeError)) and not isinstance(exc, TorchcalError):
            raise WriteError(f"{path}: not written ({_reason(exc)})") from exc
        raise


def atomic_write_text(path, text: str, encoding: str = "utf-8") -> Path:
    """Write ``text`` to ``path`` atomically (see :func:`atomic_path`); returns the path."""
    path = Path(path)
    with atomic_path(path) as tmp:
        tmp.write_text(text, encoding=encoding)
    return path


def _same_file(a: Path, b: Path) -> bool:
    try:
        if a.resolve() == b.resolve():
            return True
        return a.exists() and b.exists() and os.path.samefile(a, b)
    except OSError:
        return False


def check_output(path, force: bool = False, inputs=(), flag: str = "--force") -> Path:
    """The overwrite policy of the file-writing commands, checked before any work is done.

    Refuses (:class:`OutputExistsError`) an output that is one of ``inputs``
    (paths compared resolved: the input would be lost), a folder where a file
    goes, and an existing file unless ``force``.
    """
    path = Path(path)
    for src in inputs:
        if src is not None and _same_file(Path(src), path):
            raise OutputExistsError(f"{path}: is also the input {src}; write the output to another file")
    if path.is_dir():
        raise OutputExistsError(f"{path}: is a folder; give the output file's name")
    if (path.exists() or path.is_symlink()) and not force:
        raise OutputExistsError(f"{path}: already exists; pass {flag} to overwrite it or choose another output file")
    return path


__all__ = ["OutputExistsError", "WriteError", "atomic_path", "atomic_write_text", "check_output"]
