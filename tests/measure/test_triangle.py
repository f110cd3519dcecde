"""Three-target (AT) orientation, Paper III 6.1-6.2 and (48): frame convention, errors, propagated tracker noise."""

import math

import pytest
import torch
from hypothesis import given, settings
from hypothesis import strategies as st

from torchcal.measure.tracker import GeometryError, TrackerNoise
from torchcal.measure.triangle import (
    circumradius,
    frame_rotation_jacobian,
    triangle_angle_monte_carlo,
    triangle_angle_sigma,
    triangle_frame,
    triangle_gamma,
    triangle_orientation_error,
)

T = {"dtype": torch.float64}


def random_rotation(g):
    q = torch.randn(4, generator=g, **T)
    w, x, y, z = (q / q.norm()).tolist()
    return torch.tensor([[1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)],
                         [2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)],
                         [2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)]], **T)


def circle_triangle(center, R, radius, phases):
    """Vertices on a circle of ``radius`` about ``center`` in the plane of R's x, y columns: (3, 3)."""
    ph = torch.as_tensor(phases, **T)
    local = torch.stack([radius * ph.cos(), radius * ph.sin(), torch.zeros(3, **T)], -1)
    return torch.as_tensor(center, **T) + local @ R.T


def split(tri):
    return tri[..., 0, :], tri[..., 1, :], tri[..., 2, :]


@settings(max_examples=30, deadline=None)
@given(st.integers(0, 10_000), st.floats(0.01, 2.0),
       st.lists(st.floats(0.3, 2.0), min_size=3, max_size=3))
def test_frame_convention_on_a_known_circle(seed, radius, gaps):
    """Vertices placed counter-clockwise on a known circle: origin = its centre, z = its normal, x towards p1."""
    g = torch.Generator().manual_seed(seed)
    R = random_rotation(g)
    center = torch.randn(3, generator=g, **T) * 3
    start = float(torch.rand(1, generator=g)) * 6.0
    ph = [start, start + gaps[0], start + gaps[0] + gaps[1]]  # all gaps < π·2/3: counter-clockwise, non-degenerate
    tri = circle_triangle(center, R, radius, ph)
    F = triangle_frame(*split(tri[None]))[0]
    assert torch.allclose(F[:3, :3].T @ F[:3, :3], torch.eye(3, **T), atol=1e-12)
    assert torch.linalg.det(F[:3, :3]) == pytest.approx(1.0, abs=1e-12)
    assert torch.allclose(F[:3, 3], center, atol=1e-9 * (1 + radius))
    assert torch.allclose(F[:3, 2], R[:, 2], atol=1e-9)
    assert torch.allclose(F[:3, 0], (tri[0] - center) / radius, atol=1e-8)
    assert torch.equal(F[3], torch.tensor([0.0, 0, 0, 1], **T))
    assert float(circumradius(*split(tri[None]))[0]) == pytest.approx(radius, rel=1e-10)


def test_frame_moves_with_the_triangle():
    g = torch.Generator().manual_seed(1)
    tri = torch.randn(5, 3, 3, generator=g, **T)
    R, t = random_rotation(g), torch.randn(3, generator=g, **T)
    F = triangle_frame(*split(tri))
    F2 = triangle_frame(*split(tri @ R.T + t))
    A = torch.eye(4, **T)
    A[:3, :3], A[:3, 3] = R, t
    assert torch.allclose(F2, A @ F, atol=1e-12)


def test_gamma_48_reproduces_the_paper():
    """6.2: r_e = 0.051 mm, mean circumradius 66.43 mm -> γ = 0.0015 rad."""
    tri = circle_triangle([1.0, 2.0, 0.5], torch.eye(3, **T), 66.43e-3, [0.0, 2.1, 4.2])
    gamma = float(triangle_gamma(*split(tri[None]), 0.051e-3)[0])
    assert gamma == pytest.approx(2 * 0.051 / 66.43, rel=1e-10)
    assert round(gamma, 4) == 0.0015


def test_moving_one_vertex_off_the_plane_tilts_the_normal_by_h_over_its_altitude():
    """The exact geometry behind (48): γ = atan(h / altitude); for an equilateral triangle altitude = 1.5 R_t."""
    R_t, h = 66.43e-3, 2 * 0.051e-3
    tri = circle_triangle([0.0, 0.0, 0.0], torch.eye(3, **T), R_t, [0.0, 2 * math.pi / 3, 4 * math.pi / 3])
    moved = tri.clone()
    moved[2, 2] += h
    err = float(triangle_orientation_error(tri[None], moved[None])[0])
    assert err == pytest.approx(math.atan(h / (1.5 * R_t)), rel=1e-9)
    assert float(triangle_gamma(*split(tri[None]), h / 2)[0]) == pytest.approx(1.5 * err, rel=1e-6)
    assert float(triangle_orientation_error(tri[None], moved[None], kind="frame")[0]) >= err


def test_frame_error_sees_a_turn_in_the_plane_the_normal_error_does_not():
    g = torch.Generator().manual_seed(2)
    R = random_rotation(g)
    c = torch.tensor([2.0, -1.0, 0.4], **T)
    tri = circle_triangle(c, R, 0.07, [0.1, 2.0, 4.0])
    turned = circle_triangle(c, R, 0.07, [0.1 + 3e-4, 2.0 + 3e-4, 4.0 + 3e-4])
    pair = torch.stack([tri, turned])
    assert float(triangle_orientation_error(tri[None], turned[None])[0]) < 1e-12
    assert float(triangle_orientation_error(tri[None], turned[None], kind="frame")[0]) == pytest.approx(3e-4, rel=1e-8)
    assert triangle_orientation_error(pair, pair.flip(0), kind="frame").shape == (2,)


def test_closed_form_rotation_jacobian_matches_autograd_of_the_frame():
    g = torch.Generator().manual_seed(8)
    P = torch.randn(6, 3, 3, generator=g, **T)
    R0 = triangle_frame(*split(P))[:, :3, :3]

    def frame(pts):
        """Independent construction: circumcentre from the bisector-plane system, then the stated axes."""
        p1, p2, p3 = pts
        n = torch.linalg.cross(p2 - p1, p3 - p1)
        A = torch.stack([p2 - p1, p3 - p1, n])
        r = torch.stack([(p2 @ p2 - p1 @ p1) / 2, (p3 @ p3 - p1 @ p1) / 2, n @ p1])
        c = torch.linalg.solve(A, r)
        z = n / torch.linalg.norm(n)
        x = (p1 - c) / torch.linalg.norm(p1 - c)
        return torch.stack([x, torch.linalg.cross(z, x), z], -1)

    assert torch.allclose(torch.stack([frame(p) for p in P]), R0, atol=1e-10)

    # central differences of the exact log map of R0^T R(p ± h e_k), every vertex coordinate at once
    h = 1e-6
    steps = h * torch.eye(9, **T).reshape(9, 3, 3)
    Rp = torch.stack([torch.stack([frame(p + s_) for s_ in steps]) for p in P])
    Rm = torch.stack([torch.stack([frame(p - s_) for s_ in steps]) for p in P])

    def log(R):
        E = R0[:, None].transpose(-1, -2) @ R
        v = 0.5 * torch.stack([E[..., 2, 1] - E[..., 1, 2], E[..., 0, 2] - E[..., 2, 0], E[..., 1, 0] - E[..., 0, 1]], -1)
        s_ = torch.linalg.norm(v, dim=-1, keepdim=True)
        return v * torch.asin(s_) / s_

    ref = ((log(Rp) - log(Rm)) / (2 * h)).transpose(-1, -2).reshape(6, 3, 3, 3)  # (B, ω, vertex, coord)
    assert torch.allclose(frame_rotation_jacobian(*split(P)), ref, atol=1e-7 * float(ref.abs().max()))


def test_isotropic_vertex_noise_tilts_an_equilateral_triangle_by_2_sigma_over_sqrt3_R():
    """Analytic: only out-of-plane noise tilts the plane; the exact-fit plane's gradient has variance 2σ²/(3R²) per axis."""
    g = torch.Generator().manual_seed(4)
    R_t, sigma = 0.0665, 5e-6
    tri = torch.stack([circle_triangle(torch.randn(3, generator=g, **T), random_rotation(g), R_t,
                                       [a, a + 2 * math.pi / 3, a + 4 * math.pi / 3]) for a in (0.0, 0.7, 2.0)])
    s = triangle_angle_sigma(*split(tri), sigma**2 * torch.eye(3, **T))
    assert torch.allclose(s.normal, torch.full((3,), 2 * sigma / (math.sqrt(3) * R_t), **T), rtol=1e-9)
    assert torch.allclose(s.radius, torch.full((3,), R_t, **T), rtol=1e-12)


def test_sigma_scales_inversely_with_the_triangle_size():
    """The AT's orientation accuracy depends on the triangle size: same vertex covariance, twice the size, half the angle."""
    g = torch.Generator().manual_seed(5)
    tri = torch.randn(4, 3, 3, generator=g, **T) * 0.05 + torch.tensor([2.0, 0.5, 0.2], **T)
    A = torch.randn(3, 3, generator=g, **T) * 1e-5
    cov = A @ A.T + 1e-12 * torch.eye(3, **T)  # anisotropic, shared by every vertex
    c = tri.mean(-2, keepdim=True)
    s1 = triangle_angle_sigma(*split(tri), cov)
    s2 = triangle_angle_sigma(*split(c + 2.0 * (tri - c)), cov)
    assert torch.allclose(s2.cov, s1.cov / 4.0, rtol=1e-9)


def test_beyond_2_m_the_angle_sigma_does_not_change_when_the_whole_scene_is_scaled():
    """For d > 2 m every tracker variance grows as d² (47): scaling distances and triangle together leaves the angles."""
    tri = circle_triangle([3.0, 1.0, 0.8], torch.eye(3, **T), 0.0665, [0.0, 2.1, 4.2])
    noise = TrackerNoise.paper3()
    s1 = triangle_angle_sigma(*split(tri[None]), noise)
    s2 = triangle_angle_sigma(*split(1.7 * tri[None]), noise)
    assert torch.allclose(s1.cov, s2.cov, rtol=1e-9)


def test_linearized_angle_sigma_matches_monte_carlo_on_tracker_draws():
    """Tracker noise on (α, β, d) through the exact map (34) and the exact frame: first-order Σ_ω within MC error."""
    noise = TrackerNoise.paper3()
    g = torch.Generator().manual_seed(6)
    centers = [[1.5, 0.3, 0.4], [0.5, -2.5, 0.2], [-4.0, 2.0, 1.0], [6.0, 5.0, -0.5]]
    tri = torch.stack([circle_triangle(c, random_rotation(g), 0.0665, [0.2, 2.2, 4.3]) for c in centers])
    lin = triangle_angle_sigma(*split(tri), noise)
    mc = triangle_angle_monte_carlo(*split(tri), noise, n=40_000, seed=11)
    dg = torch.diagonal(mc.cov, dim1=-2, dim2=-1)
    dev = (lin.cov - mc.cov).abs() / torch.sqrt(dg[..., :, None] * dg[..., None, :])
    assert float(dev.max()) < 0.04  # sampling error of a variance with 4e4 draws: 0.7 %
    assert torch.allclose(lin.normal, mc.normal, rtol=0.02)
    # the AT's angle noise depends on where the triangle sits: farther is noisier
    assert float(lin.normal[3]) > 1.5 * float(lin.normal[0])


def test_degenerate_triangles_are_named():
    tri = torch.tensor([[[0.0, 0, 0], [1, 0, 0], [0, 1, 0]], [[0.0, 0, 0], [1, 1, 1], [2, 2, 2]]], **T)
    with pytest.raises(GeometryError, match=r"triangle \(1,\)"):
        triangle_frame(*split(tri))
    with pytest.raises(GeometryError, match="kind"):
        triangle_orientation_error(tri[:1], tri[:1], kind="axis")


def test_covariance_inputs_per_vertex_per_triangle_and_shared_agree():
    noise = TrackerNoise.paper3()
    g = torch.Generator().manual_seed(7)
    tri = torch.randn(3, 3, 3, generator=g, **T) * 0.05 + torch.tensor([2.5, -1.0, 0.3], **T)  # B = 3: shapes are ambiguous by size
    per_vertex = noise.covariance(tri.reshape(-1, 3)).reshape(3, 3, 3, 3)
    ref = triangle_angle_sigma(*split(tri), noise)
    assert torch.allclose(triangle_angle_sigma(*split(tri), per_vertex).cov, ref.cov, rtol=1e-12)
    per_triangle = per_vertex[:, 0] * torch.tensor([1.0, 4.0, 9.0], **T)[:, None, None]  # (B, 3, 3), differs per triangle
    same = triangle_angle_sigma(*split(tri), per_triangle[:, None].expand(3, 3, 3, 3)).cov
    assert torch.allclose(triangle_angle_sigma(*split(tri), per_triangle).cov, same, rtol=1e-12)
    shared = per_vertex[0, 0]
    assert torch.allclose(triangle_angle_sigma(*split(tri), shared).cov,
                          triangle_angle_sigma(*split(tri), shared.expand(3, 3, 3, 3)).cov, rtol=1e-12)
    with pytest.raises(GeometryError, match="covariance"):
        triangle_angle_sigma(*split(tri), torch.eye(2, **T))
