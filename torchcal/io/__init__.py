"""Files in and out: the CSV data contract, run directories, simulated truths and plots.

Everything here speaks mm and degrees on the file side and SI inside; the
conversion goes through :mod:`torchcal.core.units` only. ``plots`` is imported on
demand (it loads matplotlib).
"""

from ..core.exceptions import ConfigError
from .csv import DataError, Problem, read_measurements, read_table, write_measurements, write_table
from .rundir import RunDirError, collect_versions, load_model, load_run_config, make_run_dir, save_model, write_json
from .truth import TruthError, load_truth, save_truth

__all__ = [
    "ConfigError",
    "DataError",
    "Problem",
    "RunDirError",
    "TruthError",
    "collect_versions",
    "load_model",
    "load_run_config",
    "load_truth",
    "make_run_dir",
    "read_measurements",
    "read_table",
    "save_model",
    "save_truth",
    "write_json",
    "write_measurements",
    "write_table",
]
