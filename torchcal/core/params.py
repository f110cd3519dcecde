"""What each learnable parameter group is: kind, unit and prior scale, declared by its module.

Solvers, priors and reports need to know whether an entry is an angle or a
length and how large it may plausibly be. That is declared here by the module
that owns the parameter (``param_groups()``), never inferred from names: a URDF
joint named ``tool_roll`` is still a joint.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import torch

ANGLE, LENGTH, DIMENSIONLESS = "angle", "length", "dimensionless"
KINDS = (ANGLE, LENGTH, DIMENSIONLESS)
UNITS = {ANGLE: "rad", LENGTH: "m", DIMENSIONLESS: "1"}
"""SI unit of each kind inside torchcal (files and the CLI use deg and mm)."""


@dataclass
class ParamGroup:
    """One ``nn.Parameter`` of a model, described entry by entry (row-major).

    name: the parameter's name as in ``model.named_parameters()``, e.g. 'joint_errors.coef';
    role: what it models, for priors and reports: 'joint' (kinematic error terms),
        'backlash', 'frame' (measurement/base frame), 'tool', 'compliance', or a
        module's own word;
    entry_names: readable name per entry, e.g. 'joint3.eps_z.c2';
    kinds: per entry, one of :data:`KINDS`;
    prior_sigma: (numel,) default prior standard deviation per entry, SI;
    mask: bool tensor of the parameter's shape, the entries that exist (unused
        Chebyshev orders, switched-off terms do not).

    Example:
        >>> import torch
        >>> from torchcal.core.params import ANGLE, ParamGroup
        >>> g = ParamGroup("base.twist", "frame", ["base.eps_x"], [ANGLE], torch.tensor([0.1]), torch.tensor([True]))
        >>> g.units
        ['rad']
    """

    name: str
    role: str
    entry_names: list[str]
    kinds: list[str]
    prior_sigma: torch.Tensor
    mask: torch.Tensor = field(repr=False)

    def __post_init__(self):
        n = self.mask.numel()
        if not (len(self.entry_names) == len(self.kinds) == self.prior_sigma.numel() == n):
            raise ValueError(f"ParamGroup '{self.name}': {len(self.entry_names)} names, {len(self.kinds)} kinds, "
                             f"{self.prior_sigma.numel()} sigmas for {n} entries")
        bad = sorted(set(self.kinds) - set(KINDS))
        if bad:
            raise ValueError(f"ParamGroup '{self.name}': unknown kind(s) {bad}; use {KINDS}")

    @property
    def units(self) -> list[str]:
        """SI unit per entry ('rad', 'm', '1')."""
        return [UNITS[k] for k in self.kinds]

    def is_angle(self) -> torch.Tensor:
        """(numel,) bool, row-major."""
        return torch.tensor([k == ANGLE for k in self.kinds], dtype=torch.bool)


def term_kinds(terms) -> list[str]:
    """Kinds of twist-ordered terms: names starting with 'eps' are angles, 'delta' lengths."""
    return [ANGLE if t.startswith("eps") else LENGTH for t in terms]
