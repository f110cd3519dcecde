"""PoseInstrument (6-DOF probe), the SO(3) log map and the Euler conventions of the sensor contract."""

import math

import numpy as np
import pytest
import torch
from conftest import random_commands
from hypothesis import given, settings
from hypothesis import strategies as st
from scipy.spatial.transform import Rotation

from torchcal.identify import fit
from torchcal.identify.problem import NoiseModel
from torchcal.kinematics.transforms import so3_exp, twist_to_transform
from torchcal.measure import PoseInstrument
from torchcal.models.sensor_rig import SensorRig
from torchcal.measure.pose import (
    RotationError,
    euler_from_rotation,
    euler_mismatch,
    nearest_rotation,
    parse_convention,
    rotation_defects,
    rotation_from_euler,
    rotation_log,
)
from torchcal.core.measurements import Measurements

CONVENTIONS = [a + b + c for a in "xyz" for b in "xyz" for c in "xyz" if a != b and b != c]
CONVENTIONS += [c.upper() for c in CONVENTIONS]


def random_rotations(n, seed):
    return torch.from_numpy(Rotation.random(n, random_state=seed).as_matrix())


@pytest.mark.parametrize("convention", CONVENTIONS)
def test_euler_matches_scipy_and_round_trips(convention):
    """scipy is the independent reference for both directions ('xyz' extrinsic, 'XYZ' intrinsic)."""
    R = random_rotations(100, 0)
    ang = euler_from_rotation(R, convention)
    ref = torch.from_numpy(Rotation.from_matrix(R.numpy()).as_euler(convention, degrees=True))
    assert torch.allclose(rotation_from_euler(ref, convention), R, atol=1e-12)
    assert torch.allclose(rotation_from_euler(ang, convention), R, atol=1e-12)
    assert torch.allclose(ang, ref, atol=1e-9)
    # gimbal lock: the middle angle at its singular value still rebuilds R
    lock = 90.0 if convention[0].lower() != convention[2].lower() else 0.0
    a = torch.tensor([[30.0, lock, -50.0], [-120.0, -lock if lock else 180.0, 10.0]])
    R_lock = rotation_from_euler(a, convention)
    assert torch.allclose(rotation_from_euler(euler_from_rotation(R_lock, convention), convention), R_lock, atol=1e-9)


def test_intrinsic_and_extrinsic_naming():
    a = torch.tensor([10.0, 20.0, 30.0])
    Rx, Ry, Rz = (rotation_from_euler(torch.tensor(v), "xyz") for v in ([10.0, 0, 0], [0, 20.0, 0], [0, 0, 30.0]))
    assert torch.allclose(rotation_from_euler(a, "xyz"), Rz @ Ry @ Rx)  # extrinsic: fixed axes, x first
    assert torch.allclose(rotation_from_euler(a, "XYZ"), Rx @ Ry @ Rz)  # intrinsic: moving axes, x first
    for bad in ("xy", "xYz", "xxz", "abc", 3):
        with pytest.raises(RotationError):
            parse_convention(bad)


def test_euler_mismatch_catches_another_convention():
    R = random_rotations(20, 1)
    ang = euler_from_rotation(R, "XYZ")
    assert euler_mismatch(ang, R, "XYZ") == []
    wrong = euler_mismatch(ang, R, "xyz")
    assert len(wrong) >= 18 and all(a > 0.1 for _, a in wrong)


@settings(max_examples=80, deadline=None)
@given(st.lists(st.floats(-3.1, 3.1), min_size=3, max_size=3))
def test_rotation_log_inverts_exp(w):
    w = torch.tensor(w)
    if float(w.norm()) > math.pi - 1e-3:
        w = w / w.norm() * (math.pi - 1e-3)
    assert torch.allclose(rotation_log(so3_exp(w)), w, atol=1e-9)


def test_rotation_log_at_identity_and_pi():
    J = torch.autograd.functional.jacobian(lambda x: rotation_log(so3_exp(x)), torch.zeros(3))
    assert torch.allclose(J, torch.eye(3))  # finite, identity: residuals are zero at the truth
    for axis in torch.eye(3):
        w = rotation_log(so3_exp(axis * math.pi))
        assert torch.allclose(w.abs(), axis * math.pi, atol=1e-7)


def test_rotation_defects_and_projection():
    R = random_rotations(5, 2)
    R[1] = R[1] * 1.01  # scaled
    R[2, :, 0] *= -1  # reflection
    R[3, 0, 0] = float("nan")
    R[4] = R[4] + 1e-7  # rounding: accepted
    found = dict(rotation_defects(R))
    assert set(found) == {1, 2, 3}
    assert "not orthonormal" in found[1] and "reflection" in found[2] and "non-finite" in found[3]
    P = nearest_rotation(R[4:])
    assert torch.allclose(P.transpose(1, 2) @ P, torch.eye(3), atol=1e-14) and (P - R[4:]).abs().max() < 1e-6


def test_rotation_residual_is_in_the_tracker_frame():
    """R_pred = exp(S(w)) R_obs gives residual w, whatever R_obs: small rotations about the tracker axes."""
    R_obs = random_rotations(4, 3)
    w = torch.tensor([[1e-3, 0, 0], [0, -2e-3, 0], [0, 0, 5e-4], [3e-4, -2e-4, 1e-4]])
    R_pred = so3_exp(w) @ R_obs
    p = torch.randn(4, 3, generator=torch.Generator().manual_seed(0))
    inst = PoseInstrument(p, R_obs)
    pred = torch.cat([p + 1e-4, R_pred.reshape(4, 9)], 1)
    r = inst.residual(pred, inst.observed)
    assert torch.allclose(r[:, :3], torch.full((4, 3), 1e-4)) and torch.allclose(r[:, 3:], w, atol=1e-12)


def test_whitening_by_pose_std():
    R = random_rotations(3, 4)
    std = torch.tensor([[1e-5, 2e-5, 3e-5, 1e-4, 2e-4, 3e-4]]).expand(3, 6)
    inst = PoseInstrument(torch.ones(3, 3), R, pose_std=std)
    assert torch.allclose(inst.whiten(std.clone()), torch.ones(3, 6))
    data = Measurements.from_tensors(torch.zeros(3, 6), 0, torch.ones(3, 3))
    data.extra.update(rotation=R, pose_std=std * 2)
    assert torch.allclose(PoseInstrument.from_measurements(data).whiten(std * 2), torch.ones(3, 6))
    assert torch.allclose(PoseInstrument.from_measurements(data, pose_std=std).whiten(std), torch.ones(3, 6))
    both = PoseInstrument.cat([inst.subset(torch.tensor([0])), inst.subset(torch.tensor([1, 2]))])
    assert torch.equal(both.observed, inst.observed) and torch.allclose(both.weight.cov, inst.weight.cov)
    bad = R.clone()
    bad[1] *= 1.1
    with pytest.raises(RotationError, match="row index 1: rotation is not orthonormal"):
        PoseInstrument(torch.ones(3, 3), bad)
    data.extra["rotation"] = bad
    data.source = "probe.csv"
    with pytest.raises(RotationError, match="probe.csv: PoseInstrument: row 2: rotation is not orthonormal"):
        PoseInstrument.from_measurements(data)  # file rows (1-based) in the message
    with pytest.raises(ValueError, match="positive"):
        PoseInstrument(torch.ones(3, 3), R, pose_std=-std)


def test_probe_fit_recovers_base_and_mount(fanuc, one_thread):
    """Generic probe (T-Mac-like): truth rig with base and mount errors, pose noise; fit with joint errors held."""
    base = torch.eye(4)
    base[:3, 3] = torch.tensor([1.8, -0.4, 0.1])
    mount = twist_to_transform(torch.tensor([0.0, 0.0, 1.57, 0.0, 0.0, 0.09]))
    truth = SensorRig.for_robot(fanuc, orders=1, base_nominal=base, mount=mount)
    with torch.no_grad():
        truth.model.base.twist.copy_(torch.tensor([1e-3, -2e-3, 4e-3, 2e-3, 1e-3, -3e-3]))
        truth.mount.twist.copy_(torch.tensor([3e-3, -1e-3, 2e-3, -1e-3, 5e-4, 1e-3]))
    q = random_commands(fanuc, 40, 11)
    g = torch.Generator().manual_seed(12)
    std = torch.tensor([1e-5] * 3 + [1e-4] * 3)
    with torch.no_grad():
        T = truth.sensor_pose(q)
    R = so3_exp(torch.randn(40, 3, generator=g) * std[3:]) @ T[:, :3, :3]
    data = Measurements.from_tensors(q, 0, T[:, :3, 3] + torch.randn(40, 3, generator=g) * std[:3])
    data.extra.update(rotation=R, pose_std=std.expand(40, 6).clone())
    rig = SensorRig.for_robot(fanuc, orders=1, base_nominal=base, mount=mount)
    noise = NoiseModel(1e-5, torch.zeros(6), torch.zeros(6))  # no joint noise: v not estimated
    result = fit(rig, data, noise, instrument=PoseInstrument.from_measurements(data), fixed=("model.joint_errors",))
    assert result.success
    with torch.no_grad():
        e_base = (rig.model.base.twist - truth.model.base.twist).abs()
        e_mount = (rig.mount.twist - truth.mount.twist).abs()
    assert e_base.max() < 2e-5 and e_mount.max() < 5e-5  # perturbations 1e-3 .. 4e-3; noise-level errors ~1e-5
    assert 0.3 < result.fun / (40 * 6) < 2.0
    assert np.isfinite(result.fun)


@pytest.mark.parametrize("module", ["torchcal.measure.pose", "torchcal.models.sensor_rig"])
def test_docstring_examples(module):
    import doctest
    import importlib

    res = doctest.testmod(importlib.import_module(module), optionflags=doctest.ELLIPSIS)
    assert res.failed == 0 and res.attempted > 0


def test_subclasses_survive_subset_cat_and_to():
    class Mine(PoseInstrument):
        pass

    R = random_rotations(4, 5)
    inst = Mine(torch.ones(4, 3), R)
    assert type(inst.subset(torch.tensor([0, 2]))) is Mine and type(inst.to("cpu")) is Mine
    assert type(Mine.cat([inst, inst])) is Mine and len(Mine.cat([inst, inst])) == 8


def test_rotation_log_runs_under_vmap():
    """No data-dependent branch: autograd Jacobians vmap over rows (incl. the near-pi fallback)."""
    from torch.func import jacrev, vmap

    w = torch.tensor([[0.0, 0.0, 0.0], [0.1, -0.2, 0.3], [0.0, 0.0, math.pi]])
    out = vmap(rotation_log)(so3_exp(w))
    assert torch.allclose(out[:2], w[:2], atol=1e-12) and torch.allclose(out[2].abs(), w[2], atol=1e-7)
    J = vmap(jacrev(lambda x: rotation_log(so3_exp(x))))(w[:2])
    assert torch.isfinite(J).all() and torch.allclose(J[0], torch.eye(3))
