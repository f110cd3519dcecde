"""Compensation of the modeled errors, Paper II (46)-(52).

``compensate(model, q_nom, direction)`` returns commands q_new with
``model.flange(q_new, direction, base=False) == model.nominal_flange(q_nom)``
for many poses at once: the paper's fixed-Jacobian iteration on a fast
flange-only kernel, damped least squares for the rows that do not contract.
Every command stays within ``max_correction`` (default 5 deg) of its nominal
one; rows that would need more (next to singularities) are flagged, not
swung (``CompensationResult.correction``; ``direction_outside`` when the
model records its identification data's direction coverage).
"""

from .damped import DampedResult, damped_least_squares
from .kernel import FlangeKernel, pose_error_soa
from .newton import (
    DEFAULT_BOUND,
    CompensationResult,
    compensate,
    fixed_jacobian_iterations,
    nominal_sigma_min,
    per_joint_bound,
)
from .tables import (
    CompensationTable,
    TableAxisError,
    TableError,
    TableRangeError,
    TableSizeError,
    TableSlopeWarning,
    apply_tables,
    compensation_tables,
)

__all__ = [
    "DEFAULT_BOUND",
    "CompensationResult",
    "CompensationTable",
    "DampedResult",
    "FlangeKernel",
    "TableAxisError",
    "TableError",
    "TableRangeError",
    "TableSizeError",
    "TableSlopeWarning",
    "apply_tables",
    "compensate",
    "compensation_tables",
    "damped_least_squares",
    "fixed_jacobian_iterations",
    "nominal_sigma_min",
    "per_joint_bound",
    "pose_error_soa",
]
