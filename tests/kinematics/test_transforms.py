import math

import numpy as np
import pytest
import torch
from hypothesis import given, settings
from hypothesis import strategies as st
from scipy.spatial.transform import Rotation

from torchcal.kinematics.transforms import (
    invert, matrix_to_rpy, pose_error, rpy_to_matrix, so3_exp, so3_log, twist_to_transform, transform_to_twist,
)

vec3 = st.lists(st.floats(-3.0, 3.0), min_size=3, max_size=3)


@settings(max_examples=100, deadline=None)
@given(vec3)
def test_so3_exp_matches_scipy_and_log_inverts(w):
    w = torch.tensor(w)
    R = so3_exp(w)
    assert np.allclose(R.numpy(), Rotation.from_rotvec(w.numpy()).as_matrix(), atol=1e-13)
    if float(w.norm()) < 3.1:
        assert torch.allclose(so3_log(R), w, atol=1e-9)


def test_so3_exp_small_angles_are_exact_and_smooth():
    for scale in (0.0, 1e-12, 1e-6, 1e-4, 1e-3):
        w = torch.tensor([0.3, -0.2, 0.9]) * scale
        ref = Rotation.from_rotvec(w.numpy()).as_matrix()
        assert np.abs(so3_exp(w).numpy() - ref).max() <= 4e-16
    w = torch.zeros(3, requires_grad=True)
    (so3_exp(w) @ torch.tensor([1.0, 2.0, 3.0])).sum().backward()
    # d(R p)/dw at 0 = -S(p): column sums of -S([1,2,3])
    assert torch.allclose(w.grad, torch.tensor([-1.0, 2.0, -1.0]))


@settings(max_examples=50, deadline=None)
@given(st.lists(st.floats(-3.0, 3.0), min_size=2, max_size=2), st.floats(-1.5, 1.5))
def test_rpy_matches_urdf_convention(ry, p):
    rpy = torch.tensor([ry[0], p, ry[1]])
    ref = Rotation.from_euler("xyz", rpy.numpy()).as_matrix()  # extrinsic x, y, z = URDF rpy
    assert np.allclose(rpy_to_matrix(rpy).numpy(), ref, atol=1e-14)
    assert torch.allclose(rpy_to_matrix(matrix_to_rpy(rpy_to_matrix(rpy))), rpy_to_matrix(rpy), atol=1e-12)


def test_twist_transform_round_trip_and_first_order_matrix_20():
    e = torch.tensor([1e-3, -2e-3, 5e-4, 1e-4, -3e-5, 2e-4])
    T = twist_to_transform(e)
    assert torch.allclose(transform_to_twist(T), e, atol=1e-15)
    ex, ey, ez, dx, dy, dz = e.tolist()
    eq20 = torch.tensor([[1, -ez, ey, dx], [ez, 1, -ex, dy], [-ey, ex, 1, dz], [0, 0, 0, 1.0]])
    assert (T - eq20).abs().max() < float(e[:3].norm()) ** 2  # equal to first order
    assert torch.allclose(T @ invert(T), torch.eye(4), atol=1e-15)


def test_pose_error_is_zero_for_equal_and_first_order_twist():
    T = twist_to_transform(torch.tensor([0.3, 0.2, -0.1, 0.5, 0.1, 0.2]))
    assert pose_error(T, T).abs().max() < 1e-15
    d = torch.tensor([1e-7, 2e-7, -1e-7, 3e-7, -2e-7, 1e-7])
    T2 = T @ twist_to_transform(torch.cat([d[3:], d[:3]]))
    assert torch.allclose(pose_error(T, T2), d, atol=1e-13)


@pytest.mark.parametrize("pitch", [math.pi / 2, -math.pi / 2])
def test_rpy_round_trip_at_gimbal_lock(pitch):
    rpy = torch.tensor([[0.3, pitch, -0.7], [-1.2, pitch, 0.4]], dtype=torch.float64)
    R = rpy_to_matrix(rpy)
    back = matrix_to_rpy(R)
    assert torch.isfinite(back).all() and (back[:, 2] == 0).all()
    assert torch.allclose(rpy_to_matrix(back), R, atol=1e-12)


def test_cpu_constants_are_plain_whatever_the_context_of_first_use():
    """skew's constant map made first under inference_mode or a meta default device is still a plain CPU tensor:
    later autograd through so3_exp works and values are right (a cached inference tensor could never be saved
    for backward; a meta one would hold no values)."""
    from torchcal.kinematics import transforms as T

    T._CPU_CONSTANTS.clear()
    with torch.inference_mode():
        T.skew(torch.ones(3, dtype=torch.float64))
    with torch.device("meta"):
        T.so3_exp(torch.ones(3, dtype=torch.float32, device="cpu"))
    w = torch.tensor([0.1, -0.2, 0.3], dtype=torch.float64, requires_grad=True)
    T.so3_exp(w).sum().backward()
    assert w.grad is not None and torch.isfinite(w.grad).all()
    x, y, z = 1.0, 2.0, 3.0
    assert torch.equal(T.skew(torch.tensor([x, y, z])), torch.tensor([[0, -z, y], [z, 0, -x], [-y, x, 0]]))
    assert all(c.device.type == "cpu" and not c.is_inference() for c in T._CPU_CONSTANTS.values())
