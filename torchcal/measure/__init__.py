"""Measurement models (instruments): prediction -> residual of any dimension d, per-row whitening."""

from .base import Instrument, row_jacobians
from .points import PointTargets
from .weights import CovarianceWeight, IsotropicWeight

__all__ = ["CovarianceWeight", "Instrument", "IsotropicWeight", "PointTargets", "row_jacobians"]
