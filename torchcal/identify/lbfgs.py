"""L-BFGS (strong Wolfe) on the implicit-loop MLE, gradients by autograd.

All unknowns (model parameters b and every row's joint errors v) are optimized
together, as (33) is written. Variables are whitened first (v by its standard
deviation, b by the inverse square root of the Gauss-Newton diagonal) because
the raw problem mixes radians, metres and 1e-5 rad joint errors, and L-BFGS is
not scale invariant. torch's default tolerances stop far too early for this
problem; ours are driven by the relative change of V.
"""

from __future__ import annotations

import time

import torch
from torch.func import functional_call

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
    data = problem.data
    x0 = layout.get().to(model.device)
    _, A, _ = problem.linearize(x0, problem.v_zero())
    diag = (A * A).sum((0, 1)) + problem.prior_precision
    scale_b = 1.0 / diag.clamp(min=1e-300).sqrt()
    scale_v = 1.0 / problem.w_v.sqrt() if problem.estimate_v else torch.zeros_like(problem.w_v)
    P = x0.numel()
    z = torch.zeros(P + data.q.numel(), dtype=torch.float64, device=model.device, requires_grad=True)
    opt = torch.optim.LBFGS([z], lr=1.0, max_iter=50, history_size=history_size, tolerance_grad=1e-300,
                            tolerance_change=1e-300, line_search_fn="strong_wolfe")
    nfev = 0

    def unpack(zz):
        return x0 + scale_b * zz[:P], scale_v * zz[P:].reshape(data.q.shape)

    def objective(zz):
        x, v = unpack(zz)
        p = functional_call(model, layout.as_dict(x), (data.q, data.tool, problem.direction, v))
        f = (p - data.xyz) * problem.inv_sigma_m
        return problem.cost_from(f, x, v)

    def closure():
        nonlocal nfev
        opt.zero_grad()
        loss = objective(z)
        loss.backward()
        nfev += 1
        return loss

    history = [float(objective(z.detach()))]
    success, message, it = False, "maximum number of iterations reached", 0
    while it < max_iter:
        opt.step(closure)
        it = opt.state[opt._params[0]]["n_iter"]
        cost = float(objective(z.detach()))
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
    zz = z.detach().clone().requires_grad_(True)
    g, = torch.autograd.grad(objective(zz), zz)
    grad = torch.cat([g[:P] / scale_b, g[P:] / scale_v.reshape(-1).clamp(min=1e-300)])
    return FitResult(
        x=x.clone(), v=v.clone(), success=success, message=message, nit=int(it), nfev=nfev, fun=history[-1],
        grad_norm=float(grad.norm()), time=time.perf_counter() - t0, method="lbfgs", history=history,
        names=layout.names(),
    )
