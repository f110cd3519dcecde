"""The error variable of each joint (Paper II (24)): command q_i or URDF θ_i, whatever the coupling."""

import pytest
import torch
from hypothesis import given, settings
from hypothesis import strategies as st

from torchcal.kinematics.joint_map import JointMap, normalize_error_variable


@st.composite
def joint_maps(draw):
    n = draw(st.integers(2, 6))
    seed = draw(st.integers(0, 10_000))
    g = torch.Generator().manual_seed(seed)
    A = torch.eye(n, dtype=torch.float64) + 0.5 * torch.randn(n, n, generator=g, dtype=torch.float64).tril(-1)  # invertible
    offset = torch.randn(n, generator=g, dtype=torch.float64)
    lo = -1.0 - torch.rand(n, generator=g, dtype=torch.float64)
    limits = torch.stack([lo, lo + 0.5 + 2 * torch.rand(n, generator=g, dtype=torch.float64)], 1)
    ev = draw(st.lists(st.sampled_from(["command", "joint"]), min_size=n, max_size=n))
    return JointMap([f"J{i + 1}" for i in range(n)], A, offset, limits, torch.zeros(n, dtype=torch.bool), ev), seed


@settings(max_examples=40, deadline=None)
@given(joint_maps())
def test_error_map_follows_the_chosen_variable(jm_seed):
    jm, seed = jm_seed
    q = torch.rand(7, jm.n, generator=torch.Generator().manual_seed(seed + 1), dtype=torch.float64)
    q = jm.limits[:, 0] + q * (jm.limits[:, 1] - jm.limits[:, 0])
    A, b = jm.error_map()
    u = q @ A.T + b
    theta = jm.to_joint(q)
    for i, var in enumerate(jm.error_variable):
        assert torch.allclose(u[:, i], q[:, i] if var == "command" else theta[:, i], atol=1e-14)
    # the ranges are those of the variable over the command box: every u lies inside, and each end is reached
    r = jm.error_ranges()
    assert (u >= r[:, 0] - 1e-12).all() and (u <= r[:, 1] + 1e-12).all()
    corners = torch.where(torch.rand(512, jm.n, generator=torch.Generator().manual_seed(seed + 2)) < 0.5,
                          jm.limits[:, 0], jm.limits[:, 1])
    uc = corners @ A.T + b
    assert torch.allclose(uc.min(0).values, r[:, 0], atol=1e-12) or jm.n > 5  # 512 corners cover 2^n for n <= 5
    assert torch.allclose(uc.max(0).values, r[:, 1], atol=1e-12) or jm.n > 5


def test_error_variable_names_the_joint_when_wrong():
    with pytest.raises(ValueError, match="J2.*'gearbox'"):
        normalize_error_variable(["command", "gearbox"], 2, ["J1", "J2"])
    with pytest.raises(ValueError, match="one entry per joint"):
        normalize_error_variable(["command"], 2)
    assert normalize_error_variable("joint", 3) == ["joint"] * 3
