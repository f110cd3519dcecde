"""Simulated laser-tracker measurements of a :class:`TruthRobot`, Paper II (25) and 4.1.

Each tool configuration measures the whole pose sequence (Paper II: the same
joint commands in three tool configurations), so rows are tool-major: all
poses with tools[0], then all with tools[1], ...; pose ids 0..N-1 are shared
across tools. Every row gets its own joint positioning error
v ~ N(0, Σ_v(s)) (forward / backward variances by approach direction, Table 5)
and tracker noise ξ ~ N(0, σ_m² I), as in the objective (31)-(33).
"""

from __future__ import annotations

import torch

from ..identify.problem import NoiseModel
from ..core.measurements import Measurements, first_invalid_direction
from .sampling import approach_directions
from .truth import TruthRobot


def simulate(
    truth: TruthRobot,
    commands: torch.Tensor,
    tools,
    noise: NoiseModel | None,
    seed: int,
    directions: torch.Tensor | None = None,
) -> Measurements:
    """Measure every command with every tool configuration.

    truth: the robot; commands: (N, n) controller commands, SI; tools: tool
    indices into the truth's tool set (T'); noise: tracker sigma and joint
    variances, or None for exact points; seed: seeds the one torch.Generator
    all draws come from; directions: (N, n) approach directions, default
    :func:`approach_directions` of ``commands`` in the given order.
    -> Measurements with R = T' N rows (tool-major), q (R, n), xyz (R, 3) m,
    direction (R, n), pose (R,) = arange(N) repeated, has_direction=True,
    source="simulated", and ``extra['v']`` (R, n) / ``extra['xyz_exact']`` (R, 3),
    the drawn joint errors and the noise-free (v = 0, ξ = 0) points.

    Draws are made on the CPU in float64 and then moved to the truth's
    device, so a seed gives the same data on every device.

    Example:
        >>> import torch, torchcal
        >>> robot = torchcal.load_robot("fanuc_lrmate200i")
        >>> truth = torchcal.TruthRobot.fanuc_paper2(robot, torch.tensor([[0.0, 0.0, 0.1]], dtype=torch.float64), 0)
        >>> q = torchcal.sim.quasi_random_commands(robot.joint_map.limits, 10, 0)
        >>> data = simulate(truth, q, [0], torchcal.NoiseModel.from_robot(robot), seed=0)
        >>> len(data), data.has_direction
        (10, True)
    """
    q = torch.as_tensor(commands)
    if q.ndim != 2 or q.shape[1] != truth.n:
        raise ValueError(f"simulate: commands must have shape (N, {truth.n}), got {tuple(q.shape)}")
    device, dtype = truth.origins.device, truth.origins.dtype
    q = q.to(device=device, dtype=dtype)
    N, n = q.shape
    tool_ids = torch.as_tensor(tools, dtype=torch.long).reshape(-1)
    T = truth.tools_nominal.shape[0]
    if tool_ids.numel() == 0:
        raise ValueError("simulate: no tool configurations given")
    bad = (tool_ids < 0) | (tool_ids >= T)
    if bad.any():
        raise ValueError(f"simulate: tool index {int(tool_ids[bad][0])} out of range, the truth has {T} tools")
    if directions is None:
        s = approach_directions(q)
    else:
        s = torch.as_tensor(directions).to(device=device, dtype=dtype)
        if s.shape != q.shape:
            raise ValueError(f"simulate: directions must have shape {tuple(q.shape)}, got {tuple(s.shape)}")
        odd = first_invalid_direction(s)
        if odd is not None:
            r, c = odd
            raise ValueError(f"simulate: direction at pose {r}, joint {c + 1} is {float(s[r, c])}, expected -1, 0 or +1")
    Tn = tool_ids.numel()
    qq, ss = q.repeat(Tn, 1), s.repeat(Tn, 1)
    tool = tool_ids.to(device).repeat_interleave(N)
    pose = torch.arange(N, device=device).repeat(Tn)
    g = torch.Generator().manual_seed(int(seed))
    R = qq.shape[0]
    with torch.no_grad():
        exact = truth.points(qq, tool, ss)
        if noise is None:
            v = torch.zeros_like(qq)
            xyz = exact.clone()
        else:
            z_v = torch.randn(R, n, generator=g, dtype=torch.float64).to(device=device, dtype=dtype)
            z_m = torch.randn(R, 3, generator=g, dtype=torch.float64).to(device=device, dtype=dtype)
            v = z_v * noise.joint_variance(ss).to(qq).sqrt()
            xyz = truth.points(qq, tool, ss, v) + z_m * noise.sigma_m
    return Measurements(
        qq, tool, xyz, ss, pose, torch.arange(1, R + 1), has_direction=True, source="simulated",
        extra={"v": v, "xyz_exact": exact},
    )


def noise_free_points(truth: TruthRobot, data: Measurements) -> torch.Tensor:
    """The truth's exact points (R, 3) m for each row's command, tool and direction (v = 0, ξ = 0).

    Directions are used when ``data.has_direction`` (backlash included), else
    ignored. Use it to score a model against truth on any data set.
    """
    device = truth.origins.device
    s = data.direction.to(device) if data.has_direction else None
    with torch.no_grad():
        return truth.points(data.q.to(device), data.tool.to(device), s)
