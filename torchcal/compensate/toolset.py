"""The frame compensation puts where the nominal flange would be: the identified tool set's, not the bare flange's.

Point measurements see the tool points F_a(q) t_k, never the flange alone.
When the fit identifies the tool vectors t_k (always their corrections (27);
all of them when the tools are only counted), a rigid motion G of the flange
frame with the tool vectors moved by G^-1 predicts the same points: the
modeled flange is fixed only up to such a G (exactly along the gauge that
:mod:`torchcal.identify.gauge` pins, nearly along the near-redundant series
the prior holds). On the real IRB 120 with its reflectors' positions
estimated, two models within 0.03 mm of each other on the held-out points had
flanges 12 mm apart, and (46) on the bare flange moved the reflectors 13 mm
off their programmed points (the robot's own error: 0.7 mm).

Our reading of (46) for identified tools, stated because Paper II's tool
vectors are known designs with small corrections (where both readings agree
to those corrections): the frame that must reach the nominal flange
F_n(q_nom) is F_a(q) G, where G is the rigid motion that best carries the
nominal tool vectors onto the identified ones (least squares over the tools,
:func:`tool_set_frame`). Then the tool points land on the nominal robot's
points F_n(q_nom) t_nominal,k up to the tool set's non-rigid difference (a
tool that is itself bent), and any two models that predict the same points
give the same commands. Two tools, or tools on one line, fix their line's direction but not the turn
about it: G is then the smallest rotation carrying the nominal line onto the identified one (no turn about
the line, which 5-DOF compensation leaves free) and the mean's translation; one tool (or tools that
coincide) fixes no orientation: G is the mean translation.

Shapes: nominal, identified (T, 3) m; G (4, 4).
"""

from __future__ import annotations

import math

import torch

from ..core.exceptions import InputError
from ..kinematics.transforms import kabsch, orthogonal_unit, so3_exp

TOOL_SET_MAX_DEG = 30.0
"""deg: a tool set whose identified vectors are its nominal ones turned further than this is not these tools
(labels swapped in the data, another tool's vectors in the config): G is refused, since compensation would turn
the flange by as much. Reflector mounts differ from their drawings by a few degrees."""

LINE_TOL = 1e-3
"""m: tools whose second spread (singular value of the centred nominal vectors) is below this lie on one line
(G's rotation is then the line's tilt alone); whose first is below it coincide (G a translation)."""


def tool_set_frame(nominal: torch.Tensor, identified: torch.Tensor) -> torch.Tensor:
    """The rigid motion G (4, 4) with G t_nominal,k ~ t_identified,k in least squares (Kabsch for three or more tools
    off one line; for tools on one line the smallest rotation between the lines, no turn about them; for one
    tool the translation alone).

    Example:
        >>> import torch
        >>> t = torch.tensor([[0.0, 0.0, 0.1], [0.05, 0.0, 0.1], [0.0, 0.05, 0.1]], dtype=torch.float64)
        >>> G = tool_set_frame(t, t + torch.tensor([0.0, 0.0, 0.002], dtype=torch.float64))
        >>> torch.allclose(G[:3, 3], torch.tensor([0.0, 0.0, 0.002], dtype=torch.float64))
        True
    """
    if nominal.shape != identified.shape or nominal.ndim != 2 or nominal.shape[1] != 3:
        raise InputError(f"tool_set_frame: nominal and identified must both be (T, 3), got {tuple(nominal.shape)} "
                         f"and {tuple(identified.shape)}")
    a, b = nominal.to(torch.float64), identified.to(torch.float64)
    G = torch.eye(4, dtype=torch.float64, device=a.device)
    ca, cb = a.mean(0), b.mean(0)
    A, Bc = a - ca, b - cb
    R = torch.eye(3, dtype=torch.float64, device=a.device)
    spread = torch.linalg.svdvals(A) if a.shape[0] >= 2 else torch.zeros(3, dtype=torch.float64, device=a.device)
    if a.shape[0] >= 3 and float(spread[1]) > LINE_TOL:
        R = kabsch(a, b)[0]
    elif float(spread[0]) > LINE_TOL:
        if float(torch.linalg.svdvals(Bc)[0]) <= LINE_TOL:
            raise InputError("the identified tools coincide where their nominal vectors do not: the data measured one "
                             "point under several tool labels; check the file's 'tool' column and fit again")
        R = _line_rotation(A, Bc)
    turn = math.degrees(math.acos(max(-1.0, min(1.0, (float(R.trace()) - 1.0) / 2.0))))  # up to 180: no log
    if turn > TOOL_SET_MAX_DEG:
        raise InputError(f"the identified tool vectors are the nominal ones turned by {turn:.0f} deg (more than "
                         f"{TOOL_SET_MAX_DEG:g}): these are not the configured tools, or their labels are swapped in "
                         "the data (compensation would turn the flange by as much); check the 'tool' column and the "
                         "config's tool vectors, and fit again")
    G[:3, :3] = R
    G[:3, 3] = cb - R @ ca
    return G


def _line_rotation(A: torch.Tensor, B: torch.Tensor) -> torch.Tensor:
    """The smallest rotation (3, 3) carrying the line of the centred points A (T, 3) onto that of B (T, 3).

    Two tools (or tools on one line) fix their line's direction and nothing about the turn about it, so G takes
    the tilt the points show and no turn: its axis is orthogonal to both lines. Leaving the tilt out (G a pure
    translation) made 5-DOF compensation restore the modeled flange's orientation instead of the tools' line,
    which the fit's gauge is free to tilt: a 2-reflector FANUC landed its reflectors 0.09 mm off (1 and 3
    reflectors: 0.02 mm).
    """
    a = torch.linalg.svd(A, full_matrices=False)[2][0]
    b = (A @ a) @ B  # B's line, signed by the correspondence of the points along A's (swapped labels: reversed)
    b = b / b.norm()
    v = torch.linalg.cross(a, b)
    s = v.norm()
    if float(s) < 1e-15:  # parallel (or reversed, which the turn check refuses): no tilt about a defined axis
        return so3_exp(torch.zeros_like(v)) if float(a @ b) > 0 else so3_exp(math.pi * orthogonal_unit(a))
    return so3_exp(v / s * torch.atan2(s, a @ b))


def model_tool_set_frame(model) -> torch.Tensor | None:
    """G (4, 4) of a model with nominal and identified tool vectors (``model.tools.nominal``, ``model.tools()``),
    judged on the tools its data measured (``model.measured_tools``, as :func:`observed_dof`), on the model's
    device and dtype; None where the two are equal (G the identity: nothing to change) or the
    model carries no tool vectors."""
    tools = getattr(model, "tools", None)
    nominal = getattr(tools, "nominal", None)
    if nominal is None or not callable(tools):
        return None
    with torch.no_grad():
        identified = tools().detach()
        if torch.equal(identified, nominal):
            return None
        seen = getattr(model, "measured_tools", None)
        if seen is not None:  # a tool the data never measured keeps its nominal vector: no evidence of G
            keep = [i for i in seen if i < identified.shape[0]]
            if keep:
                nominal, identified = nominal[keep], identified[keep]
        return tool_set_frame(nominal, identified).to(identified.device, identified.dtype)


def observed_dof(model) -> tuple[int, torch.Tensor | None]:
    """How much of the tool set's pose the model's point data fix: -> (dof, axis).

    (6, None) for three or more tools off one line; (5, axis) for two tools or tools on one line, ``axis`` (3,)
    their line's direction in the modeled flange frame (the turn about it is seen by no tool); (3, None) for one
    tool (a single reflector: no orientation at all). Judged on the identified tool vectors (a set whose tools are
    only counted has zero nominal vectors) of the tools its data measured (``model.measured_tools``, set by the fit;
    all where unknown). A model without tool vectors (a sensor rig) -> (6, None).
    """
    tools = getattr(model, "tools", None)
    if tools is None or not callable(tools):
        return 6, None
    with torch.no_grad():
        t = tools().detach().to(torch.float64)
    seen = getattr(model, "measured_tools", None)
    if seen is not None:  # a tool the data never measured fixes nothing (its vector is its nominal one)
        t = t[[i for i in seen if i < t.shape[0]]]
    if t.shape[0] < 2:
        return 3, None
    c = t - t.mean(0)
    _, S, Vh = torch.linalg.svd(c)
    if t.shape[0] >= 3 and float(S[1]) > LINE_TOL:
        return 6, None
    if float(S[0]) <= LINE_TOL:  # tools that coincide: one point
        return 3, None
    return 5, Vh[0].to(tools().dtype)


def row_tool_points(model, tool: torch.Tensor) -> torch.Tensor:
    """(R,) tool indices -> (R, 3) each row's identified tool point (flange frame, m, detached): the point 3- and
    5-DOF compensation restore (``compensate(..., tool_point=)``)."""
    with torch.no_grad():
        return model.tools().detach().to(model.device, model.dtype)[tool.to(model.device)]


def inverse(G: torch.Tensor) -> torch.Tensor:
    """The inverse (4, 4) of a rigid motion G (4, 4)."""
    out = torch.eye(4, dtype=G.dtype, device=G.device)
    out[:3, :3] = G[:3, :3].T
    out[:3, 3] = -(G[:3, :3].T @ G[:3, 3])
    return out


def compensation_goal(model, q_nom: torch.Tensor, target: torch.Tensor | None = None,
                      tool_set: bool = True) -> torch.Tensor:
    """The pose (B, 4, 4) the modeled flange ``model.flange(q_new, direction, base=False)`` reaches when
    :func:`~torchcal.compensate.newton.compensate` converges: ``target`` (or F_n(q_nom)) times the inverse of
    the tool-set frame (with ``tool_set``; the bare goal where the identified tools equal the nominal ones)."""
    with torch.no_grad():
        goal = model.nominal_flange(q_nom) if target is None else target
        G = model_tool_set_frame(model) if tool_set else None
        return goal if G is None else goal @ inverse(G).to(goal)


def in_tool_set(G: torch.Tensor, t: torch.Tensor) -> torch.Tensor:
    """Points t (..., 3) of the modeled flange expressed in the tool set's frame: G^-1 t (the identified tool
    vectors become the nominal ones, up to the tool set's non-rigid difference)."""
    return (t - G[:3, 3].to(t)) @ G[:3, :3].to(t)


def tool_poses(model, q: torch.Tensor, tool: torch.Tensor, direction: torch.Tensor | None = None) -> torch.Tensor:
    """Tool poses (B, 4, 4) in the robot's nominal base frame at commands q (B, n): the identified tool point
    ``tool`` (B,) with the tool set's orientation (the frame compensation puts in the nominal flange's place);
    the position is the modeled tool point whatever G is."""
    with torch.no_grad():
        F = model.flange(q, direction, base=False)
        t = model.tools()[tool]
        G = model_tool_set_frame(model)
        if G is not None:
            F, t = F @ G, in_tool_set(G, t)
        out = F.clone()
        out[:, :3, 3] = F[:, :3, 3] + (F[:, :3, :3] @ t[..., None])[..., 0]
        return out


__all__ = ["LINE_TOL", "compensation_goal", "in_tool_set", "tool_poses", "inverse", "model_tool_set_frame", "observed_dof", "row_tool_points",
           "tool_set_frame"]
