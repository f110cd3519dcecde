"""Simulated fleets: many units of one robot type, each with its own truth, some with a damaged gearbox.

Units of one type differ in everything Paper II Table 1 lists, not only in
the joint-dependent errors: their constant geometry (mastering, link
lengths and twists) varies from unit to unit around the type's values. Our
reading, stated because the papers describe one robot: each unit's
constants are the type's (for the FANUC, Paper II Table 9) plus a normal
unit-to-unit spread of :data:`CONSTANT_SPREAD` (about a third of Table 9's
largest values), and its joint-dependent and unmodelled errors are drawn
from its own seed.

A *damaged gearbox* (a crash, a worn strain-wave gear) adds lost motion
(backlash) to one joint and multiplies its transmission error (strain-wave
amplitudes): :data:`GEARBOX_DAMAGE`.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Sequence

import numpy as np
import torch

from ..core import units
from .truth import TruthRobot

CONSTANT_SPREAD = {"mastering_deg": 0.02, "shift_mm": 0.1, "tilt_deg": 0.01}
"""Unit-to-unit standard deviation of the constant errors: mastering (deg), origin shift (mm), origin tilt (deg)."""

GEARBOX_DAMAGE = {"backlash_deg": 0.08, "wave": 4.0}
"""A damaged gearbox: 0.08 deg more lost motion (wear opens the clearance: 4-16x the type's 0.005-0.02 deg) and
strain-wave (transmission error) amplitudes x4."""


@dataclass
class FleetTruth:
    """The truths of a simulated fleet: ``truths`` (one :class:`TruthRobot` per unit), ``damaged``: {unit: joint}."""

    truths: list
    damaged: dict

    def __len__(self) -> int:
        return len(self.truths)


def unit_spread(truth: TruthRobot, seed: int, spread: dict | None = None) -> TruthRobot:
    """Add a unit's own deviation of the constant errors (:data:`CONSTANT_SPREAD`) to ``truth`` in place."""
    s = CONSTANT_SPREAD if spread is None else {**CONSTANT_SPREAD, **spread}
    g = np.random.default_rng([int(seed), 7])
    n = truth.n
    with torch.no_grad():
        f64 = dict(dtype=torch.float64, device=truth.mastering.device)
        truth.mastering += torch.tensor(g.normal(0.0, s["mastering_deg"], n), **f64) * units.DEG
        shift = torch.tensor(g.normal(0.0, s["shift_mm"], (n, 3)), **f64) * units.MM
        shift[:, 1] = 0.0  # DH form: no shift along the joint frame's y (as Paper II's Δa, Δd)
        truth.origin_shift += shift
        tilt = torch.tensor(g.normal(0.0, s["tilt_deg"], (n, 3)), **f64) * units.DEG
        tilt[:, 2] = 0.0
        truth.origin_tilt += tilt
    return truth


def damage_gearbox(truth: TruthRobot, joint: int, damage: dict | None = None) -> TruthRobot:
    """Give joint ``joint`` (0-based) of ``truth`` a damaged gearbox (:data:`GEARBOX_DAMAGE`), in place."""
    d = GEARBOX_DAMAGE if damage is None else {**GEARBOX_DAMAGE, **damage}
    with torch.no_grad():
        truth.backlash[joint] += d["backlash_deg"] * units.DEG
        truth.wave_amp[joint] *= d["wave"]
    return truth


def fleet_truths(robot, tools, count: int, seed: int = 0, damaged: dict | Sequence[int] = (),
                 kind: str = "fanuc_paper2", spread: dict | None = None, damage: dict | None = None) -> FleetTruth:
    """``count`` truths of one robot type, unit k drawn from seed ``seed * 100003 + k``.

    robot, tools: as for :class:`TruthRobot`; damaged: {unit: joint} or units
    (joint 2, the FANUC's J3 reducer, by default) with a damaged gearbox;
    kind: 'fanuc_paper2' (Paper II's FANUC constants and magnitudes) or
    'random' (:meth:`TruthRobot.random`, any robot); spread / damage: override
    :data:`CONSTANT_SPREAD` / :data:`GEARBOX_DAMAGE`.
    """
    if kind not in ("fanuc_paper2", "random"):
        raise ValueError(f"fleet_truths: kind must be 'fanuc_paper2' or 'random', got {kind!r}")
    hurt = dict(damaged) if isinstance(damaged, dict) else {int(u): 2 for u in damaged}
    bad = [u for u in hurt if not 0 <= u < count]
    if bad:
        raise ValueError(f"fleet_truths: damaged units {bad} outside 0..{count - 1}")
    out = []
    for k in range(count):
        s = int(seed) * 100003 + k
        t = TruthRobot.fanuc_paper2(robot, tools, s) if kind == "fanuc_paper2" else TruthRobot.random(robot, tools, s)
        unit_spread(t, s, spread)
        if k in hurt:
            damage_gearbox(t, hurt[k], damage)
        out.append(t)
    return FleetTruth(out, hurt)


__all__ = ["CONSTANT_SPREAD", "FleetTruth", "GEARBOX_DAMAGE", "damage_gearbox", "fleet_truths", "unit_spread"]
