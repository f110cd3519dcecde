"""The tool-tip modeled-error slope of Paper I (13)-(30), for machine tools and robots, by autograd.

Why one module: Paper I (13)-(30), the tool-tip error slope, for machines and robots, in closed form and through torch.func; the forms are checked against each other.

The modeled error of the tool tip is the difference between where the
identified model and the nominal kinematics put it, both in the machine's own
base frame (no measurement frame) and with the nominal tool vector p_tl:

    e_t(q) = p_t,model(q) - p_t,nom(q)                           (16)-(17), (23)

(the paper writes p_nom - p_AP; the sign does not matter for the bound). Its
slope along axis i, scaled to half the axis range, is

    hbar_i(q) = d e_t / d q_i * (q_i,max - q_i,min) / 2          (29)-(30)

in metres per half axis motion, and Paper I bounds |hbar_i|_2 <= c (31) over
the WHOLE axis space (where nothing was measured too). The paper derives
hbar_i in closed form for XYZCB under R_nom ~ R_AP (24)-(28); here it is the
exact derivative, by forward-mode autograd (torch.func.jacfwd, vmapped over
points), so it holds for any model: :class:`torchcal.models.machine.MachineModel`
(e_t from F_AP(q) = F_nom(q + dq(q))) and :class:`torchcal.models.robot.RobotModel`
(e_t from the modeled flange with every joint error term, gravity compliance
included, the base-frame correction and backlash excluded: the former is the
measurement frame, the latter depends on the approach direction, not on q).
Inside fits, where only values are needed (no autograd through them), a
robot's hbar and its parameter Jacobian come from :func:`robot_slope_terms`
instead: central differences of the closed-form chain and chain Jacobians,
equal to the autograd values to ~1e-8 and many times faster.

:func:`slope_points` makes the dense point set the bound is imposed on:
seeded scrambled Sobol points over the command box, plus Sobol points on every
face of the box and all its corners (a polynomial's slope is largest at the
border).
"""

from __future__ import annotations

import warnings

import numpy as np
import torch
from torch import nn
from torch.func import functional_call, jacfwd, vmap

from ..kinematics.fk import chain_frames


# ------------------------------------------------------------------ the modeled error
def is_machine_model(model) -> bool:
    return callable(getattr(model, "machine_flange", None))


def _is_robot(model) -> bool:
    return hasattr(model, "joint_errors") and callable(getattr(model, "_variables", None))


def slope_model(model):
    """-> (the model whose slope is taken, the prefix of its parameter names in ``model``).

    A MachineModel or RobotModel is itself (prefix ''); a sensor rig (Paper III,
    :class:`~torchcal.models.sensor_rig.SensorRig`: a RobotModel carrying a 6-DOF sensor) is its robot
    model ('model.'), whose error terms are what the bound is on.
    """
    inner = getattr(model, "model", None)
    if not is_machine_model(model) and not _is_robot(model) and inner is not None and _is_robot(inner):
        return inner, "model."
    return model, ""


def modeled_flange(model, q: torch.Tensor) -> torch.Tensor:
    """Modeled last-frame pose (B, 4, 4) in the machine's nominal base frame, without the measurement frame.

    MachineModel: F_AP(q) = F_nom(q + dq(q)); RobotModel: the chain with every
    joint error term at the command q (no backlash: direction unknown), no base correction.
    """
    if is_machine_model(model):
        return model.machine_flange(q)
    if _is_robot(model):
        theta, u, _ = model._variables(q, None)
        E = model.joint_errors(u, None)
        return chain_frames(model.origins, model.axes, model.prismatic, theta, E, model.tip)[2]
    raise TypeError(f"{type(model).__name__}: the slope needs a MachineModel or a RobotModel "
                    f"(machine_flange(q), or joint_errors with _variables)")


SLOPE_REFERENCES = ("nominal", "constant")


def constant_flange(model, q: torch.Tensor) -> torch.Tensor:
    """RobotModel only: the chain with just the constant (c0) term of every joint error, (B, 4, 4).

    The reference of ``model.slope_reference = 'constant'``: the slope then measures the joint-DEPENDENT
    part of the modeled error only. On a robot, constant (DH-like) errors move the tool point by their
    lever arm times the joint motion: large, legitimate slopes (~12 mm per half range on the IRB 120)
    that a bound on the whole error would fight.
    """
    from ..kinematics.transforms import twist_to_transform

    je = model.joint_errors
    e0 = (je.coef * je.mask)[..., 0]  # (n, 6): every series' constant term (c_0 = 1)
    E0 = twist_to_transform(e0).expand(q.shape[0], -1, 4, 4)
    return chain_frames(model.origins, model.axes, model.prismatic, model.joint_variables(q), E0, model.tip)[2]


def modeled_error(model, q: torch.Tensor, tool_vector: torch.Tensor) -> torch.Tensor:
    """e_t(q) (B, 3), m: modeled minus reference tool point for the tool vector (3,) in the last frame.

    The reference is the nominal chain (Paper I (23)), or for a RobotModel whose ``slope_reference`` is
    'constant' the chain with the constant error terms only (:func:`constant_flange`).
    """
    F = modeled_flange(model, q)
    ref = getattr(model, "slope_reference", "nominal")
    if ref not in SLOPE_REFERENCES:
        raise ValueError(f"slope_reference must be one of {SLOPE_REFERENCES}, got {ref!r}")
    N = constant_flange(model, q) if ref == "constant" and _is_robot(model) else model.nominal_flange(q)
    p = tool_vector.to(q)
    return (F[:, :3, :3] - N[:, :3, :3]) @ p + F[:, :3, 3] - N[:, :3, 3]


def tool_vectors(model, tool=None) -> torch.Tensor:
    """(T, 3) nominal tool vectors the slope is taken for.

    tool: None (every nominal tool of the model), an index or list of indices
    into ``model.tools.nominal``, or vectors (3,) / (T, 3) in m in the last frame.
    A sensor rig's one nominal tool is the sensor origin (the nominal mount's translation).
    """
    if slope_model(model)[1]:
        nominal = model.mount.nominal[:3, 3].reshape(1, 3)
    else:
        nominal = model.tools.nominal
    if tool is None:
        return nominal
    t = torch.as_tensor(tool)
    if not t.is_floating_point():
        return nominal[t.reshape(-1).to(nominal.device)]
    t = t.to(dtype=nominal.dtype, device=nominal.device)
    if t.shape[-1] != 3:
        raise ValueError(f"tool vectors must have shape (3,) or (T, 3), got {tuple(t.shape)}")
    return t.reshape(-1, 3)


def half_ranges(model) -> torch.Tensor:
    """(n,) half of each command range, SI: the scaling of (30)."""
    lim = model.command_limits
    return 0.5 * (lim[:, 1] - lim[:, 0])


def _slopes(model, q: torch.Tensor, P: torch.Tensor, method: str = "auto", context: dict | None = None) -> torch.Tensor:
    """hbar (T, B, n, 3) for tool vectors P (T, 3); context: :func:`machine_slope_context` or
    :func:`robot_slope_context` of (q, P) (only where q needs no gradient), or None."""
    if method not in ("auto", "autograd"):
        raise ValueError(f"slope method must be 'auto' or 'autograd', got {method!r}")
    model = slope_model(model)[0]
    if method == "auto" and is_machine_model(model):
        return machine_slope_terms(model, q, P, context=context)["hbar"]
    if method == "auto" and robot_fast_path(model) and not torch.is_grad_enabled():
        return robot_slopes(model, q, P, context=context)
    half = half_ranges(model).to(q)
    out = []
    for p in P:
        def e(q1, p=p):
            return modeled_error(model, q1[None], p)[0]

        J = vmap(jacfwd(e))(q)  # (B, 3, n)
        out.append((J * half).transpose(1, 2))
    return torch.stack(out)


# ------------------------------------------------------------------ robots: central differences of the closed form
ROBOT_FD_STEP = 1e-4
"""Step (command units: rad, m) of the central differences in :func:`robot_slope_terms`: truncation
grows as step^2, rounding as 1e-16 / step; 1e-4 measured 2e-9 (hbar) and 8e-9 (its Jacobian) relative
to autograd on an IRB 120 with order-3 errors (1e-6: 4e-8, 3e-7)."""


def robot_fast_path(model) -> bool:
    """A RobotModel (or sensor rig) whose slope reference is the nominal chain: :func:`robot_slope_terms` applies."""
    model = slope_model(model)[0]
    return (_is_robot(model) and callable(getattr(model, "chain_jacobians", None))
            and getattr(model, "slope_reference", "nominal") == "nominal")


def _stencil(q: torch.Tensor, step: float) -> torch.Tensor:
    """(M, n) -> (2 M n, n): q ± step along each axis, rows ordered [sign, point, axis]."""
    M, n = q.shape
    d = step * torch.eye(n, dtype=q.dtype, device=q.device)
    return torch.stack([q[:, None, :] + d, q[:, None, :] - d]).reshape(-1, n)


def robot_slope_context(model, q: torch.Tensor, P: torch.Tensor, step: float = ROBOT_FD_STEP) -> dict:
    """The parts of :func:`robot_slope_terms` that depend on the points and tools only, not on the parameters.

    q: (M, n) commands; P: (T, 3) tool vectors. -> dict: 'qq' (2 M n, n) the difference stencil,
    'theta', 'u' (2 M n, n) its joint and error variables, 'comp' the compliance's configuration
    functions there (gravity torques: a second forward pass of the chain, None without compliance),
    'Np' (T, 2 M n, 3) the nominal tool points, 'step'. A fit evaluates the slope at the same points
    hundreds of times: computed once, these are half of each evaluation. Rows: :func:`robot_context_rows`.
    """
    model = slope_model(model)[0]
    with torch.no_grad():
        qq = _stencil(q, step)
        theta = model.joint_variables(qq)
        comp = model.compliance.functions(theta) if model.compliance is not None else None
        N = model.nominal_flange(qq)
        Np = torch.stack([N[:, :3, :3] @ p + N[:, :3, 3] for p in P.to(q)])
        return {"qq": qq, "theta": theta, "u": model.error_variables(qq), "comp": comp, "Np": Np, "step": step,
                **_robot_point_context(model, q, P)}


def _robot_point_context(model, q: torch.Tensor, P: torch.Tensor) -> dict:
    """The parameter-free parts of :func:`robot_slopes` at the points q (M, n): commanded joint and error
    variables, the compliance's configuration functions and their joint derivatives, and the nominal tool
    points' Jacobians J_n (T, M, 3, n) w.r.t. the commands."""
    theta = model.joint_variables(q)
    comp = dcomp = None
    if model.compliance is not None:
        comp, dcomp = model.compliance.functions(theta, derivative=True)
    nR, np_, N = chain_frames(model.origins, model.axes, model.prismatic, theta, None, model.tip)
    A = model.coupling.to(q)
    Jn = torch.stack([_axis_jacobian(nR, np_, model.axes, model.prismatic, N[:, :3, :3] @ p + N[:, :3, 3]) @ A
                      for p in P.to(q)])
    return {"m_theta": theta, "m_u": model.error_variables(q), "m_comp": comp, "m_dcomp": dcomp, "Jn": Jn}


def _axis_jacobian(jR, jp, axes, prismatic, point):
    """d point / d theta (B, 3, n) through the joints' own motion (the linear rows of
    :func:`torchcal.models.jacobian.joint_axis_jacobian`)."""
    z = (jR @ axes.to(point)[:, :, None])[..., 0]  # (B, n, 3)
    lin = torch.where(prismatic[None, :, None], z, torch.linalg.cross(z, point[:, None, :] - jp, dim=-1))
    return lin.transpose(1, 2)


def robot_slopes(model, q: torch.Tensor, P: torch.Tensor, context: dict | None = None) -> torch.Tensor:
    """hbar (T, M, n, 3) of a RobotModel (or sensor rig) in closed form, m per half axis motion.

    d e_t / d q = J_p(q) - J_n(q): the modeled tool point's Jacobian w.r.t. the commands, each joint
    turning the point about its axis (z_i x (p - o_i)) and moving it through its error series
    (w_i x (p - o_i) + v_i, the twist E_i's velocity along its series' slope), the gravity
    deflection's dependence on the configuration included; J_n the nominal chain's. The same values
    as autograd to round-off (the central differences of :func:`robot_slope_terms`: ~1e-9 relative),
    for one forward pass of M rows instead of 2 n M. Fine joint-angle tables (piecewise linear) take the
    central differences. context: :func:`robot_slope_context` of (q, P) or None.
    """
    from ..models.jacobian import chebyshev_design, so3_right_jacobian
    from ..kinematics.transforms import so3_exp, twist_to_transform

    model = slope_model(model)[0]
    if model.fine is not None:
        return robot_slope_terms(model, q, P, context=context)[0]
    half = half_ranges(model).to(q)
    # without a context, differentiable (first-order autograd) where grad is enabled: what worst_points climbs
    with torch.set_grad_enabled(torch.is_grad_enabled() and context is None):
        ctx = context if context is not None and "Jn" in context else _robot_point_context(model, q, P)
        theta, u, comp = ctx["m_theta"], ctx["m_u"], ctx["m_comp"]
        A, Au = model.coupling.to(q), model.error_coupling.to(q)
        follows = model.error_follows_joint.to(q)
        dDA = None
        if comp is not None:
            c = model.compliance
            dtheta = c.deflection_from(comp)
            theta = theta + dtheta
            u = u + dtheta * follows
            d = torch.einsum("bmkn,mk->bmn", ctx["m_dcomp"], c.coef * c.mask)  # d deflection / d theta_c
            dD = torch.zeros(q.shape[0], c.n, c.n, dtype=q.dtype, device=q.device).index_add(1, c.joints, d)
            dDA = dD @ A
        je = model.joint_errors
        K, Kb = je.coef.shape[-1], je.backlash.shape[-1]
        basis, dbasis = chebyshev_design(je.normalized(u), max(K, Kb), 2.0 / (je.ranges[:, 1] - je.ranges[:, 0]))
        coef = je.coef * je.mask
        e = torch.einsum("bnk,ntk->bnt", basis[..., :K], coef)
        de = torch.einsum("bnk,ntk->bnt", dbasis[..., :K], coef)
        jR, jp, F = chain_frames(model.origins, model.axes, model.prismatic, theta, twist_to_transform(e), model.tip, None)
        # E_i's velocity along its series: angular w_i, linear v_i (the rows of torchcal.models.jacobian.twist_jacobian)
        w = (jR @ (so3_right_jacobian(e[..., :3]) @ de[..., :3, None]))[..., 0]  # (M, n, 3)
        v = (jR @ (so3_exp(e[..., :3]).transpose(-1, -2) @ de[..., 3:, None]))[..., 0]
        out = []
        for t, p in enumerate(P.to(q)):
            pt = F[:, :3, :3] @ p + F[:, :3, 3]
            Jax = _axis_jacobian(jR, jp, model.axes, model.prismatic, pt)  # (M, 3, n) per theta_i
            slope = (torch.linalg.cross(w, pt[:, None, :] - jp, dim=-1) + v).transpose(1, 2)  # (M, 3, n) per u_i
            dp = Jax @ A + slope @ Au
            if dDA is not None:
                dp = dp + (Jax + slope * follows) @ dDA
            out.append(((dp - ctx["Jn"][t]) * half).transpose(1, 2))
        return torch.stack(out)


def robot_context_rows(context: dict, rows: torch.Tensor, tools=None) -> dict:
    """A :func:`robot_slope_context` for the points ``rows`` (and tools ``tools``, a slice or indices) only."""
    n = context["qq"].shape[1]
    M = context["qq"].shape[0] // (2 * n)

    def pick(t, lead: int = 0):  # rows [sign, point, axis] of the points ``rows``, after ``lead`` leading dims
        if t is None:
            return None
        head, tail = tuple(t.shape[:lead]), tuple(t.shape[lead + 1:])
        return t.reshape(head + (2, M, n) + tail)[(slice(None),) * (lead + 1) + (rows,)].reshape(head + (-1,) + tail)

    Np = context["Np"] if tools is None else context["Np"][tools]
    Jn = context["Jn"] if tools is None else context["Jn"][tools]
    m = {k: None if context[k] is None else context[k][rows] for k in ("m_theta", "m_u", "m_comp", "m_dcomp")}
    return {"qq": pick(context["qq"]), "theta": pick(context["theta"]), "u": pick(context["u"]),
            "comp": pick(context["comp"]), "Np": pick(Np, 1), "step": context["step"], **m, "Jn": Jn[:, rows]}


def slope_context(model, q: torch.Tensor, P: torch.Tensor) -> dict | None:
    """:func:`machine_slope_context` or :func:`robot_slope_context` of (q, P), whichever applies (None: neither)."""
    if is_machine_model(model):
        return machine_slope_context(model, q, P)
    if robot_fast_path(model):
        return robot_slope_context(model, q, P)
    return None


def cat_contexts(a: dict, b: dict) -> dict:
    """The context of the points of ``a`` followed by those of ``b`` (same model and tools)."""
    if "JqA" in a:
        return {"design": torch.cat([a["design"], b["design"]]), "ddesign": torch.cat([a["ddesign"], b["ddesign"]]),
                "JqA": torch.cat([a["JqA"], b["JqA"]], 1)}
    n = a["qq"].shape[1]

    def cat(x, y, lead: int = 0):  # stencil rows [sign, point, axis]: the points of y after those of x
        if x is None:
            return None
        head = tuple(x.shape[:lead])
        xs = x.reshape(head + (2, -1, n) + tuple(x.shape[lead + 1:]))
        ys = y.reshape(head + (2, -1, n) + tuple(y.shape[lead + 1:]))
        return torch.cat([xs, ys], lead + 1).reshape(head + (-1,) + tuple(x.shape[lead + 1:]))

    m = {k: None if a[k] is None else torch.cat([a[k], b[k]]) for k in ("m_theta", "m_u", "m_comp", "m_dcomp")}
    return {"qq": cat(a["qq"], b["qq"]), "theta": cat(a["theta"], b["theta"]), "u": cat(a["u"], b["u"]),
            "comp": cat(a["comp"], b["comp"]), "Np": cat(a["Np"], b["Np"], 1), "step": a["step"], **m,
            "Jn": torch.cat([a["Jn"], b["Jn"]], 1)}


def _robot_parts(model, context: dict) -> dict:
    """``model._parts(qq, None, None, base=None)`` at the context's stencil, its parameter-free parts reused.

    The same operations in the same order as :meth:`RobotModel._variables` and :meth:`RobotModel._parts`
    (tests hold the two to bitwise equality); no backlash (direction unknown), no base frame.
    """
    from ..kinematics.transforms import twist_to_transform
    from ..models.robot import joint_series

    theta, u, comp = context["theta"], context["u"], context["comp"]
    if comp is not None:
        dtheta = model.compliance.deflection_from(comp)
        theta = theta + dtheta
        u = u + dtheta * model.error_follows_joint
    if model.fine is not None:
        dfine = model.fine(context["theta"])
        theta = theta + dfine
        u = u + dfine * model.error_follows_joint
    basis, dbasis, e, de, K, Kb = joint_series(model.joint_errors, u)
    jR, jp, F = chain_frames(model.origins, model.axes, model.prismatic, theta, twist_to_transform(e), model.tip, None)
    return dict(theta=theta, basis=basis, e=e, de=de, s=None, jR=jR, jp=jp, F=F, K=K, Kb=Kb, comp=comp)


def robot_slope_terms(model, q: torch.Tensor, P: torch.Tensor, layout=None, step: float = ROBOT_FD_STEP,
                      context: dict | None = None):
    """hbar of a RobotModel, and its Jacobian w.r.t. the free parameters, without nested autograd.

    The modeled error e_t(q) and its parameter Jacobian are closed form (the chain's forward pass and
    :meth:`RobotModel.chain_jacobians`, base frame and tool corrections left out as in
    :func:`modeled_error`); the derivative along each axis is a central difference of both, all
    points and axes in one batch of 2 n M rows. Autograd's hbar (nested forward mode, vmapped) costs
    seconds per call on a robot and its parameter Jacobian a minute; this is milliseconds, and the
    tests hold it to the autograd values.

    q: (M, n) commands; P: (T, 3) tool vectors in the last frame; layout: a
    :class:`~torchcal.identify.layout.ParameterLayout` of the model for the Jacobian (None: none);
    context: :func:`robot_slope_context` of (q, P, step), or None (computed here).
    -> hbar (T, M, n, 3) m per half axis motion, and dhbar/dx (T, M, n, 3, P) or None.
    A sensor rig's layout: the robot model's entries (prefix 'model.') move e_t, the mount and gravity do not.
    """
    M, n = q.shape
    model, prefix = slope_model(model)
    half = half_ranges(model).to(q)
    with torch.no_grad():
        if context is None:
            qq = _stencil(q, step)  # (2 M n, n): [sign, point, axis]
            parts = model._parts(qq, None, None, base=None)
            N = model.nominal_flange(qq)
            Np = [N[:, :3, :3] @ p + N[:, :3, 3] for p in P.to(q)]
        else:
            qq, step, Np = context["qq"], context["step"], context["Np"]
            parts = _robot_parts(model, context)
        return _central_differences(model, prefix, parts, qq, Np, P.to(q), layout, (M, n), half[None, :, None] / (2 * step))


def _central_differences(model, prefix: str, parts: dict, qq, Np, P, layout, lead: tuple, scale):
    """hbar (T, *lead, 3) and d hbar / dx (T, *lead, 3, P) or None from a forward pass at stencil rows
    [sign, *lead]: Np[t] the nominal points of tool t there, scale (*lead, 1) half range / (2 step)."""
    F = parts["F"]
    hbar, dhbar = [], []
    for t, p in enumerate(P):
        pt = F[:, :3, :3] @ p + F[:, :3, 3]
        e = (pt - Np[t]).reshape((2,) + lead + (3,))
        hbar.append((e[0] - e[1]) * scale)
        if layout is None:
            continue
        J = model.chain_jacobians(parts, qq, pt, rows=3)
        groups = {}
        for name, prm, _ in layout.entries:
            # e_t leaves the base frame and the tool corrections out: they do not move it
            key = name[len(prefix):] if name.startswith(prefix) else None
            g = J.get(key) if key not in (None, "base.twist", "tools.delta") else None
            groups[name] = g if g is not None else qq.new_zeros((qq.shape[0], 3) + tuple(prm.shape))
        Jx = layout.flatten_jacobian(groups, qq.shape[0]).reshape((2,) + lead + (3, -1))
        dhbar.append((Jx[0] - Jx[1]) * scale[..., None])
    return torch.stack(hbar), (torch.stack(dhbar) if layout is not None else None)


def robot_pair_terms(model, context: dict, point: torch.Tensor, axis: torch.Tensor, P: torch.Tensor, layout):
    """hbar and its parameter Jacobian as :func:`robot_slope_terms`, at (point, axis) pairs only.

    context: :func:`robot_slope_context` of all the points; point, axis: (A,) long. Only the two stencil
    rows of each pair are evaluated (the others of a point are not needed where one axis is bounded).
    -> hbar (T, A, 3), dhbar/dx (T, A, 3, P).
    """
    model, prefix = slope_model(model)
    n = context["qq"].shape[1]
    M = context["qq"].shape[0] // (2 * n)
    rows = torch.stack([point * n + axis, (M + point) * n + axis]).reshape(-1)  # [sign, pair]
    sub = {k: None if context[k] is None else context[k][rows] for k in ("qq", "theta", "u", "comp")}
    sub["Np"] = context["Np"][:, rows]
    half = half_ranges(model).to(context["qq"])
    with torch.no_grad():
        parts = _robot_parts(model, sub)
        return _central_differences(model, prefix, parts, sub["qq"], sub["Np"], P.to(sub["qq"]), layout,
                                    (point.shape[0],), (half[axis] / (2 * context["step"]))[:, None])


def robot_slopes_differentiable(model, q: torch.Tensor, P: torch.Tensor, step: float = ROBOT_FD_STEP) -> torch.Tensor:
    """hbar (T, M, n, 3) of a RobotModel by the central differences of :func:`robot_slope_terms`, differentiable
    in q by plain (first-order) autograd: what :func:`worst_points` climbs (nested autograd costs ~10x more)."""
    M, n = q.shape
    model = slope_model(model)[0]
    qq = _stencil(q, step)
    theta, u, _ = model._variables(qq, None)
    E = model.joint_errors(u, None)
    F = chain_frames(model.origins, model.axes, model.prismatic, theta, E, model.tip)[2]
    N = model.nominal_flange(qq)
    scale = half_ranges(model).to(q)[None, :, None] / (2 * step)
    out = []
    for p in P.to(q):
        e = ((F[:, :3, :3] - N[:, :3, :3]) @ p + F[:, :3, 3] - N[:, :3, 3]).reshape(2, M, n, 3)
        out.append((e[0] - e[1]) * scale)
    return torch.stack(out)


# ------------------------------------------------------------------ closed form for machines
def point_jacobian_and_hessian(origins, axes, prismatic, tip, theta, points, hessian: bool = True):
    """Nominal point Jacobians of a serial chain and their derivatives w.r.t. the joint variables.

    theta: (B, n); points: (T, 3) in the last frame. -> J (T, B, 3, n) = d p / d theta
    and H (T, B, 3, n, n) with H[..., r, s] = d J[..., r] / d theta_s (None
    unless ``hessian``): for s before r a revolute joint s turns J_r rigidly
    (z_s x J_r); for s at or after r, p moves by J_s and a revolute r turns it
    (z_r x J_s); prismatic joints translate and leave J unchanged.
    """
    jR, jp, F = chain_frames(origins, axes, prismatic, theta, None, tip, None)
    p = torch.einsum("bij,tj->tbi", F[:, :3, :3], points.to(theta)) + F[None, :, :3, 3]  # (T, B, 3)
    z = (jR @ axes.to(theta)[:, :, None])[..., 0]  # (B, n, 3)
    pm = prismatic[None, None, :, None]
    zz = z.expand(p.shape[0], -1, -1, -1)
    Jr = torch.where(pm, zz, torch.linalg.cross(zz, p[:, :, None, :] - jp, dim=-1))  # (T, B, n, 3), row r = J_r
    if not hessian:
        return Jr.transpose(-1, -2), None
    n = theta.shape[1]
    rev = (~prismatic).to(theta)
    r_idx = torch.arange(n, device=theta.device)
    before = (r_idx[None, :] < r_idx[:, None]).to(theta)  # [r, s]: s before r
    sh = Jr.shape[:2] + (n, n, 3)
    # [t, b, r, s]: z_s x J_r (s before r, s revolute) + z_r x J_s (s at or after r, r revolute)
    lower = torch.linalg.cross(zz[:, :, None, :, :].expand(sh), Jr[:, :, :, None, :].expand(sh), dim=-1)
    upper = torch.linalg.cross(zz[:, :, :, None, :].expand(sh), Jr[:, :, None, :, :].expand(sh), dim=-1)
    H = lower * (before * rev[None, :])[..., None] + upper * ((1 - before) * rev[:, None])[..., None]
    return Jr.transpose(-1, -2), H.permute(0, 1, 4, 2, 3)


def machine_slope_context(model, q: torch.Tensor, P: torch.Tensor) -> dict:
    """The parts of :func:`machine_slope_terms` that depend on the points and tools only, not on the tables.

    q: (B, n); P: (T, 3). -> dict: 'design', 'ddesign' (B, n, K) (Chebyshev values and
    d/dq_j), 'JqA' (T, B, 3, n) = J_G(q), the nominal tool point's Jacobian. A fit
    evaluates the slope at the same points hundreds of times: computed once, these are
    half of each evaluation. Index a context with :func:`context_rows`.
    """
    from ..core.basis import chebyshev_with_derivative

    with torch.no_grad():
        ae = model.axis_errors
        A = model.coupling.to(q)
        design, dl = chebyshev_with_derivative(ae.normalized(q), ae.coef.shape[-1] - 1)
        lim = ae.limits.to(q)
        ddesign = dl * (2.0 / (lim[:, 1] - lim[:, 0]))[:, None]
        theta_q = q @ A.T + model.offset.to(q)
        Jq, _ = point_jacobian_and_hessian(model.origins, model.axes, model.prismatic, model.tip, theta_q, P, False)
        return {"design": design, "ddesign": ddesign, "JqA": Jq @ A}


def context_rows(context: dict, rows: torch.Tensor, tools=None) -> dict:
    """A :func:`machine_slope_context` for the points ``rows`` (and the tools ``tools``, a slice or indices) only."""
    JqA = context["JqA"] if tools is None else context["JqA"][tools]
    return {"design": context["design"][rows], "ddesign": context["ddesign"][rows], "JqA": JqA[:, rows]}


def machine_slope_terms(model, q: torch.Tensor, P: torch.Tensor, hessian: bool = False, context: dict | None = None) -> dict:
    """hbar (30) of a MachineModel in closed form, with what its coefficient Jacobian needs.

    e_t(q) = G(q + dq(q)) - G(q), G the nominal tool point: d e_t / d q =
    J_G(a) (I + D(q)) - J_G(q), a = q + dq(q), D = d dq / d q (the table slopes).
    q: (B, n); P: (T, 3) tool vectors; context: :func:`machine_slope_context` of
    (q, P) (None: computed here; a context must not be used where q needs a gradient).
    -> dict with 'hbar' (T, B, n, 3) and the
    pieces: 'JG' (T, B, 3, n) = J_G(a), 'HG' (T, B, 3, n, n) = d J_G(a)[..., m] / d a_i
    (with ``hessian``), 'ID' (B, n, n) = I + D, 'design', 'ddesign' (B, n, K):
    Chebyshev values and their derivative w.r.t. q_j per input axis.
    """
    from ..core.basis import chebyshev_with_derivative

    ae = model.axis_errors
    A = model.coupling.to(q)
    coef = ae.masked_coef()
    if context is None:
        design, dl = chebyshev_with_derivative(ae.normalized(q), ae.coef.shape[-1] - 1)
        lim = ae.limits.to(q)
        ddesign = dl * (2.0 / (lim[:, 1] - lim[:, 0]))[:, None]
        theta_q = q @ A.T + model.offset.to(q)
        Jq, _ = point_jacobian_and_hessian(model.origins, model.axes, model.prismatic, model.tip, theta_q, P, False)
        JqA = Jq @ A
    else:
        design, ddesign, JqA = context["design"], context["ddesign"], context["JqA"]
    a = q + torch.einsum("bjk,ijk->bi", design, coef)  # q + dq(q), as AxisPerturbation.delta
    theta_a = a @ A.T + model.offset.to(q)
    Ja, Ha = point_jacobian_and_hessian(model.origins, model.axes, model.prismatic, model.tip, theta_a, P, hessian)
    JG = Ja @ A
    D = torch.einsum("bjk,ijk->bij", ddesign, coef)
    ID = torch.eye(q.shape[1], dtype=q.dtype, device=q.device) + D
    dedq = JG @ ID - JqA
    out = {"hbar": (dedq * half_ranges(model).to(q)).transpose(-1, -2), "JG": JG, "ID": ID, "design": design,
           "ddesign": ddesign}
    if hessian:
        out["HG"] = torch.einsum("tbcrs,rm,si->tbcmi", Ha, A, A)
    return out


def machine_slope_norm_jacobian(model, q: torch.Tensor, p: torch.Tensor, axis: torch.Tensor, context: dict | None = None):
    """|hbar_m| at (q_b, m = axis_b) and its Jacobian w.r.t. ``axis_errors.coef``, closed form.

    q: (A, n) points; p: (3,) tool; axis: (A,) long, the axis m of each entry; context:
    :func:`machine_slope_context` of (q, p) or None.
    -> norms (A,), d norm / d coef (A, n, n, K) (masked entries zero).

    d hbar_m / d a_kij = half_m [HG[:, m, i] . (I + D)[:, m] design_jk + J_G[:, i] delta_jm ddesign_jk]
    """
    t = machine_slope_terms(model, q, p.reshape(1, 3), hessian=True, context=context)
    ar = torch.arange(q.shape[0], device=q.device)
    h = t["hbar"][0, ar, axis]  # (A, 3)
    nrm = h.norm(dim=-1)
    u = h / nrm.clamp(min=1e-300)[:, None]
    half = half_ranges(model).to(q)[axis]  # (A,)
    col = torch.einsum("bcmi,bm->bci", t["HG"][0], t["ID"][ar, :, axis])  # (A, 3, n_i): d J_G(a) (I+D)[:, m] / d a_i
    t1 = torch.einsum("bc,bci,bjk->bijk", u, col, t["design"])
    uj = torch.einsum("bc,bci->bi", u, t["JG"][0])  # (A, n_i)
    n = q.shape[1]
    onehot = torch.nn.functional.one_hot(axis, n).to(q)  # (A, n_j)
    t2 = uj[:, :, None, None] * (onehot[:, :, None] * t["ddesign"])[:, None, :, :]
    J = (t1 + t2) * half[:, None, None, None] * model.axis_errors.mask.to(q)
    return nrm, J


def model_slopes(model, q: torch.Tensor, tool=None, method: str = "auto") -> torch.Tensor:
    """hbar (30): slope of the modeled tool-tip error per axis, scaled to half the axis range.

    model: MachineModel or RobotModel; q: (B, n) commands, SI; tool: the tool
    vector: None = the longest nominal tool of the model, an index into its
    nominal tools, or a (3,) vector in m in the last frame; method: 'auto'
    (closed form for a MachineModel, :func:`machine_slope_terms`; forward-mode
    autograd otherwise) or 'autograd' (always torch.func.jacfwd, vmapped over points).
    -> (B, n, 3), m per half axis motion: hbar[b, i] = d e_t / d q_i (q_b) (q_i,max - q_i,min) / 2.

    Example:
        >>> import torch, torchcal
        >>> from torchcal.models.machine import MachineModel
        >>> robot = torchcal.load_robot("five_axis_xyzcb")
        >>> model = MachineModel(robot, torch.tensor([[0.0, 0.0, 0.5009]], dtype=torch.float64), orders=2)
        >>> with torch.no_grad():
        ...     _ = model.axis_errors.coef[2, 4, 1].fill_(1e-4)   # Z error growing linearly with B: 0.1 mm per half B range
        >>> h = model_slopes(model, robot.joint_map.limits.mean(1)[None])
        >>> round(float(h[0, 4].detach().norm()) * 1e3, 6)         # mm per half B motion
        0.1
    """
    if tool is None:
        nominal = model.tools.nominal
        p = nominal[nominal.norm(dim=1).argmax()]
    else:
        p = tool_vectors(model, tool)
        if p.shape[0] != 1:
            raise ValueError("model_slopes takes one tool; use slope_norms for several")
        p = p[0]
    return _slopes(model, q, p[None], method)[0]


def slope_norms(model, q: torch.Tensor, tools=None, context: dict | None = None) -> torch.Tensor:
    """|hbar_i|_2 for several tools: (T, B, n), m per half axis motion; tools as in :func:`tool_vectors`;
    context: :func:`slope_context` of (q, those tools) or None."""
    return _slopes(model, q, tool_vectors(model, tools), context=context).norm(dim=-1)


def max_slope(model, q: torch.Tensor, tools=None) -> float:
    """max over points, axes and tools of |hbar_i|_2 (m per half axis motion)."""
    with torch.no_grad():
        return float(slope_norms(model, q, tools).max())


class _SlopeNorms(nn.Module):
    """slope_norms(model, q, tools) as a module whose parameters are the model's (for functional_call)."""

    def __init__(self, model):
        super().__init__()
        self.model = model

    def forward(self, q, P, context=None):
        return _slopes(self.model, q, P, context=context).norm(dim=-1)


def functional_slope_norms(model, params: dict, q: torch.Tensor, P: torch.Tensor, context: dict | None = None) -> torch.Tensor:
    """slope_norms with the model's parameters replaced by ``params`` {name: tensor} (differentiable in them);
    context: :func:`machine_slope_context` / :func:`robot_slope_context` of (q, P), or None."""
    wrapper = _SlopeNorms(model)
    return functional_call(wrapper, {f"model.{k}": t for k, t in params.items()}, (q, P, context))


# ------------------------------------------------------------------ where the bound is imposed
def _sobol(d: int, count: int, seed: int) -> np.ndarray:
    if d == 0 or count == 0:
        return np.zeros((count, d))
    from scipy.stats import qmc  # scipy.stats takes ~1-2 s to import: only where Sobol points are drawn

    sampler = qmc.Sobol(d=d, scramble=True, seed=np.random.default_rng(seed))
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", UserWarning)  # balance is best at powers of two; any count is fine here
        return sampler.random(count)


def slope_points(limits: torch.Tensor, count: int = 512, seed: int = 0, face_count: int | None = None,
                 corners: bool = True) -> torch.Tensor:
    """Dense points over the WHOLE command box where the slope bound (31) is imposed or checked.

    limits: (n, 2) command range, SI; count: scrambled Sobol points inside the
    box (seeded); face_count: Sobol points on each of the 2n faces (default
    count // 4), the axis of the face at its lower or upper limit; corners: add
    all 2^n corners (n <= 12). -> (M, n) on ``limits``' device and dtype.
    Two seeds give disjoint quasi-random points (the corners are shared).

    Example:
        >>> lim = torch.tensor([[0.0, 1.0], [-2.0, 2.0]], dtype=torch.float64)
        >>> pts = slope_points(lim, count=16, seed=0)
        >>> pts.shape, bool(((pts >= lim[:, 0]) & (pts <= lim[:, 1])).all())
        (torch.Size([36, 2]), True)
    """
    lim = torch.as_tensor(limits)
    n = lim.shape[0]
    if lim.ndim != 2 or lim.shape[1] != 2 or not bool((lim[:, 0] < lim[:, 1]).all()):
        raise ValueError(f"slope_points: limits must be (n, 2) with lower < upper, got {lim.tolist()}")
    if count < 0:
        raise ValueError(f"slope_points: count must be >= 0, got {count}")
    face_count = count // 4 if face_count is None else int(face_count)
    parts = [_sobol(n, count, seed)]
    for i in range(n):
        for side in (0.0, 1.0):
            u = _sobol(n - 1, face_count, seed * 1009 + 2 * i + int(side) + 1)
            parts.append(np.insert(u, i, side, axis=1))
    if corners and n <= 12:
        parts.append(((np.arange(2 ** n)[:, None] >> np.arange(n)[None, :]) & 1).astype(np.float64))
    u = torch.from_numpy(np.concatenate(parts)).to(dtype=lim.dtype, device=lim.device)
    return lim[:, 0] + u * (lim[:, 1] - lim[:, 0])


def worst_points(model, q0: torch.Tensor, tools=None, steps: int = 30, lr: float = 0.05) -> torch.Tensor:
    """Local maxima of the slope near given points: projected gradient ascent in the command box.

    q0: (K, n) starting commands, SI; each start climbs max over axes and tools
    of |hbar| (Adam on the normalized commands, clamped to the box, ``steps``
    steps of size ``lr`` of the half range). -> (K, n) the points reached, SI.
    Used to find where a slope bound is tightest between quasi-random points.
    """
    lim = model.command_limits.to(q0)
    lo, span = lim[:, 0], lim[:, 1] - lim[:, 0]
    P = tool_vectors(model, tools)
    u = ((q0 - lo) / span).detach().clone().requires_grad_(True)
    # Adam (torch.optim.Adam's single-tensor update, written out: constructing the optimizer imports
    # torch._dynamo, seconds on a cold process)
    beta1, beta2, eps = 0.9, 0.999, 1e-8
    m1, m2 = torch.zeros_like(u), torch.zeros_like(u)
    fast = robot_fast_path(model)
    closed = fast and slope_model(model)[0].fine is None
    for step in range(1, steps + 1):
        qs = lo + u * span
        # robots: the closed form (or the central differences), first-order autograd (nested: ~10x the time)
        if closed:
            h = robot_slopes(model, qs, P)
        else:
            h = robot_slopes_differentiable(model, qs, P) if fast else _slopes(model, qs, P)
        nrm = h.norm(dim=-1)  # (T, K, n)
        g, = torch.autograd.grad(-nrm.amax(dim=(0, 2)).sum(), u)  # u only: the model's .grad stay untouched
        with torch.no_grad():
            m1.lerp_(g, 1 - beta1)
            m2.mul_(beta2).addcmul_(g, g, value=1 - beta2)
            denom = (m2.sqrt() / (1 - beta2 ** step) ** 0.5).add_(eps)
            u.addcdiv_(m1, denom, value=-lr / (1 - beta1 ** step))
            u.clamp_(0.0, 1.0)
    return (lo + u.detach() * span).detach()
