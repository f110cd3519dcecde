"""Levenberg-Marquardt for the implicit-loop MLE, joint errors eliminated per row.

Each measured row r has its own joint-error vector v_r that enters only that
row's residual, so the Gauss-Newton normal matrix is block-arrow shaped. We
eliminate every v_r in closed form (Schur complement, one small n x n Cholesky
per row, batched) and solve only for the model parameters b:

    S = H_bb - sum_r H_bv,r H_vv,r^-1 H_vb,r,   S db = -(g_b - sum_r H_bv,r H_vv,r^-1 g_v,r)
    dv_r = -H_vv,r^-1 (g_v,r + H_vb,r db)

for any residual dimension d per row (S is formed as sum_r A_r^T (I_d - C_r H_vv,r^-1 C_r^T) A_r,
one P x Rd product). Parameter-only blocks add J^T J and J^T r to the b equations;
rows with frozen joint errors (online identification) keep dv_r = 0.

Damping follows Nielsen's rule on Marquardt's diagonal scaling, so the solver
is invariant to the units of the parameters (rad vs m).
"""

from __future__ import annotations

import time

import torch

from .blocks import block_normal_equations
from .problem import CalibrationProblem
from .result import FitResult


def _schur_step(f, A, C, w_v, v, lam_b, dx, mu, H_blk=None, g_blk=None, v_free=None, rows_information=False):
    """One damped Gauss-Newton step with v eliminated. Shapes: f (R,d), A (R,d,P), C (R,d,n), any d.

    H_blk (P, P), g_blk (P,): parameter-only blocks' J^T J and J^T r; v_free:
    (R,) bool, rows whose joint errors move (others get dv = 0).
    -> db (P,), dv (R, n), gradient of V w.r.t. (b, v) (P + R n,); with rows_information also the rows'
    own quadratic in db with v eliminated, (H (P, P), g (P,)): with mu = 0 and every v free, exactly
    :func:`torchcal.identify.online.marginal_information` of (f, A, C, w_v, v), from the same factorization.
    """
    factor = _schur_factor(A, C, w_v, lam_b, mu, H_blk)
    return _schur_solve(factor, f, v, lam_b, dx, g_blk, v_free, rows_information)


def _schur_factor(A, C, w_v, lam_b, mu, H_blk=None):
    """What a step's normal equations need of the Jacobians alone (A (R,d,P), C (R,d,n)): the rows' joint errors
    eliminated and the reduced system factored. A chord iteration (the same Jacobians, new residuals) reuses it
    with :func:`_schur_solve`. -> an opaque tuple."""
    R, d, P = A.shape
    n = C.shape[-1]
    Af = A.reshape(R * d, P)
    diag_bb = (A * A).sum((0, 1)) + lam_b  # diagonal of H_bb (for Marquardt's scaling)
    if H_blk is not None:
        diag_bb = diag_bb + torch.diagonal(H_blk)
    Ct = C.transpose(1, 2)  # (R, n, d)
    H_vv = Ct @ C + torch.diag_embed(w_v)
    H_vv_d = H_vv + mu * torch.diag_embed(torch.diagonal(H_vv, dim1=1, dim2=2))
    L = torch.linalg.cholesky(H_vv_d)
    # L^-1 explicitly (n x n per row): batched triangular solves with P right-hand sides are slow on the CPU
    eye = torch.eye(n, dtype=A.dtype, device=A.device).expand(R, n, n)
    Li = torch.linalg.solve_triangular(L, eye, upper=False)
    W = Li @ Ct  # (R, n, d): Y = L^-1 H_vb = W A
    # S = sum_r A_r^T (I - W_r^T W_r) A_r + damped diagonal: one (P x Rd) @ (Rd x P) product
    M = torch.eye(d, dtype=A.dtype, device=A.device) - W.transpose(1, 2) @ W  # (R, d, d)
    S_rows = Af.T @ (M @ A).reshape(R * d, P)
    S = S_rows if H_blk is None else S_rows + H_blk
    S = 0.5 * (S + S.T) + torch.diag(lam_b + mu * diag_bb)
    Ls, info = torch.linalg.cholesky_ex(S)
    return A, Af, Ct, w_v, Li, W, S_rows, S, (Ls if int(info) == 0 else None)


def _schur_solve(factor, f, v, lam_b, dx, g_blk=None, v_free=None, rows_information=False):
    """The step of a factored system (:func:`_schur_factor`) for residuals f (R, d) at joint errors v (R, n),
    dx = x - prior mean (P,) and the blocks' J^T r g_blk; returns as :func:`_schur_step`."""
    A, Af, Ct, w_v, Li, W, S_rows, S, Ls = factor
    g_b = Af.T @ f.reshape(-1) + lam_b * dx
    if g_blk is not None:
        g_b = g_b + g_blk
    g_v = (Ct @ f[..., None])[..., 0] + w_v * v
    if v_free is not None:
        g_v = g_v * v_free[:, None].to(g_v)
    z = Li @ g_v[..., None]  # L^-1 g_v (R, n, 1)
    elim = Af.T @ (W.transpose(1, 2) @ z).reshape(-1)
    rhs = -(g_b - elim)
    if Ls is None:
        db = torch.linalg.lstsq(S, rhs[:, None]).solution[:, 0]
    else:
        db = torch.cholesky_solve(rhs[:, None], Ls)[:, 0]
    dv = -(Li.transpose(1, 2) @ (z + W @ (A @ db[:, None])))[..., 0]
    grad = torch.cat([g_b, g_v.reshape(-1)]) * 2.0
    if rows_information:
        return db, dv, grad, (0.5 * (S_rows + S_rows.T), Af.T @ f.reshape(-1) - elim)
    return db, dv, grad


def _blocks(problem: CalibrationProblem, x: torch.Tensor):
    """Parameter-only blocks at x: J^T J, J^T r, |r|^2 (None, None, None without blocks)."""
    if not problem.blocks:
        return None, None, None
    return block_normal_equations(problem.blocks, x, problem.layout)


MU0 = 1e-8
"""Levenberg-Marquardt's first damping, relative to the diagonal (Marquardt's scaling). The problem is close to
linear and the prior keeps it positive definite, so undamped Gauss-Newton steps are what it wants; 1e-4 (the
textbook start) damped the near-redundant combinations the prior holds, and a FANUC order-6 fit took 25 iterations
instead of 7 to reach the same optimum (a rejected first step raises the damping at once)."""

GEODESIC_H = 0.1
"""The finite-difference step (a fraction of the Gauss-Newton step) for the residual's second directional
derivative in :func:`second_directional` (Transtrum & Sethna 2012 use 0.1)."""

GEODESIC_ALPHA = 0.75
"""Geodesic acceleration is kept only while 2 |a| <= alpha |delta| in Marquardt's scaling (Transtrum & Sethna):
beyond it the second-order term is no correction but a sign that the step left the region the model describes."""


def second_directional(f: torch.Tensor, f_h: torch.Tensor, lin: torch.Tensor, h: float = GEODESIC_H) -> torch.Tensor:
    """The residual's second directional derivative along a Gauss-Newton step, by one extra residual
    (Transtrum & Sethna, "Improvements to the Levenberg-Marquardt algorithm for nonlinear least-squares
    minimization", 2012): r_vv ~ (2 / h) ((r(x + h delta) - r(x)) / h - J delta).

    f: r(x), f_h: r(x + h delta), lin: r(x) + J delta (the step's linearized residual), any equal shapes,
    e.g. (m, R, d). -> r_vv, the same shape. The acceleration a solves the step's damped system with r_vv for
    the residual; the step taken is delta + a / 2.
    """
    return (2.0 / h) * ((f_h - f) / h - (lin - f))


def acceleration_kept(a: torch.Tensor, db: torch.Tensor, scale: torch.Tensor, alpha: float = GEODESIC_ALPHA) -> torch.Tensor:
    """(m,) bool: whether each model's acceleration a (m, P) is small enough beside its step db (m, P) to be taken,
    2 |a| <= alpha |db| with both measured in ``scale`` (m, P), Marquardt's diagonal: unit-free."""
    return 2.0 * (a * scale).norm(dim=-1) <= alpha * (db * scale).norm(dim=-1)


def levenberg_marquardt(
    problem: CalibrationProblem,
    max_iter: int = 100,
    ftol: float = 1e-8,
    xtol: float = 1e-10,
    mu0: float = MU0,
    callback=None,
) -> FitResult:
    """Minimize V of ``problem`` from the model's current values.

    mu0: the first damping (:data:`MU0`). ftol: stop when an accepted step lowers V by less than ftol * V and the
    Gauss-Newton model predicts no more; xtol: or when every parameter moves by
    less than xtol of its own scale. callback(it, cost) is called per iteration.
    """
    t0 = time.perf_counter()
    layout = problem.layout
    x = layout.get().to(problem.model.device)
    v = problem.v_zero()
    w_v = problem.w_v
    lam_b = problem.prior_precision
    v_free = problem.v_free
    f, A, C = problem.linearize(x, v)
    H_blk, g_blk, c_blk = _blocks(problem, x)
    cost = float(problem.cost_from(f, x, v, c_blk))
    history = [cost]
    mu, nu = mu0, 2.0
    nfev, message, success = 1, "maximum number of iterations reached", False
    grad = torch.zeros(1)
    it = 0
    # Near the solution nearly every step is accepted at once: the trial point is then linearized directly
    # (its Jacobians are the next iteration's), one kinematics pass per iteration instead of a residual and a
    # linearization. After a rejection, trials are plain residuals again until a step passes at once.
    trial_linearize = True
    for it in range(1, max_iter + 1):
        dx_prior = x - problem.prior_mean
        accepted = False
        linearized = None
        for attempt in range(30):
            db, dv, grad = _schur_step(f, A, C, w_v, v, lam_b, dx_prior, mu, H_blk, g_blk, v_free)
            x_new, v_new = x + db, v + dv
            lin = f + (A @ db[:, None])[..., 0] + (C @ dv[..., None])[..., 0]
            # blocks' Gauss-Newton model: |r + J db|^2 = c + 2 g^T db + db^T H db
            lin_blk = None if H_blk is None else c_blk + 2 * (g_blk @ db) + db @ (H_blk @ db)
            predicted = cost - float(problem.cost_from(lin, x_new, v_new, lin_blk))
            if attempt == 0 and it > 1 and 0 <= predicted <= 0.1 * ftol * cost:
                # the Gauss-Newton model at the current point sees less to gain than the stopping test
                # accepts: stop here rather than pay a kinematics pass to confirm it
                break
            if trial_linearize and attempt == 0:
                linearized = problem.linearize(x_new, v_new)
                f_new = linearized[0]
            else:
                linearized = None
                f_new = problem.residual(x_new, v_new)
            nfev += 1
            new_cost = float(problem.cost_from(f_new, x_new, v_new))
            actual = cost - new_cost
            if actual > 0 and predicted > 0:
                rho = actual / predicted
                mu *= max(1.0 / 3.0, 1.0 - (2.0 * rho - 1.0) ** 3)
                nu = 2.0
                accepted = True
                trial_linearize = attempt == 0
                break
            if predicted <= 1e-14 * max(cost, 1.0):
                break  # the quadratic model sees nothing left to gain
            mu *= nu
            nu *= 2.0
        if not accepted:
            layout.set(x)
            success = True
            message = ("converged: the predicted cost reduction is below ftol" if attempt == 0 else
                       "converged: no step lowers the cost further")
            break
        step_small = bool((db.abs() <= xtol * (x.abs() + xtol)).all())
        x, v = x_new, v_new
        cost = new_cost
        history.append(cost)
        if callback is not None:
            callback(it, cost)
        f, A, C = linearized if linearized is not None else problem.linearize(x, v)
        H_blk, g_blk, c_blk = _blocks(problem, x)
        if actual <= ftol * cost and predicted <= ftol * cost * 10:
            success, message = True, "converged: relative cost reduction below ftol"
            break
        if step_small:
            success, message = True, "converged: parameter step below xtol"
            break
    layout.set(x)
    _, _, grad = _schur_step(f, A, C, w_v, v, lam_b, x - problem.prior_mean, 0.0, H_blk, g_blk, v_free)
    return FitResult(
        x=x.detach().clone(), v=v.detach().clone(), success=success, message=message, nit=it, nfev=nfev,
        fun=cost, grad_norm=float(grad.norm()), time=time.perf_counter() - t0, method="lm",
        history=history, names=layout.names(),
    )
