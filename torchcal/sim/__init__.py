"""Simulated physical robots with known truth (Paper II Table 1 error sources) and their measurements.

- :func:`quasi_random_commands`, :func:`approach_directions`: measurement pose sequences (5.2)
- :class:`TruthRobot`: the actual robot, independent of torchcal's Chebyshev model
- :func:`simulate`, :func:`noise_free_points`: tracker measurements (25) with joint and tracker noise
- a whole simulated data set on disk (CSV, truth.json, fit.yaml): :func:`torchcal.app.simulate.simulate_dataset`
- :class:`MachineTruth`, :func:`simulate_machine_dataset`: Paper I's five-axis machine tool and its data set
- :class:`SensorTruth`: Paper III's FANUC + SmartTRACK sensor + laser tracker, and the AT targets
"""

from .machine_truth import MachineTruth, simulate_machine_dataset
from .measure import noise_free_points, simulate
from .sampling import approach_directions, quasi_random_commands
from .sensor_truth import SensorTruth
from .truth import HARMONICS, TruthRobot, harmonic_limit, perpendicular_axes

__all__ = [
    "HARMONICS",
    "MachineTruth",
    "SensorTruth",
    "TruthRobot",
    "approach_directions",
    "harmonic_limit",
    "noise_free_points",
    "perpendicular_axes",
    "quasi_random_commands",
    "simulate",
    "simulate_machine_dataset",
]
