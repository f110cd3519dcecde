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

from ..core.threads import threads_for_work


def _project_out(r: torch.Tensor, Q: torch.Tensor) -> torch.Tensor:
    """r (M, k, n) less its components along the orthonormal (or zero) rows of Q (M, K, n), twice (CGS2)."""
    if Q.shape[1] == 0:
        return r
    for _ in range(2):
        r = r - (r @ Q.transpose(1, 2)) @ Q
    return r


def _greedy(Bt: torch.Tensor, keep: torch.Tensor, rtol: float, candidates: torch.Tensor | None = None) -> torch.Tensor:
    """The greedy test: Bt (P, n) unit columns as rows, in priority order; keep (M, P) bool, M column subsets.

    Column j of subset m is dependent when less than ``rtol`` of it is new
    against the kept, independent columns before it (classical Gram-Schmidt
    twice). A plain Householder QR cannot stand in: a dependent (or masked
    out, zero) column still takes a reflector that uses up a dimension, and
    later columns lose their component along it (on 126 x 99 it pinned 7
    independent columns).

    candidates: (P,) bool, the columns that can be dependent at all (None:
    every column). Subsets of a set whose own dependent columns are known
    pass those: dropping columns only shrinks the span before any column,
    so a column independent in the full set is independent in every subset.
    The runs of columns between candidates then go through one batched QR
    each (compacted per subset, so that no zero column takes a reflector
    before a real one), each candidate through Gram-Schmidt against
    everything kept before it. -> (M, P) bool.
    """
    # many small kernels (a column or a run of columns against the kept directions): sized by their work they
    # run on one thread; two threads made the 19 calls of an order search 1.7 s quiet but 6.3 s with one
    # CPU-bound neighbour, one thread 2.1 s either way
    with threads_for_work(8.0 * keep.shape[0] * Bt.shape[0] * Bt.shape[1]):
        return _greedy_body(Bt, keep, rtol, candidates)


def _greedy_body(Bt: torch.Tensor, keep: torch.Tensor, rtol: float, candidates: torch.Tensor | None) -> torch.Tensor:
    P, n = Bt.shape
    M = keep.shape[0]
    dependent = torch.zeros(M, P, dtype=torch.bool, device=Bt.device)
    Q = Bt.new_zeros(M, P, n)  # filled up to K rows: the directions kept so far (zero rows where none)
    K = 0
    marks = (list(range(P)) if candidates is None else candidates.nonzero()[:, 0].tolist()) + [P]
    s = 0
    for c in marks:
        if c > s:  # columns s..c-1: independent wherever kept
            k = keep[:, s:c]
            if bool(k.any()):
                W = _project_out(Bt[s:c].expand(M, c - s, n), Q[:, :K])
                perm = torch.argsort((~k).to(torch.int8), dim=1, stable=True)  # kept first, in order
                count = k.sum(1)
                W = torch.gather(W, 1, perm[..., None].expand(M, c - s, n))
                real = torch.arange(c - s, device=Bt.device)[None, :] < count[:, None]  # (M, L)
                W = W * real[..., None]
                Qr = torch.linalg.qr(W.transpose(1, 2), mode="reduced")[0].transpose(1, 2)  # (M, L, n)
                Q[:, K:K + c - s] = Qr * real[..., None]
                K += c - s
        if c < P:
            r = _project_out(Bt[c].expand(M, 1, n), Q[:, :K])[:, 0]
            nr = r.norm(dim=1)
            dep = nr < rtol
            dependent[:, c] = keep[:, c] & dep
            Q[:, K] = torch.where((keep[:, c] & ~dep)[:, None], r / nr.clamp(min=1e-300)[:, None], 0.0)
            K += 1
        s = c + 1
    return dependent


def _greedy_full(Bt: torch.Tensor, rtol: float, block: int = 16) -> torch.Tensor:
    """The greedy test of :func:`_greedy` for the full set of columns alone, in blocks. -> (P,) bool.

    A block of the next columns is projected off the kept directions and factored by one QR: while its
    columns are independent, |R_jj| is exactly the greedy test's new norm of column j against everything
    kept before it. At the first dependent column the block's directions before it are kept, the column is
    pinned and the next block starts after it. A dependent column's own reflector is never kept, so it
    cannot use up a dimension that a later column needs (the trap of a plain QR of all the columns). One QR
    per block and per pinned column instead of a dozen small products per column: on a FANUC's 285 columns
    (18 pinned) 10 ms against the per-column loop's 48-65 ms (blocks of 32: 12 ms, of 64: 18 ms).
    """
    P, n = Bt.shape
    dependent = torch.zeros(P, dtype=torch.bool)
    Q = Bt.new_zeros(P, n)  # the kept directions, first K rows
    K, s = 0, 0
    with threads_for_work(8.0 * P * n * block):
        while s < P:
            c = min(s + block, P)
            W = _project_out(Bt[None, s:c], Q[None, :K])[0]  # (L, n)
            q, r = torch.linalg.qr(W.T, mode="reduced")  # (n, L), (L, L)
            diag = torch.diagonal(r)  # fewer entries than the block's columns where the rows run out (n < L)
            small = (diag.abs() < rtol).nonzero()
            j = int(small[0, 0]) if small.numel() else min(c - s, diag.numel())
            Q[K:K + j] = q[:, :j].T
            K += j
            if j < c - s:
                dependent[s + j] = True
                s += j + 1
            else:
                s = c
    return dependent


def _unit_columns_in_order(A: torch.Tensor, order: torch.Tensor):
    """A's columns in ``order``, unit-normalized, as rows (P, n), reduced to at most P coordinates by one QR
    (A = Q R with Q orthonormal keeps every inner product, so the greedy test gives the same answer on R)."""
    P = A.shape[1]
    norms = A.norm(dim=0)
    An = (A / norms.clamp(min=1e-300))[:, order.to(A.device)]
    if An.shape[0] > P:
        An = torch.linalg.qr(An, mode="r")[1]
    return An.T.contiguous(), norms == 0


def dependent_columns(A: torch.Tensor, order: torch.Tensor | None = None, rtol: float = 1e-7) -> torch.Tensor:
    """Columns of A (rows, P) that lie in the span of columns earlier in ``order``.

    Greedy Gram-Schmidt on unit-normalized columns taken in ``order``: a
    column is dependent when less than ``rtol`` of its norm is new against
    the independent columns before it. -> (P,) bool, True for dependent columns.
    """
    P = A.shape[1]
    order = torch.arange(P) if order is None else order.cpu()
    dependent = torch.zeros(P, dtype=torch.bool)
    if P == 0:
        return dependent
    _, order, zero, full = gauge_basis(A, order, rtol)
    dependent[order] = full.cpu()
    return dependent | zero.cpu()


def gauge_basis(A: torch.Tensor, order: torch.Tensor | None = None, rtol: float = 1e-7):
    """What :func:`dependent_columns_masked` needs of A (rows, P), computed once: its unit-normalized
    columns in ``order`` reduced to P coordinates, and which of them the full set pins (only those can be
    pinned in a subset). -> (Bt, order, zero columns (P,) bool, full-set dependent columns in order (P,) bool)."""
    P = A.shape[1]
    order = torch.arange(P) if order is None else order.cpu()
    Bt, zero = _unit_columns_in_order(A, order)
    full = _greedy_full(Bt, rtol).to(Bt.device)
    return Bt, order, zero, full


def dependent_columns_masked(basis, keep: torch.Tensor, rtol: float = 1e-7, chunk: int = 64) -> torch.Tensor:
    """:func:`dependent_columns` for many column subsets of one matrix at once.

    basis: :func:`gauge_basis` of the matrix (same ``rtol``); keep: (M, P)
    bool, the columns of each subset. -> (M, P) bool: the kept columns that
    lie in the span of the kept columns earlier in the order. A column the
    full matrix pins may be free in a subset (its partners are missing),
    never the other way.
    """
    Bt, order, zero, full = basis
    M, P = keep.shape
    kp = keep[:, order.to(keep.device)].to(Bt.device)
    out = torch.zeros(M, P, dtype=torch.bool)
    whole = kp.all(1).cpu()  # the full set's own answer is already known (a fleet: every unit carries every term)
    out[whole.nonzero()[:, 0][:, None], order] = full.cpu()
    part = (~whole).nonzero()[:, 0]
    for c0 in range(0, part.numel(), chunk):
        rows = part[c0:c0 + chunk]
        out[rows[:, None], order] = _greedy(Bt, kp[rows.to(kp.device)], rtol, full).cpu()
    return (out.to(keep.device) & keep) | (keep & zero[None, :].to(keep.device))


_ERROR_ROLES = ("joint", "backlash", "axis", "fine", "compliance")
"""Roles whose all-zero value is the nominal machine (the gauge is judged there)."""

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
    frames and tools with every error term (joint, backlash, axis, fine,
    compliance) at zero, where the families above are exactly redundant: at a
    warm start, joint 1's fitted eps_x / eps_y tilt its constant eps_z off the
    base's, the pair is then only nearly redundant (relative 1e-4), and left
    free it makes the solver crawl.
    """
    layout = problem.layout
    x = layout.get().to(problem.model.device)
    errors = torch.tensor([r in _ERROR_ROLES for r in layout.roles()], dtype=torch.bool, device=x.device)
    try:
        _, A, _ = problem.linearize(torch.where(errors, torch.zeros_like(x), x), problem.v_zero())
    finally:
        layout.set(x)  # linearize wrote the judging point into the model
    Af = A.reshape(-1, A.shape[-1])
    drop = dependent_columns(Af, gauge_priority(layout.roles()), rtol).to(x.device)
    names = [n for n, d in zip(layout.names(), drop.tolist()) if d]
    problem.set_layout(layout.without(drop))
    return names
