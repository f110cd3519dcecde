"""The nominal machine: URDF parsing and validation, joint maps, functional FK and Jacobians.

No error terms live here; see :mod:`torchcal.error_models`.
"""

from .chain import Chain
from .fk import chain_fk, chain_frames, geometric_jacobian, joint_motion
from .joint_map import JointMap
from .robot import Repeatability, Robot, bundled_robots, load_robot, urdf_dir
from .urdf import URDFError, load_urdf, validate_urdf

__all__ = [
    "Chain",
    "JointMap",
    "Repeatability",
    "Robot",
    "URDFError",
    "bundled_robots",
    "chain_fk",
    "chain_frames",
    "geometric_jacobian",
    "joint_motion",
    "load_robot",
    "load_urdf",
    "urdf_dir",
    "validate_urdf",
]
