"""Controller exports of the compensation tables: CSV (round trip), Siemens 840D CEC, LinuxCNC joint comp."""

import re
import warnings

import numpy as np
import pytest
import torch

from torchcal.compensate.tables import (
    CompensationTable,
    TableSizeError,
    TableSlopeWarning,
    apply_tables,
    compensation_tables,
)
from torchcal.error_models.axis_perturbation import AxisPerturbation
from torchcal.export.controller import (
    export_tables,
    read_linuxcnc_comp,
    read_tables_csv,
    write_linuxcnc_comp,
    write_siemens_cec,
    write_tables_csv,
)
from torchcal.io.csv import DataError

LIM = torch.tensor([[0.08, 6.08], [0.04, 2.56], [0.007, 0.988], [-4.7, 4.7], [-1.91, 1.92]], dtype=torch.float64)
PRIS = torch.tensor([True, True, True, False, False])
NAMES = ["X", "Y", "Z", "C", "B"]


@pytest.fixture
def tables():
    ap = AxisPerturbation(LIM, PRIS, orders=4, axis_names=NAMES)
    g = torch.Generator().manual_seed(0)
    with torch.no_grad():
        ap.coef.copy_(torch.randn(ap.coef.shape, generator=g, dtype=torch.float64) * 2e-5)
    return compensation_tables(ap, points_per_table=21)


def quiet(fn, *a, **k):
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", TableSlopeWarning)
        return fn(*a, **k)


def test_csv_round_trip_and_apply_from_file(tmp_path, tables):
    p = quiet(write_tables_csv, tmp_path / "t.csv", tables)
    head = p.read_text().splitlines()[0]
    assert head == "output_axis,input_axis,input,correction"
    back = read_tables_csv(p, NAMES, PRIS)
    assert [t.name for t in back] == [t.name for t in tables]
    for a, b in zip(tables, back):
        torch.testing.assert_close(b.input, a.input, rtol=1e-11, atol=0)
        torch.testing.assert_close(b.correction, a.correction, rtol=1e-11, atol=1e-18)
    q = LIM[:, 0] + torch.rand(50, 5, generator=torch.Generator().manual_seed(1), dtype=torch.float64) * (LIM[:, 1] - LIM[:, 0])
    torch.testing.assert_close(apply_tables(back, q), apply_tables(tables, q), rtol=0, atol=1e-14)


def test_csv_file_units_are_mm_and_deg(tmp_path):
    t = CompensationTable(2, 4, "Z", "B", [-np.pi / 2, np.pi / 2], [1e-5, 2e-5], True, False)
    c = CompensationTable(3, 0, "C", "X", [0.0, 1.0], [np.pi / 180, 0.0], False, True)
    p = quiet(write_tables_csv, tmp_path / "u.csv", [t, c])
    rows = [r.split(",") for r in p.read_text().splitlines()[1:]]
    assert [float(v) for v in rows[0][2:]] == pytest.approx([-90.0, 0.01])
    assert [float(v) for v in rows[2][2:]] == pytest.approx([0.0, 1.0])      # X in mm, C correction in deg
    assert [float(v) for v in rows[3][2:]] == pytest.approx([1000.0, 0.0])


def test_csv_reader_reports_every_problem(tmp_path):
    p = tmp_path / "bad.csv"
    p.write_text("output_axis,input_axis,input,correction\nZ,B,-90,0.01\nZ,B,abc,0.02\nQ,B,10,0\nZ,X,5,0.1\nZ,X,4,0.1\n")
    with pytest.raises(DataError) as e:
        read_tables_csv(p, NAMES, PRIS)
    msg = str(e.value)
    assert "row 2" in msg and "column 'input'" in msg and "'abc'" in msg
    assert "row 3" in msg and "column 'output_axis'" in msg and "'Q'" in msg
    p.write_text("output_axis,input_axis,input,correction\nZ,X,5,0.1\nZ,X,4,0.1\n")
    with pytest.raises(DataError, match="row 2.*does not increase"):
        read_tables_csv(p, NAMES, PRIS)
    p.write_text("output_axis,input,correction\nZ,5,0.1\n")
    with pytest.raises(DataError, match="input_axis"):
        read_tables_csv(p, NAMES, PRIS)


def parse_cec(text):
    vals, params = {}, {}
    for line in text.splitlines():
        m = re.match(r"\$AN_CEC\[(\d+),(\d+)\]=(\S+)$", line)
        if m:
            vals.setdefault(int(m[1]), {})[int(m[2])] = float(m[3])
            continue
        m = re.match(r"\$AN_CEC_(\w+)\[(\d+)\]=(\S+)$", line)
        if m:
            params.setdefault(int(m[2]), {})[m[1]] = m[3]
    return vals, params


def test_siemens_cec_program(tmp_path, tables):
    sel = [t for t in tables if t.name in ("Z(B)", "X(X)", "C(Z)")]
    p = quiet(write_siemens_cec, tmp_path / "cec.mpf", sel, max_points=21)
    text = p.read_text()
    vals, params = parse_cec(text)
    assert sorted(vals) == [0, 1, 2]
    for t_idx, t in enumerate(sel):
        x, c = t.file_units()
        v = vals[t_idx]
        assert sorted(v) == list(range(t.size))
        np.testing.assert_allclose([v[k] for k in range(t.size)], c.numpy(), rtol=0, atol=0.51e-8)  # 8 decimals
        pr = params[t_idx]
        lo, hi, step = float(pr["MIN"]), float(pr["MAX"]), float(pr["STEP"])
        assert round((hi - lo) / step) + 1 == t.size
        assert lo == pytest.approx(float(x[0])) and hi == pytest.approx(float(x[-1]))
        assert pr["INPUT_AXIS"] == f"(AX{t.input_axis + 1})" and pr["OUTPUT_AXIS"] == f"(AX{t.output_axis + 1})"
        assert pr["DIRECTION"] == "0" and pr["MULT_BY_TABLE"] == "0" and pr["IS_MODULO"] == "0"
    for needle in ("MD18342 $MN_MM_CEC_MAX_POINTS", "MD32710 $MA_CEC_ENABLE", "SD41300 $SN_CEC_TABLE_ENABLE", "M17"):
        assert needle in text
    # the NC language's numbers: fixed point, no C exponent, at most 8 decimals
    import re

    numbers = re.findall(r"^\$AN_CEC(?:_STEP|_MIN|_MAX)?\[[^\]]*\]=(\S+)$", text, flags=re.M)
    assert numbers and all(re.fullmatch(r"-?\d+(\.\d{1,8})?", v) for v in numbers), numbers[:5]


def test_siemens_too_many_points_keeps_the_others(tmp_path, tables):
    small = tables[0]
    big = compensation_tables(AxisPerturbation(LIM, PRIS, 2, pairs=[(2, 4)], axis_names=NAMES), points_per_table=50)[0]
    with pytest.raises(TableSizeError) as e:
        quiet(write_siemens_cec, tmp_path / "cec.mpf", [big, small], max_points=30)
    assert e.value.ok == [small.name] and list(e.value.failed) == ["Z(B)"]
    assert "MD18342" in str(e.value)
    vals, _ = parse_cec((tmp_path / "cec.mpf").read_text())
    assert list(vals) == [0] and len(vals[0]) == small.size


def test_siemens_modulo_axis(tmp_path):
    x = torch.linspace(0, 2 * np.pi, 13, dtype=torch.float64)
    turn = CompensationTable(0, 3, "X", "C", x, 1e-5 * torch.sin(x), True, False)
    long = CompensationTable(1, 3, "Y", "C", x * 1.5 - 4.7, 1e-5 * torch.sin(x), True, False)
    with pytest.raises(TableSizeError, match="Y\\(C\\).*360"):
        quiet(write_siemens_cec, tmp_path / "m.mpf", [turn, long], modulo_axes=("C",))
    _, params = parse_cec((tmp_path / "m.mpf").read_text())
    assert params[0]["IS_MODULO"] == "1"


def test_linuxcnc_same_axis_tables(tmp_path, tables):
    from torchcal.export.controller import TableNotWrittenWarning

    with pytest.warns(TableNotWrittenWarning, match="20 cross-axis table"):  # said, not only in a comment
        written = quiet(write_linuxcnc_comp, tmp_path / "lcnc", tables)
    assert sorted(written) == sorted(NAMES)          # one per axis: the five T_ii
    for t in tables:
        if t.output_axis != t.input_axis:
            continue
        lines = written[t.input_name].read_text().splitlines()
        assert len(lines) == t.size <= 256
        a = np.array([[float(v) for v in ln.split()] for ln in lines])
        assert (np.diff(a[:, 0]) > 0).all()
        np.testing.assert_array_equal(a[:, 1], a[:, 2])   # no backlash term: same trim both ways
        back = read_linuxcnc_comp(written[t.input_name], t.input_axis, t.input_name, t.input_prismatic)
        torch.testing.assert_close(back.correction, t.correction, rtol=1e-8, atol=1e-15)   # trim = correction to add
    ini = (tmp_path / "lcnc" / "linuxcnc_comp.ini").read_text()
    assert "COMP_FILE_TYPE = 1" in ini and "[JOINT_2]" in ini and "Z(B)" in ini


def test_linuxcnc_size_limit(tmp_path):
    ap = AxisPerturbation(LIM, PRIS, 2, pairs=[(0, 0), (1, 1)], axis_names=NAMES)
    big = compensation_tables(ap, points_per_table=300)
    ok = compensation_tables(ap, points_per_table=256)
    with pytest.raises(TableSizeError) as e:
        quiet(write_linuxcnc_comp, tmp_path / "a", [big[0], ok[1]])
    assert list(e.value.ok) == ["Y"] and list(e.value.failed) == ["X(X)"]
    assert (tmp_path / "a" / "Y.comp").exists() and not (tmp_path / "a" / "X.comp").exists()


def test_export_all_formats_warns_on_steep_ends(tmp_path):
    x = torch.linspace(LIM[2, 0], LIM[2, 1], 11, dtype=torch.float64)
    lam = (2 * (x - x[0]) / (x[-1] - x[0]) - 1)
    steep = CompensationTable(2, 2, "Z", "Z", x, 2e-3 * lam ** 7, True, True)
    with pytest.warns(TableSlopeWarning, match="Z\\(Z\\)"):
        out = export_tables(tmp_path / "e", [steep])
    assert out["csv"].exists() and out["siemens"].exists() and out["linuxcnc"]["Z"].exists()
