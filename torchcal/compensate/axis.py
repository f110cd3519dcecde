"""5-DOF compensation for axisymmetric tools: the rotation about the tool axis left free.

A drill, a spindle, a welding torch or a tracker reflector looks the same after any rotation about its
own axis, so a compensated command need not restore it: (46) is relaxed to the tool point's position
and the tool axis's direction (five conditions), and the sixth joint-space direction is left to the
solver, which keeps the correction small (pseudo-inverse steps from q_nom; Tikhonov damping toward q_nom
on the damped path), so next to the wrist singularity the joints move less than a full 6-DOF correction.

The error of (47)-(48) is taken at the tool point c (flange frame): with Ω = F_a^-1 F_n,
de_p = Ω_p + (Ω_R - I) c and de_r as in (48); the free rotation is dropped by projecting de_r on two unit
vectors b1, b2 orthogonal to the tool axis a: de_r ⊥ a vanishes exactly when Ω_R is a rotation about a,
i.e. when F_a's tool axis R_a a equals F_n's (for rotations below 180 deg). The body Jacobian moves to
the tool point as Jv' = Jv - c × Jw; its orientation rows are projected the same way.
Layouts: "soa" is the fast path's pose-last layout (rows first, poses last), "rows" the damped path's.

3-DOF (``position_only``): one measured point per pose (a single reflector) fixes the modeled flange's
orientation only up to a constant turn that the tool vector takes back (the tool set's frame, :mod:`.toolset`,
is then a translation), so the model's orientation errors at the flange are not data but the fit's choice
(on a real UR10 with one reflector, a 6-DOF correction turned the joints 4.2-4.7 deg). The conditions are then
the tool point's three coordinates alone, W = [I 0], and the solver's smallest correction keeps the rest.
"""

from __future__ import annotations

import torch

from ..core.exceptions import InputError
from ..kinematics.transforms import orthogonal_unit


class ToolAxis:
    """A free tool axis ``axis`` (3,) in the flange frame (normalized here) through the tool point ``point``
    ((3,) or (B, 3), flange frame, m; default the flange origin). ``W``: (5, 6) the rows kept of (de_p, de_r).
    ``axis=None``: every rotation free, the tool point's position alone (3-DOF, W (3, 6))."""

    def __init__(self, axis, point=None, dtype=torch.float64, device="cpu", batch: int | None = None):
        if axis is None:
            W = torch.zeros(3, 6, dtype=dtype, device=device)
            W[:, :3] = torch.eye(3, dtype=dtype, device=device)
            self.axis, self.W = None, W
        else:
            a = torch.as_tensor(axis, dtype=dtype, device=device).reshape(-1)
            if a.shape != (3,) or not bool(torch.isfinite(a).all()) or float(a.norm()) == 0.0:
                raise InputError(f"compensate: free_tool_axis must be a nonzero 3-vector in the flange frame, got {axis!r}")
            a = a / a.norm()
            b1 = orthogonal_unit(a)  # b2 = a x b1
            b2 = torch.linalg.cross(a, b1)
            W = torch.zeros(5, 6, dtype=dtype, device=device)
            W[:3, :3] = torch.eye(3, dtype=dtype, device=device)
            W[3, 3:], W[4, 3:] = b1, b2
            self.axis, self.W = a, W
        c = torch.zeros(3, dtype=dtype, device=device) if point is None else torch.as_tensor(point, dtype=dtype, device=device)
        if c.ndim == 1:
            if c.shape != (3,):
                raise InputError(f"compensate: tool_point must be (3,) or (B, 3), got {tuple(c.shape)}")
            c = c.expand(batch if batch is not None else 1, 3)
        if c.ndim != 2 or c.shape[1] != 3 or (batch is not None and c.shape[0] != batch):
            raise InputError(f"compensate: tool_point must be (3,) or ({batch}, 3), got {tuple(c.shape)}")
        self.point = c  # (B, 3)

    @property
    def position_only(self) -> bool:
        """3-DOF: every rotation free. The fast path then takes the position error and its Jacobians in the world
        frame: the flange's orientation is no datum there, and a residual taken in its frame would make the chord
        iteration's pick among the many solutions depend on the fit's choice of it."""
        return self.axis is None

    def subset(self, rows: torch.Tensor) -> "ToolAxis":
        """The same axis with the tool points of ``rows`` only."""
        out = object.__new__(ToolAxis)
        out.axis, out.W, out.point = self.axis, self.W, self.point[rows]
        return out

    # ---------------------------------------------------------------- pose-last layout (fast path)
    def pointT(self, rows: torch.Tensor | None = None) -> torch.Tensor:
        """(3, b) tool points of the given rows (all when None)."""
        c = self.point if rows is None else self.point[rows]
        return c.T.contiguous()

    @staticmethod
    def shift_soa(R: torch.Tensor, p: torch.Tensor, cT: torch.Tensor) -> torch.Tensor:
        """Flange R (3, 3, B), p (3, B) and tool points (3, B) -> tool positions (3, B)."""
        return p + (R * cT[None]).sum(1)

    def project_soa(self, de: torch.Tensor) -> torch.Tensor:
        """(6, B) -> (k, B), k = 5 (free axis) or 3 (position only)."""
        return self.W @ de

    def jacobian_soa(self, J: torch.Tensor, cT: torch.Tensor) -> torch.Tensor:
        """Body Jacobian at the flange (6, n, B) -> kept rows at the tool point (k, n, B)."""
        Jv, Jw = J[:3], J[3:]
        c = cT[:, None, :].expand_as(Jw)
        Jv = Jv - torch.linalg.cross(c, Jw, dim=0)
        return torch.einsum("kr,rnb->knb", self.W, torch.cat([Jv, Jw], 0))

    @staticmethod
    def world_jacobian_soa(R: torch.Tensor, J: torch.Tensor, xT: torch.Tensor) -> torch.Tensor:
        """Body Jacobian (6, n, B) of a frame turned by R (3, 3, B) -> the world-frame velocity (3, n, B) of its
        point xT (3, B) (3-DOF)."""
        Jw = J[3:]
        Jv = J[:3] - torch.linalg.cross(xT[:, None, :].expand_as(Jw), Jw, dim=0)
        return torch.einsum("ijb,jnb->inb", R, Jv)

    # ---------------------------------------------------------------- rows layout (damped path)
    @staticmethod
    def shift_rows(R: torch.Tensor, p: torch.Tensor, c: torch.Tensor) -> torch.Tensor:
        """R (M, 3, 3), p (M, 3), c (M, 3) -> (M, 3)."""
        return p + (R @ c[..., None])[..., 0]

    @staticmethod
    def jacobian_rows(J: torch.Tensor, c: torch.Tensor) -> torch.Tensor:
        """Body Jacobian (M, 6, n) at the flange -> at the tool points c (M, 3), all six rows."""
        Jv, Jw = J[:, :3], J[:, 3:]
        Jv = Jv - torch.linalg.cross(c[:, :, None].expand_as(Jw), Jw, dim=1)
        return torch.cat([Jv, Jw], 1)

    def project_rows(self, x: torch.Tensor) -> torch.Tensor:
        """(M, 6) or (M, 6, n) -> (M, k) or (M, k, n)."""
        if self.axis is None:  # W = [I 0]: the same numbers by a slice (a BLAS call per tiny product cost the damped
            # path's few hundred 3-DOF rows a thread barrier each, ~20 ms under load on 2 cores)
            return x[:, :3]
        return self.W @ x if x.ndim == 3 else x @ self.W.T


def tool_axis(free_tool_axis, tool_point, dtype, device, batch: int, position_only: bool = False) -> ToolAxis | None:
    """compensate()'s options -> a :class:`ToolAxis` or None. free_tool_axis: None/False (6-DOF), True (the
    flange z axis) or a (3,) direction in the flange frame; tool_point: None, (3,) or (batch, 3), m;
    position_only: the tool point's position alone (3-DOF)."""
    free = not (free_tool_axis is None or free_tool_axis is False)
    if position_only:
        if free:
            raise InputError("compensate: position_only leaves every rotation free; free_tool_axis (one free rotation) "
                             "cannot be given with it")
        return ToolAxis(None, tool_point, dtype, device, batch)
    if not free:
        if tool_point is not None:
            raise InputError("compensate: tool_point is used with free_tool_axis or position_only only (6-DOF "
                             "compensation of the flange pose reaches every tool point)")
        return None
    axis = [0.0, 0.0, 1.0] if free_tool_axis is True else free_tool_axis
    return ToolAxis(axis, tool_point, dtype, device, batch)


__all__ = ["ToolAxis", "tool_axis"]
