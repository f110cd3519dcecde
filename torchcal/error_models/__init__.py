"""Error modules of the calibrated model: joint errors (19)-(24), base/tool frames (26)-(27), gravity compliance,
fine-grained joint-angle tables."""

from .axis_perturbation import AxisPerturbation
from .compliance import GravityCompliance, Inertials, arm_angle_functions, gravity_torques, read_inertials
from .fine import FineJointErrors, SmoothnessPenalty, build_fine, hat_weights
from .frame import FrameCorrection, ToolSet
from .joint import JointErrors, joint_error_twists

__all__ = [
    "AxisPerturbation",
    "FineJointErrors",
    "FrameCorrection",
    "GravityCompliance",
    "Inertials",
    "JointErrors",
    "SmoothnessPenalty",
    "ToolSet",
    "build_fine",
    "arm_angle_functions",
    "gravity_torques",
    "hat_weights",
    "joint_error_twists",
    "read_inertials",
]
