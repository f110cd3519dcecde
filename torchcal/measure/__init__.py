"""Measurement models (instruments): prediction -> residual of any dimension d, per-row whitening.

Paper II: :class:`PointTargets` (tool points, d = 3). Paper III: the sensor
rig (:class:`SensorRig`, tracker -> robot -> sensor mount, gravity), the
SmartTRACK sensor (:class:`STSInstrument`, position + yaw, roll, level
angles, d = 6) and a generic 6-DOF probe (:class:`PoseInstrument`, position +
rotation vector, d = 6).
"""

from .base import Instrument, row_jacobians
from .points import PointTargets
from .pose import (
    PoseInstrument,
    RotationError,
    euler_from_rotation,
    rotation_from_euler,
)
from .sts import SensorRangeError, STSInstrument, STSSelection, sts_angles
from .tracker import TrackerNoise, tracker_covariance
from .triangle import triangle_frame
from .weights import CovarianceWeight, IsotropicWeight

__all__ = [
    "CovarianceWeight",
    "Instrument",
    "IsotropicWeight",
    "PointTargets",
    "PoseInstrument",
    "RotationError",
    "STSInstrument",
    "STSSelection",
    "SensorRangeError",
    "TrackerNoise",
    "euler_from_rotation",
    "rotation_from_euler",
    "row_jacobians",
    "sts_angles",
    "tracker_covariance",
    "triangle_frame",
]
