"""Initial alignment: the measurement frame and the tool vectors from the data alone.

Paper II assumes the tracker frame is near the robot base and the tool vectors
are known to a few millimetres, so its model (25)-(27) only identifies small
corrections around them. A real tracker stands metres away in its own frame,
and reflectors are glued to the flange where they fit. This module finds the
rigid part of the measurement model with no guess from the user,

    p_r = R_b (R_f(q_r) t_{tool_r} + p_f(q_r)) + b          (25) on the nominal chain

(R_b, b: the robot base seen in the measurement frame, the ``base_nominal`` of
:class:`torchcal.models.robot.RobotModel`; R_f, p_f: the nominal flange pose; t: tool
vectors in the flange frame), by least squares on the nominal kinematics, so
that the full MLE starts within the size of the robot's errors:

1. **closed-form start** (no guess): the model is linear in the lifted unknowns
   X_t = R_b ⊗ t (9 per tool), R_b and b, so one linear least squares over all
   rows gives R_b (projected onto SO(3)) and the tools; a second start
   registers the nominal flange origins on the measured points with
   :func:`kabsch` (tools ignored). Both are polished below and the better one kept.
2. **alternation**: given the frame, each tool vector is a linear least-squares
   solution (closed form: a mean of R_f^T (R_b^T (p - b) - p_f)); given the
   tools, the frame is a Kabsch registration of the modeled points on the
   measured ones.
3. **rigid refinement**: Levenberg-Marquardt on (frame twist, tool vectors)
   only, to convergence.

Any pattern of measured rows works (a reflector need not be seen at every
pose); the pose ids are not used. Everything is SI and batched over rows.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import torch

from ..core import units
from ..kinematics.fk import chain_fk
from ..kinematics.transforms import homogeneous, kabsch, matrix_to_rpy, nearest_rotation, skew, twist_to_transform  # noqa: F401 (kabsch, nearest_rotation: re-exported)
from ..core.exceptions import TorchcalError
from ..core.measurements import Measurements


class AlignmentError(TorchcalError, ValueError):
    """The data cannot determine the frame and tool vectors (missing tool, too few or degenerate poses)."""


# -------------------------------------------------------------------- result
@dataclass
class AlignmentResult:
    """What :func:`align` found.

    base_nominal: (4, 4) the robot base in the measurement frame (SI), what
    :class:`~torchcal.models.robot.RobotModel` takes as ``base_nominal``; tools: (T, 3)
    tool vectors in the flange frame, m; residuals: (R,) m, per row, of the
    rigid model on the nominal chain; rms / mean / max: of those, m;
    iterations: alternation + refinement steps; converged: the refinement met
    its tolerance; start: which closed-form start won ('lifted' or 'flange');
    estimated_frame / estimated_tools: what was free (the rest was given).
    """

    base_nominal: torch.Tensor
    tools: torch.Tensor
    residuals: torch.Tensor
    rms: float
    mean: float
    max: float
    iterations: int
    converged: bool
    start: str
    estimated_frame: bool = True
    estimated_tools: bool = True
    history: list[float] = field(default_factory=list, repr=False)

    def summary(self) -> dict:
        """A JSON-ready record in file units (mm, deg): frame as matrix and as xyz / rpy, tools, residuals."""
        T = self.base_nominal.detach().cpu()
        M = T.clone()
        M[:3, 3] = units.m_to_mm(M[:3, 3])
        return {
            "units": "mm, deg",
            "estimated_frame": self.estimated_frame,
            "estimated_tools": self.estimated_tools,
            "frame": {"description": "robot base in the measurement frame: p_measured = R p_base + xyz",
                      "xyz_mm": units.m_to_mm(T[:3, 3]).tolist(),
                      "rpy_deg": units.rad_to_deg(matrix_to_rpy(T[:3, :3])).tolist(),
                      "matrix_mm": M.tolist()},
            "tools_mm": units.m_to_mm(self.tools.detach().cpu()).tolist(),
            "residual_mm": {"rms": units.m_to_mm(self.rms), "mean": units.m_to_mm(self.mean), "max": units.m_to_mm(self.max),
                            "rows": int(self.residuals.numel())},
            "iterations": self.iterations,
            "converged": self.converged,
            "start": self.start,
        }


# ------------------------------------------------------------------- pieces
def _nominal_flange(robot, q: torch.Tensor) -> torch.Tensor:
    """Nominal flange poses (R, 4, 4) in the robot base frame for controller commands q (R, n)."""
    c = robot.chain
    theta = robot.joint_map.to_joint(q)
    return chain_fk(c.origins.to(q), c.axes.to(q.device), c.prismatic.to(q.device), theta, None, c.tip.to(q))


def _points(Rb, b, Rf, pf, tools, tool):
    """Modeled points (R, 3): R_b (R_f t + p_f) + b."""
    x = (Rf @ tools[tool][..., None])[..., 0] + pf
    return x @ Rb.T + b, x


def solve_tools(Rb, b, Rf, pf, xyz, tool, T: int) -> torch.Tensor:
    """Tool vectors (T, 3) given the frame: t = mean over the tool's rows of R_f^T (R_b^T (p - b) - p_f).

    The exact linear least-squares solution, since R_f^T R_f = I. Rb (3, 3), b (3,),
    Rf (R, 3, 3), pf (R, 3), xyz (R, 3), tool (R,) long.
    """
    y = (xyz - b) @ Rb - pf  # R_b^T (p - b) - p_f, row-wise
    z = (Rf.transpose(-1, -2) @ y[..., None])[..., 0]
    s = torch.zeros(T, 3, dtype=xyz.dtype, device=xyz.device).index_add_(0, tool, z)
    cnt = torch.zeros(T, dtype=xyz.dtype, device=xyz.device).index_add_(0, tool, torch.ones_like(z[:, 0]))
    return s / cnt[:, None]


def _lifted_start(Rf, pf, xyz, tool, T: int):
    """Closed-form start: linear least squares in X_t = R_b ⊗ t, R_b, b; None if rank-deficient."""
    R = xyz.shape[0]
    ncol = 9 * T + 4
    if R < ncol:
        return None
    A = torch.zeros(R, ncol, dtype=xyz.dtype, device=xyz.device)
    cols = 9 * tool[:, None] + torch.arange(9, device=xyz.device)  # (R, 9)
    A.scatter_(1, cols, Rf.reshape(R, 9))
    A[:, 9 * T: 9 * T + 3] = pf
    A[:, -1] = 1.0
    # columns are O(1) (rotation entries) and O(reach) (positions); scale for a well-posed solve
    scale = A.abs().amax(0).clamp_min(1e-12)
    As = A / scale
    sv = torch.linalg.svdvals(As)
    if not bool(sv[-1] > 1e-9 * sv[0]):
        return None
    X = torch.linalg.pinv(As) @ xyz / scale[:, None]  # (ncol, 3)
    Rb = nearest_rotation(X[9 * T: 9 * T + 3].T)
    Xt = X[: 9 * T].reshape(T, 3, 3, 3)  # [tool, i, j, k] = R_b[k, i] t_j
    tools = torch.einsum("ki,tijk->tj", Rb, Xt) / 3.0
    b = (xyz - _points(Rb, torch.zeros_like(X[-1]), Rf, pf, tools, tool)[0]).mean(0)
    return Rb, b


def _alternate(Rb, b, tools, Rf, pf, xyz, tool, T, free_frame, free_tools, steps, tol):
    """Block coordinate descent: tools | frame (linear LS), frame | tools (Kabsch)."""
    cost = math.inf
    hist = []
    k = 0
    for k in range(1, steps + 1):
        if free_tools:
            tools = solve_tools(Rb, b, Rf, pf, xyz, tool, T)
        if free_frame:
            _, x = _points(Rb, b, Rf, pf, tools, tool)
            Rb, b = kabsch(x, xyz)
        new = float(((_points(Rb, b, Rf, pf, tools, tool)[0] - xyz) ** 2).sum())
        hist.append(new)
        done = cost - new <= tol * new or not (free_tools and free_frame)
        cost = new
        if done:
            break
    return Rb, b, tools, cost, k, hist


def _refine(Rb, b, tools, Rf, pf, xyz, tool, T, free_frame, free_tools, max_iter, tol):
    """Levenberg-Marquardt on the frame twist (robot side, as in FrameCorrection) and the tool vectors."""
    R = xyz.shape[0]
    dev, dt = xyz.device, xyz.dtype
    nf = 6 if free_frame else 0
    P = nf + (3 * T if free_tools else 0)
    rows = torch.arange(R, device=dev)

    def residual(Rb, b, tools):
        p, x = _points(Rb, b, Rf, pf, tools, tool)
        return p - xyz, x

    r, x = residual(Rb, b, tools)
    cost = float((r**2).sum())
    mu, hist, converged, it = 1e-6, [cost], False, 0
    H = None
    for it in range(1, max_iter + 1):
        J = torch.zeros(R, 3, P, dtype=dt, device=dev)
        if free_frame:  # T_b E(eps, delta) x = R_b (exp(eps) x + delta) + b
            J[:, :, :3] = -Rb @ skew(x)
            J[:, :, 3:6] = Rb.expand(R, 3, 3)
        if free_tools:
            Jt = torch.zeros(R, 3, T, 3, dtype=dt, device=dev)
            Jt[rows, :, tool, :] = Rb @ Rf
            J[:, :, nf:] = Jt.reshape(R, 3, 3 * T)
        Jf = J.reshape(3 * R, P)
        H = Jf.T @ Jf
        g = Jf.T @ r.reshape(-1)
        improved = False
        while mu < 1e12:
            step = torch.linalg.solve(H + mu * torch.diag(torch.diagonal(H).clamp_min(1e-30)), -g)
            Rb2, b2, tools2 = Rb, b, tools
            if free_frame:
                E = twist_to_transform(step[:6])
                Rb2, b2 = Rb @ E[:3, :3], Rb @ E[:3, 3] + b
            if free_tools:
                tools2 = tools + step[nf:].reshape(T, 3)
            r2, x2 = residual(Rb2, b2, tools2)
            new = float((r2**2).sum())
            if new <= cost:
                Rb, b, tools, r, x = Rb2, b2, tools2, r2, x2
                mu = max(mu / 10.0, 1e-12)
                improved = True
                break
            mu *= 10.0
        if not improved:
            converged = True  # no descent left: at the minimum to machine precision
            break
        rel = (cost - new) / max(cost, 1e-300)
        cost = new
        hist.append(cost)
        if rel < tol or float(step.abs().max()) < 1e-13:
            converged = True
            break
    return Rb, b, tools, r, it, converged, hist, H


# ---------------------------------------------------------------------- entry
def align(robot, data: Measurements, n_tools: int | None = None, tools: torch.Tensor | None = None,
          frame: torch.Tensor | None = None, alternations: int = 50, max_iter: int = 100, tol: float = 1e-12,
          start: str = "best") -> AlignmentResult:
    """Estimate the measurement frame and / or the tool vectors on the nominal chain, with no guess.

    robot: :class:`~torchcal.kinematics.robot.Robot`; data: measurements (q, tool, xyz; SI);
    n_tools: T (default: tools' count, else 1 + the largest tool index);
    tools: (T, 3) m known tool vectors (held fixed) or None (estimated);
    frame: (4, 4) known robot base in the measurement frame (held fixed) or None (estimated);
    alternations / max_iter / tol: limits of the alternation and of the LM refinement
    (relative cost decrease); start: closed-form start(s) when the frame is free,
    'best' (both, keep the better), 'lifted' or 'flange' (see the module docstring).
    -> :class:`AlignmentResult`. Raises :class:`AlignmentError` when a tool has
    no rows or the poses cannot determine the unknowns.
    """
    xyz, q, tool = data.xyz, data.q, data.tool.long()
    dev, dt = xyz.device, xyz.dtype
    where = data.source or "measurements"
    if torch.isnan(xyz).any():
        r = int(data.rows[torch.isnan(xyz).any(1)][0])
        raise AlignmentError(f"{where}: row {r} has no measured point (x, y, z); alignment needs measured rows")
    if n_tools is None:
        n_tools = tools.shape[0] if tools is not None else int(tool.max()) + 1
    T = int(n_tools)
    if tools is not None:
        tools = torch.as_tensor(tools).to(xyz)
        if tools.shape != (T, 3):
            raise AlignmentError(f"tools must have shape ({T}, 3), got {tuple(tools.shape)}")
    if len(tool) and (int(tool.min()) < 0 or int(tool.max()) >= T):
        bad = (tool < 0) | (tool >= T)
        raise AlignmentError(f"{where}: row {int(data.rows[bad][0])}: tool index {int(tool[bad][0])} outside 0..{T - 1}")
    free_frame, free_tools = frame is None, tools is None
    if free_tools:
        seen = torch.zeros(T, dtype=torch.bool, device=dev)
        seen[tool] = True
        if not bool(seen.all()):
            missing = (~seen).nonzero()[:, 0].tolist()
            raise AlignmentError(f"{where}: no rows measured with tool(s) {missing}; their vectors cannot be estimated")
    if free_frame and len(xyz) < 3:
        raise AlignmentError(f"{where}: {len(xyz)} rows cannot determine a frame (at least 3 points, better dozens of poses)")

    F = _nominal_flange(robot, q.to(dt))
    Rf, pf = F[:, :3, :3], F[:, :3, 3]

    starts = []
    if not free_frame:
        frame = torch.as_tensor(frame).to(xyz)
        Rb0, b0 = frame[:3, :3], frame[:3, 3]
        starts.append(("given", Rb0, b0))
    else:
        if start not in ("best", "lifted", "flange"):
            raise ValueError(f"align: start must be 'best', 'lifted' or 'flange', got {start!r}")
        if start in ("best", "lifted") and free_tools:
            lifted = _lifted_start(Rf, pf, xyz, tool, T)
            if lifted is not None:
                starts.append(("lifted", *lifted))
            elif start == "lifted":
                raise AlignmentError(f"{where}: too few or degenerate rows for the lifted linear start "
                                     f"({len(xyz)} rows, {9 * T + 4} unknowns)")
        if start in ("best", "flange") or not free_tools:
            zero = torch.zeros(T, 3, dtype=dt, device=dev) if tools is None else tools
            # flange origins (or the known tool points) registered on the measured points
            starts.append(("flange", *kabsch(_points(torch.eye(3, dtype=dt, device=dev),
                                                     torch.zeros(3, dtype=dt, device=dev), Rf, pf, zero, tool)[0], xyz)))

    best = None
    for name, Rb, b in starts:
        t0 = solve_tools(Rb, b, Rf, pf, xyz, tool, T) if free_tools else tools
        Rb, b, t0, cost, k, hist = _alternate(Rb, b, t0, Rf, pf, xyz, tool, T, free_frame, free_tools, alternations, 1e-6)
        if best is None or cost < best[4]:
            best = (name, Rb, b, t0, cost, k, hist)
    name, Rb, b, t0, _, k_alt, hist = best

    Rb, b, t0, r, it, converged, hist2, H = _refine(Rb, b, t0, Rf, pf, xyz, tool, T, free_frame, free_tools, max_iter, tol)
    if H is not None and H.numel():
        ev = torch.linalg.eigvalsh(H)
        if not bool(ev[0] > 1e-12 * ev[-1]):
            raise AlignmentError(f"{where}: the poses do not determine the {'frame and ' if free_frame else ''}"
                                 f"{'tool vectors' if free_tools else 'frame'} (singular normal matrix, condition "
                                 f"{float(ev[-1] / ev[0].clamp_min(1e-300)):.3g}); measure more varied flange orientations")
    res = r.norm(dim=-1)
    return AlignmentResult(
        base_nominal=homogeneous(Rb, b), tools=t0, residuals=res, rms=float(res.pow(2).mean().sqrt()),
        mean=float(res.mean()), max=float(res.max()), iterations=k_alt + it, converged=converged, start=name,
        estimated_frame=free_frame, estimated_tools=free_tools, history=hist + hist2)


__all__ = ["AlignmentError", "AlignmentResult", "align", "kabsch", "nearest_rotation", "solve_tools"]
