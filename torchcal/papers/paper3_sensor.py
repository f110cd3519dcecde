"""Paper III: a 6-DOF sensor measured by a laser tracker, and online (adaptive) identification.

======================================================  ===========================================================
Paper III                                               torchcal
======================================================  ===========================================================
tracker covariance (10), (34)-(37), (47), (49)-(61)     :class:`TrackerNoise`, :func:`tracker_covariance`
measurement loop tracker -> robot -> sensor (13)-(16)   :class:`SensorRig` (models/sensor_rig.py)
gravity vector of the level (27)                        :func:`gravity_from_xy`, :func:`check_gravity`
STS angles (17)-(27), residual (28)-(30), noise (46)    :class:`STSInstrument`, :func:`sts_angles`
a generic 6-DOF probe (position + rotation)             :class:`PoseInstrument` (measure/pose.py)
three-target (AT) orientation (48)                      :func:`triangle_frame` (measure/triangle.py)
orientation repeatability (41)-(45)                     :func:`orientation_repeatability`
prior (31), online adaptive identification (33)         :class:`OnlineCalibration` (identify/online.py)
tracker frame + sensor mount from the data              :func:`hand_eye` (identify/hand_eye.py)
sensor runs of ``torchcal fit``                         :func:`run_sensor_fit` (app/sensor.py)
``torchcal update`` (a run updated with new data)       :func:`run_update` (app/update.py)
simulated FANUC + STS + tracker with known truth        :class:`SensorTruth` (sim/sensor_truth.py)
======================================================  ===========================================================

The experiment that reproduces the paper's figures is ``experiments/paper3_sts/run.py``; real 6-DOF data
(UR10, Leica T-Mac) go through ``experiments/ur10_tmac/run.py``.
"""

from ..analysis.orientation import orientation_repeatability
from ..app.sensor import run_sensor_fit
from ..app.update import run_update
from ..identify.hand_eye import hand_eye
from ..identify.online import OnlineCalibration
from ..measure import PoseInstrument, STSInstrument, TrackerNoise, sts_angles, tracker_covariance, triangle_frame
from ..measure.gravity import check_gravity, gravity_from_xy
from ..models.sensor_rig import SensorRig
from ..sim.sensor_truth import SensorTruth

__all__ = [
    "OnlineCalibration",
    "PoseInstrument",
    "STSInstrument",
    "SensorRig",
    "SensorTruth",
    "TrackerNoise",
    "check_gravity",
    "gravity_from_xy",
    "hand_eye",
    "orientation_repeatability",
    "run_sensor_fit",
    "run_update",
    "sts_angles",
    "tracker_covariance",
    "triangle_frame",
]
