"""Each unit's measurement frame (``measurement_frame: estimate``): a plant measures every unit from
wherever the tracker stood at its cell. The frame is estimated per unit on the nominal robot (as ``torchcal
fit`` estimates it), the unit is solved in its robot base frame, and its model gets the frame back as its
nominal measurement frame."""

from __future__ import annotations

import logging

import torch

from ..core.progress import task
from .common import failed_row

log = logging.getLogger("torchcal")


def align_units(cfg, robot, loaded: list, rows: dict, label: str) -> tuple[list, dict, dict]:
    """With ``measurement_frame: estimate`` (each unit measured from wherever its tracker stood): every unit's
    measurement frame from its own identification data on the nominal robot, as ``torchcal fit`` estimates
    it. -> (the units aligned, {unit: (4, 4) robot base in the measurement frame, SI}, {unit: the
    alignment's summary, alignment.json}); a unit whose data cannot determine its frame is failed in ``rows``.
    Other modes: the units unchanged and no frames (one frame, the config's, for every unit)."""
    from .common import placement_text
    from .fit import config_alignment, config_frame

    if config_frame(cfg)[0] != "estimate":
        return loaded, {}, {}
    kept, frames, summaries = [], {}, {}
    with task("estimating each unit's measurement frame", total=len(loaded)) as bar:
        for name, ident, val in loaded:
            try:
                _, frame, res = config_alignment(cfg, robot, ident, f"{label}: unit {name}")
            except Exception as exc:  # this unit's failure, not the fleet's
                rows[name] = failed_row(exc, unit=name)
                log.warning("unit %s: not fitted: %s", name, exc)
            else:
                frames[name], summaries[name] = frame.detach().cpu(), res.summary()
                log.info(f"unit {name}: measurement frame: {placement_text(summaries[name])} (alignment residual "
                         f"rms {summaries[name]['residual_mm']['rms']:.4f} mm)")
                kept.append((name, ident, val))
            bar.advance(note=name)
    return kept, frames, summaries


def in_base(data, frame: torch.Tensor | None):
    """A unit's measurements with the points moved from its measurement frame into its robot base frame
    (``frame``: (4, 4) the base in the measurement frame; None: unchanged). A rigid move leaves every distance,
    and so the fit's isotropic tracker weighting, as it was."""
    if frame is None:
        return data
    from dataclasses import replace

    R, t = frame[:3, :3].to(data.xyz), frame[:3, 3].to(data.xyz)
    return replace(data, xyz=(data.xyz - t) @ R)


__all__ = ["align_units", "in_base"]
