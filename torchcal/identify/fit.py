"""One entry point for identification: build the MLE problem, fix the gauge, run a solver."""

from __future__ import annotations

import contextvars
import functools
import logging
from contextlib import contextmanager

import torch

from ..core.measurements import Measurements
from ..core.threads import threads_for_work
from .gauge import fix_gauge
from .layout import copy_overlap
from .lbfgs import lbfgs
from .lm import levenberg_marquardt
from .problem import CalibrationProblem, NoiseModel, Prior
from .result import FitResult

SOLVERS = {"lm": levenberg_marquardt, "lbfgs": lbfgs}

log = logging.getLogger("torchcal")


def problem_work(problem: CalibrationProblem) -> float:
    """Flops of one Gauss-Newton iteration (the Schur complement's R d x P^2 product): what threads follow."""
    return float(problem.rows * problem.dim * problem.layout.size ** 2)


@torch.no_grad()
def _warm_start(problem: CalibrationProblem, warm) -> None:
    """Free entries of the problem's model from ``warm``; pinned and fixed entries keep their values."""
    model = problem.model
    keep = {n: p.detach().clone() for n, p in model.named_parameters()}
    copy_overlap(warm, model)
    x = problem.layout.get()
    for n, p in model.named_parameters():
        p.copy_(keep[n])
    problem.layout.set(x)


def resolve_noise(model, noise: NoiseModel | None) -> NoiseModel:
    """``noise``, or the robot's own (:meth:`NoiseModel.from_robot`) when None, logging where it comes from."""
    if noise is not None:
        return noise
    robot = getattr(model, "robot", None)
    if robot is None:
        raise ValueError(f"{type(model).__name__} has no robot to take the joint repeatability from: pass noise=")
    noise = NoiseModel.from_robot(robot)
    log.info("joint repeatability of robot '%s' from %s; sigma_m = %.3g mm", robot.name, noise.source,
             noise.sigma_m * 1e3)
    return noise


FAR_FRAME_MM = 20.0
"""A start this far off the points (RMS, mm) is no calibration error: the frame or tools are not the model's
(as ``torchcal fit``'s implausible-residual warning, :data:`torchcal.app.fit.NOMINAL_IMPLAUSIBLE_MM`)."""


_FRAME = contextvars.ContextVar("torchcal_frame_check", default=None)


@contextmanager
def frame_check(quiet: bool = False):
    """Within this block :func:`fit` warns of a far measurement frame at most once (order selection and the
    slope constraint fit many times on one data set); ``quiet``: never (the caller, e.g. ``torchcal fit``'s
    pipeline, says it its own way). Nested blocks share the outer one's state."""
    outer = _FRAME.get()
    if outer is not None and not quiet:
        yield
        return
    token = _FRAME.set({"said": quiet})
    try:
        yield
    finally:
        _FRAME.reset(token)


def warns_once(fn):
    """Decorator: a function that fits many times on one data set warns of a far frame at most once a call."""
    @functools.wraps(fn)
    def inner(*args, **kwargs):
        with frame_check():
            return fn(*args, **kwargs)
    return inner


def _warn_far_frame(model, data: Measurements) -> bool:
    """Warn when the model starts metres off the points: an LM or L-BFGS fit from there runs its iterations out in
    the rotation of the frame (a user's 2 m tracker offset: 100 iterations, 122 mm left, no word otherwise)."""
    if not (hasattr(model, "robot") and hasattr(model, "points")) or len(data) == 0:
        return False
    with torch.no_grad():
        p = model.points(data.q, data.tool, data.direction if data.has_direction else None)
        d = (p - data.xyz.to(p)).norm(dim=-1)
        d = d[torch.isfinite(d)]
        rms = float(d.square().mean().sqrt()) * 1e3 if d.numel() else 0.0
    if rms > FAR_FRAME_MM:
        import warnings

        warnings.warn(
            f"torchcal.fit: before the fit the model misses the points of {data.source or 'the data'} by {rms:.1f} mm "
            f"RMS (> {FAR_FRAME_MM:g} mm): the measurement frame is probably not the model's (the tracker stood "
            "elsewhere) or the tools are wrong; torchcal.align(robot, data, tools=...) estimates the frame "
            "(.base_nominal, for RobotModel(..., base_nominal=...)), as `torchcal fit` does with "
            "measurement_frame: estimate", UserWarning, stacklevel=3)
        return True
    return False


def fit(
    model,
    data: Measurements,
    noise: NoiseModel | None = None,
    prior: Prior | None = Prior(),
    method: str = "lm",
    fixed=(),
    gauge: bool = True,
    instrument=None,
    blocks=(),
    fixed_rows=None,
    v0=None,
    warm=None,
    **solver_options,
) -> FitResult:
    """Identify ``model``'s error parameters from ``data`` by maximum likelihood (Paper II (33)).

    model: a :class:`torchcal.RobotModel`, updated in place, starting from its
    current values; noise: tracker sigma and joint variances (None: the
    robot's declared repeatability, :meth:`NoiseModel.from_robot`, its source
    logged on the 'torchcal' logger); prior: Gaussian prior on the parameters
    (None for none); method: 'lm' (Levenberg-Marquardt with the joint errors
    eliminated per row, the default: converges in tens of iterations) or
    'lbfgs' (autograd + L-BFGS, strong Wolfe, needs thousands); fixed:
    parameter groups held at their value (e.g. 'tools', 'base'); gauge: pin
    exactly redundant parameters first; instrument: the measurement model
    (:mod:`torchcal.measure`; default point targets on ``data.xyz``); blocks:
    parameter-only residual blocks (:mod:`torchcal.identify.blocks`, e.g.
    :class:`GaussianPrior`); fixed_rows: (R,) bool, rows whose joint errors
    are held at ``v0`` (R, n) (online identification, Paper III); warm: a
    model of the same kind (other orders allowed) whose values start the free
    entries (:func:`~torchcal.identify.layout.copy_overlap`), the gauge fixed
    first at ``model``'s own values, as in a cold fit.
    When the data carry approach directions, ``model.coverage`` records them
    (:class:`torchcal.core.coverage.DirectionCoverage`).

    Example:
        >>> import torch, torchcal
        >>> robot = torchcal.load_robot("fanuc_lrmate200i")
        >>> tools = torch.tensor([[0.033, 0.058, 0.161], [0.057, -0.034, 0.161], [-0.034, -0.057, 0.161]], dtype=torch.float64)
        >>> truth = torchcal.TruthRobot.fanuc_paper2(robot, tools, 0)
        >>> q = torchcal.sim.quasi_random_commands(robot.joint_map.limits, 40, 0)
        >>> data = torchcal.simulate(truth, q, [0, 1, 2], torchcal.NoiseModel.from_robot(robot), 0)
        >>> model = torchcal.RobotModel(robot, tools, orders=1, backlash=True)
        >>> result = torchcal.fit(model, data)  # noise: the robot's own repeatability (Table 5 for the FANUC)
        >>> result.success, result.x.numel() > 50
        (True, True)
    """
    if method not in SOLVERS:
        raise ValueError(f"unknown solver '{method}', choose from {sorted(SOLVERS)}")
    dtype = getattr(model, "dtype", torch.float64)
    if dtype != torch.float64:  # said here: the commands' dtype message below would name a q the user never gave
        from ..core.exceptions import InputError

        raise InputError(f"fit: the model is {dtype}; identification runs in float64 (model.to(torch.float64)); a "
                         "fitted model may be moved to float32 afterwards for prediction and compensation")
    state = _FRAME.get()
    if instrument is None and not (state is not None and state["said"]):
        if _warn_far_frame(model, data) and state is not None:
            state["said"] = True
    problem = CalibrationProblem(model, data, resolve_noise(model, noise), prior, fixed, instrument, blocks, fixed_rows, v0)
    with threads_for_work(problem_work(problem)):
        pinned = fix_gauge(problem) if gauge else []
        if warm is not None:
            _warm_start(problem, warm)
        result = SOLVERS[method](problem, **solver_options)
    result.pinned = pinned
    if data.has_direction and hasattr(model, "command_limits"):
        from ..core.coverage import DirectionCoverage

        model.coverage = DirectionCoverage.from_data(data.q, data.direction, model.command_limits)
    if hasattr(model, "record_data_span"):
        model.data_span = None  # this fit's data alone (a refit of a loaded model starts over)
        model.record_data_span(data.q)
    if hasattr(model, "measured_tools"):  # what compensation may restore (compensate.observed_dof)
        model.measured_tools = sorted({int(t) for t in data.tool.tolist()})
    return result
