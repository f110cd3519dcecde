import numpy as np
import pytest
import torch

from torchcal.core.basis import chebyshev
from torchcal.error_models.joint import JointErrors
from torchcal.error_models.frame import FrameCorrection, ToolSet


def make(orders=3, backlash=True, n=3):
    ranges = torch.tensor([[-1.0, 1.0], [0.0, 2.0], [-3.0, 3.0]])[:n]
    je = JointErrors(ranges, orders, backlash)
    with torch.no_grad():
        je.coef.normal_(generator=torch.Generator().manual_seed(0))
        je.backlash.normal_(generator=torch.Generator().manual_seed(1))
    return je, ranges


def test_twists_are_the_chebyshev_series_of_eq_23():
    je, ranges = make(orders=[1, 2, 3])
    theta = torch.tensor([[0.5, 1.5, -2.0], [-1.0, 0.0, 3.0]])
    e = je.twists(theta)
    for i in range(3):
        lam = 2 * (theta[:, i] - ranges[i, 0]) / (ranges[i, 1] - ranges[i, 0]) - 1
        m = [1, 2, 3][i]
        ref = chebyshev(lam, m) @ je.coef[i, :, : m + 1].T  # orders above m are masked out
        assert torch.allclose(e[:, i], ref)


def test_backlash_enters_eps_z_with_the_direction_sign():
    je, _ = make()
    theta = torch.tensor([[0.2, 0.4, 0.6]])
    plus = je.twists(theta, torch.ones(1, 3))
    minus = je.twists(theta, -torch.ones(1, 3))
    none = je.twists(theta, None)
    assert torch.allclose(plus[..., [0, 1, 3, 4, 5]], minus[..., [0, 1, 3, 4, 5]])
    assert torch.allclose((plus + minus)[..., 2] / 2, none[..., 2])
    assert ((plus - minus)[..., 2].abs() > 0).all()


def test_order_tables_and_validation():
    je = JointErrors(torch.tensor([[0.0, 1.0]] * 2), orders=[[0, 1, 2, -1, 0, 0], [3, 3, 3, 3, 3, 3]])
    assert je.mask[0, 3].sum() == 0  # -1 switches a term off
    assert je.mask[0, 2].sum() == 3
    with pytest.raises(ValueError, match="order"):
        JointErrors(torch.tensor([[0.0, 1.0]] * 2), orders=11)
    with pytest.raises(ValueError, match="per-joint"):
        JointErrors(torch.tensor([[0.0, 1.0]] * 2), orders=[1, 2, 3])


def test_frame_error_and_tools():
    fe = FrameCorrection(torch.eye(4))
    with torch.no_grad():
        fe.twist.copy_(torch.tensor([0.0, 0.0, 0.1, 0.01, 0.0, 0.0]))
    T = fe()
    assert torch.allclose(T[:3, 3], torch.tensor([0.01, 0.0, 0.0]))
    assert np.isclose(float(torch.atan2(T[1, 0], T[0, 0]).detach()), 0.1)
    ts = ToolSet(torch.tensor([[0.0, 0.0, 0.1]]))
    with torch.no_grad():
        ts.delta.fill_(1e-3)
    assert torch.allclose(ts(), torch.tensor([[1e-3, 1e-3, 0.101]]))
    with pytest.raises(ValueError):
        ToolSet(torch.zeros(3))
