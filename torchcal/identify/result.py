"""Result objects of the solvers, in the manner of scipy.optimize.OptimizeResult."""

from __future__ import annotations

from dataclasses import dataclass, field

import torch


@dataclass
class FitResult:
    """Outcome of an identification.

    x: free parameters in layout order (SI); v: (R, n) identified joint
    positioning errors; success: converged by the solver's criteria; message:
    why it stopped; nit: iterations; nfev: objective evaluations; fun: final V;
    grad_norm: |dV/d(x, v)| at the end; time: seconds; method: 'lm' or 'lbfgs';
    history: V after each iteration; names: parameter names of x.
    """

    x: torch.Tensor
    v: torch.Tensor
    success: bool
    message: str
    nit: int
    nfev: int
    fun: float
    grad_norm: float
    time: float
    method: str
    history: list[float] = field(default_factory=list)
    names: list[str] = field(default_factory=list)
    pinned: list[str] = field(default_factory=list)

    def summary(self) -> dict:
        """JSON-ready scalars."""
        return {
            "method": self.method,
            "converged": bool(self.success),
            "message": self.message,
            "iterations": int(self.nit),
            "evaluations": int(self.nfev),
            "cost": float(self.fun),
            "grad_norm": float(self.grad_norm),
            "time_s": float(self.time),
            "parameters": int(self.x.numel()),
            "joint_errors": int(self.v.numel()),
            "pinned": len(self.pinned),
        }
