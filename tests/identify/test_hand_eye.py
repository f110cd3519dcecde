"""Hand-eye first guesses: exact on noise-free loops, close under noise, each frame alone, degenerate data refused."""

import pytest
import torch

from torchcal.identify.hand_eye import HandEyeError, hand_eye
from torchcal.kinematics.transforms import homogeneous, rpy_to_matrix


def _frame(rpy, xyz):
    return homogeneous(rpy_to_matrix(torch.tensor(rpy, dtype=torch.float64)), torch.tensor(xyz, dtype=torch.float64))


def _poses(n, seed):
    g = torch.Generator().manual_seed(seed)
    return homogeneous(rpy_to_matrix((torch.rand(n, 3, generator=g, dtype=torch.float64) - 0.5) * 4),
                       torch.rand(n, 3, generator=g, dtype=torch.float64))


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_recovers_both_frames_even_when_the_mount_is_turned_half_a_turn(seed):
    F = _poses(60, seed)
    X = _frame([0.05, -0.1, 2.5], [2.0, -1.0, 0.4])
    M = _frame([3.14, 0.02, 0.3], [0.001, 0.016, 0.12])  # 180° about x, like the UR10 T-Mac's nominal guess
    Xe, Me = hand_eye(F, X @ F @ M, seed=seed)
    assert torch.allclose(Xe, X, atol=1e-9) and torch.allclose(Me, M, atol=1e-9)


def test_noise_gives_close_frames():
    F = _poses(200, 3)
    X, M = _frame([0.0, 0.0, 1.0], [1.5, 0.2, 0.1]), _frame([0.1, 0.2, 0.3], [0.0, 0.0, 0.1])
    T = X @ F @ M
    g = torch.Generator().manual_seed(0)
    T[:, :3, 3] += 1e-4 * torch.randn(200, 3, generator=g, dtype=torch.float64)
    Xe, Me = hand_eye(F, T)
    assert (Xe[:3, 3] - X[:3, 3]).norm() < 1e-4 and (Me[:3, 3] - M[:3, 3]).norm() < 1e-4
    assert (Xe[:3, :3] - X[:3, :3]).abs().max() < 1e-4


def test_one_known_frame_gives_the_other():
    F = _poses(20, 4)
    X, M = _frame([0.3, 0.1, -0.4], [0.5, 0.5, 0.0]), _frame([0.0, 1.0, 0.0], [0.02, 0.0, 0.05])
    T = X @ F @ M
    assert torch.allclose(hand_eye(F, T, X=X)[1], M, atol=1e-10)
    assert torch.allclose(hand_eye(F, T, M=M)[0], X, atol=1e-10)


def test_motion_about_one_axis_is_refused():
    ang = torch.linspace(0, 3, 30, dtype=torch.float64)
    F = homogeneous(rpy_to_matrix(torch.stack([torch.zeros_like(ang), torch.zeros_like(ang), ang], 1)),
                    torch.zeros(30, 3, dtype=torch.float64))
    with pytest.raises(HandEyeError, match="the flange only turns about one direction"):
        hand_eye(F, F)
    with pytest.raises(HandEyeError, match="need >= 3"):
        hand_eye(F[:2], F[:2])
