"""The benchmark suite: every bench quiet and with one CPU-bound competitor, one table of ratios and targets.

    python bench/run.py [--only NAME ...] [--quick] [--repeats K] [--workdir runs/bench]
                        [--wait-quiet SECONDS] [--irb120-data DIR] [-v]

NAMEs: fit, order_auto, sweep, compensation, identification, scaling, constraint (bench/README.md).
Not part of the test run (pytest collects tests/ only).
"""

from __future__ import annotations

import torchcal  # noqa: F401  first: OMP_WAIT_POLICY=PASSIVE before torch loads

import importlib
import sys

from harness import execute, parser

BENCHES = ["fit", "order_auto", "sweep", "compensation", "identification", "scaling", "constraint"]  # longest last


def main(argv=None) -> int:
    ap = parser(__doc__.split("\n")[0])
    ap.add_argument("--only", nargs="+", choices=BENCHES, metavar="NAME", help=f"run only these: {', '.join(BENCHES)}")
    args = ap.parse_args(argv)
    names = [b for b in BENCHES if not args.only or b in args.only]
    return execute([importlib.import_module(n) for n in names], args)


if __name__ == "__main__":
    sys.exit(main())
