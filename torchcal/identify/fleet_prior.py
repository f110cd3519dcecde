"""A fleet's parameter distribution as a Gaussian prior: covariance estimators for few units and many parameters.

A fitted fleet gives M units' parameter vectors Z (M, k), k ~ 270 for an
order-6 FANUC model, M ~ 100: the sample covariance is singular (rank M - 1)
and must be regularized before it can serve as a prior (issue #18). Every
estimator here works on the standardized parameters (each column divided by
its sample standard deviation: the entries mix radians and metres) and scales
back, so each keeps the sample variances on its diagonal:

- 'shrunk': the correlations shrunk towards zero with Schaefer and Strimmer's
  (2005) optimal weight (target D, the diagonal);
- 'ledoit-wolf': Ledoit and Wolf's (2004) weight on the scaled identity of the
  standardized data (equivalent target, its own weight formula);
- 'factor': low rank + diagonal, the r leading principal components of the
  correlation matrix plus each entry's remaining variance (PCA of the fleet);
- 'sample': the plain sample covariance (needs M > k, e.g. an oracle fleet);
- 'block': block-diagonal, one block per group of entries (by default the
  entries of one joint, the base, each tool: a unit's gearboxes are separate
  parts, so their errors vary independently from unit to unit), each block
  Ledoit-Wolf shrunk: k^2 / 2 covariances to estimate become sum_g k_g^2 / 2.

:func:`prior_from_parameters` turns an estimate into a
:class:`~torchcal.identify.blocks.GaussianPrior` on named entries; the
fleet's gauge pins (entries the fleet held at zero) can be carried as tight
entries so that a unit fitted without its own gauge fixing stays in the
fleet's gauge (where the prior's coordinates mean what they meant in the
fleet).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Sequence

import torch

METHODS = ("shrunk", "ledoit-wolf", "factor", "sample", "block")


def _standardize(Z: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """Z (M, k) -> (Y (M, k) centred and divided by the columns' sample std, sd (k,))."""
    M = Z.shape[0]
    Zc = Z - Z.mean(0)
    sd = Zc.pow(2).sum(0).div(M - 1).sqrt().clamp(min=1e-300)
    return Zc / sd, sd


def shrunk_correlation(Y: torch.Tensor) -> tuple[torch.Tensor, float]:
    """Schaefer-Strimmer shrinkage of the correlation matrix of the standardized rows Y (M, k) towards the
    identity -> (R (k, k), weight on the target in [0, 1])."""
    M, k = Y.shape
    W = Y[:, :, None] * Y[:, None, :]  # (M, k, k)
    Wm = W.mean(0)
    R = Wm * M / (M - 1)
    var_r = (W - Wm).pow(2).sum(0) * M / (M - 1) ** 3
    off = ~torch.eye(k, dtype=torch.bool, device=Y.device)
    lam = float((var_r[off].sum() / R[off].pow(2).sum().clamp(min=1e-300)).clamp(0.0, 1.0))
    Rs = (1.0 - lam) * R
    Rs.diagonal().fill_(1.0)
    return Rs, lam


def ledoit_wolf_correlation(Y: torch.Tensor) -> tuple[torch.Tensor, float]:
    """Ledoit-Wolf (2004) shrinkage of S = Y^T Y / M (Y (M, k) standardized rows) towards mu I, mu = tr(S) / k,
    rescaled to unit diagonal -> (R (k, k), weight on the target in [0, 1])."""
    M, k = Y.shape
    S = Y.T @ Y / M
    mu = S.diagonal().mean()
    eye = torch.eye(k, dtype=Y.dtype, device=Y.device)
    d2 = (S - mu * eye).pow(2).sum()
    # (1/M^2) sum_m |y_m y_m^T - S|_F^2 = (1/M^2) sum_m (|y_m|^4 - 2 y_m^T S y_m + |S|^2), without the (M, k, k) stack
    n2 = Y.pow(2).sum(1)
    b2 = (n2.pow(2) - 2.0 * ((Y @ S) * Y).sum(1)).sum() / M ** 2 + S.pow(2).sum() / M
    lam = float((torch.minimum(b2, d2) / d2.clamp(min=1e-300)).clamp(0.0, 1.0))
    C = lam * mu * eye + (1.0 - lam) * S
    d = C.diagonal().sqrt()
    return C / d[:, None] / d[None, :], lam


def factor_correlation(Y: torch.Tensor, rank: int | None = None, floor: float = 1e-3) -> tuple[torch.Tensor, int]:
    """Low rank + diagonal correlation of the standardized rows Y (M, k): the ``rank`` leading principal components
    of the sample correlation plus a diagonal that restores the unit variances (at least ``floor``).
    rank None: the components that carry 99 % of the variance (at most M - 1). -> (R (k, k), rank)."""
    M, k = Y.shape
    R = Y.T @ Y / (M - 1)
    ev, U = torch.linalg.eigh(R)
    ev, U = ev.flip(0).clamp(min=0.0), U.flip(1)
    if rank is None:
        frac = ev.cumsum(0) / ev.sum().clamp(min=1e-300)
        rank = int((frac < 0.99).sum()) + 1
    rank = max(0, min(int(rank), M - 1, k))
    L = U[:, :rank] * ev[:rank].sqrt()
    low = L @ L.T
    resid = (1.0 - low.diagonal()).clamp(min=float(floor))
    out = low + torch.diag(resid)
    d = out.diagonal().sqrt()
    return out / d[:, None] / d[None, :], rank


def entry_groups(names: Sequence[str]) -> list[torch.Tensor]:
    """Indices of the entries that share a module prefix (the name up to its first '.': 'joint3', 'base',
    'tool1'), in order of first appearance -> list of (k_g,) long tensors."""
    where: dict[str, list[int]] = {}
    for i, nm in enumerate(names):
        where.setdefault(nm.split(".", 1)[0], []).append(i)
    return [torch.tensor(v, dtype=torch.long) for v in where.values()]


def fleet_covariance(Z: torch.Tensor, method: str = "shrunk", rank: int | None = None,
                     groups: Sequence[torch.Tensor] | None = None) -> tuple[torch.Tensor, dict]:
    """Covariance (k, k) of the rows of Z (M, k) (the units' parameters) by ``method`` (:data:`METHODS`, module
    docstring); rank: components kept by 'factor'; groups: the blocks of 'block' (index tensors that partition
    range(k); None: one block). -> (cov, info: {'method', 'weight' or 'rank' or 'weights'})."""
    if method not in METHODS:
        raise ValueError(f"fleet_covariance: method must be one of {METHODS}, got {method!r}")
    M, k = Z.shape
    if M < 3:
        raise ValueError(f"fleet_covariance: {M} units; at least 3 are needed for a spread")
    Y, sd = _standardize(Z)
    info: dict = {"method": method}
    if method == "shrunk":
        R, info["weight"] = shrunk_correlation(Y)
    elif method == "ledoit-wolf":
        R, info["weight"] = ledoit_wolf_correlation(Y)
    elif method == "factor":
        R, info["rank"] = factor_correlation(Y, rank)
    elif method == "block":
        groups = [torch.arange(k)] if groups is None else [torch.as_tensor(g_, dtype=torch.long) for g_ in groups]
        cover = torch.cat(groups).sort().values if groups else torch.empty(0, dtype=torch.long)
        if not torch.equal(cover, torch.arange(k)):
            raise ValueError("fleet_covariance: the groups must partition the k entries")
        R = torch.zeros(k, k, dtype=Z.dtype, device=Z.device)
        info["weights"] = []
        for g_ in groups:
            g_ = g_.to(Z.device)
            Rg, w = ledoit_wolf_correlation(Y[:, g_])
            R[g_[:, None], g_[None, :]] = Rg
            info["weights"].append(w)
    else:
        if M <= k:
            raise ValueError(f"fleet_covariance: the sample covariance of {M} units in {k} parameters is singular; "
                             f"use 'shrunk', 'ledoit-wolf' or 'factor'")
        R = Y.T @ Y / (M - 1)
    return R * sd[:, None] * sd[None, :], info


@dataclass
class FleetPriorParts:
    """A fleet prior's pieces: ``names`` (k,) of the prior's entries, ``mean`` (k,), ``cov`` (k, k) SI,
    ``free`` (P,) bool: the entries of the full layout the prior covers, ``info`` (the estimator's)."""

    names: list
    mean: torch.Tensor
    cov: torch.Tensor
    free: torch.Tensor
    info: dict


def prior_from_parameters(X: torch.Tensor, keep: torch.Tensor, names: Sequence[str], base_sigma: torch.Tensor,
                          method: str = "shrunk", rank: int | None = None, inflate: float = 1.0, floor: float = 1e-3,
                          pin_gauge: bool = False, pin: float = 1e-6) -> FleetPriorParts:
    """Mean and covariance of the units' parameters X (M, P) (full layout, SI) as a prior.

    keep: (M, P) bool, the entries each unit had free (the fleet's gauge pins are False); names: (P,) entry names;
    base_sigma: (P,) the default prior's sigmas (every variance is at least (floor x base_sigma)^2, so no entry is
    pinned by a fleet that happens to agree on it); method, rank: :func:`fleet_covariance`; inflate: factor on the
    standard deviations. pin_gauge: also cover the entries some unit had pinned, at their fleet mean (zero) with
    sigma ``pin`` x base_sigma, uncorrelated: a unit fitted with ``gauge=False`` is then held in the fleet's gauge.
    -> :class:`FleetPriorParts` (entries in layout order).
    """
    P = X.shape[1]
    free = keep.all(0)
    Z = X[:, free]
    fnames = [nm for nm, f in zip(names, free.tolist()) if f]
    cov, info = fleet_covariance(Z, method, rank, entry_groups(fnames) if method == "block" else None)
    cov = cov * float(inflate) ** 2
    base = base_sigma.to(X)
    grow = ((base[free] * float(floor)).pow(2) - cov.diagonal()).clamp(min=0.0)
    cov = cov + torch.diag(grow)
    mean = Z.mean(0)
    cover = free.clone()
    if pin_gauge and bool((~free).any()):
        k, kp = int(free.sum()), int((~free).sum())
        full = torch.zeros(k + kp, k + kp, dtype=X.dtype, device=X.device)
        full[:k, :k] = cov
        full[k:, k:] = torch.diag((base[~free] * float(pin)).pow(2))
        order = torch.cat([free.nonzero()[:, 0], (~free).nonzero()[:, 0]])
        inv = torch.empty_like(order)
        inv[order] = torch.arange(P, device=order.device)
        mean = torch.cat([mean, X[:, ~free].mean(0)])[inv]
        cov = full[inv][:, inv]
        cover = torch.ones(P, dtype=torch.bool, device=X.device)
    kept = [nm for nm, f in zip(names, cover.tolist()) if f]
    return FleetPriorParts(kept, mean, cov, cover, info)


def fleet_prior(fit, exclude: Sequence[int] = (), inflate: float = 1.0, floor: float = 1e-3,
                method: str = "shrunk", rank: int | None = None, pin_gauge: bool = False):
    """A Gaussian prior for a new unit of the type: the fleet's mean and covariance of every parameter.

    fit: a :class:`~torchcal.identify.fleet.FleetFit` (its ``batch`` and ``layout``). The covariance is the units' sample covariance regularized by ``method``
    (:func:`torchcal.identify.fleet_prior.fleet_covariance`: 'shrunk', the
    default, shrinks the correlations towards zero (Schaefer-Strimmer);
    'ledoit-wolf'; 'factor', low rank (``rank`` components) + diagonal;
    'sample' where there are more units than parameters; 'block', one
    Ledoit-Wolf block per joint, the base and each tool, none across): it carries how the
    parameters vary *together* from unit to unit (a strain-wave error of
    random phase moves a joint's Chebyshev coefficients along a few
    directions only), which is what lets a unit measured with a few poses
    borrow the fleet's knowledge. exclude: units left out (the flagged
    outliers); inflate: factor on the standard deviations; floor: each
    variance is at least (floor x the default :class:`Prior`'s sigma)^2, so
    no entry is pinned by a fleet that happens to agree on it. Entries the
    fleet's gauge pinned are left to the unit's own gauge, or, with
    ``pin_gauge``, held at the fleet's value (zero) by a tight prior (1e-6 x
    the default sigma), so that a unit fitted with ``gauge=False`` stays in
    the fleet's gauge, the coordinates the covariance was estimated in.
    -> (:class:`~torchcal.identify.blocks.GaussianPrior` to pass as
    ``blocks=[...]`` to :func:`torchcal.fit`, mean (P,) in the full layout: a
    start for the unit's model).
    """
    from .blocks import GaussianPrior
    from .problem import Prior

    X, keep, names = fit.batch.x, fit.batch.keep, fit.batch.names
    skip = set(int(e) for e in exclude)
    use = torch.tensor([m not in skip for m in range(X.shape[0])], device=X.device)
    if int(use.sum()) < 3:
        raise ValueError(f"fleet_prior: {int(use.sum())} units left; at least 3 are needed for a spread")
    base = Prior().sigma(fit.layout).to(X)
    parts = prior_from_parameters(X[use], keep[use], names, base, method, rank, inflate, floor, pin_gauge)
    mean = torch.zeros(X.shape[1], dtype=X.dtype, device=X.device)
    mean[parts.free] = parts.mean
    return GaussianPrior(parts.names, parts.mean.cpu(), parts.cov.cpu()), mean


TENSION_WARN = 2.0
"""d^2 / E above which (and beyond E + 4 sd, for data that see few directions) a unit fitted under a fleet prior
is said to lie farther from the fleet than its spread explains (:func:`prior_tension`). Measured on a helper's
24-FANUC fleet with 30 poses: a healthy new unit 0.34, one with a J3 gearbox whose backlash is 8x the fleet's 4.1
(its model 0.17 mm off, 8x its 250-pose fit)."""


@dataclass
class PriorTension:
    """How far a unit fitted under a Gaussian prior lies from the prior's mean, against what its data let a unit
    drawn from the prior move (:func:`prior_tension`): ``d2`` the Mahalanobis distance squared of the fitted
    entries, ``expected`` its expectation and ``sd`` its standard deviation for such a unit, ``groups`` each
    module's share of ``d2`` ('joint3', 'base', 'tool1'; largest first; a correlated prior's cross terms can make
    a share negative)."""

    d2: float
    expected: float
    sd: float
    groups: list

    @property
    def ratio(self) -> float:
        """d2 / expected: about 1 (or below: the fleet's spread is a bound, not a fit) for a unit like the
        fleet's; far above it for a unit the prior holds back from its own data."""
        return self.d2 / self.expected if self.expected > 0 else float("nan")

    def summary(self) -> dict:
        """JSON-ready."""
        return {"d2": self.d2, "expected": self.expected, "sd": self.sd, "ratio": self.ratio,
                "groups": [[g, share] for g, share in self.groups]}


def prior_tension(block, problem, x: torch.Tensor, v: torch.Tensor) -> PriorTension:
    """The fitted unit's distance from the fleet prior ``block`` (a :class:`~torchcal.identify.blocks.
    GaussianPrior`, mean mu, covariance S over k entries), judged against its data.

    d^2 = (x - mu)^T S^-1 (x - mu) on the block's entries. For a unit drawn from N(mu, S) and fitted (linear
    Gaussian model) on data of information H (``problem``'s rows at (x, v), joint errors eliminated:
    :func:`~torchcal.identify.online.marginal_information`), x - mu has covariance S - S_post, S_post the block
    of (H + the problem's prior precision + S^-1)^-1, so E d^2 = k - tr(S^-1 S_post) (the number of directions
    the data determine) and Var d^2 = 2 tr(M^2), M = I - S^-1 S_post. A unit whose data pull it far from the
    fleet (a damaged gearbox) shows d^2 several times E while its residual stays small: the prior hides what
    the few poses cannot show.

    problem: the :class:`~torchcal.identify.problem.CalibrationProblem` of the fit (its layout, rows and noise);
    x: (P,) the fitted layout values; v: (R, n) the fitted joint errors.
    """
    from .online import marginal_information

    f, A, C = problem.linearize(x, v)
    H, _ = marginal_information(f, A, C, problem.w_v, v)
    idx, mean, Linv, _ = block._bind(problem.layout, x)
    idx = idx.to(H.device)
    Lam = (Linv.T @ Linv).to(H)  # S^-1 on the entries the layout has free
    N = H + torch.diag(problem.prior_precision.to(H))
    N[idx[:, None], idx[None, :]] += Lam
    post = torch.linalg.inv(N)[idx[:, None], idx[None, :]]
    M = torch.eye(idx.numel(), dtype=H.dtype, device=H.device) - Lam @ post
    d = x[idx].to(H) - mean.to(H)
    w = Lam @ d
    names = [problem.layout.names()[i] for i in idx.tolist()]
    share: dict[str, float] = {}
    for nm, c in zip(names, (d * w).tolist()):
        key = nm.split(".", 1)[0]
        share[key] = share.get(key, 0.0) + c
    return PriorTension(float(d @ w), float(torch.trace(M)), float((2.0 * torch.trace(M @ M)).clamp(min=0).sqrt()),
                        sorted(share.items(), key=lambda kv: -kv[1]))


__all__ = ["FleetPriorParts", "METHODS", "PriorTension", "TENSION_WARN", "entry_groups", "factor_correlation",
           "fleet_covariance", "fleet_prior", "ledoit_wolf_correlation", "prior_from_parameters", "prior_tension",
           "shrunk_correlation"]
