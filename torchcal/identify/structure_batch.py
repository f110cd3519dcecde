"""Models of several structures (e.g. per-joint orders) of one factory fitted on one data set, together.

The center structure is fitted exactly; every other starts from its one-step
solve at the center's linearization (:mod:`.candidates`) and all are polished
together by the batched solver (:mod:`.batched`).
"""

from __future__ import annotations

from typing import Sequence

import torch

from ..core.measurements import Measurements
from ..core.progress import task
from .batched import BatchedFitResult, fit_batch
from .candidates import SharedLinearization
from .fit import fit, resolve_noise, warns_once
from .layout import copy_overlap
from .problem import NoiseModel, Prior


@warns_once
def fit_structures(make, keys: Sequence, data: Measurements, noise: NoiseModel | None = None,
                   prior: Prior | None = Prior(), center=None, **options) -> tuple[list[torch.nn.Module], BatchedFitResult]:
    """Fit one model per structure key (e.g. per-joint order lists) of one factory on one data set, together.

    make(key) -> a fresh model; keys: the structures; center: the key fitted
    first (default: the middle one). The center is fitted exactly, every
    other model starts from its one-step solve at the center's linearization
    (:class:`~torchcal.identify.candidates.SharedLinearization`: already
    within ~0.1 % of its optimum for neighbours), and then all are polished
    together by :func:`~torchcal.identify.batched.fit_batch` (a few iterations each instead of tens from
    zero). -> (the fitted models, in ``keys`` order, and the batch result).

    Example:
        >>> import torch, torchcal
        >>> robot = torchcal.load_robot("fanuc_lrmate200i")
        >>> tools = torch.tensor([[0.033, 0.058, 0.161], [0.057, -0.034, 0.161]], dtype=torch.float64)
        >>> truth = torchcal.TruthRobot.fanuc_paper2(robot, tools, 0)
        >>> q = torchcal.sim.quasi_random_commands(robot.joint_map.limits, 40, 0)
        >>> data = torchcal.simulate(truth, q, [0, 1], torchcal.NoiseModel.from_robot(robot), 0)
        >>> models, out = fit_structures(lambda o: torchcal.RobotModel(robot, tools, orders=o), [1, 2, 3], data)
        >>> len(models), all(r.success for r in out.results)
        (3, True)
    """
    keys = list(keys)
    models = [make(k) for k in keys]
    noise = resolve_noise(models[0], noise)
    center = keys[len(keys) // 2] if center is None else center
    # the superset: every parameter at the largest shape any model has
    shapes: dict[str, list[int]] = {}
    for m in models:
        for name, p in m.named_parameters():
            s = shapes.setdefault(name, list(p.shape))
            shapes[name] = [max(a, b) for a, b in zip(s, p.shape)]
    superset = max(models, key=lambda m: sum(p.numel() for p in m.parameters()))
    if any(list(p.shape) != shapes[n] for n, p in superset.named_parameters()):
        raise ValueError("fit_structures: no model carries every term of the others; give keys whose largest "
                         "model contains the rest (e.g. orders up to the largest)")
    superset = make(keys[models.index(superset)])
    fit_opts = {k: v for k, v in options.items() if k in ("fixed", "gauge", "ftol", "xtol", "max_iter", "mu0")}
    c = make(center)
    r = fit(c, data, noise, prior, **fit_opts)
    copy_overlap(c, superset)
    with task("one-step solves of every model", total=None):
        lin = SharedLinearization(superset, data, noise, prior, v=r.v, fixed=fit_opts.get("fixed", ()),
                                  gauge=fit_opts.get("gauge", True))
        X = lin.solve(lin.masks(models))
    for m, x in zip(models, X):
        lin.layout.set(x)
        copy_overlap(superset, m)
    out = fit_batch(superset, models, data, noise, prior, **{k: v for k, v in options.items() if k != "center"})
    return models, out


__all__ = ["fit_structures"]
