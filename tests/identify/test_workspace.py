"""torchcal.identify.workspace: named buffers reused across iterations."""

from __future__ import annotations

import torch

from torchcal.identify.workspace import Workspace


def test_take_reuses_a_name_and_grows_it():
    """A name hands out views of one buffer while it is big enough (the same memory: no allocation, no page
    faults), a bigger request or another dtype gets a new one, and different names never share memory."""
    ws = Workspace()
    like = torch.empty(0, dtype=torch.float64)
    a = ws.take("a", (4, 5), like)
    assert a.shape == (4, 5) and a.dtype == torch.float64 and a.is_contiguous()
    b = ws.take("a", (3, 2), like)
    assert b.data_ptr() == a.data_ptr() and b.shape == (3, 2)
    c = ws.take("a", (7, 5), like)
    assert c.shape == (7, 5) and c.numel() == 35
    assert ws.take("a", (2, 2), like).data_ptr() == c.data_ptr()
    d = ws.take("b", (7, 5), like)
    d.fill_(1.0)
    c.fill_(2.0)
    assert bool((d == 1.0).all())  # names are separate buffers
    f32 = ws.take("a", (2, 2), torch.empty(0, dtype=torch.float32))
    assert f32.dtype == torch.float32
