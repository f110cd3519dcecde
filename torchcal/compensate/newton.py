"""Batched compensation of the modeled errors, Paper II (46)-(52).

For a nominal command q_nom the compensated command q_new makes the modeled
robot reach the pose the nominal robot would have reached (46):

    E_base · F_a(q_new, s) = F_n(q_nom),
    i.e. ``model.flange(q_new, direction, base=False) == model.nominal_flange(q_nom)``,

with the identified tool set's rigid motion G on the left (F_a G: :mod:`.toolset`, our reading for tools that
the fit identifies; ``tool_set=False`` is the equation as printed, and the two agree for nominal tools).

The paper's iteration (47)-(51): Ω = F_a(q^r)^-1 F_n(q_nom), de from Ω (48),
dq = J(q_nom)^-1 de (49), q <- q + dq (50) until ||dq|| < tol (51). With the
Jacobian held at q_nom this is a chord method: one factorization per pose,
then each iteration is one flange evaluation and a 6x6 mat-vec; it converges
linearly at a rate about the relative size of the model error (~1e-3), i.e.
4-5 iterations to 1e-10 rad. Rows that do not contract (near singularities,
targets out of the modeled robot's reach) are handed to damped least squares
with the current model Jacobian (:mod:`.damped`); rows that never converge
come out flagged with their lowest-error solution, never dropped.

Bounded corrections: a compensated command is a calibration-sized change of
the nominal one. Next to a singularity the exact solution of (46) can lie
tens of degrees away (at q5 = 0 a small orientation error turns q4 and q6
by up to 90 degrees) or on another branch; sending it makes the robot swing.
compensate() therefore keeps every row within ``max_correction`` of q_nom
(steps within ``max_step``): the fast path's rows that converge further away
and the rows near singularities (small singular values of the Jacobian) go
to the damped path, which first minimizes |r|² + λ²|q - q_nom|² (Tikhonov
damping toward q_nom: the null space, e.g. the wrist's q4/q6 combination,
stays at q_nom), then polishes without λ inside the same box. Rows that
cannot meet the tolerance within the bound are flagged (not converged) with
that bounded best effort; ``CompensationResult.correction`` is each row's
largest |q_new - q_nom|. Branches: a solution on another configuration than q_nom's (the sign of det J of
the nominal kinematics changes between them, :mod:`.branch`) is refused; every flagged row carries a
status code (:mod:`.result`) that ``reasons()`` turns into words.

Why one module: the fast path (the chord iteration, its refreshes) and the hand-over to the damped path
share the working set, the bounds and the status bookkeeping of one call; the pieces that stand alone
live beside it (:mod:`.result`, :mod:`.bounds`, :mod:`.branch`, :mod:`.axis`, :mod:`.damped`, :mod:`.kernel`).

The fast path runs on :class:`.kernel.FlangeKernel` (pose index last; on the
CPU in float64 its evaluations are the numba-compiled kernel of
:mod:`.fused`, elsewhere torch ops); the damped path and every reported
figure can be checked against ``RobotModel.flange`` directly. On the CPU in float64 the common calls (6-DOF, and
3-DOF ``position_only``) first go through one compiled pass pose by pose (:mod:`.fused_targets`,
:mod:`.fused_position`); the rows it hands on are solved here.
"""

from __future__ import annotations

import contextlib
import math

import torch

from ..core.exceptions import InputError
from ..kinematics.transforms import homogeneous
from ..core.measurements import first_invalid_direction
from ..core.progress import task as progress_task
from ..core.contract import require
from ..core.threads import threads_for_work
from .axis import tool_axis
from .bounds import (  # noqa: F401 (re-exported)
    DEFAULT_BOUND, DEFAULT_CORRECTION_DEG, DEFAULT_PRISMATIC_MM, DEFAULT_STEP_DEG, per_joint_bound,
)
from .branch import PATH_ABOVE, branch_changed, det_sign_soa, jacobian_lipschitz, surely_same_branch
from .damped import damped_least_squares
from .kernel import FlangeKernel, pose_error_soa
from .toolset import inverse, model_tool_set_frame
from .result import (AT_BOUND, BRANCH, CONVERGED, NOT_CONVERGED, OUT_OF_REACH, SINGULAR,  # noqa: F401 (re-export)
                     SINGULAR_FLOOR, CompensationResult, range_and_coverage)


# ---------------------------------------------------------------------------- core
def nominal_jacobian_inverse(J: torch.Tensor, sigma_floor: float = 0.0, length: float = 1.0):
    """Inverse (n == 6) or pseudo-inverse of nominal body Jacobians.

    J: (m, n, B) -> P: (n, m, B), J's inverse (m = n) or Moore-Penrose pseudo-inverse (m = 6; 5 for a free
    tool axis), and ok: (B,) bool
    (finite, non-singular).
    sigma_floor: rows whose smallest singular value (orientation rows times
    ``length``, m / rad) is below this are not ok either; the bound used is
    1 / ||P||_F <= sigma_min, so a row is let through only when it is well
    clear of the floor (inv_ex succeeds on numerically singular matrices, and
    a chord step through such an inverse moves the null space at will).
    The inverse is formed once per pose and reused every iteration: an
    inexact inverse only slows the fixed-point iteration (the residual (47) is
    always exact), it does not move its fixed point.
    """
    Jb = J.permute(2, 0, 1)  # (B, 6, n)
    m, n = Jb.shape[-2:]
    if n == m:
        P, info = torch.linalg.inv_ex(Jb)
    else:  # the pseudo-inverse of a full-rank J by its normal matrix (an SVD per pose costs ~10x more: a 7-axis
        # arm's compensation spent half its time in pinv); a rank-deficient row fails inv_ex or the floor below
        Jt = Jb.transpose(-1, -2)
        G, info = torch.linalg.inv_ex(Jb @ Jt if n > m else Jt @ Jb)
        P = Jt @ G if n > m else G @ Jt
    ok = info == 0
    ok = ok & torch.isfinite(P).all(-1).all(-1)
    if sigma_floor > 0.0:
        fro2 = (P[..., :3] ** 2).sum((-1, -2)) + (P[..., 3:] ** 2).sum((-1, -2)) / length**2
        ok = ok & (fro2 * sigma_floor**2 < 1.0)
    return P.permute(1, 2, 0).contiguous(), ok


def _matvec(P: torch.Tensor, de: torch.Tensor) -> torch.Tensor:
    """P (n, 6, B) @ de (6, B) -> (n, B) as six multiply-adds over the pose axis."""
    out = P[:, 0] * de[0]
    for j in range(1, de.shape[0]):
        out = torch.addcmul(out, P[:, j], de[j])
    return out


def _weighted_norm(de: torch.Tensor, length: float) -> torch.Tensor:
    """(6, B) -> (B,) sqrt(|de_p|² + length² |de_r|²)."""
    return torch.sqrt((de[:3] * de[:3]).sum(0) + length**2 * (de[3:] * de[3:]).sum(0))


def _colnorm(x: torch.Tensor) -> torch.Tensor:
    """(k, B) -> (B,) Euclidean norm of each column (a sum over rows is cheaper than norm(dim=0))."""
    return torch.sqrt((x * x).sum(0))


def fixed_jacobian_iterations(
    kernel: FlangeKernel,
    qT: torch.Tensor,
    sT: torch.Tensor | None,
    Rn: torch.Tensor,
    pn: torch.Tensor,
    P: torch.Tensor,
    start: torch.Tensor,
    tol: float,
    max_iter: int,
    contraction: float,
    length: float,
    residual_tol: float,
    broyden: bool = True,
    qref: torch.Tensor | None = None,
    max_correction: torch.Tensor | None = None,
    axis=None,
    cT: torch.Tensor | None = None,
):
    """Paper II's iteration (47)-(51) with a fixed (pseudo-)inverse Jacobian, all poses at once.

    qT: (n, B) start (q_nom on the first pass); sT: (n, B) directions or None; Rn (3, 3, B), pn (3, B):
    target F_n(q_nom); P: (n, 6, B) inverse Jacobian; start: (B,) bool rows to
    iterate (the others fail at once); tol: ||dq|| for (51); contraction: a
    row fails when a step is not at least this much shorter than the one
    before (it would not converge, or only slowly); length: m per rad;
    residual_tol: a row converges at q^r when ||dq^r|| < tol (51) *and* the
    weighted pose error evaluated at q^r is below this (m);
    broyden: refine the stored inverse by Broyden's rank-1 update after each
    step (see below) instead of keeping it fixed as in (49);
    qref: (n, B) reference commands (q_nom) for the bounds, default qT (no step
    bound here: the contraction test bounds the steps);
    max_correction: (n,) per-joint bound (rad / m; see :func:`per_joint_bound`): a row
    that reaches (51) further than this from qref on any joint is not ok: it is
    handed on with its best iterate.
    -> dict of q (n, B) (q^r for converged rows; the lowest-error iterate
       for failed ones), de (6, B) the error at q for converged rows,
       step (B,) ||dq^r||, iterations (B,) updates made, ok (B,) bool, far (B,)
       bool: reached (51) outside max_correction (not ok).
    axis, cT: a :class:`.axis.ToolAxis` and the rows' tool points (3, B): 5-DOF, P is (n, 5, B), pn the
    tool points' targets, de the full error at the tool point; 3-DOF (position only), P is (n, 3, B) of the
    world-frame Jacobian (:meth:`.axis.ToolAxis.world_jacobian_soa`).
    Finished rows leave the working set, so a few slow rows do not make the
    whole batch iterate.

    Broyden: with the model errors of a real robot the solution lies ~1e-2 rad
    from q_nom, where the Jacobian differs from J(q_nom) by a few per cent,
    so the fixed chord contracts only by ~1e-2..1e-1 per step. "Good"
    Broyden corrects P with what the last step s = dq taught it: with the
    plain chord step u = P de_new, H' = H + u (s^T H) / (s^T (s - u)) and the
    next step is u |s|² / (s^T (s - u)). This is ~100 flops per pose against
    ~1500 for one flange evaluation and turns the linear rate superlinear;
    the fixed point and the stopping rule (51) are unchanged.
    """
    n, B = qT.shape
    dtype, device = qT.dtype, qT.device
    q_out = qT.clone()
    de_out = torch.full((6, B), float("nan"), dtype=dtype, device=device)
    step_out = torch.full((B,), float("inf"), dtype=dtype, device=device)
    it_out = torch.zeros(B, dtype=torch.long, device=device)
    ok_out = torch.zeros(B, dtype=torch.bool, device=device)
    far_out = torch.zeros(B, dtype=torch.bool, device=device)

    idx = start.nonzero()[:, 0]
    st = {
        "q": qT[:, idx], "s": None if sT is None else sT[:, idx], "R": Rn[..., idx], "p": pn[:, idx], "P": P[..., idx],
        "best_q": qT[:, idx], "best_res": torch.full((idx.numel(),), float("inf"), dtype=dtype, device=device),
        "prev": torch.full((idx.numel(),), float("inf"), dtype=dtype, device=device), "last": None, "idx": idx,
        "ref": None if max_correction is None else (qT if qref is None else qref)[:, idx],
        "c": None if cT is None else cT[:, idx],
    }
    live = torch.ones(idx.numel(), dtype=torch.bool, device=device)
    any_dead = False
    for r in range(max_iter + 1):
        if st["idx"].numel() == 0:
            break
        q, Pa, prev, last = st["q"], st["P"], st["prev"], st["last"]
        # (47)-(48) at q^r
        R, p = kernel.flange(q, st["s"])
        if axis is not None:
            p = axis.shift_soa(R, p, st["c"])
        de_full = de = pose_error_soa(R, p, st["R"], st["p"])
        if axis is not None:  # the rotation about the tool axis is free; 3-DOF: every rotation, world frame
            de = st["p"] - p if axis.position_only else axis.project_soa(de)
        res = _weighted_norm(de, length)
        better = res < st["best_res"]  # NaN compares False: a blown-up row keeps its last good iterate
        st["best_res"] = torch.where(better, res, st["best_res"])
        st["best_q"] = torch.where(better, q, st["best_q"])
        # (49), with Broyden's correction of the stored inverse
        dq = _matvec(Pa, de)
        if broyden and last is not None:
            ss = (last * last).sum(0)
            den = ss - (last * dq).sum(0)
            use = den.abs() > 0.1 * ss  # skip near-degenerate updates (row is not contracting anyway)
            f = torch.where(use, 1.0 / torch.where(use, den, torch.ones_like(den)), torch.zeros_like(den))
            sP = (last[:, None] * Pa).sum(0)  # s^T H, (6, b)
            st["P"] = torch.addcmul(Pa, dq[:, None] * f, sP[None])
            dq = dq * torch.where(use, ss * f, torch.ones_like(f))
        step = _colnorm(dq)
        # (51) at q^r, confirmed by the error evaluated there: q^r is returned with
        # that error (the paper returns q^r + dq^r, a step below tol further on)
        done = live & (step < tol) & (res <= residual_tol)
        fail = live & ~done & (~torch.isfinite(step) | (step > contraction * prev) | (r == max_iter))
        finished = done | fail
        if bool(finished.any()):
            f = finished.nonzero()[:, 0]
            rows, d = st["idx"][f], done[f]
            if max_correction is not None:
                # a solution further than max_correction from q_nom is another branch or a swing next to
                # a singularity, not a calibration-sized correction: the row goes on to the bounded path.
                # (The iterates in between need no check: each step is at most `contraction` times the
                # one before, so they stay within |dq^0| / (1 - contraction) of the start.)
                far = d & ((q[:, f] - st["ref"][:, f]).abs() / max_correction[:, None]).amax(0).gt(1.0)
                d = d & ~far
                far_out[rows] = far
            q_out[:, rows] = torch.where(d, q[:, f], st["best_q"][:, f])
            de_out[:, rows] = de_full[:, f]
            step_out[rows] = step[f]
            it_out[rows] = r
            ok_out[rows] = d
            live = live & ~finished
            any_dead = True
            nlive = int(live.sum())
            if nlive == 0:
                break
            if nlive < 0.8 * live.numel():
                # compact the working set (finished rows only cost arithmetic until then)
                keep = live.nonzero()[:, 0]
                st["prev"], st["last"] = step, dq
                st = {k: (None if v is None else v[..., keep]) for k, v in st.items()}
                live = torch.ones(nlive, dtype=torch.bool, device=device)
                any_dead = False
                step, dq = st["prev"], st["last"]
        if any_dead:
            dq = torch.where(live, dq, torch.zeros_like(dq))  # finished rows stay put
        # (50)
        st["q"] = st["q"] + dq
        st["prev"], st["last"] = step, dq
    return {"q": q_out, "de": de_out, "step": step_out, "iterations": it_out, "ok": ok_out, "far": far_out}


def _check_inputs(model, q_nom: torch.Tensor, direction: torch.Tensor | None, given: bool = True):
    """compensate()'s arguments; given: q_nom is the caller's (not an IK solution of compensate_targets, which may
    wander off the range where a target is out of reach): judged for degrees too."""
    require(model, "compensate commands", "compensate")  # the model contract (torchcal.core.contract)
    if not isinstance(q_nom, torch.Tensor) or q_nom.ndim != 2 or q_nom.shape[1] != model.n:
        shape = tuple(q_nom.shape) if isinstance(q_nom, torch.Tensor) else type(q_nom).__name__
        raise InputError(f"compensate: q_nom must be a (B, {model.n}) tensor of commands, got {shape}")
    if q_nom.device != model.device:
        raise InputError(f"compensate: q_nom is on {q_nom.device}, the model on {model.device}; move one of them")
    if not q_nom.is_floating_point():
        raise TypeError(f"compensate: q_nom must be floating point (rad / m), got {q_nom.dtype}")
    if q_nom.dtype != model.dtype:  # a float32 model given float64 commands ended 'out of reach' on 98 % of rows
        raise InputError(f"compensate: q_nom is {q_nom.dtype}, the model {model.dtype}: convert one of them "
                         f"(q_nom.to({model.dtype}) or model.to({q_nom.dtype}))")
    if given:
        refuse_degrees(model, q_nom, "compensate: q_nom")
    bad = ~torch.isfinite(q_nom)
    if bad.any():
        i, j = (int(x) for x in bad.nonzero()[0])
        raise InputError(f"compensate: q_nom is not finite at pose {i}, joint {j + 1} ({float(q_nom[i, j])})")
    if direction is not None:
        if direction.shape != q_nom.shape:
            raise InputError(f"compensate: direction must have the shape of q_nom {tuple(q_nom.shape)}, got {tuple(direction.shape)}")
        if direction.device != model.device:
            raise InputError(f"compensate: direction is on {direction.device}, the model on {model.device}")
        bad = first_invalid_direction(direction)
        if bad is not None:
            i, j = bad
            raise InputError(f"compensate: direction must be -1, 0 or +1, got {float(direction[i, j])} at pose {i}, joint {j + 1}")


def refuse_degrees(model, q: torch.Tensor, what: str) -> None:
    """Commands in degrees given to the Python API (it takes radians) reach hundreds of 'radians': every row then
    fails. Refused, naming the joint, where a revolute joint's command lies beyond 2 pi and twice its range's
    largest magnitude (no controller's command; a wide J6 range stays valid)."""
    robot = getattr(model, "robot", None)
    jm = getattr(robot, "joint_map", None)
    if jm is None or q.numel() == 0:
        return
    lim = jm.limits.to(q)
    reach = torch.maximum(lim[:, 0].abs(), lim[:, 1].abs())
    peak = q.abs().amax(0)
    far = (~jm.prismatic.to(q.device)) & (peak > 2 * math.pi) & (peak > 2 * reach)
    if bool(far.any()):
        j = int(far.nonzero()[0, 0])
        raise InputError(f"{what} reaches {float(peak[j]):.4g} rad on joint {j + 1}, far outside its range "
                         f"[{float(lim[j, 0]):.4g}, {float(lim[j, 1]):.4g}] rad: degrees? The Python API takes radians "
                         "(torch.deg2rad(q)); files and the CLI take degrees")


def nominal_sigma_min(model, q: torch.Tensor, length: float = 1.0) -> torch.Tensor:
    """Smallest singular value of the nominal flange Jacobian.  q: (B, n) -> (B,) m/rad.

    Orientation rows are multiplied by ``length`` (m) so that both row blocks
    are lengths per radian; 0.1 mm/deg with 1 mrad·m = 1 mm is 5.73e-3 here.
    """
    kernel = FlangeKernel(model)
    _, _, J = kernel.nominal_flange_jacobian(q.T.to(model.dtype).contiguous())
    return sigma_min_soa(J, length)


def sigma_min_soa(J: torch.Tensor, length: float) -> torch.Tensor:
    """Smallest singular value of body Jacobians J (6, n, B), orientation rows times ``length`` -> (B,) m/rad."""
    J = J.permute(2, 0, 1).clone()
    J[:, 3:] *= length
    return torch.linalg.svdvals(J)[:, -1]


FLOPS_PER_POSE = 2e4
"""Work of one compensated pose (6-7 flange evaluations with Jacobians, ~1 500 flops each, and the
updates): the size :func:`torchcal.core.threads.threads_for` gives threads by."""


FUSED_MIN_POSES = 1024

GPU_CHUNK = 4_000_000
"""Poses per chunk on a GPU (a few GB of work space in float64)."""

FLOAT32_TOL = 1e-5
FLOAT32_RESIDUAL_TOL = 1e-6
"""The least ``tol`` / ``residual_tol`` used for float32 commands (float64's defaults are below float32's
resolution)."""
"""Batches smaller than this run on the torch ops, not the compiled kernel (see :func:`compensate`'s body)."""


def _fused_warm() -> bool:
    """The compiled kernel has run in this process already (without importing numba where it has not)."""
    import sys

    fused = sys.modules.get("torchcal.compensate.fused")
    return fused is not None and fused.warm()


@torch.no_grad()
def compensate(
    model,
    q_nom: torch.Tensor,
    direction: torch.Tensor | None = None,
    tol: float = 1e-10,
    max_iter: int = 30,
    damping: float = 1e-5,
    chunk_size: int | None = None,
    *,
    max_damped_iter: int = 50,
    contraction: float = 0.5,
    length: float = 1.0,
    residual_tol: float = 1e-12,
    sigma: bool = False,
    broyden: bool = True,
    refresh: int = 2,
    refresh_model: bool = True,
    max_step: float | torch.Tensor | str | None = DEFAULT_BOUND,
    max_correction: float | torch.Tensor | str | None = DEFAULT_BOUND,
    null_damping: float = 1e-3,
    branch: bool = True,
    free_tool_axis=None,
    tool_point=None,
    target: torch.Tensor | None = None,
    tool_set: bool = True,
    position_only: bool = False,
) -> CompensationResult:
    """Compensated joint commands for many poses, Paper II (46)-(52).

    model: RobotModel (its parameters are read once, no gradients).
    q_nom: (B, n) nominal commands, rad / m, on the model's device.
    direction: (B, n) approach directions in {-1, 0, +1} for backlash, or None.
    tol: ||dq|| stopping tolerance (51), rad / m (joint-space step norm).
    max_iter: fixed-Jacobian iterations before a row is handed to the damped path.
    damping: initial Levenberg-Marquardt damping, relative to max diag(J^T J).
    chunk_size: poses solved together on the fast path; None: up to 262 144 (on a GPU :data:`GPU_CHUNK`)
        (bounded memory, ~300 bytes a pose). Fewer chunks mean fewer tail
        iterations over a handful of slow rows, each paying the full per-op
        dispatch cost; cache locality on the CPU comes from the kernel's own
        blocks (:class:`FlangeKernel`), not from the chunks.
    max_damped_iter: iteration cap of the damped path (99 % of the rows that
        converge there need fewer than 35; the tail costs a full iteration of
        per-op overhead each, whatever the number of rows left).
    contraction: a fixed-Jacobian step must be shorter than this times the
        previous one, else the row goes to the damped path.
    length: m per rad for orientation errors where position and orientation
        are mixed (damped path, residual, sigma_min).
    residual_tol: a row converges when ||dq|| < tol (51) and its weighted pose
        error, evaluated at the returned command, is below this (m).
    sigma: also return sigma_min of the nominal Jacobian at q_nom (costs an SVD per pose).
    broyden: rank-1 updates of the stored inverse Jacobian (same fixed point,
        fewer iterations); False is the paper's plain fixed-Jacobian iteration.
    refresh: times a row that does not contract gets its Jacobian re-evaluated
        at its best iterate (nominal chain, fast kernel) before it goes to the
        damped path; 0 is the paper's single Jacobian at q_nom.
    max_step: trust bound, the largest change of any joint in one update
        (rad / m); default 5 deg per revolute and 5 mm per prismatic joint (:data:`DEFAULT_STEP_DEG`);
        a number for every joint or an (n,) tensor per joint
        (:func:`per_joint_bound`); None: unbounded.
    max_correction: bound on |q_new - q_nom| for every joint and every row,
        flagged or not (rad / m, like max_step: default 30 deg / 5 mm, :data:`DEFAULT_CORRECTION_DEG`). The
        correction is a calibration-sized one (typically < 1 deg, 5-8 deg next to the wrist singularity,
        where a small orientation error turns q4 and q6 in opposite directions); a row whose exact solution
        lies further away is not converged: it comes out flagged with a bounded best effort instead of a
        command that makes the robot swing. None: unbounded (the paper's behaviour).
    branch: refuse solutions on another branch than q_nom's (:mod:`.branch`: the sign of det J of the
        nominal kinematics changes between them, i.e. a configuration flag changes): such a row is
        solved again on the damped path from q_nom and, if that ends across the surface too, flagged
        (status BRANCH). Only for n = 6.
    free_tool_axis: None (6-DOF, (46)); True or a (3,) direction in the flange frame (True: z): 5-DOF
        compensation for axisymmetric tools, the rotation about that axis left free (:mod:`.axis`):
        the tool point reaches its nominal position and the tool axis its nominal direction, with the
        smallest correction the solver finds (pseudo-inverse / Tikhonov toward q_nom).
    target: (B, 4, 4) flange poses to reach (robot's nominal base frame, SI) instead of the nominal flange
        F_n(q_nom); q_nom is then the start, the reference of the bounds and of the branch, and the point
        where the chord Jacobian is taken: a command near the target on the controller's branch (e.g. the
        controller's nominal IK of a Cartesian target for its nominal tool, :mod:`.targets`).
    tool_point: with free_tool_axis or position_only, the point (flange frame, m; (3,) or (B, 3); default
        the flange origin) whose position is compensated.
    position_only: 3-DOF, the tool point's position alone, every rotation left free (:mod:`.axis`): for a
        model identified from one measured point per pose, whose flange orientation the data do not fix
        (:func:`observed_dof`); the correction is the smallest the solver finds, as for free_tool_axis.
    tool_set: the frame that reaches the goal (F_n(q_nom) or ``target``) is the modeled flange carried by
        the identified tool set's rigid motion G (:mod:`.toolset`: point data fix the flange only up to G
        when the tools are identified, so any two models that predict the same points give the same
        commands, and the tools land on the nominal robot's points); False: the bare flange, (46) as
        printed. Identical where the identified tools equal the nominal ones. With free_tool_axis the axis
        is given in the tool set's frame, tool_point in the modeled flange's (as ``model.tools()`` holds
        the identified tool points).
    null_damping: Tikhonov damping toward q_nom on the damped path (m / rad,
        like ``length``-weighted singular values): directions of the Jacobian
        with singular values well below it (the q4/q6 combination that does
        not move the flange at q5 = 0) stay at q_nom. That pass is followed by
        an undamped one inside the same bounds, so converged rows meet (46)
        to residual_tol; a row that does not converge there keeps its lowest
        error if that stays inside the bounds (an unreachable target), else
        the damped (minimum-swing) solution. 0 disables the pass.
    -> :class:`CompensationResult`; float64, on the model's device.
    Fast path first: rows whose Jacobian at q_nom is clear of 0.1 null_damping
    (null_damping after a refresh) and whose fixed-Jacobian iteration ends
    inside the bounds never reach the damped path.

    Example:
        >>> import torch, torchcal
        >>> robot = torchcal.load_robot("fanuc_lrmate200i")
        >>> model = torchcal.RobotModel(robot, torch.zeros(1, 3, dtype=torch.float64), orders=0)
        >>> with torch.no_grad():
        ...     model.joint_errors.coef[:, 2, 0] = 1e-3  # 0.06 deg offset on every joint
        >>> q = torch.tensor([[0.1, 0.2, 0.3, 0.4, 0.5, 0.6]], dtype=torch.float64)
        >>> res = compensate(model, q)
        >>> bool(res.converged[0]), float(res.correction[0]) < 0.01
        (True, True)
    """
    if q_nom.dtype == torch.float32:
        # float32 (a GPU's fast path) carries ~1e-7 of a metre: the float64 tolerances cannot be met, so every row
        # would be flagged; these are the float32 floor (measured: commands within ~1e-5 rad of float64's)
        tol, residual_tol = max(tol, FLOAT32_TOL), max(residual_tol, FLOAT32_RESIDUAL_TOL)
    G = model_tool_set_frame(model) if tool_set else None
    g_inv = None if G is None else inverse(G)
    if G is not None and free_tool_axis is not None and free_tool_axis is not False:
        # the axis is the tool's, given in the tool set's frame: in the modeled flange it is turned by G
        a = torch.tensor([0.0, 0.0, 1.0]) if free_tool_axis is True else torch.as_tensor(free_tool_axis)
        free_tool_axis = G[:3, :3] @ a.to(G)
    args = (tol, max_iter, damping, chunk_size, max_damped_iter, contraction, length, residual_tol, sigma, broyden,
            refresh, refresh_model, max_step, max_correction, null_damping, branch, free_tool_axis, tool_point,
            position_only)
    with threads_for_work(q_nom.shape[0] * FLOPS_PER_POSE):  # small batches on one thread (torchcal.core.threads)
        eligible = (target is None and branch and broyden and refresh_model and not sigma and free_tool_axis is None
                    and (tool_point is None or position_only)
                    and model.n == 6 and (q_nom.shape[0] >= FUSED_MIN_POSES
                                          or (_fused_warm() and not (position_only and _position_cold()))))
        if eligible:
            _check_inputs(model, q_nom, direction)
            setup = compiled_pass_setup(model, q_nom, dict(tol=tol, max_iter=max_iter, contraction=contraction,
                                                           length=length, residual_tol=residual_tol, refresh=refresh,
                                                           max_correction=max_correction, null_damping=null_damping))
            if setup is not None and position_only:  # 3-DOF: .fused_position (the tool points (B, 3), checked)
                points = tool_axis(None, tool_point, torch.float64, q_nom.device, q_nom.shape[0], True).point.detach()
                return _with_rest(model, q_nom, direction, _compiled_pass(setup, q_nom, direction, g_inv, points),
                                  length, args, g_inv, points)
            if setup is not None:
                return _with_rest(model, q_nom, direction, _compiled_pass(setup, q_nom, direction, g_inv), length, args,
                                  g_inv)
        return _solve(model, q_nom, direction, *args, target, g_inv)


def _position_cold() -> bool:
    """The 3-DOF pass's kernel is not compiled in this machine's cache (a cache older than it): a small batch then
    runs on the torch ops rather than wait minutes for the compile (a large one pays it, announced)."""
    from ..core.compiled import cold

    return bool(cold("position"))


def compiled_pass_setup(model, q: torch.Tensor, options: dict):
    """(the model's compiled flange, the pass's settings) for :mod:`.fused_targets` from :func:`compensate`'s
    keyword arguments (its defaults where ``options`` leaves one out), or None where the pass does not apply
    (not CPU float64 with numba, a live model: compliance, fine tables)."""
    from . import fused

    if not fused.available(q.device, q.dtype):
        return None
    kernel = FlangeKernel(model)
    if kernel.fused is None:
        return None
    o = {**_compensate_defaults(), **options}
    length = float(o["length"])
    bound = per_joint_bound(o["max_correction"], model.n, torch.float64, "cpu", "max_correction",
                            model.robot.joint_map.prismatic if hasattr(model, "robot") else None)
    return kernel.fused, dict(tol=o["tol"], residual_tol=o["residual_tol"], max_iter=o["max_iter"],
                              contraction=o["contraction"], length=length, max_correction=bound, path_above=PATH_ABOVE,
                              sigma_floor=0.1 * o["null_damping"], refresh=o["refresh"] if o["refresh_model"] else 0,
                              refresh_floor=o["null_damping"], lipschitz=jacobian_lipschitz(kernel, length))


def _compensate_defaults() -> dict:
    """compensate()'s keyword defaults (one source for the compiled pass's settings)."""
    import inspect

    return {k: p.default for k, p in inspect.signature(compensate).parameters.items()
            if p.default is not inspect.Parameter.empty}


def _compiled_pass(setup, q_nom, direction, g_inv=None, points=None) -> dict:
    """:func:`.fused_targets.solve_commands` over every row (the same iteration as :func:`_solve`'s fast path, pose
    by pose in one compiled pass), in chunks; points: (B, 3) tool points: 3-DOF, :func:`.fused_position.solve_positions`."""
    from .fused_position import solve_positions
    from .fused_targets import solve_commands

    fused, opts = setup
    B, size = q_nom.shape[0], 262144  # chunks: progress on long batches, bounded scratch

    def part(c0):
        d = None if direction is None else direction[c0:c0 + size]
        if points is None:
            return solve_commands(fused, q_nom[c0:c0 + size], d, **opts, tool_set_inverse=g_inv)
        return solve_positions(fused, q_nom[c0:c0 + size], d, points[c0:c0 + size], **opts, tool_set_inverse=g_inv)

    parts = [part(c0) for c0 in _chunks(B, size, "compensation, compiled pass (chunks)")]
    return {k: torch.cat([p[k] for p in parts]) for k in parts[0]}


def compiled_rows(fast: dict, length: float, position_only: bool = False):
    """The compiled pass's output as result columns, rows it handed on still to fill: -> dict of done (B,) bool,
    q, pose_error, step, iterations, residual (weighted, m; position_only: the position's alone, as
    :func:`_solve`'s), converged, damped, status (:mod:`.result` codes)."""
    from .fused_targets import DONE

    done = fast["status"] == DONE
    de = fast["pose_error"].clone()
    res = de[:, :3].norm(dim=-1) if position_only else torch.cat([de[:, :3], length * de[:, 3:]], 1).norm(dim=-1)
    return {"done": done, "q": fast["q"].clone(), "pose_error": de, "step": fast["step"].clone(),
            "iterations": fast["iterations"].clone(),
            "residual": res, "converged": done.clone(),
            "damped": torch.zeros_like(done), "status": torch.where(done, CONVERGED, NOT_CONVERGED).to(torch.int8)}


def fill_rows(cols: dict, rows: torch.Tensor, res: CompensationResult) -> None:
    """Write a :class:`CompensationResult` of the handed-on ``rows`` into :func:`compiled_rows`' columns."""
    for k in ("q", "pose_error", "step", "iterations", "residual", "converged", "damped", "status"):
        cols[k][rows] = getattr(res, k)


def _with_rest(model, q_nom, direction, fast, length, args, g_inv=None, points=None) -> CompensationResult:
    """The compiled pass's rows, with the rows it handed on (near a singularity, beyond its bounds, a possible
    branch change) solved by :func:`_solve`, in input order; points: (B, 3) the tool points of a 3-DOF call."""
    c = compiled_rows(fast, length, points is not None)
    rest = (~c["done"]).nonzero()[:, 0]
    if rest.numel():
        work = None
        if points is not None:  # args[17]: _solve's tool_point, the rest's rows of it
            args = args[:17] + (points[rest],) + args[18:]
            # 3-DOF: the rest (~0.2 % of the rows) runs on torch ops alone (no compiled damped pass with a free
            # rotation), dispatch-bound: on one thread, as threads_for sizes it (100 000 poses, 158 rows handed on,
            # 2 cores with a neighbour: 1.6 s on two threads, 0.35 s on one)
            work = rest.numel() * FLOPS_PER_POSE
        with threads_for_work(work) if work is not None else contextlib.nullcontext():
            fill_rows(c, rest, _solve(model, q_nom[rest], None if direction is None else direction[rest], *args, None,
                                      g_inv))
    q = c["q"]
    within, outside = range_and_coverage(model, q, direction)
    return CompensationResult(q, c["converged"], c["iterations"], c["pose_error"], c["residual"], c["step"],
                              c["damped"], within, None, (q - q_nom).abs().amax(-1), outside, c["status"])


def _chunks(count: int, chunk_size: int, name: str):
    """range(0, count, chunk_size), reported as a progress task (:mod:`torchcal.core.progress`) of one item per chunk."""
    with progress_task(name, total=-(-count // chunk_size)) as t:
        for c0 in range(0, count, chunk_size):
            yield c0
            t.advance()


@torch.no_grad()
def _solve(model, q_nom, direction, tol, max_iter, damping, chunk_size, max_damped_iter, contraction, length,
           residual_tol, sigma, broyden, refresh, refresh_model, max_step, max_correction, null_damping, branch,
           free_tool_axis, tool_point, position_only=False, target=None, g_inv=None):
    """:func:`compensate`'s work, on the calling thread count; g_inv: (4, 4) the inverse of the tool-set frame
    taken on the right of every goal, or None."""
    _check_inputs(model, q_nom, direction, given=target is None)
    if target is not None and (target.shape != (q_nom.shape[0], 4, 4) or target.device != q_nom.device):
        raise InputError(f"compensate: target must be ({q_nom.shape[0]}, 4, 4) poses on {q_nom.device}, "
                         f"got {tuple(target.shape)} on {target.device}")
    dtype, device = model.dtype, model.device
    if target is not None:
        target = target.to(dtype)
    q_nom = q_nom.to(dtype)
    B, n = q_nom.shape
    prismatic = model.robot.joint_map.prismatic if hasattr(model, "robot") else None
    max_step = per_joint_bound(max_step, n, dtype, device, "max_step", prismatic)
    max_correction = per_joint_bound(max_correction, n, dtype, device, "max_correction", prismatic)
    ax = tool_axis(free_tool_axis, tool_point, dtype, device, B, position_only)
    if direction is not None:
        direction = direction.to(dtype)
    # the compiled kernel's first call in a process costs ~0.5-0.8 s (numba loads its cached machine code and
    # sets up LLVM), more than the torch ops take for a few thousand poses (the fit's compensation check)
    kernel = FlangeKernel(model, fused=None if B >= FUSED_MIN_POSES or _fused_warm() else False)
    if chunk_size is None:
        # a GPU is bound by kernel launches (~25 000 per call, whatever the batch): one chunk of every pose
        # (measured on an H200: 1.4e6 poses/s in chunks of 262 144, 2.5e6 in one chunk of 10^6)
        chunk_size = min(max(B, 1), GPU_CHUNK if q_nom.device.type == "cuda" else 262144)
    chunk_size = max(int(chunk_size), 1)
    branch = branch and n == 6

    q_out = torch.empty(B, n, dtype=dtype, device=device)
    step = torch.empty(B, dtype=dtype, device=device)
    iters = torch.zeros(B, dtype=torch.long, device=device)
    ok = torch.zeros(B, dtype=torch.bool, device=device)
    de_out = torch.empty(B, 6, dtype=dtype, device=device)
    sig = torch.empty(B, dtype=dtype, device=device) if sigma else None
    targets_R = torch.empty(3, 3, B, dtype=dtype, device=device)
    targets_p = torch.empty(3, B, dtype=dtype, device=device)
    # branch test: rows clear of a singular surface at q_nom, and det J's sign there
    clear = torch.zeros(B, dtype=torch.bool, device=device)
    sign0 = torch.zeros(B, dtype=dtype, device=device)
    # a lower bound of sigma_min at q_nom (from the inverse the iteration uses): rows that provably stay on
    # their branch skip the test (branch.surely_same_branch); 0 where no bound is known (5-DOF)
    sig_lb = torch.zeros(B, dtype=dtype, device=device)
    lipschitz = jacobian_lipschitz(kernel, length) if branch and ax is None else None

    for c0 in _chunks(B, chunk_size, "fixed-Jacobian Newton (chunks)"):
        sl = slice(c0, min(c0 + chunk_size, B))
        qT = q_nom[sl].T.contiguous()
        sT = None if direction is None else direction[sl].T.contiguous()
        Rn, pn, J = kernel.nominal_flange_jacobian(qT)
        R_chord = Rn  # the frame of J (the nominal flange's)
        if target is not None:
            Rn, pn = target[sl, :3, :3].permute(1, 2, 0).contiguous(), target[sl, :3, 3].T.contiguous()
        if g_inv is not None:  # goal G^-1: the tool set's frame F_a G reaches the goal (.toolset)
            g = g_inv.to(dtype)
            pn = pn + torch.einsum("ijb,j->ib", Rn, g[:3, 3])
            Rn = torch.einsum("ijb,jk->ikb", Rn, g[:3, :3])
        targets_R[..., sl], targets_p[:, sl] = Rn, pn
        if sigma:
            sig[sl] = sigma_min_soa(J, length)
        if branch:
            sign0[sl] = det_sign_soa(J)
        cT = None if ax is None else ax.pointT(torch.arange(sl.start, sl.stop, device=device))
        xT = cT  # the tool points in the chord's frame: G^-1 c in the nominal flange's (the goal is F_n G^-1)
        if cT is not None and g_inv is not None:
            g = g_inv.to(dtype)
            xT = g[:3, :3] @ cT + g[:3, 3, None]
        if ax is not None:  # 5- / 3-DOF: the tool point's target, the kept rows of the Jacobian
            pn = ax.shift_soa(Rn, pn, cT)
            J = ax.world_jacobian_soa(R_chord, J, xT) if ax.position_only else ax.jacobian_soa(J, cT)
        P, invertible = nominal_jacobian_inverse(J, 0.1 * null_damping, length)
        clear[sl] = invertible
        if lipschitz is not None:
            fro2 = (P[:, :3] ** 2).sum((0, 1)) + (P[:, 3:] ** 2).sum((0, 1)) / length**2
            sig_lb[sl] = torch.where(invertible, fro2.clamp(min=1e-300).rsqrt(), torch.zeros_like(fro2))
        out = fixed_jacobian_iterations(
            kernel, qT, sT, Rn, pn, P, invertible, tol, max_iter, contraction, length, residual_tol, broyden,
            qT, max_correction, ax, cT,
        )
        qc, de, st, it, okc, far = out["q"], out["de"], out["step"], out["iterations"], out["ok"], out["far"]
        # Rows that did not contract moved far from q_nom (near a singularity a
        # small orientation error needs tenths of a radian): linearize again at
        # their best iterate and repeat, still on the fast kernel.
        for _ in range(refresh):
            f = (~okc & ~far).nonzero()[:, 0]  # a row that converged beyond the bound would only do it again
            if f.numel() == 0:
                break
            sf = None if sT is None else sT[:, f]
            Rf, _, Jf = (kernel.flange_jacobian(qc[:, f], sf) if refresh_model else kernel.nominal_flange_jacobian(qc[:, f]))
            if ax is not None and ax.position_only:
                Jf = ax.world_jacobian_soa(Rf, Jf, (cT if refresh_model else xT)[:, f])
            elif ax is not None:
                Jf = ax.jacobian_soa(Jf, cT[:, f])
            # (a stricter floor here: at a row's best iterate the modeled joint may sit just off a
            # singularity that the solution lies on, where a chord step moves the null space freely)
            Pf, okf = nominal_jacobian_inverse(Jf, null_damping, length)
            o = fixed_jacobian_iterations(
                kernel, qc[:, f], sf, Rn[..., f], pn[:, f], Pf, okf, tol, max_iter, contraction, length, residual_tol, broyden,
                qT[:, f], max_correction, ax, None if cT is None else cT[:, f],
            )
            qc[:, f], de[:, f], st[f], okc[f], far[f] = o["q"], o["de"], o["step"], o["ok"], o["far"]
            it[f] += o["iterations"]
        q_out[sl], step[sl], iters[sl], ok[sl] = qc.T, st, it, okc
        de_out[sl] = de.T

    status = torch.full((B,), NOT_CONVERGED, dtype=torch.int8, device=device)
    status[ok] = CONVERGED
    crossed = torch.zeros(B, dtype=torch.bool, device=device)
    if branch:  # a fast-path solution on another branch: solve it again from q_nom on the damped path
        sure = surely_same_branch(q_nom, q_out, sig_lb, lipschitz)
        crossed = branch_changed(kernel, q_nom, q_out, ok & clear & ~sure, sign_from=sign0)
        ok &= ~crossed
    damped = ~ok
    if damped.any():
        k = damped.nonzero()[:, 0]
        target = homogeneous(targets_R[..., k].permute(2, 0, 1), targets_p[:, k].T)
        for c0 in _chunks(k.numel(), chunk_size, f"damped least squares, {k.numel()} poses (chunks)"):
            kk = k[c0:c0 + chunk_size]
            tk = target[c0:c0 + chunk_size]
            dk = None if direction is None else direction[kk]
            axk = None if ax is None else ax.subset(kk)
            # start from the fast path's best iterate only when it is a bounded correction on the nominal
            # command's branch (rows whose best lies on another branch restart at q_nom)
            away = crossed[kk]
            if max_correction is not None:
                away = away | (((q_out[kk] - q_nom[kk]).abs() / max_correction).amax(-1) > 1.0)
            q_out[kk] = torch.where(away[:, None], q_nom[kk], q_out[kk])
            opts = dict(tol=tol, max_iter=max_damped_iter, damping=damping, length=length, residual_tol=residual_tol,
                        kernel=kernel, q_ref=q_nom[kk], max_step=max_step, max_correction=max_correction,
                        stop_at_bound=True, axis=axk)
            if null_damping:
                # first pass: only picks the branch and the null-space component (the polish below
                # restores the accuracy), so a loose tolerance and few iterations do; rows whose exact
                # solution lies outside the bounds would otherwise crawl along the box's faces
                first = dict(opts, tol=max(tol, 1e-8), max_iter=min(max_damped_iter, 20))
                res = damped_least_squares(model, q_out[kk], tk, dk, lam=null_damping, **first)
            else:
                res = damped_least_squares(model, q_out[kk], tk, dk, **opts)
            q_out[kk], ok[kk], step[kk], de_out[kk] = res.q, res.converged, res.step, res.pose_error
            status[kk] = _damped_status(res)
            iters[kk] += res.iterations
            if null_damping:
                # the damped pass leaves a bias of ~lam² |dq| / sigma: polish without it, inside the same
                # bounds. Rows blocked by the bounds already (the damped optimum lies outside) keep the
                # damped pass's iterate: flagged, with the smallest swing
                m = (~res.converged & ~res.blocked).nonzero()[:, 0]
                if m.numel():
                    km = kk[m]
                    opts["q_ref"] = q_nom[km]
                    opts["axis"] = None if ax is None else ax.subset(km)
                    # from there Levenberg-Marquardt needs a handful of steps (a solution outside the
                    # bounds runs into the box and stops)
                    opts["max_iter"] = min(max_damped_iter, 20)
                    pol = damped_least_squares(model, res.q[m], tk[m], None if dk is None else dk[m], **opts)
                    iters[km] += pol.iterations
                    # converged, or stopped at a stationary point of the error inside the bounds (an
                    # unreachable target's best pose): take it; run into the bounds: keep the damped pass
                    c = (pol.converged | ~pol.blocked).nonzero()[:, 0]
                    kc = km[c]
                    q_out[kc], ok[kc], step[kc], de_out[kc] = pol.q[c], pol.converged[c], pol.step[c], pol.pose_error[c]
                    status[kc] = _damped_status(pol)[c]
        if branch:  # the damped path's solutions on another branch are refused: flagged
            sure = surely_same_branch(q_nom, q_out, sig_lb, lipschitz)
            again = branch_changed(kernel, q_nom, q_out, ok & damped & clear & ~sure, sign_from=sign0)
            ok &= ~again
            status[again] = BRANCH
    _mark_singular_ends(kernel, q_out, direction, status, length, ax)

    lim = model.command_limits.to(dtype)
    within = ((q_out >= lim[:, 0]) & (q_out <= lim[:, 1])).all(-1)
    w = torch.cat([de_out[:, :3], length * de_out[:, 3:]], -1)
    residual = (w if ax is None else ax.project_rows(w)).norm(dim=-1)
    correction = (q_out - q_nom).abs().amax(-1) if n else torch.zeros(B, dtype=dtype, device=device)
    outside = None
    coverage = getattr(model, "coverage", None)
    if coverage is not None and direction is not None:
        # the approach pattern of the command actually sent (the bins may differ from q_nom's)
        outside = coverage.outside(q_out, direction).to(device=device, dtype=torch.bool)
    return CompensationResult(q_out, ok, iters, de_out, residual, step, damped, within, sig, correction, outside, status)


def _mark_singular_ends(kernel, q, direction, status, length: float, ax=None) -> None:
    """Rows that ran out of iterations (NOT_CONVERGED) where the modeled Jacobian at their best command has lost
    rank -> SINGULAR, in place: they ended on a singular surface of the model, which the flag then names.
    q: (B, n); direction: (B, n) or None; status: (B,) int8; ax: a :class:`.axis.ToolAxis` (the rank of its kept
    rows: a wrist singularity does not stop a 3-DOF solve) or None."""
    k = (status == NOT_CONVERGED).nonzero()[:, 0]
    if k.numel() == 0:
        return
    s = None if direction is None else direction[k].T.contiguous()
    _, _, J = kernel.flange_jacobian(q[k].T.contiguous(), s)
    if ax is not None:
        J = ax.jacobian_soa(J, ax.pointT(k))
    status[k[sigma_min_soa(J, length) < SINGULAR_FLOOR]] = SINGULAR


def _damped_status(res) -> torch.Tensor:
    """A :class:`.damped.DampedResult`'s rows -> status codes (:mod:`.result`)."""
    st = torch.full(res.converged.shape, NOT_CONVERGED, dtype=torch.int8, device=res.converged.device)
    st[res.stationary] = OUT_OF_REACH
    st[res.blocked] = AT_BOUND
    st[res.converged] = CONVERGED
    return st
