"""Laser-tracker measurement noise of Paper III: kinematics (10), map (34), specification (47), covariance (35)-(37).

A tracker measures a point by two encoder angles and a distance. With the
tracker kinematics (10), F_LT = Rot_z(α) Rot_y(β), the beam leaves the
tracker origin along z_LT2 (the third column of F_LT), so the measured point
in the tracker base frame LT0 is (34)

    p = d (cos α sin β, sin α sin β, cos β).

Angle convention (the paper's, kept here):

- α, "azimuth": rotation about z_LT0, measured from x_LT0 towards y_LT0, in (-π, π];
- β, called "elevation" in the paper, is measured from the +z_LT0 axis (a polar,
  zenith angle): β = 0 points straight up, β = π/2 is horizontal, in [0, π];
- d: distance from the tracker origin, metres.

Errors Δα ~ N(0, σ_α²), Δβ ~ N(0, σ_β²), Δd ~ N(0, σ_d(d)²), independent,
make the Cartesian error non-diagonal and distance dependent. The appendix
(49)-(61) linearizes (34): Σ_p = J diag(σ_α², σ_β², σ_d²) J^T with
J = ∂p/∂(α, β, d). Equivalently, in the beam frame F_LT of (10) (columns
x_LT2 = ∂p/∂β / d, y_LT2 = ∂p/∂α / (d sin β), z_LT2 = p / d):

    Σ_p = F_LT diag(d² σ_β², d² sin²β σ_α², σ_d²) F_LT^T.

Erratum: multiplying the coefficients of (52)-(54), the printed (36) and
(59)-(61) lose two minus signs (∂x/∂α = -d sα sβ and ∂z/∂β = -d sβ): the
correct covariances are

    Σ_xy = -(d sβ)² sα cα σ_α² + (d cβ)² sα cα σ_β² + sβ² sα cα σ_d²
    Σ_xz = -d² sβ cβ cα σ_β² + cα sβ cβ σ_d²
    Σ_yz = -d² sβ cβ sα σ_β² + sα sβ cβ σ_d².

:func:`tracker_covariance` implements the linearization with the correct
signs (a test compares it with Monte Carlo sampling of (α, β, d) through the
exact map (34)); :func:`tracker_covariance_as_printed` keeps the printed
formulas for comparison only: they are J' diag(σ²) J'^T with those two
entries of J negated, a valid covariance of the wrong, mirrored, ellipsoid
(its xy correlation has the wrong sign wherever the azimuth term dominates).
The specification (47) of the paper's API Radian R-20 is
:meth:`TrackerNoise.paper3`.

Everything is SI (rad, m, m²); :meth:`TrackerNoise.from_file_units` and
:meth:`TrackerNoise.file_units` speak degrees and millimetres.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import torch

from ..core import units
from ..core.exceptions import TorchcalError


class GeometryError(TorchcalError, ValueError):
    """Input a measurement geometry cannot use: a point at the tracker origin, a degenerate triangle, a non-finite value."""


WORKING_RANGE = {"d": (1.0, 10.0), "alpha": (-math.pi, math.pi), "beta": (math.radians(15.0), math.radians(150.0))}
"""The working range the covariance check covers (SI): distance 1-10 m, every azimuth,
β from 15° to 150° from the vertical (elevation +75° to -60° above the horizon, roughly a
tracker's elevation travel). At β = 0 (straight up) α is undefined and the first-order
variance of some coordinates vanishes, so relative errors there mean nothing."""


def tracker_points(p, name: str = "points") -> torch.Tensor:
    p = torch.as_tensor(p)
    if not p.is_floating_point():
        p = p.to(torch.float64)
    if p.ndim < 1 or p.shape[-1] != 3:
        raise GeometryError(f"{name}: expected (..., 3) positions, got shape {tuple(p.shape)}")
    bad = ~torch.isfinite(p).all(-1)
    if bad.any():
        idx = tuple(int(i) for i in bad.nonzero()[0])
        raise GeometryError(f"{name}: row {idx} is not finite: {p[idx].tolist()}")
    return p


def spherical(p) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """Tracker angles and distance of points, the inverse of (34).

    p: (..., 3) m in the tracker base frame -> (α, β, d), each (...): azimuth
    (rad, (-π, π]), polar angle from +z (rad, [0, π]), distance (m).

    Example:
        >>> import torch
        >>> a, b, d = spherical(torch.tensor([[0.0, 2.0, 0.0]], dtype=torch.float64))
        >>> [round(float(a[0]), 6), round(float(b[0]), 6), float(d[0])]
        [1.570796, 1.570796, 2.0]
    """
    p = tracker_points(p)
    d = torch.linalg.norm(p, dim=-1)
    if (d == 0).any():
        idx = tuple(int(i) for i in (d == 0).nonzero()[0])
        raise GeometryError(f"tracker point {idx} is at the tracker origin: no direction")
    alpha = torch.atan2(p[..., 1], p[..., 0])
    # atan2 of (horizontal radius, z) keeps full precision near the poles, unlike acos(z / d)
    beta = torch.atan2(torch.linalg.norm(p[..., :2], dim=-1), p[..., 2])
    return alpha, beta, d


def cartesian(alpha, beta, d) -> torch.Tensor:
    """The map (34): (α, β, d), each (...), rad / rad / m -> (..., 3) m in the tracker base frame."""
    alpha, beta, d = torch.broadcast_tensors(torch.as_tensor(alpha), torch.as_tensor(beta), torch.as_tensor(d))
    sb = torch.sin(beta)
    return torch.stack([d * torch.cos(alpha) * sb, d * torch.sin(alpha) * sb, d * torch.cos(beta)], -1)


def tracker_kinematics(alpha, beta) -> torch.Tensor:
    """F_LT = Rot_z(α) Rot_y(β) of (10): (...) rad -> (..., 4, 4); its z axis is the beam direction."""
    alpha, beta = torch.broadcast_tensors(torch.as_tensor(alpha), torch.as_tensor(beta))
    ca, sa, cb, sb = torch.cos(alpha), torch.sin(alpha), torch.cos(beta), torch.sin(beta)
    z, o = torch.zeros_like(ca), torch.ones_like(ca)
    rows = [[ca * cb, -sa, ca * sb, z], [sa * cb, ca, sa * sb, z], [-sb, z, cb, z], [z, z, z, o]]
    return torch.stack([torch.stack(r, -1) for r in rows], -2)


def spherical_jacobian(alpha, beta, d) -> torch.Tensor:
    """∂p/∂(α, β, d) of (34), the coefficients of (49)-(54): (...) -> (..., 3, 3), columns α, β, d (m/rad, m/rad, 1)."""
    alpha, beta, d = torch.broadcast_tensors(torch.as_tensor(alpha), torch.as_tensor(beta), torch.as_tensor(d))
    ca, sa, cb, sb = torch.cos(alpha), torch.sin(alpha), torch.cos(beta), torch.sin(beta)
    z = torch.zeros_like(ca)
    rows = [[-d * sa * sb, d * ca * cb, ca * sb], [d * ca * sb, d * sa * cb, sa * sb], [z, -d * sb, cb]]
    return torch.stack([torch.stack(r, -1) for r in rows], -2)


def tracker_covariance(p, sigma_alpha, sigma_beta, sigma_d) -> torch.Tensor:
    """Linearized Cartesian covariance (35) of tracker points (appendix (49)-(61), signs corrected).

    p: (R, 3) (or (..., 3)) m, tracker base frame; sigma_alpha, sigma_beta:
    rad; sigma_d: m; each a float or a tensor broadcastable to p's leading
    shape (per point). -> (R, 3, 3) m², J diag(σ_α², σ_β², σ_d²) J^T.

    Example:
        >>> import torch
        >>> S = tracker_covariance(torch.tensor([[3.0, 0.0, 0.0]], dtype=torch.float64), 1e-6, 2e-6, 5e-6)
        >>> [round(float(v) * 1e12, 3) for v in torch.diagonal(S[0])]  # µm²: σ_d², (dσ_α)², (dσ_β)²
        [25.0, 9.0, 36.0]
    """
    alpha, beta, d = spherical(p)
    J = spherical_jacobian(alpha, beta, d)
    s = [torch.as_tensor(x, dtype=J.dtype, device=J.device).expand_as(d) for x in (sigma_alpha, sigma_beta, sigma_d)]
    var = torch.stack(s, -1) ** 2
    return (J * var[..., None, :]) @ J.transpose(-1, -2)


def tracker_covariance_as_printed(p, sigma_alpha, sigma_beta, sigma_d) -> torch.Tensor:
    """(36) and (59)-(61) exactly as printed (two minus signs lost, see the module docstring); for comparison only.

    Same arguments and shapes as :func:`tracker_covariance`.
    """
    alpha, beta, d = spherical(p)
    sa, ca, sb, cb = torch.sin(alpha), torch.cos(alpha), torch.sin(beta), torch.cos(beta)
    va, vb, vd = (torch.as_tensor(x, dtype=d.dtype, device=d.device).expand_as(d) ** 2 for x in (sigma_alpha, sigma_beta, sigma_d))
    xx = (d * sa * sb) ** 2 * va + (d * ca * cb) ** 2 * vb + (ca * sb) ** 2 * vd
    yy = (d * ca * sb) ** 2 * va + (d * sa * cb) ** 2 * vb + (sa * sb) ** 2 * vd
    zz = (d * sb) ** 2 * vb + cb**2 * vd
    xy = (d * sb) ** 2 * sa * ca * va + (d * cb) ** 2 * sa * ca * vb + sb**2 * sa * ca * vd
    xz = d**2 * sb * ca * cb * vb + ca * sb * cb * vd
    yz = d**2 * sa * cb * sb * vb + sa * sb * cb * vd
    return torch.stack([torch.stack([xx, xy, xz], -1), torch.stack([xy, yy, yz], -1), torch.stack([xz, yz, zz], -1)], -2)


@dataclass(frozen=True)
class TrackerNoise:
    """A laser tracker's measurement noise, (47): angle and distance standard deviations, SI.

    sigma_alpha, sigma_beta: rad (azimuth, polar angle); the distance noise is
    σ_d(d) = sigma_d_const for d <= d_break and sigma_d_rel · d beyond
    (m, dimensionless m/m, m).

    Example:
        >>> import torch
        >>> noise = TrackerNoise.paper3()
        >>> [round(float(s) * 1e6, 3) for s in noise.sigma_d(torch.tensor([1.0, 2.0, 4.0], dtype=torch.float64))]  # µm
        [5.0, 5.0, 10.0]
        >>> noise.covariance(torch.tensor([[2.0, 1.0, 0.5]], dtype=torch.float64)).shape
        torch.Size([1, 3, 3])
    """

    sigma_alpha: float = 3.5e-6
    sigma_beta: float = 3.5e-6
    sigma_d_const: float = 5e-6
    sigma_d_rel: float = 2.5e-6
    d_break: float = 2.0

    def __post_init__(self):
        for name in ("sigma_alpha", "sigma_beta", "sigma_d_const", "sigma_d_rel", "d_break"):
            v = getattr(self, name)
            if not (math.isfinite(float(v)) and float(v) >= 0):
                raise GeometryError(f"TrackerNoise: {name} must be a finite number >= 0, got {v}")

    @classmethod
    def paper3(cls) -> TrackerNoise:
        """The API Radian R-20 specification of Paper III (47): 3.5 µrad, 3.5 µrad, 5 µm up to 2 m, 2.5 µm/m beyond."""
        return cls(3.5e-6, 3.5e-6, 5e-6, 2.5e-6, 2.0)

    @classmethod
    def from_file_units(cls, sigma_alpha_deg: float, sigma_beta_deg: float, sigma_d_const_mm: float,
                        sigma_d_rel: float, d_break_mm: float) -> TrackerNoise:
        """From file units: angles in degrees, distances in mm; sigma_d_rel is dimensionless (mm/mm = m/m)."""
        return cls(float(units.deg_to_rad(sigma_alpha_deg)), float(units.deg_to_rad(sigma_beta_deg)),
                   float(units.mm_to_m(sigma_d_const_mm)), float(sigma_d_rel), float(units.mm_to_m(d_break_mm)))

    def file_units(self) -> dict:
        """The keyword arguments of :meth:`from_file_units` (degrees, mm) that rebuild this noise."""
        return {"sigma_alpha_deg": units.rad_to_deg(self.sigma_alpha), "sigma_beta_deg": units.rad_to_deg(self.sigma_beta),
                "sigma_d_const_mm": units.m_to_mm(self.sigma_d_const), "sigma_d_rel": self.sigma_d_rel,
                "d_break_mm": units.m_to_mm(self.d_break)}

    def sigma_d(self, d) -> torch.Tensor:
        """Distance standard deviation (47), m: d (...) m -> (...)."""
        d = torch.as_tensor(d)
        return torch.where(d <= self.d_break, torch.full_like(d, self.sigma_d_const), self.sigma_d_rel * d)

    def covariance(self, p) -> torch.Tensor:
        """Linearized covariance of tracker points: p (R, 3) m, tracker base frame -> (R, 3, 3) m²."""
        p = tracker_points(p)
        return tracker_covariance(p, self.sigma_alpha, self.sigma_beta, self.sigma_d(torch.linalg.norm(p, dim=-1)))


def sample_tracker_points(p, noise: TrackerNoise, n: int, seed: int) -> torch.Tensor:
    """Measured points: true p (R, 3) m -> (R, n, 3) m, noise drawn on (α, β, d) and mapped exactly by (34).

    σ_d is evaluated at each point's true distance; the draws come from a
    generator seeded with ``seed`` on p's device.
    """
    p = tracker_points(p)
    alpha, beta, d = spherical(p)
    g = torch.Generator(device=p.device).manual_seed(int(seed))
    e = torch.randn((*p.shape[:-1], int(n), 3), generator=g, dtype=p.dtype, device=p.device)
    sig = torch.stack([torch.full_like(d, noise.sigma_alpha), torch.full_like(d, noise.sigma_beta), noise.sigma_d(d)], -1)
    e = e * sig[..., None, :]
    return cartesian(alpha[..., None] + e[..., 0], beta[..., None] + e[..., 1], d[..., None] + e[..., 2])


def monte_carlo_covariance(p, noise: TrackerNoise, n: int = 200_000, seed: int = 0, chunk: int = 50_000) -> torch.Tensor:
    """Sample covariance (R, 3, 3) m² of ``n`` measurements of each point p (R, 3) m (:func:`sample_tracker_points`).

    Draws ``chunk`` samples per point at a time (memory R · chunk · 3 floats)
    and accumulates deviations from the true point, so the result is the
    unbiased (n - 1) covariance about the sample mean. Chunk k uses seed + k.
    """
    p = tracker_points(p)
    if int(n) < 2:
        raise GeometryError(f"monte_carlo_covariance: need at least 2 samples, got {n}")
    s1 = torch.zeros_like(p)
    s2 = torch.zeros((*p.shape, 3), dtype=p.dtype, device=p.device)
    done, k = 0, 0
    while done < n:
        m = min(int(chunk), int(n) - done)
        # deviations from the true point (~1e-5 m) keep the sums free of cancellation
        dev = sample_tracker_points(p, noise, m, seed + k) - p[..., None, :]
        s1 += dev.sum(-2)
        s2 += dev.transpose(-1, -2) @ dev
        done, k = done + m, k + 1
    mean = s1 / n
    return (s2 - n * mean[..., :, None] * mean[..., None, :]) / (n - 1)


def covariance_deviation(reference: torch.Tensor, other: torch.Tensor) -> torch.Tensor:
    """Element-wise relative deviation (R, 3, 3) of ``other`` from ``reference`` (both (R, 3, 3)).

    |other_ij - reference_ij| / sqrt(reference_ii reference_jj): on the
    diagonal the relative error of a variance, off the diagonal the error of a
    covariance in units of the product of the two standard deviations (the
    error of the correlation coefficient, which stays meaningful where a
    covariance itself is near zero).
    """
    dg = torch.diagonal(reference, dim1=-2, dim2=-1)
    scale = torch.sqrt(dg[..., :, None] * dg[..., None, :])
    return (other - reference).abs() / scale


def working_range_points(n_d: int = 3, n_alpha: int = 4, n_beta: int = 3, dtype=torch.float64, device=None) -> torch.Tensor:
    """A grid over :data:`WORKING_RANGE`: (n_d · n_alpha · n_beta, 3) m, tracker base frame.

    Distances and polar angles span their ranges end to end; azimuths are
    spread over the full turn without repeating -π and π, offset by a quarter
    step so that no point lies on a coordinate plane (all correlations non-zero).
    """
    d = torch.linspace(*WORKING_RANGE["d"], n_d, dtype=dtype, device=device)
    step = 2 * math.pi / n_alpha
    a = -math.pi + step * (torch.arange(n_alpha, dtype=dtype, device=device) + 0.25)
    b = torch.linspace(*WORKING_RANGE["beta"], n_beta, dtype=dtype, device=device)
    D, A, B = torch.meshgrid(d, a, b, indexing="ij")
    return cartesian(A.reshape(-1), B.reshape(-1), D.reshape(-1))


def covariance_check(noise: TrackerNoise, points=None, n_samples: int = 200_000, seed: int = 0) -> float:
    """Worst relative deviation of the linearized covariance from Monte Carlo over ``points``.

    points: (R, 3) m (default :func:`working_range_points`); every element of
    every point's 3x3 covariance is compared by :func:`covariance_deviation`
    with the Monte Carlo covariance as the reference. The Monte Carlo error of
    one element is about sqrt(2 / n_samples) (0.3 % at 2e5), the linearization
    error about σ_α, σ_β (1e-5): the number measures the sampling noise unless
    the linearization is wrong.
    """
    pts = working_range_points() if points is None else tracker_points(points)
    lin = noise.covariance(pts)
    mc = monte_carlo_covariance(pts, noise, n_samples, seed)
    return float(covariance_deviation(mc, lin).max())
