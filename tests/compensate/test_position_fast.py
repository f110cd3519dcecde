"""The compiled 3-DOF pass (torchcal.compensate.fused_position) against the batched torch path it replaces on the
CPU: the same commands, flags and figures, the rows it hands on finished by the torch path, the tool point on its
goal."""

from __future__ import annotations

import math

import pytest
import torch
from conftest import random_commands, randomize

from torchcal.compensate import fused, fused_position, newton
from torchcal.compensate.fused_targets import BEYOND, BRANCH_SIGN, DONE
from torchcal.compensate.toolset import compensation_goal, inverse, model_tool_set_frame
from torchcal.models.robot import RobotModel

pytestmark = pytest.mark.skipif(not fused.HAVE_NUMBA, reason="the compiled pass needs numba")

TOOL = [[0.06, 0.03, 0.12]]  # one reflector, off the J6 axis (m)


def _model(fanuc, seed=51):
    model = randomize(RobotModel(fanuc, torch.tensor(TOOL, dtype=torch.float64), orders=4, backlash=True), seed,
                      rot=3e-3, trans=3e-4)
    with torch.no_grad():  # an identified tool that differs from the nominal one: the tool set's frame is not I
        model.tools.delta.copy_(torch.tensor([[2e-4, -1e-4, 3e-4]], dtype=torch.float64))
    return model


def _torch_path(model, q, s, c, max_correction=newton.DEFAULT_BOUND):
    """compensate(position_only=True)'s batched torch solver (the path every 3-DOF call took before the pass)."""
    G = model_tool_set_frame(model)
    return newton._solve(model, q, s, 1e-10, 30, 1e-5, None, 50, 0.5, 1.0, 1e-12, False, True, 2, True,
                         newton.DEFAULT_BOUND, max_correction, 1e-3, True, None, c, True, target=None,
                         g_inv=None if G is None else inverse(G))


def _spy(monkeypatch):
    """Record the status codes the compiled pass returns (and that it ran at all)."""
    seen = []
    solve = fused_position.solve_positions

    def spy(*a, **k):
        out = solve(*a, **k)
        seen.append(out["status"].clone())
        return out

    monkeypatch.setattr(fused_position, "solve_positions", spy)
    return seen


def _same(res, ref):
    assert torch.equal(res.converged, ref.converged)
    assert torch.equal(res.status, ref.status)
    assert torch.equal(res.damped, ref.damped)
    assert float((res.q - ref.q).abs().max()) < 1e-9  # every row, flagged ones too
    assert float((res.residual - ref.residual).abs().max()) < 1e-9
    assert float((res.pose_error - ref.pose_error).abs().max()) < 1e-9
    assert float((res.correction - ref.correction).abs().max()) < 1e-9


def test_compiled_3dof_pass_equals_the_torch_path(fanuc, monkeypatch):
    """1 200 poses (>= FUSED_MIN_POSES) with a tool point of their own each and approach directions: the compiled
    pass takes them, and the result is the torch path's to 1e-9, row for row; the tool point lands on its goal."""
    model = _model(fanuc)
    B = 1200
    assert B >= newton.FUSED_MIN_POSES
    q = random_commands(fanuc, B, 52)
    g = torch.Generator().manual_seed(53)
    s = torch.where(torch.rand(B, 6, generator=g) < 0.5, -1.0, 1.0).double()
    c = model.tools()[0].detach() + 1e-2 * torch.randn(B, 3, generator=g, dtype=torch.float64)  # (B, 3)
    seen = _spy(monkeypatch)
    res = newton.compensate(model, q, s, position_only=True, tool_point=c)
    assert len(seen) == 1 and int((seen[0] == DONE).sum()) > 0.95 * B  # the pass ran and finished most rows
    ref = _torch_path(model, q, s, c)
    _same(res, ref)
    assert int(res.converged.sum()) > 0.98 * B
    with torch.no_grad():  # the modeled tool point at q on F_n(q_nom) G^-1 c
        F = model.flange(res.q, s, base=False)
        goal = compensation_goal(model, q)
        reach = (F[:, :3, :3] @ c[..., None])[..., 0] + F[:, :3, 3]
        want = (goal[:, :3, :3] @ c[..., None])[..., 0] + goal[:, :3, 3]
    assert float((reach - want)[res.converged].norm(dim=-1).max()) < 1e-9
    assert float(res.correction.median()) > 1e-4  # the commands did change


def test_rows_the_3dof_pass_hands_on_are_finished_by_the_torch_path(fanuc, monkeypatch):
    """Rows with q5 next to 0 (the minimum-norm correction turns q5 across the wrist singularity: det J changes
    sign) and a tight bound on joint 1 (corrections beyond it): the pass hands them on, the torch path solves them
    from q_nom as it would have (some converge there, the others come out flagged), all equal to its result."""
    model = _model(fanuc, 61)
    B = 1100
    q = random_commands(fanuc, B, 62)
    g = torch.Generator().manual_seed(63)
    q[:150, 4] = (torch.rand(150, generator=g, dtype=torch.float64) - 0.5) * 4e-3
    c = model.tools()[0]  # as the model holds it (a parameter: requires grad)
    assert c.requires_grad
    bound = torch.full((6,), math.radians(30.0), dtype=torch.float64)
    bound[0] = 0.0125  # rad: about a third of the rows' corrections of joint 1 (~1e-2) exceed it
    seen = _spy(monkeypatch)
    res = newton.compensate(model, q, position_only=True, tool_point=c, max_correction=bound)
    st = seen[0]
    assert int((st == BRANCH_SIGN).sum()) >= 5 and int((st == BEYOND).sum()) >= 5
    ref = _torch_path(model, q, None, c, bound)
    _same(res, ref)
    handed = st != DONE
    assert bool(res.converged[handed].any()) and not bool(res.converged[handed].all())
    assert not bool(res.damped[~handed].any())  # the pass's own rows
    assert float((res.q - q)[res.converged, 0].abs().max()) <= 0.0125 + 1e-12  # the bound held


def test_a_small_3dof_batch_does_not_start_a_cold_compile(fanuc, monkeypatch):
    """Where the cache predates the 3-DOF kernel, a handful of poses would wait minutes for its compile: they take
    the torch path (same numbers); a large batch still takes the pass."""
    model = _model(fanuc)
    c = model.tools()[0].detach()
    q = random_commands(fanuc, 40, 3)
    big = random_commands(fanuc, newton.FUSED_MIN_POSES, 4)
    newton.compensate(model, big, position_only=True, tool_point=c)  # a large batch: the process is warm now
    seen = _spy(monkeypatch)
    monkeypatch.setattr(newton, "_position_cold", lambda: True)
    small = newton.compensate(model, q, position_only=True, tool_point=c)
    assert seen == []  # the torch path
    _same(small, _torch_path(model, q, None, c))
    monkeypatch.setattr(newton, "_position_cold", lambda: False)
    newton.compensate(model, q, position_only=True, tool_point=c)
    assert len(seen) == 1  # warm and cached: the pass
