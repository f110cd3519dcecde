"""The CSV contract: unit conversions, round trips, and one message listing every bad input."""

import math
import re

import numpy as np
import pandas as pd
import pytest
from hypothesis import example, given, settings
from hypothesis import strategies as st
import torch

from torchcal.io.csv import MAX_LISTED, DataError, read_measurements, read_table, write_measurements
from torchcal.kinematics import load_robot
from torchcal.core.measurements import Measurements

HEADER = "pose,tool,q1,q2,q3,q4,q5,q6,dir1,dir2,dir3,dir4,dir5,dir6,x,y,z,label"
GOOD = [
    "0,0,10,20,30,40,50,60,1,1,1,1,1,1,100,200,300,a",
    "0,1,10,20,30,40,50,60,1,1,1,1,1,1,101,201,301,b",
    "1,0,-10,-20,-25,-40,-50,-60,-1,-1,-1,-1,-1,-1,400,500,600,c",
]


def write(tmp_path, lines, name="data.csv"):
    p = tmp_path / name
    p.write_text("\n".join(lines) + "\n")
    return p


def test_units_against_hand_computed_numbers(tmp_path, fanuc):
    data = read_measurements(write(tmp_path, [HEADER, *GOOD]), fanuc, n_tools=2)
    assert len(data) == 3
    assert data.q[0].tolist() == pytest.approx([math.radians(v) for v in (10, 20, 30, 40, 50, 60)], abs=1e-15)
    assert data.q[2, 2].item() == pytest.approx(-25 * math.pi / 180, abs=1e-15)
    assert data.xyz[1].tolist() == pytest.approx([0.101, 0.201, 0.301], abs=1e-15)
    assert data.tool.tolist() == [0, 1, 0]
    assert data.pose.tolist() == [0, 0, 1]
    assert data.direction[2].tolist() == [-1.0] * 6
    assert data.has_direction
    assert data.rows.tolist() == [1, 2, 3]
    assert list(data.extra["label"]) == ["a", "b", "c"]

    # writing converts back: pi/4 rad -> 45 deg, 0.25 m -> 250 mm
    m = Measurements.from_tensors(torch.full((1, 6), math.pi / 4), [0], torch.tensor([[0.25, -0.5, 1.0]]))
    out = write_measurements(tmp_path / "w.csv", m, fanuc)
    row = pd.read_csv(out).iloc[0]
    assert [row[f"q{i}"] for i in range(1, 7)] == pytest.approx([45.0] * 6, abs=1e-9)
    assert [row["x"], row["y"], row["z"]] == pytest.approx([250.0, -500.0, 1000.0], abs=1e-9)
    assert "dir1" not in row.index  # no directions recorded, none written


def test_round_trip_reproduces_values_and_extra_columns(tmp_path, fanuc):
    g = torch.Generator().manual_seed(0)
    lim = fanuc.joint_map.limits
    R = 40
    q = lim[:, 0] + torch.rand(R, 6, generator=g) * (lim[:, 1] - lim[:, 0])
    xyz = torch.randn(R, 3, generator=g) * 0.5
    d = torch.where(torch.rand(R, 6, generator=g) > 0.5, 1.0, -1.0)
    m = Measurements(q, torch.arange(R) % 3, xyz, d, torch.arange(R) // 3, torch.arange(1, R + 1), True, "mem",
                     extra={"operator": np.array([f"op {i}, shift" for i in range(R)], dtype=object)})
    path = write_measurements(tmp_path / "rt.csv", m, fanuc)
    back = read_measurements(path, fanuc, n_tools=3)
    # 12 significant digits in the file: far below a tracker's 5 um noise
    assert torch.allclose(back.q, q, rtol=1e-11, atol=1e-13)
    assert torch.allclose(back.xyz, xyz, rtol=1e-11, atol=1e-13)
    assert torch.equal(back.tool, m.tool) and torch.equal(back.pose, m.pose) and torch.equal(back.direction, d)
    assert list(back.extra["operator"]) == list(m.extra["operator"])  # text with a comma survives quoting
    # and a second round trip is exact: what was read is what gets written
    again = read_measurements(write_measurements(tmp_path / "rt2.csv", back, fanuc), fanuc, n_tools=3)
    assert torch.equal(again.q, back.q) and torch.equal(again.xyz, back.xyz)


def test_prismatic_joints_are_millimetres(tmp_path):
    (tmp_path / "slide.urdf").write_text("""<robot name="slide">
      <link name="a"/><link name="b"/><link name="c"/>
      <joint name="x" type="prismatic"><parent link="a"/><child link="b"/><axis xyz="1 0 0"/>
        <limit lower="0" upper="0.8" effort="1" velocity="1"/></joint>
      <joint name="c" type="revolute"><parent link="b"/><child link="c"/><axis xyz="0 0 1"/>
        <limit lower="-3" upper="3" effort="1" velocity="1"/></joint>
    </robot>""")
    robot = load_robot(tmp_path / "slide.urdf")
    data = read_measurements(write(tmp_path, ["pose,tool,q1,q2,x,y,z", "0,0,250,90,1,2,3"]), robot, 1)
    assert data.q[0].tolist() == pytest.approx([0.25, math.pi / 2], abs=1e-15)
    with pytest.raises(DataError, match=r"row 1 \(line 2\), column 'q1': 900 mm is outside .*\[0, 800\] mm"):
        read_measurements(write(tmp_path, ["pose,tool,q1,q2,x,y,z", "0,0,900,0,1,2,3"], "far.csv"), robot, 1)


BAD_CELLS = [
    # (column, bad value, words expected in the message)
    ("q2", "abc", "'abc' is not a finite number"),
    ("q3", "nan", "'nan' is not a finite number"),
    ("x", "", "empty"),
    ("dir4", "0", "'0' is not an approach direction"),
    ("dir1", "2", "'2' is not an approach direction"),
    ("q1", "120", "120 deg is outside the controller range [-100, 100] deg"),
    ("q5", "-90.5", "-90.5 deg is outside the controller range"),
    ("tool", "2", "tool 2 is not configured"),
    ("tool", "-1", "tool -1 is not configured"),
    ("tool", "0.5", "'0.5' is not an integer"),
    ("pose", "x7", "'x7' is not a finite number"),
    ("pose", "1e308", "'1e308' is beyond the exact integers"),  # became -2**63 silently
    ("pose", "1732800000123456789", "is beyond the exact integers"),  # a ns timestamp: two could merge
    ("x", "1e300", "1e+300 mm is beyond any tracker's range"),  # finite: once overflowed the solver
    ("z", "-1e30", "-1e+30 mm is beyond any tracker's range"),  # a lost-beam code
]


@pytest.mark.parametrize("column, value, words", BAD_CELLS)
def test_each_bad_cell_names_file_row_line_and_column(tmp_path, fanuc, column, value, words):
    cols = HEADER.split(",")
    cells = GOOD[2].split(",")
    cells[cols.index(column)] = value
    path = write(tmp_path, [HEADER, GOOD[0], GOOD[1], ",".join(cells)])
    with pytest.raises(DataError) as err:
        read_measurements(path, fanuc, n_tools=2)
    msg = str(err.value)
    assert str(path) in msg
    assert f"row 3 (line 4), column '{column}': " in msg
    assert words in msg
    assert len(err.value.problems) == 1


def test_all_problems_listed_not_just_the_first(tmp_path, fanuc):
    rows = [HEADER,
            "0,0,10,abc,30,40,50,60,1,1,1,1,1,1,100,200,300,a",      # row 1: q2
            "0,1,10,20,30,40,50,60,1,1,1,0,1,1,101,201,301,b",       # row 2: dir4
            "",                                                       # row 3: a blank line inside the data
            "0,1,10,20,30,40,50,60,1,1,1,1,1,1,1,2,3,dup",           # row 4: duplicate (pose 0, tool 1)
            "1,5,10,20,300,40,50,60,1,1,1,1,1,1,4,5,,d"]             # row 5: tool, q3 range, z empty
    path = write(tmp_path, rows)
    with pytest.raises(DataError) as err:
        read_measurements(path, fanuc, n_tools=2)
    msg = str(err.value)
    for needle in ["row 1 (line 2), column 'q2'", "row 2 (line 3), column 'dir4'", "row 3 (line 4): blank line",
                   "row 4 (line 5), column 'pose, tool': duplicate of row 2", "row 5 (line 6), column 'tool'",
                   "row 5 (line 6), column 'q3'", "row 5 (line 6), column 'z'"]:
        assert needle in msg, needle
    # the blank line is reported once (not dropped silently, not once per empty cell)
    assert sum(p.row == 3 for p in err.value.problems) == 1
    assert len(err.value.problems) == 7


def test_long_lists_are_cut_with_a_count(tmp_path, fanuc):
    rows = [HEADER] + [f"{i},0,500,20,30,40,50,60,1,1,1,1,1,1,1,2,3,a" for i in range(MAX_LISTED + 7)]
    with pytest.raises(DataError) as err:
        read_measurements(write(tmp_path, rows), fanuc, n_tools=1)
    msg = str(err.value)
    assert len(err.value.problems) == MAX_LISTED + 8  # every row's cell, and the whole file's note listed first
    assert "... and 8 more problems" in msg and "another robot?" in msg.splitlines()[1]
    assert len(re.findall(r"column 'q1'", msg)) == MAX_LISTED - 1


def test_missing_columns_and_wrong_robot(tmp_path, fanuc):
    path = write(tmp_path, ["pose,tool,q1,q2,q3,q4,q5,q7,dir1,x,y", "0,0,1,2,3,4,5,6,1,1,2"])
    with pytest.raises(DataError) as err:
        read_measurements(path, fanuc, n_tools=1)
    msg = str(err.value)
    assert str(path) in msg
    for needle in ["column 'q6': missing", "column 'z': missing", "dir1..dir6 or none"]:
        assert needle in msg, needle


def test_header_and_shape_errors(tmp_path, fanuc):
    with pytest.raises(DataError, match="no header"):
        read_measurements(write(tmp_path, [""], "empty.csv"), fanuc, 1)
    with pytest.raises(DataError, match="no data rows"):
        read_measurements(write(tmp_path, [HEADER], "header.csv"), fanuc, 1)
    with pytest.raises(DataError, match="column 'q2': appears twice"):
        read_measurements(write(tmp_path, ["pose,tool,q1,q2,q2", "0,0,1,2,3"], "dup.csv"), fanuc, 1)
    with pytest.raises(DataError) as err:
        read_measurements(write(tmp_path, [HEADER, GOOD[0] + ",extra", GOOD[1], "1,2"], "ragged.csv"), fanuc, 2)
    msg = str(err.value)
    assert "ragged.csv" in msg
    assert "row 1 (line 2): has 19 fields, the header has 18" in msg and "row 3 (line 4): has 2 fields" in msg
    with pytest.raises(DataError, match="file not found"):
        read_measurements(tmp_path / "nope.csv", fanuc, 1)


def test_line_numbers_follow_quoted_newlines(tmp_path, fanuc):
    # a note spanning two lines shifts every later line: messages must still point at the right line
    rows = [HEADER, GOOD[0][:-1] + '"two\nlines"', GOOD[1], GOOD[2].replace(",-20,", ",abc,")]
    data_ok = read_measurements(write(tmp_path, rows[:3], "ok.csv"), fanuc, 2)
    assert data_ok.extra["label"][0] == "two\nlines"
    with pytest.raises(DataError, match=r"row 3 \(line 5\), column 'q2'"):
        read_measurements(write(tmp_path, rows), fanuc, 2)


def test_prediction_input_needs_no_pose_or_xyz(tmp_path, fanuc):
    path = write(tmp_path, ["tool,q1,q2,q3,q4,q5,q6,note", "1,0,0,0,0,0,0,first", "0,5,5,5,5,5,5,second"])
    data, raw = read_table(path, fanuc, n_tools=2, require_xyz=False)
    assert torch.isnan(data.xyz).all()
    assert not data.has_direction
    assert data.tool.tolist() == [1, 0]
    assert list(raw.columns) == ["tool", "q1", "q2", "q3", "q4", "q5", "q6", "note"]
    # compensation input: no tool needed; a tool column is then just carried through
    data, _ = read_table(path, fanuc, n_tools=None, require_xyz=False)
    assert data.tool.tolist() == [0, 0] and list(data.extra["tool"]) == ["1", "0"]


def test_european_export_is_read_with_a_note(tmp_path, fanuc, caplog):
    """';' separators and decimal commas (a spreadsheet in a European locale): read, and said so."""
    plain = read_measurements(write(tmp_path, [HEADER, *GOOD], "plain.csv"), fanuc, n_tools=2)
    eu = [HEADER.replace(",", ";")] + [r.replace(",", ";") for r in GOOD]
    eu[1] = eu[1].replace(";10;20;", ";10,0;20,5;").replace(";100;", ";100,25;")
    eu[3] = eu[3][: -len(";c")] + ";comment, with comma"
    path = write(tmp_path, eu, "europe.csv")
    with caplog.at_level("WARNING", logger="torchcal"):
        data, df = read_table(path, fanuc, 2)
    notes = [r.getMessage() for r in caplog.records]
    assert any("europe.csv" in n and "European" in n and "decimal commas" in n for n in notes)
    assert df.attrs["notes"] and "';'" in df.attrs["notes"][0]
    assert data.q[0, 1].item() == pytest.approx(math.radians(20.5), abs=1e-15)
    assert data.xyz[0, 0].item() == pytest.approx(0.10025, abs=1e-15)
    torch.testing.assert_close(data.q[1:], plain.q[1:], rtol=0, atol=0)
    torch.testing.assert_close(data.xyz[1:], plain.xyz[1:], rtol=0, atol=0)
    assert list(data.extra["label"])[2] == "comment, with comma"  # other columns as written
    # a bad cell is still reported with its row and column, not as "has N fields"
    eu[2] = eu[2].replace(";101;", ";1o1;")
    with pytest.raises(DataError) as err:
        read_measurements(write(tmp_path, eu, "europe_bad.csv"), fanuc, 2)
    assert "row 2 (line 3), column 'x'" in str(err.value) and "fields" not in str(err.value)


def test_one_field_header_says_what_separates_fields(tmp_path, fanuc):
    # tab-separated files are read; a decimal comma in one is named by row and column
    lines = [HEADER.replace(",", "\t")] + [r.replace(",", "\t") for r in GOOD]
    lines[1] = lines[1].replace("\t100\t", "\t100,5\t")
    with pytest.raises(DataError) as err:
        read_measurements(write(tmp_path, lines, "tabs.csv"), fanuc, 2)
    assert "row 1 (line 2), column 'x'" in str(err.value) and "'100,5'" in str(err.value)
    # space-separated: one line saying so, not "column missing" for every column
    lines = [HEADER.replace(",", " ")] + [r.replace(",", " ") for r in GOOD]
    with pytest.raises(DataError) as err:
        read_measurements(write(tmp_path, lines, "spaces.csv"), fanuc, 2)
    assert "the contract separates fields with ','" in str(err.value) and "missing" not in str(err.value)
    assert "whitespace" in str(err.value) and "decimal comma" not in str(err.value)
    # space-separated with decimal commas: changing the separators alone would not read it, so it says both
    lines[1] = lines[1].replace(" 100 ", " 100,5 ")
    with pytest.raises(DataError) as err:
        read_measurements(write(tmp_path, lines, "spaces_commas.csv"), fanuc, 2)
    assert "whitespace" in str(err.value) and "decimal commas (e.g. '100,5')" in str(err.value)


def test_data_error_is_a_torchcal_error():
    from torchcal.core.exceptions import TorchcalError

    assert issubclass(DataError, TorchcalError) and issubclass(DataError, ValueError)


def test_line_numbers_survive_column_access_without_a_copy_per_row(tmp_path):
    """pandas deep-copies a frame's attrs on every column access: the line numbers are an immutable tuple whose
    copy is itself (a list of ints cost a call per row on every access), and they still name the file's lines."""
    import copy

    from torchcal.io.csv import LineNumbers, read_raw_table

    p = tmp_path / "blank_line.csv"
    p.write_text("pose,tool,q1\n0,0,1.0\n\n1,0,2.0\n")
    df = read_raw_table(p)
    lines = df.attrs["lines"]
    assert isinstance(lines, LineNumbers) and list(lines) == [2, 3, 4]
    assert copy.deepcopy(lines) is lines
    col = df["q1"]  # a column access: pandas' __finalize__ deep-copies attrs into the Series
    assert col.attrs["lines"] is lines and df.attrs["lines"] is lines


@settings(max_examples=60, deadline=None)
@given(cells=st.lists(st.lists(st.text(alphabet="0123456789.-eE \t\r\u00a0\u2003x;", max_size=6), min_size=3, max_size=3),
                      min_size=1, max_size=6))
def test_a_file_read_without_stripping_is_the_file_read_with_it(tmp_path_factory, cells):
    """read_raw_table strips cells only where the file holds whitespace other than line breaks (or quotes): the
    frame is the one stripping every cell gives (the reference: the padding test made to match always)."""
    import torchcal.io.csv as C

    p = tmp_path_factory.mktemp("strip") / "t.csv"
    p.write_text("pose,tool,q1\n" + "".join(",".join(r) + "\n" for r in cells), encoding="utf-8")

    def read():
        try:
            df = C.read_raw_table(p)
        except DataError as exc:
            return str(exc)
        return df.to_dict("list"), list(df.attrs["lines"])

    fast = read()
    always = re.compile(r"[\s\S]")
    real, C._PADDING = C._PADDING, always
    try:
        ref = read()
    finally:
        C._PADDING = real
    assert fast == ref


@settings(max_examples=60, deadline=None)
@given(cells=st.lists(st.one_of(
    st.text(alphabet="0123456789.+-eE_, \u00a0\u0661xnaifINF", max_size=8),
    st.floats(allow_nan=True, allow_infinity=True).map(repr),
    st.sampled_from(["", "-0", "1e400", "1e-400", "+.5", "5.", "1_000", "Infinity", "0x10", "\u0661\u0662"])),
    min_size=1, max_size=40))
@example(cells=["E", "-0"])  # found by this test in CI: the two forms sign this zero differently
def test_numbers_parsed_as_pandas_parses_a_column_of_strings(cells):
    """parse_numbers reads a column's cells as one object array: the same values (overflow included) and the
    same rejected cells as pandas' conversion of the column of strings. Not the sign of a zero: pandas reads
    '-0' as -0.0 or 0.0 depending on the column's other cells, in either form (['E', '-0']: 0.0 from the
    strings, -0.0 from the object array; other columns the other way round), and no arithmetic here sees it."""
    import numpy as np
    import pandas as pd

    from torchcal.io.csv import parse_numbers

    df = pd.DataFrame({"x": pd.Series(cells, dtype="string[python]")})
    problems = []
    got = parse_numbers(df, "x", problems)
    ref = pd.to_numeric(df["x"], errors="coerce").to_numpy(dtype=np.float64, na_value=np.nan)
    assert np.array_equal(np.isnan(got), np.isnan(ref))
    ok = ~np.isnan(ref)
    assert np.array_equal(got[ok], ref[ok])  # == : -0.0 equals 0.0
    assert sorted(p.row for p in problems) == [int(r) + 1 for r in np.flatnonzero(~np.isfinite(ref))]


# ---------------------------------------------------------------------------- the clean-file fast path
def _same_measurements(a, b) -> bool:
    fields = ("q", "tool", "xyz", "direction", "pose", "rows")
    return (all(torch.equal(getattr(a, k), getattr(b, k)) for k in fields) and a.has_direction == b.has_direction
            and a.source == b.source and list(a.extra) == list(b.extra)
            and all(np.array_equal(a.extra[k], b.extra[k]) for k in a.extra)
            and torch.equal(torch.signbit(a.q), torch.signbit(b.q)))


@settings(max_examples=25, deadline=None)
@given(rows=st.integers(1, 40), directions=st.booleans(), extra=st.booleans(), seed=st.integers(0, 2**31 - 1),
       zeros=st.booleans())
def test_a_clean_file_reads_the_same_by_the_fast_path(tmp_path_factory, rows, directions, extra, seed, zeros):
    """read_measurements reads a clean file by pandas' C float parser (csv._read_clean) into exactly what the
    checked path (read_table, every cell as text) gives: the same bits, signed zeros included."""
    from torchcal.io.csv import _read_clean

    robot = load_robot("fanuc_lrmate200i")
    g = np.random.default_rng(seed)
    lim = np.degrees(robot.joint_map.limits.numpy())
    q = g.uniform(lim[:, 0], lim[:, 1], (rows, 6))
    if zeros:
        q[:, 0] = 0.0  # '0' cells; a '-0' cell goes the checked way (its sign follows pandas' text path)
    cols = {"pose": np.arange(rows) // 3, "tool": np.arange(rows) % 3}
    cols.update({f"q{i + 1}": q[:, i] for i in range(6)})
    if directions:
        cols.update({f"dir{i + 1}": g.choice([-1, 1], rows) for i in range(6)})
    cols.update({c: g.normal(0, 500, rows) for c in ("x", "y", "z")})
    if extra:
        cols["note"] = [f"n{k}" for k in range(rows)]
    path = tmp_path_factory.mktemp("clean") / "m.csv"
    pd.DataFrame(cols).to_csv(path, index=False, float_format="%.12g", lineterminator="\n")
    fast = _read_clean(path, robot, 3)
    assert fast is not None
    assert _same_measurements(fast, read_table(path, robot, 3)[0])
    assert _same_measurements(read_measurements(path, robot, 3), fast)


@pytest.mark.parametrize("edit", ["blank line", "padding", "quotes", "semicolons", "text cell", "empty cell",
                                  "out of range", "direction 2", "tool 3", "duplicate", "short line", "inf",
                                  "minus zero"])
def test_anything_unusual_goes_the_checked_way(tmp_path, edit):
    """The fast path declines every file the checked path would say something about (or reads otherwise), so
    its problems are still named by row and column, or it is read as before."""
    from torchcal.io.csv import _read_clean

    robot = load_robot("fanuc_lrmate200i")
    lines = ["pose,tool,q1,q2,q3,q4,q5,q6,dir1,dir2,dir3,dir4,dir5,dir6,x,y,z"]
    lines += [f"{k},0,{k},10,-5,0,20,0,1,-1,1,1,-1,1,{500 + k},{k},300" for k in range(4)]
    edits = {"blank line": lambda ls: ls[:2] + [""] + ls[2:], "padding": lambda ls: ls[:1] + [" " + ls[1]] + ls[2:],
             "quotes": lambda ls: ls[:1] + [ls[1].replace(",0,", ',"0",', 1)] + ls[2:],
             "minus zero": lambda ls: ls[:1] + [ls[1].replace(",0,20,", ",-0,20,")] + ls[2:],
             "semicolons": lambda ls: [x.replace(",", ";") for x in ls],
             "text cell": lambda ls: ls[:1] + [ls[1].replace(",300", ",abc")] + ls[2:],
             "empty cell": lambda ls: ls[:1] + [ls[1].replace(",300", ",")] + ls[2:],
             "out of range": lambda ls: ls[:1] + [ls[1].replace(",10,-5,", ",500,-5,")] + ls[2:],
             "direction 2": lambda ls: ls[:1] + [ls[1].replace(",1,-1,1,1,-1,1,", ",2,-1,1,1,-1,1,")] + ls[2:],
             "tool 3": lambda ls: ls[:1] + [ls[1].replace("0,0,", "0,3,", 1)] + ls[2:],
             "duplicate": lambda ls: ls + [ls[1]], "short line": lambda ls: ls + ["9,0,1"],
             "inf": lambda ls: ls[:1] + [ls[1].replace(",300", ",inf")] + ls[2:]}
    path = tmp_path / "m.csv"
    path.write_text("\n".join(lines) + "\n")
    assert _read_clean(path, robot, 3) is not None  # the file as written is clean
    path.write_text("\n".join(edits[edit](lines)) + "\n")
    assert _read_clean(path, robot, 3) is None
    try:  # what read_measurements does with it is the checked path's answer
        got = read_measurements(path, robot, 3)
    except DataError as exc:
        with pytest.raises(DataError) as checked:
            read_table(path, robot, 3)
        assert str(exc) == str(checked.value)
    else:
        assert _same_measurements(got, read_table(path, robot, 3)[0])


def test_a_clean_windows_file_reads_the_same_by_the_fast_path(tmp_path):
    """CRLF line ends: read as the csv module reads them, the same bits as the checked path."""
    from torchcal.io.csv import _read_clean

    robot = load_robot("fanuc_lrmate200i")
    lines = ["pose,tool,q1,q2,q3,q4,q5,q6,x,y,z"] + [f"{k},{k % 2},{k}.5,10,-5,0,20,0,{500 + k},{k},300" for k in range(5)]
    path = tmp_path / "m.csv"
    path.write_bytes(("\r\n".join(lines) + "\r\n").encode())
    fast = _read_clean(path, robot, 2)
    assert fast is not None and _same_measurements(fast, read_table(path, robot, 2)[0])


@pytest.mark.parametrize("edit, words", [
    (lambda r: r.replace("0,1,10,20,", "0,1,20,20,"), ["row 2 (pose 0, tool 1) against row 1", "q1 20 against 10"]),
    (lambda r: r.replace(",1,1,1,1,1,1,101,", ",1,1,-1,1,1,1,101,"), ["row 2 (pose 0, tool 1)", "approach directions"]),
])
def test_rows_of_one_pose_that_differ_are_named(tmp_path, fanuc, caplog, edit, words):
    """Rows of one pose are one robot position measured with several tools: a row whose joint command or
    approach direction differs from its pose's first row (a pose number used twice) is warned about, naming the
    file and the rows, whichever reading path the file takes; consistent files say nothing."""
    with caplog.at_level("WARNING", logger="torchcal"):
        read_measurements(write(tmp_path, [HEADER, *GOOD], "ok.csv"), fanuc, n_tools=2)
    assert not caplog.records
    bad = [GOOD[0], edit(GOOD[1]), GOOD[2]]
    assert bad[1] != GOOD[1]
    for name, lines in (("clean.csv", [HEADER, *bad]), ("padded.csv", [HEADER, *[r.replace(",", ", ") for r in bad]])):
        caplog.clear()
        with caplog.at_level("WARNING", logger="torchcal"):
            data = read_measurements(write(tmp_path, lines, name), fanuc, n_tools=2)
        notes = [r.getMessage() for r in caplog.records if "pose's first row" in r.getMessage()]
        assert len(notes) == 1 and name in notes[0] and all(w in notes[0] for w in words), notes
        assert len(data) == 3  # fitted as they are: nothing dropped


def test_a_header_in_another_case_is_one_problem(tmp_path, fanuc):
    """Q1, X, ... instead of q1, x: one line saying the names are lower case, not 'missing' for every column; a
    direction column in capitals is named too (not read as an extra column, leaving the file without directions)."""
    upper = HEADER.replace("pose,tool,", "POSE,Tool,").replace("q", "Q").replace(",x,y,z,", ",X,Y,Z,")
    with pytest.raises(DataError) as err:
        read_measurements(write(tmp_path, [upper, *GOOD]), fanuc, n_tools=2)
    text = str(err.value)
    assert "lower case" in text and "Q1" in text and "X, Y, Z" in text and "missing" not in text
    with pytest.raises(DataError, match="names DIR1, DIR2"):
        read_measurements(write(tmp_path, [HEADER.replace("dir", "DIR"), *GOOD], "dirs.csv"), fanuc, n_tools=2)


def test_a_file_without_a_header_line_is_named_as_such(tmp_path, fanuc):
    """Rows of numbers from the first line: one message saying the header is missing, not 'column 1 appears
    twice' or a missing column for every name."""
    body = "\n".join(",".join(str(v) for v in [p, 0, *[10.0 * j for j in range(6)], 500.0, 0.0, 300.0])
                     for p in range(3))
    path = tmp_path / "noheader.csv"
    path.write_text(body + "\n")
    with pytest.raises(DataError) as err:
        read_measurements(path, fanuc, n_tools=1)
    msg = str(err.value)
    assert "the file has no header line" in msg and "appears twice" not in msg and msg.count("\n  - ") == 1


def test_a_file_for_another_robot_says_so_before_its_cells(tmp_path, fanuc):
    """Most rows beyond the controller range (an IRB 120's file read as a FANUC: 1 539 cells listed one by one)
    is the file's problem, said first; a few stray rows are not."""
    rows = [HEADER] + [f"{k},0,150,20,30,40,50,60,1,1,1,1,1,1,100,200,300,r{k}" for k in range(12)]
    with pytest.raises(DataError) as err:
        read_measurements(write(tmp_path, rows, "other.csv"), fanuc, n_tools=2)
    first = str(err.value).splitlines()[1]
    assert "12 of 12 rows command a joint outside the controller range of 'fanuc_lrmate200i': is this file for "\
           "another robot?" in first
    few = [HEADER] + [f"{k},0,{150 if k < 2 else 10},20,30,40,50,60,1,1,1,1,1,1,100,200,300,r{k}" for k in range(12)]
    with pytest.raises(DataError) as err:
        read_measurements(write(tmp_path, few, "few.csv"), fanuc, n_tools=2)
    assert "another robot" not in str(err.value) and len(err.value.problems) == 2


def test_marked_commands_past_the_range_but_not_beyond_any_joint(tmp_path, fanuc):
    """predict / compensate mark a command past the controller range (and go on); one beyond any joint (1e300)
    was marked too and predicted NaN, written as empty cells with rc 0."""
    from torchcal.io.csv import read_table

    cells = GOOD[2].split(",")
    cells[2] = "175"  # q1 past its 170 deg limit: marked
    path = write(tmp_path, [HEADER, GOOD[0], GOOD[1], ",".join(cells)])
    data, _ = read_table(path, fanuc, 2, outside_limits="mark")
    assert data.extra["outside_limits"].tolist() == [False, False, True]
    cells[2] = "1e300"
    path = write(tmp_path, [HEADER, GOOD[0], GOOD[1], ",".join(cells)], "huge.csv")
    with pytest.raises(DataError, match=r"row 3 \(line 4\), column 'q1': 1e\+300 deg is far beyond any command"):
        read_table(path, fanuc, 2, outside_limits="mark")
