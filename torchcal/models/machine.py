"""The calibrated machine tool: nominal chain driven by perturbed commands, Paper I (2)-(12).

``MachineModel`` is Paper I's measurement model (8)-(10) with the axis
perturbation model (2)-(7): the position of tool t measured in the tracker
frame for the command q is

    p = T_mf E_mf F_nom(q + dq(q) + v) p_tl,t       (12), p_tl,t = l_t + delta_t  (10)

T_mf E_mf is :class:`~torchcal.error_models.FrameCorrection` (nominal T_mf and
the 6-DOF correction (9)); the tool vectors are a
:class:`~torchcal.error_models.ToolSet` whose corrections are, by default,
only along the tool axis (the paper's delta_t of (10); ``tool_terms='xyz'``
frees all three); v are the axis positioning errors of the implicit loop
(11)-(12). v enters as (12) writes it: added to the perturbed command, while
the tables dq are evaluated at the command q itself (the controller looks the
tables up at the command it was given). Several tools per command are rows of
the data with the same q.

It mirrors the surface of :class:`torchcal.models.robot.RobotModel` that the
identification, persistence and analysis code use, so :func:`torchcal.fit`,
:func:`torchcal.io.rundir.save_model` / ``load_model`` and the slope
constraint (:mod:`torchcal.identify.constrained`) work on it unchanged.
"""

from __future__ import annotations

from typing import Any

import torch
from torch import nn

from ..error_models.axis_perturbation import AxisPerturbation
from ..error_models.frame import FrameCorrection, ToolSet
from .jacobian import joint_axis_jacobian, twist_jacobian
from ..kinematics.fk import chain_frames
from ..kinematics.robot import ChainBuffers, Robot
from ..kinematics.transforms import twist_to_transform

TOOL_TERMS = ("z", "xyz")


class MachineModel(ChainBuffers, nn.Module):
    """Paper I's model of a machine tool: axis perturbation tables + measurement frame + tools.

    robot: the nominal machine (e.g. ``torchcal.load_robot("five_axis_xyzcb")``);
    tools: (T, 3) nominal tool vectors in the last frame, m (Paper I: [0, 0, l_t]);
    orders: Chebyshev order of every table (int) or an (n, n) table (rows:
    output axis, columns: input axis, -1 off); pairs: optional enabled (i, j)
    list (the tables the controller offers); base_nominal: (4, 4) T_mf
    (identity: the tracker frame is the machine frame); tool_terms: 'z' (the
    paper's tool-length corrections delta_t along the tool's own z, (10)) or
    'xyz'.

    Example:
        >>> import torch, torchcal
        >>> machine = torchcal.load_robot("five_axis_xyzcb")
        >>> tools = torch.tensor([[0, 0, 0.4029], [0, 0, 0.5009]], dtype=torch.float64)
        >>> model = MachineModel(machine, tools, orders=6)
        >>> q = machine.joint_map.limits.mean(1).expand(3, 5)
        >>> model.points(q, torch.tensor([0, 1, 1])).shape, len(model.axis_errors.pairs)
        (torch.Size([3, 3]), 25)
    """

    def __init__(self, robot: Robot, tools, orders=6, pairs=None, base_nominal: torch.Tensor | None = None,
                 tool_terms: str = "z"):
        super().__init__()
        if tool_terms not in TOOL_TERMS:
            raise ValueError(f"MachineModel: tool_terms must be one of {TOOL_TERMS}, got {tool_terms!r}")
        self.robot = robot
        jm = robot.joint_map
        self.register_chain(robot)
        self.axis_errors = AxisPerturbation(jm.limits, jm.prismatic, orders, pairs, jm.names)
        self.base = FrameCorrection(base_nominal)
        self.tools = ToolSet(tools)
        self.tool_terms = tool_terms
        self.coverage = None  # RobotModel's direction coverage; machines carry none

    # -------------------------------------------------------------- kinematics
    def perturbed_commands(self, q: torch.Tensor, v: torch.Tensor | None = None) -> torch.Tensor:
        """q + dq(q) (+ v): what the nominal kinematics are driven with, (B, n) -> (B, n), SI."""
        a = q + self.axis_errors.delta(q)
        return a if v is None else a + v

    def joint_variables(self, a: torch.Tensor) -> torch.Tensor:
        """Controller commands (B, n) -> URDF joint variables (B, n) (identity for XYZCB)."""
        return a @ self.coupling.T + self.offset

    def _fk(self, a: torch.Tensor, T0: torch.Tensor | None):
        return chain_frames(self.origins, self.axes, self.prismatic, self.joint_variables(a), None, self.tip, T0)

    def flange(self, q, direction=None, v=None, base: bool = True) -> torch.Tensor:
        """Modeled last-frame pose (B, 4, 4): T_mf E_mf F_AP(q) (base=True) or F_AP(q) in the machine frame.

        direction is accepted for the common model interface and ignored (no backlash term).
        """
        T0 = self.base() if base else None
        return self._fk(self.perturbed_commands(q, v), T0)[2]

    def machine_flange(self, q: torch.Tensor) -> torch.Tensor:
        """F_AP(q) = F_nom(q + dq(q)) (B, 4, 4) in the machine's nominal base frame: no measurement frame."""
        return self._fk(self.perturbed_commands(q), None)[2]

    def nominal_flange(self, q: torch.Tensor) -> torch.Tensor:
        """F_nom(q) (B, 4, 4) in the machine's nominal base frame."""
        return self._fk(q, None)[2]

    def tool_points(self, flange: torch.Tensor, tool: torch.Tensor) -> torch.Tensor:
        """Tool positions (B, 3) for last-frame poses (B, 4, 4) and tool indices (B,)."""
        p_t = self.tools()[tool]
        return (flange[:, :3, :3] @ p_t[..., None])[..., 0] + flange[:, :3, 3]

    def points(self, q, tool, direction=None, v=None) -> torch.Tensor:
        """Measured-point model (8)/(12): tool t's position (B, 3) in the tracker frame, m."""
        return self.tool_points(self.flange(q, direction, v), tool)

    def forward(self, q, tool, direction=None, v=None) -> torch.Tensor:
        """Same as :meth:`points`."""
        return self.points(q, tool, direction, v)

    def nominal_points(self, q, tool) -> torch.Tensor:
        """Nominal prediction (B, 3): nominal kinematics, nominal tools, nominal T_mf."""
        F = self.base.nominal @ self.nominal_flange(q)
        p_t = self.tools.nominal[tool]
        return (F[:, :3, :3] @ p_t[..., None])[..., 0] + F[:, :3, 3]

    # --------------------------------------------------------------- Jacobians
    def point_jacobians(self, q, tool, direction=None, v=None):
        """Tool points and their Jacobians w.r.t. every parameter group and the axis errors v.

        q: (B, n); tool: (B,) long; v: (B, n) or None.
        -> p (B, 3) and {'axis_errors.coef': (B, 3, n, n, K), 'base.twist': (B, 3, 6),
        'tools.delta': (B, 3, T, 3), 'v': (B, 3, n)}. Closed form: d p / d a, the
        nominal point Jacobian at the perturbed command a = q + dq(q) + v, times
        d a / d(.) (the Chebyshev values for a_k,ij, the identity for v).
        """
        B = q.shape[0]
        ae = self.axis_errors
        a = self.perturbed_commands(q, v)
        T0 = self.base()
        jR, jp, F = self._fk(a, T0)
        p = self.tool_points(F, tool)
        Ja = joint_axis_jacobian(jR, jp, self.axes, self.prismatic, p)[:, :3, :] @ self.coupling  # (B, 3, n)
        design = ae.design(q)  # (B, n_j, K)
        J = {"axis_errors.coef": torch.einsum("bci,bjk,ijk->bcijk", Ja, design, ae.mask.to(Ja))}
        nominal = self.base.nominal.expand(B, 4, 4)
        T0b = nominal @ twist_to_transform(self.base.twist)
        J["base.twist"] = twist_jacobian(T0b[:, :3, :3], T0b[:, :3, 3], self.base.twist.expand(B, 6), p)[:, :3, :]
        Jt = torch.zeros(B, 3, self.tools.count, 3, dtype=q.dtype, device=q.device)
        Jt[torch.arange(B, device=q.device), :, tool, :] = F[:, :3, :3]
        J["tools.delta"] = Jt
        J["v"] = Ja
        return p, J

    # ------------------------------------------------------------ declarations
    def tool_mask(self) -> torch.Tensor:
        """(T, 3) bool: the tool corrections that are free ('z': delta_t along the tool axis only)."""
        m = torch.ones(self.tools.count, 3, dtype=torch.bool)
        if self.tool_terms == "z":
            m[:, :2] = False
        return m

    def parameter_groups(self) -> list:
        """Declared parameters in ``named_parameters()`` order: 'axis_errors.coef' (role 'axis'),
        'base.twist' (role 'frame'), 'tools.delta' (role 'tool', masked to the tool axis by default)."""
        groups = list(self.axis_errors.param_groups("axis_errors")) + list(self.base.param_groups("base"))
        (tg,) = self.tools.param_groups("tools")
        tg.mask = tg.mask & self.tool_mask().to(tg.mask.device)
        return groups + [tg]

    # ------------------------------------------------------------ persistence
    def spec(self) -> dict[str, Any]:
        """What it takes to rebuild this model's structure (the state dict holds the values); 'kind': 'machine'."""
        return {
            "kind": "machine",
            "robot": self.robot.source or self.robot.name,
            "tools": self.tools.nominal.tolist(),
            "orders": self.axis_errors.orders.tolist(),
            "base_nominal": self.base.nominal.tolist(),
            "tool_terms": self.tool_terms,
        }

    @classmethod
    def from_spec(cls, spec: dict[str, Any], robot: Robot | None = None) -> MachineModel:
        """Rebuild an (all-zero) model from :meth:`spec`; load the state dict to restore values."""
        from ..kinematics.robot import load_robot

        robot = robot or load_robot(spec["robot"])
        return cls(robot, torch.tensor(spec["tools"], dtype=torch.float64), spec["orders"],
                   base_nominal=torch.tensor(spec["base_nominal"], dtype=torch.float64),
                   tool_terms=spec.get("tool_terms", "z"))
