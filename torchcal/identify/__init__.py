"""Identification (Paper II (28)-(33)): the MLE objective, gauge fixing, solvers and results."""

from .fit import SOLVERS, fit
from .gauge import dependent_columns, fix_gauge
from .layout import ParameterLayout
from .lbfgs import lbfgs
from .lm import levenberg_marquardt
from .order import OrderSelection, held_out_errors, loo_residuals, paired_improvement, pose_folds, score_orders, select_orders
from .problem import PAPER2_JOINT_VAR_BWD, PAPER2_JOINT_VAR_FWD, CalibrationProblem, NoiseModel, Prior
from .result import FitResult

__all__ = [
    "PAPER2_JOINT_VAR_BWD",
    "PAPER2_JOINT_VAR_FWD",
    "SOLVERS",
    "CalibrationProblem",
    "FitResult",
    "NoiseModel",
    "OrderSelection",
    "ParameterLayout",
    "Prior",
    "dependent_columns",
    "fit",
    "fix_gauge",
    "held_out_errors",
    "lbfgs",
    "levenberg_marquardt",
    "loo_residuals",
    "paired_improvement",
    "pose_folds",
    "score_orders",
    "select_orders",
]
