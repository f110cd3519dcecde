"""Paper II: high-order joint-dependent errors of a serial robot, identified and compensated.

======================================================  ===========================================================
Paper II                                                torchcal
======================================================  ===========================================================
error sources, Table 1, (4)-(14)                        :class:`TruthRobot` (sim/truth.py: a simulated robot)
Chebyshev series on the joint command (21)-(24)         :func:`chebyshev`, :func:`normalize` (core/basis.py)
E_i(q_i, s_i) (19)-(20), backlash (13)-(14)             :class:`JointErrors` (error_models/joint.py)
base frame error (26), tool vectors (27)                :class:`FrameCorrection` (error_models/frame.py)
measurement model (25)                                  :class:`RobotModel` (models/robot.py)
closed-form Jacobians (34)-(45)                         models/jacobian.py, ``RobotModel.point_jacobians``
maximum likelihood (28)-(33), Σ_v, σ_m                  :func:`fit`, :class:`NoiseModel`, :class:`Prior`
order selection (5.5, Figure 11)                        :func:`select_orders` (identify/order.py)
residual statistics, Gamma 99 % (Figure 13)             :func:`residual_stats` (analysis/stats.py)
joint variances (53)-(54), ISO 9283 (5.3)               :func:`joint_variances`, :func:`iso9283_repeatability`
compensation (46)-(52)                                  :func:`compensate` -> :class:`CompensationResult`
Cartesian targets through the calibrated model          :func:`compensate_targets` (compensate/targets.py)
the whole run, Tables 6-7 (config -> run directory)     :func:`run_fit` (app/fit.py)
======================================================  ===========================================================

The bundled FANUC LR Mate 200iC is ``urdf/fanuc_lrmate200i.urdf`` + ``.yaml`` (its joint map: θ3 = q2 + q3,
the errors on the command, (24)); the experiment that reproduces Tables 6-7 and Figures 11-16 is
``experiments/paper2_fanuc/run.py``.
"""

from ..analysis.repeatability import iso9283_repeatability, joint_variances
from ..analysis.stats import residual_stats
from ..app.fit import run_fit
from ..compensate import CompensationResult, compensate
from ..compensate.targets import compensate_targets
from ..core.basis import chebyshev, normalize
from ..error_models.frame import FrameCorrection
from ..error_models.joint import JointErrors
from ..identify import NoiseModel, Prior, fit
from ..identify.order import select_orders
from ..models.robot import RobotModel
from ..sim.truth import TruthRobot

__all__ = [
    "CompensationResult",
    "FrameCorrection",
    "JointErrors",
    "NoiseModel",
    "Prior",
    "RobotModel",
    "TruthRobot",
    "chebyshev",
    "compensate",
    "compensate_targets",
    "fit",
    "iso9283_repeatability",
    "joint_variances",
    "normalize",
    "residual_stats",
    "run_fit",
    "select_orders",
]
