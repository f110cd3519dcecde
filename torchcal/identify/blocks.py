"""Parameter-only residual blocks added to the objective (Paper III (31)'s prior, Paper I's slope penalty, ...).

A block is any object with ``linearize(x, layout) -> (r (k,), J (k, P))``:
its whitened residual at the free vector x (P,) of ``layout`` and the
Jacobian. LM adds J^T J and J^T r to the normal equations, L-BFGS adds |r|^2
(so r must be computed from x with differentiable torch operations). A block
that is a quadratic in x may also offer ``normal_equations(x, layout) -> (H,
g, cost)`` and ``cost(x, layout)``, used instead (both must agree with each
other; the cost may differ from |r|^2 by a constant). Blocks
refer to parameters by entry name (:meth:`ParameterLayout.names`), so they
survive the gauge fixing that pins some entries.
"""

from __future__ import annotations

from typing import Protocol, Sequence, runtime_checkable

import torch

from .layout import ParameterLayout


@runtime_checkable
class ParamBlock(Protocol):
    def linearize(self, x: torch.Tensor, layout: ParameterLayout) -> tuple[torch.Tensor, torch.Tensor]:
        """x: (P,) free values -> whitened residual r (k,), Jacobian dr/dx (k, P)."""
        ...


class GaussianPrior:
    """A Gaussian prior with full covariance on named entries: r = L^-1 (x_names - mean), cov = L L^T.

    names: k entry names (as :meth:`ParameterLayout.names`); mean: (k,) SI;
    cov: (k, k) SI. Entries the layout does not have free (pinned by the
    gauge or held fixed) are dropped: the prior on the others is the marginal.

    Example:
        >>> import torch
        >>> b = GaussianPrior(["base.eps_x"], torch.zeros(1), torch.eye(1) * 1e-4)
        >>> b.mean.tolist()
        [0.0]
    """

    linear_residual = True
    """Its residual is linear in x: a Gauss-Newton model of its cost is the cost itself."""

    def __init__(self, names: Sequence[str], mean: torch.Tensor, cov: torch.Tensor):
        self.names = list(names)
        self.mean = torch.as_tensor(mean, dtype=torch.float64).reshape(-1)
        self.cov = torch.as_tensor(cov, dtype=torch.float64)
        k = len(self.names)
        if self.mean.numel() != k or self.cov.shape != (k, k):
            raise ValueError(f"GaussianPrior: {k} names, mean {tuple(self.mean.shape)}, cov {tuple(self.cov.shape)}")
        if len(set(self.names)) != k:
            raise ValueError("GaussianPrior: names repeat")
        self._cache: tuple | None = None

    @classmethod
    def over(cls, layout: ParameterLayout, mean: torch.Tensor, cov: torch.Tensor) -> "GaussianPrior":
        """A prior over every free entry of ``layout`` (its names, in order)."""
        return cls(layout.names(), mean, cov)

    def _bind(self, layout: ParameterLayout, like: torch.Tensor):
        names = layout.names()
        key = (id(layout), tuple(names))
        if self._cache is None or self._cache[0] != key:
            where = {n: i for i, n in enumerate(names)}
            unknown = [n for n in self.names if n not in where and not _is_parameter_entry(layout, n)]
            if unknown:
                raise ValueError(f"GaussianPrior: {unknown[:5]} are not parameter entries of the model")
            keep = [i for i, n in enumerate(self.names) if n in where]
            idx = torch.tensor([where[self.names[i]] for i in keep], dtype=torch.long)
            keep_t = torch.tensor(keep, dtype=torch.long)
            cov = self.cov[keep_t][:, keep_t]
            L = torch.linalg.cholesky(cov)
            Linv = torch.linalg.solve_triangular(L, torch.eye(len(keep), dtype=cov.dtype), upper=False)
            J = torch.zeros(len(keep), len(names), dtype=cov.dtype)
            J[:, idx] = Linv
            self._cache = (key, idx, self.mean[keep_t], Linv, J)
        _, idx, mean, Linv, J = self._cache
        return idx.to(like.device), mean.to(like), Linv.to(like), J.to(like)

    def linearize(self, x: torch.Tensor, layout: ParameterLayout) -> tuple[torch.Tensor, torch.Tensor]:
        idx, mean, Linv, J = self._bind(layout, x)
        return Linv @ (x[idx] - mean), J


def _is_parameter_entry(layout: ParameterLayout, name: str) -> bool:
    return any(name in g.entry_names for g in layout._all_groups)


def block_normal_equations(blocks, x: torch.Tensor, layout: ParameterLayout):
    """Sum over blocks of J^T J (P, P), J^T r (P,) and |r|^2 at x."""
    P = x.numel()
    H = torch.zeros(P, P, dtype=x.dtype, device=x.device)
    g = torch.zeros(P, dtype=x.dtype, device=x.device)
    cost = x.new_zeros(())
    for b in blocks:
        if hasattr(b, "normal_equations"):  # a quadratic block hands its H, g, cost over directly
            Hb, gb, cb = b.normal_equations(x, layout)
            H, g, cost = H + Hb, g + gb, cost + cb
            continue
        r, J = b.linearize(x, layout)
        H = H + J.T @ J
        g = g + J.T @ r
        cost = cost + (r * r).sum()
    return H, g, cost


def block_cost(blocks, x: torch.Tensor, layout: ParameterLayout) -> torch.Tensor:
    """Sum over blocks of |r(x)|^2 (differentiable in x where the blocks are)."""
    cost = x.new_zeros(())
    for b in blocks:
        if hasattr(b, "cost"):
            cost = cost + b.cost(x, layout)
            continue
        r, _ = b.linearize(x, layout)
        cost = cost + (r * r).sum()
    return cost
