"""The branch test's sign of det J (both of its paths, the elementwise elimination a GPU runs and LAPACK's LU on
the CPU) against torch.linalg.det, on random, permuted, scaled and exactly singular matrices."""

import pytest
import torch
from hypothesis import given, settings
from hypothesis import strategies as st

from torchcal.compensate import branch


@settings(max_examples=25, deadline=None)
@given(st.integers(min_value=2, max_value=7), st.integers(min_value=0, max_value=2**31 - 1))
def test_det_sign_matches_torch_det(n, seed):
    g = torch.Generator().manual_seed(seed)
    A = torch.randn(400, n, n, generator=g, dtype=torch.float64)
    A[:40] = A[:40][:, torch.randperm(n, generator=g)]  # row swaps flip the sign
    A[40:80] *= torch.logspace(-6, 6, n, dtype=torch.float64)  # badly scaled columns
    A[80:90, -1] = A[80:90, 0]  # exactly singular: sign 0 expected from det; either path may give +-1 only
    ref = torch.sign(torch.linalg.det(A))
    clear = torch.linalg.det(A).abs() > 1e-8 * torch.linalg.matrix_norm(A).pow(n)
    soa = A.permute(1, 2, 0).contiguous()
    for path in ("cpu", "elimination"):
        got = branch.det_sign_soa(soa) if path == "cpu" else branch._det_sign_elimination(soa)
        assert torch.equal(got[clear], ref[clear]), path


@pytest.mark.skipif(not torch.cuda.is_available(), reason="needs CUDA")
def test_det_sign_on_cuda_is_the_cpus():
    g = torch.Generator().manual_seed(5)
    A = torch.randn(1000, 6, 6, generator=g, dtype=torch.float64)
    soa = A.permute(1, 2, 0).contiguous()
    assert torch.equal(branch.det_sign_soa(soa.cuda()).cpu(), branch.det_sign_soa(soa))


@pytest.mark.parametrize("name", ["fanuc_lrmate200i", "ur10", "abb_irb120"])
def test_the_lipschitz_bound_holds_and_sure_rows_keep_their_sign(name):
    """jacobian_lipschitz is an upper bound of how fast the (scaled) nominal Jacobian changes with the commands,
    checked on random pairs of commands (incl. the FANUC's coupled q2/q3); rows that surely_same_branch passes
    keep det J's sign at the end point and along the path."""
    import math

    import torchcal
    from torchcal.compensate.kernel import FlangeKernel

    robot = torchcal.load_robot(name)
    kernel = FlangeKernel(torchcal.RobotModel(robot, torch.zeros(1, 3, dtype=torch.float64), orders=0), fused=False)
    length = 1.0
    L = branch.jacobian_lipschitz(kernel, length)
    g = torch.Generator().manual_seed(7)
    lo, hi = robot.joint_map.limits[:, 0], robot.joint_map.limits[:, 1]
    q0 = lo + (hi - lo) * torch.rand(3000, 6, generator=g, dtype=torch.float64)
    dq = (torch.rand(3000, 6, generator=g, dtype=torch.float64) - 0.5) * torch.logspace(-3, 0, 3000, dtype=torch.float64)[:, None]
    q1 = q0 + dq
    D = torch.tensor([1.0] * 3 + [length] * 3, dtype=torch.float64)[:, None]
    J0 = kernel.nominal_flange_jacobian(q0.T.contiguous())[2]
    J1 = kernel.nominal_flange_jacobian(q1.T.contiguous())[2]
    change = torch.linalg.matrix_norm((D * (J1 - J0)).permute(2, 0, 1), 2)
    assert bool((change <= L * dq.abs().sum(1) * (1 + 1e-9)).all())
    P = torch.linalg.inv((D * J0).permute(2, 0, 1))
    sigma_lower = 1.0 / torch.linalg.matrix_norm(P)  # Frobenius: a lower bound of sigma_min
    sure = branch.surely_same_branch(q0, q1, sigma_lower, L)
    assert int(sure.sum()) > 100  # the test says something
    s0 = branch.det_sign_soa(J0)
    for t in (0.25, 0.5, 0.75, 1.0):
        qt = q0 + t * dq
        st = branch.det_sign_soa(kernel.nominal_flange_jacobian(qt.T.contiguous())[2])
        assert torch.equal(st[sure], s0[sure]), t
