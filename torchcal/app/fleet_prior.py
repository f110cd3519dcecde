"""``prior.fleet``: a ``torchcal fleet`` run's fitted units as the prior of one more unit of the type (issue #18).

A plant that has calibrated a fleet of one robot type measures a new unit with a few poses and fits it with the
fleet's parameter distribution as its prior (:mod:`torchcal.identify.fleet_prior` estimates the covariance).
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import torch

from ..core.exceptions import ConfigError
from .fleet_summary import read_summary


@dataclass
class FleetRunPrior:
    """A fleet run's parameter distribution as a prior (:func:`prior_from_fleet_run`): ``block`` (a
    :class:`~torchcal.identify.blocks.GaussianPrior` for :func:`torchcal.fit`'s ``blocks``), ``mean`` (P,) in the
    full parameter layout (the unit's start), ``names`` (P,) that layout's entries, the ``units`` used and the ones
    ``left_out`` (failed, flagged or under-determined), the covariance ``method``, ``free`` (P,) bool: the
    entries the fleet fitted (the others its gauge pinned), ``unit_model``: the first used unit's fitted model
    (the type's structure and tools)."""

    block: object
    mean: torch.Tensor
    names: list
    units: list
    left_out: list
    method: str
    free: torch.Tensor
    unit_model: object

    def summary(self, run_dir) -> dict:
        """JSON-ready: where the prior came from."""
        return {"fleet": str(run_dir), "units": len(self.units), "left_out": list(self.left_out),
                "method": self.method, "entries": len(self.block.names)}


def prior_from_fleet_run(run_dir, method: str = "shrunk", device=None, robot=None) -> FleetRunPrior:
    """The fitted units of a ``torchcal fleet`` run directory as a Gaussian prior for one more unit of the type.

    Units whose fit failed, that the fleet flagged (a damaged gearbox, a bad measurement) or whose data could not
    determine their parameters (fewer equations than parameters) are left out; at least 3 must remain. Entries
    that are zero in every unit are the ones the fleet's gauge fixing pinned: they are held at zero by a tight
    prior (``pin_gauge``), so a unit fitted without its own gauge fixing stays in the coordinates the fleet's
    covariance was estimated in. method: as
    :func:`torchcal.identify.fleet_prior.fleet_covariance`; robot: the unit's robot, refused (ConfigError) when
    the fleet's units are another type (name or joint limits). -> :class:`FleetRunPrior`.
    """
    from ..identify.blocks import GaussianPrior
    from ..identify.fleet_prior import prior_from_parameters
    from ..identify.layout import ParameterLayout
    from ..identify.problem import Prior
    from ..io.rundir import load_model, require_finished

    run_dir = Path(run_dir)
    require_finished(run_dir, "a fleet prior")  # an interrupted fleet's units are not the type's spread
    table = read_summary(run_dir)
    flagged = table["flagged"].fillna(False).astype(bool) if "flagged" in table else False
    # a unit with fewer equations than parameters holds the prior's values, not the type's spread
    thin = ~table["determined"].fillna(True).astype(bool) if "determined" in table else False
    use = table["status"].eq("fitted") & ~flagged & ~thin
    names = [str(u) for u in table.loc[use, "unit"]]
    left_out = [str(u) for u in table.loc[~use, "unit"]]
    if len(names) < 3:
        raise ConfigError(f"prior.fleet: {run_dir} has {len(names)} fitted, unflagged units; at least 3 are needed "
                          f"for a spread")
    models = [load_model(run_dir / "units" / nm, device) for nm in names]
    if robot is not None:
        theirs = models[0].robot
        mine_lim, their_lim = robot.joint_map.limits.cpu(), theirs.joint_map.limits.cpu()
        if theirs.name != robot.name or mine_lim.shape != their_lim.shape or not bool(
                torch.allclose(mine_lim.to(their_lim), their_lim)):
            raise ConfigError(f"prior.fleet: the units of {run_dir} are a {theirs.name}, this unit a {robot.name} "
                              f"(a fleet's prior serves units of its own type)")
    layouts = [ParameterLayout(m) for m in models]
    entry_names = layouts[0].names()
    for nm, lay in zip(names[1:], layouts[1:]):
        if lay.names() != entry_names:
            raise ConfigError(f"prior.fleet: unit {nm} of {run_dir} has another model structure than unit {names[0]}")
    X = torch.stack([lay.get().detach() for lay in layouts])
    keep = (X != 0).any(0).expand_as(X)  # an entry the gauge pinned is exactly zero in every unit
    parts = prior_from_parameters(X, keep, entry_names, Prior().sigma(layouts[0]).to(X), method, pin_gauge=True)
    mean = torch.zeros(X.shape[1], dtype=X.dtype, device=X.device)
    mean[parts.free] = parts.mean
    return FleetRunPrior(GaussianPrior(parts.names, parts.mean.cpu(), parts.cov.cpu()), mean, entry_names, names,
                         left_out, method, keep[0].clone(), models[0])


def fleet_backlash_orders(run_dir) -> list[int]:
    """The backlash orders of a ``torchcal fleet`` run's units (its first fitted unit's model: every unit has the
    fleet's structure). A unit fitted with the fleet's prior and ``model.backlash: true`` takes these, not the
    orders its own few poses would suggest, so that its model has the structure the prior describes."""
    from ..io.rundir import RunDirError, first_readable_model

    run_dir = Path(run_dir)
    table = read_summary(run_dir)
    fitted = [str(u) for u in table.loc[table["status"].eq("fitted"), "unit"]]
    if not fitted:
        raise ConfigError(f"prior.fleet: {run_dir} has no fitted unit")
    try:
        model = first_readable_model(run_dir / "units" / name for name in fitted)
    except RunDirError as exc:
        raise ConfigError(f"prior.fleet: {run_dir}: {exc}") from None
    return [int(b) for b in model.joint_errors.backlash_orders.tolist()]


__all__ = ["FleetRunPrior", "fleet_backlash_orders", "prior_from_fleet_run"]
