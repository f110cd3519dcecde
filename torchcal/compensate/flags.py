"""Configuration flags of a 6R arm with a spherical wrist, and the controller's seed for a target from its flags.

A robot program gives a Cartesian target together with the configuration the
controller must reach it in (FANUC's "N U T", ABB's cfx, KUKA's status bits):
which of the (up to 8) solutions of the nominal IK to take. They are the signs
of the three factors of det J that vanish on the arm's three singular surfaces
(:mod:`.branch` tests their product). Our reading, in the nominal kinematics,
from the joint axes z_i and points o_i on them (the frame each joint moves in)
and the wrist centre c (where axes 4 and 5 meet):

- shoulder = sign(z2 · ((c - o1) × z1)): the side of axis 1 the wrist centre is
  on (zero when c lies on axis 1: the shoulder singularity);
- elbow = sign(z2 · ((o3 - o2) × (c - o3))): the elbow bent one way or the
  other (zero when o2, o3 and c line up: the stretched or folded elbow);
- wrist = sign(z4 · (z5 × z6)): flip / no flip (zero when the three wrist axes
  are coplanar, e.g. axis 6 along axis 4).

The vendors' letters map onto these signs one to one, each by a fixed sign
convention of its own; a file gives the signs (+1 / -1) as columns
``shoulder``, ``elbow``, ``wrist``. For an arm whose axes 4 and 5 do not meet
(UR-style offset wrists) the reading does not apply and :func:`configuration_flags`
refuses it.

:func:`seeds_for_flags` solves the nominal IK of each target from several
starts at once (a scrambled Sobol design over the joint range) and keeps, per
target, the solution with the requested flags nearest to a reference command
(default: the middle of the joint range; it stands in for the controller's
turn numbers, which pick among solutions 2π apart).
"""

from __future__ import annotations

import torch

from ..core.exceptions import InputError
from ..kinematics.fk import chain_frames
from .damped import damped_least_squares

FLAG_NAMES = ("shoulder", "elbow", "wrist")

WRIST_MEET_TOL = 1e-6
"""m: axes 4 and 5 closer than this meet (a spherical wrist)."""


def _wrist_centre(z4, o4, z5, o5):
    """Closest point on axis 5 to axis 4 and the axes' distance.  z, o: (B, 3) -> c (B, 3), d (B,)."""
    w = o5 - o4
    b = (z4 * z5).sum(-1)
    d4, d5 = (z4 * w).sum(-1), (z5 * w).sum(-1)
    den = (1 - b * b).clamp(min=1e-12)
    t5 = (b * d4 - d5) / den  # parameter along axis 5 of the common perpendicular's foot
    c = o5 + t5[:, None] * z5
    t4 = (d4 - b * d5) / den
    gap = (o4 + t4[:, None] * z4 - c).norm(dim=-1)
    return c, gap


def configuration_flags(model, q: torch.Tensor) -> torch.Tensor:
    """Shoulder, elbow and wrist flags of commands q in the nominal kinematics (module docstring).

    model: a RobotModel (its robot's nominal chain); q: (B, 6) commands (rad). -> (B, 3) float in {-1, 0, +1}.
    Raises ValueError for an arm that is not 6R or whose axes 4 and 5 do not meet.
    """
    robot = model.robot
    require_6r(robot)
    q = q.to(model.dtype)
    with torch.no_grad():
        R, p, _ = chain_frames(model.origins, model.axes, model.prismatic, model.joint_variables(q), None, model.tip)
        z = (R @ model.axes.to(R.dtype)[None, :, :, None])[..., 0]  # (B, 6, 3) axes in the base frame
        c, gap = _wrist_centre(z[:, 3], p[:, 3], z[:, 4], p[:, 4])
    z6, o6 = z[:, 5], p[:, 5]
    off6 = torch.linalg.cross(c - o6, z6).norm(dim=-1)  # the wrist centre's distance from axis 6
    gap = torch.maximum(gap, off6)
    if bool((gap > WRIST_MEET_TOL).any()):
        raise ValueError(f"configuration flags: the wrist axes of '{robot.name}' do not meet in one point (they pass "
                         f"{float(gap.max()) * 1e3:.3g} mm apart): the flags' reading needs a spherical wrist; give "
                         "seed commands")
    z1, z2, z4, z5 = z[:, 0], z[:, 1], z[:, 3], z[:, 4]
    o1, o2, o3 = p[:, 0], p[:, 1], p[:, 2]
    shoulder = (z2 * torch.linalg.cross(c - o1, z1)).sum(-1)
    elbow = (z2 * torch.linalg.cross(o3 - o2, c - o3)).sum(-1)
    wrist = (z4 * torch.linalg.cross(z5, z6)).sum(-1)
    return torch.sign(torch.stack([shoulder, elbow, wrist], -1))


def require_6r(robot) -> None:
    """ValueError unless ``robot`` is a 6R arm, the only kind the flags describe (said before any IK is tried)."""
    if robot.joint_map.n != 6 or bool(robot.joint_map.prismatic.any()):
        raise ValueError(f"configuration flags: defined for 6R arms; '{robot.name}' has {robot.joint_map.n} joints"
                         f"{' (prismatic ones)' if bool(robot.joint_map.prismatic.any()) else ''}: give seed commands "
                         "q1..qN instead of shoulder, elbow, wrist")


def seeds_for_flags(model, target: torch.Tensor, flags: torch.Tensor, tool=0, starts: int = 64, seed: int = 0,
                    reference: torch.Tensor | None = None, chunk: int = 1024):
    """The controller's command for each target in the configuration its flags name, to seed
    :func:`.targets.compensate_targets`.

    model: a RobotModel; target: (B, 4, 4) tool poses in the robot's nominal base frame (SI); flags: (B, 3)
    shoulder, elbow, wrist in {-1, +1}; tool: index or (B,) indices of the controller's (nominal) tool;
    starts: nominal IK starts per target (a scrambled Sobol design over the joint range, ``seed``; 8x and 64x as
    many for the targets the rounds before leave);
    reference: (6,) or (B, 6) command whose nearest solution is taken among those with the flags (default:
    the middle of the joint range); chunk: targets solved together (memory: starts x chunk rows).
    -> q (B, 6) commands (rad; rows not found hold the reference), found (B,) bool.

    Example:
        >>> import torch, torchcal
        >>> from torchcal.compensate.flags import configuration_flags, seeds_for_flags
        >>> robot = torchcal.load_robot("fanuc_lrmate200i")
        >>> model = torchcal.RobotModel(robot, torch.zeros(1, 3, dtype=torch.float64), orders=0)
        >>> q = torch.tensor([[0.3, 0.2, -0.4, 0.5, -0.7, 0.2]], dtype=torch.float64)
        >>> T = model.nominal_flange(q).detach()
        >>> seed, found = seeds_for_flags(model, T, configuration_flags(model, q))
        >>> bool(found[0]), float((model.nominal_flange(seed) - T).abs().max()) < 1e-9
        (True, True)
    """
    from .targets import flange_for, nominal_model

    B = target.shape[0]
    if target.shape[1:] != (4, 4) or flags.shape != (B, 3):
        raise InputError(f"seeds_for_flags: target must be (B, 4, 4) and flags (B, 3), got {tuple(target.shape)} "
                         f"and {tuple(flags.shape)}")
    if not bool(((flags == 1) | (flags == -1)).all()):
        raise InputError("seeds_for_flags: every flag must be +1 or -1")
    require_6r(model.robot)
    dt, dev = model.dtype, model.device
    lim = model.command_limits.to(dt)
    ref = (lim[:, 0] + lim[:, 1]) / 2 if reference is None else reference.to(dt)
    ref = ref.expand(B, 6)
    tool = torch.as_tensor(tool, dtype=torch.long, device=dev).expand(B)
    goal = flange_for(target.to(dt), model.tools.nominal.to(dev, dt)[tool])
    engine = torch.quasirandom.SobolEngine(6, scramble=True, seed=seed)
    nominal = nominal_model(model)
    out, found = ref.clone(), torch.zeros(B, dtype=torch.bool, device=dev)
    # more rounds, 8x the starts each, for the targets the rounds before left (most starts settle on the target
    # turned half a turn, which the IK refuses: the requested branch's basin is small); the points continue the
    # same Sobol sequence
    for k in (starts, 8 * starts, 64 * starts):
        q0 = lim[:, 0] + engine.draw(k).to(dev, dt) * (lim[:, 1] - lim[:, 0])  # (k, 6)
        todo = (~found).nonzero()[:, 0]
        per = max(1, chunk * starts // k)
        for c0 in range(0, todo.numel(), per):
            rows = todo[c0:c0 + per]
            m = rows.numel()
            res = damped_least_squares(nominal, q0.repeat(m, 1), goal[rows].repeat_interleave(k, 0), None, max_iter=60)
            qs = res.q.view(m, k, 6)
            inside = ((qs >= lim[:, 0]) & (qs <= lim[:, 1])).all(-1)
            same = (configuration_flags(model, res.q).view(m, k, 3) == flags[rows, None].to(dt)).all(-1)
            ok = res.converged.view(m, k) & inside & same
            dist = torch.where(ok, (qs - ref[rows, None]).abs().sum(-1), torch.full(ok.shape, float("inf"), dtype=dt,
                                                                                    device=dev))
            best = dist.argmin(1)
            hit = ok.any(1)
            out[rows[hit]] = qs[torch.arange(m, device=dev), best][hit]
            found[rows[hit]] = True
        if bool(found.all()):
            break
    return out, found


__all__ = ["FLAG_NAMES", "configuration_flags", "seeds_for_flags"]
