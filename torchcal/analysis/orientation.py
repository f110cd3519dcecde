"""Orientation repeatability, Paper III (41)-(45): the ISO 9283 procedure carried over to orientations.

ISO 9283 defines position repeatability only (:func:`iso9283_repeatability`,
RP = l̄ + 3 S_l). Paper III measures K = 20 orientations at each of P = 5
poses with the STS and, for each pose i,

- (41) averages the measured z_s0 axes, z̄_i = (1/K) Σ_j z_ij (not normalized);
- (42) takes the angle τ_ij between z̄_i and each z_ij;
- (43), (44) their mean τ̄_i and sample standard deviation σ_τ,i (K - 1);
- (45) defines the local orientation repeatability R_o,i = τ̄_i + 3 σ_τ,i.

(42) as printed divides the arc cosine, not its argument, by the norms; the
angle between the two vectors is meant and computed here, as
atan2(|z̄ × z|, z̄ · z), which keeps full precision at the 1e-4 rad scale of
robot repeatability (the arc cosine keeps only ~1e-8 rad absolute precision
and, below ~1e-7 rad, sees its rounded argument exceed 1).

``axis=None`` extends the procedure to the whole orientation: the mean
rotation is the projection of the arithmetic mean of the K rotation matrices
onto SO(3) (the chordal L2 mean, via SVD) and τ_ij the geodesic angle
between it and R_ij.

For a rotation scatter R_ij = R_i exp([ω_ij]×), ω ~ N(0, s² I), the z axis
tilts by a Rayleigh(s) angle, so R_o → s (sqrt(π/2) + 3 sqrt(2 - π/2)) ≈
3.218 s for large K; the whole-rotation angle |ω| is Maxwell(s) distributed,
R_o → s (2 sqrt(2/π) + 3 sqrt(3 - 8/π)) ≈ 3.616 s. Both are
:func:`expected_orientation_repeatability`.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import torch

from ..core.exceptions import TorchcalError


class RepeatabilityError(TorchcalError, ValueError):
    """Orientation samples the repeatability procedure cannot use (shape, too few samples, not rotations)."""


@dataclass
class OrientationRepeatability:
    """Result of :func:`orientation_repeatability`, rad; P poses, K samples each.

    tau: (P, K) angle of each sample to its pose's mean (42); mean: (P,) τ̄ (43);
    std: (P,) σ_τ (44); ro: (P,) R_o = τ̄ + 3 σ_τ (45); mean_axis: (P, 3) unit
    mean axis (axis mode) or mean_rotation: (P, 3, 3) (axis=None).
    """

    tau: torch.Tensor
    mean: torch.Tensor
    std: torch.Tensor
    ro: torch.Tensor
    mean_axis: torch.Tensor | None = None
    mean_rotation: torch.Tensor | None = None

    @property
    def worst(self) -> torch.Tensor:
        """The largest R_o over the poses (Paper III 5.2 reports this maximum), rad."""
        return self.ro.max()


def _check(x: torch.Tensor, tail: tuple, name: str) -> torch.Tensor:
    x = torch.as_tensor(x)
    if not x.is_floating_point():
        x = x.to(torch.float64)
    if x.ndim == len(tail) + 1:
        x = x[None]
    if x.ndim != len(tail) + 2 or tuple(x.shape[2:]) != tail:
        raise RepeatabilityError(f"{name}: expected (K, {', '.join(map(str, tail))}) or (P, K, {', '.join(map(str, tail))}), "
                                 f"got {tuple(x.shape)}")
    if x.shape[1] < 2:
        raise RepeatabilityError(f"{name}: orientation repeatability needs at least 2 samples per pose, got {x.shape[1]}")
    bad = ~torch.isfinite(x.reshape(*x.shape[:2], -1)).all(-1)
    if bad.any():
        p, k = bad.nonzero()[0].tolist()
        raise RepeatabilityError(f"{name}: pose {p + 1}, sample {k + 1} is not finite")
    return x


def _stats(tau: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    mean = tau.mean(-1)
    std = tau.std(-1, correction=1)
    return mean, std, mean + 3.0 * std


def axis_repeatability(axes) -> OrientationRepeatability:
    """(41)-(45) on measured axis vectors: (P, K, 3) or (K, 3), any length -> per-pose statistics, rad.

    For the STS these are the measured z_s0 axes; for the AT method the
    triangle normals (:func:`torchcal.measure.triangle.triangle_frame`).

    Example:
        >>> import torch
        >>> z = torch.tensor([[0.0, 0.0, 1.0], [1e-4, 0.0, 1.0], [-1e-4, 0.0, 1.0]], dtype=torch.float64)
        >>> r = axis_repeatability(z)
        >>> [round(float(t) * 1e4, 6) for t in r.tau[0]], round(float(r.ro[0]) * 1e4, 4)
        ([0.0, 1.0, 1.0], 2.3987)
    """
    z = _check(axes, (3,), "axes")
    nz = torch.linalg.norm(z, dim=-1)
    if (nz == 0).any():
        p, k = (nz == 0).nonzero()[0].tolist()
        raise RepeatabilityError(f"axes: pose {p + 1}, sample {k + 1} is the zero vector")
    zbar = z.mean(1, keepdim=True)  # (41)
    if (torch.linalg.norm(zbar, dim=-1) == 0).any():
        p = int((torch.linalg.norm(zbar, dim=-1) == 0).nonzero()[0, 0])
        raise RepeatabilityError(f"axes: pose {p + 1}: the axes cancel, their mean has no direction")
    zb = zbar.expand_as(z)
    tau = torch.atan2(torch.linalg.norm(torch.linalg.cross(zb, z), dim=-1), (zb * z).sum(-1))  # (42)
    mean, std, ro = _stats(tau)
    return OrientationRepeatability(tau, mean, std, ro, mean_axis=(zbar / torch.linalg.norm(zbar, dim=-1, keepdim=True))[:, 0])


def mean_rotation(rotations) -> torch.Tensor:
    """Chordal L2 mean of rotations (P, K, 3, 3) -> (P, 3, 3): the SO(3) matrix closest to their arithmetic mean."""
    R = _check(rotations, (3, 3), "rotations")
    U, _, Vh = torch.linalg.svd(R.mean(1))
    D = torch.ones(U.shape[:-1], dtype=U.dtype, device=U.device)
    D[..., -1] = torch.sign(torch.linalg.det(U @ Vh))
    return (U * D[..., None, :]) @ Vh


def orientation_repeatability(rotations, axis: int | None = 2, tol: float = 1e-6) -> OrientationRepeatability:
    """Local orientation repeatability (41)-(45) of P poses: rotations (P, K, 3, 3) (or (K, 3, 3)) -> statistics, rad.

    axis: column of the rotations whose direction is compared, 2 = z_s0 as in
    the paper; None compares whole rotations (chordal mean, geodesic angle;
    see the module docstring). Rotations must be orthonormal with det +1
    within ``tol``; the first offending pose and sample are named otherwise.
    Batched over poses; ``.worst`` is the maximum R_o.

    Example:
        >>> import torch
        >>> R = torch.eye(3, dtype=torch.float64).expand(4, 20, 3, 3)
        >>> orientation_repeatability(R).ro.tolist()
        [0.0, 0.0, 0.0, 0.0]
    """
    R = _check(rotations, (3, 3), "rotations")
    eye = torch.eye(3, dtype=R.dtype, device=R.device)
    off = (R.transpose(-1, -2) @ R - eye).abs().amax((-1, -2)) > tol
    off |= (torch.linalg.det(R) - 1.0).abs() > tol
    if off.any():
        p, k = off.nonzero()[0].tolist()
        raise RepeatabilityError(f"rotations: pose {p + 1}, sample {k + 1} is not a rotation matrix (tol {tol})")
    if axis is not None:
        if axis not in (0, 1, 2):
            raise RepeatabilityError(f"orientation_repeatability: axis must be 0, 1, 2 or None, got {axis!r}")
        return axis_repeatability(R[..., :, axis])
    M = mean_rotation(R)
    E = M[:, None].transpose(-1, -2) @ R
    v = torch.stack([E[..., 2, 1] - E[..., 1, 2], E[..., 0, 2] - E[..., 2, 0], E[..., 1, 0] - E[..., 0, 1]], -1)
    tr = E[..., 0, 0] + E[..., 1, 1] + E[..., 2, 2]
    tau = torch.atan2(0.5 * torch.linalg.norm(v, dim=-1), 0.5 * (tr - 1.0))
    mean, std, ro = _stats(tau)
    return OrientationRepeatability(tau, mean, std, ro, mean_rotation=M)


def expected_orientation_repeatability(sigma: float, axis: bool = True) -> float:
    """R_o for isotropic small-rotation scatter ω ~ N(0, σ² I) (rad per axis) and many samples, rad.

    axis=True: the tilt of one axis, Rayleigh(σ): mean σ sqrt(π/2), standard
    deviation σ sqrt(2 - π/2). axis=False: the whole rotation angle, Maxwell(σ):
    mean 2σ sqrt(2/π), standard deviation σ sqrt(3 - 8/π).
    """
    if axis:
        return sigma * (math.sqrt(math.pi / 2) + 3.0 * math.sqrt(2.0 - math.pi / 2))
    return sigma * (2.0 * math.sqrt(2.0 / math.pi) + 3.0 * math.sqrt(3.0 - 8.0 / math.pi))
