"""Measurement models: what an instrument reports for what the kinematic model predicts.

In the manner of theseus' CostFunction / CostWeight / AutoDiffCostFunction: an
:class:`Instrument` holds the observations of R rows, maps the kinematic
model's prediction of each row to what the instrument reports (a residual of
any dimension d per row) and whitens it with a per-row square-root information
matrix (:mod:`.weights`). Jacobians come in closed form where the instrument
and model provide them (:meth:`Instrument.predict_jacobians`), otherwise by
autograd (:func:`row_jacobians`, torch.func, vmapped over rows).
"""

from __future__ import annotations

import copy
from typing import Callable

import torch
from torch.func import jacrev, vmap


class Instrument:
    """Observations y (R, d) of one instrument, its measurement model and its noise.

    Subclasses set ``dim`` and ``observed`` (R, d) and implement :meth:`predict`;
    ``weight`` whitens (see :mod:`torchcal.measure.weights`).
    """

    dim: int = 0
    observed: torch.Tensor
    weight = None

    def __len__(self) -> int:
        return self.observed.shape[0]

    def predict(self, model, q, tool, direction=None, v=None) -> torch.Tensor:
        """What the instrument would report: (B, n) commands, (B,) tools, (B, n) directions, (B, n) joint errors -> (B, d)."""
        raise NotImplementedError

    def predict_jacobians(self, model, q, tool, direction=None, v=None):
        """Closed form: prediction (B, d) and {parameter name: (B, d, *shape), 'v': (B, d, n)}, or None (use autograd)."""
        return None

    def residual(self, pred: torch.Tensor, observed: torch.Tensor) -> torch.Tensor:
        """Raw residual (B, d) = prediction - observation (subclasses wrap angles here).

        Its derivative with respect to ``pred`` must be the identity (true for
        differences and for wrapped angle differences), so that closed-form
        prediction Jacobians are residual Jacobians.
        """
        return pred - observed

    def whiten(self, t: torch.Tensor) -> torch.Tensor:
        """(R, d, ...) raw residuals or Jacobians -> whitened (S_r t_r)."""
        return self.weight.whiten(t)

    def unwhiten(self, t: torch.Tensor) -> torch.Tensor:
        """(R, d, ...) whitened -> raw (S_r^-1 t_r)."""
        return self.weight.unwhiten(t)

    def sqrt_info(self) -> torch.Tensor:
        """(R, d, d) per-row whitening S_r, S_r^T S_r = Sigma_r^-1."""
        return self.weight.sqrt_info(len(self), self.dim, self.observed)

    def subset(self, index) -> "Instrument":
        """The same instrument on the rows ``index`` (bool mask or indices).

        Default: a shallow copy whose tensors with one entry per row (first dimension R) are indexed, its
        weight's too: enough for an instrument holding its observations and per-row data. Override it where the
        instrument holds another tensor that happens to have R rows (station positions of a 4-row test)."""
        _plain(self, "subset")
        R = len(self)
        out = copy.copy(self)
        for k, v in vars(self).items():
            if isinstance(v, torch.Tensor) and v.ndim >= 1 and v.shape[0] == R:
                setattr(out, k, v[index])
        if self.weight is not None:
            if not hasattr(self.weight, "subset"):
                raise NotImplementedError(f"{type(self).__name__}.subset: its weight {type(self.weight).__name__} has no "
                                          "subset(index); give it one, or write the instrument's own subset")
            out.weight = self.weight.subset(index)
        return out

    def to(self, device) -> "Instrument":
        """On another device: a shallow copy with every tensor attribute (and the weight's) moved."""
        _plain(self, "to")
        out = copy.copy(self)
        for k, v in vars(self).items():
            if isinstance(v, torch.Tensor):
                setattr(out, k, v.to(device))
        if self.weight is not None:
            out.weight = copy.copy(self.weight)
            for k, v in vars(self.weight).items():
                if isinstance(v, torch.Tensor):
                    setattr(out.weight, k, v.to(device))
        return out

    def own_parameters(self) -> list[str]:
        """Names of tensors this instrument holds that ask for gradients (an ``nn.Parameter`` among them): the fit
        estimates the model's parameters only, so these stay where they are (the fit warns)."""
        found = [k for k, v in vars(self).items() if isinstance(v, torch.Tensor) and v.requires_grad]
        if isinstance(self, torch.nn.Module):
            found += [k for k, _ in self.named_parameters()]
        return sorted(set(found))


def _plain(instrument, what: str) -> None:
    """The default subset / to walk plain attributes; an nn.Module keeps its tensors as parameters and buffers."""
    if isinstance(instrument, torch.nn.Module):
        raise NotImplementedError(f"{type(instrument).__name__} is an nn.Module: its parameters and buffers are not "
                                  f"plain attributes, so the default {what}() would miss them; write its own {what}()")


def closed_form_declined(model) -> bool:
    """Whether a model says its closed-form Jacobians would leave out terms of its own (``RobotModel.closed_form``:
    a research subclass): its instruments then take autograd (exact, slower), and the batched solvers, which need
    the closed form, say so instead of fitting without the term."""
    ok = getattr(model, "closed_form", None)
    return ok is not None and not ok()


def concat(instruments) -> Instrument:
    """One instrument holding the rows of ``instruments`` in order: ``type(first).cat(instruments)``.

    Every instrument class that can be concatenated provides a classmethod
    ``cat(list)``; mixing classes is an error (their rows mean different things).
    """
    instruments = list(instruments)
    if not instruments:
        raise ValueError("concat: no instruments")
    cls = type(instruments[0])
    if any(type(i) is not cls for i in instruments):
        raise ValueError(f"concat: instruments of different kinds {sorted({type(i).__name__ for i in instruments})}")
    cat = getattr(cls, "cat", None)
    if cat is None:
        raise ValueError(f"concat: {cls.__name__} has no classmethod cat(instruments)")
    return cat(instruments)


def row_jacobians(fn: Callable, params: dict[str, torch.Tensor], v: torch.Tensor, *rows):
    """Per-row Jacobians by autograd: fn(params, v_r (1, n), *row_r (1, ...)) -> residual (1, d).

    params: {name: tensor} shared by all rows; v: (R, n); rows: per-row tensors
    (R, ...) or None. Uses torch.func.jacrev, vmapped over rows (one reverse
    pass per residual component, batched over the rows).
    -> residual (R, d), {name: (R, d, *shape)}, d residual / d v (R, d, n).
    """
    def one(p, vr, *rr):
        r = fn(p, vr[None], *(None if x is None else x[None] for x in rr))[0]
        return r, r

    in_dims = (None, 0) + tuple(None if x is None else 0 for x in rows)
    (Jp, Jv), r = vmap(jacrev(one, argnums=(0, 1), has_aux=True), in_dims=in_dims)(params, v, *rows)
    return r, Jp, Jv
