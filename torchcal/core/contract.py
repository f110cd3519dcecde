"""The model contract: what a calibrated model offers, as :class:`typing.Protocol` s.

Three models are identified: the robot's joint-dependent error model
(:class:`torchcal.models.robot.RobotModel`, Paper II), the machine tool's axis
perturbation model (:class:`torchcal.models.machine.MachineModel`, Paper I) and the
6-DOF sensor rig (:class:`torchcal.models.sensor_rig.SensorRig`, Paper III). Each
implements :class:`CalibratedModel` (predict what the instrument sees, its
parameter groups, a spec to rebuild it); each *capability* beyond that is a
protocol of its own, in the manner of theseus' ``CostFunction``: a consumer
asks :func:`require` for the capability it needs, and a model that lacks it is
refused with a message that says what the model is and what to do instead,
not with an ``AttributeError`` from deep inside.

    >>> import torch, torchcal
    >>> model = torchcal.RobotModel(torchcal.load_robot("fanuc_lrmate200i"), torch.zeros(1, 3, dtype=torch.float64))
    >>> isinstance(model, CalibratedModel), capabilities(model)
    (True, ['predict points', 'compensate commands'])
"""

from __future__ import annotations

from typing import Any, Protocol, runtime_checkable

import torch


@runtime_checkable
class CalibratedModel(Protocol):
    """Every identified model: the prediction the fit compares with the measurements, its parameters."""

    def points(self, q: torch.Tensor, tool=None, direction=None, v=None) -> torch.Tensor:
        """(B, 3) what the instrument measures of each row, measurement frame, metres."""
        ...

    def flange(self, q: torch.Tensor, direction=None, v=None) -> torch.Tensor:
        """(B, 4, 4) the modeled flange (or spindle / sensor carrier) pose."""
        ...

    def parameter_groups(self) -> list:
        """The identified parameters (:class:`torchcal.core.params.ParamGroup`): names, roles, priors, masks."""
        ...

    def spec(self) -> dict[str, Any]:
        """What rebuilds the model's structure (``from_spec``); the values are its state dict."""
        ...


@runtime_checkable
class PredictsPoints(CalibratedModel, Protocol):
    """Tool points of controller commands, modeled and nominal (``torchcal predict``)."""

    def nominal_points(self, q: torch.Tensor, tool) -> torch.Tensor:
        """(B, 3) the nominal chain's tool points."""
        ...


@runtime_checkable
class CompensatesCommands(PredictsPoints, Protocol):
    """Joint-space compensation, Paper II (46)-(52): a joint-error series on a robot chain."""

    robot: Any

    def flange_snapshot(self) -> Any:
        """The chain and its error series frozen for the fast flange backends
        (:class:`torchcal.kinematics.snapshot.ChainSnapshot`)."""
        ...

    def nominal_flange(self, q: torch.Tensor) -> torch.Tensor:
        ...


@runtime_checkable
class ExportsTables(PredictsPoints, Protocol):
    """Per-axis error tables for a controller (Paper I, ``torchcal export-tables``): axis error series."""

    axis_errors: Any


CAPABILITIES: dict[str, type] = {
    "predict points": PredictsPoints,
    "compensate commands": CompensatesCommands,
    "export tables": ExportsTables,
}
"""Capability name -> the protocol a model must implement for it."""

def _instead(model, capability: str, has: list[str]) -> str:
    """What to do instead, for the kind of model at hand."""
    if capability == "compensate commands":
        if "export tables" in has:
            return "A machine tool is compensated by its axis tables: torchcal export-tables, torchcal.compensate.tables."
        if hasattr(model, "sensor_pose"):
            return ("A sensor rig (Paper III) calibrates the sensor on the robot, not the robot's commands; fit the "
                    "robot from point measurements to compensate it.")
        return "Compensation solves Paper II (46)-(52) for a RobotModel."
    if capability == "export tables":
        return ("Tables are written for machine tools (model.kind: axis_perturbation); a robot is compensated by "
                "torchcal compensate.")
    if capability == "predict points":
        return "A sensor rig predicts sensor poses: SensorRig.sensor_pose (torchcal predict writes them)."
    return ""


def _members(proto: type) -> set[str]:
    """The attributes and methods a protocol (and the protocols it extends) declares."""
    out: set[str] = set()
    for cls in proto.__mro__:
        if cls in (Protocol, object) or not getattr(cls, "_is_protocol", False):
            continue
        out |= set(getattr(cls, "__annotations__", {}))
        out |= {k for k, v in vars(cls).items() if callable(v) and not k.startswith("_")}
    return out


def implements(model, proto: type) -> bool:
    """Whether ``model`` has every member of ``proto``, looked up as attribute access does.

    isinstance() with a runtime-checkable protocol looks members up statically from Python 3.12 on, and so
    misses what an ``nn.Module`` keeps in its registries (a submodule such as ``joint_errors``)."""
    return all(hasattr(model, name) for name in _members(proto))


def capabilities(model) -> list[str]:
    """The capabilities (:data:`CAPABILITIES`) ``model`` implements, in that order."""
    return [name for name, proto in CAPABILITIES.items() if implements(model, proto)]


def require(model, capability: str, who: str | None = None) -> None:
    """Raise TypeError unless ``model`` implements ``capability`` (a key of :data:`CAPABILITIES`).

    The message names the model, what it can do, and the way to do the asked thing for it.

    Example:
        >>> require(object(), "compensate commands", "compensate")  # doctest: +ELLIPSIS
        Traceback (most recent call last):
        ...
        TypeError: compensate: object cannot compensate commands (it has none of: ...). Compensation solves ...
    """
    try:
        proto = CAPABILITIES[capability]
    except KeyError:
        raise ValueError(f"require: unknown capability {capability!r}; one of {', '.join(CAPABILITIES)}") from None
    if implements(model, proto):
        return
    has = capabilities(model)
    can = f"it can: {', '.join(has)}" if has else f"it has none of: {', '.join(CAPABILITIES)}"
    if hasattr(model, "sensor_pose"):  # predict works on it: it predicts poses, not points (a user read "none")
        can = "it predicts sensor poses (torchcal predict), not tool points" + (f"; it can: {', '.join(has)}" if has else "")
    raise TypeError(f"{who or 'torchcal'}: {type(model).__name__} cannot {capability} ({can}). "
                    f"{_instead(model, capability, has)}".rstrip())


__all__ = ["CAPABILITIES", "CalibratedModel", "CompensatesCommands", "ExportsTables", "PredictsPoints",
           "capabilities", "implements", "require"]
