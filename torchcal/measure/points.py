"""Point targets: a tracker measuring tool points in its own frame (Paper II (25)), d = 3."""

from __future__ import annotations

import torch

from ..core.exceptions import InputError
from ..core.measurements import Measurements
from .base import Instrument, closed_form_declined
from .weights import CovarianceWeight, IsotropicWeight


class PointTargets(Instrument):
    """Tool positions (R, 3) in the measurement frame, metres.

    xyz: (R, 3) observed points; sigma: isotropic standard deviation per axis
    (m), or cov: (R, 3, 3) per-row covariance (m^2), e.g. a tracker's
    distance-dependent one. The model must provide ``points(q, tool, direction, v)``
    -> (B, 3); with ``point_jacobians`` the Jacobians are closed form.

    Example:
        >>> import torch
        >>> pt = PointTargets(torch.zeros(2, 3, dtype=torch.float64), sigma=5e-6)
        >>> pt.whiten(torch.full((2, 3), 5e-6, dtype=torch.float64))[0].tolist()
        [1.0, 1.0, 1.0]
    """

    dim = 3

    def __init__(self, xyz: torch.Tensor, sigma: float | None = None, cov: torch.Tensor | None = None):
        xyz = torch.as_tensor(xyz)
        if xyz.ndim != 2 or xyz.shape[1] != 3:
            raise ValueError(f"PointTargets: points must have shape (R, 3), got {tuple(xyz.shape)}")
        if (sigma is None) == (cov is None):
            raise ValueError("PointTargets: give exactly one of sigma (isotropic, m) or cov ((R, 3, 3), m^2)")
        if torch.isnan(xyz).any():
            r = int(torch.isnan(xyz).any(1).nonzero()[0])
            raise ValueError(f"PointTargets: row {r} has no measured x, y, z")
        self.observed = xyz
        if cov is not None:
            cov = torch.as_tensor(cov).to(xyz)
            if cov.shape != (xyz.shape[0], 3, 3):
                raise ValueError(f"PointTargets: covariance must have shape ({xyz.shape[0]}, 3, 3), got {tuple(cov.shape)}")
            self.weight = CovarianceWeight(cov)
        else:
            self.weight = IsotropicWeight(sigma)

    @classmethod
    def from_measurements(cls, data: Measurements, sigma: float | None = None, cov=None) -> "PointTargets":
        """The tracker points of ``data`` (its ``xyz``), raising with the file name when a row has none."""
        if torch.isnan(data.xyz).any():
            raise InputError(f"{data.source or 'the measurements'}: identification data has rows without a measured "
                             "x, y, z")
        return cls(data.xyz, sigma, cov)

    def predict(self, model, q, tool, direction=None, v=None) -> torch.Tensor:
        return model.points(q, tool, direction, v)

    def predict_jacobians(self, model, q, tool, direction=None, v=None):
        pj = getattr(model, "point_jacobians", None)
        if pj is None or closed_form_declined(model):
            return None
        return pj(q, tool, direction, v)

    def subset(self, index) -> "PointTargets":
        out = PointTargets.__new__(PointTargets)
        out.observed = self.observed[index]
        out.weight = self.weight.subset(index)
        return out

    @classmethod
    def cat(cls, instruments: list) -> "PointTargets":
        """The rows of several PointTargets, in order, as one (their observations and per-row weights).

        Isotropic weights with one sigma stay isotropic; any other mix becomes
        a per-row (R, 3, 3) covariance, so no row changes its weight.

        Example:
            >>> import torch
            >>> a = PointTargets(torch.zeros(2, 3, dtype=torch.float64), sigma=5e-6)
            >>> b = PointTargets(torch.ones(1, 3, dtype=torch.float64), sigma=1e-5)
            >>> c = PointTargets.cat([a, b])
            >>> len(c), [round(w, 9) for w in c.whiten(torch.full((3, 3), 1e-5, dtype=torch.float64))[:, 0].tolist()]
            (3, [2.0, 2.0, 1.0])
        """
        instruments = list(instruments)
        if not instruments or not all(isinstance(i, PointTargets) for i in instruments):
            raise ValueError(f"PointTargets.cat: expected a non-empty list of PointTargets, got "
                             f"{[type(i).__name__ for i in instruments]}")
        xyz = torch.cat([i.observed for i in instruments])
        sigmas = {getattr(i.weight, "sigma", None) for i in instruments}
        if len(sigmas) == 1 and None not in sigmas:
            return cls(xyz, sigma=sigmas.pop())
        covs = [i.weight.cov.to(xyz) if isinstance(i.weight, CovarianceWeight) else
                (i.weight.sigma ** 2) * torch.eye(3, dtype=xyz.dtype, device=xyz.device).expand(len(i), 3, 3)
                for i in instruments]
        return cls(xyz, cov=torch.cat(covs))

    def to(self, device) -> "PointTargets":
        out = PointTargets.__new__(PointTargets)
        out.observed = self.observed.to(device)
        w = self.weight
        if isinstance(w, CovarianceWeight):
            w = w.to(device)
        out.weight = w
        return out
