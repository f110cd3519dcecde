"""Moved to :mod:`torchcal.coverage` (below the model and the solvers, which record it); re-exported here."""

from ..coverage import DirectionCoverage

__all__ = ["DirectionCoverage"]
