"""What :func:`.newton.compensate` returns, and why a flagged row is flagged.

A module of its own so that newton.py keeps to the iteration (it was 630 lines); re-exported there
under the old names. Status codes (``CompensationResult.status``, int8 per row), set by the solver
from how each row ended, so that ``reasons()`` does not have to guess them from the numbers:

- ``CONVERGED`` (46) met to the tolerances;
- ``AT_BOUND``: the damped path ran into the correction bound (the solution on this branch lies farther);
- ``BRANCH``: the only solution found within the bound lies across a singular surface of the controller's
  kinematics, i.e. on another configuration (:mod:`.branch`);
- ``OUT_OF_REACH``: the damped path stopped at a stationary point of the pose error with error left, inside
  the bound: the modeled robot cannot reach the pose on this branch (measured: it ends on a singular surface
  of the *model*, which the errors shift away from the nominal one: the pose lies beyond the branch's fold);
- ``NOT_CONVERGED``: the iteration limit;
- ``SINGULAR``: the iteration limit, at a command where the *modeled* Jacobian has lost rank (sigma_min below
  :data:`SINGULAR_FLOOR`): the row ended on a singular surface of the model, e.g. a 7-axis arm's elbow
  stretched at the edge of its reach, where Levenberg-Marquardt only creeps (measured on a LBR iiwa written
  from its DH table: rows left 0.01-0.3 mm off after 40 iterations, a few of them reached after 100-300 more).
'joint limit' (the command leaves the controller's range) and 'singular' (sigma_min of the nominal
Jacobian below a floor) are read from ``within_limits`` and ``sigma_min`` by :meth:`CompensationResult.reasons`.
"""

from __future__ import annotations

from dataclasses import dataclass

import torch

from .bounds import DEFAULT_BOUND, per_joint_bound

CONVERGED, AT_BOUND, BRANCH, OUT_OF_REACH, NOT_CONVERGED, SINGULAR = 0, 1, 2, 3, 4, 5
JOINT_LIMIT = "joint limit: the compensated command leaves the controller's range"
"""The reason of a row whose command leaves the controller's range (:meth:`CompensationResult.reasons`)."""
SINGULAR_FLOOR = 5.73e-4
"""m/rad (orientation rows times 1 m): 0.01 mm/deg, below it a nominal command counts as singular."""


def range_and_coverage(model, q: torch.Tensor, direction: torch.Tensor | None):
    """(B,) bool within the controller's command limits, and (B,) bool outside the identification data's
    direction coverage (None without coverage or directions) of commands q (B, n)."""
    lim = model.command_limits.to(device=q.device, dtype=q.dtype)
    within = ((q >= lim[:, 0]) & (q <= lim[:, 1])).all(-1)
    coverage = getattr(model, "coverage", None)
    if coverage is None or direction is None:
        return within, None
    return within, coverage.outside(q, direction).to(device=q.device, dtype=torch.bool)


@dataclass
class CompensationResult:
    """Compensated commands for B poses (SI: rad / m).

    q: (B, n) compensated commands q_new (52).
    converged: (B,) bool, ||dq|| < tol (51) reached and the pose error left at q
        (evaluated) below residual_tol, on the nominal command's branch.
    iterations: (B,) long, updates (50) made, fixed-Jacobian plus damped.
    pose_error: (B, 6) final error vector (47)-(48) at q: (dx, dy, dz) m and
        (rx, ry, rz) rad, in the modeled flange frame (with ``free_tool_axis``: at the tool point, and
        the rotation about the tool axis, which was left free, included).
    residual: (B,) norm of the error compensate() drives to zero with orientation times ``length`` (m)
        (with ``free_tool_axis`` the rotation about the tool axis is not part of it).
    step: (B,) norm of the last update ||dq|| (rad / m).
    damped: (B,) bool, the row needed the damped least-squares path.
    within_limits: (B,) bool, q inside model.command_limits.
    sigma_min: (B,) smallest singular value of the nominal Jacobian at q_nom
        with orientation rows times ``length`` (m / rad), or None when not asked for.
    correction: (B,) largest |q_new - q_nom| over the joints (rad / m); never
        above compensate()'s max_correction.
    direction_outside: (B,) bool, the row's approach directions at q_new lie
        outside what the identification data covered (``model.coverage``), or
        None when the model carries no coverage or no directions were given.
    status: (B,) int8, how the row ended (module docstring: CONVERGED, AT_BOUND, BRANCH, OUT_OF_REACH,
        NOT_CONVERGED, SINGULAR), or None.
    """

    q: torch.Tensor
    converged: torch.Tensor
    iterations: torch.Tensor
    pose_error: torch.Tensor
    residual: torch.Tensor
    step: torch.Tensor
    damped: torch.Tensor
    within_limits: torch.Tensor
    sigma_min: torch.Tensor | None = None
    correction: torch.Tensor | None = None
    direction_outside: torch.Tensor | None = None
    status: torch.Tensor | None = None

    @property
    def position_error(self) -> torch.Tensor:
        """(B,) final flange position error |de_p| (m)."""
        return self.pose_error[:, :3].norm(dim=-1)

    @property
    def orientation_error(self) -> torch.Tensor:
        """(B,) final flange orientation error |de_r| (rad)."""
        return self.pose_error[:, 3:].norm(dim=-1)

    def reasons(self, max_correction=None, prismatic=None, singular: float = SINGULAR_FLOOR) -> list[str]:
        """Why each row is flagged, '' for a converged row within the joint range: 'joint limit' (the command
        leaves the controller's range), 'branch change' (the solution lies on another configuration),
        'needs more than the bound' (the correction ran into max_correction: the solution lies farther from
        the nominal command), 'singular' (the row ended unfinished on a singular surface of the model, status
        SINGULAR; or sigma_min at the nominal command below ``singular`` m/rad, 0.01 mm/deg, when it was
        computed), 'out of reach' (the modeled robot cannot reach the pose on this branch), else
        'not converged' with the error left. max_correction: compensate()'s bound (number, (n,) tensor or
        the default), used only when ``status`` is None (results built by hand)."""
        status = self.status
        if status is None:  # infer from the numbers, as before there were status codes
            n = self.q.shape[1]
            bound = per_joint_bound(DEFAULT_BOUND if max_correction is None else max_correction, n, self.q.dtype,
                                    self.q.device, "max_correction", prismatic)
            status = torch.full_like(self.iterations, NOT_CONVERGED)
            if bound is not None and self.correction is not None:
                status[self.correction >= 0.999 * float(bound.min())] = AT_BOUND
            status[self.converged] = CONVERGED
        err_mm = (self.residual * 1e3).tolist()
        st = status.tolist()
        conv, within = self.converged.tolist(), self.within_limits.tolist()
        sig = None if self.sigma_min is None else self.sigma_min.tolist()
        out = []
        for i in range(self.q.shape[0]):
            if conv[i] and within[i]:
                out.append("")
            elif not within[i]:
                out.append(JOINT_LIMIT)
            elif st[i] == BRANCH:
                out.append("branch change: the solution within the bound lies on another configuration (across "
                           "a singular surface of the controller's kinematics)")
            elif st[i] == AT_BOUND:
                out.append(f"needs more than the bound: stopped at the correction bound, {err_mm[i]:.3g} mm "
                           "left (near a singular pose, e.g. a straight wrist, the exact solution turns joints far: "
                           "compensate fewer degrees of freedom, --dof 5 or 3, or measure another pose; raise "
                           "--max-correction-deg only if that move is acceptable and no branch change is near)")
            elif st[i] == SINGULAR:
                out.append(f"singular: ended on a singular surface of the modeled robot, {err_mm[i]:.3g} mm left (the "
                           "edge of its reach on this branch, where the solver only creeps)")
            elif sig is not None and sig[i] < singular:
                out.append(f"singular: sigma_min {sig[i]:.3g} m/rad at the nominal command")
            elif st[i] == OUT_OF_REACH:
                out.append(f"out of reach: the modeled robot gets no closer than {err_mm[i]:.3g} mm on this "
                           "branch (a singular surface of the model lies between)")
            else:
                out.append(f"not converged: {err_mm[i]:.3g} mm left")
        return out

    def summary(self) -> dict:
        """Counts and worst errors as plain Python numbers, SI (the unit in each key; a prismatic joint's correction
        counts in metres under ``max_correction_converged_rad``)."""
        c = self.converged
        return {
            "poses": int(c.numel()),
            "converged": int(c.sum()),
            "damped": int(self.damped.sum()),
            "within_limits": int(self.within_limits.sum()),
            "max_iterations": int(self.iterations.max()) if c.numel() else 0,
            "max_position_error_converged_m": float(self.position_error[c].max()) if c.any() else 0.0,
            "max_orientation_error_converged_rad": float(self.orientation_error[c].max()) if c.any() else 0.0,
            "max_correction_converged_rad": float(self.correction[c].max()) if self.correction is not None and c.any() else 0.0,
            "direction_outside": int(self.direction_outside.sum()) if self.direction_outside is not None else None,
        }
