"""Paper I: interpolation and extrapolation of a machine tool's volumetric errors (five-axis XYZCB).

======================================================  ===========================================================
Paper I                                                 torchcal
======================================================  ===========================================================
axis perturbation model (2)-(7), f_ij Chebyshev series  :class:`AxisPerturbation` (error_models/axis_perturbation.py)
measurement model (8)-(10): tracker frame, tool lengths  :class:`MachineModel` (models/machine.py)
identification (11)-(12), implicit loop, Σ_v, Σ_ξ       :func:`fit` (identify/fit.py), :class:`NoiseModel`
tool-tip error slope h̄_i (13)-(30)                      :func:`max_slope` (identify/slope.py)
slope constraint (31) ‖h̄_i‖ ≤ c on the whole space      :func:`fit_constrained` (identify/constrained.py)
choosing c (3.4): sweep, knee                           :func:`auto_constraint` (identify/constrained.py)
BORDER, reverse k-NN counts (3.4, Tables 1-2)           :func:`border_points`, :func:`reverse_knn_counts`
compensation tables −f_ij                               :func:`compensation_tables` (compensate/tables.py)
tables for controllers (CSV, Siemens CEC, LinuxCNC)     :func:`export_tables` (export/controller.py)
the config stage (c: auto, BORDER axes)                 :func:`identify_constrained` (app/constraint.py)
simulated XYZCB machine with known truth                :class:`MachineTruth` (sim/machine_truth.py)
======================================================  ===========================================================

The five-axis machine itself is ``urdf/five_axis_xyzcb.urdf`` (Figure 9, (34)-(38)); the experiment that
reproduces Table 5 and Figure 14 is ``experiments/paper1_machine_tool/run.py``.
"""

from ..analysis.border import border_points, reverse_knn_counts
from ..app.constraint import identify_constrained
from ..compensate.tables import compensation_tables
from ..error_models.axis_perturbation import AxisPerturbation
from ..export.controller import export_tables
from ..identify import NoiseModel, fit
from ..identify.constrained import auto_constraint, fit_constrained
from ..identify.slope import max_slope
from ..models.machine import MachineModel
from ..sim.machine_truth import MachineTruth

__all__ = [
    "AxisPerturbation",
    "MachineModel",
    "MachineTruth",
    "NoiseModel",
    "auto_constraint",
    "border_points",
    "compensation_tables",
    "export_tables",
    "fit",
    "fit_constrained",
    "identify_constrained",
    "max_slope",
    "reverse_knn_counts",
]
