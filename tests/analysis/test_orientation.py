"""Orientation repeatability, Paper III (41)-(45): known scatter, an independent loop reference, invariances."""

import math

import numpy as np
import pytest
import torch
from hypothesis import given, settings
from hypothesis import strategies as st

from torchcal.analysis.orientation import (
    RepeatabilityError,
    axis_repeatability,
    expected_orientation_repeatability,
    mean_rotation,
    orientation_repeatability,
)

T = {"dtype": torch.float64}


def skew(w):
    z = torch.zeros_like(w[..., 0])
    return torch.stack([torch.stack([z, -w[..., 2], w[..., 1]], -1), torch.stack([w[..., 2], z, -w[..., 0]], -1),
                        torch.stack([-w[..., 1], w[..., 0], z], -1)], -2)


def scatter(P, K, sigma, seed):
    """R_ij = R_i exp([ω_ij]), ω ~ N(0, σ² I): random base orientation per pose, known isotropic scatter."""
    g = torch.Generator().manual_seed(seed)
    base = torch.linalg.matrix_exp(skew(torch.randn(P, 3, generator=g, **T) * 2.0))
    w = torch.randn(P, K, 3, generator=g, **T) * sigma
    return base[:, None] @ torch.linalg.matrix_exp(skew(w))


def reference_41_45(z: np.ndarray):
    """(41)-(45) for one pose, a plain loop with numpy's arccos of the normalized dot product."""
    zbar = sum(z) / len(z)
    tau = [math.acos(float(np.dot(zbar, zj) / (np.linalg.norm(zbar) * np.linalg.norm(zj)))) for zj in z]
    m = sum(tau) / len(tau)
    s = math.sqrt(sum((t - m) ** 2 for t in tau) / (len(tau) - 1))
    return m, s, m + 3 * s


def test_matches_a_plain_loop_of_41_45():
    R = scatter(5, 20, 0.02, 0)  # 20 samples at 5 poses, as in the paper; angles big enough for arccos
    out = orientation_repeatability(R)
    for i in range(5):
        m, s, ro = reference_41_45(R[i, :, :, 2].numpy())
        assert (float(out.mean[i]), float(out.std[i]), float(out.ro[i])) == pytest.approx((m, s, ro), rel=1e-9)
    assert float(out.worst) == float(out.ro.max())


def test_axis_tilt_scatter_gives_the_rayleigh_repeatability():
    sigma = 1.2e-4
    out = orientation_repeatability(scatter(8, 2000, sigma, 1))
    assert float(out.mean.mean()) == pytest.approx(sigma * math.sqrt(math.pi / 2), rel=0.02)
    assert float(out.std.mean()) == pytest.approx(sigma * math.sqrt(2 - math.pi / 2), rel=0.03)
    assert float(out.ro.mean()) == pytest.approx(expected_orientation_repeatability(sigma), rel=0.02)
    assert torch.allclose(out.ro, torch.full((8,), expected_orientation_repeatability(sigma), **T), rtol=0.06)


def test_whole_rotation_scatter_gives_the_maxwell_repeatability():
    sigma = 1.2e-4
    out = orientation_repeatability(scatter(8, 2000, sigma, 2), axis=None)
    assert float(out.mean.mean()) == pytest.approx(2 * sigma * math.sqrt(2 / math.pi), rel=0.02)
    assert float(out.ro.mean()) == pytest.approx(expected_orientation_repeatability(sigma, axis=False), rel=0.02)
    # the mean rotation is the scatter's centre: within a few σ/sqrt(K) of the true base orientation
    base = scatter(8, 1, 0.0, 2)[:, 0]
    err = torch.linalg.matrix_norm(out.mean_rotation - base)
    assert float(err.max()) < 5 * sigma * math.sqrt(3 / 2000) * math.sqrt(2)


@settings(max_examples=15, deadline=None)
@given(st.integers(0, 1000), st.sampled_from([2, None]))
def test_a_common_rotation_changes_nothing(seed, axis):
    g = torch.Generator().manual_seed(seed)
    R = scatter(3, 20, 3e-4, seed)
    C = torch.linalg.matrix_exp(skew(torch.randn(3, 3, generator=g, **T)))[:, None]  # one per pose
    ref = orientation_repeatability(R, axis=axis)
    left = orientation_repeatability(C @ R, axis=axis)
    assert torch.allclose(left.tau, ref.tau, rtol=1e-6, atol=1e-12)
    # right: any rotation for whole orientations, a turn about the measured z axis for the axis statistic
    if axis is None:
        Q = torch.linalg.matrix_exp(skew(torch.randn(3, generator=g, **T)))
    else:
        Q = torch.linalg.matrix_exp(skew(torch.tensor([0.0, 0.0, float(torch.randn(1, generator=g))], **T)))
    right = orientation_repeatability(R @ Q, axis=axis)
    assert torch.allclose(right.tau, ref.tau, rtol=1e-6, atol=1e-12)


def test_batched_poses_equal_single_poses_and_axis_vectors():
    R = scatter(4, 15, 5e-4, 3)
    out = orientation_repeatability(R, axis=None)
    for i in range(4):
        one = orientation_repeatability(R[i], axis=None)
        assert torch.allclose(one.ro, out.ro[i : i + 1], rtol=1e-12)
    z = orientation_repeatability(R)
    scaled = axis_repeatability(R[..., :, 2] * 3.7)  # (41)-(42) do not care about the vectors' length
    assert torch.allclose(z.ro, scaled.ro, rtol=1e-9)
    assert torch.allclose(mean_rotation(R), out.mean_rotation)


def test_sub_microradian_angles_keep_their_precision():
    """atan2 instead of arccos: a 1e-7 rad scatter still comes out right (rounding pushes arccos's argument above 1 there)."""
    sigma = 1e-7
    out = orientation_repeatability(scatter(4, 2000, sigma, 4))
    assert float(out.ro.mean()) == pytest.approx(expected_orientation_repeatability(sigma), rel=0.03)


def test_bad_samples_are_named():
    R = scatter(2, 5, 1e-3, 5)
    bad = R.clone()
    bad[1, 3] *= 1.01
    with pytest.raises(RepeatabilityError, match="pose 2, sample 4"):
        orientation_repeatability(bad)
    bad = R.clone()
    bad[0, 2, 0, 0] = float("nan")
    with pytest.raises(RepeatabilityError, match="pose 1, sample 3"):
        orientation_repeatability(bad)
    with pytest.raises(RepeatabilityError, match="at least 2"):
        orientation_repeatability(R[:, :1])
    with pytest.raises(ValueError, match="axis"):
        orientation_repeatability(R, axis=3)
