"""Error modules of the calibrated model: joint errors (19)-(24), base/tool frames (26)-(27), gravity compliance."""

from .compliance import GravityCompliance, Inertials, arm_angle_functions, gravity_torques, read_inertials
from .frame import FrameCorrection, ToolSet
from .joint import JointErrors, joint_error_twists

__all__ = [
    "FrameCorrection",
    "GravityCompliance",
    "Inertials",
    "JointErrors",
    "ToolSet",
    "arm_angle_functions",
    "gravity_torques",
    "joint_error_twists",
    "read_inertials",
]
