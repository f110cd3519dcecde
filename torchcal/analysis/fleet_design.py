"""Bayesian pose design for a unit calibrated with few poses and a fleet prior (issue #18).

With a Gaussian prior N(mu, Sigma0) on the k free parameters (a fleet's,
:func:`torchcal.identify.fleet.fleet_prior`) and the whitened, joint-error-
marginalized Jacobian of every candidate pose, B_c (m, k) (m = tools x 3
rows, :func:`pose_jacobians`), the linearized posterior after measuring the
poses S is

    Sigma_S = (Sigma0^-1 + sum_{c in S} B_c^T B_c)^-1,

and the model's predicted mean squared error at validation points whose
parameter Jacobian is G (g, k) (metres) is tr(G Sigma_S G^T) / points: the
Bayesian A-optimality criterion weighted by where the model is used
(I-optimality). :func:`greedy_design` picks poses one at a time, each the
candidate that lowers the criterion most (or, 'D', that raises
log det Sigma_S^-1 most), with rank-m updates of the products it needs:
no candidate's posterior is ever formed.

Everything here is a pure tensor function (float64, any device, batched over
candidates); the only loop is the greedy selection's loop over the picks.
"""

from __future__ import annotations

import torch


def pose_jacobians(A: torch.Tensor, C: torch.Tensor, w_v: torch.Tensor, rows: torch.Tensor) -> torch.Tensor:
    """Each pose's whitened Jacobian with its rows' joint errors marginalized.

    A: (R, d, k) whitened parameter Jacobian; C: (R, d, n) whitened joint-error Jacobian; w_v: (R, n) joint-error
    precisions (as :meth:`CalibrationProblem.linearize` and ``problem.w_v`` give them); rows: (N, T) long, the rows
    of each of N poses (e.g. its T tools). -> B (N, T d, k), B^T B summed over poses = the Schur-complemented
    normal matrix (:func:`torchcal.analysis.identifiability.reduced_jacobian`).
    """
    from .identifiability import reduced_jacobian

    At = reduced_jacobian(A, C, w_v)
    N, T = rows.shape
    return At[rows.reshape(-1)].reshape(N, T * A.shape[1], A.shape[2])


def error_weight(G: torch.Tensor, points: int | None = None) -> torch.Tensor:
    """A square root W (r, k) of G^T G / points (G (g, k): the model points' Jacobian at the validation commands,
    g = 3 x points rows, metres) so that tr(W Sigma W^T) is the predicted mean squared point error (m^2) of a
    parameter error of covariance Sigma (k, k). r = k (eigen-decomposition: near-null directions give zero rows)."""
    npts = G.shape[0] // 3 if points is None else int(points)
    H = G.T @ G / npts
    ev, U = torch.linalg.eigh(H)
    return (U * ev.clamp(min=0.0).sqrt()).T


def posterior_covariance(prior_cov: torch.Tensor, B: torch.Tensor) -> torch.Tensor:
    """(k, k) linearized posterior covariance (Sigma0^-1 + sum_c B_c^T B_c)^-1 of prior_cov Sigma0 (k, k) and the
    poses' whitened Jacobians B (N, m, k) (N = 0 allowed), in the covariance form (Woodbury): Sigma0 - Sigma0 B^T
    (I + B Sigma0 B^T)^-1 B Sigma0, which needs no inverse of Sigma0."""
    Bf = B.reshape(-1, B.shape[-1])
    if Bf.shape[0] == 0:
        return prior_cov.clone()
    SB = prior_cov @ Bf.T  # (k, r)
    F = torch.linalg.cholesky(torch.eye(Bf.shape[0], dtype=B.dtype, device=B.device) + Bf @ SB)
    U = torch.linalg.solve_triangular(F, SB.T, upper=False)  # (r, k)
    out = prior_cov - U.T @ U
    return 0.5 * (out + out.T)


def posterior_mean(prior_mean: torch.Tensor, prior_cov: torch.Tensor, B: torch.Tensor, y: torch.Tensor) -> torch.Tensor:
    """(k,) posterior mean of the linear-Gaussian model y = B x + e, e ~ N(0, I), x ~ N(prior_mean, prior_cov):
    prior_mean + Sigma0 B^T (I + B Sigma0 B^T)^-1 (y - B prior_mean). B (N, m, k), y (N, m) whitened."""
    Bf, yf = B.reshape(-1, B.shape[-1]), y.reshape(-1)
    SB = prior_cov @ Bf.T
    K = torch.eye(Bf.shape[0], dtype=B.dtype, device=B.device) + Bf @ SB
    return prior_mean + SB @ torch.linalg.solve(K, yf - Bf @ prior_mean)


def predicted_mse(cov: torch.Tensor, W: torch.Tensor) -> torch.Tensor:
    """Predicted mean squared point error tr(W cov W^T) (m^2) of a parameter error of covariance cov (k, k);
    W (r, k) from :func:`error_weight`. Batched: cov (..., k, k) -> (...)."""
    return (W @ cov @ W.T).diagonal(dim1=-2, dim2=-1).sum(-1)


def known_group_gain(cov: torch.Tensor, W: torch.Tensor, groups: dict) -> dict:
    """How much of the predicted mean squared error tr(W cov W^T) (m^2) each group of entries carries: the drop
    if that group alone were known exactly, tr(W cov_g. cov_gg^-1 cov_g. ^T W^T) (the value of knowing it; groups
    overlap in what they explain where the posterior correlates them, so the drops need not add up to the total).
    cov: (k, k); W: (r, k); groups: {name: index list into k}. -> {name: drop (m^2)}."""
    out = {}
    for name, ix in groups.items():
        ix = torch.as_tensor(ix, dtype=torch.long, device=cov.device)
        if ix.numel() == 0:
            out[name] = 0.0
            continue
        Sg = cov[:, ix]  # (k, g)
        F = torch.linalg.cholesky(cov[ix][:, ix])
        Y = torch.linalg.solve_triangular(F, (W @ Sg).T, upper=False)  # (g, r)
        out[name] = float(Y.pow(2).sum())
    return out


def greedy_design(B: torch.Tensor, prior_cov: torch.Tensor, count: int, W: torch.Tensor | None = None,
                  criterion: str = "A", start: torch.Tensor | None = None) -> tuple[torch.Tensor, torch.Tensor]:
    """Pick ``count`` of the N candidate poses, greedily, for the linearized posterior of a Gaussian prior.

    B: (N, m, k) candidates' whitened Jacobians (:func:`pose_jacobians`); prior_cov: (k, k); W: (r, k) the error
    weight (:func:`error_weight`; None: the identity, plain A-optimality on the parameters); criterion: 'A' (each
    pick lowers tr(W Sigma W^T), the predicted mean squared model error, most) or 'D' (raises log det Sigma^-1
    most); start: (s,) long, poses already measured (part of the posterior, not picked again).
    -> (picked (count,) long in pick order, objective (count + 1,): tr(W Sigma W^T) for 'A', log det Sigma^-1
    - log det Sigma0^-1 for 'D', before the first pick and after each).

    Per pick the products Z_c = B_c Sigma (N, m, k), S_c = B_c Sigma B_c^T (N, m, m) and V_c = B_c Sigma W^T
    (N, m, r) are updated by the rank-m downdate of Sigma, O(N m^2 (k + r)); the A gain of candidate c is
    tr((I + S_c)^-1 V_c V_c^T), the D gain log det (I + S_c).
    """
    if criterion not in ("A", "D"):
        raise ValueError(f"greedy_design: criterion must be 'A' or 'D', got {criterion!r}")
    N, m, k = B.shape
    if not 0 < count <= N:
        raise ValueError(f"greedy_design: count {count} outside 1..{N} candidates")
    dt, dev = B.dtype, B.device
    Wt = torch.eye(k, dtype=dt, device=dev) if W is None else W.to(B)
    eye = torch.eye(m, dtype=dt, device=dev)
    Sigma = prior_cov.to(B)
    taken = torch.zeros(N, dtype=torch.bool, device=dev)
    if start is not None and start.numel():
        start = start.to(dev).long()
        Sigma = posterior_covariance(Sigma, B[start])
        taken[start] = True
    Z = B @ Sigma  # (N, m, k)
    S = Z @ B.transpose(1, 2)  # (N, m, m)
    V = Z @ Wt.T  # (N, m, r)
    obj = [predicted_mse(Sigma, Wt) if criterion == "A" else torch.zeros((), dtype=dt, device=dev)]
    picked = []
    for _ in range(int(count)):
        F = torch.linalg.cholesky(eye + 0.5 * (S + S.transpose(1, 2)))  # (N, m, m)
        if criterion == "A":
            X = torch.cholesky_solve(V, F)  # (I + S)^-1 V
            gain = (X * V).sum((1, 2))
        else:
            gain = 2.0 * F.diagonal(dim1=1, dim2=2).log().sum(1)
        gain = gain.masked_fill(taken, -torch.inf)
        s = int(torch.argmax(gain))
        picked.append(s)
        taken[s] = True
        obj.append(obj[-1] - gain[s] if criterion == "A" else obj[-1] + gain[s])
        # Sigma' = Sigma - U U^T, U = Sigma B_s^T F_s^-T (k, m); every product downdated by B_c U
        Fs = F[s]
        U = torch.linalg.solve_triangular(Fs, Z[s], upper=False).T  # (k, m)
        BU = torch.linalg.solve_triangular(Fs, (Z @ B[s].T).transpose(1, 2), upper=False).transpose(1, 2)  # (N, m, m)
        Z = Z - BU @ U.T
        S = S - BU @ BU.transpose(1, 2)
        V = V - BU @ (Wt @ U).T
    return torch.tensor(picked, dtype=torch.long, device=dev), torch.stack(obj)


def design_poses(model, prior_mean: torch.Tensor, prior_cov: torch.Tensor, free: torch.Tensor, candidates: torch.Tensor,
                 count: int, noise, validation: torch.Tensor, seed: int = 0) -> tuple[torch.Tensor, torch.Tensor]:
    """Which ``count`` of the candidate commands to measure on a unit fitted with a prior (a fleet's).

    model: the unit's model (structure and tools; its parameters are left as they are); prior_mean (P,),
    free (P,) bool: the prior's entries in the model's full layout; prior_cov (k, k) over the free ones;
    candidates (N, n): reachable commands; noise: the instrument's :class:`NoiseModel`; validation (V, n):
    commands where the model will be used (the predicted error is averaged there). Each candidate is measured
    with every tool; its approach directions are not known before the visiting order is (drawn at random,
    seeded, as the order decorrelates them from position). Linearized at the prior mean.
    -> (picked (count,) long, predicted RMS model error in m before the first pick and after each (count + 1,)).
    """
    from ..core.measurements import Measurements
    from ..identify.layout import ParameterLayout
    from ..identify.problem import CalibrationProblem, Prior

    layout = ParameterLayout(model)
    saved = layout.get().detach().clone()
    T = int(model.tools.count)
    N = candidates.shape[0]
    dt, dev = prior_cov.dtype, candidates.device
    g = torch.Generator().manual_seed(int(seed))
    dirs = torch.where(torch.rand(candidates.shape, generator=g, dtype=dt) > 0.5, 1.0, -1.0).to(dev)

    def jacobians(q, s):
        R = q.shape[0]
        data = Measurements.from_tensors(q.repeat(T, 1), torch.arange(T, device=dev).repeat_interleave(R),
                                         torch.zeros(T * R, 3, dtype=dt, device=dev), direction=s.repeat(T, 1))
        prob = CalibrationProblem(model, data, noise, Prior())
        _, A, C = prob.linearize(prior_mean.to(dt), prob.v_zero())
        return A[..., free], C, prob.w_v

    try:
        A, C, w_v = jacobians(candidates, dirs)
        B = pose_jacobians(A, C, w_v, torch.arange(T * N, device=dev).reshape(T, N).T)
        A, _, _ = jacobians(validation, torch.ones_like(validation))
        W = error_weight(A.reshape(-1, A.shape[-1]) * float(noise.sigma_m))  # whitened -> metres
    finally:
        layout.set(saved)
    picked, obj = greedy_design(B, prior_cov.to(B), count, W, "A")
    return picked, obj.clamp(min=0.0).sqrt()


__all__ = ["design_poses", "error_weight", "greedy_design", "known_group_gain", "pose_jacobians", "posterior_covariance", "posterior_mean",
           "predicted_mse"]
