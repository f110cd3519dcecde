"""Each paper of the dissertation in one place: what it specifies, equation by equation, and where that lives.

The package is organized by what the code does (kinematics, error models, identification, compensation,
instruments, files), because the three papers share most of it: Paper III's sensor rig is Paper II's robot
model measured differently, Paper I's slope constraint is a penalty block of the same solver. A reader who
starts from a paper starts here instead:

- :mod:`torchcal.papers.paper1_machine_tool`: Paper I, machine tools (axis perturbation model, slope
  constraint, BORDER, compensation tables);
- :mod:`torchcal.papers.paper2_robot`: Paper II, robots (joint-dependent Chebyshev errors, maximum
  likelihood, order selection, compensation);
- :mod:`torchcal.papers.paper3_sensor`: Paper III, 6-DOF sensors and online identification (tracker
  covariance, the SmartTRACK sensor, the measurement loop, adaptive updates).

Each module's docstring is the equation -> function map, and the module re-exports those functions and
classes under their own names, so ``from torchcal.papers.paper2_robot import RobotModel, fit, compensate``
reads as the paper does. Nothing is defined here: the definitions stay where the layers put them.
"""
