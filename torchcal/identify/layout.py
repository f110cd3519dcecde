"""A flat view of a model's free parameters, for solvers that work on one vector."""

from __future__ import annotations

from typing import Iterable

import torch
from torch import nn


def _masks(model: nn.Module) -> dict[str, torch.Tensor]:
    """Which entries of each parameter are free (unused Chebyshev orders are not)."""
    masks = {}
    for name, p in model.named_parameters():
        masks[name] = torch.ones_like(p, dtype=torch.bool)
    je = getattr(model, "joint_errors", None)
    if je is not None:
        masks["joint_errors.coef"] = je.mask.expand_as(je.coef).clone()
        masks["joint_errors.backlash"] = je.backlash_mask.clone()
    comp = getattr(model, "compliance", None)
    if comp is not None:
        masks["compliance.coef"] = comp.mask.clone()
    return masks


class ParameterLayout:
    """Maps a model's free parameter entries to one vector and back.

    fixed: names (or prefixes, e.g. 'tools') of parameters held at their value;
    masks: optional {name: bool tensor} narrowing which entries are free
    (used to pin the redundant parameters, see :func:`torchcal.identify.gauge.fix_gauge`).
    """

    def __init__(self, model: nn.Module, fixed: Iterable[str] = (), masks: dict[str, torch.Tensor] | None = None):
        self.model = model
        self.fixed = tuple(fixed)
        params = dict(model.named_parameters())
        self.entries: list[tuple[str, nn.Parameter, torch.Tensor]] = []
        for name, mask in _masks(model).items():
            if any(name == f or name.startswith(f + ".") for f in self.fixed):
                continue
            if masks is not None and name in masks:
                mask = mask & masks[name].to(mask.device)
            if mask.any():
                self.entries.append((name, params[name], mask))
        self.size = sum(int(m.sum()) for _, _, m in self.entries)

    def without(self, drop: torch.Tensor) -> "ParameterLayout":
        """A layout with the free entries flagged in ``drop`` (P,) bool pinned at their value."""
        masks, i = {}, 0
        for name, p, m in self.entries:
            k = int(m.sum())
            keep = m.clone()
            keep[m] = ~drop[i : i + k].to(m.device)
            masks[name] = keep
            i += k
        return ParameterLayout(self.model, self.fixed, masks)

    def get(self) -> torch.Tensor:
        """Current free values (P,)."""
        return torch.cat([p.detach()[m] for _, p, m in self.entries]) if self.entries else torch.zeros(0, dtype=torch.float64)

    def as_dict(self, x: torch.Tensor) -> dict[str, torch.Tensor]:
        """Parameter tensors with the free entries taken from x, differentiably (for torch.func.functional_call)."""
        out, i = {}, 0
        for name, p, m in self.entries:
            k = int(m.sum())
            out[name] = p.detach().masked_scatter(m, x[i : i + k].to(p))
            i += k
        return out

    @torch.no_grad()
    def set(self, x: torch.Tensor) -> None:
        """Write free values (P,) into the model."""
        i = 0
        for _, p, m in self.entries:
            k = int(m.sum())
            p[m] = x[i : i + k].to(p)
            i += k

    def flatten_jacobian(self, J: dict[str, torch.Tensor], rows: int) -> torch.Tensor:
        """Stack per-group Jacobians (B, c, *param_shape) into (B, c, P) in layout order."""
        cols = []
        for name, p, m in self.entries:
            if name not in J:
                # a group without a closed-form Jacobian must not be treated as one that does not move the points
                raise KeyError(f"no Jacobian for free parameter group '{name}' (point_jacobians returned {sorted(J)}); "
                               f"fix it or hold it fixed")
            g = J[name]
            B, c = g.shape[:2]
            cols.append(g.reshape(B, c, -1)[:, :, m.flatten()])
        return torch.cat(cols, -1)

    def names(self) -> list[str]:
        """A readable name for each free entry, e.g. 'joint3.eps_z.c2', 'base.delta_x', 'tool1.dz'."""
        out = []
        for name, p, m in self.entries:
            out += [n for n, keep in zip(self._entry_names(name, p), m.flatten().tolist()) if keep]
        return out

    def _entry_names(self, name: str, p: torch.Tensor) -> list[str]:
        je = getattr(self.model, "joint_errors", None)
        if name == "joint_errors.coef" and je is not None:
            return je.parameter_names()[0]
        if name == "joint_errors.backlash" and je is not None:
            return je.parameter_names()[1]
        comp = getattr(self.model, "compliance", None)
        if name == "compliance.coef" and comp is not None:
            return comp.parameter_names()
        if name == "base.twist":
            return [f"base.{t}" for t in ("eps_x", "eps_y", "eps_z", "delta_x", "delta_y", "delta_z")]
        if name == "tools.delta":
            return [f"tool{t}.d{a}" for t in range(p.shape[0]) for a in "xyz"]
        return [f"{name}[{i}]" for i in range(p.numel())]

    def is_rotation(self) -> torch.Tensor:
        """(P,) bool: which free entries are angles (rad) rather than lengths (m)."""
        flags = []
        for n in self.names():
            term = n.split(".")[-2] if n.count(".") >= 2 else n.split(".")[-1]
            flags.append(term.startswith("eps") or term == "backlash" or "compliance" in n)
        return torch.tensor(flags, dtype=torch.bool)
