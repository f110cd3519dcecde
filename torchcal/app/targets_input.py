"""A Cartesian targets file for ``torchcal compensate``: what its columns mean, and what it must not be.

A targets file gives x, y, z and an orientation per row, and the controller's branch by seed commands q1..qN or
by configuration flags (shoulder, elbow, wrist). Read wrongly, every row still "converges": x, y, z without an
orientation were taken for joint commands (17.7 mm off on a user's truth robot), and rx, ry, rz typed in
radians came back flagged with nothing said of the unit. The checks here refuse such files, naming the file and
the columns; :func:`torchcal.app.files.compensate_file` calls them before anything is solved.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import torch

from ..core import units
from ..core.progress import task as progress_task


def has_flags(df, robot) -> bool:
    """The table names the controller's branch by configuration flags (shoulder, elbow, wrist) and gives no
    seed commands (with both, the seeds win: they are the controller's own commands)."""
    from ..compensate.flags import FLAG_NAMES
    from ..io.csv import joint_columns

    cols = set(df.columns)
    return set(FLAG_NAMES) <= cols and not set(joint_columns(robot.joint_map.n)) & cols


def ignored_flags_note(df, robot, path) -> str | None:
    """A targets table with both seed commands and flag columns: the seeds give the branch and the flags are not
    read. Said, since a file whose flags contradicted 29 of 30 seeds ran silently on the seeds' branches."""
    from ..compensate.flags import FLAG_NAMES
    from ..io.csv import joint_columns

    cols = set(df.columns)
    given = [c for c in FLAG_NAMES if c in cols]
    if not given or not set(joint_columns(robot.joint_map.n)) & cols:
        return None
    return (f"{path}: both seed commands q1..q{robot.joint_map.n} and flag columns ({', '.join(given)}): the seeds "
            "give each row's branch and the flags are not read; leave out the seeds to choose the branch by flags")


def seeds_from_flags(model, path, df):
    """q1..qN seed columns (file units) for a targets table with flag columns (:mod:`torchcal.compensate.flags`);
    -> (the table with them, (R,) bool rows for which no nominal IK solution with the flags was found).
    Raises DataError naming every flag cell that is not +1 or -1."""
    from ..compensate.flags import FLAG_NAMES, seeds_for_flags
    from ..compensate.targets import target_poses
    from ..io.csv import DataError, Problem, joint_columns, joints_to_file, parse_numbers, read_targets

    problems = []
    flags = np.stack([parse_numbers(df, c, problems) for c in FLAG_NAMES], 1)
    for r, j in zip(*np.nonzero(np.isfinite(flags) & (np.abs(flags) != 1.0))):
        problems.append(Problem(int(r) + 1, FLAG_NAMES[j], f"a configuration flag must be +1 or -1, got {flags[r, j]:g}"))
    if problems:
        raise DataError(path, problems)
    _, pos, ori = read_targets(df, path)
    tool = torch.zeros(len(df), dtype=torch.long)
    if "tool" in df.columns:
        tool = torch.as_tensor(parse_numbers(df, "tool", problems), dtype=torch.float64).nan_to_num(0).long()
    T = target_poses(pos, ori).to(model.device, model.dtype)
    try:
        with progress_task(f"nominal IK for the configuration flags of {len(df)} targets"):
            q, found = seeds_for_flags(model, T, torch.from_numpy(flags).to(model.device, model.dtype),
                                       tool.clamp(0, model.tools.count - 1).to(model.device))
    except ValueError as exc:
        raise DataError(path, [Problem(None, "shoulder", str(exc))]) from None
    out = df.copy()
    qf = joints_to_file(q, model.robot)
    for i, c in enumerate(joint_columns(model.robot.joint_map.n)):
        out[c] = qf[:, i]
    return out, ~found.cpu()


def refuse_targets_without_orientation(path: Path, df) -> None:
    """x, y, z with no orientation and no pose column: meant as Cartesian targets (a tracker file's rows carry
    their pose id), which would otherwise be read as joint commands, their x, y, z ignored (17.7 mm off on a
    user's truth robot, every row 'converged')."""
    from ..io.csv import TARGET_QUAT, TARGET_RPY, XYZ, DataError, Problem, target_kind

    cols = set(df.columns)
    if target_kind(df) is not None or not set(XYZ) <= cols or "pose" in cols:
        return
    have = [c for c in (*TARGET_RPY, *TARGET_QUAT) if c in cols]
    raise DataError(path, [Problem(None, "rx, ry, rz", (
        f"x, y, z without an orientation ({'only ' + ', '.join(have) if have else 'no orientation columns'}): "
        "Cartesian targets need rx, ry, rz (deg) or qw, qx, qy, qz; to compensate the joint commands q1..qN "
        "instead, leave x, y, z out (a tracker file's measured points come with its pose column)"))])


RADIAN_RPY_DEG = (20.0, 0.25)
"""A targets file's rx, ry, rz are refused as radians when, read as degrees, their orientations lie more than the
first (deg, median over rows) from the nominal robot's at the seeds, and read as radians less than the second
times that: seeds that are only branch hints lie tens of degrees from their targets, and the wrong reading of a
file is a random turn (~120 deg median) away."""


def refuse_radian_orientations(model, path: Path, df, seeds: torch.Tensor) -> None:
    """rx, ry, rz typed in radians: read as degrees every target turns by up to 180 deg from where the seeds point
    the tool, and the rows come back flagged with nothing said about the unit. The seeds (the controller's own
    commands for the targets) decide, as the measured points do for joints in radians."""
    from ..compensate.targets import target_poses
    from ..io.csv import TARGET_RPY, DataError, Problem, read_targets
    from ..io.unit_checks import OVERRIDE
    from ..measure.pose import rotation_error

    kind, pos, ori = read_targets(df, path)
    ok = torch.isfinite(seeds).all(1)
    if kind != "rpy" or int(ok.sum()) == 0:
        return
    with torch.no_grad():
        R = model.nominal_flange(seeds[ok].to(model.device, model.dtype))[:, :3, :3].cpu().to(torch.float64)

    def off_deg(rpy):
        turn = rotation_error(target_poses(pos[ok], rpy[ok])[:, :3, :3], R).norm(dim=-1)
        return float(units.rad_to_deg(turn).median())

    as_deg, as_rad = off_deg(ori), off_deg(units.rad_to_deg(ori))  # the file's numbers read as radians
    far, share = RADIAN_RPY_DEG
    if as_deg > far and as_rad < share * as_deg:
        raise DataError(path, [Problem(None, ", ".join(TARGET_RPY), (
            f"the orientations look like radians: read as degrees (the file contract) they lie {as_deg:.1f} deg "
            f"(median) from the nominal orientation at the seeds q1..q{model.robot.joint_map.n}, read as radians "
            f"{as_rad:.2f} deg; write rx, ry, rz in degrees, or pass {OVERRIDE} if they really are degrees"))])


__all__ = ["RADIAN_RPY_DEG", "has_flags", "refuse_radian_orientations", "refuse_targets_without_orientation",
           "seeds_from_flags"]
