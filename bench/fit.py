"""Bench: one FANUC fit (order 6 + backlash, 250 poses x 3 tools), quiet and loaded.

Cases:
- solver: ``torchcal.fit`` in this process on the data of ``torchcal simulate`` (seed 0), the
  config's noise and prior; time = the fit call's wall clock (after one warm-up fit);
  target <= 2 s, loaded / quiet <= 1.3;
- CLI: the whole ``torchcal fit fit.yaml`` as a subprocess (start-up, alignment, fit, evaluation,
  compensation check, plots); target <= 8 s, loaded / quiet <= 1.3.

    python bench/fit.py [--quick] [--repeats K]
"""

from __future__ import annotations

import torchcal  # noqa: F401  first: OMP_WAIT_POLICY=PASSIVE before torch loads

import sys

import data as bench_data
from harness import Context, Row, at_most, fresh_out, guarded, main, run_cli

NAME = "fit"


def fanuc_fit_setup(ctx: Context, order: int = 6):
    """(make_model, ident, noise, prior, opts) of the bench's FANUC config."""
    import torch

    from torchcal.core import units
    from torchcal.app.config import load_config
    from torchcal.io.csv import read_measurements
    from torchcal.kinematics import load_robot
    from torchcal.models.robot import RobotModel
    from torchcal.app.fit import config_noise, config_prior, solver_options

    folder = bench_data.fanuc(ctx)
    cfg = load_config(folder / "fit.yaml")
    robot = load_robot(cfg.robot)
    tools = units.mm_to_m(torch.tensor([list(t) for t in cfg.tools], dtype=torch.float64))
    ident = read_measurements(folder / "identification.csv", robot, tools.shape[0])
    noise, prior, opts = config_noise(cfg, robot), config_prior(cfg), solver_options(cfg)

    def make():
        return RobotModel(robot, tools, orders=order, backlash=True)

    return make, ident, noise, prior, opts


def solver_case(ctx: Context) -> Row:
    from torchcal.identify import fit

    make, ident, noise, prior, opts = fanuc_fit_setup(ctx)
    fit(make(), ident, noise, prior, **opts)  # warm-up: imports, numba caches, allocator

    def one():
        return fit(make(), ident, noise, prior, **opts)

    p = ctx.pair(one, label="fit solver")
    res = p.out_quiet[-1]
    return p.row(NAME, "FANUC order 6 + backlash, 250 x 3: torchcal.fit (in process)", target=at_most(2, "s"),
                 ratio_target=1.3, note=f"{res.nit} LM iterations, {res.x.numel()} parameters, "
                                        f"{'converged' if res.success else 'NOT converged'}")


def cli_case(ctx: Context) -> Row:
    cfg = bench_data.fanuc(ctx) / "fit.yaml"
    run_cli(["fit", "-q", cfg, f"out={fresh_out(ctx, 'warmup')}"])  # warm-up (numba on-disk cache)

    def one():
        run_cli(["fit", "-q", cfg, f"out={fresh_out(ctx, 'fit')}"])

    p = ctx.pair(one, label="torchcal fit")
    return p.row(NAME, "torchcal fit fit.yaml (FANUC, whole CLI, subprocess)", target=at_most(8, "s"), ratio_target=1.3,
                 note="simulate + fit.yaml of `torchcal simulate` (seed 0)")


def run(ctx: Context) -> list[Row]:
    return (guarded(NAME, "FANUC fit solver", lambda: solver_case(ctx), ctx)
            + guarded(NAME, "torchcal fit (CLI)", lambda: cli_case(ctx), ctx))


if __name__ == "__main__":
    sys.exit(main([sys.modules[__name__]], description=__doc__.split("\n")[0]))
