"""Robust compensation: damped least squares (Levenberg-Marquardt) on the pose error (47)-(48).

The fixed-Jacobian iteration of Paper II (49)-(50) contracts only while the
Jacobian it holds stays a good model of the actual robot around the
solution. Near a singularity, or when the modeled robot cannot reach the
target at all, it stalls or diverges. Those rows come here: Levenberg-
Marquardt with the *current* model Jacobian (error slopes included), the
damping adapted per pose (Nielsen's rule), so steps shrink along directions
whose singular values are small instead of blowing up. Rows that cannot be
brought to zero error end at their lowest-error iterate and are flagged.
With ``q_ref`` the correction is bounded (a box |q - q_ref| <= max_correction,
steps <= max_step) and optionally damped toward q_ref (Tikhonov ``lam``), so
that near-null directions do not swing the joints; see :func:`damped_least_squares`.

All rows are solved together (a loop over iterations, masks over rows);
finished rows leave the working set. SI units: m, rad; orientation errors are
weighted by ``length`` (m) so that both parts of the residual are lengths.
"""

from __future__ import annotations

import os
from dataclasses import dataclass

import torch

from ..kinematics.transforms import skew, small_matmul
from .kernel import FlangeKernel


def pose_residual(Ra: torch.Tensor, pa: torch.Tensor, Rn: torch.Tensor, pn: torch.Tensor):
    """Error transform Ω = inv(F_a) F_n pieces and de of (47)-(48), rows first.

    Ra, Rn: (M, 3, 3); pa, pn: (M, 3) -> de (M, 6) (m, rad) and Ω_R (M, 3, 3).
    """
    Rt = Ra.transpose(1, 2)
    OR = small_matmul(Rt, Rn)
    dp = small_matmul(Rt, (pn - pa)[..., None])[..., 0]
    dr = 0.5 * torch.stack([OR[:, 2, 1] - OR[:, 1, 2], OR[:, 0, 2] - OR[:, 2, 0], OR[:, 1, 0] - OR[:, 0, 1]], -1)
    return torch.cat([dp, dr], -1), OR


def residual_jacobian(de: torch.Tensor, OR: torch.Tensor, J: torch.Tensor, length: float) -> torch.Tensor:
    """Exact derivative of r = (de_p, length * de_r) w.r.t. the commands.

    de: (M, 6) and OR: (M, 3, 3) from :func:`pose_residual`; J: (M, 6, n) body
    Jacobian of F_a. -> (M, 6, n).

    With F_a(q + dq) = F_a(q) exp(ξ), ξ = (v, w) = J dq, the error transform
    becomes Ω' = exp(-ξ) Ω, so d de_p = -v + S(de_p) w and
    d de_r = -½ (tr(Ω_R) I - Ω_R) w. At the solution (Ω = I) this is -J; away
    from it the extra terms keep Gauss-Newton exact for the residual it
    minimizes, so an unreachable target ends at a true stationary point.
    """
    Jv, Jw = J[:, :3], J[:, 3:]
    tr = OR.diagonal(dim1=-2, dim2=-1).sum(-1)
    eye = torch.eye(3, dtype=J.dtype, device=J.device)
    G = 0.5 * (tr[:, None, None] * eye - OR)
    Jp = -Jv + small_matmul(skew(de[:, :3]), Jw)
    Jr = -small_matmul(G, Jw)
    return torch.cat([Jp, length * Jr], 1)


def weighted(de: torch.Tensor, length: float) -> torch.Tensor:
    """(M, 6) -> r (M, 6) = (de_p, length * de_r)."""
    return torch.cat([de[:, :3], length * de[:, 3:]], -1)


@dataclass
class DampedResult:
    """Outcome of :func:`damped_least_squares` for M rows.

    q: (M, n) lowest-error iterate; converged: (M,) bool; iterations: (M,) long;
    pose_error: (M, 6) de at q (m, rad); residual: (M,) weighted norm (m);
    step: (M,) norm of the last step (rad / m); blocked: (M,) bool, stopped at
    the bound (``stop_at_bound``); stationary: (M,) bool, stopped at a stationary point of the cost with
    error left, inside the bound (an unreachable target's best pose).
    """

    q: torch.Tensor
    converged: torch.Tensor
    iterations: torch.Tensor
    pose_error: torch.Tensor
    residual: torch.Tensor
    step: torch.Tensor
    blocked: torch.Tensor | None = None
    stationary: torch.Tensor | None = None


class _Eval:
    """Row-layout adapter around :class:`FlangeKernel`: q (M, n) -> rotations (M, 3, 3), positions (M, 3)."""

    def __init__(self, kernel: FlangeKernel):
        self.k = kernel

    def flange(self, q, s):
        R, p = self.k.flange(q.T.contiguous(), None if s is None else s.T.contiguous())
        return R.permute(2, 0, 1), p.T

    def flange_jacobian(self, q, s):
        R, p, J = self.k.flange_jacobian(q.T.contiguous(), None if s is None else s.T.contiguous())
        return R.permute(2, 0, 1), p.T, J.permute(2, 0, 1)


@torch.no_grad()
def damped_least_squares(
    model,
    q0: torch.Tensor,
    target: torch.Tensor,
    direction: torch.Tensor | None = None,
    tol: float = 1e-10,
    max_iter: int = 100,
    damping: float = 1e-5,
    length: float = 1.0,
    residual_tol: float = 1e-12,
    kernel: FlangeKernel | None = None,
    stall_rtol: float = 1e-10,
    window: int = 5,
    window_rtol: float = 1e-8,
    q_ref: torch.Tensor | None = None,
    lam: float = 0.0,
    max_step: float | None = None,
    max_correction: float | None = None,
    stop_at_bound: bool = False,
    axis=None,
    fixed_shape: bool | None = None,
) -> DampedResult:
    """Solve model.flange(q, direction, base=False) = target for every row by Levenberg-Marquardt.

    q0: (M, n) start (rad / m); target: (M, 4, 4) in the robot's nominal base
    frame; direction: (M, n) or None; tol: step norm for convergence (51);
    max_iter: iterations per row; damping: initial damping relative to the
    largest diagonal entry of J^T J; length: m per rad for orientation rows;
    residual_tol: a row only counts as converged when its weighted pose error
    is below this (m) -- a vanishing step alone also happens at the
    least-squares optimum of an unreachable target; kernel: a
    :class:`FlangeKernel` of the model (built when None); stall_rtol: a row
    whose nearly undamped (Gauss-Newton) step is accepted but lowers the cost
    by less than this fraction sits at a stationary point with nonzero error:
    it stops there, not converged. (Towards a reachable target such a step
    removes most of the cost; near an unreachable optimum Gauss-Newton only
    converges linearly and would need many more iterations to shrink the
    step below tol without changing the result.) window, window_rtol: a row
    whose cost fell by less than this fraction over the last `window`
    iterations is stuck the same way and stops, flagged.

    Bounded, minimum-norm corrections (q_ref: (M, n) reference commands, the
    nominal ones in :func:`.compensate`): the cost becomes
    ½|r(q)|² + ½ lam² |q - q_ref|², Tikhonov damping toward q_ref (lam in m
    per rad), so directions whose singular values are well below lam (the
    wrist's q4/q6 combination at q5 = 0) stay at q_ref instead of drifting;
    each step is scaled to max|dq| <= max_step (rad / m; a number, or an (n,)
    tensor per joint) and every iterate is kept inside the box
    |q - q_ref| <= max_correction (likewise). lam > 0 biases the
    solution (residual ~ lam² |q - q_ref| / sigma), so a converged command
    needs a final pass with lam = 0 (what :func:`.compensate` does).
    stop_at_bound: a row whose step runs into the box stops there, flagged
    (the optimum lies outside it; creeping along the box's faces costs many
    iterations for nothing a flagged row needs). DampedResult.blocked marks them.

    fixed_shape: finished rows stay in place, frozen, instead of leaving the working set, and the linear
    solves are Cholesky's (:mod:`.damped_graph`: on a GPU the iterations are then replayed as CUDA graphs;
    True also on the CPU, in torch ops instead of the compiled pass). None: on a CUDA device (6-DOF, no
    gravity compliance) unless TORCHCAL_CUDA_GRAPHS=0.
    """
    M, n = q0.shape
    dtype, device = q0.dtype, q0.device
    ev = _Eval(kernel if kernel is not None else FlangeKernel(model))
    if M and ev.k.fused is not None and axis is None and not fixed_shape:
        return _compiled(ev.k.fused, q0, target, direction, q_ref, tol, max_iter, damping, length, residual_tol,
                         stall_rtol, window, window_rtol, lam, max_step, max_correction, stop_at_bound)
    q_out = q0.clone()
    conv_out = torch.zeros(M, dtype=torch.bool, device=device)
    it_out = torch.zeros(M, dtype=torch.long, device=device)
    step_out = torch.full((M,), float("inf"), dtype=dtype, device=device)
    de_out = torch.zeros(M, 6, dtype=dtype, device=device)
    blk_out = torch.zeros(M, dtype=torch.bool, device=device)
    sta_out = torch.zeros(M, dtype=torch.bool, device=device)
    if M == 0:
        return DampedResult(q_out, conv_out, it_out, de_out, torch.zeros(0, dtype=dtype, device=device), step_out, blk_out,
                            sta_out)
    eye = torch.eye(n, dtype=dtype, device=device)
    lam2 = float(lam) ** 2
    ref = q0.clone() if q_ref is None else q_ref.to(dtype)
    if max_correction is not None:
        q0 = torch.minimum(torch.maximum(q0, ref - max_correction), ref + max_correction)

    q = q0.clone()
    Rn, pn = target[:, :3, :3], target[:, :3, 3]
    c = None
    if axis is not None:
        c = axis.point
        pn = axis.shift_rows(Rn, pn, c)
    C = dict(s=direction, c=c, Rn=Rn, pn=pn, ref=ref)
    opts = _Options(ev, axis, length, lam2, eye, max_step, max_correction, stop_at_bound, tol, residual_tol, stall_rtol,
                    window_rtol)
    de, r, Jr, near = _evaluate(opts, q, C)
    cost = 0.5 * (r * r).sum(-1) + (_prior(lam2, q, ref) if lam2 else 0.0)
    cost = torch.where(torch.isfinite(cost), cost, torch.full_like(cost, float("inf")))
    A = small_matmul(Jr.transpose(1, 2), Jr)
    mu = damping * A.diagonal(dim1=-2, dim2=-1).amax(-1).clamp_min(1e-12)
    S = dict(q=q, r=r, de=de, Jr=Jr, near=near, cost=cost, mu=mu, nu=torch.full_like(mu, 2.0),
             it=torch.zeros(M, dtype=torch.long, device=device),
             step=torch.full((M,), float("inf"), dtype=dtype, device=device), cost_ref=cost.clone(),
             hits=torch.zeros(M, dtype=torch.long, device=device))
    if fixed_shape is None:
        fixed_shape = device.type == "cuda" and axis is None and ev.k.model is None and graphs_enabled()
    if fixed_shape:
        from .damped_graph import solve_fixed_shape  # (imported here: CPU runs never need it)

        o = solve_fixed_shape(lambda S, C, check: lm_step(opts, S, C, check, spd_solve), S, C, max_iter, window,
                              graphs=device.type == "cuda" and graphs_enabled())
        S, conv_out, blk_out, sta_out = o["state"], o["converged"], o["blocked"], o["stationary"]
        q_out, it_out, step_out, de_out = S["q"], S["it"], S["step"], S["de"]
    else:
        _eager_loop(opts, S, C, max_iter, window, q_out, conv_out, it_out, step_out, de_out, blk_out, sta_out)
    res = weighted(de_out, length)
    res = (res if axis is None else axis.project_rows(res)).norm(dim=-1)
    return DampedResult(q_out, conv_out, it_out, de_out, res, step_out, blk_out, sta_out)


def graphs_enabled() -> bool:
    """On a GPU the iterations run as captured CUDA graphs (:mod:`.damped_graph`) unless TORCHCAL_CUDA_GRAPHS=0."""
    return os.environ.get("TORCHCAL_CUDA_GRAPHS", "1") != "0"


@dataclass(frozen=True)
class _Options:
    """What one Levenberg-Marquardt iteration of :func:`damped_least_squares` reads besides its rows."""

    ev: _Eval
    axis: object
    length: float
    lam2: float
    eye: torch.Tensor
    max_step: object
    max_correction: object
    stop_at_bound: bool
    tol: float
    residual_tol: float
    stall_rtol: float
    window_rtol: float


def _prior(lam2, q, ref):
    d = q - ref
    return 0.5 * lam2 * (d * d).sum(-1)


def _evaluate(o: _Options, q, C):
    """-> de (M, 6), the residual r and its Jacobian (5-DOF: projected), and whether the orientation error
    is below 90 deg (the residual ½ vee(Ω_R - Ω_R^T) = sin(angle) axis vanishes at 180 deg too: an LM
    started far away can settle on the pose turned half a turn, which is no solution)."""
    Ra, pa, J = o.ev.flange_jacobian(q, C["s"])
    c = C["c"]
    if c is not None:
        pa, J = o.axis.shift_rows(Ra, pa, c), o.axis.jacobian_rows(J, c)
    de, OR = pose_residual(Ra, pa, C["Rn"], C["pn"])
    r, Jr = weighted(de, o.length), residual_jacobian(de, OR, J, o.length)
    if c is not None:
        r, Jr = o.axis.project_rows(r), o.axis.project_rows(Jr)
    # (5-DOF: the turn about the free axis may be anything; the axis itself is in the residual)
    near = torch.ones_like(r[:, 0], dtype=torch.bool) if c is not None else OR.diagonal(dim1=-2, dim2=-1).sum(-1) > 1.0
    return de, r, Jr, near


def lu_solve(A: torch.Tensor, b: torch.Tensor):
    """(M, n, n), (M, n) -> x (M, n), ok (M,) bool: LAPACK's / cuSOLVER's LU (the eager loop's solve)."""
    x, info = torch.linalg.solve_ex(A, b)
    return x, info == 0


def spd_solve(A: torch.Tensor, b: torch.Tensor):
    """(M, n, n) symmetric positive definite, (M, n) -> x (M, n), ok (M,) bool: Cholesky unrolled over the n
    columns, elementwise over the rows: nothing but elementwise kernels and no host synchronization, which a
    CUDA graph can hold (torch.linalg.solve's CUDA path could not be captured, pytorch/pytorch#96632; solve_ex was
    not tried). A row that is not positive definite gets ok False (and a non-finite x)."""
    n = A.shape[-1]
    At = A.permute(1, 2, 0).contiguous()  # (n, n, M): each entry a contiguous run of rows
    L = [[None] * n for _ in range(n)]
    inv = [None] * n  # 1 / L_jj
    ok = torch.ones_like(b[:, 0], dtype=torch.bool)
    for j in range(n):
        d = At[j, j]
        for k in range(j):
            d = torch.addcmul(d, L[j][k], L[j][k], value=-1.0)
        ok = ok & (d > 0)
        inv[j] = torch.rsqrt(d)
        for i in range(j + 1, n):
            v = At[i, j]
            for k in range(j):
                v = torch.addcmul(v, L[i][k], L[j][k], value=-1.0)
            L[i][j] = v * inv[j]
    bt = b.T
    y = [None] * n
    for j in range(n):  # L y = b
        v = bt[j]
        for k in range(j):
            v = torch.addcmul(v, L[j][k], y[k], value=-1.0)
        y[j] = v * inv[j]
    x = [None] * n
    for j in reversed(range(n)):  # L^T x = y
        v = y[j]
        for k in range(j + 1, n):
            v = torch.addcmul(v, L[k][j], x[k], value=-1.0)
        x[j] = v * inv[j]
    return torch.stack(x, -1), ok


def lm_step(o: _Options, S: dict, C: dict, check_window: bool | torch.Tensor, solve=lu_solve):
    """One Levenberg-Marquardt iteration of every row of S (the state: q, r, de, Jr, near, cost, mu, nu, it,
    step, cost_ref, hits; C: the rows' targets, directions, references), as pure tensor functions.

    -> (the new state, conv, stall, blocked (or None)): every (M, ...) row on its own, so that the eager loop may
    drop finished rows and the fixed-shape loop of a GPU may freeze them instead. check_window: this iteration
    closes a window of ``window`` iterations (the progress test): a bool, or a 0-dim bool tensor on the rows'
    device."""
    q, r, Jr, cost, mu, nu, ref = S["q"], S["r"], S["Jr"], S["cost"], S["mu"], S["nu"], C["ref"]
    lam2, eye = o.lam2, o.eye
    JrT = Jr.transpose(1, 2)
    A = small_matmul(JrT, Jr)
    g = small_matmul(JrT, r[..., None])[..., 0]  # gradient of ½|r|²
    if lam2:
        A = A + lam2 * eye
        g = g + lam2 * (q - ref)
    dq, solved = solve(A + mu[:, None, None] * eye, -g)
    dq = torch.where(solved[:, None] & torch.isfinite(dq), dq, torch.zeros_like(dq))
    if o.max_step is not None:  # trust bound (a number or one per joint): scale the step, keep its direction
        big = (dq.abs() / o.max_step).amax(-1, keepdim=True)
        dq = dq * torch.clamp(1.0 / big.clamp_min(1e-300), max=1.0)
    qt = q + dq
    blocked, hits = None, S["hits"]
    if o.max_correction is not None:  # stay in the box around q_ref
        qb = torch.minimum(torch.maximum(qt, ref - o.max_correction), ref + o.max_correction)
        if o.stop_at_bound:  # twice: a first, overshooting LM step is no evidence yet
            hits = hits + (qb != qt).any(-1).long()
            blocked = hits >= 2
        qt = qb
        dq = qt - q
    # evaluate the trial with its Jacobian: most steps are accepted and need it next
    de_t, rt, Jr_t, near_t = _evaluate(o, qt, C)
    cost_t = 0.5 * (rt * rt).sum(-1) + (_prior(lam2, qt, ref) if lam2 else 0.0)
    cost_t = torch.where(torch.isfinite(cost_t), cost_t, torch.full_like(cost_t, float("inf")))
    # Nielsen: the decrease the linear model predicts for the step taken (scaled or clipped:
    # -g·dq - ½ dq·A dq; for the plain LM step this is ½ dq·(mu dq - g))
    pred = -(dq * (g + 0.5 * small_matmul(A, dq[..., None])[..., 0])).sum(-1)
    rho = (cost - cost_t) / pred.clamp_min(1e-300)
    acc = (cost_t < cost) & (rho > 0)
    # an accepted, nearly undamped step that no longer lowers the cost: stationary point
    flat = acc & ((cost - cost_t) <= o.stall_rtol * cost) & (mu <= 1e-3 * A.diagonal(dim1=-2, dim2=-1).amax(-1))
    a1 = acc[:, None]
    N = dict(q=torch.where(a1, qt, q), cost=torch.where(acc, cost_t, cost), r=torch.where(a1, rt, r),
             de=torch.where(a1, de_t, S["de"]), near=torch.where(acc, near_t, S["near"]),
             Jr=torch.where(a1[..., None], Jr_t, Jr),
             mu=torch.where(acc, mu * torch.clamp(1.0 - (2.0 * rho - 1.0) ** 3, min=1.0 / 3.0), mu * nu),
             nu=torch.where(acc, torch.full_like(nu, 2.0), 2.0 * nu), it=S["it"] + 1, step=dq.norm(dim=-1),
             cost_ref=S["cost_ref"], hits=hits)
    small = N["step"] < o.tol
    conv = small & ((N["r"] * N["r"]).sum(-1).sqrt() <= o.residual_tol) & N["near"]
    # stalled: a vanishing step far from zero error (least-squares optimum of an
    # unreachable target, or damping so large that nothing moves any more)
    stall = ((small | flat) & ~conv) | (N["mu"] > 1e20) | ~torch.isfinite(N["cost"])
    if isinstance(check_window, torch.Tensor):  # decided on the device (a captured graph replays every iteration)
        stall = stall | (check_window & ~conv & (N["cost"] > (1.0 - o.window_rtol) * S["cost_ref"]))
        N["cost_ref"] = torch.where(check_window, N["cost"], S["cost_ref"])
    elif check_window:
        # no real progress over the last `window` iterations: stuck at a stationary
        # point (or crawling along a singular direction); keep the best, flag it
        stall = stall | (~conv & (N["cost"] > (1.0 - o.window_rtol) * S["cost_ref"]))
        N["cost_ref"] = N["cost"]
    if blocked is not None:
        stall = stall | (blocked & ~conv)
    return N, conv, stall, blocked


def _eager_loop(o: _Options, S, C, max_iter, window, q_out, conv_out, it_out, step_out, de_out, blk_out, sta_out):
    """The iterations with finished rows dropped from the working set (CPU, or a GPU without graphs); the rows'
    results are written into the *_out tensors (M, ...) in place."""
    idx = torch.arange(q_out.shape[0], device=q_out.device)
    for k_it in range(max_iter):
        S, conv, stall, blocked = lm_step(o, S, C, (k_it + 1) % window == 0)
        done = conv | stall
        if bool(done.any()):
            d = done.nonzero()[:, 0]
            rows = idx[d]
            q_out[rows], conv_out[rows], it_out[rows] = S["q"][d], conv[d], S["it"][d]
            step_out[rows], de_out[rows] = S["step"][d], S["de"][d]
            if blocked is not None:
                blk_out[rows] = blocked[d]
            sta_out[rows] = (stall & ~conv)[d] & ~blk_out[rows]
            keep = (~done).nonzero()[:, 0]
            idx = idx[keep]
            S = {k: v[keep] for k, v in S.items()}
            C = {k: None if v is None else v[keep] for k, v in C.items()}
            if idx.numel() == 0:
                break
    if idx.numel():  # iteration limit: keep the lowest-error iterate, not converged
        q_out[idx], it_out[idx], step_out[idx], de_out[idx] = S["q"], S["it"], S["step"], S["de"]


def _compiled(fused, q0, target, direction, q_ref, tol, max_iter, damping, length, residual_tol, stall_rtol, window,
              window_rtol, lam, max_step, max_correction, stop_at_bound) -> DampedResult:
    """:func:`damped_least_squares` on the CPU in float64 (6-DOF): :mod:`.fused_damped`'s compiled pass, the same
    iteration row by row (the torch form above pays ~2 ms of dispatch an iteration, whatever the row count)."""
    from .bounds import per_joint_bound
    from .fused_damped import solve_damped

    n = q0.shape[1]
    ref = q0 if q_ref is None else q_ref
    o = solve_damped(fused, q0, target, direction, ref, tol=tol, max_iter=max_iter, damping=damping, length=length,
                     residual_tol=residual_tol, stall_rtol=stall_rtol, window=window, window_rtol=window_rtol, lam=lam,
                     max_step=per_joint_bound(max_step, n, torch.float64, "cpu", "max_step"),
                     max_correction=per_joint_bound(max_correction, n, torch.float64, "cpu", "max_correction"),
                     stop_at_bound=stop_at_bound)
    res = weighted(o["pose_error"], length).norm(dim=-1)
    return DampedResult(o["q"], o["converged"], o["iterations"], o["pose_error"], res, o["step"], o["blocked"],
                        o["stationary"])
