"""Cartesian targets in, calibrated joint commands and corrected targets out: a robot program filter.

Robot programs are written as Cartesian targets (a tool pose in the robot's
base frame) that the controller's *nominal* inverse kinematics turns into
joint commands. :func:`compensate_targets` gives, for a batch of targets:

- the joint commands that put the tool there on the calibrated model: the
  controller's nominal IK from its seed (nominal tool), then Paper II's
  compensation (46)-(52) from that command to the flange pose that puts the
  model's identified tool on the target (:func:`.newton.compensate` with
  ``target=``);
- the corrected target to send to a controller that keeps its nominal IK
  and nominal tool data: the nominal pose of those commands, so that the
  controller's own IK of it gives them back (on the seed's branch).

The branch is the controller's: every row starts from a seed command (the
command the controller's IK chooses for the target, or any command near it on
the same branch: configuration flags become a seed by the controller's own
program). Rows whose nominal IK cannot reach the target, or whose
compensation is flagged, say why in ``reason``.

On the CPU (float64, 6 joints, numba) the rows go through one compiled pass
first (:mod:`.fused_targets`; on Paper II's FANUC, 2 cores: ~1e5 targets/s
against 4 000-20 000 for the batched solves alone); the rows it hands on (near
a singularity, beyond a bound, a seed far from the target) are solved by the
batched path.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import torch

from ..core.exceptions import InputError
from ..core.contract import require
from ..kinematics.transforms import homogeneous, matrix_to_rpy, rpy_to_matrix
from .damped import damped_least_squares
from .newton import CompensationResult, compensate, compiled_pass_setup, compiled_rows, fill_rows
from .result import JOINT_LIMIT, range_and_coverage
from .toolset import in_tool_set, inverse, model_tool_set_frame

FAST_MIN_TARGETS = 64
"""Batches smaller than this skip the compiled pass (its first call in a process loads numba's cached code)."""


@dataclass
class TargetResult:
    """Outcome of :func:`compensate_targets` for B targets.

    q: (B, n) calibrated joint commands (rad / m); q_nominal: (B, n) the
    nominal IK's commands for the same target and tool (what the controller
    would run without calibration); command_target: (B, 4, 4) the corrected
    tool pose to send to a controller that runs nominal IK with the nominal
    tool; converged: (B,) bool; reason: per row '' or why it is flagged;
    compensation: the :class:`CompensationResult` of the second stage.
    """

    q: torch.Tensor
    q_nominal: torch.Tensor
    command_target: torch.Tensor
    converged: torch.Tensor
    reason: list[str] = field(default_factory=list)
    compensation: CompensationResult | None = None


def target_poses(position: torch.Tensor, orientation: torch.Tensor) -> torch.Tensor:
    """Poses (B, 4, 4) from positions (B, 3) and orientations: (B, 3) URDF roll-pitch-yaw (fixed X, Y, Z) or
    (B, 4) unit quaternions (w, x, y, z). SI."""
    if orientation.shape[-1] == 3:
        return homogeneous(rpy_to_matrix(orientation), position)
    w, x, y, z = orientation.unbind(-1)
    R = torch.stack([
        torch.stack([1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)], -1),
        torch.stack([2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)], -1),
        torch.stack([2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)], -1),
    ], -2)
    return homogeneous(R, position)


def pose_rpy(T: torch.Tensor) -> torch.Tensor:
    """Poses (B, 4, 4) -> (B, 6): x, y, z and URDF roll-pitch-yaw, SI (the inverse of :func:`target_poses`)."""
    return torch.cat([T[:, :3, 3], matrix_to_rpy(T[:, :3, :3])], 1)


def tool_pose(F: torch.Tensor, t: torch.Tensor) -> torch.Tensor:
    """Flange poses (B, 4, 4) and tool points (B, 3) in the flange frame -> tool poses (B, 4, 4) (the flange's
    orientation at the tool point: the run's tools are points)."""
    return homogeneous(F[:, :3, :3], F[:, :3, 3] + (F[:, :3, :3] @ t[..., None])[..., 0])


def flange_for(T: torch.Tensor, t: torch.Tensor) -> torch.Tensor:
    """Tool poses (B, 4, 4) and tool points (B, 3) -> the flange poses that put the tool there."""
    return homogeneous(T[:, :3, :3], T[:, :3, 3] - (T[:, :3, :3] @ t[..., None])[..., 0])


@torch.no_grad()
def compensate_targets(model, target: torch.Tensor, seed: torch.Tensor, tool=0, direction: torch.Tensor | None = None,
                       ik_tol: float = 1e-10, ik_max_iter: int = 100, free_tool_axis=None, position_only: bool = False,
                       **options) -> TargetResult:
    """Calibrated joint commands and corrected Cartesian targets for tool poses in the robot's base frame.

    model: a model that compensates commands (:class:`torchcal.models.robot.RobotModel`,
    see :mod:`torchcal.core.contract`); target: (B, 4, 4) tool poses in the
    robot's nominal base frame, SI; seed: (B, n) commands on the branch the
    controller uses (rad / m); tool: an index or (B,) indices into the model's
    tools; direction: (B, n) approach directions or None; ik_tol / ik_max_iter:
    the nominal IK's step tolerance and iterations; free_tool_axis: None (6-DOF) or True / a (3,) direction
    in the flange frame: an axisymmetric tool, the rotation about its axis (through the model's identified
    tool point) left free in the compensation (:mod:`.axis`; the tool point and the axis's direction are
    reached, with less joint motion next to the wrist); position_only: the identified tool point's position
    alone (3-DOF, a model fitted from one point per pose); options: for :func:`.newton.compensate`
    (max_correction, tol, ...). -> :class:`TargetResult`.

    Example:
        >>> import torch, torchcal
        >>> robot = torchcal.load_robot("fanuc_lrmate200i")
        >>> model = torchcal.RobotModel(robot, torch.tensor([[0.0, 0.0, 0.1]], dtype=torch.float64), orders=0)
        >>> with torch.no_grad():
        ...     model.joint_errors.coef[:, 2, 0] = 1e-3
        >>> q = torch.tensor([[0.1, 0.2, 0.3, 0.4, 0.5, 0.6]], dtype=torch.float64)
        >>> T = model.nominal_flange(q) @ torch.tensor([[1, 0, 0, 0], [0, 1, 0, 0], [0, 0, 1, 0.1], [0, 0, 0, 1.0]],
        ...                                              dtype=torch.float64)      # the tool's pose
        >>> res = compensate_targets(model, T, seed=q)
        >>> bool(res.converged[0]), float((res.q_nominal - q).abs().max()) < 1e-9
        (True, True)
    """
    require(model, "compensate commands", "compensate_targets")
    if target.ndim != 3 or target.shape[1:] != (4, 4):
        raise InputError(f"compensate_targets: target must be (B, 4, 4) poses, got {tuple(target.shape)}")
    B = target.shape[0]
    if seed.shape != (B, model.n):
        raise InputError(f"compensate_targets: seed must be ({B}, {model.n}) commands, got {tuple(seed.shape)}")
    from .newton import refuse_degrees

    refuse_degrees(model, seed, "compensate_targets: seed")
    dev, dt = model.device, seed.dtype
    tool = torch.as_tensor(tool, device=dev, dtype=torch.long).expand(B)
    if bool(((tool < 0) | (tool >= model.tools.count)).any()):
        raise InputError(f"compensate_targets: tool indices must lie in 0..{model.tools.count - 1}")
    t_nominal = model.tools.nominal.to(dev, dt)[tool]
    t_identified = model.tools().to(dev, dt)[tool]
    if free_tool_axis is not None and free_tool_axis is not False:
        options = dict(options, free_tool_axis=free_tool_axis, tool_point=t_identified)
    if position_only:
        options = dict(options, position_only=True, tool_point=t_identified)
    # the identified tool point in the tool set's frame (.toolset), which compensate() puts on the flange goal
    G = model_tool_set_frame(model) if options.get("tool_set", True) else None
    t_actual = t_identified if G is None else in_tool_set(G, t_identified)
    fast = _fast_pass(model, target, seed, direction, t_nominal, t_actual, ik_tol, ik_max_iter, options, G)
    if fast is None:
        return _general(model, target, seed, direction, t_nominal, t_actual, ik_tol, ik_max_iter, options)
    return _merged(model, fast, target, seed, direction, t_nominal, t_actual, ik_tol, ik_max_iter, options)


def _general(model, target, seed, direction, t_nominal, t_actual, ik_tol, ik_max_iter, options,
             solved_ik: bool = False) -> TargetResult:
    """Every row by batched solves: the controller's nominal IK from the seed, then :func:`.newton.compensate`
    from that command to the flange goal of the identified tool (robust near singularities and bounds; every
    flagged row gets its reason). solved_ik: the seeds are the compiled pass's converged nominal IK commands (rows
    it handed on): not solved again (from there the IK would stop at once, for ~0.01 s a call)."""
    # the controller's view: nominal IK for the nominal tool (its command: the start, the bounds' and the branch's
    # reference)
    if solved_ik:
        q_ik, reached = seed, torch.ones(seed.shape[0], dtype=torch.bool, device=seed.device)
    else:
        ik_c = damped_least_squares(nominal_model(model), seed, flange_for(target, t_nominal), None, tol=ik_tol,
                                    max_iter=ik_max_iter)
        q_ik, reached = ik_c.q, ik_c.converged
    comp = compensate(model, q_ik, direction, target=flange_for(target, t_actual), **options)
    if not bool(reached.all()):
        # out of reach: the IK's last iterate is no command (a helper's 5 m target came back with J2 at 803 deg
        # while max_dq said 30): the row keeps its seed, unmoved, and is flagged
        away = ~reached
        q_ik = torch.where(away[:, None], seed, q_ik)
        comp.q = torch.where(away[:, None], seed, comp.q)
        comp.correction = torch.where(away, torch.zeros_like(comp.correction), comp.correction)
        comp.converged = comp.converged & reached
        comp.within_limits, comp.direction_outside = range_and_coverage(model, comp.q, direction)
    ok = reached & comp.converged & comp.within_limits
    command = tool_pose(model.nominal_flange(comp.q), t_nominal)
    reason = comp.reasons(options.get("max_correction"), model.robot.joint_map.prismatic)
    for i in (~reached).nonzero()[:, 0].tolist():
        reason[i] = "out of reach: the nominal IK does not reach the target from the seed"
    return TargetResult(comp.q, q_ik, command, ok, reason, comp)


# options the compiled pass reads (or that only concern rows it leaves to the general path)
_FAST_OPTIONS = {"tol", "max_iter", "residual_tol", "contraction", "length", "max_correction", "max_step", "damping",
                 "max_damped_iter", "null_damping", "refresh", "refresh_model", "chunk_size", "tool_set"}


def _fast_pass(model, target, seed, direction, t_nominal, t_actual, ik_tol, ik_max_iter, options,
               G=None) -> dict | None:
    """:mod:`.fused_targets`' compiled pass over every row, or None where it does not apply (no numba, not CPU
    float64, not 6 joints, a live model (compliance, fine tables), 5- or 3-DOF, an option it does not implement)."""
    if model.n != 6 or not set(options) <= _FAST_OPTIONS or target.shape[0] < FAST_MIN_TARGETS:
        return None
    setup = compiled_pass_setup(model, seed, options)
    if setup is None:
        return None
    from .fused_targets import solve_targets

    fused, opts = setup
    return solve_targets(fused, target, t_nominal, t_actual, seed, direction, ik_tol=ik_tol, ik_max_iter=ik_max_iter,
                         **opts, tool_set_inverse=None if G is None else inverse(G))


def _merged(model, fast, target, seed, direction, t_nominal, t_actual, ik_tol, ik_max_iter, options) -> TargetResult:
    """The compiled pass's rows, with the rows it left solved again by :func:`_general`, in input order: from the
    seed where the pass's nominal IK failed, else from the pass's IK command."""
    from .fused_targets import IK_FAILED

    c = compiled_rows(fast, float(options.get("length", 1.0)))
    q_nominal, command = fast["q_nominal"].clone(), fast["command"]
    correction = (c["q"] - q_nominal).abs().amax(-1)
    rest = (~c["done"]).nonzero()[:, 0]
    failed = fast["status"][rest] == IK_FAILED
    solved = []  # (rows, their TargetResult)
    for rows, solved_ik in ((rest[failed], False), (rest[~failed], True)):
        if rows.numel():
            start = fast["q_nominal"][rows] if solved_ik else seed[rows]
            g = _general(model, target[rows], start, None if direction is None else direction[rows], t_nominal[rows],
                         t_actual[rows], ik_tol, ik_max_iter, options, solved_ik=solved_ik)
            fill_rows(c, rows, g.compensation)
            q_nominal[rows], command[rows], correction[rows] = g.q_nominal, g.command_target, g.compensation.correction
            solved.append((rows, g))
    q = c["q"]
    within, outside = range_and_coverage(model, q, direction)
    comp = CompensationResult(q, c["converged"], c["iterations"], c["pose_error"], c["residual"], c["step"],
                              c["damped"], within, None, correction, outside, c["status"])
    ok = c["converged"] & within
    reason = [""] * target.shape[0]
    for i in (~within).nonzero()[:, 0].tolist():
        reason[i] = JOINT_LIMIT
    for rows, g in solved:
        ok[rows] = g.converged  # also needs the controller's IK
        for i, r in zip(rows.tolist(), g.reason):
            reason[i] = r
    return TargetResult(q, q_nominal, command, ok, reason, comp)


def nominal_model(model):
    """The model's nominal chain as a model with every error term zero: the controller's kinematics (the
    model's own class: compensation and the models are sibling layers)."""
    return type(model)(model.robot, model.tools.nominal, orders=0, backlash=None).to(model.device)


__all__ = ["TargetResult", "compensate_targets", "flange_for", "nominal_model", "pose_rpy", "target_poses", "tool_pose"]
