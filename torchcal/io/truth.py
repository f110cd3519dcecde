"""``truth.json``: the simulated robot behind a data set, readable by people and reloadable exactly.

Written by ``torchcal simulate``. It holds how the truth was made (kind,
robot, tools in mm, seed, noise in mm / deg², the error variable each joint's
errors follow), its error magnitudes in file units
(:meth:`TruthRobot.describe`), and every buffer of the
:class:`torchcal.sim.TruthRobot` (SI) so that :func:`load_truth` rebuilds the
very same robot without re-running the random draws (independent of later
changes to the simulator's constructors).

``error_variable`` (one word per joint, 'command' or 'joint') is recorded since
the truth's gear errors follow the controller command (Paper II (24)); a file
without it was written when they followed the URDF joint variable and loads
as 'joint'.
"""

from __future__ import annotations

import json
from pathlib import Path

import torch

from ..core import units
from ..core.exceptions import TorchcalError
from .rundir import read_json, write_json

TRUTH_FORMAT = "torchcal.TruthRobot"


class TruthError(TorchcalError, ValueError):
    """A truth.json that cannot be used; the message names the file."""


def save_truth(path, truth, kind: str, seed: int, noise=None, robot_spec: str | None = None) -> Path:
    """Write ``truth`` (a TruthRobot) to ``path`` as JSON; ``noise`` (a NoiseModel, SI) is stored in mm / deg²."""
    recipe = {
        "kind": kind,
        "robot": robot_spec or truth.robot.source or truth.robot.name,
        "seed": int(seed),
        "error_variable": list(truth.error_variable),
        "backlash_on": getattr(truth, "backlash_on", "joint"),
        "tools_mm": units.m_to_mm(truth.tools_nominal.cpu()).tolist(),
    }
    if noise is not None:
        scale2 = units.joint_scale(truth.prismatic.cpu()) ** 2
        recipe["noise"] = {
            "sigma_m_mm": units.m_to_mm(float(noise.sigma_m)),
            "joint_var_fwd": (noise.joint_var_fwd.cpu() / scale2).tolist(),
            "joint_var_bwd": (noise.joint_var_bwd.cpu() / scale2).tolist(),
        }
    blob = {
        "format": TRUTH_FORMAT,
        **recipe,
        "describe": truth.describe(),
        "state_si": {k: v.detach().cpu().tolist() for k, v in truth.state_dict().items() if v.dtype.is_floating_point},
    }
    return write_json(path, blob)


def load_truth(path, robot=None):
    """Rebuild the TruthRobot of a ``truth.json`` (on CPU). robot: a loaded Robot to use instead of the recorded one."""
    from ..kinematics import load_robot
    from ..sim.truth import TruthRobot

    path = Path(path)
    if not path.is_file():
        raise TruthError(f"{path}: truth file not found")
    try:
        blob = read_json(path)
    except json.JSONDecodeError as exc:
        raise TruthError(f"{path}: not valid JSON (line {exc.lineno}: {exc.msg})") from None
    if not isinstance(blob, dict) or blob.get("format") != TRUTH_FORMAT:
        raise TruthError(f"{path}: not a truth file written by 'torchcal simulate'")
    robot = robot or load_robot(blob["robot"])
    tools = units.mm_to_m(torch.tensor(blob["tools_mm"], dtype=torch.float64))
    # files from before the key existed evaluated every error on the URDF joint variable
    try:
        truth = TruthRobot(robot, tools, error_variable=blob.get("error_variable", "joint"),
                           backlash_on=blob.get("backlash_on", "joint"))
    except ValueError as exc:
        raise TruthError(f"{path}: {exc}") from None
    state = truth.state_dict()
    for k, v in blob["state_si"].items():
        if k not in state:
            raise TruthError(f"{path}: unknown truth parameter '{k}' (written by another torchcal version?)")
        value = torch.tensor(v, dtype=state[k].dtype)
        if value.shape != state[k].shape:
            raise TruthError(f"{path}: '{k}' has shape {tuple(value.shape)}, the robot needs {tuple(state[k].shape)}")
        state[k] = value
    truth.load_state_dict(state)
    return truth


def truth_noise(path, prismatic=None):
    """The NoiseModel (SI) a truth.json's data were simulated with, or None. prismatic: (n,) bool joint types."""
    from ..identify import NoiseModel

    blob = read_json(path)
    nz = blob.get("noise")
    if nz is None:
        return None
    return NoiseModel.from_file_units(nz["sigma_m_mm"], nz["joint_var_fwd"], nz["joint_var_bwd"], prismatic)


__all__ = ["TruthError", "load_truth", "save_truth", "truth_noise"]
