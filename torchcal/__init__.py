"""torchcal: volumetric error calibration and compensation of industrial robots, in PyTorch.

The main API at the top level (imported on first use, so ``import torchcal``
stays light: torch loads when a function needs it)::

    import torchcal  # before torch: its OpenMP threads then sleep rather than spin (torchcal.core.threads)

    robot = torchcal.load_robot("fanuc_lrmate200i")                # bundled, a joint-map YAML or a URDF
    data = torchcal.read_measurements("ident.csv", robot, n_tools=3)  # CSV contract (mm, deg) -> SI
    model = torchcal.RobotModel(robot, tools_m, orders=6, backlash=True)
    result = torchcal.fit(model, data)  # maximum likelihood, in place; noise: the robot's own repeatability
    q_new = torchcal.compensate(model, q, direction).q                # compensated commands (rad)

Config-driven runs: ``torchcal.run_fit(torchcal.load_config("fit.yaml"))``
(what ``torchcal fit`` does). Every error torchcal raises on purpose (bad data,
robot, config, run directory) is a :class:`TorchcalError`.

``torchcal.compensate`` is the subpackage of that name, made callable as its
function: ``torchcal.compensate(model, q)`` == ``torchcal.compensate.compensate(model, q)``.
"""

from __future__ import annotations

import sys
import types
from importlib import import_module

from .core.threads import WAIT_POLICY as _WAIT_POLICY
from .core.threads import configure_openmp as _configure_openmp

# before anything loads torch: OpenMP threads that wait sleep instead of spinning (torchcal.core.threads says why)
_policy_chosen = _WAIT_POLICY in __import__("os").environ
if not _configure_openmp() and not _policy_chosen:
    # measured beside one busy process on 2 cores: a 6-model batched fit 5.7-7.3 s against 3.5-4.1 s, 100 000
    # compensated poses 1.0-1.7 s against 0.8-0.9 s
    __import__("warnings").warn(
        "torch was imported before torchcal: torch's OpenMP threads keep spinning while they wait, which makes "
        "torchcal 1.2-1.8x slower when another process is busy on the machine; import torchcal first, or set "
        f"{_WAIT_POLICY}=PASSIVE before starting Python", RuntimeWarning, stacklevel=2)

from .core.exceptions import TorchcalError as TorchcalError  # noqa: E402  (re-exported)

_LAZY = {
    # robots and models
    "load_robot": ("torchcal.kinematics", "load_robot"),
    "Robot": ("torchcal.kinematics", "Robot"),
    "Repeatability": ("torchcal.kinematics", "Repeatability"),
    "RobotModel": ("torchcal.models.robot", "RobotModel"),
    # data
    "Measurements": ("torchcal.core.measurements", "Measurements"),
    "read_measurements": ("torchcal.io.csv", "read_measurements"),
    "write_measurements": ("torchcal.io.csv", "write_measurements"),
    # identification
    "fit": ("torchcal.identify", "fit"),
    "NoiseModel": ("torchcal.identify", "NoiseModel"),
    "Prior": ("torchcal.identify", "Prior"),
    "FitResult": ("torchcal.identify", "FitResult"),
    "identifiability": ("torchcal.analysis.identifiability", "identifiability"),
    "align": ("torchcal.identify.alignment", "align"),  # the measurement frame / tools on the nominal chain
    "PointTargets": ("torchcal.measure", "PointTargets"),
    # Paper III: 6-DOF measurement and online identification
    "SensorRig": ("torchcal.models.sensor_rig", "SensorRig"),
    "STSInstrument": ("torchcal.measure", "STSInstrument"),
    "PoseInstrument": ("torchcal.measure", "PoseInstrument"),
    "TrackerNoise": ("torchcal.measure", "TrackerNoise"),
    "read_pose_measurements": ("torchcal.io.sensor_csv", "read_pose_measurements"),
    "OnlineCalibration": ("torchcal.identify.online", "OnlineCalibration"),
    # Paper I: machine tools, the slope constraint, compensation tables
    "MachineModel": ("torchcal.models.machine", "MachineModel"),
    "fit_constrained": ("torchcal.identify.constrained", "fit_constrained"),
    "auto_constraint": ("torchcal.identify.constrained", "auto_constraint"),
    "compensation_tables": ("torchcal.compensate.tables", "compensation_tables"),
    "ParamGroup": ("torchcal.core.params", "ParamGroup"),
    # backlash: what the data cover, how far direction and position are confounded
    "DirectionCoverage": ("torchcal.core.coverage", "DirectionCoverage"),
    "backlash_confounding": ("torchcal.analysis.confounding", "backlash_confounding"),
    # compensation, simulation, planning
    "compensate": ("torchcal.compensate", None),  # the subpackage, callable as its compensate()
    "compensate_targets": ("torchcal.compensate.targets", "compensate_targets"),
    "seeds_for_flags": ("torchcal.compensate.flags", "seeds_for_flags"),
    "configuration_flags": ("torchcal.compensate.flags", "configuration_flags"),
    # fleets: many units of one type
    "fit_fleet": ("torchcal.identify.fleet", "fit_fleet"),
    "CompensationResult": ("torchcal.compensate", "CompensationResult"),
    "simulate": ("torchcal.sim", "simulate"),
    "sim": ("torchcal.sim", None),  # the simulators' subpackage (quasi_random_commands, fleets), as examples use it
    "TruthRobot": ("torchcal.sim", "TruthRobot"),
    "plan_poses": ("torchcal.analysis.planning", "plan_poses"),
    # config-driven runs
    "load_config": ("torchcal.app.config", "load_config"),
    "run_fit": ("torchcal.app.fit", "run_fit"),
    "load_model": ("torchcal.io.rundir", "load_model"),
    # errors
    "URDFError": ("torchcal.kinematics.urdf", "URDFError"),
    "DataError": ("torchcal.io.csv", "DataError"),
    "ConfigError": ("torchcal.app.config", "ConfigError"),
    "RunDirError": ("torchcal.io.rundir", "RunDirError"),
}
"""Top-level name -> (module, attribute), imported on first access."""

__all__ = sorted([*_LAZY, "TorchcalError", "__version__"])


def _version() -> str:
    from importlib.metadata import PackageNotFoundError, version

    try:
        return version("torchcal")
    except PackageNotFoundError:  # a source tree that was never installed
        return "0+unknown"


def __getattr__(name: str):
    if name in _LAZY:
        module, attr = _LAZY[name]
        value = import_module(module) if attr is None else getattr(import_module(module), attr)
        globals()[name] = value  # cache: the next access is a plain attribute
        return value
    if name == "__version__":
        value = _version()
        globals()[name] = value
        return value
    raise AttributeError(f"module 'torchcal' has no attribute '{name}'")


def __dir__():
    # the public names and the subpackages loaded so far, not this module's own imports (sys, types, ...)
    return sorted(set(__all__) | {k for k, v in globals().items() if isinstance(v, types.ModuleType)
                                  and not k.startswith("_") and k not in ("sys", "types")})


class _CallableModule(types.ModuleType):
    """The subpackage ``torchcal.compensate``, callable as its function: ``torchcal.compensate(model, q)``
    is ``torchcal.compensate.compensate(model, q)``; attribute access and imports are unchanged."""

    def __call__(self, *args, **kwargs):
        return self.compensate(*args, **kwargs)

    @property
    def __wrapped__(self):  # inspect.signature / help() show the function's signature
        return self.compensate


class _Package(types.ModuleType):
    """The package module: binding the subpackage ``compensate`` (the import system does it on first
    import) makes it callable as the function of the same name."""

    def __setattr__(self, name, value):
        if name == "compensate" and type(value) is types.ModuleType:
            value.__class__ = _CallableModule
        super().__setattr__(name, value)


sys.modules[__name__].__class__ = _Package
_sub = sys.modules.get(__name__ + ".compensate")
if _sub is not None and type(_sub) is types.ModuleType:  # imported before this module ran (reload)
    _sub.__class__ = _CallableModule
del _sub
