"""Paper II's joint-dependent 6-DOF error transforms E_i(q_i, s_i), eqs. (19)-(24).

Each of the six small error terms of E_i (20) is an order-m Chebyshev series
(23) of the joint's normalized error variable (24): the controller command q_i
by default, as the paper has it, or the URDF joint variable θ_i (the model
chooses, see :class:`torchcal.kinematics.JointMap`). Backlash (13)-(14) adds
``s_i * b_i(q_i)`` to eps_z, the rotation about the joint's own axis, with its
own (low, by default) order: quasi-random poses measured in sequence make a
joint's approach direction nearly a function of its position, and a backlash
series as rich as eps_z's then fits position errors as direction errors. Joint i's
E_i sits in the joint frame before the joint moves, so its constant terms are
the assembly errors of link i-1 (18) and there is none after the last joint
(19): that one belongs to the tool.
"""

from __future__ import annotations

from typing import Sequence

import torch
from torch import nn

from ..core.basis import chebyshev, normalize
from ..kinematics.transforms import twist_to_transform
from ..core.params import ANGLE, LENGTH, ParamGroup, term_kinds

TERMS = ("eps_x", "eps_y", "eps_z", "delta_x", "delta_y", "delta_z")
"""The six error terms of (20), in twist order: rotations (rad) then translations (m)."""

MAX_ORDER = 10
DEFAULT_BACKLASH_ORDER = 2
"""Order of the backlash series when backlash is switched on without one (``backlash=True``)."""

BACKLASH_SIGMA = 1e-2
"""Prior sigma (rad) of the constant backlash coefficient c0: wide, the data determine it."""

BACKLASH_VARIATION_SIGMA = 3e-5
"""Prior sigma (rad, ~0.002 deg) of the backlash coefficients c1.. (how backlash varies along the range).

Backlash varies with position by a fraction of itself (Paper II, Fig. 3; industrial
gearing: backlash 0.005-0.05 deg). Measured on the simulated FANUC in sequence order
(250 poses, 3 seeds, order 6, backlash order 2), model error at poses approached in
random directions: 0.022-0.056 mm with the joint terms' prior (0.01 rad), 0.021-0.029 mm
with this one, unchanged (0.015 mm) on data of the identification's own pattern.
"""


def joint_error_twists(
    coef: torch.Tensor,
    basis: torch.Tensor,
    backlash_coef: torch.Tensor | None = None,
    backlash_basis: torch.Tensor | None = None,
    direction: torch.Tensor | None = None,
    screw: torch.Tensor | None = None,
) -> torch.Tensor:
    """Six error terms per pose and joint, eq. (23) plus backlash (13).

    coef: (n, 6, K) Chebyshev coefficients (K = max order + 1; unused orders are zero);
    basis: (B, n, K) Chebyshev values at each normalized joint variable;
    backlash_coef: (n, Kb); backlash_basis: (B, n, Kb); direction: (B, n) in {-1, 0, +1};
    screw: (n, 6) the twist one unit of each joint's backlash adds (:func:`backlash_screws`), default eps_z.
    -> (B, n, 6) = (eps_x, eps_y, eps_z, delta_x, delta_y, delta_z).
    """
    e = torch.einsum("bnk,ntk->bnt", basis, coef)
    if backlash_coef is not None and direction is not None and backlash_coef.shape[-1] > 0:
        b = (backlash_basis * backlash_coef).sum(-1) * direction
        e = e + (torch.nn.functional.pad(b[..., None], (2, 3)) if screw is None else b[..., None] * screw)
    return e


def backlash_on_eps_z(screw: torch.Tensor | None, joints: torch.Tensor | None = None) -> bool:
    """Whether backlash screws (n, 6) (of the ``joints`` (n,) bool given, default all) are eps_z, Paper II's DH
    form, which the factored fits and the compiled kernels' plain path read (None: eps_z, as before screws)."""
    if screw is None:
        return True
    s = screw if joints is None else screw[joints]
    return bool((s == s.new_tensor([0.0, 0.0, 1.0, 0.0, 0.0, 0.0])).all())


def backlash_screws(axes: torch.Tensor, prismatic: torch.Tensor) -> torch.Tensor:
    """(n, 6) the error twist one unit of each joint's backlash adds: a turn about its own axis (revolute) or a
    move along it (prismatic), Paper II (13), whose eps_z is that turn in DH frames. URDF axes need not be z: a
    ROS-style (0 1 0) axis, or a rail, got a turn about the frame's z (a rail's backlash became a carriage yaw).

    axes: (n, 3) unit joint axes; prismatic: (n,) bool.

    Example:
        >>> backlash_screws(torch.tensor([[0.0, 0.0, 1.0], [1.0, 0.0, 0.0]]), torch.tensor([False, True])).tolist()
        [[0.0, 0.0, 1.0, 0.0, 0.0, 0.0], [0.0, 0.0, 0.0, 1.0, 0.0, 0.0]]
    """
    a = axes / axes.norm(dim=-1, keepdim=True)
    p = prismatic.to(torch.bool)[:, None]
    zero = torch.zeros_like(a)
    return torch.cat([torch.where(p, zero, a), torch.where(p, a, zero)], -1)


def _order_table(orders, n: int) -> torch.Tensor:
    """Per-joint, per-term order table (n, 6) from an int, a per-joint list or an (n, 6) table."""
    t = torch.as_tensor(orders, dtype=torch.long)
    if t.ndim == 0:
        t = t.expand(n, 6)
    elif t.ndim == 1:
        if t.numel() != n:
            raise ValueError(f"model order: expected {n} per-joint orders, got {t.numel()}")
        t = t[:, None].expand(n, 6)
    if t.shape != (n, 6):
        raise ValueError(f"model order: expected shape ({n}, 6), got {tuple(t.shape)}")
    if (t < -1).any() or (t > MAX_ORDER).any():
        raise ValueError(f"model order must be in 0..{MAX_ORDER} (or -1 to switch a term off)")
    return t.clone()


class JointErrors(nn.Module):
    """Learnable E_i(q_i, s_i) for every joint of a chain.

    ranges: (n, 2) range of each joint's error variable, for the normalization (24);
    orders: int, per-joint list, or (n, 6) table (-1 switches a term off);
    backlash: None/False (off), True (order :data:`DEFAULT_BACKLASH_ORDER`) or an
    int / per-joint list of orders (-1 switches a joint's backlash off).

    Example:
        >>> je = JointErrors(torch.tensor([[-1.0, 1.0], [0.0, 2.0]]), orders=2, backlash=True)
        >>> je(torch.zeros(5, 2), torch.ones(5, 2)).shape
        torch.Size([5, 2, 4, 4])
    """

    def __init__(self, ranges: torch.Tensor, orders=6, backlash=None, joint_names: Sequence[str] | None = None,
                 prismatic: Sequence[bool] | None = None, axes: torch.Tensor | None = None):
        super().__init__()
        n = ranges.shape[0]
        # a prismatic joint's backlash is lost motion along it: a length (m), labelled mm, not deg
        self.prismatic_joints = [bool(b) for b in prismatic] if prismatic is not None else [False] * n
        # the twist a unit of backlash adds (structure, rebuilt with the model: not in the state dict)
        screw = (backlash_screws(axes.to(torch.float64), torch.tensor(self.prismatic_joints)) if axes is not None
                 else torch.nn.functional.pad(torch.ones(n, 1, dtype=torch.float64), (2, 3)))
        self.register_buffer("screw", screw, persistent=False)
        table = _order_table(orders, n)
        K = int(table.max().clamp(min=0)) + 1
        k = torch.arange(K)
        self.joint_names = list(joint_names or [f"joint{i + 1}" for i in range(n)])
        self.register_buffer("ranges", ranges.to(torch.float64).clone())
        self.register_buffer("orders", table)
        self.register_buffer("mask", k[None, None, :] <= table[..., None])
        self.coef = nn.Parameter(torch.zeros(n, 6, K, dtype=torch.float64))
        if backlash is None or backlash is False:
            b_orders = torch.full((n,), -1, dtype=torch.long)
        elif backlash is True:
            b_orders = torch.full((n,), DEFAULT_BACKLASH_ORDER, dtype=torch.long)
        else:
            b_orders = torch.as_tensor(backlash, dtype=torch.long).expand(n).clone()
            if (b_orders < -1).any() or (b_orders > MAX_ORDER).any():
                raise ValueError(f"backlash order must be in 0..{MAX_ORDER} (or -1 to switch a joint's off), got {b_orders.tolist()}")
        Kb = int(b_orders.max().clamp(min=-1)) + 1
        self.register_buffer("backlash_orders", b_orders)
        self.register_buffer("backlash_mask", torch.arange(Kb)[None, :] <= b_orders[:, None])
        self.backlash = nn.Parameter(torch.zeros(n, Kb, dtype=torch.float64))

    @property
    def n(self) -> int:
        return self.coef.shape[0]

    @property
    def has_backlash(self) -> bool:
        return bool(self.backlash_mask.any())

    def normalized(self, theta: torch.Tensor) -> torch.Tensor:
        """Error variables (B, n) -> lam (B, n) in [-1, 1] over the model's ranges (24)."""
        return normalize(theta, self.ranges[:, 0], self.ranges[:, 1])

    def twists(self, theta: torch.Tensor, direction: torch.Tensor | None = None) -> torch.Tensor:
        """(B, n) error variables (+ (B, n) directions) -> (B, n, 6) error terms."""
        lam = self.normalized(theta)
        basis = chebyshev(lam, self.coef.shape[-1] - 1)
        coef = self.coef * self.mask
        if self.has_backlash and direction is not None:
            bb = chebyshev(lam, self.backlash.shape[-1] - 1)
            return joint_error_twists(coef, basis, self.backlash * self.backlash_mask, bb, direction.to(theta),
                                      self.screw)
        return joint_error_twists(coef, basis)

    def backlash_values(self, theta: torch.Tensor, direction: torch.Tensor) -> torch.Tensor:
        """s_i Δq_ib(u_i) (B, n): each joint's backlash (13) at error variables (B, n) and directions (B, n)."""
        lam = self.normalized(theta)
        bb = chebyshev(lam, self.backlash.shape[-1] - 1)
        return (bb * self.backlash * self.backlash_mask).sum(-1) * direction.to(theta)

    def forward(self, theta: torch.Tensor, direction: torch.Tensor | None = None) -> torch.Tensor:
        """Error transforms E_i: (B, n) -> (B, n, 4, 4)."""
        return twist_to_transform(self.twists(theta, direction))

    def param_groups(self, prefix: str = "joint_errors") -> list[ParamGroup]:
        """Declared kinds and prior scales of ``coef`` and ``backlash``.

        coef: the six terms in twist order, angles (prior 0.01 rad) then lengths
        (prior 1 mm), about 20x the paper's largest constant errors; backlash:
        angles, c0 prior :data:`BACKLASH_SIGMA`, c1.. :data:`BACKLASH_VARIATION_SIGMA`
        (where direction and position are confounded in the data, this is what
        keeps the variation terms from describing position errors). Only
        existing orders are in the masks.
        """
        n, _, K = self.coef.shape
        coef_names, bl_names = self.parameter_names()
        kinds = [k for _ in range(n) for k in term_kinds(TERMS) for _ in range(K)]
        sigma = torch.tensor([1e-2 if k == ANGLE else 1e-3 for k in kinds], dtype=torch.float64)
        k = torch.arange(self.backlash.shape[1]).expand_as(self.backlash).flatten()
        # float64 from the start: python scalars in torch.where take the default dtype (float32 unless a user
        # changed it), which rounded these sigmas and made a fit depend on torch.get_default_dtype()
        bl_sigma = torch.where(k == 0, torch.tensor(BACKLASH_SIGMA, dtype=torch.float64),
                               torch.tensor(BACKLASH_VARIATION_SIGMA, dtype=torch.float64))
        return [
            ParamGroup(f"{prefix}.coef", "joint", coef_names, kinds, sigma, self.mask.expand_as(self.coef).clone()),
            ParamGroup(f"{prefix}.backlash", "backlash", bl_names,
                       [LENGTH if self.prismatic_joints[i] else ANGLE for i in range(n) for _ in range(self.backlash.shape[1])],
                       bl_sigma, self.backlash_mask.clone()),
        ]

    def parameter_names(self) -> tuple[list[str], list[str]]:
        """Names of every entry of ``coef`` and ``backlash`` (row-major), e.g. 'joint3.eps_z.c2'."""
        n, _, K = self.coef.shape
        coef = [f"{self.joint_names[i]}.{t}.c{k}" for i in range(n) for t in TERMS for k in range(K)]
        bl = [f"{self.joint_names[i]}.backlash.c{k}" for i in range(n) for k in range(self.backlash.shape[1])]
        return coef, bl
