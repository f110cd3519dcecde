"""Paper I's axis perturbation model (2)-(7): tables, normalization, switched-off pairs, declarations."""

import numpy as np
import pytest
import torch
from numpy.polynomial import chebyshev as npcheb

from torchcal.error_models.axis_perturbation import AxisPerturbation, order_table
from torchcal.core.params import ANGLE, LENGTH

LIM = torch.tensor([[0.0832, 6.0811], [0.0372, 2.5571], [0.0074, 0.9882], [-4.7072, 4.7106], [-1.9111, 1.9181]])
PRISMATIC = torch.tensor([True, True, True, False, False])


def random_ap(seed=0, orders=4, pairs=None):
    ap = AxisPerturbation(LIM, PRISMATIC, orders, pairs, list("XYZCB"))
    g = torch.Generator().manual_seed(seed)
    with torch.no_grad():
        ap.coef.copy_(torch.randn(ap.coef.shape, generator=g) * 1e-4)
    return ap


def test_f_is_the_chebyshev_series_of_the_normalized_command():
    """f_ij (6)-(7) against numpy's Chebyshev series on qbar = 2 (q - min) / (max - min) - 1."""
    ap = random_ap(1)
    x = torch.linspace(float(LIM[4, 0]), float(LIM[4, 1]), 11)
    lam = 2 * (x.numpy() - LIM[4, 0].item()) / (LIM[4, 1] - LIM[4, 0]).item() - 1
    ref = npcheb.chebval(lam, ap.coef[2, 4].detach().numpy())
    assert np.allclose(ap.f(2, 4, x).detach().numpy(), ref, atol=1e-16)


def test_delta_is_the_sum_of_the_tables_3():
    ap = random_ap(2)
    g = torch.Generator().manual_seed(3)
    q = LIM[:, 0] + torch.rand(7, 5, generator=g) * (LIM[:, 1] - LIM[:, 0])
    with torch.no_grad():
        dq = ap.delta(q)
        ref = torch.stack([sum(ap.f(i, j, q[:, j]) for j in range(5)) for i in range(5)], 1)
    assert torch.allclose(dq, ref, atol=1e-18)


def test_switched_off_pairs_contribute_nothing_and_are_not_parameters():
    ap = AxisPerturbation(LIM, PRISMATIC, 3, pairs=[(0, 0), (2, 4), (3, 3)])
    with torch.no_grad():
        ap.coef.fill_(1e-3)  # also in the switched-off tables: the mask must keep them out
    assert ap.pairs == [(0, 0), (2, 4), (3, 3)]
    assert float(ap.f(1, 1, torch.tensor([1.0])).detach().abs()) == 0.0
    q = LIM.mean(1).expand(2, 5)
    dq = ap.delta(q).detach()
    assert float(dq[:, [1, 4]].abs().max()) == 0.0 and float(dq[:, 0].abs().min()) > 0
    (g,) = ap.param_groups("axis_errors")
    assert int(g.mask.sum()) == 3 * 4
    assert g.role == "axis"


def test_kind_follows_the_output_axis():
    ap = AxisPerturbation(LIM, PRISMATIC, 1, axis_names=list("XYZCB"))
    (g,) = ap.param_groups()
    kinds = np.array(g.kinds).reshape(5, 5, 2)
    assert (kinds[:3] == LENGTH).all() and (kinds[3:] == ANGLE).all()
    assert g.entry_names[2 * 5 * 2 + 4 * 2 + 1] == "axis.f_Z_B.c1"


def test_slopes_match_finite_differences():
    ap = random_ap(4)
    x = torch.linspace(float(LIM[3, 0]) + 0.01, float(LIM[3, 1]) - 0.01, 9)
    h = 1e-6
    fd = (ap.f(4, 3, x + h) - ap.f(4, 3, x - h)) / (2 * h)
    assert torch.allclose(ap.df(4, 3, x), fd, rtol=1e-6, atol=1e-12)
    q = LIM.mean(1)[None].repeat(9, 1)
    q[:, 3] = x
    D = ap.slopes(q)
    assert torch.allclose(D[:, 4, 3], ap.df(4, 3, x), atol=1e-15)


def test_any_chain_and_bad_tables():
    ap = AxisPerturbation(torch.tensor([[-1.0, 1.0]] * 6), torch.zeros(6, dtype=torch.bool), 6)
    assert ap.delta(torch.zeros(3, 6)).shape == (3, 6)
    with pytest.raises(ValueError, match="outside"):
        order_table(2, 3, pairs=[(0, 3)])
    with pytest.raises(ValueError, match="order"):
        AxisPerturbation(LIM, PRISMATIC, 20)
