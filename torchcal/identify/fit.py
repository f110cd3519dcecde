"""One entry point for identification: build the MLE problem, fix the gauge, run a solver."""

from __future__ import annotations

from ..measurements import Measurements
from .gauge import fix_gauge
from .lbfgs import lbfgs
from .lm import levenberg_marquardt
from .problem import CalibrationProblem, NoiseModel, Prior
from .result import FitResult

SOLVERS = {"lm": levenberg_marquardt, "lbfgs": lbfgs}


def fit(
    model,
    data: Measurements,
    noise: NoiseModel | None = None,
    prior: Prior | None = Prior(),
    method: str = "lm",
    fixed=(),
    gauge: bool = True,
    **solver_options,
) -> FitResult:
    """Identify ``model``'s error parameters from ``data`` by maximum likelihood (Paper II (33)).

    model: a :class:`torchcal.RobotModel`, updated in place, starting from its
    current values; noise: tracker sigma and joint variances (default: Paper
    II's); prior: Gaussian prior on the parameters (None for none); method:
    'lm' (Levenberg-Marquardt with the joint errors eliminated per row, the
    default: converges in tens of iterations) or 'lbfgs' (autograd + L-BFGS,
    strong Wolfe, needs thousands); fixed: parameter groups held at their
    value (e.g. 'tools', 'base'); gauge: pin exactly redundant parameters first.
    """
    if method not in SOLVERS:
        raise ValueError(f"unknown solver '{method}', choose from {sorted(SOLVERS)}")
    problem = CalibrationProblem(model, data, noise or NoiseModel.paper2(), prior, fixed)
    pinned = fix_gauge(problem) if gauge else []
    result = SOLVERS[method](problem, **solver_options)
    result.pinned = pinned
    return result
