"""A flat view of a model's free parameters, for solvers that work on one vector.

What each entry is (its name, role, kind and default prior scale) comes from
the modules' declarations (:class:`torchcal.core.params.ParamGroup`, see
:func:`parameter_groups`), never from parameter names.
"""

from __future__ import annotations

from typing import Iterable

import torch

from ..core.exceptions import InputError
from torch import nn

from ..core.params import ANGLE, ParamGroup


def parameter_groups(model: nn.Module) -> list[ParamGroup]:
    """Every learnable parameter of ``model`` with its declaration, in ``named_parameters()`` order.

    Uses ``model.parameter_groups()`` where the model has one; otherwise walks
    ``model.named_modules()`` and asks each module that declares its
    parameters (``param_groups(prefix)``) for them. A parameter no module
    declares is an error: its kind and prior would have to be guessed.
    """
    if callable(getattr(model, "parameter_groups", None)):
        groups = list(model.parameter_groups())
    else:
        groups = []
        for prefix, module in model.named_modules():
            declare = getattr(module, "param_groups", None)
            if callable(declare) and module is not model:
                groups += list(declare(prefix))
    by_name: dict[str, ParamGroup] = {}
    for g in groups:
        if g.name in by_name:
            raise ValueError(f"parameter '{g.name}' is declared twice (two modules' param_groups())")
        by_name[g.name] = g
    out = []
    for name, p in model.named_parameters():
        g = by_name.pop(name, None)
        if g is None:
            raise ValueError(f"{type(model).__name__}: parameter '{name}' {tuple(p.shape)} has no declaration; "
                             f"its module must list it in param_groups() (kind, unit, prior sigma), "
                             f"or the model must provide parameter_groups()")
        if g.mask.shape != p.shape:
            raise ValueError(f"ParamGroup '{name}': mask shape {tuple(g.mask.shape)} != parameter shape {tuple(p.shape)}")
        out.append(g)
    if by_name:
        raise ValueError(f"{type(model).__name__}: declared parameter groups {sorted(by_name)} are not parameters of the model")
    return out


class ParameterLayout:
    """Maps a model's free parameter entries to one vector and back.

    fixed: names (or prefixes, e.g. 'tools') of parameters held at their value;
    masks: optional {name: bool tensor} narrowing which entries are free
    (used to pin the redundant parameters, see :func:`torchcal.identify.gauge.fix_gauge`).
    ``entries`` lists (name, parameter, free mask) per group with a free entry;
    ``groups`` the matching declarations.
    """

    def __init__(self, model: nn.Module, fixed: Iterable[str] = (), masks: dict[str, torch.Tensor] | None = None,
                 groups: list[ParamGroup] | None = None):
        self.model = model
        self.fixed = self.fixed_names(fixed)
        self._all_groups = parameter_groups(model) if groups is None else groups
        names = [g.name for g in self._all_groups]
        unknown = [f for f in self.fixed if not any(n == f or n.startswith(f + ".") for n in names)]
        if unknown:  # a misspelt group would fit what the user meant to hold fixed, and say nothing
            prefixes = sorted({n.split(".")[0] for n in names} | set(names))
            raise InputError(f"fixed: {', '.join(repr(f) for f in unknown)} names no parameter group of the model; "
                             f"give a name or a prefix of: {', '.join(prefixes)}")
        params = dict(model.named_parameters())
        self.entries: list[tuple[str, nn.Parameter, torch.Tensor]] = []
        self.groups: list[ParamGroup] = []
        for g in self._all_groups:
            name = g.name
            if any(name == f or name.startswith(f + ".") for f in self.fixed):
                continue
            p = params[name]
            mask = g.mask.to(device=p.device, dtype=torch.bool).clone()
            if masks is not None and name in masks:
                mask = mask & masks[name].to(mask.device)
            if mask.any():
                self.entries.append((name, p, mask))
                self.groups.append(g)
        self.size = sum(int(m.sum()) for _, _, m in self.entries)

    @staticmethod
    def fixed_names(fixed: Iterable[str] | str) -> tuple[str, ...]:
        """``fixed`` as the tuple a layout keeps (one name or several)."""
        return (fixed,) if isinstance(fixed, str) else tuple(fixed)

    def without(self, drop: torch.Tensor) -> "ParameterLayout":
        """A layout with the free entries flagged in ``drop`` (P,) bool pinned at their value."""
        masks, i = {}, 0
        for name, p, m in self.entries:
            k = int(m.sum())
            keep = m.clone()
            keep[m] = ~drop[i : i + k].to(m.device)
            masks[name] = keep
            i += k
        return ParameterLayout(self.model, self.fixed, masks, self._all_groups)

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

    def _flat_index(self) -> list:
        """Per entry: the flat indices of its free entries (None where all are free), computed once."""
        if getattr(self, "_index_cache", None) is None:
            self._index_cache = [None if bool(m.all()) else m.flatten().nonzero()[:, 0] for _, _, m in self.entries]
        return self._index_cache

    def has_jacobians(self, J: dict[str, torch.Tensor]) -> bool:
        """Whether ``J`` holds a Jacobian for every free group."""
        return all(name in J for name, _, _ in self.entries)

    def flatten_jacobian(self, J: dict[str, torch.Tensor], rows: int) -> torch.Tensor:
        """Stack per-group Jacobians (B, c, *param_shape) into (B, c, P) in layout order."""
        cols = []
        for (name, p, m), idx in zip(self.entries, self._flat_index()):
            if name not in J:
                # a group without a closed-form Jacobian must not be treated as one that does not move the points
                raise KeyError(f"no Jacobian for free parameter group '{name}' (point_jacobians returned {sorted(J)}): "
                               "the batched solvers (fit_batch, fleets) take closed-form Jacobians only; fit each "
                               "model with torchcal.fit (it falls back to autograd), give point_jacobians the group, "
                               "or hold it fixed")
            g = J[name]
            B, c = g.shape[:2]
            g = g.reshape(B, c, -1)
            # index_select with a precomputed index: boolean-mask indexing costs a nonzero() pass every call
            cols.append(g if idx is None else g.index_select(2, idx.to(g.device)))
        if not cols:
            return torch.zeros(rows, 0, 0)
        return torch.cat(cols, -1)

    def _per_entry(self, values) -> list:
        """Flatten a per-group, per-entry attribute to the free entries, layout order."""
        out = []
        for g, (_, _, m) in zip(self.groups, self.entries):
            out += [val for val, keep in zip(values(g), m.flatten().tolist()) if keep]
        return out

    def names(self) -> list[str]:
        """A readable name for each free entry, e.g. 'joint3.eps_z.c2', 'base.eps_x', 'tool1.dz' (declared)."""
        return self._per_entry(lambda g: g.entry_names)

    def roles(self) -> list[str]:
        """Declared role of each free entry: 'joint', 'backlash', 'frame', 'tool', 'compliance', ..."""
        return self._per_entry(lambda g: [g.role] * g.mask.numel())

    def kinds(self) -> list[str]:
        """Declared kind of each free entry: 'angle', 'length' or 'dimensionless'."""
        return self._per_entry(lambda g: g.kinds)

    def prior_sigma(self) -> torch.Tensor:
        """(P,) declared default prior standard deviation of each free entry, SI."""
        return torch.tensor(self._per_entry(lambda g: g.prior_sigma.flatten().tolist()), dtype=torch.float64)

    def is_rotation(self) -> torch.Tensor:
        """(P,) bool: which free entries are angles (rad) rather than lengths (m) or numbers (declared kinds)."""
        return torch.tensor([k == ANGLE for k in self.kinds()], dtype=torch.bool)


@torch.no_grad()
def copy_overlap(src: torch.nn.Module, dst: torch.nn.Module) -> None:
    """Write ``src``'s parameter values into ``dst`` where both have the parameter (the overlapping leading
    slice along every axis, e.g. the common Chebyshev orders); every other entry of ``dst`` becomes zero.
    A warm start between models of one factory with different orders."""
    sp = dict(src.named_parameters())
    for name, p in dst.named_parameters():
        p.zero_()
        q = sp.get(name)
        if q is not None and q.ndim == p.ndim:
            sl = tuple(slice(0, min(a, b)) for a, b in zip(p.shape, q.shape))
            p[sl] = q[sl].to(p)
