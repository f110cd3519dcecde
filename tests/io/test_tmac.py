"""T-Mac export importer: decimal commas, line endings, Euler convention, std columns, bad cells named."""

import math

import numpy as np
import pytest
import torch

from torchcal.io.csv import DataError
from torchcal.io.tmac import TMAC_JOINTS, read_tmac, read_trafo

HEAD = ["Timestamp", "Goal x"] + list(TMAC_JOINTS) + ["measurement_temperature", "measurement_x", "measurement_std_x",
        "measurement_y", "measurement_std_y", "measurement_z", "measurement_std_z", "measurement_rx",
        "measurement_std_rx", "measurement_ry", "measurement_std_ry", "measurement_rz", "measurement_std_rz"]


def _rows(n, seed=0):
    rng = np.random.default_rng(seed)
    q = rng.uniform(-3, 3, (n, 6))
    xyz = rng.uniform(-3000, 3000, (n, 3))
    ang = rng.uniform(-80, 80, (n, 3))
    std = rng.uniform(0.001, 0.05, (n, 6))
    return q, xyz, ang, std


def _write(path, q, xyz, ang, std, newline="\r\n", nul=False):
    def c(v):
        return repr(float(v)).replace(".", ",")

    lines = [";".join(HEAD)]
    for i in range(len(q)):
        m = []
        for k in range(3):
            m += [c(xyz[i, k]), c(std[i, k])]
        for k in range(3):
            m += [c(ang[i, k]), c(std[i, 3 + k])]
        lines.append(";".join(["2,02011E+13", "-0,1"] + [c(v) for v in q[i]] + ["21,68"] + m))
    end = ("\x00" if nul else "") + newline
    path.write_bytes(end.join(lines).encode() + end.encode())
    return path


def _rot_xyz_intrinsic(a, b, c):
    """Rx(a) Ry(b) Rz(c), degrees, with plain numpy."""
    a, b, c = np.radians([a, b, c])
    Rx = np.array([[1, 0, 0], [0, math.cos(a), -math.sin(a)], [0, math.sin(a), math.cos(a)]])
    Ry = np.array([[math.cos(b), 0, math.sin(b)], [0, 1, 0], [-math.sin(b), 0, math.cos(b)]])
    Rz = np.array([[math.cos(c), -math.sin(c), 0], [math.sin(c), math.cos(c), 0], [0, 0, 1]])
    return Rx @ Ry @ Rz


@pytest.mark.parametrize("newline,nul", [("\r\n", False), ("\n", True)])
def test_reads_values_in_si_with_intrinsic_xyz(tmp_path, newline, nul):
    q, xyz, ang, std = _rows(7)
    m = read_tmac(_write(tmp_path / "m.csv", q, xyz, ang, std, newline, nul))
    assert len(m) == 7 and m.rows.tolist() == list(range(1, 8)) and m.pose.tolist() == list(range(1, 8))
    assert np.allclose(m.q.numpy(), q, atol=1e-15, rtol=1e-15)
    assert np.allclose(m.xyz.numpy(), xyz / 1000, rtol=1e-15, atol=0)
    ref = np.stack([_rot_xyz_intrinsic(*a) for a in ang])
    assert np.abs(m.extra["rotation"].numpy() - ref).max() < 1e-14
    ps = m.extra["pose_std"].numpy()
    assert np.allclose(ps[:, :3], std[:, :3] / 1000) and np.allclose(ps[:, 3:], np.radians(std[:, 3:]))
    assert torch.allclose(m.extra["temperature"], torch.full((7,), 21.68, dtype=torch.float64))
    # the subset slices the rotations with the rows
    assert torch.equal(m.subset(torch.tensor([2, 4])).extra["rotation"], m.extra["rotation"][[2, 4]])


def test_bad_cells_named_by_row_and_column(tmp_path):
    q, xyz, ang, std = _rows(5)
    p = _write(tmp_path / "bad.csv", q, xyz, ang, std)
    lines = p.read_bytes().decode().split("\r\n")
    cells = lines[3].split(";")
    cells[HEAD.index("elbow_joint")] = "abc"
    cells[HEAD.index("measurement_ry")] = "1,2,3"
    lines[3] = ";".join(cells)
    lines[5] = lines[5] + ";7"
    p.write_bytes("\r\n".join(lines).encode())
    with pytest.raises(DataError) as e:
        read_tmac(p)
    msg = str(e.value)
    assert "bad.csv" in msg and "3 problems" in msg
    assert "row 3 (line 4), column 'elbow_joint': not a number: 'abc'" in msg
    assert "row 3 (line 4), column 'measurement_ry'" in msg
    assert "row 5 (line 6): 22 fields, the header has 21" in msg


def test_missing_column_and_joint_limits(tmp_path):
    q, xyz, ang, std = _rows(3)
    p = _write(tmp_path / "m.csv", q, xyz, ang, std)
    text = p.read_bytes().decode().replace("measurement_rz", "rz", 1)
    (tmp_path / "n.csv").write_bytes(text.encode())
    with pytest.raises(DataError, match="column 'measurement_rz': column missing"):
        read_tmac(tmp_path / "n.csv")
    # a column name given twice: header.index took the first one's values silently
    text = p.read_bytes().decode().replace("Goal x", "measurement_x", 1)
    (tmp_path / "d.csv").write_bytes(text.encode())
    with pytest.raises(DataError, match=r"column 'measurement_x': appears 2 times in the header"):
        read_tmac(tmp_path / "d.csv")
    import torchcal

    q[1, 2] = 7.0  # beyond +-360 deg
    p = _write(tmp_path / "lim.csv", q, xyz, ang, std)
    with pytest.raises(DataError, match="row 2 .*column 'elbow_joint': 7 rad is outside"):
        read_tmac(p, torchcal.load_robot("ur10"))


def test_trafo_file(tmp_path):
    p = tmp_path / "Trafo.txt"
    p.write_text("0. 1. 0. 10.\n-1. 0. 0. 0.\n0. 0. 1. -109.\n0. 0. 0. 1.")
    T = read_trafo(p)
    assert torch.allclose(T[:3, 3], torch.tensor([0.01, 0.0, -0.109], dtype=torch.float64))
    assert torch.allclose(T[:3, :3] @ T[:3, :3].T, torch.eye(3, dtype=torch.float64))
    p.write_text("1 0 0\n0 1 0")
    with pytest.raises(DataError, match="expected 16 numbers"):
        read_trafo(p)


def test_convert_to_the_sensor_contract_round_trips(tmp_path):
    import torchcal
    from torchcal.io.sensor_csv import read_pose_measurements
    from torchcal.io.tmac import convert_tmac

    robot = torchcal.load_robot("ur10")
    q, xyz, ang, std = _rows(6, seed=3)
    src = _write(tmp_path / "m.csv", q, xyz, ang, std)
    out = convert_tmac(src, tmp_path / "contract.csv", robot)
    back = read_pose_measurements(out, robot)
    m = read_tmac(src, robot)
    assert back.pose.tolist() == m.pose.tolist()
    assert torch.allclose(back.q, m.q, atol=1e-12) and torch.allclose(back.xyz, m.xyz, atol=1e-12)
    assert torch.allclose(back.extra["rotation"], m.extra["rotation"], atol=1e-11)
    assert torch.allclose(back.extra["pose_std"], m.extra["pose_std"], rtol=1e-9)


def test_cli_import_tmac_excludes_named_rows(tmp_path):
    from typer.testing import CliRunner

    import torchcal
    from torchcal.cli import app
    from torchcal.io.sensor_csv import read_pose_measurements

    q, xyz, ang, std = _rows(5, seed=4)
    src = _write(tmp_path / "m.csv", q, xyz, ang, std)
    res = CliRunner().invoke(app, ["import-tmac", str(src), str(tmp_path / "c.csv"), "--exclude", "2", "--exclude", "4"])
    assert res.exit_code == 0, res.output
    assert "left out data rows [2, 4]" in res.output
    back = read_pose_measurements(tmp_path / "c.csv", torchcal.load_robot("ur10"))
    assert back.pose.tolist() == [1, 3, 5]
    res = CliRunner().invoke(app, ["import-tmac", str(src), str(tmp_path / "d.csv"), "--exclude", "9"])
    assert res.exit_code == 2 and "rows [9] to exclude are not data rows" in res.output


def test_rows_repeated_bit_for_bit_are_kept_and_named(tmp_path):
    """A logger that wrote one sample twice: said (with the --exclude to drop it), kept in the output. A row that
    differs in one digit of one cell is a second measurement, not a repeat."""
    from typer.testing import CliRunner

    import torchcal
    from torchcal.cli import app
    from torchcal.io.sensor_csv import read_pose_measurements
    from torchcal.io.tmac import repeated_rows

    q, xyz, ang, std = _rows(6, seed=5)
    for a in (q, xyz, ang, std):
        a[3] = a[1]  # data row 4 repeats row 2
        a[5] = a[1]  # row 6 too
        a[4] = a[0]  # row 5 = row 1 ...
    xyz[4, 2] += 1e-3  # ... but for one digit of z: a second measurement
    src = _write(tmp_path / "m.csv", q, xyz, ang, std)
    assert repeated_rows(read_tmac(src)) == [(4, 2), (6, 2)]
    res = CliRunner().invoke(app, ["import-tmac", str(src), str(tmp_path / "c.csv")])
    assert res.exit_code == 0, res.output
    assert "2 data rows repeat an earlier row bit for bit" in res.output
    assert "4 (= row 2), 6 (= row 2)" in res.output and "--exclude 4 --exclude 6" in res.output
    back = read_pose_measurements(tmp_path / "c.csv", torchcal.load_robot("ur10"))
    assert back.pose.tolist() == [1, 2, 3, 4, 5, 6]  # nothing dropped
    res = CliRunner().invoke(app, ["import-tmac", str(src), str(tmp_path / "d.csv"), "--exclude", "4", "--exclude", "6"])
    assert res.exit_code == 0 and "bit for bit" not in res.output
    with pytest.warns(UserWarning, match="repeat an earlier row"):
        from torchcal.io.tmac import convert_tmac

        convert_tmac(src, tmp_path / "e.csv", torchcal.load_robot("ur10"))


def test_a_stale_reading_is_named(tmp_path):
    """The tracker did not update: a row repeats the previous row's measurement bit for bit while the joints moved
    (the UR10's Series B, rows 533 and 1064). Said with its --exclude, kept; a row whose joints also repeat is a
    logger's repeat instead, and a second measurement of the same pose differs in its last digits."""
    from typer.testing import CliRunner

    from torchcal.cli import app
    from torchcal.io.tmac import stale_rows

    q, xyz, ang, std = _rows(6, seed=7)
    xyz[2], ang[2], std[2] = xyz[1], ang[1], std[1]  # row 3: row 2's reading, its own joints
    src = _write(tmp_path / "m.csv", q, xyz, ang, std)
    assert stale_rows(read_tmac(src)) == [(3, 2)]
    res = CliRunner().invoke(app, ["import-tmac", str(src), str(tmp_path / "c.csv")])
    said = " ".join(res.output.split())
    assert res.exit_code == 0 and "1 data row repeats the previous row's measurement bit for bit while the joints moved: "\
        "3 (= row 2)" in said and "--exclude 3" in said, said
    q[2] = q[1]  # now a logger's repeat: the other message, not this one
    assert stale_rows(read_tmac(_write(tmp_path / "r.csv", q, xyz, ang, std))) == []
    q[2, 0] += 1e-6  # a robot standing still, its encoder's last digits apart: no stale reading either
    assert stale_rows(read_tmac(_write(tmp_path / "s.csv", q, xyz, ang, std))) == []
