"""Geodesic acceleration's pieces (torchcal.identify.lm): the second directional derivative and the test that
keeps an acceleration, against exact derivatives and the test's own invariance."""

from __future__ import annotations

import torch
from hypothesis import given, settings
from hypothesis import strategies as hst
from torch.func import functional_call, jvp

import torchcal
import torchcal.sim
from torchcal.identify.lm import GEODESIC_H, acceleration_kept, second_directional


@settings(max_examples=30, deadline=None)
@given(seed=hst.integers(0, 2**31 - 1), h=hst.floats(1e-3, 1.0))
def test_second_directional_derivative_is_exact_for_a_quadratic_residual(seed, h):
    """r(x) = c + B x + (x^T Q_i x) / 2 per entry: its second directional derivative along delta is delta^T Q_i
    delta, whatever h."""
    g = torch.Generator().manual_seed(seed)
    n, k = 5, 7
    c, B = torch.randn(k, generator=g, dtype=torch.float64), torch.randn(k, n, generator=g, dtype=torch.float64)
    Q = torch.randn(k, n, n, generator=g, dtype=torch.float64)
    Q = Q + Q.transpose(1, 2)
    x, d = torch.randn(n, generator=g, dtype=torch.float64), torch.randn(n, generator=g, dtype=torch.float64)

    def r(x):
        return c + B @ x + 0.5 * torch.einsum("i,kij,j->k", x, Q, x)

    J_d = B @ d + torch.einsum("i,kij,j->k", x, Q, d)
    exact = torch.einsum("i,kij,j->k", d, Q, d)
    r0, rh = r(x), r(x + h * d)
    got = second_directional(r0, rh, r0 + J_d, h)
    # exact in exact arithmetic; in float64 the difference of residuals loses eps * |r| / h^2 (h = 1e-3, an
    # unlucky draw: 5e-9 against a bound of 4.5e-9 without this term)
    eps = torch.finfo(torch.float64).eps
    cancel = 16 * eps * float(rh.abs().max() + r0.abs().max() + h * J_d.abs().max()) / h**2
    assert torch.allclose(got, exact, rtol=1e-8, atol=1e-8 * float(exact.abs().max()) + cancel)


def test_second_directional_derivative_of_a_robots_tool_points():
    """Along a step of the FANUC's error parameters the kinematics bend: the finite difference at h = 0.1 is
    the exact second derivative (forward-mode autodiff twice) to within its O(h) truncation."""
    robot = torchcal.load_robot("fanuc_lrmate200i")
    tools = torch.tensor([[0.03, 0.05, 0.16]], dtype=torch.float64)
    model = torchcal.RobotModel(robot, tools, orders=3, backlash=False)
    layout = torchcal.identify.layout.ParameterLayout(model)
    q = torchcal.sim.quasi_random_commands(robot.joint_map.limits, 50, 0)
    tool = torch.zeros(len(q), dtype=torch.long)
    g = torch.Generator().manual_seed(1)
    x0 = 1e-3 * torch.randn(layout.size, generator=g, dtype=torch.float64)
    d = 2e-3 * torch.randn(layout.size, generator=g, dtype=torch.float64)

    def points(x):  # the model's forward: its tool points
        return functional_call(model, layout.as_dict(x), (q, tool))

    with torch.no_grad():
        p0, J_d = jvp(points, (x0,), (d,))
        _, p_dd = jvp(lambda x: jvp(points, (x,), (d,))[1], (x0,), (d,))
        p_h = points(x0 + GEODESIC_H * d)
    got = second_directional(p0, p_h, p0 + J_d)
    assert float(p_dd.abs().max()) > 1e-9  # the kinematics do bend along this step
    assert float((got - p_dd).abs().max()) < 0.1 * float(p_dd.abs().max())


@settings(max_examples=50, deadline=None)
@given(seed=hst.integers(0, 2**31 - 1), log_units=hst.lists(hst.floats(-6, 6), min_size=6, max_size=6))
def test_the_kept_acceleration_does_not_depend_on_the_parameters_units(seed, log_units):
    """Marquardt's scaling makes the test unit-free: a parameter measured in other units (a, db times u,
    its scale divided by u) keeps the same verdict; and an acceleration within the bound is kept, one beyond
    it is not."""
    g = torch.Generator().manual_seed(seed)
    a, db = torch.randn(4, 6, generator=g, dtype=torch.float64), torch.randn(4, 6, generator=g, dtype=torch.float64)
    scale = torch.rand(4, 6, generator=g, dtype=torch.float64) + 0.1
    u = torch.tensor(log_units, dtype=torch.float64).exp2()
    ratio = (a * scale).norm(dim=1) / (db * scale).norm(dim=1)
    clear = (2.0 * ratio - 0.75).abs() > 1e-9  # away from the bound, where rounding could tip it
    assert torch.equal(acceleration_kept(a, db, scale)[clear], acceleration_kept(a * u, db * u, scale / u)[clear])
    assert bool(acceleration_kept(0.3 * db, db, scale).all()) and not bool(acceleration_kept(0.4 * db, db, scale).any())
