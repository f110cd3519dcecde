"""Tracker-export importer: directions before dropping, failed readings, base outliers, drift, errors, CLI."""

import math
from pathlib import Path

import numpy as np
import pytest
import torch
from typer.testing import CliRunner

from conftest import random_commands
from torchcal.cli import app
from torchcal.io.csv import DataError, read_measurements, write_table
from torchcal.io.tracker import import_tracker, read_rows, rigid_to_reference
from torchcal.kinematics import load_robot
from torchcal.models.robot import RobotModel

DEG = math.pi / 180
TOOLS_MM = [[0.3, 0.3, 119.2], [75.0, 89.0, 214.7], [150.6, -1.9, 122.2]]
BASE_MM = np.array([[-150.0, 250.0, 0.0], [260.0, 140.0, 5.0], [40.0, -270.0, -3.0]])  # robot base frame
P = 40


def rot(axis, angle):
    axis = np.asarray(axis, float) / np.linalg.norm(axis)
    K = np.array([[0, -axis[2], axis[1]], [axis[2], 0, -axis[0]], [-axis[1], axis[0], 0]])
    return np.eye(3) + math.sin(angle) * K + (1 - math.cos(angle)) * K @ K


# tracker <- robot base: a fixed, arbitrary rigid placement
R_TRK = rot([0.2, -0.3, 1.0], 2.1)
B_TRK = np.array([2600.0, 300.0, -560.0])


@pytest.fixture(scope="module")
def irb():
    return load_robot("abb_irb120")


@pytest.fixture(scope="module")
def session(irb):
    """Undrifted tracker points (mm) of P commanded poses: q (P, 6) deg, targets (T, P, 3), bases (K, P, 3)."""
    q = random_commands(irb, P, 11)
    model = RobotModel(irb, torch.tensor(TOOLS_MM) * 1e-3, orders=1)
    with torch.no_grad():
        pts = [model.nominal_points(q, torch.full((P,), t, dtype=torch.long)).numpy() * 1e3 for t in range(3)]
    targets = np.stack([p @ R_TRK.T + B_TRK for p in pts])
    bases = np.repeat((BASE_MM @ R_TRK.T + B_TRK)[:, None], P, 1)
    return {"q": q.numpy() / DEG, "targets": targets, "bases": bases}


def write(path: Path, values: np.ndarray, sep: str = " ") -> Path:
    path.write_text("\n".join(sep.join(repr(float(v)) for v in row) for row in values) + "\n")
    return path


def files(tmp_path, q, targets, bases=None, seps=(" ", ",", ", ")):
    j = write(tmp_path / "joints.txt", q)
    t = [write(tmp_path / f"SMR_{i + 1}.txt", x, seps[i % len(seps)]) for i, x in enumerate(targets)]
    b = [write(tmp_path / f"base_{i + 1}.txt", x) for i, x in enumerate(bases)] if bases is not None else []
    return j, t, b


def reference_directions(q: np.ndarray) -> np.ndarray:
    """Plain loop: sign of each joint's move from the previous pose; no move keeps the last sign; first pose +1."""
    out = np.ones_like(q)
    for r in range(1, len(q)):
        for c in range(q.shape[1]):
            step = np.sign(q[r, c] - q[r - 1, c])
            out[r, c] = step if step != 0 else out[r - 1, c]
    return out


def test_failed_readings_dropped_after_directions(tmp_path, irb, session):
    q = session["q"].copy()
    q[8, 2] = q[7, 2]  # joint 3 does not move into pose 9: keeps its previous direction
    targets = session["targets"].copy()
    failed = [5, 6, 20]  # 1-based rows of SMR_2 read as 0 0 0
    targets[1, np.array(failed) - 1] = 0.0
    targets[2, 30] = 0.0  # SMR_3 row 31
    j, t, _ = files(tmp_path, q, targets)
    res = import_tracker(j, t, robot=irb)
    tab = res.table
    assert list(tab.columns) == ["pose", "tool"] + [f"q{i}" for i in range(1, 7)] + [f"dir{i}" for i in range(1, 7)] + ["x", "y", "z"]
    assert len(tab) == 3 * P - 4
    assert sorted(set(range(1, P + 1)) - set(tab.pose[tab.tool == 1])) == failed
    assert sorted(set(range(1, P + 1)) - set(tab.pose[tab.tool == 2])) == [31]
    assert set(tab.pose[tab.tool == 0]) == set(range(1, P + 1))
    assert res.dropped == {str(t[0]): [], str(t[1]): failed, str(t[2]): [31]}
    report = "\n".join(res.report)
    assert f"{t[1]}: 3 failed reading(s)" in report and "rows 5, 6, 20" in report and "rows 31" in report
    # directions from the full commanded sequence, not from the rows left after dropping
    ref = reference_directions(q)
    kept = tab[tab.tool == 1]
    dirs = kept[[f"dir{i}" for i in range(1, 7)]].to_numpy()
    assert np.array_equal(dirs, ref[kept.pose.to_numpy() - 1])
    assert not np.array_equal(dirs, reference_directions(q[kept.pose.to_numpy() - 1]))  # dropping first would differ
    assert ref[8, 2] == ref[7, 2]
    # values carried through, tools in --target order
    for ti in range(3):
        rows = tab[tab.tool == ti]
        assert np.array_equal(rows[["x", "y", "z"]].to_numpy(), targets[ti, rows.pose.to_numpy() - 1])
        assert np.array_equal(rows[[f"q{i}" for i in range(1, 7)]].to_numpy(), q[rows.pose.to_numpy() - 1])
    # the summary table lists every reflector
    summ = {s.name: s for s in res.reflectors}
    assert summ["T2"].failed == failed and summ["T2"].kept == P - 3 and summ["T3"].failed == [31]
    assert res.summary_table().row_count == 3


def test_written_csv_reads_back(tmp_path, irb, session):
    j, t, b = files(tmp_path, session["q"], session["targets"], session["bases"])
    res = import_tracker(j, t, b, robot=irb)
    out = write_table(tmp_path / "out.csv", res.table)
    data = read_measurements(out, irb, 3)
    assert len(data) == 3 * P and data.has_direction
    # the undrifted import reproduces the simulated points (12 significant digits in the file)
    xyz = np.stack([session["targets"][t_, p_ - 1] for t_, p_ in zip(data.tool.tolist(), data.pose.tolist())])
    assert np.abs(data.xyz.numpy() * 1e3 - xyz).max() < 1e-8
    assert np.abs(res.drift_mm).max() < 1e-9


def test_drift_outliers_and_correction(tmp_path, irb, session):
    targets, bases = session["targets"].copy(), session["bases"].copy()
    drifted = np.arange(10, 18)  # 0-based poses whose tracker frame moved
    g = np.random.default_rng(4)
    truth_T = {}
    for p in drifted:
        R = rot(g.normal(size=3), 2e-4)
        b = g.normal(size=3) * 0.2
        truth_T[p] = (R, b)
        targets[:, p] = targets[:, p] @ R.T + b
        bases[:, p] = bases[:, p] @ R.T + b
    bases[2, 3] = bases[2, 3] + np.array([250.0, -120.0, 40.0])  # base 3 locks onto another target at row 4
    bases[1, 25] = 0.0  # base 2 fails at row 26
    j, t, b = files(tmp_path, session["q"], targets, bases)

    with pytest.raises(DataError) as err:
        import_tracker(j, t, b, robot=irb, drift_threshold_mm=0.05)
    msg = str(err.value)
    assert str(b[0]) in msg and "pose 11:" in msg and "pose 18:" in msg and "pose 10:" not in msg and "pose 19:" not in msg
    assert "--correct-drift" in msg

    res = import_tracker(j, t, b, robot=irb, drift_threshold_mm=0.05, correct_drift=True)
    assert res.corrected
    summ = {s.name: s for s in res.reflectors}
    assert [r for r, _ in summ["B3"].outliers] == [4] and summ["B3"].failed == []
    assert summ["B2"].failed == [26] and summ["B2"].outliers == [] and summ["B1"].outliers == []
    assert abs(summ["B3"].outliers[0][1] - np.linalg.norm([250.0, -120.0, 40.0])) < 1e-9
    report = "\n".join(res.report)
    assert "row 4 (" in report and str(b[2]) in report and "drift corrected" in report
    # the correction undoes the drift exactly; undrifted poses are left alone (their outlier / failed rows included)
    for ti in range(3):
        rows = res.table[res.table.tool == ti]
        assert np.abs(rows[["x", "y", "z"]].to_numpy() - session["targets"][ti, rows.pose.to_numpy() - 1]).max() < 1e-9
    # drift per pose: the largest displacement of the pose's base and target points, zero where nothing moved
    undrifted = np.setdiff1d(np.arange(P), drifted)
    assert np.abs(res.drift_mm[undrifted]).max() < 1e-9
    for p in drifted:
        R, bb = truth_T[p]
        pts = np.concatenate([bases[:, p], targets[:, p]])
        expect = np.linalg.norm(pts - (pts - bb) @ R, axis=1).max()  # |x - R^T (x - b)|
        assert abs(res.drift_mm[p] - expect) < 1e-9
    # without the outlier exclusion the wrong reading would have spoilt pose 4; with it, pose 4 used 2 base readings
    assert "translation-only" in report and "4, 26" in report


def test_real_drift_below_threshold_passes_and_is_reported(tmp_path, irb, session):
    bases = session["bases"].copy()
    bases[:, 7] += np.array([0.01, -0.02, 0.0])  # 0.022 mm: under the default 0.1 mm
    j, t, b = files(tmp_path, session["q"], session["targets"], bases)
    res = import_tracker(j, t, b, robot=irb)
    assert not res.corrected
    assert abs(res.drift_mm[7] - math.hypot(0.01, 0.02)) < 1e-9
    assert any("max 0.0224 mm (pose 8)" in line for line in res.report)
    # not corrected: the targets are written as measured
    rows = res.table[res.table.pose == 8]
    assert np.array_equal(rows[["x", "y", "z"]].to_numpy(), session["targets"][rows.tool.to_numpy(), 7])


def test_rigid_to_reference_batched():
    g = np.random.default_rng(0)
    ref = g.normal(size=(4, 3)) * 300
    Rs = np.stack([rot(g.normal(size=3), a) for a in (0.3, -1.0, 2.5)])
    bs = g.normal(size=(3, 3)) * 50
    x = np.einsum("pji,pkj->pki", Rs, ref[None] - bs[:, None])  # R^T (ref - b): R x + b = ref
    w = np.array([[True] * 4, [True, True, True, False], [True, False, False, False]])
    R, b, cnt = rigid_to_reference(x, ref, w)
    assert cnt.tolist() == [4, 3, 1]
    assert np.abs(R[:2] - Rs[:2]).max() < 1e-12 and np.abs(b[:2] - bs[:2]).max() < 1e-9
    assert np.array_equal(R[2], np.eye(3)) and np.abs(x[2, 0] + b[2] - ref[0]).max() < 1e-9


# ---------------------------------------------------------------------------- errors
def test_joint_outside_limits_names_file_row_column(tmp_path, irb, session):
    q = session["q"].copy()
    q[2, 2] = 75.0  # J3 upper limit is +70 deg
    q[6, 5] = -401.0
    j, t, _ = files(tmp_path, q, session["targets"])
    with pytest.raises(DataError) as err:
        import_tracker(j, t, robot=irb)
    msg = str(err.value)
    assert str(j) in msg
    assert "row 3 (line 3), column '3 (J3)': 75 deg is outside" in msg
    assert "row 7 (line 7), column '6 (J6)': -401 deg" in msg
    # without a robot the limits are not checked, and the report says so
    res = import_tracker(j, t)
    assert any("limits not checked" in line for line in res.report)


def test_bad_rows_name_file_row_column(tmp_path, session):
    j, t, _ = files(tmp_path, session["q"], session["targets"])
    lines = t[1].read_text().splitlines()
    lines[4] = "1.0 abc 2.0"
    lines[9] = "1.0 2.0"
    lines.insert(12, "")  # blank line between rows
    t[1].write_text("\n".join(lines) + "\n\n")  # trailing blank lines are fine
    with pytest.raises(DataError) as err:
        import_tracker(j, t)
    msg = str(err.value)
    assert str(t[1]) in msg
    assert "row 5 (line 5), column '2 (y)': 'abc' is not a finite number" in msg
    assert "row 10 (line 10): has 2 fields, expected 3" in msg
    assert "row 13 (line 13): blank line" in msg


def test_comment_lines_shift_line_not_row(tmp_path):
    p = tmp_path / "x.txt"
    p.write_text("# exported by the tracker\n1 2 3\n4,5,6\n7 nan 9\n")
    with pytest.raises(DataError, match=r"row 3 \(line 4\), column '2 \(y\)'"):
        read_rows(p, ["x", "y", "z"])


def test_a_reading_commented_out_in_one_file_only_is_refused(tmp_path, session):
    """Rows pair across files by position: a reading commented out in the joints file and another in a target file
    paired pose k's joints with pose k + 1's point from there on, written with rc 0."""
    j, t, _ = files(tmp_path, session["q"], session["targets"])
    lines = j.read_text().splitlines()
    lines[9] = "# " + lines[9]
    j.write_text("# exported by the robot\n" + "\n".join(lines) + "\n")  # a header comment is fine
    tl = t[0].read_text().splitlines()
    tl[4] = "# " + tl[4]
    t[0].write_text("\n".join(tl) + "\n")
    with pytest.raises(DataError) as err:
        import_tracker(j, t)
    msg = " ".join(str(err.value).split())
    assert f"{j} line 11 is commented out after data row 9" in msg and f"{t[0]} line 5" in msg
    assert "missing" not in msg  # not the row count's message, which blamed the end of the file
    for f in t:  # the same reading left out everywhere: the poses stay paired
        fl = f.read_text().splitlines()
        fl[4] = fl[4] if fl[4].startswith("#") else "# " + fl[4]
        fl[9] = "# " + fl[9]
        f.write_text("\n".join(fl) + "\n")
    jl = j.read_text().splitlines()
    jl[5] = "# " + jl[5]  # data row 5 (line 6 after the header comment)
    j.write_text("\n".join(jl) + "\n")
    table = import_tracker(j, t).table
    assert len(table) == 3 * (P - 2)
    q = table[[f"q{i}" for i in range(1, 7)]].to_numpy()
    idx = np.abs(q[:, None, :] - session["q"][None]).max(-1).argmin(1)  # each row's pose in the session
    assert np.abs(q - session["q"][idx]).max() < 1e-9 and set(range(P)) - set(idx.tolist()) == {4, 9}
    xyz = session["targets"][table["tool"].to_numpy(), idx]
    assert np.abs(table[["x", "y", "z"]].to_numpy() - xyz).max() < 1e-8  # every point with its own pose's joints


def test_unequal_length_and_never_reading(tmp_path, session):
    j, t, _ = files(tmp_path, session["q"], session["targets"])
    write(t[2], session["targets"][2][:-2])
    with pytest.raises(DataError) as err:
        import_tracker(j, t)
    assert str(t[2]) in str(err.value) and f"has {P - 2} rows" in str(err.value) and f"rows {P - 1}..{P} are missing" in str(err.value)
    write(t[2], np.zeros((P, 3)))
    with pytest.raises(DataError, match="never read") as err:
        import_tracker(j, t)
    assert str(t[2]) in str(err.value)


def test_a_target_file_in_metres_is_named(tmp_path, irb, session):
    """One of three reflector files exported in metres: refused naming that file (the others' distances are the
    reference, no robot needed); a single file in metres, with the robot given, is warned about against the
    nominal flange; the same files in mm pass both checks."""
    j, t, _ = files(tmp_path, session["q"], session["targets"])
    assert not [r for r in import_tracker(j, t, robot=irb).report if "look like" in r]
    write(t[1], session["targets"][1] / 1000.0)
    with pytest.raises(DataError) as err:
        import_tracker(j, t)
    msg = str(err.value)
    assert str(t[1]) in msg and "x, y, z" in msg and "metres" in msg and str(t[0]) not in msg
    with pytest.raises(DataError) as err:  # two files: the one in metres is named, against the other's median
        import_tracker(j, t[:2])
    assert str(t[1]) in str(err.value) and "other target file'" in str(err.value)
    res = import_tracker(j, [t[1]], robot=irb)
    assert any(str(t[1]) in r and "metres" in r for r in res.report)
    assert not [r for r in import_tracker(j, [t[0]], robot=irb).report if "look like" in r]


def test_one_tool_in_metres_is_refused_by_the_fit_checks(irb, session):
    """A merged measurement file whose tool 2 rows are in metres: the median over every tool's distances still
    looks like mm, so the tool is judged on its own rows, and named."""
    from torchcal.io.unit_checks import UnitsError, check_point_scale, tool_scales
    from torchcal.core.measurements import Measurements

    q = torch.from_numpy(session["q"]) * DEG
    xyz = torch.from_numpy(session["targets"]) * 1e-3  # (T, P, 3) m
    rows = [(k, t) for t in range(3) for k in range(P)]
    pose = torch.tensor([k for k, _ in rows])
    tool = torch.tensor([t for _, t in rows])
    pts = torch.stack([xyz[t, k] for k, t in rows])
    data = Measurements.from_tensors(q[pose], tool, pts, pose=pose)
    tools = torch.tensor(TOOLS_MM) * 1e-3
    check_point_scale(data, irb, tools)  # mm throughout: passes
    assert all(0.9 < s < 1.1 for s in tool_scales(data, irb, tools).values())
    slipped = Measurements.from_tensors(data.q, tool, torch.where((tool == 2)[:, None], pts * 1e-3, pts), pose=pose)
    with pytest.raises(UnitsError, match="tool 2: the distances") as err:
        check_point_scale(slipped, irb, tools)
    assert "metres" in str(err.value)


# ---------------------------------------------------------------------------- CLI
def test_cli(tmp_path, session):
    targets = session["targets"].copy()
    targets[0, 2] = 0.0
    j, t, b = files(tmp_path, session["q"], targets, session["bases"])
    out = tmp_path / "m.csv"
    args = ["import-tracker", "--joints", j] + sum([["--target", x] for x in t], []) + sum([["--base", x] for x in b], [])
    r = CliRunner().invoke(app, [str(a) for a in args + ["--robot", "abb_irb120", out]])
    assert r.exit_code == 0, r.output
    assert "Tracker import" in r.output and "SMR_1.txt" in r.output and "base drift" in r.output
    assert f"wrote {3 * P - 1} rows" in r.output
    data = read_measurements(out, load_robot("abb_irb120"), 3)
    assert len(data) == 3 * P - 1
    # a joint outside the controller range: exit status 2, the message names file, row and column
    q = session["q"].copy()
    q[0, 1] = 120.0
    write(j, q)
    r = CliRunner().invoke(app, [str(a) for a in args + ["--robot", "abb_irb120", out, "--force"]])
    assert r.exit_code == 2
    assert "joints.txt" in r.output and "row 1 (line 1), column '2 (J2)'" in r.output


def test_tracker_errors_are_torchcal_errors(tmp_path):
    from torchcal.core.exceptions import TorchcalError

    joints = tmp_path / "J.txt"
    joints.write_text("0 0 0 0 0 0\n")
    with pytest.raises(TorchcalError, match="no target reflector files"):
        import_tracker(joints, [], [], None, 0.1, False, 1.0)
    with pytest.raises(ValueError, match="file not found"):  # still a ValueError for older except clauses
        read_rows(tmp_path / "missing.txt", ["x", "y", "z"])


def test_a_semicolon_file_with_decimal_commas_is_read(tmp_path):
    """A European spreadsheet export of a tracker file (';' between fields, ',' as the decimal mark) reads as
    the same numbers as its plain form (it said 'has 4 fields, expected 3')."""
    plain = tmp_path / "plain.txt"
    plain.write_text("2641.5495 162.21378 -7.8522\n2890.9784 33.593321 -193.29479\n")
    euro = tmp_path / "euro.txt"
    euro.write_text("2641,5495;162,21378;-7,8522\n2890,9784;33,593321;-193,29479\n")
    a, b = read_rows(plain, ["x", "y", "z"]), read_rows(euro, ["x", "y", "z"])
    assert np.array_equal(a.values, b.values)
