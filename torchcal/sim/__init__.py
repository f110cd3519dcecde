"""Simulated physical robots with known truth (Paper II Table 1 error sources) and their measurements.

- :func:`quasi_random_commands`, :func:`approach_directions`: measurement pose sequences (5.2)
- :class:`TruthRobot`: the actual robot, independent of torchcal's Chebyshev model
- :func:`simulate`, :func:`noise_free_points`: tracker measurements (25) with joint and tracker noise
- :func:`simulate_dataset`: a whole simulated data set on disk (CSV, truth.json, fit.yaml)
"""

from .dataset import default_joint_variances, simulate_dataset
from .measure import noise_free_points, simulate
from .sampling import approach_directions, quasi_random_commands
from .truth import HARMONICS, TruthRobot, harmonic_limit, perpendicular_axes

__all__ = [
    "HARMONICS",
    "TruthRobot",
    "approach_directions",
    "default_joint_variances",
    "harmonic_limit",
    "noise_free_points",
    "perpendicular_axes",
    "quasi_random_commands",
    "simulate",
    "simulate_dataset",
]
