"""How far a fit's residual lies beyond what its noise model explains.

Under the fit's own noise model a row's residual r (3,) at the identified
parameters has E|r|^2 = 3 sigma_m^2 + sum_j |J_v,j|^2 var_j: the tracker per
axis, and each joint's repeatability through its column of the point Jacobian
(Paper II's joint positioning error). The ratio

    rho = sqrt(mean_rows |r|^2 / mean_rows E|r|^2)

is about 1 or below for a model that holds every systematic error (below: the
parameters take part of the identification rows' misfit, and a datasheet's
repeatability is a bound). Far above it the model lacks an error source (arm
sag without ``model.compliance``, too low an order, thermal drift between
sessions) or the instrument and robot scatter more than the config says; either
way the maximum-likelihood weights and the Laplace standard deviations, which
assume the noise model, are off by about rho. On a helper's KUKA truth with a
gravity sag fitted without compliance rho was 2.2 (identification) / 2.8
(validation), where its truths without the sag (or the fit with compliance) gave 0.2-0.4.
"""

from __future__ import annotations

from typing import NamedTuple

import torch

NOISE_RATIO_WARN = 2.0
"""rho above which ``torchcal fit`` warns (the validation set's where there is one)."""


class NoiseCheck(NamedTuple):
    """:func:`noise_ratio`'s answer: ``ratio`` rho, and ``sigma_m`` (m) the tracker sigma per axis that, with the
    joints' repeatability as given, would explain the rows' mean squared residual (0 where the joints' part alone
    exceeds it)."""

    ratio: float
    sigma_m: float


def noise_ratio(model, data, noise, distance: torch.Tensor) -> NoiseCheck | None:
    """rho of rows ``data`` whose modeled residuals have lengths ``distance`` (R,) m, under ``noise``
    (:class:`~torchcal.identify.NoiseModel`: ``sigma_m`` m, ``joint_variance(direction)`` (R, n)).

    None where the model gives no closed-form point Jacobians (a sensor rig, a research subclass): the joint
    term cannot be taken cheaply there.

    Example:
        >>> import torch, torchcal
        >>> robot = torchcal.load_robot("fanuc_lrmate200i")
        >>> model = torchcal.RobotModel(robot, torch.zeros(1, 3, dtype=torch.float64), orders=0)
        >>> q = torch.zeros(4, 6, dtype=torch.float64)
        >>> data = torchcal.Measurements.from_tensors(q, torch.zeros(4, dtype=torch.long), torch.zeros(4, 3))
        >>> noise = torchcal.NoiseModel.from_robot(robot)
        >>> check = noise_ratio(model, data, noise, torch.full((4,), 1e-3, dtype=torch.float64))
        >>> check.ratio > 10.0  # 1 mm against 5 um of tracker noise and the joints' repeatability
        True
    """
    jac = getattr(model, "point_jacobians", None)
    closed = getattr(model, "closed_form", None)
    if jac is None or (closed is not None and not closed()) or len(data) == 0:
        return None
    direction = data.direction if data.has_direction else torch.zeros_like(data.q)
    with torch.no_grad():
        _, J = jac(data.q, data.tool, direction if data.has_direction else None)
        var = noise.joint_variance(direction.to(J["v"]))
        joints = (J["v"] ** 2 * var[:, None, :]).sum((1, 2)).mean()
        d = distance.to(joints)
        seen = (d * d).mean()
        ratio = float((seen / (3.0 * noise.sigma_m ** 2 + joints)).sqrt())
        return NoiseCheck(ratio, float(((seen - joints).clamp(min=0.0) / 3.0).sqrt()))


__all__ = ["NOISE_RATIO_WARN", "NoiseCheck", "noise_ratio"]
