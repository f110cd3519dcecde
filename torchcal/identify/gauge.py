"""Fixing the gauge: pin the parameters that the data cannot tell apart from others.

Constant terms of neighbouring error transforms are redundant (Paper II (18)):
a rotation about, or a shift along, joint i's own axis commutes with the joint
and can move into E_(i+1); the base correction (26) duplicates E_1's constants;
the last joint's axial terms duplicate the tool vectors. Left free, these
families make the normal matrix singular and the solver crawl along curved
valleys. We walk the columns of the whitened Jacobian in a priority order and
pin every column that is (numerically) a combination of the ones kept before
it, so that the remaining problem is full rank. Which member of a family is
kept is a convention: never read meaning into single parameters.
"""

from __future__ import annotations

import torch


def dependent_columns(A: torch.Tensor, order: torch.Tensor | None = None, rtol: float = 1e-7) -> torch.Tensor:
    """Columns of A (rows, P) that lie in the span of columns earlier in ``order``.

    On unit-normalized columns taken in ``order``, the diagonal of the R factor
    of a QR decomposition (no pivoting) is the norm of what each column adds
    to the span of the columns before it: a column is dependent when that is
    below ``rtol`` (the greedy Gram-Schmidt test, done by one Householder QR
    instead of P projections). -> (P,) bool, True for dependent columns.
    """
    P = A.shape[1]
    order = torch.arange(P) if order is None else order.cpu()
    norms = A.norm(dim=0)
    dependent = torch.zeros(P, dtype=torch.bool)
    dependent[(norms == 0).cpu()] = True
    if P == 0:
        return dependent
    An = (A / norms.clamp(min=1e-300))[:, order.to(A.device)]
    if An.shape[0] < P:  # more columns than rows: pad with zero rows (R stays P x P)
        An = torch.cat([An, An.new_zeros(P - An.shape[0], P)])
    r = torch.linalg.qr(An, mode="r")[1].diagonal().abs().cpu()
    dependent[order] |= r < rtol
    return dependent


def gauge_basis(A: torch.Tensor, order: torch.Tensor | None = None):
    """What :func:`dependent_columns_masked` needs of A (rows, P), computed once: its unit-normalized columns
    in ``order`` reduced to their R factor (P, P) (A = Q R with Q orthonormal, so any subset of A's columns
    has the same dependences as that subset of R's: the per-subset QRs then run on P rows, not rows).
    -> (R, order, zero columns (P,) bool)."""
    P = A.shape[1]
    order = torch.arange(P) if order is None else order.cpu()
    norms = A.norm(dim=0)
    An = (A / norms.clamp(min=1e-300))[:, order.to(A.device)]
    if An.shape[0] < P:
        An = torch.cat([An, An.new_zeros(P - An.shape[0], P)])
    return torch.linalg.qr(An, mode="r")[1], order, norms == 0


def dependent_columns_masked(basis, keep: torch.Tensor, rtol: float = 1e-7, chunk: int = 16) -> torch.Tensor:
    """:func:`dependent_columns` for many column subsets of one matrix at once.

    basis: :func:`gauge_basis` of the matrix; keep: (M, P) bool, the columns of
    each subset. -> (M, P) bool: the kept columns that lie in the span of the
    kept columns earlier in the order (one batched QR per ``chunk`` subsets). A
    column the full matrix pins may be free in a subset (its partners are
    missing), never the other way.
    """
    Rb, order, zero = basis
    M, P = keep.shape
    kp = keep[:, order.to(keep.device)].to(Rb)
    out = torch.zeros(M, P, dtype=torch.bool)
    for c0 in range(0, M, chunk):
        r = torch.linalg.qr(Rb[None] * kp[c0:c0 + chunk, None, :], mode="r")[1].diagonal(dim1=-2, dim2=-1).abs().cpu()
        out[c0:c0 + chunk, order] = r < rtol
    return (out.to(keep.device) & keep) | (keep & zero[None, :].to(keep.device))


_ROLE_RANK = {"frame": 0, "tool": 1, "compliance": 3}


def gauge_priority(roles: list[str]) -> torch.Tensor:
    """Order in which columns claim identifiability, by declared role: frame, tools, joints root to tip
    (low order first; and any other role), compliance.

    The gravity compliance comes last: where its functions duplicate a joint's
    own Chebyshev series exactly (not the case for the default functions), the
    geometric term is kept.
    """
    return torch.tensor(sorted(range(len(roles)), key=lambda i: (_ROLE_RANK.get(roles[i], 2), i)), dtype=torch.long)


def fix_gauge(problem, rtol: float = 1e-7):
    """Replace ``problem.layout`` by one with the redundant parameters pinned; returns their names.

    The redundancy is judged on the measurement Jacobian at the current
    parameters with the joint errors at zero.
    """
    layout = problem.layout
    x = layout.get().to(problem.model.device)
    _, A, _ = problem.linearize(x, problem.v_zero())
    Af = A.reshape(-1, A.shape[-1])
    drop = dependent_columns(Af, gauge_priority(layout.roles()), rtol).to(x.device)
    names = [n for n, d in zip(layout.names(), drop.tolist()) if d]
    problem.set_layout(layout.without(drop))
    return names
