"""torchcal.core.hugepages: large CPU buffers advised onto transparent huge pages, their contents untouched."""

from __future__ import annotations

import sys
from pathlib import Path

import pytest
import torch

from torchcal.core import hugepages
from torchcal.identify.workspace import Workspace

_THP = Path("/sys/kernel/mm/transparent_hugepage/enabled")


def _thp_mode() -> str | None:
    """The system's transparent huge page mode ('always', 'madvise', 'never'), None off Linux."""
    try:
        text = _THP.read_text()
    except OSError:
        return None
    return text.split("[", 1)[1].split("]", 1)[0] if "[" in text else None


def _huge_kib(t: torch.Tensor) -> int:
    """KiB of huge pages backing the mappings that hold ``t``'s memory (/proc/self/smaps)."""
    lo, hi = t.data_ptr(), t.data_ptr() + t.numel() * t.element_size()
    total, inside = 0, False
    for line in Path("/proc/self/smaps").read_text().splitlines():
        head = line.split(" ", 1)[0]
        if "-" in head and ":" not in head:
            a, b = (int(x, 16) for x in head.split("-"))
            inside = a < hi and b > lo
        elif inside and line.startswith("AnonHugePages:"):
            total += int(line.split()[1])
    return total


def test_advice_keeps_the_contents_and_skips_what_it_cannot_back():
    """Advising changes no value (written before and after), small tensors and a tensor on the meta device are
    left alone, and empty() gives a tensor of the asked shape, dtype and device."""
    x = torch.arange(6 << 17, dtype=torch.float64)  # 6 MiB
    ref = x.clone()
    hugepages.advise(x)
    assert torch.equal(x, ref)
    x.mul_(2.0)
    assert torch.equal(x, 2.0 * ref)
    assert not hugepages.advise(torch.ones(16, dtype=torch.float64))
    assert not hugepages.advise(torch.empty(1 << 22, dtype=torch.float64, device="meta"))
    e = hugepages.empty((3, 1 << 18), torch.empty(0, dtype=torch.float32))
    assert e.shape == (3, 1 << 18) and e.dtype == torch.float32 and e.device.type == "cpu"


@pytest.mark.skipif(not sys.platform.startswith("linux") or _thp_mode() not in ("always", "madvise"),
                    reason="transparent huge pages are not enabled here")
def test_a_workspace_buffer_lands_on_huge_pages():
    """A large Workspace buffer (where a fleet's linearizations and Gram blocks live), written after it was
    taken, is backed by huge pages in madvise mode, where memory never advised is not (the test would fail if
    Workspace allocated plainly)."""
    like = torch.empty(0, dtype=torch.float64)
    ws = Workspace()
    buf = ws.take("gram", (64 << 17,), like)  # 64 MiB
    buf.fill_(1.0)
    assert _huge_kib(buf) >= 2048
    if _thp_mode() == "madvise":
        plain = torch.empty(64 << 17, dtype=torch.float64)
        plain.fill_(1.0)
        assert _huge_kib(plain) == 0
