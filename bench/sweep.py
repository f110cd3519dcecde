"""Bench: Figure 11's sweep, 30 models (orders 1..10 x 150, 250, 350 poses), quiet and loaded.

``torchcal sweep CONFIG model.order=1:10 data.n_poses=150,250,350`` as a subprocess, CONFIG the
fit.yaml of ``torchcal simulate DIR --identification 350`` (seed 0, so every pose count is
available). Target <= 60 s, loaded / quiet <= 1.3. Until the ``sweep`` command exists the case
reports "not available".

    python bench/sweep.py [--quick] [--repeats K]
"""

from __future__ import annotations

import torchcal  # noqa: F401  first: OMP_WAIT_POLICY=PASSIVE before torch loads

import sys

import data as bench_data
from harness import Context, Row, Skip, at_most, cli_available, guarded, main, run_cli

NAME = "sweep"
CASE = "torchcal sweep fit.yaml model.order=1:10 data.n_poses=150,250,350 (30 models)"


def case(ctx: Context) -> Row:
    if not cli_available("sweep"):
        raise Skip("not available: `torchcal sweep` is not a command of this torchcal yet")
    cfg = bench_data.fanuc(ctx, identification=350) / "fit.yaml"

    def one():
        run_cli(["sweep", cfg, "model.order=1:10", "data.n_poses=150,250,350"], timeout=3600)

    p = ctx.pair(one, repeats=1 if ctx.quick else min(ctx.repeats, 2), label="sweep")
    return p.row(NAME, CASE, target=at_most(60, "s"), ratio_target=1.3, note="FANUC, simulate --identification 350")


def run(ctx: Context) -> list[Row]:
    return guarded(NAME, CASE, lambda: case(ctx), ctx, target=at_most(60, "s"), ratio_target=1.3)


if __name__ == "__main__":
    sys.exit(main([sys.modules[__name__]], description=__doc__.split("\n")[0]))
