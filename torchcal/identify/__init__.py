"""Identification (Paper II (28)-(33)): the MLE objective, gauge fixing, solvers and results."""

from .backlash import select_backlash_orders
from .blocks import GaussianPrior, ParamBlock
from .constrained import (AutoConstraintResult, ConstrainedFitResult, ConstraintError, SlopePenalty, SweepResult,
                          auto_constraint, constraint_sweep, fit_constrained, pick_knee)
from .fit import SOLVERS, fit, resolve_noise
from .gauge import dependent_columns, fix_gauge
from .layout import ParameterLayout, parameter_groups
from .lbfgs import lbfgs
from .lm import levenberg_marquardt
from .online import InformationBlock, OnlineCalibration, OnlineStep, batch_refit, marginal_information
from .order import OrderSelection, held_out_errors, loo_residuals, paired_improvement, pose_folds, score_orders, select_orders
from .problem import PAPER2_JOINT_VAR_BWD, PAPER2_JOINT_VAR_FWD, CalibrationProblem, NoiseModel, Prior, raw_residual, row_errors
from .result import FitResult
from .slope import model_slopes, slope_points

__all__ = [
    "AutoConstraintResult",
    "ConstrainedFitResult",
    "ConstraintError",
    "SlopePenalty",
    "SweepResult",
    "auto_constraint",
    "constraint_sweep",
    "fit_constrained",
    "model_slopes",
    "pick_knee",
    "slope_points",
    "PAPER2_JOINT_VAR_BWD",
    "PAPER2_JOINT_VAR_FWD",
    "SOLVERS",
    "CalibrationProblem",
    "FitResult",
    "GaussianPrior",
    "InformationBlock",
    "NoiseModel",
    "OnlineCalibration",
    "OnlineStep",
    "OrderSelection",
    "ParamBlock",
    "ParameterLayout",
    "Prior",
    "batch_refit",
    "dependent_columns",
    "fit",
    "fix_gauge",
    "held_out_errors",
    "lbfgs",
    "levenberg_marquardt",
    "loo_residuals",
    "marginal_information",
    "paired_improvement",
    "parameter_groups",
    "pose_folds",
    "raw_residual",
    "resolve_noise",
    "row_errors",
    "score_orders",
    "select_backlash_orders",
    "select_orders",
]
