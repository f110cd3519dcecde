"""The sensor CSV contract: one row per pose of a 6-DOF sensor or probe, millimetres and degrees.

Columns (header required, order free, names case-sensitive):

================================  =================================================
``pose``                          int, unique per row
``q1..qN``                        commanded joints (deg, mm if prismatic)
``dir1..dirN``                    optional approach directions, +1 / -1
``x, y, z``                       sensor origin in the tracker frame, mm
``r11, r12, r13, ..., r33``       rotation of the sensor frame in the tracker frame,
                                  row-major (columns of R are the sensor axes)
``sx, sy, sz, srx, sry, srz``     optional per-row standard deviations: mm along,
                                  deg about the tracker axes (:class:`~torchcal.measure.pose.PoseInstrument`)
anything else                     carried through as text
================================  =================================================

Instead of the r-columns a file may give Euler angles (deg) in columns named
by ``euler_columns`` with a declared ``euler_convention`` (scipy naming:
'xyz' extrinsic, 'XYZ' intrinsic, see
:func:`torchcal.measure.pose.rotation_from_euler`); when it gives both, the
declared convention must rebuild the r-columns on every row (within
:data:`EULER_TOL_DEG`), which catches a wrong declaration.

Checks, each reported with file, row, line and column in one
:class:`~torchcal.io.csv.DataError`: everything :func:`torchcal.io.csv.parse_table`
checks (joints in range, directions, duplicate poses, ...); rotations that
are not orthonormal (tolerance :data:`~torchcal.measure.pose.ORTHONORMAL_TOL`;
accepted ones are projected onto SO(3)); a sensor at the tracker origin;
non-positive standard deviations; with ``sensor='sts'`` angles outside the
SmartTRACK's ranges. Rows are never dropped.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pandas as pd
import torch

from ..core import units
from ..measure.pose import (
    ORTHONORMAL_TOL,
    euler_mismatch,
    nearest_rotation,
    parse_convention,
    rotation_defects,
    rotation_from_euler,
)
from ..core.measurements import Measurements
from ..measure.gravity import GRAVITY_TOL, GravityError, check_gravity  # noqa: F401  (moved; old imports keep working)
from .csv import (
    DataError,
    Problem,
    parse_numbers,
    read_raw_table,
    measurements_frame,
    parse_table,
    write_table,
)

R_COLUMNS = tuple(f"r{i}{j}" for i in (1, 2, 3) for j in (1, 2, 3))
"""Row-major rotation columns r11 .. r33."""

STD_COLUMNS = ("sx", "sy", "sz", "srx", "sry", "srz")
"""Optional per-row standard deviations: mm (sx, sy, sz) and deg (srx, sry, srz)."""

EULER_TOL_DEG = 1e-3
"""How far (deg) Euler columns in the declared convention may miss the r-columns of the same row."""

MIN_DISTANCE_MM = 1e-3
"""A sensor origin closer than this to the tracker origin is a failed reading."""


TRANSPOSE_MIN_DEG = 5.0
"""Median misfit (deg) of the rotations as read above which a much better fit of their transposes is reported."""


def rotation_fit(q: torch.Tensor, rot: torch.Tensor, robot) -> tuple[float, float, int] | None:
    """How well the rotations fit the nominal robot as read and transposed: (median deg, median deg, pairs).

    q: (R, n) SI commands, rot: (R, 3, 3) rotations (finite rows only). The rotation between consecutive
    rows, in the sensor frame, is the nominal flange's (in the flange frame) turned by the constant mount
    rotation, whatever the tracker frame; a transposed file breaks that. The mount is fitted (Kabsch) on
    the rotation vectors; -> the median misfit of each reading, or None with fewer than 6 rows.
    """
    from scipy.spatial.transform import Rotation

    if q.shape[0] < 6:
        return None
    F = robot.chain.fk(robot.joint_map.to_joint(q.detach().cpu()))[:, :3, :3].numpy()
    a = Rotation.from_matrix(np.swapaxes(F[:-1], 1, 2) @ F[1:]).as_rotvec()
    R = nearest_rotation(rot.detach().cpu()).numpy()
    out = []
    for cand in (R, np.swapaxes(R, 1, 2)):
        b = Rotation.from_matrix(np.swapaxes(cand[:-1], 1, 2) @ cand[1:]).as_rotvec()
        U, _, Vt = np.linalg.svd(a.T @ b)
        d = np.sign(np.linalg.det(Vt.T @ U.T)) or 1.0
        Q = Vt.T @ np.diag([1.0, 1.0, d]) @ U.T
        out.append(float(np.degrees(np.median(np.linalg.norm(b - a @ Q.T, axis=1)))))
    return out[0], out[1], len(a)


def transposed_message(fit: tuple[float, float, int] | None, columns: str) -> str | None:
    """One line when the transposes fit the nominal robot far better than the rotations as read, else None."""
    if fit is None:
        return None
    as_read, transposed, pairs = fit
    if as_read > TRANSPOSE_MIN_DEG and as_read > 10 * transposed:
        return (f"the rotations look transposed: between consecutive rows they miss the nominal robot by {as_read:.3g} "
                f"deg (median of {pairs} row pairs), their transposes by {transposed:.3g} deg; "
                + (f"{columns} must hold the sensor axes as the columns of R (row-major: r11 r12 r13 is the first row)"
                   if columns.startswith("r11") else f"{columns} give the inverse of the sensor's rotation"))
    return None


def _problem_rows(problems: list[Problem], lines) -> list[Problem]:
    if lines is None:
        return problems
    return [p if p.row is None or p.line is not None else Problem(p.row, p.column, p.message, lines[p.row - 1])
            for p in problems]


def parse_pose_table(df: pd.DataFrame, path, robot, require_pose: bool = True, euler_columns=None,
                     euler_convention: str | None = None, sensor: str | None = None, gravity=None) -> Measurements:
    """Validate a raw text table (see :func:`read_pose_measurements`) -> SI :class:`Measurements` with extras.

    extra['rotation']: (R, 3, 3); extra['pose_std']: (R, 6) m, m, m, rad, rad, rad (when the file has sx..srz).
    """
    path = str(path)
    R = len(df)
    cols = set(df.columns)
    problems: list[Problem] = []
    try:
        data = parse_table(df, path, robot, None, require_xyz=require_pose, require_pose=require_pose)
    except DataError as exc:
        problems += exc.problems
        data = None
    lines = df.attrs.get("lines")
    lines = lines if lines is not None and len(lines) == R else None
    if sensor not in (None, "sts", "pose"):
        raise ValueError(f"sensor must be None, 'pose' or 'sts', got {sensor!r}")
    if "tool" in cols:
        problems.append(Problem(None, "tool", "the sensor contract has one sensor per row and no 'tool' column"))

    def numbers(c: str, filled_only: bool) -> np.ndarray:
        if not filled_only:
            return parse_numbers(df, c, problems)
        filled = (df[c] != "").to_numpy()
        out = np.full(R, np.nan)
        sub = df.loc[filled, [c]].reset_index(drop=True)
        sub_p: list[Problem] = []
        out[np.flatnonzero(filled)] = parse_numbers(sub, c, sub_p)
        rows = np.flatnonzero(filled)
        problems.extend(Problem(int(rows[p.row - 1]) + 1, p.column, p.message) for p in sub_p)
        return out

    scratch: list[Problem] = []  # x, y, z problems are parse_table's to report
    xyz_mm = np.stack([parse_numbers(df, c, scratch) if c in cols else np.full(R, np.nan) for c in "xyz"], 1)

    # rotations: r-columns, Euler columns, or both (then they must agree)
    has_r = [c for c in R_COLUMNS if c in cols]
    eu = list(euler_columns) if euler_columns else []
    has_eu = bool(eu) and all(c in cols for c in eu)
    if eu and len(eu) != 3:
        raise ValueError(f"euler_columns must name three columns, got {eu}")
    if eu and not has_eu and not has_r:
        problems.append(Problem(None, None, f"no rotation: neither r11..r33 nor the Euler columns {eu} are there"))
    if has_r and len(has_r) != 9:
        problems.append(Problem(None, None, f"rotation columns must be all of r11..r33; missing "
                                            f"{[c for c in R_COLUMNS if c not in cols]}"))
    rot = np.full((R, 3, 3), np.nan)
    r_ok = len(has_r) == 9
    if r_ok:
        vals = [numbers(c, not require_pose) for c in R_COLUMNS]
        rot = np.stack(vals, 1).reshape(R, 3, 3)
    elif not has_eu and require_pose and not eu:
        problems.append(Problem(None, "r11..r33", f"missing: the sensor contract needs the rotation of the sensor frame "
                                                  f"(or Euler columns with a declared convention); columns found: "
                                                  f"{', '.join(df.columns)}"))
    if has_eu:
        if euler_convention is None:
            if not r_ok:
                problems.append(Problem(None, ", ".join(eu), "Euler angles without a declared convention "
                                                            "(euler_convention='xyz' extrinsic or 'XYZ' intrinsic, ...)"))
        else:
            parse_convention(euler_convention)  # a bad declaration is the caller's error, raised as such
            ang = np.stack([numbers(c, not require_pose) for c in eu], 1)
            ok = np.isfinite(ang).all(1)
            if r_ok:
                rr = np.isfinite(rot).all((1, 2)) & ok
                idx = np.flatnonzero(rr)
                if idx.size:
                    bad = euler_mismatch(torch.from_numpy(ang[idx]), torch.from_numpy(rot[idx]), euler_convention, EULER_TOL_DEG)
                    for b, a in bad:
                        problems.append(Problem(int(idx[b]) + 1, ", ".join(eu),
                                                f"Euler angles in the declared convention '{euler_convention}' miss the "
                                                f"rotation r11..r33 by {a:.4g} deg (tolerance {EULER_TOL_DEG:g}): "
                                                f"another convention?"))
            else:
                rot = np.where(ok[:, None, None], rotation_from_euler(torch.from_numpy(np.where(ok[:, None], ang, 0.0)),
                                                                      euler_convention).numpy(), np.nan)
    r_col = "r11..r33" if r_ok else ", ".join(eu)
    present = np.isfinite(rot).all((1, 2))
    idx = np.flatnonzero(present)
    if idx.size:
        for b, msg in rotation_defects(torch.from_numpy(rot[idx])):
            problems.append(Problem(int(idx[b]) + 1, r_col, msg))
    if require_pose and (r_ok or (has_eu and euler_convention is not None)):
        # rows without one, where the file has rotation columns (their absence is said once, above)
        for r in np.flatnonzero(~present & ~(df == "").all(axis=1).to_numpy()):
            if not any(p.row == r + 1 and p.column in R_COLUMNS + tuple(eu) for p in problems):
                problems.append(Problem(int(r) + 1, r_col, "no rotation on this row"))

    # sensor at the tracker origin: a failed reading
    dist = np.linalg.norm(xyz_mm, axis=1)
    for r in np.flatnonzero(np.isfinite(dist) & (dist < MIN_DISTANCE_MM)):
        problems.append(Problem(int(r) + 1, "x, y, z", f"sensor at {dist[r]:.6g} mm from the tracker origin "
                                                       f"(a failed 0, 0, 0 reading?): no beam direction"))

    # per-row standard deviations
    has_std = [c for c in STD_COLUMNS if c in cols]
    std = None
    if has_std and len(has_std) != 6:
        problems.append(Problem(None, None, f"standard deviation columns must be all of {', '.join(STD_COLUMNS)} or none; "
                                            f"missing {[c for c in STD_COLUMNS if c not in cols]}"))
    elif has_std:
        std = np.stack([numbers(c, not require_pose) for c in STD_COLUMNS], 1)
        for r, k in zip(*np.nonzero(np.isfinite(std) & ~(std > 0))):
            problems.append(Problem(int(r) + 1, STD_COLUMNS[k], f"{std[r, k]:.6g} is not a positive standard deviation"))

    # STS: the sensor's ranges
    g = None
    if sensor == "sts":
        g = check_gravity([0.0, 0.0, 1.0] if gravity is None else gravity, f"{path}: gravity")
        from ..measure.sts import sts_validity

        ok = present & np.isfinite(xyz_mm).all(1) & (dist >= MIN_DISTANCE_MM)
        idx = np.flatnonzero(ok)
        if idx.size:
            v = sts_validity(units.mm_to_m(torch.from_numpy(xyz_mm[idx])), torch.from_numpy(rot[idx]), g)
            for b, name, msg in v.problems:
                problems.append(Problem(int(idx[b]) + 1, f"{name} angle (from x, y, z, {r_col})", msg))

    if not problems and require_pose and data is not None and bool(present.all()):
        msg = transposed_message(rotation_fit(data.q, torch.from_numpy(rot), robot), r_col)
        if msg:
            problems.append(Problem(None, r_col, msg))
    if problems:
        raise DataError(path, _problem_rows(problems, lines))
    assert data is not None
    rotation = torch.from_numpy(rot)
    if bool(present.all()):
        rotation = nearest_rotation(rotation)
    elif present.any():
        rotation[torch.from_numpy(present)] = nearest_rotation(rotation[torch.from_numpy(present)])
    extra = {k: v for k, v in data.extra.items() if k not in R_COLUMNS + STD_COLUMNS}
    extra["rotation"] = rotation
    if std is not None:
        s = torch.from_numpy(std)
        extra["pose_std"] = torch.cat([units.mm_to_m(s[:, :3]), units.deg_to_rad(s[:, 3:])], 1)
    data.extra = extra
    return data


def read_pose_measurements(path, robot, require_pose: bool = True, euler_columns=None, euler_convention: str | None = None,
                           sensor: str | None = None, gravity=None) -> Measurements:
    """Read a sensor CSV (mm, deg) into SI :class:`Measurements`: ``xyz`` (R, 3) m, ``extra['rotation']`` (R, 3, 3),
    ``extra['pose_std']`` (R, 6) m / rad when the file has sx..srz.

    robot: a :class:`torchcal.kinematics.Robot`; require_pose: measured data
    (False for prediction input: only pose and q needed, empty cells allowed);
    euler_columns / euler_convention: see the module; sensor: 'sts' also
    checks the SmartTRACK ranges with the tracker's measured ``gravity``
    ('up', unit, default (0, 0, 1)). Raises :class:`~torchcal.io.csv.DataError`
    listing every problem with row, line and column.

    Example:
        >>> import pathlib, tempfile
        >>> from torchcal.kinematics import load_robot
        >>> path = pathlib.Path(tempfile.mkdtemp()) / "s.csv"
        >>> _ = path.write_text("pose,q1,q2,q3,q4,q5,q6,x,y,z,r11,r12,r13,r21,r22,r23,r31,r32,r33\\n"
        ...                     "0,0,0,0,0,0,0,1500,0,300,1,0,0,0,1,0,0,0,1\\n")
        >>> data = read_pose_measurements(path, load_robot("fanuc_lrmate200i"))
        >>> data.xyz[0].tolist(), tuple(data.extra["rotation"].shape)
        ([1.5, 0.0, 0.3], (1, 3, 3))
    """
    path = Path(path)
    df = read_raw_table(path)
    return parse_pose_table(df, path, robot, require_pose, euler_columns, euler_convention, sensor, gravity)


def pose_columns(T: torch.Tensor) -> dict[str, np.ndarray]:
    """Poses (R, 4, 4) (m) -> {'x', 'y', 'z' (mm), 'r11' .. 'r33'} file columns."""
    T = T.detach().to("cpu", torch.float64)
    out = {c: units.m_to_mm(T[:, i, 3]).numpy() for i, c in enumerate("xyz")}
    for k, c in enumerate(R_COLUMNS):
        out[c] = T[:, k // 3, k % 3].numpy()
    return out


def sensor_frame(data: Measurements, robot, modeled: torch.Tensor | None = None) -> pd.DataFrame:
    """The sensor contract's table for ``data``: pose, q, [dir], x, y, z, r11..r33, [sx..srz], then text extras.

    modeled: (R, 4, 4) poses (m) written in x, y, z, r11..r33 instead of the
    measured ones (``torchcal predict`` on a sensor run).
    """
    base = measurements_frame(data, robot).drop(columns=["tool"])
    head = [c for c in base.columns if c not in ("x", "y", "z")]
    cols = {c: base[c].to_numpy() for c in head if c in ("pose",) or c.startswith(("q", "dir"))}
    if modeled is not None:
        T = torch.as_tensor(modeled)
        if T.shape != (len(data), 4, 4):
            raise ValueError(f"modeled poses must have shape ({len(data)}, 4, 4), got {tuple(T.shape)}")
        cols.update(pose_columns(T))
    else:
        cols.update({c: units.m_to_mm(data.xyz[:, i].detach().cpu().double()).numpy() for i, c in enumerate("xyz")})
        rot = data.extra.get("rotation")
        rot = torch.full((len(data), 3, 3), float("nan"), dtype=torch.float64) if rot is None else torch.as_tensor(rot)
        rot = rot.detach().cpu().double()
        for k, c in enumerate(R_COLUMNS):
            cols[c] = rot[:, k // 3, k % 3].numpy()
    std = data.extra.get("pose_std")
    if std is not None:
        s = torch.as_tensor(std).detach().cpu().double().expand(len(data), 6)
        s = torch.cat([units.m_to_mm(s[:, :3]), units.rad_to_deg(s[:, 3:])], 1)
        for k, c in enumerate(STD_COLUMNS):
            cols[c] = s[:, k].numpy()
    for c in base.columns:  # text extras carried through
        if c not in cols and c not in ("x", "y", "z"):
            cols[c] = base[c].to_numpy()
    return pd.DataFrame(cols)


def write_pose_measurements(path, data: Measurements, robot, modeled: torch.Tensor | None = None) -> Path:
    """Write 6-DOF :class:`Measurements` in the sensor contract (mm, deg); NaN becomes an empty cell.

    modeled: (R, 4, 4) model poses to write instead of the measured ones (see :func:`sensor_frame`).
    """
    return write_table(path, sensor_frame(data, robot, modeled))


__all__ = [
    "EULER_TOL_DEG",
    "GRAVITY_TOL",
    "MIN_DISTANCE_MM",
    "ORTHONORMAL_TOL",
    "R_COLUMNS",
    "STD_COLUMNS",
    "GravityError",
    "check_gravity",
    "parse_pose_table",
    "pose_columns",
    "read_pose_measurements",
    "sensor_frame",
    "write_pose_measurements",
]
