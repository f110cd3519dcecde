"""CPU products through numpy's BLAS (torchcal.core.blas): the same products as torch's, the machine's choice,
and numpy's thread pool held by limit_threads."""

from __future__ import annotations

import pytest
import torch
from hypothesis import given, settings
from hypothesis import strategies as hst

from torchcal.core import blas
from torchcal.core.threads import limit_threads


@pytest.fixture
def choose(monkeypatch):
    """Set the choice through the environment, as a user would (the cached decision re-read)."""

    def set_(value):
        monkeypatch.setenv(blas.ENV, value)
        blas.numpy_blas.cache_clear()

    yield set_
    blas.numpy_blas.cache_clear()


@settings(max_examples=30, deadline=None)
@given(B=hst.integers(1, 5), m=hst.integers(1, 9), k=hst.integers(1, 12), n=hst.integers(1, 9),
       ta=hst.booleans(), tb=hst.booleans(), strided_out=hst.booleans(), seed=hst.integers(0, 2**31 - 1))
def test_numpy_products_are_torchs(B, m, k, n, ta, tb, strided_out, seed):
    """Views as the fleet's contraction passes them (transposed matrices, batches apart, an output inside a larger
    buffer) give torch.bmm's product, and nothing outside the output is written."""
    g = torch.Generator().manual_seed(seed)
    a = torch.randn(B, k, m, generator=g, dtype=torch.float64).transpose(1, 2) if ta else \
        torch.randn(B, 2, m, k, generator=g, dtype=torch.float64)[:, 1]
    b = torch.randn(B, n, k, generator=g, dtype=torch.float64).transpose(1, 2) if tb else \
        torch.randn(B, k, n, generator=g, dtype=torch.float64)
    big = torch.full((B, 3, m, n), 7.0, dtype=torch.float64)
    out = big[:, 1] if strided_out else torch.empty(B, m, n, dtype=torch.float64)
    blas.numpy_blas.cache_clear()
    try:
        with pytest.MonkeyPatch.context() as mp:
            mp.setenv(blas.ENV, "numpy")
            got = blas.bmm(a, b, out)
    finally:
        blas.numpy_blas.cache_clear()
    assert got.data_ptr() == out.data_ptr()
    torch.testing.assert_close(out, torch.bmm(a, b), rtol=1e-12, atol=1e-12)
    if strided_out:
        assert bool((big[:, 0] == 7.0).all()) and bool((big[:, 2] == 7.0).all())


def test_the_choice_is_the_environments_else_the_cpus(choose, monkeypatch):
    choose("numpy")
    assert blas.numpy_blas()
    choose("torch")
    assert not blas.numpy_blas()
    choose("mkl")
    with pytest.raises(ValueError, match="TORCHCAL_BLAS"):
        blas.numpy_blas()
    choose("")
    mkl = torch.backends.mkl.is_available()
    for vendor, expected in (("GenuineIntel", False), ("AuthenticAMD", mkl), ("", False)):
        monkeypatch.setattr(blas, "_vendor", lambda v=vendor: v)
        blas.numpy_blas.cache_clear()
        assert blas.numpy_blas() is expected, vendor


def test_limit_threads_holds_numpys_blas_pool(choose):
    """Two streams each on one thread must not each wake numpy's OpenBLAS pool (it spins while it waits)."""
    threadpoolctl = pytest.importorskip("threadpoolctl")
    pools = threadpoolctl.ThreadpoolController().select(user_api="blas")
    if not pools.lib_controllers:
        pytest.skip("numpy without a BLAS threadpoolctl knows")

    def counts():
        return [c.num_threads for c in threadpoolctl.ThreadpoolController().select(user_api="blas").lib_controllers]

    with threadpoolctl.threadpool_limits(3, user_api="blas"):  # a pool the limit visibly changes, on any machine
        choose("numpy")
        before = counts()
        with limit_threads(1):
            assert counts() == [1] * len(before)
        assert counts() == before == [3] * len(before)
        choose("torch")
        with limit_threads(1):
            assert counts() == before  # torch's products: numpy's pool left as the user set it
