"""The closed measurement loop of Paper III (13)-(16): tracker -> measurement frame -> robot -> sensor mount.

    T_s0^LT0(q) = T_m^LT0 E_0^m F_a(q + v) T_s0^n E_s0^n          (13), (16)

The wrapped :class:`~torchcal.models.robot.RobotModel` supplies T_m^LT0 E_0^m (its
``base``: nominal = the known tracker -> measurement frame transform, times a
small correction, (14)-(15)) and F_a (its joint errors, (3)-(9)); the rig adds
the flange -> sensor ``mount`` T_s0^n E_s0^n (nominal = the measured mount,
times a small correction, (16)) and, for the SmartTRACK sensor's level, the
gravity direction (27) in the tracker frame.

Identifiability: the mount's correction and the constant error terms of the
last joint(s) are partly the same motion. The mount is declared with role
'tool', so the gauge (:func:`torchcal.identify.gauge.fix_gauge`) keeps the
mount and pins the redundant joint terms (frame, then tool, then joints), and
the Prior's frame sigmas apply to it. The robot's own tool vectors are not
used by the rig (its measured point is the sensor origin) and are declared
with an empty mask, i.e. never identified.
"""

from __future__ import annotations

from dataclasses import replace
from typing import Any

import torch
from torch import nn

from ..error_models.frame import FrameCorrection
from ..core.params import DIMENSIONLESS, ParamGroup
from ..measure.gravity import gravity_from_xy

GRAVITY_PRIOR_SIGMA = 0.05
"""Declared prior sigma of (g_x, g_y), dimensionless (about 2.9 deg of tilt), centred on 0 like every
prior: a tracker stands upright on its stand, so gravity is close to its z axis."""


class SensorRig(nn.Module):
    """A robot carrying a 6-DOF sensor, measured by a tracker: Paper III (13)-(16), (27).

    model: the robot's :class:`~torchcal.models.robot.RobotModel` (its ``base`` is
    the measurement frame: robot base in the tracker frame; its tools are not
    used); mount: (4, 4) nominal flange -> sensor transform T_s0^n (m),
    identity by default; gravity: initial (g_x, g_y) or a unit (3,) vector in
    the tracker frame (default (0, 0, 1): tracker z up).

    Parameters (``named_parameters()``): 'model.joint_errors.coef',
    'model.joint_errors.backlash', 'model.base.twist', 'model.tools.delta'
    (declared with an empty mask: not identified), ['model.compliance.coef'],
    'mount.twist' (role 'tool': eps_x, eps_y, eps_z rad, delta_x, delta_y,
    delta_z m, applied on the sensor side, E_s0^n of (16)), 'gravity' ((2,),
    g_x, g_y, dimensionless, role 'gravity', prior :data:`GRAVITY_PRIOR_SIGMA`).

    Example:
        >>> import torch, torchcal
        >>> robot = torchcal.load_robot("fanuc_lrmate200i")
        >>> rig = SensorRig.for_robot(robot, orders=1)
        >>> rig.sensor_pose(torch.zeros(2, 6, dtype=torch.float64)).shape, rig.gravity_vector().tolist()
        (torch.Size([2, 4, 4]), [0.0, 0.0, 1.0])
    """

    def __init__(self, model, mount: torch.Tensor | None = None, gravity=None):
        super().__init__()
        self.model = model
        dtype, device = model.dtype, model.device
        self.mount = FrameCorrection(None if mount is None else torch.as_tensor(mount, dtype=torch.float64)).to(device)
        if self.mount.nominal.shape != (4, 4):
            raise ValueError(f"SensorRig: mount must be a (4, 4) transform, got {tuple(self.mount.nominal.shape)}")
        g = torch.zeros(2, dtype=dtype, device=device)
        if gravity is not None:
            g = torch.as_tensor(gravity, dtype=dtype, device=device)
            if g.shape == (3,):
                from ..measure.gravity import check_gravity

                g = check_gravity(g, "SensorRig(gravity=...)")[:2]
            elif g.shape != (2,) or not bool((g * g).sum() < 1):
                raise ValueError(f"SensorRig: gravity must be (g_x, g_y) with g_x^2 + g_y^2 < 1 or a unit (3,) vector "
                                 f"with positive z, got {g.tolist()}")
        self.gravity = nn.Parameter(g.clone())

    @classmethod
    def for_robot(cls, robot, orders=3, backlash=None, base_nominal=None, mount=None, gravity=None,
                  compliance=False, error_variable=None) -> SensorRig:
        """A rig around a fresh :class:`~torchcal.models.robot.RobotModel` of ``robot`` (one zero tool vector)."""
        from .robot import RobotModel

        model = RobotModel(robot, torch.zeros(1, 3, dtype=torch.float64), orders, backlash,
                           None if base_nominal is None else torch.as_tensor(base_nominal, dtype=torch.float64),
                           compliance=compliance, error_variable=error_variable)
        return cls(model, mount, gravity)

    # ----------------------------------------------------------------- shapes
    @property
    def robot(self):
        return self.model.robot

    @property
    def n(self) -> int:
        return self.model.n

    @property
    def dtype(self) -> torch.dtype:
        return self.model.dtype

    @property
    def device(self) -> torch.device:
        return self.model.device

    @property
    def command_limits(self) -> torch.Tensor:
        return self.model.command_limits

    @property
    def coverage(self):
        """The wrapped model's DirectionCoverage (set by fit(), saved with the spec)."""
        return self.model.coverage

    @coverage.setter
    def coverage(self, value):
        self.model.coverage = value

    # ------------------------------------------------------------- kinematics
    def gravity_vector(self) -> torch.Tensor:
        """Modeled gravity ('up') direction in the tracker frame, (3,), Paper III (27)."""
        return gravity_from_xy(self.gravity)

    def flange(self, q, direction=None, v=None) -> torch.Tensor:
        """Modeled flange pose (B, 4, 4) in the tracker frame: T_m^LT0 E_0^m F_a(q + v)."""
        return self.model.flange(q, direction, v)

    def sensor_pose(self, q, tool=None, direction=None, v=None) -> torch.Tensor:
        """Modeled sensor frame s0 in the tracker frame (B, 4, 4), (13) and (16).

        q: (B, n) commands; tool: ignored (the rig has one measured frame);
        direction: (B, n) approach directions or None; v: (B, n) joint errors or None.
        """
        return self.model.flange(q, direction, v) @ self.mount()

    def forward(self, q, tool=None, direction=None, v=None) -> torch.Tensor:
        """Same as :meth:`sensor_pose`."""
        return self.sensor_pose(q, tool, direction, v)

    def points(self, q, tool=None, direction=None, v=None) -> torch.Tensor:
        """Modeled sensor origin (B, 3) in the tracker frame, (13); lets PointTargets fit the rig on positions."""
        return self.sensor_pose(q, tool, direction, v)[:, :3, 3]

    def nominal_sensor_pose(self, q) -> torch.Tensor:
        """Nominal chain, nominal base and mount, no error terms: (B, 4, 4)."""
        return self.model.base.nominal @ self.model.nominal_flange(q) @ self.mount.nominal

    # -------------------------------------------------------------- Jacobians
    def closed_form(self) -> bool:
        """Whether :meth:`pose_jacobians` hold every term of this rig: not when the wrapped model is a research
        subclass with a term of its own (:meth:`RobotModel.extended`; its chain Jacobians know the paper's terms
        only, and a rig around one was fitted on them silently), nor for a rig subclass that moved the sensor frame
        without writing its own Jacobians. Its instruments then take autograd."""
        if type(self).pose_jacobians is not SensorRig.pose_jacobians:
            return True
        extended = getattr(self.model, "extended", None)
        return type(self).sensor_pose is SensorRig.sensor_pose and not (extended is not None and extended())

    def pose_jacobians(self, q, direction=None, v=None):
        """Sensor poses and their closed-form Jacobians (no autograd: the fixed cost of a small batch stays small).

        q: (B, n); direction: (B, n) or None; v: (B, n) or None.
        -> T (B, 4, 4) sensor frames in the tracker frame, and {name: (B, 6, *shape)} for every
        parameter group of the rig but 'gravity' (which moves no frame), plus 'v' (B, 6, n): rows 0-2 the
        velocity of the sensor origin, rows 3-5 the angular velocity (tracker frame), so that
        dR = S(omega) R. Same chain as :meth:`sensor_pose`, the robot part as in
        :meth:`RobotModel.point_jacobians <torchcal.models.robot.RobotModel.point_jacobians>`.
        """
        from .jacobian import twist_jacobian

        m = self.model
        d = m._parts(q, direction, v)
        M = self.mount()
        T = d["F"] @ M
        p = T[:, :3, 3]
        B = q.shape[0]
        chain = m.chain_jacobians(d, q, p, rows=6)
        J = {"v": chain.pop("v")} | {f"model.{k}": t for k, t in chain.items()}
        J["model.tools.delta"] = q.new_zeros(B, 6, m.tools.count, 3)  # not used by the rig (empty mask)
        ER = self.mount.nominal[:3, :3].T @ M[:3, :3]  # the mount error's rotation, from the frame (no exponential)
        J["mount.twist"] = twist_jacobian(T[:, :3, :3], p, self.mount.twist.expand(B, 6), p, ER)
        return T, J

    # ------------------------------------------------------------- parameters
    def parameter_groups(self) -> list[ParamGroup]:
        """Declarations of every parameter, ``named_parameters()`` order (see the class docstring)."""
        groups = []
        for g in self.model.parameter_groups():
            g = replace(g, name=f"model.{g.name}")
            if g.role == "tool":  # the robot's tool vectors: the rig measures the sensor origin, not tool points
                g = replace(g, mask=torch.zeros_like(g.mask))
            groups.append(g)
        (m,) = self.mount.param_groups("mount")
        groups.append(replace(m, role="tool"))  # gauge: frame, then mount, then joints
        groups.append(ParamGroup("gravity", "gravity", ["gravity.g_x", "gravity.g_y"], [DIMENSIONLESS] * 2,
                                 torch.full((2,), GRAVITY_PRIOR_SIGMA, dtype=torch.float64),
                                 torch.ones(2, dtype=torch.bool)))
        return groups

    # ------------------------------------------------------------ persistence
    def spec(self) -> dict[str, Any]:
        """Structure for :func:`torchcal.io.rundir.save_model`: kind, the robot model's spec, the nominal mount."""
        inner = self.model.spec()
        return {"kind": "sensor_rig", "robot": inner["robot"], "model": inner,
                "mount_nominal": self.mount.nominal.tolist()}

    @classmethod
    def from_spec(cls, spec: dict[str, Any], robot=None) -> SensorRig:
        """Rebuild an (all-zero) rig from :meth:`spec`; load the state dict to restore values."""
        from .robot import RobotModel

        inner = dict(spec["model"])
        inner["robot"] = spec.get("robot", inner["robot"])  # save_model resolves the top-level path
        model = RobotModel.from_spec(inner, robot)
        return cls(model, torch.tensor(spec["mount_nominal"], dtype=torch.float64))


__all__ = ["GRAVITY_PRIOR_SIGMA", "SensorRig"]
