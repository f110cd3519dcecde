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

    Greedy Gram-Schmidt (twice, for stability) on unit-normalized columns;
    a column is dependent when less than ``rtol`` of its norm is new.
    -> (P,) bool, True for dependent columns.
    """
    A = A / A.norm(dim=0).clamp(min=1e-300)
    P = A.shape[1]
    order = torch.arange(P) if order is None else order
    dependent = torch.zeros(P, dtype=torch.bool)
    Q = torch.zeros(A.shape[0], 0, dtype=A.dtype, device=A.device)
    for j in order.tolist():
        a = A[:, j]
        if float(a.norm()) == 0.0:
            dependent[j] = True
            continue
        r = a - Q @ (Q.T @ a)
        r = r - Q @ (Q.T @ r)
        nr = float(r.norm())
        if nr < rtol:
            dependent[j] = True
        else:
            Q = torch.cat([Q, (r / nr)[:, None]], 1)
    return dependent


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
