"""The sensor CSV contract: round trip, Euler columns, and every bad input named by row and column."""

import math

import pandas as pd
import pytest
import torch
from scipy.spatial.transform import Rotation

from torchcal.core.exceptions import TorchcalError
from torchcal.io.csv import DataError
from torchcal.io.sensor_csv import (
    R_COLUMNS,
    GravityError,
    check_gravity,
    read_pose_measurements,
    sensor_frame,
    write_pose_measurements,
)
from torchcal.measure.sts import sts_rotation
from torchcal.core.measurements import Measurements

DEG = math.pi / 180


def pose_rows(fanuc, n=6, seed=0, std=True):
    g = torch.Generator().manual_seed(seed)
    lim = fanuc.joint_map.limits
    q = lim[:, 0] + torch.rand(n, 6, generator=g) * (lim[:, 1] - lim[:, 0])
    xyz = torch.tensor([2.0, 0.5, 0.3]) + torch.rand(n, 3, generator=g) * 0.2
    R = torch.from_numpy(Rotation.random(n, random_state=seed).as_matrix())
    data = Measurements.from_tensors(q, 0, xyz, direction=torch.ones(n, 6), pose=torch.arange(10, 10 + n))
    data.extra["rotation"] = R
    if std:
        data.extra["pose_std"] = torch.tensor([1e-5, 2e-5, 3e-5, 1e-4, 2e-4, 3e-4]).expand(n, 6).clone()
    data.extra["note"] = [f"n{i}" for i in range(n)]
    return data


def test_round_trip(tmp_path, fanuc):
    data = pose_rows(fanuc)
    path = write_pose_measurements(tmp_path / "s.csv", data, fanuc)
    header = path.read_text().splitlines()[0].split(",")
    assert header[:13] == ["pose"] + [f"q{i}" for i in range(1, 7)] + [f"dir{i}" for i in range(1, 7)]
    assert header[13:25] == ["x", "y", "z"] + list(R_COLUMNS)
    assert header[25:] == ["sx", "sy", "sz", "srx", "sry", "srz", "note"]
    back = read_pose_measurements(path, fanuc)
    assert torch.allclose(back.q, data.q, atol=1e-12) and torch.equal(back.pose, data.pose)
    assert torch.allclose(back.xyz, data.xyz, atol=1e-12) and back.has_direction
    assert torch.allclose(back.extra["rotation"], data.extra["rotation"], atol=1e-11)
    assert torch.allclose(back.extra["pose_std"], data.extra["pose_std"], rtol=1e-10)
    assert list(back.extra["note"]) == data.extra["note"]
    # mm and deg in the file
    df = pd.read_csv(path)
    assert abs(df["x"][0] - data.xyz[0, 0].item() * 1e3) < 1e-6 and abs(df["srz"][0] - 3e-4 / DEG) < 1e-9


def test_modeled_columns_replace_the_measured_pose(tmp_path, fanuc):
    data = pose_rows(fanuc, std=False)
    T = torch.eye(4).repeat(6, 1, 1)
    T[:, :3, :3] = data.extra["rotation"].transpose(1, 2)
    T[:, :3, 3] = 1.0
    df = sensor_frame(data, fanuc, modeled=T)
    assert (df["x"] == 1000.0).all() and abs(df["r12"][2] - float(T[2, 0, 1])) < 1e-15
    with pytest.raises(ValueError, match="shape"):
        sensor_frame(data, fanuc, modeled=T[:3])
    # prediction input: commands only
    path = tmp_path / "q.csv"
    path.write_text("pose,q1,q2,q3,q4,q5,q6\n0,0,0,0,0,0,0\n1,10,0,0,0,0,0\n")
    d = read_pose_measurements(path, fanuc, require_pose=False)
    assert len(d) == 2 and bool(d.xyz.isnan().all()) and bool(d.extra["rotation"].isnan().all())


def test_euler_columns_with_a_declared_convention(tmp_path, fanuc):
    data = pose_rows(fanuc, std=False)
    df = sensor_frame(data, fanuc)
    eul = Rotation.from_matrix(data.extra["rotation"].numpy()).as_euler("XYZ", degrees=True)
    for i, c in enumerate(("rx", "ry", "rz")):
        df[c] = eul[:, i]
    only = df.drop(columns=list(R_COLUMNS))
    only.to_csv(tmp_path / "e.csv", index=False)
    back = read_pose_measurements(tmp_path / "e.csv", fanuc, euler_columns=("rx", "ry", "rz"), euler_convention="XYZ")
    assert torch.allclose(back.extra["rotation"], data.extra["rotation"], atol=1e-12)
    with pytest.raises(DataError, match="without a declared convention"):
        read_pose_measurements(tmp_path / "e.csv", fanuc, euler_columns=("rx", "ry", "rz"))
    # both given: the declaration must rebuild the r-columns; extrinsic 'xyz' misses
    df.to_csv(tmp_path / "b.csv", index=False)
    read_pose_measurements(tmp_path / "b.csv", fanuc, euler_columns=("rx", "ry", "rz"), euler_convention="XYZ")
    with pytest.raises(DataError) as info:
        read_pose_measurements(tmp_path / "b.csv", fanuc, euler_columns=("rx", "ry", "rz"), euler_convention="xyz")
    msg = str(info.value)
    assert "row 1 (line 2), column 'rx, ry, rz'" in msg and "declared convention 'xyz'" in msg


def write_df(tmp_path, df, name="bad.csv"):
    path = tmp_path / name
    df.to_csv(path, index=False)
    return path


def test_bad_rotation_and_distance_name_row_and_column(tmp_path, fanuc):
    df = sensor_frame(pose_rows(fanuc, std=False), fanuc)
    df.loc[1, "r11"] *= 1.01  # not orthonormal
    df.loc[3, ["r11", "r21", "r31"]] *= -1  # reflection
    df.loc[4, ["x", "y", "z"]] = 0.0  # failed reading at the tracker origin
    df.loc[5, "r22"] += 2e-6  # rounding: within the tolerance, accepted
    with pytest.raises(DataError) as info:
        read_pose_measurements(write_df(tmp_path, df), fanuc)
    msg = str(info.value)
    assert "row 2 (line 3), column 'r11..r33': rotation is not orthonormal" in msg
    assert "row 4 (line 5), column 'r11..r33'" in msg and "reflection" in msg
    assert "row 5 (line 6), column 'x, y, z': sensor at 0 mm from the tracker origin" in msg
    assert "row 6" not in msg and len(info.value.problems) == 3
    assert isinstance(info.value, TorchcalError)


def test_missing_and_partial_columns(tmp_path, fanuc):
    df = sensor_frame(pose_rows(fanuc), fanuc)
    with pytest.raises(DataError, match="r11..r33.*missing"):
        read_pose_measurements(write_df(tmp_path, df.drop(columns=list(R_COLUMNS))), fanuc)
    with pytest.raises(DataError, match=r"all of r11..r33; missing \['r23'\]") as info:
        read_pose_measurements(write_df(tmp_path, df.drop(columns=["r23"])), fanuc)
    assert "no rotation on this row" not in str(info.value)  # the missing column is said once, not per row
    with pytest.raises(DataError, match="sx, sy, sz, srx, sry, srz or none"):
        read_pose_measurements(write_df(tmp_path, df.drop(columns=["srz"])), fanuc)
    bad = df.copy()
    bad.loc[2, "sry"] = -1.0
    with pytest.raises(DataError, match="row 3 .*column 'sry': -1 is not a positive standard deviation"):
        read_pose_measurements(write_df(tmp_path, bad), fanuc)
    bad = df.copy()
    bad.insert(1, "tool", 0)
    with pytest.raises(DataError, match="column 'tool'"):
        read_pose_measurements(write_df(tmp_path, bad), fanuc)
    bad = df.astype({"r31": object})
    bad.loc[0, "r31"] = "abc"
    bad.loc[1, "q2"] = 400.0
    with pytest.raises(DataError) as info:
        read_pose_measurements(write_df(tmp_path, bad), fanuc)
    msg = str(info.value)  # the base contract's checks and ours in one message
    assert "row 1 (line 2), column 'r31': 'abc' is not a finite number" in msg and "row 2 (line 3), column 'q2'" in msg


def test_sts_ranges_are_checked_with_the_tracker_gravity(tmp_path, fanuc):
    data = pose_rows(fanuc, std=False)
    g = torch.tensor([0.0, 0.0, 1.0])
    ang = torch.tensor([[10.0, 5.0, 20.0]] * 6) * DEG
    ang[2, 1] = 57.0 * DEG  # roll out of range
    ang[4, 2] = -62.0 * DEG  # level out of range
    data.extra["rotation"] = sts_rotation(data.xyz, ang, g)
    path = write_pose_measurements(tmp_path / "sts.csv", data, fanuc)
    read_pose_measurements(path, fanuc)  # a generic probe has no such ranges
    with pytest.raises(DataError) as info:
        read_pose_measurements(path, fanuc, sensor="sts", gravity=[0.0, 0.0, 1.0])
    msg = str(info.value)
    assert "row 3 (line 4), column 'roll angle (from x, y, z, r11..r33)': roll angle 57.0000 deg" in msg
    assert "row 5 (line 6), column 'level angle (from x, y, z, r11..r33)': level angle -62.0000 deg" in msg
    assert len(info.value.problems) == 2
    with pytest.raises(GravityError, match="not normalized"):
        read_pose_measurements(path, fanuc, sensor="sts", gravity=[0.0, 0.1, 1.0])


def test_check_gravity():
    assert torch.allclose(check_gravity([0.6, 0.0, 0.8], "cfg"), torch.tensor([0.6, 0.0, 0.8]))
    with pytest.raises(GravityError, match="cfg 'gravity'.*not normalized.*norm 1.004987"):
        check_gravity([0.1, 0.0, 1.0], "cfg 'gravity'")
    with pytest.raises(GravityError, match="g_z > 0"):
        check_gravity([0.0, 0.0, -1.0], "cfg")
    with pytest.raises(GravityError, match="three"):
        check_gravity([0.0, 1.0], "cfg")
    with pytest.raises(GravityError, match="three"):
        check_gravity("up", "cfg")
    assert issubclass(GravityError, TorchcalError) and issubclass(GravityError, ValueError)


def test_docstring_examples():
    import doctest

    import torchcal.io.sensor_csv as mod

    res = doctest.testmod(mod, optionflags=doctest.ELLIPSIS)
    assert res.failed == 0 and res.attempted > 0
