"""parameters.csv and the report name each entry's unit: a gravity compliance is a deflection per N·m."""

from __future__ import annotations

import math

import torch

import torchcal


def test_a_compliance_per_torque_is_labelled_per_newton_metre():
    """IRB 120 with gravity compliance (its URDF inertials): the 'tau' entries are rad per N·m, shown in deg per
    N·m (they read 'deg'; the real run's J5 value 1.49 beside 0.012 for J2 / J3 looked like a huge angle); the
    joint terms stay deg and mm, and the values are converted as their units say."""
    from torchcal.analysis.identifiability import identifiability
    from torchcal.app.fit import parameter_uncertainty
    from torchcal.report.model_sections import _display

    robot = torchcal.load_robot("abb_irb120")
    tools = torch.tensor([[0.0, 0.0, 0.12], [0.075, 0.09, 0.21], [0.15, 0.0, 0.12]], dtype=torch.float64)
    model = torchcal.RobotModel(robot, tools, orders=0, compliance="gravity")
    with torch.no_grad():
        model.compliance.coef.fill_(1e-5)
    q = torchcal.sim.quasi_random_commands(robot.joint_map.limits, 40, 0)
    data = torchcal.simulate(torchcal.TruthRobot.random(robot, tools, 0), q, [0, 1, 2], None, 0)
    rows = {r["name"]: r for r in parameter_uncertainty(identifiability(model, data))}
    tau = [r for n, r in rows.items() if n.startswith("compliance.") and n.endswith(".tau")]
    assert tau and all(r["unit"] == "deg/(N·m)" for r in tau)
    assert all(math.isclose(r["value"], math.degrees(1e-5), rel_tol=1e-12) for r in tau)
    assert {r["unit"] for n, r in rows.items() if not n.startswith("compliance.")} == {"deg", "mm"}
    shown, unit = _display([1e-5, 1e-5, 1e-3], ["angle", "angle", "length"],
                           ["compliance.joint2.tau", "joint1.eps_x.c0", "joint1.delta_x.c0"])
    assert unit == ["deg/(N·m)", "deg", "mm"] and math.isclose(shown[0], math.degrees(1e-5))
