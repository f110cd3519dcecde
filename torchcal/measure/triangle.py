"""Orientation from three position targets: the Active Target (AT) method of Paper III, 6.1-6.2 and (48).

The AT method measures every pose three times with the target in three
set-ups on the end effector (Paper II's three tool vectors, on a circle of
radius ≈ 66.5 mm about the flange axis). The three points form a triangle;
the vector perpendicular to its plane is the measured orientation (the "z
axis of the robot's last frame", 6.1).

Frame convention of :func:`triangle_frame` (the paper gives only the normal;
the rest is chosen here):

- origin: the circumcentre (the centre of the circle through the three
  points, radius R_t of (48));
- z: the unit normal (p2 - p1) × (p3 - p1), so the targets run
  counter-clockwise about z;
- x: from the circumcentre towards p1; y = z × x.

Section 6.2 explains the AT's orientation accuracy by (48): moving one
vertex by the diameter 2 r_e of its uncertainty ball tilts the normal by
γ = 2 r_e / R_t (:func:`triangle_gamma`). That is a worst-case, order-of-
magnitude figure: the exact tilt from moving one vertex by h normal to the
plane is h / (its distance to the opposite side), 1.5 R_t for an equilateral
triangle. :func:`triangle_angle_sigma` gives the statistical answer, the
tracker covariance of each vertex propagated (to first order) to the small
rotation of the triangle frame; :func:`triangle_angle_monte_carlo` the
sampled one.

Everything is SI (m, rad).
"""

from __future__ import annotations

from dataclasses import dataclass

import torch

from .tracker import GeometryError, TrackerNoise, tracker_points, sample_tracker_points

_DEGENERATE = 1e-9  # |a × b| / (|a| |b|): sine of the smallest admissible angle between two sides


def _vertices(p1, p2, p3) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    p1, p2, p3 = tracker_points(p1, "p1"), tracker_points(p2, "p2"), tracker_points(p3, "p3")
    p1, p2, p3 = torch.broadcast_tensors(p1, p2.to(p1), p3.to(p1))
    a, b = p2 - p1, p3 - p1
    n = torch.linalg.cross(a, b)
    size = torch.linalg.norm(a, dim=-1) * torch.linalg.norm(b, dim=-1)
    bad = ~(torch.linalg.norm(n, dim=-1) > _DEGENERATE * size)
    if bad.any():
        idx = tuple(int(i) for i in bad.nonzero()[0])
        raise GeometryError(f"triangle {idx}: the three points are (nearly) collinear or coincide: "
                            f"{p1[idx].tolist()}, {p2[idx].tolist()}, {p3[idx].tolist()}")
    return p1, p2, p3


def _frame(p1, p2, p3) -> torch.Tensor:
    """Unchecked :func:`triangle_frame` (vmap and autograd friendly)."""
    a, b = p1 - p3, p2 - p3
    axb = torch.linalg.cross(a, b)
    num = torch.linalg.cross((a * a).sum(-1, keepdim=True) * b - (b * b).sum(-1, keepdim=True) * a, axb)
    c = p3 + num / (2.0 * (axb * axb).sum(-1, keepdim=True))
    z = torch.linalg.cross(p2 - p1, p3 - p1)
    z = z / torch.linalg.norm(z, dim=-1, keepdim=True)
    x = p1 - c
    x = x / torch.linalg.norm(x, dim=-1, keepdim=True)
    y = torch.linalg.cross(z, x)
    R = torch.stack([x, y, z], -1)
    top = torch.cat([R, c[..., :, None]], -1)
    bottom = torch.zeros_like(top[..., :1, :])
    bottom[..., 0, 3] = 1.0
    return torch.cat([top, bottom], -2)


def triangle_frame(p1, p2, p3) -> torch.Tensor:
    """Frame of the triangle of three target points: (B, 3) each, m -> (B, 4, 4).

    Origin at the circumcentre, z = unit normal (p2 - p1) × (p3 - p1), x
    towards p1, y = z × x (see the module docstring). Raises
    :class:`GeometryError` naming the row of a degenerate triangle.

    Example:
        >>> import torch
        >>> p = torch.eye(3, dtype=torch.float64)
        >>> T = triangle_frame(p[0][None], p[1][None], p[2][None])
        >>> [round(v, 4) for v in T[0, :3, 2].tolist()], [round(v, 4) for v in T[0, :3, 3].tolist()]
        ([0.5774, 0.5774, 0.5774], [0.3333, 0.3333, 0.3333])
    """
    return _frame(*_vertices(p1, p2, p3))


def circumradius(p1, p2, p3) -> torch.Tensor:
    """Radius R_t (B,) m of the circle through three points (B, 3): |a| |b| |c| / (2 |(p2 - p1) × (p3 - p1)|)."""
    p1, p2, p3 = _vertices(p1, p2, p3)
    la, lb, lc = (torch.linalg.norm(u, dim=-1) for u in (p2 - p1, p3 - p2, p1 - p3))
    return la * lb * lc / (2.0 * torch.linalg.norm(torch.linalg.cross(p2 - p1, p3 - p1), dim=-1))


def triangle_gamma(p1, p2, p3, r_e) -> torch.Tensor:
    """The AT orientation uncertainty γ = 2 r_e / R_t of (48): r_e m (float or (B,)) -> (B,) rad."""
    return 2.0 * torch.as_tensor(r_e) / circumradius(p1, p2, p3)


def _rotation_angle(R: torch.Tensor) -> torch.Tensor:
    """Geodesic angle (...) of rotations (..., 3, 3), atan2 form: accurate for tiny angles too."""
    v = torch.stack([R[..., 2, 1] - R[..., 1, 2], R[..., 0, 2] - R[..., 2, 0], R[..., 1, 0] - R[..., 0, 1]], -1)
    tr = R[..., 0, 0] + R[..., 1, 1] + R[..., 2, 2]
    return torch.atan2(0.5 * torch.linalg.norm(v, dim=-1), 0.5 * (tr - 1.0))


def _rotation_vector(R: torch.Tensor) -> torch.Tensor:
    """Log map (..., 3, 3) -> (..., 3) for angles well below π."""
    v = 0.5 * torch.stack([R[..., 2, 1] - R[..., 1, 2], R[..., 0, 2] - R[..., 2, 0], R[..., 1, 0] - R[..., 0, 1]], -1)
    s = torch.linalg.norm(v, dim=-1, keepdim=True)
    ang = _rotation_angle(R)[..., None]
    scale = torch.where(s > 0, ang / torch.where(s > 0, s, torch.ones_like(s)), torch.ones_like(s))
    return v * scale


def _unit_angle(u: torch.Tensor, w: torch.Tensor) -> torch.Tensor:
    return torch.atan2(torch.linalg.norm(torch.linalg.cross(u, w), dim=-1), (u * w).sum(-1))


def _stacked(t, name: str) -> torch.Tensor:
    t = tracker_points(t, name)
    if t.ndim < 2 or t.shape[-2] != 3:
        raise GeometryError(f"{name}: expected (B, 3, 3) triangles (rows p1, p2, p3), got shape {tuple(t.shape)}")
    return t


def triangle_orientation_error(measured, modeled, kind: str = "normal") -> torch.Tensor:
    """Angle (B,) rad between measured and modeled triangle frames; both (B, 3, 3), rows p1, p2, p3, m.

    kind="normal": angle between the two normals, the AT angular residual of
    Table 6 (orientation = the normal; rotation about it is not measured);
    kind="frame": geodesic angle between the two full frames of
    :func:`triangle_frame`. Use :func:`torchcal.core.units.rad_to_deg` for degrees.
    """
    m, h = _stacked(measured, "measured"), _stacked(modeled, "modeled")
    Tm = triangle_frame(m[..., 0, :], m[..., 1, :], m[..., 2, :])
    Th = triangle_frame(h[..., 0, :], h[..., 1, :], h[..., 2, :]).to(Tm)
    if kind == "normal":
        return _unit_angle(Tm[..., :3, 2], Th[..., :3, 2])
    if kind == "frame":
        return _rotation_angle(Tm[..., :3, :3].transpose(-1, -2) @ Th[..., :3, :3])
    raise GeometryError(f"triangle_orientation_error: kind must be 'normal' or 'frame', got {kind!r}")


@dataclass
class TriangleAngleSigma:
    """Orientation uncertainty of triangle frames, SI.

    cov: (B, 3, 3) rad², covariance of the small rotation ω of the frame,
    R_measured = R exp([ω]×), ω in the triangle frame's own axes (ω_x, ω_y
    tilt the normal, ω_z turns the frame in its plane); normal: (B,) rad, RMS
    tilt of the normal sqrt(E|Δn|²) = sqrt(cov_xx + cov_yy); in_plane: (B,)
    rad, sqrt(cov_zz); radius: (B,) m, circumradius R_t.
    """

    cov: torch.Tensor
    normal: torch.Tensor
    in_plane: torch.Tensor
    radius: torch.Tensor

    @classmethod
    def from_cov(cls, cov: torch.Tensor, radius: torch.Tensor) -> TriangleAngleSigma:
        return cls(cov, torch.sqrt(cov[..., 0, 0] + cov[..., 1, 1]), torch.sqrt(cov[..., 2, 2]), radius)


def _vertex_cov(P: torch.Tensor, lead: tuple, noise) -> torch.Tensor:
    """Vertices (B, 3, 3) (B = prod(lead)) -> (B, 3, 3, 3) covariance per vertex.

    A tensor's rank decides its reading: (3, 3) every vertex, (*lead, 3, 3)
    per triangle, (*lead, 3, 3, 3) per vertex.
    """
    if isinstance(noise, TrackerNoise):
        return noise.covariance(P.reshape(-1, 3)).reshape(*P.shape, 3)
    cov = torch.as_tensor(noise).to(P)
    L = len(lead)
    if cov.shape == (3, 3):
        return cov.expand(*P.shape, 3)
    if cov.shape == (*lead, 3, 3):
        return cov.reshape(-1, 1, 3, 3).expand(*P.shape, 3)
    if cov.shape == (*lead, 3, 3, 3):
        return cov.reshape(*P.shape, 3)
    raise GeometryError(f"triangle_angle_sigma: noise must be a TrackerNoise or a covariance in m² of shape (3, 3), "
                        f"{(*lead, 3, 3)} or {(*lead, 3, 3, 3)}, got {tuple(cov.shape)} ({L} batch dimensions)")


def frame_rotation_jacobian(p1, p2, p3) -> torch.Tensor:
    """∂ω/∂p_k of the triangle frame's small rotation, R(p + δp) = R exp([ω]×): (B, 3) each -> (B, 3, 3, 3), m⁻¹.

    Index order (batch, ω component in the frame's axes, vertex k, coordinate).
    Closed form: with a = p2 - p1, b = p3 - p1, u = a × b, ω_x = -y · δu / |u|
    and ω_y = x · δu / |u| (the normal's tilt); ω_z = y · (δp1 - δc) / R_t,
    the circumcentre's motion δc from differentiating the linear system
    (p2 - p1) · c = (|p2|² - |p1|²) / 2, (p3 - p1) · c = (|p3|² - |p1|²) / 2,
    u · c = u · p1 that defines it.
    """
    p1, p2, p3 = _vertices(p1, p2, p3)
    T = _frame(p1, p2, p3)
    x, y, c = T[..., :3, 0], T[..., :3, 1], T[..., :3, 3]
    cross = torch.linalg.cross
    a, b = p2 - p1, p3 - p1
    u = cross(a, b)
    nu = torch.linalg.norm(u, dim=-1, keepdim=True)
    e = p1 - c
    radius = torch.linalg.norm(e, dim=-1, keepdim=True)

    def by_vertex(ga, gb, g1_extra=0.0):
        # δa = δp2 - δp1, δb = δp3 - δp1
        return torch.stack([g1_extra - ga - gb, ga, gb], -2)

    jx = by_vertex(-cross(b, y) / nu, -cross(y, a) / nu)
    jy = by_vertex(cross(b, x) / nu, cross(x, a) / nu)
    A = torch.stack([a, b, u], -2)
    m = torch.linalg.solve(A.transpose(-1, -2), y[..., None])[..., 0]
    m1, m2, m3 = m[..., 0:1], m[..., 1:2], m[..., 2:3]
    # y · δc per vertex
    dc2 = m1 * (p2 - c) + m3 * cross(b, e)
    dc3 = m2 * (p3 - c) + m3 * cross(e, a)
    dc1 = -(m1 + m2) * e + m3 * u - m3 * cross(b, e) - m3 * cross(e, a)
    jz = torch.stack([y - dc1, -dc2, -dc3], -2) / radius[..., None]
    return torch.stack([jx, jy, jz], -3)


def triangle_angle_sigma(p1, p2, p3, noise) -> TriangleAngleSigma:
    """First-order orientation uncertainty of the triangle frame from the noise of its three vertices.

    p1, p2, p3: (B, 3) m, true target positions in the tracker frame; noise:
    a :class:`TrackerNoise` (each vertex gets its own distance-dependent
    covariance) or a covariance in m², (3, 3) for all vertices, (B, 3, 3) per
    triangle or (B, 3, 3, 3) per vertex. Vertices are independent:
    Σ_ω = Σ_k J_k Σ_k J_k^T with J_k = ∂ω/∂p_k (:func:`frame_rotation_jacobian`).

    Example:
        >>> import torch
        >>> c = torch.tensor([2.0, 0.0, 0.0], dtype=torch.float64)
        >>> ang = torch.tensor([0.0, 2.0944, 4.1888], dtype=torch.float64)
        >>> tri = c + 0.0665 * torch.stack([torch.zeros(3, dtype=torch.float64), ang.cos(), ang.sin()], -1)
        >>> s = triangle_angle_sigma(tri[0][None], tri[1][None], tri[2][None], TrackerNoise.paper3())
        >>> round(float(s.normal[0]) * 1e6)  # µrad
        87
    """
    p1, p2, p3 = _vertices(p1, p2, p3)
    lead = p1.shape[:-1]
    P = torch.stack([p1, p2, p3], -2).reshape(-1, 3, 3)
    J = frame_rotation_jacobian(P[:, 0], P[:, 1], P[:, 2])  # (B, 3 ω, 3 vertices, 3 coords)
    C = _vertex_cov(P, tuple(lead), noise)  # (B, 3 vertices, 3, 3)
    Jk = J.permute(0, 2, 1, 3)  # (B, vertex, 3 ω, 3 coords)
    cov = (Jk @ C @ Jk.transpose(-1, -2)).sum(1)
    return TriangleAngleSigma.from_cov(cov.reshape(*lead, 3, 3), circumradius(p1, p2, p3))


def triangle_angle_monte_carlo(p1, p2, p3, noise: TrackerNoise, n: int = 20_000, seed: int = 0) -> TriangleAngleSigma:
    """Sampled counterpart of :func:`triangle_angle_sigma`: n tracker measurements of each vertex.

    Every vertex is drawn by :func:`sample_tracker_points` (noise on α, β, d,
    exact map (34)); ω = log(R^T R_measured) of each sample; cov is the
    sample second moment of ω about zero (the true frame), normal the RMS
    angle between measured and true normals. Memory: B · 3 · n · 3 floats.
    """
    p1, p2, p3 = _vertices(p1, p2, p3)
    lead = p1.shape[:-1]
    P = torch.stack([p1, p2, p3], -2).reshape(-1, 3, 3)
    R0 = _frame(P[:, 0], P[:, 1], P[:, 2])[:, :3, :3]
    S = sample_tracker_points(P, noise, n, seed)  # (B, 3, n, 3)
    Rm = _frame(S[:, 0], S[:, 1], S[:, 2])[..., :3, :3]  # (B, n, 3, 3)
    w = _rotation_vector(R0[:, None].transpose(-1, -2) @ Rm)
    cov = (w.transpose(-1, -2) @ w) / n
    out = TriangleAngleSigma.from_cov(cov.reshape(*lead, 3, 3), circumradius(p1, p2, p3))
    tilt = _unit_angle(R0[:, None, :, 2].expand_as(Rm[..., 2]), Rm[..., :, 2])
    out.normal = torch.sqrt((tilt**2).mean(-1)).reshape(lead)
    return out
