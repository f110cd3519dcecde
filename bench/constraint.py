"""Bench: the slope constraint's ``c: auto`` (BORDER, constraint sweep, knee, refit), quiet and loaded.

Each case is ``torchcal fit CONFIG`` as a subprocess:
- Paper I's machine: experiments/paper1_machine_tool/fit.yaml on the data of
  experiments/paper1_machine_tool/run.py (seed 0); target <= 30 s;
- IRB 120, the shipped config experiments/irb120_faro/fit.yaml (order 4 + backlash + gravity
  compliance, BORDER in (J2, J5), 512 / 2048 points) on run.py's 70/30 split (seed 0); target <= 60 s;
- IRB 120 with only ``constraint: {c: auto}`` (defaults for everything else); target <= 120 s.
Every case: loaded / quiet <= 1.3. Each case runs once per condition (minutes each); the IRB
cases are left out by --quick.

    python bench/constraint.py [--quick] [--repeats K] [--irb120-data DIR]
"""

from __future__ import annotations

import torchcal  # noqa: F401  first: OMP_WAIT_POLICY=PASSIVE before torch loads

import json
import sys

import data as bench_data
from harness import Context, Row, at_most, fresh_out, guarded, main, run_cli

NAME = "constraint"


def knee_note(run_dir) -> str:
    """'c = ... mm; sweep fits (c: s); held out mean / max' from a run directory's metrics.json (best effort)."""
    try:
        m = json.loads((run_dir / "metrics.json").read_text())
    except (OSError, ValueError):
        return ""
    parts = []
    con = m.get("constraint") or {}
    if con.get("c") is not None:
        parts.append(f"c = {con['c']:.3g} mm" if isinstance(con["c"], (int, float)) else f"c = {con['c']}")
    sweep = con.get("sweep") or []
    if sweep:
        parts.append("sweep fits " + ", ".join(f"{'free' if s.get('c_mm') is None else format(s['c_mm'], 'g')}: "
                                               f"{s.get('time_s', float('nan')):.0f} s" for s in sweep))
    val = ((m.get("sets") or {}).get("validation") or {}).get("modeled") or {}
    if "mean" in val:
        parts.append(f"held out {val['mean']:.4f} / {val.get('max', float('nan')):.3f} mm")
    return "; ".join(parts) + " (last loaded run)"


def cli_case(ctx: Context, label: str, cfg, target: float, repeats: int | None = None) -> Row:
    outs = []

    def one():
        out = fresh_out(ctx, "constraint")
        run_cli(["fit", "-q", cfg, f"out={out}"], timeout=3600)
        outs.append(out)

    p = ctx.pair(one, repeats=repeats, label=label)
    return p.row(NAME, label, target=at_most(target, "s"), ratio_target=1.3, note=knee_note(outs[-1]))


def run(ctx: Context) -> list[Row]:
    rows = guarded(NAME, "Paper I machine, c: auto", lambda: cli_case(
        ctx, "Paper I machine: torchcal fit paper1_machine_tool/fit.yaml (c: auto)", bench_data.paper1(ctx), 30,
        repeats=1), ctx)
    if ctx.quick:
        rows.append(Row(NAME, "IRB 120 c: auto (shipped config, only c: auto)", skipped="--quick (minutes per run)"))
        return rows
    rows += guarded(NAME, "IRB 120 shipped config", lambda: cli_case(
        ctx, "IRB 120: torchcal fit irb120_faro/fit.yaml (shipped, c: auto)", bench_data.irb120_config(ctx, "shipped"),
        60, repeats=1), ctx)
    rows += guarded(NAME, "IRB 120 only c: auto", lambda: cli_case(
        ctx, "IRB 120: shipped model with only constraint: {c: auto}", bench_data.irb120_config(ctx, "only_c_auto"),
        120, repeats=1), ctx)
    return rows


if __name__ == "__main__":
    sys.exit(main([sys.modules[__name__]], description=__doc__.split("\n")[0]))
