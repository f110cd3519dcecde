"""Moved to :mod:`torchcal.core.coverage` (below the model and the solvers, which record it); re-exported here."""

from ..core.coverage import DirectionCoverage

__all__ = ["DirectionCoverage"]
