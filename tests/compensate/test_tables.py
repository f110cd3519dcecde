"""Compensation tables -f_ij (Paper I (2)-(3)) and the controller's table lookup."""

import numpy as np
import pytest
import torch
from numpy.polynomial import chebyshev as npcheb

from torchcal.compensate.tables import (
    CompensationTable,
    TableAxisError,
    TableRangeError,
    TableSizeError,
    TableSlopeWarning,
    apply_tables,
    compensation_tables,
    warn_end_slopes,
)
from torchcal.error_models.axis_perturbation import AxisPerturbation
from torchcal.core.exceptions import TorchcalError

LIM = torch.tensor([[0.08, 6.08], [0.04, 2.56], [0.007, 0.988], [-4.7, 4.7], [-1.91, 1.92]], dtype=torch.float64)
PRIS = torch.tensor([True, True, True, False, False])
NAMES = ["X", "Y", "Z", "C", "B"]


def random_ap(seed=0, order=6, scale=1e-4):
    ap = AxisPerturbation(LIM, PRIS, orders=order, axis_names=NAMES)
    g = torch.Generator().manual_seed(seed)
    with torch.no_grad():
        ap.coef.copy_(torch.randn(ap.coef.shape, generator=g, dtype=torch.float64) * scale / (1 + torch.arange(ap.coef.shape[-1])))
    return ap


def random_q(B, seed=1):
    g = torch.Generator().manual_seed(seed)
    u = torch.rand(B, 5, generator=g, dtype=torch.float64)
    return LIM[:, 0] + u * (LIM[:, 1] - LIM[:, 0])


def test_tables_are_minus_f_on_the_whole_range():
    ap = random_ap()
    tables = compensation_tables(ap, points_per_table=41)
    assert len(tables) == 25 and [(t.output_axis, t.input_axis) for t in tables] == ap.pairs
    for t in tables:
        j = t.input_axis
        assert t.lower == pytest.approx(float(LIM[j, 0])) and t.upper == pytest.approx(float(LIM[j, 1]))
        assert t.size == 41 and t.equally_spaced()
        # independent reference: numpy's Chebyshev series on the normalized input (Paper I (6)-(7))
        lam = (2 * (t.input - LIM[j, 0]) / (LIM[j, 1] - LIM[j, 0]) - 1).numpy()
        ref = -npcheb.chebval(lam, ap.coef[t.output_axis, j].detach().numpy())
        np.testing.assert_allclose(t.correction.numpy(), ref, rtol=1e-12, atol=1e-18)
        assert t.output_prismatic == bool(PRIS[t.output_axis]) and t.input_prismatic == bool(PRIS[j])


def test_apply_matches_numpy_interp_reference():
    ap = random_ap(3)
    tables = compensation_tables(ap, points_per_table=17)
    q = random_q(200)
    got = apply_tables(tables, q)
    ref = q.numpy().copy()
    for t in tables:
        ref[:, t.output_axis] += np.interp(q[:, t.input_axis].numpy(), t.input.numpy(), t.correction.numpy())
    np.testing.assert_allclose(got.numpy(), ref, rtol=0, atol=1e-15)


def test_tables_invert_the_perturbation_to_second_order():
    """q^ = q + T(q) drives the modeled machine to q: q^ + dq(q^) = q up to O(dq * slope) + interpolation error."""
    ap = random_ap(5)
    q = random_q(500, 7)
    d = ap.delta(q).detach()
    for K, tol in ((401, 0.01), (2001, 0.005)):
        qh = apply_tables(compensation_tables(ap, points_per_table=K), q)
        r = qh + ap.delta(qh).detach() - q
        assert (r.abs() / d.abs().max(0).values).max() < tol
    # without the tables the commands are off by the whole perturbation
    assert (d.abs().max(0).values > 1e-5).all()


def test_interpolation_exact_for_linear_and_at_nodes():
    x = torch.linspace(-1, 2, 7, dtype=torch.float64)
    t = CompensationTable(0, 1, "X", "Y", x, 3e-4 * x - 1e-4, True, True)
    q = torch.zeros(50, 2, dtype=torch.float64)
    q[:, 1] = torch.linspace(-1, 2, 50, dtype=torch.float64)
    out = apply_tables([t], q)
    torch.testing.assert_close(out[:, 0], 3e-4 * q[:, 1] - 1e-4, rtol=0, atol=1e-16)
    torch.testing.assert_close(out[:, 1], q[:, 1])
    torch.testing.assert_close(t(x), t.correction, rtol=0, atol=0)


def test_end_values_held_or_reported():
    t = CompensationTable(2, 2, "Z", "Z", [0.0, 0.5, 1.0], [1e-5, 2e-5, 4e-5], True, True)
    q = torch.tensor([[0.0, 0.0, -0.2], [0.0, 0.0, 0.25], [0.0, 0.0, 1.3]], dtype=torch.float64)
    held = apply_tables([t], q, outside="hold")
    torch.testing.assert_close(held[:, 2] - q[:, 2], torch.tensor([1e-5, 1.5e-5, 4e-5], dtype=torch.float64))
    with pytest.raises(TableRangeError) as e:
        apply_tables([t], q)
    msg = str(e.value)
    assert "Z(Z)" in msg and "rows [1, 3]" in msg and "mm" in msg
    assert isinstance(e.value, TorchcalError) and isinstance(e.value, ValueError)


def test_bad_pairs_keep_the_good_tables():
    ap = random_ap()
    with pytest.raises(TableAxisError) as e:
        compensation_tables(ap, points_per_table=5, pairs=[(0, 1), ("Z", "B"), (0, 7), ("W", "X")])
    assert [t.name for t in e.value.ok] == ["X(Y)", "Z(B)"]
    assert set(e.value.failed) == {"0(7)", "W(X)"}
    with pytest.raises(TableSizeError):
        compensation_tables(ap, points_per_table=1)


def test_apply_rejects_tables_for_missing_axes():
    t = CompensationTable(5, 0, "U", "X", [0.0, 1.0], [0.0, 0.0], True, True)
    with pytest.raises(TableAxisError, match="U\\(X\\)"):
        apply_tables([t], torch.zeros(3, 5, dtype=torch.float64))


def test_bad_table_construction():
    with pytest.raises(TableSizeError, match="increasing"):
        CompensationTable(0, 0, "X", "X", [0.0, 0.0, 1.0], [0.0, 0.0, 0.0], True, True)
    with pytest.raises(TableSizeError):
        CompensationTable(0, 0, "X", "X", [0.0], [0.0], True, True)


def test_slope_warning_only_for_steep_ends():
    x = torch.linspace(0, 1, 11, dtype=torch.float64)
    flat = CompensationTable(0, 0, "X", "X", x, 1e-5 * torch.sin(x), True, True)
    steep = CompensationTable(0, 1, "X", "Y", x, 1e-3 * x ** 8, True, True)   # 8 mm/half range at the upper end
    with pytest.warns(TableSlopeWarning, match="X\\(Y\\).*upper"):
        msgs = warn_end_slopes([flat, steep])
    assert len(msgs) == 1


def test_device_and_dtype_follow_q():
    ap = random_ap()
    tables = compensation_tables(ap, points_per_table=9)
    q = random_q(4)
    assert apply_tables(tables, q).dtype == torch.float64
