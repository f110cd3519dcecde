"""One root for every error torchcal raises on purpose.

``except torchcal.TorchcalError`` catches bad input files, configs, robots and
run directories alike; each concrete class also derives from the builtin it
refines (``ValueError``, ``FileNotFoundError``) so older ``except ValueError``
code keeps working.
"""

from __future__ import annotations


class TorchcalError(Exception):
    """Base class of every torchcal exception (bad input, config, robot, run directory).

    Example:
        >>> import torchcal
        >>> try:
        ...     torchcal.load_robot("no_such_robot")
        ... except torchcal.TorchcalError as exc:
        ...     print(type(exc).__name__)
        URDFError
    """


class ConfigError(TorchcalError, ValueError):
    """A config that cannot be used; the message names the file (or override) and the key."""


class InputError(TorchcalError, ValueError):
    """An argument of a library call that cannot be used (its shape, dtype, device or values); the message
    names the call and the argument."""

