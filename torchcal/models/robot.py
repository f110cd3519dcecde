"""The calibrated robot: nominal chain + joint error modules + base frame + tools.

``RobotModel`` is the measurement model of Paper II (25): the position of tool
t measured in the measurement frame for controller command q,

    p = T_0^m  F_a(q + v, s)  p_T,t            (25)-(27)
    F_a = Π_i origin_i · E_i(u_i, s_i) · joint_i(θ_i),   θ = joint_map(q + v)   (19)

where u_i, the variable joint i's error series (23) is evaluated on, is the
controller command (q + v)_i normalized over the command limits (24) — the
paper's reading and the default — or the URDF joint variable θ_i (per joint,
``error_variable``; the FANUC's J3 gear turns with q3 while θ3 = q2 + q3).

Backlash (13) turns URDF joint i about its own Z by s_i Δq_ib(u_i) (``backlash_on='joint'``, the paper's).
A gear's lost motion is an error of the controller joint it drives, though: where a joint map couples
joints (a parallelogram arm, whose J2 also turns θ3), ``backlash_on='command'`` puts s_j Δq_jb(u_j) on the
command q_j and carries it to the URDF joints by the coupling, θ = A (q + v + β) + offset (u is taken at
q + v: β is a few hundredths of a degree). With an identity map both readings agree to first order.

Everything is SI inside (m, rad); convert at the file boundary with
:mod:`torchcal.core.units`.
"""

from __future__ import annotations

from typing import Any

import torch
from torch import nn

from ..error_models.compliance import build_compliance
from ..error_models.fine import build_fine
from ..error_models.frame import FrameCorrection, ToolSet
from ..error_models.joint import JointErrors
from .jacobian import chebyshev_design, joint_axis_jacobian, twist_jacobian
from ..kinematics.fk import chain_frames
from ..kinematics.robot import ChainBuffers, Robot
from ..kinematics.transforms import homogeneous, so3_exp


BACKLASH_ON = ("joint", "command")
"""Where backlash acts: the URDF joint's own axis (Paper II (13)) or the controller command, through the coupling."""


def joint_series(je: JointErrors, u: torch.Tensor):
    """Joint errors' Chebyshev series (23) at error variables u (B, n), with their derivatives.

    -> basis, dbasis (B, n, max(K, Kb)) (d/du), e, de (B, n, 6) (the terms without backlash and
    their slopes), K, Kb (coefficients per term and per backlash series).
    """
    K, Kb = je.coef.shape[-1], je.backlash.shape[-1]
    basis, dbasis = chebyshev_design(je.normalized(u), max(K, Kb), 2.0 / (je.ranges[:, 1] - je.ranges[:, 0]))
    coef = je.coef * je.mask
    e = torch.einsum("bnk,ntk->bnt", basis[..., :K], coef)
    de = torch.einsum("bnk,ntk->bnt", dbasis[..., :K], coef)
    return basis, dbasis, e, de, K, Kb


FLANGE_METHODS = ("_variables", "joint_variables", "flange", "_parts", "flange_jacobian", "point_jacobians")
"""RobotModel methods the flange and its Jacobians come from: a subclass overriding one is evaluated live by the
fast backends (:meth:`RobotModel.extended`)."""

OWN_MODULES = frozenset({"joint_errors", "base", "tools", "compliance", "fine"})
"""The submodules a RobotModel has; another one (an error module a subclass adds) makes it :meth:`extended`."""


class RobotModel(ChainBuffers, nn.Module):
    """Paper II's generalized kinematic error model (19)-(27) for one robot.

    robot: nominal machine (chain + joint map); tools: (T, 3) nominal tool
    vectors in the flange frame (m); orders: Chebyshev order per joint (int,
    list or (n, 6) table, see :class:`JointErrors`); backlash: direction term
    on eps_z; base_nominal: (4, 4) first guess of the measurement frame ->
    robot base (identity when the tracker frame is the base frame);
    compliance: optional gravity compliance of the joints carrying the arm
    (:class:`~torchcal.error_models.compliance.GravityCompliance`, parameter
    ``compliance.coef``): False (off, the default), True / 'auto', 'gravity',
    'functions', or a dict of its keywords (mode, joints, gravity, inertials).
    Its deflection Δθ(θ(q)) adds to the URDF joint variables where the joint
    errors v act, evaluated at the commanded q (v does not enter it).
    error_variable: 'command' (Paper II (24)), 'joint', or one per joint; None
    takes the robot's joint map (``error_variable:`` of its YAML, 'command' by default).
    fine: optional fine-grained joint-angle error tables
    (:class:`~torchcal.error_models.fine.FineJointErrors`, parameter
    ``fine.values``): None (off, the default), a module, or a dict of its
    keywords; like the compliance, Δθ(θ(q)) adds to the joint variables at the commanded q.
    backlash_on: 'joint' (Paper II (13): about the URDF joint's own axis) or 'command' (on the controller
    command, carried by the joint map's coupling: a parallelogram's motor-side backlash), see the module.

    Example:
        >>> import torch, torchcal
        >>> robot = torchcal.load_robot("fanuc_lrmate200i")
        >>> model = RobotModel(robot, torch.tensor([[0.0, 0.0, 0.1]], dtype=torch.float64), orders=6, backlash=True)
        >>> model.error_variable[2], model.points(torch.zeros(4, 6, dtype=torch.float64), torch.zeros(4, dtype=torch.long)).shape
        ('command', torch.Size([4, 3]))
    """

    def __init__(self, robot: Robot, tools, orders=6, backlash=None, base_nominal: torch.Tensor | None = None,
                 compliance=False, error_variable=None, fine=None, backlash_on: str = "joint"):
        super().__init__()
        if backlash_on not in BACKLASH_ON:
            raise ValueError(f"backlash_on: {backlash_on!r} is not one of {BACKLASH_ON}")
        self.backlash_on = backlash_on
        if error_variable is not None:
            robot = robot.with_error_variable(error_variable)
        self.robot = robot
        chain, jm = robot.chain, robot.joint_map
        self.register_chain(robot)
        self.error_variable = list(jm.error_variable)
        A_u, b_u = jm.error_map()
        # structure, not state: rebuilt from the spec, so state dicts of older runs (without them) still load
        self.register_buffer("error_coupling", A_u.clone(), persistent=False)
        self.register_buffer("error_offset", b_u.clone(), persistent=False)
        # a joint whose errors follow θ_i also sees the gravity deflection of θ_i; one on the command does not
        self.register_buffer("error_follows_joint", jm.follows_joint().to(torch.float64), persistent=False)
        # backlash (13) adds a turn about (a move along) each joint's own axis to E_i: eps_z for a revolute joint
        # about +z (every bundled robot), the axis' components otherwise (a ROS-style axis, a rail)
        self.joint_errors = JointErrors(jm.error_ranges(), orders, backlash, chain.joint_names,
                                        prismatic=self.prismatic.tolist(), axes=self.axes)
        self.base = FrameCorrection(base_nominal)
        self.tools = ToolSet(tools)
        self.compliance = build_compliance(robot, compliance)
        self.fine = build_fine(robot, fine)
        self._spec = {"orders": self.joint_errors.orders.tolist(), "backlash": self.joint_errors.backlash_orders.tolist()}
        self.coverage = None  # DirectionCoverage of the identification data, set by fit()
        self.data_span = None  # (n, 2) least / greatest error variable per joint in the identification data (fit())
        self.measured_tools = None  # the tool indices the identification data measured (fit()); None: not known

    # -------------------------------------------------------------- kinematics
    def backlash_coupling(self) -> torch.Tensor | None:
        """(n, n) map from the backlash terms s_j Δq_jb to the URDF joint variables θ ('command': the joint map's
        coupling, a parallelogram's motor-side backlash also turning θ3), or None where they add to each E_i the
        turn about (move along) the joint's own axis (Paper II (13), ``joint_errors.screw``)."""
        return self.coupling if self.backlash_on == "command" else None

    def joint_variables(self, q: torch.Tensor) -> torch.Tensor:
        """Controller commands (B, n) -> URDF joint variables (B, n)."""
        return q @ self.coupling.T + self.offset

    def error_variables(self, q: torch.Tensor) -> torch.Tensor:
        """Controller commands (B, n) -> the variable u (B, n) each joint's error series is evaluated on."""
        return q @ self.error_coupling.T + self.error_offset

    def _variables(self, q: torch.Tensor, v: torch.Tensor | None):
        """θ (joint motion) and u (error series) at q + v, both with the gravity deflection where it applies.

        -> theta (B, n), u (B, n), and the compliance functions (B, m, K) at the commanded q (None without
        compliance): the deflection is a function of the commanded configuration, v does not enter it.
        """
        qv = q if v is None else q + v
        theta = self.joint_variables(qv)
        u = self.error_variables(qv)
        comp = None
        if self.compliance is not None:
            comp = self._compliance_functions(q)  # (B, m, K)
            dtheta = self.compliance.deflection_from(comp)
            theta = theta + dtheta
            u = u + dtheta * self.error_follows_joint
        if self.fine is not None:
            dfine = self.fine(self.joint_variables(q))
            theta = theta + dfine
            u = u + dfine * self.error_follows_joint
        return theta, u, comp

    def _compliance_functions(self, q: torch.Tensor) -> torch.Tensor:
        """compliance.functions(θ(q)), remembered for the last few command tensors.

        They depend on the commands and the URDF's inertials only (no parameter), and a fit evaluates them for
        the same data commands at every residual and linearization: a second pass over the chain each time
        (~10 s of a constrained IRB 120 fit). Keyed on the tensor object itself and its version counter (the
        cache holds a reference, so its memory cannot be reused by another tensor while cached).
        """
        if q.requires_grad or torch._C._functorch.peek_interpreter_stack() is not None:
            # differentiated, or inside a torch.func transform (vmap over models, jacfwd): never cached
            return self.compliance.functions(self.joint_variables(q))
        cache = self.__dict__.setdefault("_comp_cache", [])
        for entry in cache:
            if entry[0] is q and entry[1] == q._version:
                return entry[2]
        out = self.compliance.functions(self.joint_variables(q))
        if not out.requires_grad:
            cache.insert(0, (q, q._version, out))
            del cache[4:]
        return out

    def frames(self, q: torch.Tensor, direction: torch.Tensor | None = None, v: torch.Tensor | None = None, base: bool = True):
        """Joint frames and flange pose with all errors, see :func:`chain_frames`.

        q: (B, n) commands; direction: (B, n) approach directions s_i or None;
        v: (B, n) joint positioning errors (controller space) or None;
        base: include T_0^m (measurement frame) or work in the robot's nominal base frame.
        """
        theta, u, _ = self._variables(q, v)
        if (Mb := self.backlash_coupling()) is not None:
            E = self.joint_errors(u, None)
            if direction is not None and self.joint_errors.has_backlash:
                theta = theta + self.joint_errors.backlash_values(u, direction) @ Mb.T
        else:
            E = self.joint_errors(u, direction)
        T0 = self.base() if base else self.base.correction()
        return chain_frames(self.origins, self.axes, self.prismatic, theta, E, self.tip, T0)

    def flange(self, q, direction=None, v=None, base: bool = True) -> torch.Tensor:
        """Modeled flange pose (B, 4, 4) in the measurement frame (base=True) or the robot's nominal base frame."""
        self.check_commands(q, "RobotModel.flange")
        return self.frames(q, direction, v, base)[2]

    def nominal_flange(self, q: torch.Tensor) -> torch.Tensor:
        """Nominal flange pose F_n(q) (B, 4, 4) in the robot's nominal base frame: no error terms."""
        self.check_commands(q, "RobotModel.nominal_flange")
        return chain_frames(self.origins, self.axes, self.prismatic, self.joint_variables(q), None, self.tip)[2]


    def flange_snapshot(self):
        """This model frozen for the fast flange backends of compensation (:class:`ChainSnapshot`): copies of
        its chain and masked series, detached; ``live`` is the model itself where its flange depends on the
        whole configuration (gravity compliance, fine joint tables), which the backends then evaluate live."""
        from ..kinematics.snapshot import ChainSnapshot

        je = self.joint_errors
        with torch.no_grad():
            return ChainSnapshot(
                coupling=self.coupling.detach().clone(), offset=self.offset.detach().clone(),
                error_coupling=self.error_coupling.detach().clone(), error_offset=self.error_offset.detach().clone(),
                ranges=je.ranges.detach().clone(), coef=(je.coef * je.mask).detach().clone(),
                backlash=(je.backlash * je.backlash_mask).detach().clone() if je.has_backlash else None,
                backlash_screw=je.screw.detach().clone(),
                origins=self.origins.detach().clone(), axes=self.axes.detach().clone(),
                prismatic=self.prismatic.detach().clone(), tip=self.tip.detach().clone(),
                base=self.base.correction().detach().clone(),
                live=self if (self.compliance is not None or self.fine is not None
                              or self.backlash_coupling() is not None or self.extended()) else None)

    def closed_form(self) -> bool:
        """Whether :meth:`point_jacobians` / :meth:`flange_jacobian` hold every term of this model: not for an
        :meth:`extended` subclass that kept the base class's (they know only the paper's terms; a flange override
        was fitted 1 mm off, silently), unless it wrote its own."""
        return not self.extended() or type(self).point_jacobians is not RobotModel.point_jacobians

    def extended(self) -> bool:
        """Whether this is a subclass that changes how the flange is computed (a method of :data:`FLANGE_METHODS`
        overridden, or an ``nn.Module`` of its own beside :data:`OWN_MODULES`): the frozen snapshot would leave
        its terms out (compensation converged 0.6 mm off a researcher's cross-coupling term), so the fast
        backends evaluate such a model live."""
        cls = type(self)
        return (any(getattr(cls, m) is not getattr(RobotModel, m) for m in FLANGE_METHODS)
                or any(name not in OWN_MODULES for name, _ in self.named_children()))

    def tool_points(self, flange: torch.Tensor, tool: torch.Tensor) -> torch.Tensor:
        """Tool positions (B, 3) for flange poses (B, 4, 4) and tool indices (B,)."""
        p_t = self.tools()[tool]
        return (flange[:, :3, :3] @ p_t[..., None])[..., 0] + flange[:, :3, 3]

    def forward(self, q, tool, direction=None, v=None) -> torch.Tensor:
        """Same as :meth:`points`."""
        return self.points(q, tool, direction, v)

    def points(self, q, tool, direction=None, v=None) -> torch.Tensor:
        """Measured-point model (25): tool t's position (B, 3) in the measurement frame.

        q: (B, n) commands (rad / m) of the model's dtype and device; tool: (B,) or one index; direction:
        (B, n) in {-1, 0, +1} or None; v: (B, n) joint errors or None."""
        self.check_commands(q, "RobotModel.points")
        return self.tool_points(self.flange(q, direction, v), tool)

    def nominal_points(self, q, tool) -> torch.Tensor:
        """Nominal prediction (B, 3): nominal chain, nominal tools, nominal measurement frame."""
        F = self.base.nominal @ self.nominal_flange(q)
        p_t = self.tools.nominal[tool]
        return (F[:, :3, :3] @ p_t[..., None])[..., 0] + F[:, :3, 3]

    # --------------------------------------------------------------- Jacobians
    def _parts(self, q, direction, v, base: bool = True):
        """Forward pass keeping what the closed-form Jacobians need."""
        je = self.joint_errors
        theta, u, comp = self._variables(q, v)
        basis, dbasis, e, de, K, Kb = joint_series(je, u)
        s, db = None, None
        if je.has_backlash and direction is not None:
            s = direction.to(u)
            bl = je.backlash * je.backlash_mask
            if (Mb := self.backlash_coupling()) is not None:  # β moves θ (through the coupling); its slope apart
                theta = theta + ((basis[..., :Kb] * bl).sum(-1) * s) @ Mb.T
                db = (dbasis[..., :Kb] * bl).sum(-1) * s
            else:  # about (along) each joint's own axis: eps_z for a joint about +z
                e = e + ((basis[..., :Kb] * bl).sum(-1) * s)[..., None] * je.screw
                de = de + ((dbasis[..., :Kb] * bl).sum(-1) * s)[..., None] * je.screw
        # base=None: no base frame at all (Paper I's modeled error is taken in the robot's own base frame)
        T0 = None if base is None else (self.base() if base else self.base.correction())
        ER = so3_exp(e[..., :3])  # kept: the error twists' Jacobians need it again
        jR, jp, F = chain_frames(self.origins, self.axes, self.prismatic, theta, homogeneous(ER, e[..., 3:]), self.tip,
                                 T0)
        return dict(theta=theta, basis=basis, e=e, ER=ER, de=de, s=s, db=db, jR=jR, jp=jp, F=F, K=K, Kb=Kb, comp=comp,
                    T0=T0 if base is True else None)

    def point_jacobians(self, q, tool, direction=None, v=None):
        """Tool points and their Jacobians w.r.t. every parameter group and the joint errors v.

        q: (B, n); tool: (B,) long; direction: (B, n) or None; v: (B, n) or None.
        -> p: (B, 3) and a dict of Jacobians d p / d(.) keyed like named_parameters():
           'joint_errors.coef' (B, 3, n, 6, K), 'joint_errors.backlash' (B, 3, n, Kb),
           'base.twist' (B, 3, 6), 'tools.delta' (B, 3, T, 3), with compliance
           'compliance.coef' (B, 3, m, K), with fine tables 'fine.values' (B, 3, n, K), and 'v' (B, 3, n) (controller space,
           error-term slopes included).
        """
        d = self._parts(q, direction, v)
        F = d["F"]
        p = self.tool_points(F, tool)
        J = self.chain_jacobians(d, q, p, rows=3)
        # out of place (one-hot), so that torch.func.vmap can batch it over models
        onehot = torch.nn.functional.one_hot(tool, self.tools.count).to(F)  # (B, T)
        J["tools.delta"] = F[:, :3, None, :3] * onehot[:, None, :, None]
        return p, J

    def chain_jacobians(self, d: dict, q: torch.Tensor, p: torch.Tensor, rows: int = 3) -> dict:
        """Jacobians of a point p (B, 3) carried by the flange w.r.t. every chain parameter group and v.

        d: :meth:`_parts` at (q, direction, v); rows: 3 (velocity of p) or 6 (then also the angular
        velocity of the flange, so that dR = S(omega) R). -> {'joint_errors.coef' (B, rows, n, 6, K),
        'joint_errors.backlash', 'base.twist' (B, rows, 6), ['compliance.coef'], ['fine.values'],
        'v' (B, rows, n)}: everything but the tool vectors, shared by point targets and sensor rigs.
        """
        B, n = q.shape
        Je = twist_jacobian(d["jR"], d["jp"], d["e"], p[:, None, :], d.get("ER"))[:, :, :rows, :]  # (B, n, rows, 6)
        Jax = joint_axis_jacobian(d["jR"], d["jp"], self.axes, self.prismatic, p)[:, :rows, :]  # per θ_i
        slope = torch.einsum("bnct,bnt->bcn", Je, d["de"])  # (B, rows, n): through E_i's series
        J = {"joint_errors.coef": torch.einsum("bnct,bnk->bcntk", Je, d["basis"][..., : d["K"]])}
        if d["s"] is not None and d["db"] is not None:  # backlash moving θ = M β (backlash_coupling)
            Jcmd = Jax @ self.backlash_coupling()  # (B, rows, n) per backlash term
            J["joint_errors.backlash"] = torch.einsum("bcj,bjk->bcjk", Jcmd * d["s"][:, None, :],
                                                      d["basis"][..., : d["Kb"]])
            slope = slope + Jcmd * d["db"][:, None, :]
        elif d["s"] is not None:
            along = torch.einsum("bnct,nt->bnc", Je, self.joint_errors.screw)  # the joint's own turn / move
            J["joint_errors.backlash"] = torch.einsum("bnc,bnk->bcnk", along * d["s"][..., None], d["basis"][..., : d["Kb"]])
        else:
            J["joint_errors.backlash"] = torch.zeros(B, rows, n, d["Kb"], dtype=q.dtype, device=q.device)
        T0 = d.get("T0")  # the corrected base, where _parts made it
        if T0 is None:
            T0 = self.base()
        # E's rotation from the frame itself (nominal^T T0), not a second exponential
        ER = self.base.nominal[:3, :3].T @ T0[:3, :3]
        J["base.twist"] = twist_jacobian(T0[:3, :3].expand(B, 3, 3), T0[:3, 3].expand(B, 3), self.base.twist.expand(B, 6),
                                         p, ER)[:, :rows, :]
        # Δθ_j (compliance, fine tables) moves θ_j and u_j where the errors follow θ_j: d / d Δθ_j
        moves = Jax + slope * self.error_follows_joint
        if self.compliance is not None:
            c = self.compliance
            J["compliance.coef"] = torch.einsum("bcm,bmk->bcmk", moves[:, :, c.joints], d["comp"]) * c.mask
        if self.fine is not None:
            w, _ = self.fine.weights(self.joint_variables(q))
            J["fine.values"] = torch.einsum("bcn,bnk->bcnk", moves, w) * self.fine.mask
        # v moves θ = A (q + v) + offset and u = A_u (q + v) + b_u
        J["v"] = Jax @ self.coupling + slope @ self.error_coupling
        return J

    def flange_jacobian(self, q, direction=None, base: bool = False):
        """Flange pose and its body-frame Jacobian w.r.t. the controller commands, error slopes included.

        -> F: (B, 4, 4) (robot nominal base frame unless base=True) and J: (B, 6, n)
        mapping dq to (v, w) of the flange expressed in the flange frame, the
        frame of the pose error (47)-(48).
        """
        d = self._parts(q, direction, None, base)
        F = d["F"]
        o = F[:, :3, 3]
        Je = twist_jacobian(d["jR"], d["jp"], d["e"], o[:, None, :], d.get("ER"))  # (B, n, 6, 6)
        Jax = joint_axis_jacobian(d["jR"], d["jp"], self.axes, self.prismatic, o)  # (B, 6, n) per θ_i
        slope = torch.einsum("bnct,bnt->bcn", Je, d["de"])  # (B, 6, n) per u_i
        if d["db"] is not None:  # backlash moving θ: its slope moves θ through backlash_coupling
            slope = slope + (Jax @ self.backlash_coupling()) * d["db"][:, None, :]
        Rt = F[:, :3, :3].transpose(1, 2)

        def body(Js):
            return torch.cat([Rt @ Js[:, :3], Rt @ Js[:, 3:]], 1)

        dtheta_dq, du_dq = self.coupling, self.error_coupling
        if self.compliance is not None:
            # θ = A q + offset + Δθ(A q + offset): dθ/dq = (I + dΔθ/dθ) A per pose; u follows Δθ where it follows θ
            DA = self.compliance.deflection_jacobian(self.joint_variables(q)) @ self.coupling
            dtheta_dq = self.coupling + DA
            du_dq = self.error_coupling + self.error_follows_joint[:, None] * DA
        if self.fine is not None:
            # the table's slope at θ(q) scales each joint's motion: dΔθ_i/dq = slope_i · A_i,:
            Ds = self.fine.slope(self.joint_variables(q))[:, :, None] * self.coupling
            dtheta_dq = dtheta_dq + Ds
            du_dq = du_dq + self.error_follows_joint[:, None] * Ds
        return F, body(Jax) @ dtheta_dq + body(slope) @ du_dq

    def parameter_groups(self) -> list:
        """Kind, unit and prior scale of every learnable parameter, declared by the module that owns it.

        -> list of :class:`torchcal.core.params.ParamGroup` in ``named_parameters()``
        order ('joint_errors.coef', 'joint_errors.backlash', 'base.twist',
        'tools.delta'[, 'compliance.coef'][, 'fine.values']).
        """
        groups = []
        for prefix, module in self.named_children():
            declare = getattr(module, "param_groups", None)
            if callable(declare):
                groups += list(declare(prefix))
        return groups

    # ------------------------------------------------------------ persistence
    def spec(self) -> dict[str, Any]:
        """What it takes to rebuild this model's structure (the state dict holds the values)."""
        out = {
            "robot": self.robot.source or self.robot.name,
            "tools": self.tools.nominal.tolist(),
            "orders": self._spec["orders"],
            "backlash": self._spec["backlash"],
            "base_nominal": self.base.nominal.tolist(),
            "error_variable": list(self.error_variable),
        }
        if self.coverage is not None:
            out["coverage"] = self.coverage.to_dict()
        if self.data_span is not None:  # absent in runs fitted before it (nothing is then said about extrapolation)
            out["data_span"] = torch.as_tensor(self.data_span).cpu().tolist()
        if self.measured_tools is not None:  # absent in older runs: every tool counts as measured
            out["measured_tools"] = [int(t) for t in self.measured_tools]
        if self.compliance is not None:  # absent when off: specs of models without it stay as they were
            out["compliance"] = self.compliance.spec()
        if self.fine is not None:  # likewise absent when off
            out["fine"] = self.fine.spec()
        if self.backlash_on != "joint":  # likewise: older specs are the paper's reading
            out["backlash_on"] = self.backlash_on
        return out

    @classmethod
    def from_spec(cls, spec: dict[str, Any], robot: Robot | None = None) -> RobotModel:
        """Rebuild an (all-zero) model from :meth:`spec`; load the state dict to restore values."""
        from ..kinematics.robot import load_robot

        robot = robot or load_robot(spec["robot"])
        b = spec.get("backlash")
        backlash = None if b is None or max(b) < 0 else b
        # runs written before the error variable existed evaluated every series on the URDF joint variable
        model = cls(robot, torch.tensor(spec["tools"], dtype=torch.float64), spec["orders"], backlash,
                    torch.tensor(spec["base_nominal"], dtype=torch.float64), compliance=spec.get("compliance") or False,
                    error_variable=spec.get("error_variable", "joint"), fine=spec.get("fine"),
                    backlash_on=spec.get("backlash_on", "joint"))
        if spec.get("coverage") is not None:
            from ..core.coverage import DirectionCoverage

            model.coverage = DirectionCoverage.from_dict(spec["coverage"])
        if spec.get("measured_tools") is not None:
            model.measured_tools = [int(t) for t in spec["measured_tools"]]
        if spec.get("data_span") is not None:
            model.data_span = torch.tensor(spec["data_span"], dtype=torch.float64)
        return model

    def record_data_span(self, q: torch.Tensor) -> None:
        """Keep the least / greatest error variable (:meth:`error_variables`: the command, or θ where a joint's
        errors follow it) of each joint over the identification commands q (R, n), widening a span already
        kept (online updates): what :meth:`outside_data` judges against."""
        if q.shape[0] == 0:
            return
        with torch.no_grad():
            u = self.error_variables(q.to(self.error_offset))
            lo, hi = u.amin(0).detach().cpu(), u.amax(0).detach().cpu()
        span = self.data_span
        self.data_span = torch.stack([lo, hi], 1) if span is None else torch.stack(
            [torch.minimum(span[:, 0], lo), torch.maximum(span[:, 1], hi)], 1)

    def outside_data(self, q: torch.Tensor) -> torch.Tensor | None:
        """(B, n) bool: commands q (B, n) at which a joint's error variable lies beyond the identification data's
        range (the model extrapolates that joint's error series there), or None when no range was recorded."""
        if self.data_span is None:
            return None
        with torch.no_grad():
            u = self.error_variables(q.to(self.error_offset))
        span = torch.as_tensor(self.data_span).to(u.device, u.dtype)
        return (u < span[:, 0]) | (u > span[:, 1])
