"""Fine-grained joint-angle tables: interpolation, held ends, Jacobians, persistence, smoothness block, recovery."""

import math

import numpy as np
import pytest
import torch
from hypothesis import given, settings
from hypothesis import strategies as st

import torchcal
from torchcal.error_models import FineJointErrors, SmoothnessPenalty, hat_weights
from torchcal.identify import ParameterLayout
from torchcal.models.robot import RobotModel

D = torch.float64


def test_table_interpolates_linearly_between_knots_and_holds_its_ends():
    fe = FineJointErrors(torch.tensor([-0.3]), torch.tensor([0.7]), spacing=0.1)
    knots = fe.knots(0)
    assert fe.counts.tolist() == [11] and torch.allclose(knots[[0, -1]], torch.tensor([-0.3, 0.7], dtype=D))
    vals = torch.sin(7 * knots)
    with torch.no_grad():
        fe.values[0, : knots.numel()] = vals
    # at the knots: the values; between: numpy's linear interpolation (an independent reference)
    th = torch.linspace(-0.3, 0.7, 97, dtype=D)[:, None]
    ref = np.interp(th[:, 0].numpy(), knots.numpy(), vals.numpy())
    assert np.abs(fe(th)[:, 0].detach().numpy() - ref).max() < 1e-14
    # outside the covered range: the end value, and no slope
    out = torch.tensor([[-2.0], [-0.31], [0.71], [5.0]], dtype=D)
    assert torch.allclose(fe(out)[:, 0], vals[[0, 0, -1, -1]])
    assert torch.equal(fe.slope(out), torch.zeros_like(out))


@settings(max_examples=30, deadline=None)
@given(st.floats(-3, 3), st.floats(0.01, 0.4))
def test_weights_sum_to_one_and_slope_matches_finite_difference(theta, h):
    lower, step, counts = torch.tensor([-1.0], dtype=D), torch.tensor([h], dtype=D), torch.tensor([int(2 / h) + 2])
    w, dw = hat_weights(torch.tensor([[theta]], dtype=D), lower, step, counts, int(counts) + 1)
    assert abs(float(w.sum()) - 1.0) < 1e-12 and float(w.min()) >= -1e-15
    hi = float(lower + step * (counts - 1))
    eps = 1e-7
    # away from knots (where the slope jumps) the derivative is the finite difference
    t = (theta + 1.0) / h
    if abs(t - round(t)) > 1e-4 and abs(theta - hi) > 1e-4 and abs(theta + 1.0) > 1e-4:
        wp, _ = hat_weights(torch.tensor([[theta + eps]], dtype=D), lower, step, counts, int(counts) + 1)
        wm, _ = hat_weights(torch.tensor([[theta - eps]], dtype=D), lower, step, counts, int(counts) + 1)
        assert torch.allclose((wp - wm) / (2 * eps), dw, atol=1e-5 / h)


@pytest.fixture(scope="module")
def ur10():
    return torchcal.load_robot("ur10")


def _model(robot, seed=0, spacing=0.2):
    g = torch.Generator().manual_seed(seed)
    q = (torch.rand(60, 6, generator=g, dtype=D) - 0.5) * 3
    fe = FineJointErrors.from_data(q, spacing, joint_names=robot.chain.joint_names)
    tools = torch.tensor([[0.01, -0.02, 0.09]], dtype=D)
    model = RobotModel(robot, tools, orders=1, fine=fe)
    with torch.no_grad():
        fe.values.copy_(torch.randn(fe.values.shape, generator=g, dtype=D) * 1e-3 * fe.mask)
        model.joint_errors.coef.copy_(torch.randn(model.joint_errors.coef.shape, generator=g, dtype=D) * 1e-4
                                      * model.joint_errors.mask)
    return model, q


def test_point_jacobian_of_the_tables_matches_autograd(ur10):
    model, q = _model(ur10)
    q = q[:7] * 1.1  # some beyond the covered range: held ends, zero Jacobian outside
    tool = torch.zeros(len(q), dtype=torch.long)
    _, J = model.point_jacobians(q, tool)
    vals = model.fine.values

    def pts(v):
        return torch.func.functional_call(model, {"fine.values": v}, (q, tool))

    Jref = torch.autograd.functional.jacobian(pts, vals.detach().clone())  # (B, 3, n, K)
    assert J["fine.values"].shape == Jref.shape
    assert torch.allclose(J["fine.values"], Jref, atol=1e-12)


def test_flange_jacobian_includes_the_table_slope(ur10):
    model, q = _model(ur10, seed=1)
    q = q[:5] * 0.9  # inside the tables (at an end the slope is one-sided)
    _, J = model.flange_jacobian(q)
    eps = 1e-6
    for j in range(6):
        dq = torch.zeros_like(q)
        dq[:, j] = eps
        Fp, Fm = model.flange(q + dq, base=False), model.flange(q - dq, base=False)
        F = model.flange(q, base=False)
        dp = (Fp[:, :3, 3] - Fm[:, :3, 3]) / (2 * eps)
        body = (F[:, :3, :3].transpose(1, 2) @ dp[..., None])[..., 0]
        assert torch.allclose(J[:, :3, j], body, atol=1e-6), j
    # the slope matters: the same model without the table gives another Jacobian
    plain = RobotModel(ur10, model.tools.nominal, orders=1)
    plain.load_state_dict({k: v for k, v in model.state_dict().items() if not k.startswith("fine")}, strict=False)
    assert (plain.flange_jacobian(q)[1] - J).abs().max() > 1e-4


def test_spec_round_trip_and_off_means_absent(ur10):
    model, q = _model(ur10, seed=2)
    spec = model.spec()
    assert "fine" in spec and "fine" not in RobotModel(ur10, model.tools.nominal, orders=1).spec()
    back = RobotModel.from_spec(spec, ur10)
    back.load_state_dict(model.state_dict())
    tool = torch.zeros(len(q), dtype=torch.long)
    assert torch.equal(back.points(q * 1.2, tool), model.points(q * 1.2, tool))
    names = [g.name for g in back.parameter_groups()]
    assert names[-1] == "fine.values"


def test_smoothness_block_zero_on_lines_and_jacobian_with_pinned_entries(ur10):
    model, _ = _model(ur10, seed=3)
    fe = model.fine
    with torch.no_grad():  # a straight line in every table: no curvature
        for i in range(6):
            fe.values[i, : int(fe.counts[i])] = 1e-4 * (i + 1) * fe.knots(i)
    block = SmoothnessPenalty(fe, 1e-5)
    layout = ParameterLayout(model, fixed=("joint_errors", "base", "tools"))
    x = layout.get()
    r, _ = block.linearize(x, layout)
    assert r.abs().max() < 1e-9 and r.numel() == int((fe.counts - 2).sum())
    # pin a few entries: the residual still sees them (at their value), the Jacobian drops them
    drop = torch.zeros(layout.size, dtype=torch.bool)
    drop[[0, 5, 40]] = True
    small = layout.without(drop)
    x2 = small.get() + torch.randn(small.size, dtype=D, generator=torch.Generator().manual_seed(0)) * 1e-4
    r2, J2 = block.linearize(x2, small)
    Jref = torch.autograd.functional.jacobian(lambda z: block.linearize(z, small)[0], x2)
    assert torch.allclose(J2, Jref, atol=1e-9) and J2.shape == (r.numel(), small.size)
    assert r2.abs().max() > 1.0  # curvature of 1e-4 rad per knot against sigma 1e-5


def test_fit_recovers_a_fine_grained_angle_error(ur10):
    """Truth: the nominal UR10 whose joints carry periodic errors of period 0.4 rad, written without torchcal's model.

    An order-1 geometric model alone cannot follow them; with 0.1 rad tables the held-out error drops several-fold.
    """
    g = torch.Generator().manual_seed(5)
    q = (torch.rand(240, 6, generator=g, dtype=D) - 0.5) * 2.4
    amp = torch.tensor([2e-4, 3e-4, 2e-4, 0.0, 0.0, 0.0], dtype=D)
    theta = q + amp * torch.sin(2 * math.pi * q / 0.4 + torch.arange(6))
    F = ur10.chain.fk(theta)
    tool = torch.tensor([0.0, 0.0, 0.1], dtype=D)
    xyz = (F[:, :3, :3] @ tool) + F[:, :3, 3]
    data = torchcal.Measurements.from_tensors(q, 0, xyz)
    train, test = data.subset(torch.arange(180)), data.subset(torch.arange(180, 240))
    noise = torchcal.NoiseModel(1e-6, torch.zeros(6, dtype=D), torch.zeros(6, dtype=D))

    def held_out(fine):
        model = RobotModel(ur10, tool[None], orders=1, fine=fine)
        blocks = [SmoothnessPenalty(model.fine, 1e-4)] if fine is not None else []
        torchcal.fit(model, train, noise, blocks=blocks, max_iter=5)
        with torch.no_grad():
            return float((model.points(test.q, test.tool) - test.xyz).norm(dim=1).mean())

    geo = held_out(None)
    fine = held_out(FineJointErrors.from_data(q, 0.1, joints=range(3), joint_names=ur10.chain.joint_names))
    assert geo > 1e-4 and fine < geo / 4, (geo, fine)
