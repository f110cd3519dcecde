"""Data sets of the benchmarks, written once into the work directory (default runs/bench).

- ``fanuc(ctx, n)``: what ``torchcal simulate DIR --identification n --force`` writes (simulated FANUC,
  seed 0, 300 validation poses, fit.yaml with order 6 + backlash);
- ``paper1(ctx)``: the simulated XYZCB machine split of ``experiments/paper1_machine_tool/run.py``
  (seed 0) and a copy of ``experiments/paper1_machine_tool/fit.yaml`` pointing at it;
- ``irb120(ctx)``: the IRB 120 + FARO import and the seeded 70/30 split of
  ``experiments/irb120_faro/run.py`` (its own ``load`` and ``split``, seed 0) as
  identification.csv / validation.csv, and configs derived from ``experiments/irb120_faro/fit.yaml``.

The raw IRB 120 files are read by path (``--irb120-data``), never copied into the repository.
"""

from __future__ import annotations

import torchcal  # noqa: F401  first (OMP_WAIT_POLICY)

import copy
import importlib.util
import sys
from pathlib import Path

import yaml

from harness import ROOT, Context, Skip

IRB_FILES = ["commanded_joints.txt"] + [f"measured_SMR_{i}.txt" for i in (1, 2, 3)] + [f"measured_base_{i}.txt" for i in (1, 2, 3)]


def _done(path: Path) -> bool:
    return (path / ".complete").exists()


def fanuc(ctx: Context, identification: int = 250) -> Path:
    """Folder with identification.csv, validation.csv, truth.json, fit.yaml (``torchcal simulate``, seed 0)."""
    from torchcal.app.simulate import simulate_dataset

    out = ctx.workdir / ("fanuc" if identification == 250 else f"fanuc{identification}")
    if not _done(out):
        simulate_dataset(out, "fanuc_lrmate200i", identification=identification, validation=300, validation_tool=2,
                         seed=0, order=6, force=True)
        (out / ".complete").write_text("torchcal simulate, seed 0\n")
    return out


def paper1(ctx: Context) -> Path:
    """Config (fit.yaml) of Paper I's machine with the data of experiments/paper1_machine_tool/run.py (seed 0)."""
    import torch

    from torchcal.sim.machine_truth import MachineTruth, simulate_machine_dataset, write_machine_csv

    out = ctx.workdir / "paper1"
    cfg_path = out / "fit.yaml"
    if not _done(out):
        out.mkdir(parents=True, exist_ok=True)
        data, split = simulate_machine_dataset(MachineTruth(seed=0), seed=0, csv_path=out / "measurements.csv")
        write_machine_csv(out / "identification.csv", data.subset(split["identification"]))
        write_machine_csv(out / "validation.csv",
                          data.subset(torch.cat([split["interpolation"], split["extrapolation"]])))
        cfg = yaml.safe_load((ROOT / "experiments/paper1_machine_tool/fit.yaml").read_text())
        cfg["data"] = {"identification": str(out / "identification.csv"), "validation": str(out / "validation.csv")}
        cfg["out"] = str(out / "runs")
        cfg_path.write_text(yaml.safe_dump(cfg, sort_keys=False))
        (out / ".complete").write_text("experiments/paper1_machine_tool/run.py split, seed 0\n")
    return cfg_path


def _irb_run_module():
    path = ROOT / "experiments/irb120_faro/run.py"
    spec = importlib.util.spec_from_file_location("irb120_faro_run", path)
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    return mod


def irb120_raw(ctx: Context) -> Path:
    d = ctx.irb120_data
    missing = [f for f in IRB_FILES if not (d / f).is_file()]
    if missing:
        raise Skip(f"IRB 120 + FARO data not found in {d} (missing {', '.join(missing[:3])}); pass --irb120-data DIR "
                   f"(4-DataProcess/Input of github.com/icelinker/Robot-Calibration-LaserTracker)")
    return d


def irb120(ctx: Context) -> Path:
    """Folder with the imported IRB 120 data and the seed-0 70/30 split of experiments/irb120_faro/run.py."""
    raw = irb120_raw(ctx)
    out = ctx.workdir / "irb120"
    if not _done(out):
        out.mkdir(parents=True, exist_ok=True)
        from torchcal.io.csv import write_measurements
        from torchcal.kinematics import load_robot

        run = _irb_run_module()
        robot = load_robot("abb_irb120")
        _, data = run.load(raw, robot, out)  # import_tracker with drift correction -> out/measurements.csv
        ident, val = run.split(data, 0)
        write_measurements(out / "identification.csv", ident, robot)
        write_measurements(out / "validation.csv", val, robot)
        (out / ".complete").write_text(f"experiments/irb120_faro/run.py load + split, seed 0, from {raw}\n")
    return out


def irb120_measurements(ctx: Context):
    """(robot, identification, validation) Measurements of :func:`irb120`."""
    from torchcal.io.csv import read_measurements
    from torchcal.kinematics import load_robot

    d = irb120(ctx)
    robot = load_robot("abb_irb120")
    return robot, read_measurements(d / "identification.csv", robot, 3), read_measurements(d / "validation.csv", robot, 3)


def irb120_config(ctx: Context, variant: str = "shipped") -> Path:
    """experiments/irb120_faro/fit.yaml on the bench's split.

    variant 'shipped': the config as shipped; 'only_c_auto': its ``constraint:`` replaced by ``{c: auto}``
    (BORDER axes, point counts at their defaults); 'unconstrained': no constraint.
    """
    d = irb120(ctx)
    cfg = yaml.safe_load((ROOT / "experiments/irb120_faro/fit.yaml").read_text())
    cfg = copy.deepcopy(cfg)
    cfg["data"] = {"identification": str(d / "identification.csv"), "validation": str(d / "validation.csv")}
    cfg["out"] = str(d / "runs")
    if variant == "only_c_auto":
        cfg["constraint"] = {"c": "auto"}
    elif variant == "unconstrained":
        cfg.pop("constraint", None)
    elif variant != "shipped":
        raise ValueError(variant)
    path = d / f"fit_{variant}.yaml"
    path.write_text(yaml.safe_dump(cfg, sort_keys=False))
    return path


if __name__ == "__main__":  # prepare everything: python bench/data.py [--workdir DIR] [--irb120-data DIR]
    from harness import parser

    ctx = Context(parser("prepare the benchmark data").parse_args(sys.argv[1:]))
    print(fanuc(ctx), fanuc(ctx, 350), paper1(ctx))
    try:
        print(irb120(ctx))
    except Skip as e:
        print(f"skipped: {e}")
