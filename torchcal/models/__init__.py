"""The calibrated models: what a fit identifies and what compensation, prediction and export use.

- :mod:`torchcal.models.robot`: :class:`RobotModel`, Paper II's measurement model (25) of a robot.
- :mod:`torchcal.models.machine`: :class:`MachineModel`, Paper I's axis perturbation model (2)-(12).
- :mod:`torchcal.models.sensor_rig`: :class:`SensorRig`, Paper III's tracker -> robot -> 6-DOF sensor loop (13)-(16).
- :mod:`torchcal.models.jacobian`: their closed-form Jacobians (Paper II (34)-(45), (56)-(77)).

All three keep one contract, :mod:`torchcal.core.contract`. This package imports none of its
modules on purpose: they sit on different floors (the sensor rig uses the instruments of
:mod:`torchcal.measure`, which use the robot model), so ``import torchcal.models`` stays cycle-free;
import the module you need (``from torchcal.models.robot import RobotModel``) or use the facade
(``torchcal.RobotModel``).
"""
