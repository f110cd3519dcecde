"""The damped Gauss-Newton step of many models at once, each row's joint errors eliminated in closed form.

Every batched solve (:func:`~torchcal.identify.batched.solve_batched`: sweeps,
noise studies, a fleet's units on a GPU) takes its Levenberg-Marquardt step
here: the batched form of :func:`torchcal.identify.lm._schur_step`, with the
normal matrix as one product per model (what a GPU is fast at) and every
per-row product elementwise or with a long inner dimension.
"""

from __future__ import annotations

import torch

from ..kinematics.transforms import small_matmul


def inv3_sym(G: torch.Tensor) -> torch.Tensor:
    """(..., 3, 3) inverse of symmetric positive definite 3x3 matrices by the adjugate, elementwise (a batched
    solve of 3x3 blocks is one tiny problem per block on a GPU)."""
    a, b, c = G[..., 0, 0], G[..., 0, 1], G[..., 0, 2]
    d, e, f = G[..., 1, 1], G[..., 1, 2], G[..., 2, 2]
    A, B, C = d * f - e * e, c * e - b * f, b * e - c * d
    D, E, F = a * f - c * c, b * c - a * e, a * d - b * b
    det = a * A + b * B + c * C
    return torch.stack([A, B, C, B, D, E, C, E, F], -1).reshape(G.shape) / det[..., None, None]


def schur_steps(f, A, C, w_v, V, lam, dx, mu, keep, again: bool = False):
    """Damped Gauss-Newton steps of m models at once (the batched :func:`~torchcal.identify.lm._schur_step`).

    f (m, R, d), A (m, R, d, P), C (m, R, d, n), w_v (m, R, n), V (m, R, n), lam (P,), dx (m, P), mu (m,),
    keep (m, P). -> db (m, P), dv (m, R, n), predicted linearized residual (m, R, d); with ``again``, also
    :class:`Resolve`: the same damped system solved for another residual (geodesic acceleration).

    Each row's joint errors are eliminated in Woodbury form. Their damped block is
    H_vv = C^T C + D, D = (1 + mu) w_v + mu diag(C^T C) diagonal, so the row's projector
    I - C H_vv^-1 C^T is M = (I + C D^-1 C^T)^-1, a d x d inverse (d = 3), and
    C H_vv^-1 = M C D^-1. The reduced normal matrix is sum_r A_r^T M_r A_r, one
    product of (m, P, R d) by (m, R d, P) after M A is formed row by row; every
    other product has an inner dimension of P or R d, or is elementwise.
    """
    m, R, d, P = A.shape
    kf = keep.to(A)
    Af = A.reshape(m, R * d, P)
    lam_m = lam * kf
    diag_bb = (A * A).sum((1, 2)) + lam_m
    mu4 = mu[:, None, None]
    D = (1.0 + mu4) * w_v + mu4 * (C * C).sum(-2)  # (m, R, n)
    CD = C / D[..., None, :]
    G = (CD[..., :, None, :] * C[..., None, :, :]).sum(-1) + torch.eye(d, dtype=A.dtype, device=A.device)
    Mr = inv3_sym(G) if d == 3 else torch.linalg.inv(G)  # (m, R, d, d)
    r = (Mr * (f - (CD * (w_v * V)[..., None, :]).sum(-1))[..., None, :]).sum(-1)  # f with the joint errors' response out
    MA = small_matmul(Mr, A)
    S = Af.transpose(1, 2) @ MA.reshape(m, R * d, P)
    S = 0.5 * (S + S.transpose(1, 2))
    # entries a model lacks: unit diagonal, zero right-hand side, so their step is zero
    S = S + torch.diag_embed(lam_m + mu[:, None] * diag_bb + (1.0 - kf))
    rhs = -((Af.transpose(1, 2) @ r.reshape(m, -1, 1))[..., 0] + lam_m * dx) * kf
    Ls, info = torch.linalg.cholesky_ex(S)
    bad = info != 0

    def solve(rhs):
        """S^-1 rhs (m, P), least squares for a model whose S has no Cholesky factor."""
        out = torch.cholesky_solve(rhs[..., None], Ls)[..., 0]
        if bool(bad.any()):
            out[bad] = torch.linalg.lstsq(S[bad], rhs[bad][..., None]).solution[..., 0]
        return out

    db = solve(rhs)
    Adb = (Af @ db[..., None]).reshape(m, R, d)
    y = ((Adb + f)[..., None] * C).sum(-2) + w_v * V  # g_v + C^T A db  (m, R, n)
    Dy = y / D
    u = (Mr * (C * Dy[..., None, :]).sum(-1)[..., None, :]).sum(-1)  # M C D^-1 y  (m, R, d)
    dv = (CD * u[..., None]).sum(-2) - Dy  # -(D^-1 y - D^-1 C^T M C D^-1 y)
    lin = f + Adb + (C * dv[..., None, :]).sum(-1)
    if not again:
        return db, dv, lin

    def resolve(r):
        rr = (Mr * r[..., None, :]).sum(-1)
        return solve(-(Af.transpose(1, 2) @ rr.reshape(m, -1, 1))[..., 0] * kf)

    return db, dv, lin, Resolve(resolve, diag_bb.sqrt())


class Resolve:
    """A step's damped system, kept to be solved again for another whitened residual r (m, R, d), with the
    priors' terms zero: ``resolve(r)`` -> the parameter part (m, P) (the joint errors eliminated as in the
    step). ``scale`` (m, P): Marquardt's scaling of the parameters (the square root of the system's diagonal
    before damping), to measure a step in. Valid until the solver's next step (it may share buffers)."""

    def __init__(self, solve, scale: torch.Tensor):
        self._solve, self.scale = solve, scale

    def __call__(self, r: torch.Tensor) -> torch.Tensor:
        return self._solve(r)


__all__ = ["Resolve", "inv3_sym", "schur_steps"]
