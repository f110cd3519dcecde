"""The tool-tip modeled-error slope hbar of Paper I (13)-(30): closed form, autograd, the paper's form, FD."""

import numpy as np
import pytest
import torch

import torchcal
import torchcal.sim
from conftest import XYZCB_TOOLS, random_commands, randomize
from torchcal.identify.slope import (cat_contexts, context_rows, machine_slope_context, machine_slope_norm_jacobian,
                                     machine_slope_terms, model_slopes, modeled_error, robot_context_rows,
                                     robot_slope_context, robot_slope_terms, robot_slopes, robot_slopes_differentiable,
                                     slope_norms, slope_points, tool_vectors, worst_points)
from torchcal.models.machine import MachineModel
from torchcal.models.robot import RobotModel

TOOLS = XYZCB_TOOLS  # Paper I (32)



@pytest.fixture(autouse=True)
def _single_thread(one_thread):
    """Tiny tensors: torch's intra-op threads only contend on the shared 2-core machine."""


def machine_model(machine, coef_fn, orders=4):
    model = MachineModel(machine, TOOLS, orders=orders)
    with torch.no_grad():
        model.axis_errors.coef.copy_(coef_fn(model.axis_errors.coef.shape) * model.axis_errors.mask)
    return model


def paper_slopes(model, q, l_t):
    """hbar by Paper I (25)-(30), (35), (42)-(47), written out with numpy (sign of (23): e = p_nom - p_AP)."""
    ae = model.axis_errors
    with torch.no_grad():
        dq = ae.delta(q).numpy()
        D = ae.slopes(q).numpy()
    q = q.numpy()
    half = 0.5 * (ae.limits[:, 1] - ae.limits[:, 0]).numpy()
    out = np.zeros((q.shape[0], 5, 3))
    for b in range(q.shape[0]):
        C, B = q[b, 3], q[b, 4]
        ID = np.eye(5) + D[b]
        Jv_ap, Jv_nom = ID[:3], np.eye(5)[:3]
        cA = C + dq[b, 3]
        Jw_ap = np.outer([-np.sin(cA), np.cos(cA), 0.0], ID[4]) + np.outer([0.0, 0.0, 1.0], ID[3])  # (27), (42)-(44)
        Jw_nom = np.zeros((3, 5))
        Jw_nom[:, 4] = [-np.sin(C), np.cos(C), 0.0]
        Jw_nom[2, 3] = 1.0  # (47)
        Rn = np.array([[np.cos(C), -np.sin(C), 0], [np.sin(C), np.cos(C), 0], [0, 0, 1]]) @ \
            np.array([[np.cos(B), 0, np.sin(B)], [0, 1, 0], [-np.sin(B), 0, np.cos(B)]])
        pt = Rn @ np.array([0.0, 0.0, l_t])
        for i in range(5):
            dw, dv = Jw_nom[:, i] - Jw_ap[:, i], Jv_nom[:, i] - Jv_ap[:, i]
            out[b, i] = (np.cross(dw, pt) + dv) * half[i]  # S(a) x = a x x, (29)-(30)
    return out


def test_equals_the_papers_form_where_its_assumption_holds(machine):
    """(25) assumes R_AP = R_nom: exact when only X, Y, Z carry tables, and where the rotary tables are zero."""
    g = torch.Generator().manual_seed(0)
    lin = machine_model(machine, lambda s: torch.cat([torch.randn((3,) + s[1:], generator=g),
                                                      torch.zeros((2,) + s[1:])]) * 1e-4)
    q = torchcal.sim.quasi_random_commands(machine.joint_map.limits, 16, 0)
    ours = model_slopes(lin, q, 1).detach().numpy()
    assert np.abs(ours).max() > 1e-5
    assert np.allclose(ours, -paper_slopes(lin, q, 0.5009), atol=1e-14)

    def rot(s):  # f_CX, f_BX odd in qbar_X (c1, c3): zero at mid X, slopes there are not
        c = torch.zeros(s)
        c[3, 0, 1], c[3, 0, 3], c[4, 0, 1], c[4, 0, 3] = 2e-5, -1e-5, 3e-5, 1e-5
        c[0, 4, 2] = 1e-4
        return c

    model = machine_model(machine, rot)
    q[:, 0] = machine.joint_map.limits[0].mean()
    ours = model_slopes(model, q, 1).detach().numpy()
    assert np.abs(ours[:, 0]).max() > 1e-6
    assert np.allclose(ours, -paper_slopes(model, q, 0.5009), atol=1e-14)


def test_exact_slope_keeps_the_term_the_paper_drops(machine):
    """A constant C offset rotates the tool: its slope along C is |dq_C| |J_C| half range, (25) gives 0."""
    def const_c(s):
        c = torch.zeros(s)
        c[3, 3, 0] = 1e-4
        return c

    model = machine_model(machine, const_c)
    q = torchcal.sim.quasi_random_commands(machine.joint_map.limits, 8, 1)
    ours = model_slopes(model, q, 1).detach()
    assert np.abs(paper_slopes(model, q, 0.5009)[:, 3]).max() == 0.0
    half_c = 0.5 * float(machine.joint_map.limits[3].diff())
    expected = 1e-4 * 0.5009 * torch.sin(q[:, 4]).abs() * half_c  # |Rz(C + d) - Rz(C)| on a radius l sin B, to O(d^2)
    assert torch.allclose(ours[:, 3].norm(dim=1), expected, rtol=1e-3)


def assert_slopes_match_central_differences(model, q, tool, h):
    """h (B, n, 3) against central differences of the modeled error along each axis, scaled to half its range."""
    lim = model.command_limits
    half = 0.5 * (lim[:, 1] - lim[:, 0])
    n = q.shape[1]
    for i in range(n):
        d = torch.zeros(n)
        d[i] = 1e-6
        with torch.no_grad():
            fd = (modeled_error(model, q + d, tool) - modeled_error(model, q - d, tool)) / 2e-6 * half[i]
        assert torch.allclose(fd, h[:, i], atol=1e-9), i


def test_machine_slopes_match_finite_differences_and_autograd(machine):
    g = torch.Generator().manual_seed(2)
    model = machine_model(machine, lambda s: torch.randn(s, generator=g) * 1e-4)
    q = torchcal.sim.quasi_random_commands(machine.joint_map.limits, 6, 2)
    h = model_slopes(model, q, 0).detach()
    assert torch.allclose(model_slopes(model, q, 0, method="autograd").detach(), h, atol=1e-15)
    assert_slopes_match_central_differences(model, q, TOOLS[0], h)


def test_robot_slopes_match_finite_differences(fanuc, tools_m):
    model = randomize(RobotModel(fanuc, tools_m, orders=3, backlash=True), 3)
    q = random_commands(fanuc, 4, 3)
    h = model_slopes(model, q, 2).detach()
    assert h.shape == (4, 6, 3)
    assert_slopes_match_central_differences(model, q, tools_m[2], h)
    # the nominal robot has no modeled error and no slope; the base correction is not a machine error
    nominal = RobotModel(fanuc, tools_m, orders=3)
    with torch.no_grad():
        nominal.base.twist.fill_(1e-2)
    assert float(model_slopes(nominal, q).detach().abs().max()) == 0.0


@pytest.mark.slow  # nested autograd over a robot with compliance: ~20 s (the closed form's check below is fast)
def test_robot_fast_path_matches_autograd(monkeypatch):
    """Robots: hbar and the penalty's parameter Jacobian by central differences of the closed-form chain
    (what fits use) against nested autograd, with compliance (gravity torques) and backlash in the model."""
    from torchcal.identify.constrained import SlopePenalty
    from torchcal.identify.layout import ParameterLayout

    robot = torchcal.load_robot("abb_irb120")
    tools = torch.tensor([[0.05, 0.0, 0.1], [0.0, 0.04, 0.12]], dtype=torch.float64)
    model = RobotModel(robot, tools, orders=3, backlash=True, compliance={"mode": "gravity", "joints": [1, 2, 4]})
    g = torch.Generator().manual_seed(0)
    with torch.no_grad():
        for p in model.parameters():
            p.copy_(torch.randn(p.shape, generator=g, dtype=p.dtype) * 1e-3)
        model.compliance.coef.mul_(1e-2)  # rad per N·m
    q = slope_points(model.command_limits, 8, seed=1)
    P = tool_vectors(model)
    with torch.no_grad():
        h_fast = robot_slope_terms(model, q, P)[0]
        h_closed = robot_slopes(model, q, P)
        assert torch.equal(slope_norms(model, q), h_closed.norm(dim=-1))  # no_grad routes robots to the closed form
    h_ad = model_slopes(model, q, 0).detach()  # grad enabled: nested autograd
    assert float((h_fast[0] - h_ad).abs().max()) < 1e-8 * float(h_ad.abs().max())  # measured 2e-9
    assert float((h_closed[0] - h_ad).abs().max()) < 1e-12 * float(h_ad.abs().max())  # measured 2e-14
    layout = ParameterLayout(model)
    x = layout.get()
    pen = SlopePenalty(model, q, c=1e-4)
    with torch.no_grad():
        active = (pen.norms(x, layout) > pen.c).nonzero()
    assert active.shape[0] > 50
    active = active[torch.randperm(active.shape[0], generator=g)[:60]]  # autograd's Jacobian costs ~0.3 s an entry
    J_fast = pen._jacobian(x, layout, active)
    import torchcal.identify.constrained as constrained

    monkeypatch.setattr(constrained, "robot_fast_path", lambda model: False)
    J_ad = pen._jacobian(x, layout, active)
    assert float((J_fast - J_ad).abs().max()) < 1e-7 * float(J_ad.abs().max())  # measured 8e-9


def test_norm_jacobian_matches_autograd(machine):
    g = torch.Generator().manual_seed(4)
    model = machine_model(machine, lambda s: torch.randn(s, generator=g) * 1e-4)
    q = torchcal.sim.quasi_random_commands(machine.joint_map.limits, 5, 4)
    axis = torch.tensor([0, 2, 3, 4, 3])
    nrm, J = machine_slope_norm_jacobian(model, q, TOOLS[1], axis)
    coef = model.axis_errors.coef.detach()
    from torch.func import functional_call, jacrev

    def norms(c):
        params = {k: v.detach() for k, v in model.named_parameters()}
        params["axis_errors.coef"] = c

        class W(torch.nn.Module):
            def __init__(self):
                super().__init__()
                self.model = model

            def forward(self, qq):
                return model_slopes(self.model, qq, TOOLS[1][None], method="autograd")

        h = functional_call(W(), {f"model.{k}": v for k, v in params.items()}, (q,))
        return h[torch.arange(5), axis].norm(dim=-1)

    assert torch.allclose(norms(coef), nrm, atol=1e-16)
    assert torch.allclose(jacrev(norms)(coef), J, atol=1e-12)


def test_slope_points_cover_the_whole_box():
    lim = torch.tensor([[0.0, 1.0], [-2.0, 2.0], [5.0, 6.0]])
    pts = slope_points(lim, count=32, seed=0)
    assert pts.shape == (32 + 6 * 8 + 8, 3)
    assert bool(((pts >= lim[:, 0]) & (pts <= lim[:, 1])).all())
    corners = pts[-8:]
    assert bool(((corners == lim[:, 0]) | (corners == lim[:, 1])).all())
    on_face = ((pts == lim[:, 0]) | (pts == lim[:, 1])).any(1)
    assert int(on_face.sum()) == 6 * 8 + 8
    assert torch.equal(slope_points(lim, 32, 0), pts)
    other = slope_points(lim, 32, 1)
    assert float(torch.cdist(other[:32], pts[:32]).min()) > 0


def test_worst_points_climb_to_a_larger_slope(machine):
    g = torch.Generator().manual_seed(5)
    model = machine_model(machine, lambda s: torch.randn(s, generator=g) * 1e-4)
    q0 = torchcal.sim.quasi_random_commands(machine.joint_map.limits, 8, 5)
    q1 = worst_points(model, q0, steps=15)
    lim = machine.joint_map.limits
    assert bool(((q1 >= lim[:, 0] - 1e-12) & (q1 <= lim[:, 1] + 1e-12)).all())
    with torch.no_grad():
        before = slope_norms(model, q0).amax(dim=(0, 2))
        after = slope_norms(model, q1).amax(dim=(0, 2))
    assert bool((after >= before - 1e-12).all()) and float(after.max()) > float(before.max())


def test_robot_constant_reference_bounds_only_the_joint_dependent_terms():
    """slope_reference='constant': constant (DH-like) errors have no slope; a c1 term has the same one either way
    when it is the only error."""
    import torchcal
    from torchcal.identify.slope import model_slopes, slope_points

    robot = torchcal.load_robot("abb_irb120")
    m = torchcal.RobotModel(robot, torch.tensor([[0.0, 0.0, 0.1]], dtype=torch.float64), orders=2)
    q = slope_points(m.command_limits, 32, 0)
    g = torch.Generator().manual_seed(0)
    with torch.no_grad():
        m.joint_errors.coef[..., 1] = 1e-4 * torch.randn(m.joint_errors.coef[..., 1].shape, generator=g,
                                                         dtype=torch.float64)
    m.slope_reference = "constant"
    linear_only = model_slopes(m, q, 0).detach()
    m.slope_reference = "nominal"
    assert torch.allclose(model_slopes(m, q, 0).detach(), linear_only, atol=1e-12)
    with torch.no_grad():
        m.joint_errors.coef[..., 0] = 1e-3 * torch.randn(m.joint_errors.coef[..., 0].shape, generator=g,
                                                         dtype=torch.float64)
        m.joint_errors.coef[..., 1] = 0.0
    assert model_slopes(m, q, 0).detach().norm(dim=-1).max() > 1e-3  # constants move the tool with the joints
    m.slope_reference = "constant"
    assert model_slopes(m, q, 0).detach().norm(dim=-1).max() < 1e-12


def _irb120(compliance=True, orders=3, seed=0):
    robot = torchcal.load_robot("abb_irb120")
    tools = torch.tensor([[0.05, 0.0, 0.1], [0.0, 0.04, 0.12]], dtype=torch.float64)
    model = RobotModel(robot, tools, orders=orders, backlash=True,
                       compliance={"mode": "gravity", "joints": [1, 2, 4]} if compliance else False)
    g = torch.Generator().manual_seed(seed)
    with torch.no_grad():
        for p in model.parameters():
            p.copy_(torch.randn(p.shape, generator=g, dtype=p.dtype) * 1e-3)
        if compliance:
            model.compliance.coef.mul_(1e-2)  # rad per N·m
    return model


@pytest.mark.parametrize("compliance", [True, False])
def test_robot_closed_form_slope_matches_autograd(compliance):
    """robot_slopes (joint axes, error-series velocities, the gravity deflection's configuration slope) against
    nested autograd of the modeled error, at points over the whole box, corners included."""
    model = _irb120(compliance)
    q = slope_points(model.command_limits, 16, seed=3)
    P = tool_vectors(model)
    with torch.no_grad():
        h = robot_slopes(model, q, P)
    for t in range(P.shape[0]):
        h_ad = model_slopes(model, q, t).detach()
        assert float((h[t] - h_ad).abs().max()) < 1e-12 * float(h_ad.abs().max())


def test_slope_contexts_change_nothing(machine):
    """The parameter-free parts cached per point set (contexts), their rows and their concatenation give the
    values computed from scratch: bitwise for whole sets, to round-off for rows."""
    g = torch.Generator().manual_seed(7)
    mm = machine_model(machine, lambda s: torch.randn(s, generator=g) * 1e-4)
    q = slope_points(machine.joint_map.limits, 16, seed=2)
    P = tool_vectors(mm)
    with torch.no_grad():
        ctx = machine_slope_context(mm, q, P)
        assert torch.equal(machine_slope_terms(mm, q, P, context=ctx)["hbar"], machine_slope_terms(mm, q, P)["hbar"])
        both = cat_contexts(machine_slope_context(mm, q[:10], P), machine_slope_context(mm, q[10:], P))
        assert torch.equal(machine_slope_terms(mm, q, P, context=both)["hbar"], machine_slope_terms(mm, q, P)["hbar"])
        rows = torch.tensor([1, 7, 30])
        sub = machine_slope_terms(mm, q[rows], P[1:], context=context_rows(ctx, rows, slice(1, 2)))["hbar"]
        assert torch.allclose(sub, machine_slope_terms(mm, q[rows], P[1:])["hbar"], rtol=1e-13, atol=1e-20)
    robot = _irb120()
    from torchcal.identify.layout import ParameterLayout

    layout = ParameterLayout(robot)
    q = slope_points(robot.command_limits, 8, seed=2)
    P = tool_vectors(robot)
    with torch.no_grad():
        ctx = robot_slope_context(robot, q, P)
        h0, d0 = robot_slope_terms(robot, q, P, layout)
        h1, d1 = robot_slope_terms(robot, q, P, layout, context=ctx)
        assert torch.equal(h0, h1) and torch.equal(d0, d1)  # the same operations as RobotModel._parts
        assert torch.equal(robot_slopes(robot, q, P, ctx), robot_slopes(robot, q, P))
        both = cat_contexts(robot_slope_context(robot, q[:20], P), robot_slope_context(robot, q[20:], P))
        assert torch.equal(robot_slope_terms(robot, q, P, context=both)[0], h0)
        assert torch.equal(robot_slopes(robot, q, P, both), robot_slopes(robot, q, P))
        rows = torch.tensor([0, 5, 40])
        h2, d2 = robot_slope_terms(robot, q[rows], P, layout, context=robot_context_rows(ctx, rows))
        assert torch.allclose(h2, h0[:, rows], rtol=1e-12, atol=1e-18)
        assert torch.allclose(d2, d0[:, rows], rtol=1e-12, atol=1e-18)


def test_worst_points_climb_on_a_robot():
    """Robots climb the central-difference slope with first-order autograd (not nested): the points reached
    have a larger slope, by the closed form too."""
    model = _irb120(orders=4, seed=3)
    q0 = slope_points(model.command_limits, 8, seed=9)[:8]
    with torch.no_grad():
        before = slope_norms(model, q0).amax(dim=(0, 2))
    h = robot_slopes_differentiable(model, q0, tool_vectors(model)).detach()
    assert torch.allclose(h.norm(dim=-1), slope_norms(model, q0), rtol=1e-7)
    q1 = worst_points(model, q0, steps=10)
    with torch.no_grad():
        after = slope_norms(model, q1).amax(dim=(0, 2))
    assert bool((after >= before - 1e-12).all()) and float((after - before).max()) > 0


def test_sensor_rig_slope_is_its_robots_at_the_sensor_origin(fanuc):
    """A sensor rig (Paper III): the bound is on its robot model's error, the tool point the sensor origin."""
    from torchcal.models.sensor_rig import SensorRig

    mount = torch.eye(4, dtype=torch.float64)
    mount[:3, 3] = torch.tensor([0.02, -0.01, 0.15], dtype=torch.float64)
    rig = SensorRig.for_robot(fanuc, orders=2, mount=mount)
    g = torch.Generator().manual_seed(1)
    with torch.no_grad():
        for p in rig.parameters():
            p.copy_(torch.randn(p.shape, generator=g, dtype=p.dtype) * 1e-3)
    assert torch.equal(tool_vectors(rig), mount[:3, 3][None])
    q = slope_points(rig.command_limits, 8, seed=4)
    with torch.no_grad():
        assert torch.equal(slope_norms(rig, q), slope_norms(rig.model, q, mount[:3, 3]))
    h_ad = model_slopes(rig.model, q, mount[:3, 3]).detach()
    assert torch.allclose(slope_norms(rig, q)[0], h_ad.norm(dim=-1), rtol=1e-10)
