"""small_matmul's off-CPU forms (a broadcast product and a sum; multiply-adds of rows) against torch's matmul, on
the shapes and batch broadcasting the kinematics and the batched step use (the CUDA tests run them on the GPU)."""

import torch
from hypothesis import given, settings
from hypothesis import strategies as st

from torchcal.kinematics.transforms import elementwise_matmul, rowwise_matmul, small_matmul


@settings(max_examples=40, deadline=None)
@given(seed=st.integers(0, 10_000), i=st.integers(1, 6), k=st.integers(1, 6), j=st.integers(1, 6),
       batch_a=st.lists(st.integers(1, 4), max_size=3), drop=st.integers(0, 3), ones=st.integers(0, 7))
def test_elementwise_forms_equal_matmul(seed, i, k, j, batch_a, drop, ones):
    g = torch.Generator().manual_seed(seed)
    batch_b = batch_a[min(drop, len(batch_a)):]  # fewer leading dims, broadcast against a's
    batch_b = [1 if (ones >> n) & 1 else d for n, d in enumerate(batch_b)]  # and size-1 dims
    a = torch.randn(*batch_a, i, k, generator=g, dtype=torch.float64)
    b = torch.randn(*batch_b, k, j, generator=g, dtype=torch.float64)
    ref = a @ b
    for form in (elementwise_matmul, rowwise_matmul):
        got = form(a, b)
        assert got.shape == ref.shape
        assert torch.allclose(got, ref, rtol=1e-13, atol=1e-13)


def test_small_matmul_is_matmul_on_the_cpu():
    a = torch.randn(5, 3, 3, dtype=torch.float64)
    b = torch.randn(5, 3, 1, dtype=torch.float64)
    assert torch.equal(small_matmul(a, b), a @ b)
