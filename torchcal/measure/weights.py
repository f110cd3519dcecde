"""Per-row whitening of instrument residuals (theseus' CostWeight): f_r = S_r r_r, S_r^T S_r = Sigma_r^-1.

A weight maps raw residuals (R, d, ...) to whitened ones and back; the
trailing dimensions let the same call whiten residuals (R, d) and Jacobians
(R, d, P) alike.
"""

from __future__ import annotations

import torch


class IsotropicWeight:
    """Sigma_r = sigma^2 I for every row: S = I / sigma. sigma: standard deviation per axis (SI)."""

    def __init__(self, sigma: float):
        if not float(sigma) > 0:
            raise ValueError(f"IsotropicWeight: sigma must be positive, got {sigma}")
        self.sigma = float(sigma)

    def whiten(self, t: torch.Tensor) -> torch.Tensor:
        """(R, d, ...) raw -> whitened."""
        return t / self.sigma

    def unwhiten(self, t: torch.Tensor) -> torch.Tensor:
        """(R, d, ...) whitened -> raw."""
        return t * self.sigma

    def sqrt_info(self, rows: int, dim: int, like: torch.Tensor) -> torch.Tensor:
        """(R, d, d) whitening matrices S_r."""
        eye = torch.eye(dim, dtype=like.dtype, device=like.device) / self.sigma
        return eye.expand(rows, dim, dim)

    def subset(self, index) -> "IsotropicWeight":
        return self


class CovarianceWeight:
    """A full (R, d, d) covariance per row (e.g. a tracker's distance-dependent one): S_r = L_r^-1, Sigma_r = L_r L_r^T."""

    def __init__(self, cov: torch.Tensor):
        cov = torch.as_tensor(cov)
        if cov.ndim != 3 or cov.shape[1] != cov.shape[2]:
            raise ValueError(f"CovarianceWeight: covariance must have shape (R, d, d), got {tuple(cov.shape)}")
        L, info = torch.linalg.cholesky_ex(cov)
        if bool((info != 0).any()):
            r = int((info != 0).nonzero()[0])
            raise ValueError(f"CovarianceWeight: covariance of row {r} is not positive definite: {cov[r].tolist()}")
        self.cov = cov
        self.L = L
        self.S = torch.linalg.solve_triangular(L, torch.eye(cov.shape[1], dtype=cov.dtype, device=cov.device).expand_as(cov),
                                               upper=False)

    def whiten(self, t: torch.Tensor) -> torch.Tensor:
        S = self.S.to(t)
        return (S @ t.reshape(t.shape[0], t.shape[1], -1)).reshape(t.shape)

    def unwhiten(self, t: torch.Tensor) -> torch.Tensor:
        L = self.L.to(t)
        return (L @ t.reshape(t.shape[0], t.shape[1], -1)).reshape(t.shape)

    def sqrt_info(self, rows: int, dim: int, like: torch.Tensor) -> torch.Tensor:
        if self.S.shape[0] != rows or self.S.shape[1] != dim:
            raise ValueError(f"CovarianceWeight: {tuple(self.S.shape)} whitening for {rows} rows of dimension {dim}")
        return self.S.to(like)

    @classmethod
    def _of(cls, cov: torch.Tensor, L: torch.Tensor, S: torch.Tensor) -> "CovarianceWeight":
        out = cls.__new__(cls)
        out.cov, out.L, out.S = cov, L, S
        return out

    def subset(self, index) -> "CovarianceWeight":
        # the factors are per row: taken with the rows, not factored again (a batch's set-up cost)
        return CovarianceWeight._of(self.cov[index], self.L[index], self.S[index])

    def to(self, device) -> "CovarianceWeight":
        """On ``device`` (itself where it is there already), factors moved with it."""
        if self.cov.device == torch.device(device):
            return self
        return CovarianceWeight._of(self.cov.to(device), self.L.to(device), self.S.to(device))
