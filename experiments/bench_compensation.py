"""Moved: the compensation benchmark lives in bench/compensation.py (part of the bench/ suite).

    python experiments/bench_compensation.py [ARGS]   ==   python bench/compensation.py --report [ARGS]

prints the detailed report (throughput against roboticstoolbox's ik_LM, accuracy, robustness,
corrections); ``python bench/compensation.py`` times it quiet and loaded against ik_LM and
pytorch-kinematics at equal accuracy (see bench/README.md).
"""

import runpy
import sys
from pathlib import Path

if __name__ == "__main__":
    bench = Path(__file__).resolve().parents[1] / "bench"
    sys.path.insert(0, str(bench))
    sys.argv = [str(bench / "compensation.py"), "--report", *sys.argv[1:]]
    runpy.run_path(sys.argv[0], run_name="__main__")
