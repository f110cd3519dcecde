"""Compensation of the modeled errors, Paper II (46)-(52).

``compensate(model, q_nom, direction)`` returns commands q_new with
``model.flange(q_new, direction, base=False) @ G == model.nominal_flange(q_nom)``
(G: the identified tool set's rigid motion, :mod:`.toolset`, the identity where the tools are nominal;
``compensation_goal`` gives the right side times G^-1) for many poses at once: the paper's fixed-Jacobian iteration on a fast
flange-only kernel, damped least squares for the rows that do not contract.
Every command stays within ``max_correction`` (default 30 deg) of its nominal
one and on its branch (configuration flags, :mod:`.branch`); rows that would need more, another
branch, or cannot be reached are flagged with a reason, not swung (``CompensationResult.status``,
``reasons()``; ``direction_outside`` when the model records its identification data's direction
coverage). ``free_tool_axis`` leaves the rotation about an axisymmetric tool's axis free, ``position_only`` every
rotation (one measured point per pose, :func:`observed_dof`) (:mod:`.axis`).
On the CPU the rows go through one compiled pass first (:mod:`.fused_targets`); Cartesian targets:
:mod:`.targets`, configuration flags: :mod:`.flags`.
"""

from .axis import ToolAxis
from .branch import branch_changed
from .damped import DampedResult, damped_least_squares
from .kernel import FlangeKernel, pose_error_soa
from .newton import (
    DEFAULT_BOUND,
    DEFAULT_CORRECTION_DEG,
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
from .toolset import compensation_goal, observed_dof, row_tool_points, tool_poses, tool_set_frame

__all__ = [
    "DEFAULT_BOUND",
    "DEFAULT_CORRECTION_DEG",
    "ToolAxis",
    "branch_changed",
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
    "compensation_goal",
    "compensation_tables",
    "damped_least_squares",
    "fixed_jacobian_iterations",
    "nominal_sigma_min",
    "observed_dof",
    "row_tool_points",
    "tool_poses",
    "tool_set_frame",
    "per_joint_bound",
    "pose_error_soa",
]
