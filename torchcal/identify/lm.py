"""Levenberg-Marquardt for the implicit-loop MLE, joint errors eliminated per row.

Each measured row r has its own joint-error vector v_r that enters only that
row's residual, so the Gauss-Newton normal matrix is block-arrow shaped. We
eliminate every v_r in closed form (Schur complement, one small n x n Cholesky
per row, batched) and solve only for the model parameters b:

    S = H_bb - sum_r H_bv,r H_vv,r^-1 H_vb,r,   S db = -(g_b - sum_r H_bv,r H_vv,r^-1 g_v,r)
    dv_r = -H_vv,r^-1 (g_v,r + H_vb,r db)

Damping follows Nielsen's rule on Marquardt's diagonal scaling, so the solver
is invariant to the units of the parameters (rad vs m).
"""

from __future__ import annotations

import time

import torch

from .problem import CalibrationProblem
from .result import FitResult


def _schur_step(f, A, C, w_v, v, lam_b, dx, mu):
    """One damped Gauss-Newton step with v eliminated. Shapes: f (R,3), A (R,3,P), C (R,3,n)."""
    R, _, P = A.shape
    n = C.shape[-1]
    Af = A.reshape(R * 3, P)
    H_bb = Af.T @ Af + torch.diag(lam_b)
    g_b = Af.T @ f.reshape(-1) + lam_b * dx
    H_vv = C.transpose(1, 2) @ C + torch.diag_embed(w_v)
    g_v = (C.transpose(1, 2) @ f[..., None])[..., 0] + w_v * v
    H_vb = C.transpose(1, 2) @ A  # (R, n, P)
    H_bb_d = H_bb + mu * torch.diag(torch.diagonal(H_bb))
    H_vv_d = H_vv + mu * torch.diag_embed(torch.diagonal(H_vv, dim1=1, dim2=2))
    L = torch.linalg.cholesky(H_vv_d)
    Y = torch.linalg.solve_triangular(L, H_vb, upper=False)  # L^-1 H_vb
    z = torch.linalg.solve_triangular(L, g_v[..., None], upper=False)  # L^-1 g_v
    Yf = Y.reshape(R * n, P)
    S = H_bb_d - Yf.T @ Yf
    rhs = -(g_b - Yf.T @ z.reshape(-1))
    Ls, info = torch.linalg.cholesky_ex(S)
    if int(info) != 0:
        db = torch.linalg.lstsq(S, rhs[:, None]).solution[:, 0]
    else:
        db = torch.cholesky_solve(rhs[:, None], Ls)[:, 0]
    dv = -torch.cholesky_solve(g_v[..., None] + H_vb @ db[None, :, None], L)[..., 0]
    grad = torch.cat([g_b, g_v.reshape(-1)]) * 2.0
    return db, dv, grad


def levenberg_marquardt(
    problem: CalibrationProblem,
    max_iter: int = 100,
    ftol: float = 1e-8,
    xtol: float = 1e-10,
    mu0: float = 1e-4,
    callback=None,
) -> FitResult:
    """Minimize V of ``problem`` from the model's current values.

    ftol: stop when an accepted step lowers V by less than ftol * V and the
    Gauss-Newton model predicts no more; xtol: or when every parameter moves by
    less than xtol of its own scale. callback(it, cost) is called per iteration.
    """
    t0 = time.perf_counter()
    layout = problem.layout
    x = layout.get().to(problem.model.device)
    v = problem.v_zero()
    w_v = problem.w_v
    lam_b = problem.prior_precision
    f, A, C = problem.linearize(x, v)
    cost = float(problem.cost_from(f, x, v))
    history = [cost]
    mu, nu = mu0, 2.0
    nfev, message, success = 1, "maximum number of iterations reached", False
    grad = torch.zeros(1)
    it = 0
    for it in range(1, max_iter + 1):
        dx_prior = x - problem.prior_mean
        accepted = False
        for _ in range(30):
            db, dv, grad = _schur_step(f, A, C, w_v, v, lam_b, dx_prior, mu)
            x_new, v_new = x + db, v + dv
            lin = f + (A @ db[:, None])[..., 0] + (C @ dv[..., None])[..., 0]
            predicted = cost - float(problem.cost_from(lin, x_new, v_new))
            f_new = problem.residual(x_new, v_new)
            nfev += 1
            new_cost = float(problem.cost_from(f_new, x_new, v_new))
            actual = cost - new_cost
            if actual > 0 and predicted > 0:
                rho = actual / predicted
                mu *= max(1.0 / 3.0, 1.0 - (2.0 * rho - 1.0) ** 3)
                nu = 2.0
                accepted = True
                break
            if predicted <= 1e-14 * max(cost, 1.0):
                break  # the quadratic model sees nothing left to gain
            mu *= nu
            nu *= 2.0
        if not accepted:
            layout.set(x)
            success = True
            message = "converged: no step lowers the cost further"
            break
        step_small = bool((db.abs() <= xtol * (x.abs() + xtol)).all())
        x, v = x_new, v_new
        cost = new_cost
        history.append(cost)
        if callback is not None:
            callback(it, cost)
        f, A, C = problem.linearize(x, v)
        if actual <= ftol * cost and predicted <= ftol * cost * 10:
            success, message = True, "converged: relative cost reduction below ftol"
            break
        if step_small:
            success, message = True, "converged: parameter step below xtol"
            break
    layout.set(x)
    _, _, grad = _schur_step(f, A, C, w_v, v, lam_b, x - problem.prior_mean, 0.0)
    return FitResult(
        x=x.detach().clone(), v=v.detach().clone(), success=success, message=message, nit=it, nfev=nfev,
        fun=cost, grad_norm=float(grad.norm()), time=time.perf_counter() - t0, method="lm",
        history=history, names=layout.names(),
    )
