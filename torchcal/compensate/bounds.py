"""compensate()'s bounds: the defaults and per-joint bound tensors.

A module of its own so that :mod:`.result` (reasons of flagged rows) and :mod:`.newton` (the solver) share
them without importing each other.
"""

from __future__ import annotations

import math

import torch

from ..core.exceptions import InputError

DEFAULT_BOUND = "default"
"""compensate()'s default bounds: max_correction 30 deg per revolute joint (:data:`DEFAULT_CORRECTION_DEG`),
max_step 5 deg (:data:`DEFAULT_STEP_DEG`), 5 mm per prismatic joint for both."""

DEFAULT_CORRECTION_DEG = 30.0
"""The default correction bound (revolute joints). It is an outer guard, not what tells a branch flip from a
legitimate correction: that is the branch test (:mod:`.branch`: det J of the controller's kinematics keeps its
sign between q_nom and q_new). Measured on Paper II's simulated FANUC: corrections next to the wrist (q5 of
4-9 deg) need 5-8 deg and converge on their branch; the flips the old 5 deg bound was made against move a joint
30-117 deg and change the sign of det J."""
DEFAULT_STEP_DEG = 5.0
DEFAULT_PRISMATIC_MM = 5.0


def per_joint_bound(bound, n: int, dtype, device, name: str = "bound", prismatic=None) -> torch.Tensor | None:
    """A step or correction bound as an (n,) tensor: None stays None, a number applies to every joint.

    :data:`DEFAULT_BOUND` is :data:`DEFAULT_CORRECTION_DEG` (``name`` 'max_correction', also any other name)
    or :data:`DEFAULT_STEP_DEG` (``name`` 'max_step') per revolute and 5 mm per prismatic joint
    (``prismatic``: (n,) bool, the controller joints; all revolute if None).
    For other per-joint bounds pass an (n,) tensor (rad / m), e.g.
    ``units.joint_scale(prismatic) * 2.0`` for 2 deg / 2 mm. Raises
    ValueError for a wrong length or a bound that is not positive.
    """
    if bound is None:
        return None
    if isinstance(bound, str):
        if bound != DEFAULT_BOUND:
            raise InputError(f"compensate: {name} must be a number, one per joint, None or '{DEFAULT_BOUND}', got {bound!r}")
        pr = torch.zeros(n, dtype=torch.bool) if prismatic is None else torch.as_tensor(prismatic, dtype=torch.bool).cpu()
        deg = DEFAULT_STEP_DEG if name == "max_step" else DEFAULT_CORRECTION_DEG
        bound = torch.where(pr, torch.tensor(DEFAULT_PRISMATIC_MM * 1e-3, dtype=torch.float64),
                            torch.tensor(math.radians(deg), dtype=torch.float64))
    t = torch.as_tensor(bound, dtype=dtype, device=device)
    t = t.expand(n).clone() if t.ndim == 0 else t
    if t.shape != (n,):
        raise InputError(f"compensate: {name} must be a number or one value per joint ({n}), got shape {tuple(t.shape)}")
    if not bool((t > 0).all()):
        raise InputError(f"compensate: {name} must be positive, got {t.tolist()}")
    return t
