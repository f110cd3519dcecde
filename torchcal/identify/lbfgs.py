"""L-BFGS (strong Wolfe) on the implicit-loop MLE, gradients by autograd.

All unknowns (model parameters b and every row's joint errors v) are optimized
together, as (33) is written. L-BFGS is not invariant to scaling and the raw
problem mixes radians, metres and 1e-5 rad joint errors with parameters that
are strongly correlated, so the variables are preconditioned once at the start
with the block structure of the Gauss-Newton matrix: b through the Cholesky
factor of its Schur complement, each row's v through the Cholesky factor of
its own n x n block. torch's default tolerances stop far too early for this
problem; ours are driven by the relative change of V.
"""

from __future__ import annotations

import time

import torch

from .blocks import block_normal_equations
from .problem import CalibrationProblem
from .result import FitResult


def lbfgs(
    problem: CalibrationProblem,
    max_iter: int = 20000,
    ftol: float = 1e-8,
    max_time: float | None = None,
    history_size: int = 50,
    callback=None,
) -> FitResult:
    """Minimize V with torch.optim.LBFGS; same result type as the LM solver.

    Stops when V changes by less than ftol * V over 50 consecutive iterations,
    after max_iter iterations, or after max_time seconds.
    """
    t0 = time.perf_counter()
    layout = problem.layout
    model = problem.model
    x0 = layout.get().to(model.device)
    v_start = problem.v_zero()
    f, A, C = problem.linearize(x0, v_start)  # C is zero on rows whose v is not solved for
    R, d, P = A.shape
    n = C.shape[-1]
    free = problem.v_free[:, None, None].to(A)
    Ct = C.transpose(1, 2)
    H_vv = Ct @ C + torch.diag_embed(problem.w_v)
    L_v = torch.linalg.cholesky(H_vv)
    eye_n = torch.eye(n, dtype=A.dtype, device=A.device).expand(R, n, n)
    Li_v = torch.linalg.solve_triangular(L_v, eye_n, upper=False)  # (R, n, n) L_v^-1
    H_vb = Ct @ A
    Y = (Li_v @ H_vb).reshape(R * n, P)
    Af = A.reshape(R * d, P)
    H_blk = block_normal_equations(problem.blocks, x0, layout)[0] if problem.blocks else 0.0
    S = Af.T @ Af + torch.diag(problem.prior_precision) + H_blk - Y.T @ Y
    L_b = torch.linalg.cholesky(S + 1e-12 * torch.diag(torch.diagonal(S)))
    eye_b = torch.eye(P, dtype=S.dtype, device=S.device)
    M_b = torch.linalg.solve_triangular(L_b.T, eye_b, upper=True)  # x = x0 + L_b^-T z
    M_v = Li_v.transpose(1, 2) * free  # v = v_start + L_v^-T z_v - K dx on free rows; fixed rows stay
    # block-LDL change of variables: v follows b as in the Schur elimination
    K = (Li_v.transpose(1, 2) @ (Li_v @ H_vb)) * free  # (R, n, P) = H_vv^-1 H_vb
    z = torch.zeros(P + R * n, dtype=torch.float64, device=model.device, requires_grad=True)
    opt = torch.optim.LBFGS([z], lr=1.0, max_iter=50, history_size=history_size, tolerance_grad=1e-300,
                            tolerance_change=1e-300, line_search_fn="strong_wolfe")
    nfev = 0

    def unpack(zz):
        dx = M_b @ zz[:P]
        v = v_start + (M_v @ zz[P:].reshape(R, n, 1))[..., 0] - K @ dx
        return x0 + dx, v

    def objective(zz):
        x, v = unpack(zz)
        return problem.cost_from(problem.whitened_residual(x, v), x, v)

    def closure():
        nonlocal nfev
        opt.zero_grad()
        loss = objective(z)
        loss.backward()
        nfev += 1
        return loss

    def value() -> float:
        with torch.no_grad():  # the model's own parameters require grad too: a value, not a graph
            return float(objective(z.detach()))

    history = [value()]
    success, message, it = False, "maximum number of iterations reached", 0
    while it < max_iter:
        opt.step(closure)
        it = opt.state[opt._params[0]]["n_iter"]
        cost = value()
        history.append(cost)
        if callback is not None:
            callback(it, cost)
        if abs(history[-2] - cost) <= ftol * cost:
            success, message = True, "converged: relative cost change over 50 iterations below ftol"
            break
        if max_time is not None and time.perf_counter() - t0 > max_time:
            message = f"stopped at the time limit ({max_time:g} s)"
            break
    x, v = unpack(z.detach())
    layout.set(x)
    # gradient in the original variables (x, v), for a report comparable with LM's
    xg = x.clone().requires_grad_(True)
    vg = v.clone().requires_grad_(True)
    gx, gvv = torch.autograd.grad(problem.cost_from(problem.whitened_residual(xg, vg), xg, vg), (xg, vg))
    gvv = gvv * problem.v_free[:, None].to(gvv)
    grad = torch.cat([gx, gvv.reshape(-1)])
    return FitResult(
        x=x.clone(), v=v.clone(), success=success, message=message, nit=int(it), nfev=nfev, fun=history[-1],
        grad_norm=float(grad.norm()), time=time.perf_counter() - t0, method="lbfgs", history=history,
        names=layout.names(),
    )
