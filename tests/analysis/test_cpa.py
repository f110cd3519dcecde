"""Circle Point Analysis: sweeps (Table 8), circle fits, the POE model and DH / Hayati extraction (Tables 2, 9)."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch
from hypothesis import given, settings
from hypothesis import strategies as st

from torchcal.analysis import (
    PAPER2_TABLE8,
    CPAModel,
    cpa_sweep_commands,
    cpa_validation_commands,
    dh_parameters,
    dh_table,
    fit_circle,
    fit_cpa,
    fit_joint_axis,
    point_residuals,
)
from torchcal.kinematics.transforms import transform_to_twist
from torchcal.core.measurements import Measurements
from torchcal.models.robot import RobotModel

F64 = torch.float64


def random_q(robot, count, seed):
    g = torch.Generator().manual_seed(seed)
    lim = robot.joint_map.limits
    return lim[:, 0] + torch.rand(count, robot.n, generator=g, dtype=F64) * (lim[:, 1] - lim[:, 0])


HOMES = [None, torch.deg2rad(torch.tensor([20.0, 10.0, -15.0, 30.0, -40.0, 60.0], dtype=F64))]


def measure_cpa(actual: RobotModel, robot, tool: int = 0, home=None):
    """Noise-free CPA data from a simulated robot: Table 8 sweeps with one tool + home points of every tool."""
    sweeps = []
    home_q = torch.zeros(robot.n, dtype=F64) if home is None else home
    with torch.no_grad():
        for i, q in enumerate(cpa_sweep_commands(robot, home=home)):
            t = torch.full((q.shape[0],), tool, dtype=torch.long)
            sweeps.append(Measurements.from_tensors(q, t, actual.points(q, t), source=f"sweep J{i + 1}"))
        T = actual.tools.count
        home_points = actual.points(home_q.expand(T, -1), torch.arange(T))
    return sweeps, home_points


# --------------------------------------------------------------- commands


def test_sweeps_follow_table8_and_turn_one_urdf_joint(fanuc):
    cmds = cpa_sweep_commands(fanuc)
    assert [c.shape[0] for c in cmds] == [67, 41, 66, 72, 61, 72]  # Table 8's point counts
    jm = fanuc.joint_map
    theta_home = jm.to_joint(torch.zeros(1, 6, dtype=F64))
    for i, (q, r) in enumerate(zip(cmds, PAPER2_TABLE8)):
        torch.testing.assert_close(torch.rad2deg(q[:, i]), torch.as_tensor(r.values(), dtype=F64))
        dtheta = jm.to_joint(q) - theta_home
        others = torch.cat([dtheta[:, :i], dtheta[:, i + 1:]], 1)
        assert others.abs().max() < 1e-14
        assert (dtheta[:, i].diff() > 0).all()
    # FANUC coupling θ3 = q2 + q3: turning URDF joint 2 alone needs q3 = -q2
    torch.testing.assert_close(cmds[1][:, 2], -cmds[1][:, 1])
    assert cmds[1][:, [0, 3, 4, 5]].abs().max() == 0


def test_full_turn_rule_is_for_revolute_joints_only(tmp_path):
    """A 400 mm prismatic sweep keeps its last point: 360 is a full turn in degrees, not in mm."""
    from conftest import PRISMATIC_URDF

    from torchcal.analysis import SweepRange
    from torchcal.kinematics import load_robot

    assert SweepRange(-180.0, 180.0, 5.0).values().size == 72  # 180 repeats -180: dropped
    v = SweepRange(0.0, 400.0, 50.0).values(prismatic=True)
    np.testing.assert_allclose(v, np.arange(0.0, 401.0, 50.0))  # 9 points, 400 mm kept
    assert SweepRange(0.0, 400.0, 50.0).values().size == 8  # the same numbers in degrees: a full turn

    path = tmp_path / "rpr.urdf"
    path.write_text(PRISMATIC_URDF.replace('upper="0.5"', 'upper="0.6"'))
    robot = load_robot(path)
    table = (SweepRange(-90.0, 90.0, 10.0), SweepRange(100.0, 500.0, 50.0), SweepRange(-180.0, 180.0, 10.0))
    cmds = cpa_sweep_commands(robot, table)
    assert [c.shape[0] for c in cmds] == [19, 9, 36]
    torch.testing.assert_close(cmds[1][-1, 1], torch.tensor(0.5, dtype=F64))  # the last point, 500 mm, in metres


def test_validation_commands_are_seeded_and_inside_the_ranges(fanuc):
    a = cpa_validation_commands(fanuc, per_joint=60, seed=4)
    b = cpa_validation_commands(fanuc, per_joint=60, seed=4)
    c = cpa_validation_commands(fanuc, per_joint=60, seed=5)
    assert all(torch.equal(x, y) for x, y in zip(a, b)) and not torch.equal(a[0], c[0])
    for i, (q, r) in enumerate(zip(a, PAPER2_TABLE8)):
        deg = torch.rad2deg(q[:, i])
        assert q.shape == (60, 6) and deg.min() >= r.start and deg.max() <= r.end
        # quasi-random: every tenth of the range holds some points
        hist = torch.histc(deg, bins=10, min=r.start, max=r.end)
        assert (hist > 0).all()


# ------------------------------------------------------------- circle fit


def circle_points(w, c, r, phi):
    w = w / np.linalg.norm(w)
    a = np.eye(3)[np.argmin(np.abs(w))]
    e1 = np.cross(w, a)
    e1 /= np.linalg.norm(e1)
    e2 = np.cross(w, e1)
    return c + r * (np.cos(phi)[:, None] * e1 + np.sin(phi)[:, None] * e2)


unit_vec = st.tuples(*[st.floats(-1, 1)] * 3).map(np.array).filter(lambda v: np.linalg.norm(v) > 0.2)
centre = st.tuples(*[st.floats(-2, 2)] * 3).map(np.array)


@settings(max_examples=60, deadline=None)
@given(w=unit_vec, c=centre, r=st.floats(0.02, 1.0), start=st.floats(-math.pi, math.pi),
       span=st.floats(math.radians(30), 2 * math.pi), m=st.integers(3, 60))
def test_circle_fit_exact_without_noise(w, c, r, start, span, m):
    phi = start + np.linspace(0, span, m, endpoint=span < 2 * math.pi - 1e-9)
    f = fit_circle(torch.as_tensor(circle_points(w, c, r, phi)))
    wn = w / np.linalg.norm(w)
    assert np.linalg.norm(f.center.numpy() - c) < 1e-9
    assert abs(f.radius - r) < 1e-10
    assert np.linalg.norm(np.cross(f.normal.numpy(), wn)) < 1e-9
    assert f.residuals.abs().max() < 1e-10


@settings(max_examples=40, deadline=None)
@given(w=unit_vec, c=centre, r=st.floats(0.05, 0.5), start=st.floats(-math.pi, math.pi),
       span=st.floats(math.radians(90), 2 * math.pi), m=st.integers(20, 80), seed=st.integers(0, 2**31))
def test_circle_fit_within_noise(w, c, r, start, span, m, seed):
    sigma = 1e-5
    phi = start + np.linspace(0, span, m, endpoint=False)
    P = circle_points(w, c, r, phi) + sigma * np.random.default_rng(seed).normal(size=(m, 3))
    f = fit_circle(torch.as_tensor(P))
    wn = w / np.linalg.norm(w)
    # empirically <= 3 sigma over 300 draws of this family; 10 sigma leaves room without hiding a bias
    assert np.linalg.norm(f.center.numpy() - c) < 10 * sigma
    assert abs(f.radius - r) < 10 * sigma
    assert np.linalg.norm(np.cross(f.normal.numpy(), wn)) * r < 10 * sigma
    # the residual spread is the noise's, not a misfit
    assert f.residuals.pow(2).mean().sqrt() < 3 * sigma


def test_axis_direction_follows_the_joint_motion():
    w = np.array([0.3, -0.2, 0.9])
    theta = np.linspace(-1.0, 1.5, 25)
    P = torch.as_tensor(circle_points(w, np.array([0.1, 0.2, 0.3]), 0.2, theta))
    wn = torch.as_tensor(w / np.linalg.norm(w))
    fit = fit_joint_axis(P, torch.as_tensor(theta))
    torch.testing.assert_close(fit.direction, wn)
    fit_rev = fit_joint_axis(P, torch.as_tensor(-theta))
    torch.testing.assert_close(fit_rev.direction, -wn)
    # the angles reported about the signed axis grow with the joint variable
    assert (np.diff(np.unwrap(fit_rev.circle.angles.numpy()[::-1])) > 0).all()


def test_circle_fit_rejects_degenerate_points():
    with pytest.raises(ValueError, match="collinear"):
        fit_circle(torch.tensor([[0.0, 0, 0], [1, 0, 0], [2, 0, 0], [3, 0, 0]], dtype=F64))
    with pytest.raises(ValueError, match="coincide"):
        fit_circle(torch.ones(5, 3, dtype=F64))


# -------------------------------------------------------------- CPA model


def constant_error_robot(robot, tools, seed, orders=0):
    model = RobotModel(robot, tools, orders=orders)
    g = torch.Generator().manual_seed(seed)
    with torch.no_grad():
        c = torch.randn(model.joint_errors.coef.shape, generator=g, dtype=F64)
        c[:, :3] *= 2e-3  # rad
        c[:, 3:] *= 1e-3  # m
        model.joint_errors.coef.copy_(c)
        model.base.twist.copy_(torch.randn(6, generator=g, dtype=F64) * 2e-3)
        model.tools.delta.copy_(torch.randn(3, 3, generator=g, dtype=F64) * 1e-3)
    return model


@pytest.mark.parametrize("home_q", HOMES, ids=["zero-home", "other-home"])
def test_cpa_is_exact_for_constant_errors(fanuc, tools_m, home_q):
    actual = constant_error_robot(fanuc, tools_m, seed=7)
    sweeps, home = measure_cpa(actual, fanuc, tool=1, home=home_q)
    cpa = fit_cpa(fanuc, sweeps, home, home=home_q, tools_nominal=tools_m)
    q = random_q(fanuc, 500, seed=8)
    tool = torch.arange(500) % 3  # tools 0 and 2 were only measured at home
    with torch.no_grad():
        truth = actual.points(q, tool)
        err = (cpa.points(q, tool) - truth).norm(dim=1)
        nominal_err = (cpa.nominal_points(q, tool) - truth).norm(dim=1)
    assert err.max() < 1e-9
    assert nominal_err.mean() > 1e-3  # the errors were not negligible to begin with
    # identified axes keep the joints' positive sense, close to the nominal axes
    from torchcal.analysis import nominal_axes

    _, ndirs, _ = nominal_axes(fanuc, home_q)
    assert ((cpa.axis_dirs * ndirs).sum(1) > 0.999).all()
    for s, f in zip(sweeps, cpa.fits):
        assert f.residuals.max() < 1e-10
        assert point_residuals(cpa, s).max() < 1e-9
    # persistence round trip
    again = CPAModel.from_spec(cpa.spec(), fanuc)
    with torch.no_grad():
        torch.testing.assert_close(again.points(q, tool), cpa.points(q, tool), atol=1e-14, rtol=0)


def test_cpa_cannot_follow_joint_dependent_errors(fanuc, tools_m):
    actual = constant_error_robot(fanuc, tools_m, seed=9, orders=3)
    sweeps, home = measure_cpa(actual, fanuc)
    cpa = fit_cpa(fanuc, sweeps, home)
    data = Measurements.from_tensors(random_q(fanuc, 200, 10), 0)
    with torch.no_grad():
        data.xyz = actual.points(data.q, data.tool)
    assert point_residuals(cpa, data).mean() > 1e-5


def test_fit_cpa_rejects_a_sweep_that_moves_another_joint(fanuc, tools_m):
    actual = constant_error_robot(fanuc, tools_m, seed=1)
    sweeps, home = measure_cpa(actual, fanuc)
    q = sweeps[2].q.clone()
    q[5, 0] += 0.01  # joint 1 off home during the joint-3 sweep
    with torch.no_grad():
        bad = Measurements.from_tensors(q, 0, actual.points(q, torch.zeros(len(q), dtype=torch.long)), source="j3.csv")
    with pytest.raises(ValueError, match=r"j3.csv, row 6: URDF joint 1 is not at home"):
        fit_cpa(fanuc, sweeps[:2] + [bad] + sweeps[3:], home)


@pytest.mark.skipif(not torch.cuda.is_available(), reason="needs a GPU")
def test_cpa_model_moves_to_gpu(fanuc, tools_m):
    actual = constant_error_robot(fanuc, tools_m, seed=7)
    sweeps, home = measure_cpa(actual, fanuc)
    cpa = fit_cpa(fanuc, sweeps, home).to("cuda")
    q = random_q(fanuc, 10, 1)
    p = cpa.points(q.cuda(), torch.zeros(10, dtype=torch.long, device="cuda"))
    assert p.device.type == "cuda" and p.dtype == F64


# ---------------------------------------------------------------- DH table


TABLE2 = {  # Paper II, Table 2, rows 1-5 (the 6th is the flange/tool)
    "theta_offset": [0, -90, 0, 0, 0], "d": [0, 0, 0, -290, 0], "a": [150, 250, 75, 0, 0], "alpha": [-90, 180, -90, 90, -90],
}


@pytest.mark.parametrize("home_q", HOMES, ids=["zero-home", "other-home"])
def test_dh_of_the_nominal_fanuc_is_table2(fanuc, tools_m, home_q):
    # through the whole pipeline: sweeps of the error-free robot -> circles -> axes -> DH;
    # the table describes the machine, so it must not depend on where CPA was done
    sweeps, home = measure_cpa(RobotModel(fanuc, tools_m, orders=0), fanuc, home=home_q)
    nominal, ident = dh_parameters(fit_cpa(fanuc, sweeps, home, home=home_q), fanuc)
    for p in (nominal, ident):
        torch.testing.assert_close(torch.rad2deg(p.theta_offset), torch.tensor(TABLE2["theta_offset"], dtype=F64), atol=1e-8, rtol=0)
        torch.testing.assert_close(p.d * 1e3, torch.tensor(TABLE2["d"], dtype=F64), atol=1e-8, rtol=0)
        torch.testing.assert_close(p.a * 1e3, torch.tensor(TABLE2["a"], dtype=F64), atol=1e-8, rtol=0)
        torch.testing.assert_close(torch.rad2deg(p.alpha), torch.tensor(TABLE2["alpha"], dtype=F64), atol=1e-8, rtol=0)
        torch.testing.assert_close(p.beta, torch.zeros(5, dtype=F64), atol=1e-10, rtol=0)
    assert nominal.hayati.tolist() == [False, True, False, False, False]  # joints 2-3 are parallel
    rows = dh_table(fit_cpa(fanuc, sweeps, home, home=home_q), fanuc)
    # Table 9's parameter list
    assert [r["parameter"] for r in rows] == [
        "theta1", "theta2", "theta3", "theta4", "theta5", "d1", "d3", "d4", "d5",
        "a1", "a2", "a3", "a4", "a5", "alpha1", "alpha2", "alpha3", "alpha4", "alpha5", "beta2"]
    by = {r["parameter"]: r for r in rows}
    assert by["theta2"]["nominal"] == pytest.approx(-90) and by["theta3"]["expression"] == "q2 + q3"
    assert by["d4"]["identified"] == pytest.approx(-290, abs=1e-8) and by["a1"]["unit"] == "mm"


def _rot(axis, t):
    c, s = math.cos(t), math.sin(t)
    R = {"x": [[1, 0, 0], [0, c, -s], [0, s, c]], "y": [[c, 0, s], [0, 1, 0], [-s, 0, c]], "z": [[c, -s, 0], [s, c, 0], [0, 0, 1]]}[axis]
    T = np.eye(4)
    T[:3, :3] = R
    return T


def _trans(x=0.0, z=0.0):
    T = np.eye(4)
    T[0, 3], T[2, 3] = x, z
    return T


def test_dh_extraction_recovers_known_parameter_changes(fanuc, tools_m):
    """An actual FANUC built from perturbed DH / Hayati rows: CPA + extraction must return those rows."""
    rng = np.random.default_rng(11)
    n = 6
    nom = {k: np.array(v, dtype=float) for k, v in TABLE2.items()}
    d0, a0 = nom["d"] * 1e-3, nom["a"] * 1e-3
    al0 = np.radians(nom["alpha"])
    dth = rng.normal(size=n) * 2e-3
    dd, da, dal, dbeta = (rng.normal(size=5) * s for s in (1e-3, 1e-3, 2e-3, 2e-3))
    dd[1] = 0.0  # Hayati row: no d
    origins = fanuc.chain.origins.numpy()
    coef = torch.zeros(n, 6, 1, dtype=F64)
    for j in range(n):  # E_j sits before joint j turns: (fixed part of row j-1, perturbed) then Rz(dθ_j)
        if j == 0:
            row = np.eye(4)
        elif j == 2:  # Hayati-Mirmirani row 2: Rz Tx(a) Rx(α) Ry(β)
            row = _trans(x=a0[1] + da[1]) @ _rot("x", al0[1] + dal[1]) @ _rot("y", dbeta[1])
        else:
            i = j - 1
            row = _trans(z=d0[i] + dd[i]) @ _trans(x=a0[i] + da[i]) @ _rot("x", al0[i] + dal[i])
        E = np.linalg.inv(origins[j]) @ row @ _rot("z", dth[j])
        coef[j, :, 0] = transform_to_twist(torch.as_tensor(E))
    actual = RobotModel(fanuc, tools_m, orders=0)
    with torch.no_grad():
        actual.joint_errors.coef.copy_(coef)
    sweeps, home = measure_cpa(actual, fanuc)
    cpa = fit_cpa(fanuc, sweeps, home)
    _, ident = dh_parameters(cpa, fanuc)
    tol = dict(atol=1e-9, rtol=0)
    torch.testing.assert_close(ident.theta_offset, torch.as_tensor(np.radians(nom["theta_offset"]) + dth[:5]), **tol)
    dh_rows = [0, 2, 3, 4]
    torch.testing.assert_close(ident.d[dh_rows], torch.as_tensor(d0 + dd)[dh_rows], **tol)
    torch.testing.assert_close(ident.a, torch.as_tensor(a0 + da), **tol)
    torch.testing.assert_close(ident.alpha, torch.as_tensor(al0 + dal), **tol)
    torch.testing.assert_close(ident.beta[1], torch.tensor(dbeta[1], dtype=F64), **tol)
    # the constructed frames carry the identified axes: z_i along axis i+1, origin on it
    F = ident.frames
    torch.testing.assert_close(F[:, :3, 2], cpa.axis_dirs, **tol)
    off = F[:, :3, 3] - cpa.axis_points
    torch.testing.assert_close(torch.linalg.cross(off, cpa.axis_dirs, dim=1), torch.zeros(n, 3, dtype=F64), **tol)
