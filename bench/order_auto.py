"""Bench: ``model.order: auto`` with backlash orders (FANUC, 250 x 3, no validation set), quiet and loaded.

``torchcal fit fit.yaml model.order=auto data.validation=null data.truth=null`` as a subprocess
(without a validation set the simulated truth's compensation check cannot run either): the Chebyshev
order of every joint by leave-one-pose-out residuals (Figure 11's procedure without a validation
set), then the backlash order of every joint, then the final fit and the run directory.
Target <= 15 s, loaded / quiet <= 1.3.

    python bench/order_auto.py [--quick] [--repeats K]
"""

from __future__ import annotations

import torchcal  # noqa: F401  first: OMP_WAIT_POLICY=PASSIVE before torch loads

import json
import sys

import data as bench_data
from harness import Context, Row, at_most, fresh_out, guarded, main, run_cli

NAME = "order_auto"


def case(ctx: Context) -> Row:
    cfg = bench_data.fanuc(ctx) / "fit.yaml"
    outs = []

    def one():
        out = fresh_out(ctx, "order-auto")
        # no validation set; the simulated truth's compensation check needs one, so it goes too
        run_cli(["fit", "-q", cfg, "model.order=auto", "data.validation=null", "data.truth=null", f"out={out}"])
        outs.append(out)

    p = ctx.pair(one, repeats=1 if ctx.quick else min(ctx.repeats, 2), label="order auto")
    note = ""
    try:
        rec = json.loads((outs[-1] / "orders.json").read_text())
        note = f"orders {rec.get('orders')}, backlash orders {rec.get('backlash_orders')} ({rec.get('criterion')})"
    except (OSError, ValueError):
        pass
    return p.row(NAME, "torchcal fit fit.yaml model.order=auto data.validation=null data.truth=null (FANUC 250 x 3)",
                 target=at_most(15, "s"), ratio_target=1.3, note=note)


def run(ctx: Context) -> list[Row]:
    return guarded(NAME, "order auto", lambda: case(ctx), ctx, target=at_most(15, "s"), ratio_target=1.3)


if __name__ == "__main__":
    sys.exit(main([sys.modules[__name__]], description=__doc__.split("\n")[0]))
