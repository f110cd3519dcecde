import numpy as np
import torch
from hypothesis import given, settings
from hypothesis import strategies as st

from torchcal.core.basis import chebyshev, chebyshev_with_derivative, normalize, series


@settings(max_examples=50, deadline=None)
@given(st.lists(st.floats(-1.0, 1.0), min_size=1, max_size=20), st.integers(0, 10))
def test_chebyshev_matches_numpy(lam, order):
    lam_t = torch.tensor(lam)
    assert np.allclose(chebyshev(lam_t, order).numpy(), np.polynomial.chebyshev.chebvander(np.array(lam), order), atol=1e-12)


def test_derivative_matches_numpy_chebder_including_endpoints():
    lam = torch.linspace(-1, 1, 41)
    c, d = chebyshev_with_derivative(lam, 10)
    assert torch.allclose(c, chebyshev(lam, 10))
    for k in range(11):
        coef = np.zeros(11)
        coef[k] = 1.0
        ref = np.polynomial.chebyshev.chebval(lam.numpy(), np.polynomial.chebyshev.chebder(coef))
        assert np.allclose(d[:, k].numpy(), ref, atol=1e-10)


def test_normalize_maps_range_to_unit_interval_and_series():
    lo, hi = torch.tensor(-0.5), torch.tensor(2.0)
    assert torch.allclose(normalize(torch.tensor([-0.5, 0.75, 2.0]), lo, hi), torch.tensor([-1.0, 0.0, 1.0]))
    lam = torch.tensor([0.3])
    coef = torch.tensor([1.0, 2.0, 3.0])
    # 1 + 2 x + 3 (2 x^2 - 1)
    assert torch.allclose(series(coef, chebyshev(lam, 2)), torch.tensor([1 + 0.6 + 3 * (2 * 0.09 - 1)]))
