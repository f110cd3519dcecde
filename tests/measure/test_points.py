import pytest
import torch

from torchcal.measure import CovarianceWeight, IsotropicWeight, PointTargets, row_jacobians


def test_weights_round_trip_and_sqrt_info():
    g = torch.Generator().manual_seed(0)
    B = torch.randn(5, 3, 3, generator=g)
    cov = B @ B.transpose(1, 2) + 0.1 * torch.eye(3)
    w = CovarianceWeight(cov)
    r = torch.randn(5, 3, generator=g)
    J = torch.randn(5, 3, 7, generator=g)
    assert torch.allclose(w.unwhiten(w.whiten(r)), r, atol=1e-12)
    S = w.sqrt_info(5, 3, r)
    assert torch.allclose(S.transpose(1, 2) @ S, torch.linalg.inv(cov), rtol=1e-9, atol=1e-12)
    assert torch.allclose(w.whiten(J), S @ J, atol=1e-12)
    iso = IsotropicWeight(2.0)
    assert torch.allclose(iso.sqrt_info(5, 3, r) @ r[..., None], iso.whiten(r)[..., None])
    assert torch.allclose(w.subset(torch.tensor([1, 3])).whiten(r[[1, 3]]), w.whiten(r)[[1, 3]])
    # a subset's factors are the rows' own (taken, not factored again): equal to a fresh factorization
    sub, fresh = w.subset(torch.tensor([4, 0])), CovarianceWeight(cov[[4, 0]])
    assert torch.equal(sub.cov, fresh.cov) and torch.equal(sub.L, fresh.L) and torch.equal(sub.S, fresh.S)
    assert w.to("cpu") is w and w.to(torch.device("cpu")) is w


def test_bad_inputs_name_the_row():
    cov = torch.eye(3).repeat(4, 1, 1)
    cov[2, 1, 1] = -1.0
    with pytest.raises(ValueError, match="row 2"):
        CovarianceWeight(cov)
    xyz = torch.zeros(4, 3)
    xyz[3, 0] = float("nan")
    with pytest.raises(ValueError, match="row 3"):
        PointTargets(xyz, sigma=1e-6)
    with pytest.raises(ValueError, match="exactly one"):
        PointTargets(torch.zeros(4, 3))
    with pytest.raises(ValueError, match="sigma"):
        IsotropicWeight(0.0)


def test_point_targets_subset_keeps_rows_and_weights():
    g = torch.Generator().manual_seed(1)
    xyz = torch.randn(6, 3, generator=g)
    B = torch.randn(6, 3, 3, generator=g)
    pt = PointTargets(xyz, cov=B @ B.transpose(1, 2) + torch.eye(3))
    sub = pt.subset(torch.tensor([True, False, True, False, False, True]))
    assert len(sub) == 3 and torch.equal(sub.observed, xyz[[0, 2, 5]])
    r = torch.randn(3, 3, generator=g)
    assert torch.allclose(sub.whiten(r), pt.whiten(torch.zeros(6, 3).index_copy(0, torch.tensor([0, 2, 5]), r))[[0, 2, 5]])


def test_row_jacobians_match_the_analytic_ones():
    """fn(params, v_r, x_r) = [a * x_r . v_r, b^2 + v_r[0]] per row: d = 2, vmapped jacrev."""
    g = torch.Generator().manual_seed(2)
    R, n = 7, 3
    params = {"a": torch.tensor(1.5), "b": torch.randn(2, generator=g)}
    v = torch.randn(R, n, generator=g)
    x = torch.randn(R, n, generator=g)

    def fn(p, vr, xr):
        return torch.stack([p["a"] * (xr * vr).sum(-1), (p["b"] ** 2).sum() + vr[:, 0]], -1)

    r, Jp, Jv = row_jacobians(fn, params, v, x)
    assert torch.allclose(r, fn(params, v, x))
    assert torch.allclose(Jp["a"], torch.stack([(x * v).sum(-1), torch.zeros(R)], -1))
    assert torch.allclose(Jp["b"], torch.stack([torch.zeros(R, 2), (2 * params["b"]).expand(R, 2)], 1))
    expected_v = torch.zeros(R, 2, n)
    expected_v[:, 0] = 1.5 * x
    expected_v[:, 1, 0] = 1.0
    assert torch.allclose(Jv, expected_v)
