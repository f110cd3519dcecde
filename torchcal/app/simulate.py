"""A simulated data set on disk: measurements in the CSV contract, truth.json and a ready fit.yaml.

What ``torchcal simulate`` writes, as a library function (the CLI only parses
options and prints the paths): Paper II's protocol (5.2, 5.5) on a
:class:`TruthRobot` with known errors.
"""

from __future__ import annotations

import logging
from pathlib import Path

PAPER2_TOOLS_MM = [[33.06, 57.73, 161.22], [57.26, -33.86, 161.22], [-33.96, -57.23, 161.22]]
"""Paper II Table 4: the three measurement tool vectors, mm, flange frame."""

TRACKER_SIGMA_MM = 0.005
"""Simulated tracker noise, mm per axis (Paper II 4.1)."""


def default_joint_variances(n: int) -> tuple[list[float], list[float]]:
    """Joint variances (deg²) for simulated data: Paper II Table 5 for 6 joints, else its median for every joint."""
    from ..identify import PAPER2_JOINT_VAR_BWD, PAPER2_JOINT_VAR_FWD

    if n == len(PAPER2_JOINT_VAR_FWD):
        return list(PAPER2_JOINT_VAR_FWD), list(PAPER2_JOINT_VAR_BWD)
    med_f = sorted(PAPER2_JOINT_VAR_FWD)[len(PAPER2_JOINT_VAR_FWD) // 2]
    med_b = sorted(PAPER2_JOINT_VAR_BWD)[len(PAPER2_JOINT_VAR_BWD) // 2]
    return [med_f] * n, [med_b] * n


def simulated_joint_variances(robot) -> tuple[list[float], list[float]]:
    """Joint variances (deg², mm² for prismatic joints) the simulated robot repeats with: its own
    ``repeatability:`` where its YAML declares one, else :func:`default_joint_variances` (written into fit.yaml
    either way, so the fit uses what the simulation used)."""
    rep = getattr(robot, "repeatability", None)
    if rep is None:
        return default_joint_variances(robot.joint_map.n)
    from ..core import units

    scale2 = units.joint_scale(robot.joint_map.prismatic.cpu()) ** 2
    # back in the YAML's units, at the digits a YAML holds (SI and back leaves the last bit off)
    return ([float(f"{v:.12g}") for v in (rep.var_fwd.cpu() / scale2).tolist()],
            [float(f"{v:.12g}") for v in (rep.var_bwd.cpu() / scale2).tolist()])


def simulate_dataset(out_dir, robot: str = "fanuc_lrmate200i", identification: int = 250, validation: int = 300,
                     validation_tool: int = 2, seed: int = 0, order: int = 6, force: bool = False,
                     error_variable="command", pose_order: str = "shuffled",
                     backlash_on: str = "joint") -> dict[str, Path]:
    """Write simulated measurements in the CSV contract plus truth.json and a ready-to-run fit.yaml.

    Paper II's protocol (5.2, 5.5): quasi-random commands over the controller
    range, each identification pose measured with all three tools of Table 4,
    disjoint validation commands measured with ``validation_tool``; tracker
    sigma 0.005 mm and the robot's own joint repeatability (its YAML's; Table 5 for the
    FANUC; without one, :func:`default_joint_variances`). The truth is Paper II's FANUC
    (:meth:`TruthRobot.fanuc_paper2`) for the bundled FANUC, else
    :meth:`TruthRobot.random`, with its gear errors following
    ``error_variable`` ('command', Paper II (24), or 'joint'; one word or one
    per joint), recorded in truth.json. The fit.yaml leaves the model's error
    variable to the robot file. pose_order: 'shuffled' (a seeded random visiting
    order) or 'sequence' (the quasi-random sequence's own order, as the paper
    measured: each joint's approach direction then nearly follows its position,
    see :func:`torchcal.sim.sampling.quasi_random_commands`).
    -> name -> path of the files written.

    Bad options raise :class:`torchcal.core.exceptions.ConfigError` (also importable from :mod:`torchcal.app.config`).
    """
    import torch
    import yaml

    from ..core import units
    from ..identify import NoiseModel
    from ..core.exceptions import ConfigError
    from ..io.atomic import atomic_write_text
    from ..io.csv import write_measurements
    from ..io.truth import save_truth
    from ..kinematics import load_robot
    from ..kinematics.joint_map import normalize_error_variable
    from ..sim.measure import simulate
    from ..sim.sampling import quasi_random_commands
    from ..sim.truth import TruthRobot

    out_dir = Path(out_dir)
    names = {"identification": "identification.csv", "validation": "validation.csv", "truth": "truth.json", "config": "fit.yaml"}
    existing = [n for n in names.values() if (out_dir / n).exists()]
    if existing and not force:
        raise ConfigError(f"{out_dir}: already holds {existing}; choose another folder or pass --force to overwrite")
    if pose_order not in ("shuffled", "sequence"):
        raise ConfigError(f"--pose-order {pose_order!r}: choose 'shuffled' or 'sequence'")
    if identification < 1 or validation < 0:
        raise ConfigError(f"--identification must be >= 1 and --validation >= 0 (got {identification}, {validation})")
    tools_mm = PAPER2_TOOLS_MM
    if not 0 <= validation_tool < len(tools_mm):
        raise ConfigError(f"--validation-tool {validation_tool}: tools are 0..{len(tools_mm) - 1} (Paper II Table 4)")
    rob = load_robot(robot)
    n = rob.joint_map.n
    if rob.name == MACHINE:
        return _simulate_machine(out_dir, names, identification, validation, seed, order, error_variable, pose_order,
                                 backlash_on)
    # fit.yaml must pass `torchcal fit`'s own check: the same rule, not a copy of it
    from .config import make_config

    make_config({"robot": rob.name, "tools": PAPER2_TOOLS_MM, "data": {"identification": names["identification"]},
                 "model": {"order": order}}, label="--order", base_dir=out_dir)
    try:
        error_variable = normalize_error_variable(error_variable, n, rob.joint_map.names)
    except ValueError as exc:
        raise ConfigError(f"--error-variable: {exc}") from None
    tools_m = units.mm_to_m(torch.tensor(tools_mm, dtype=torch.float64))
    kind = "fanuc_paper2" if rob.name == "fanuc_lrmate200i" and n == 6 else "random"
    # fit.yaml and truth.json name a robot file absolutely: they are read from another folder
    robot_spec = str(Path(rob.source).resolve()) if Path(rob.source).suffix else (rob.source or rob.name)
    make = TruthRobot.fanuc_paper2 if kind == "fanuc_paper2" else TruthRobot.random
    if backlash_on not in ("joint", "command"):
        raise ConfigError(f"--backlash-on '{backlash_on}': give joint (Paper II (13)) or command (through the joint map)")
    truth = make(rob, tools_m, seed, error_variable=error_variable)
    truth.backlash_on = backlash_on  # (recorded in truth.json; the fit.yaml leaves the model at the paper's reading)
    var_f, var_b = simulated_joint_variances(rob)
    stand_in = None
    if getattr(rob, "repeatability", None) is None:  # said, and written into fit.yaml: never another robot's silently
        stand_in = ("Paper II's FANUC Table 5" if n == 6 else "the median of Paper II's FANUC Table 5, every joint")
        logging.getLogger("torchcal").warning(
            "robot '%s' declares no repeatability: the simulated joint noise uses %s (noise.joint_var_fwd / _bwd in "
            "fit.yaml); give the robot's own in its YAML ('repeatability:') or in the config for real data",
            rob.name, stand_in)
    sigma_mm = TRACKER_SIGMA_MM
    noise = NoiseModel.from_file_units(sigma_mm, var_f, var_b, rob.joint_map.prismatic)
    limits = rob.joint_map.limits
    # one scrambled sequence: validation continues where identification stopped, so the sets are disjoint
    shuffle = pose_order == "shuffled"
    q_id = quasi_random_commands(limits, identification, seed, shuffle=shuffle)
    ident = simulate(truth, q_id, list(range(len(tools_mm))), noise, seed)
    val = None
    if validation:
        q_val = quasi_random_commands(limits, validation, seed, skip=identification, shuffle=shuffle)
        val = simulate(truth, q_val, [validation_tool], noise, seed + 1)
    out_dir.mkdir(parents=True, exist_ok=True)
    # everything is computed; the old set goes first and fit.yaml comes last, so that Ctrl-C or a full disk
    # while writing leaves an incomplete set that `torchcal fit` cannot start from, never one mixing two seeds
    for name in ("config", "identification", "validation", "truth"):
        (out_dir / names[name]).unlink(missing_ok=True)
    paths = {"identification": write_measurements(out_dir / names["identification"], ident, rob)}
    if val is not None:
        paths["validation"] = write_measurements(out_dir / names["validation"], val, rob)
    paths["truth"] = save_truth(out_dir / names["truth"], truth, kind, seed, noise, robot_spec=robot_spec)
    cfg = {
        "robot": robot_spec,
        "tools": tools_mm,
        "data": {"identification": names["identification"], "validation": names["validation"] if validation else None,
                 "truth": names["truth"] if validation else None},
        "model": {"order": order, "backlash": True},
        "noise": {"sigma_m": sigma_mm, "joint_var_fwd": var_f, "joint_var_bwd": var_b},
        "seed": seed,
        "out": "runs",
    }
    ev = error_variable[0] if len(set(error_variable)) == 1 else ", ".join(error_variable)
    header = (f"# Simulated '{rob.name}' data written by `torchcal simulate` (truth: {kind}, seed {seed}, "
              f"errors follow: {ev}, poses in {pose_order} order).\n"
              f"# Run:  torchcal fit {out_dir / names['config']}  [key=value ...]\n"
              "# Units: mm, deg, deg^2 (mm^2 for linear axes). Relative paths resolve against this file's folder.\n"
              + (f"# noise.joint_var_fwd / _bwd: {stand_in} (the robot declares no repeatability), not this robot's.\n"
                 if stand_in else "") +
              "# 'data.truth' enables the compensation check on the simulated robot (Paper II Table 7, Fig. 16).\n")
    atomic_write_text(out_dir / names["config"], header + yaml.safe_dump(cfg, sort_keys=False, default_flow_style=None))
    paths["config"] = out_dir / names["config"]
    return paths


MACHINE = "five_axis_xyzcb"
"""The bundled machine tool: simulated by Paper I's machine (:class:`torchcal.sim.machine_truth.MachineTruth`)."""


def _simulate_machine(out_dir: Path, names: dict, identification: int, validation: int, seed: int, order: int,
                      error_variable, pose_order: str, backlash_on: str) -> dict[str, Path]:
    """Paper I's data set (4.1) on the simulated XYZCB machine and a fit.yaml for its axis perturbation model:
    validation = interpolation + extrapolation rows (half each), both tools; no truth.json (the machine's truth
    is Paper I's simulator, which the compensation check of robots does not run)."""
    import yaml

    from ..core.exceptions import ConfigError
    from ..io.atomic import atomic_write_text
    from ..sim.machine_truth import PAPER1_TOOLS_MM, MachineTruth, simulate_machine_dataset, write_machine_csv

    robot_only = [f"--{k.replace('_', '-')} {v}" for k, v, d in (("error_variable", error_variable, "command"),
                                                               ("pose_order", pose_order, "shuffled"),
                                                               ("backlash_on", backlash_on, "joint")) if v != d]
    if robot_only:
        raise ConfigError(f"{', '.join(robot_only)}: robot options; the machine ({MACHINE}) is simulated as Paper I's")
    extrap = validation // 2
    data, split = simulate_machine_dataset(MachineTruth(seed=seed), n_commands=identification + validation, seed=seed,
                                           n_interpolation=validation - extrap, n_extrapolation=extrap)
    out_dir.mkdir(parents=True, exist_ok=True)
    for name in ("config", "identification", "validation", "truth"):
        (out_dir / names[name]).unlink(missing_ok=True)
    import torch

    paths = {"identification": write_machine_csv(out_dir / names["identification"], data.subset(split["identification"]))}
    if validation:
        paths["validation"] = write_machine_csv(out_dir / names["validation"], data.subset(
            torch.cat([split["interpolation"], split["extrapolation"]])))
    cfg = {"robot": MACHINE, "tools": [[0.0, 0.0, float(l)] for l in PAPER1_TOOLS_MM],
           "data": {"identification": names["identification"], "validation": names["validation"] if validation else None},
           "model": {"kind": "axis_perturbation", "order": order}, "noise": {"sigma_m": 0.02}, "seed": seed,
           "out": "runs"}
    header = (f"# Simulated '{MACHINE}' data written by `torchcal simulate` (Paper I's machine, seed {seed}).\n"
              f"# Run:  torchcal fit {out_dir / names['config']}  [constraint.c=auto ...]\n"
              "# then: torchcal export-tables RUN_DIR --format all TABLES_DIR\n"
              "# Units: mm, deg. Validation: Paper I's interpolation and extrapolation rows (column 'set').\n")
    atomic_write_text(out_dir / names["config"], header + yaml.safe_dump(cfg, sort_keys=False, default_flow_style=None))
    paths["config"] = out_dir / names["config"]
    return paths


__all__ = ["PAPER2_TOOLS_MM", "TRACKER_SIGMA_MM", "default_joint_variances", "simulate_dataset", "simulated_joint_variances"]
