"""The LinuxCNC volumetric HAL component: its C, compiled with gcc, against torchcal's own table lookup.

The component's C part is the generated header verbatim; a small driver program includes the header,
reads positions (mm / deg) and prints the corrections, and every check compares it with
:func:`torchcal.compensate.tables.tables_delta` (the controller's lookup, end values held).
"""

import os
import shutil
import subprocess
import tempfile
import warnings

import numpy as np
import pytest
import torch
from typer.testing import CliRunner

from conftest import XYZCB_TOOLS
from torchcal.cli import app
from torchcal.compensate.tables import TableSlopeWarning, compensation_tables, tables_delta
from torchcal.export.controller import export_run_tables, write_linuxcnc_comp
from torchcal.export.linuxcnc_hal import (
    FILES,
    TableNotWrittenWarning,
    volumetric_component,
    write_linuxcnc_volumetric,
)
from torchcal.io.rundir import load_model, save_model
from torchcal.models.machine import MachineModel

GCC = shutil.which("gcc")
needs_gcc = pytest.mark.skipif(GCC is None, reason="gcc is not installed")

DRIVER = r"""
#include <stdio.h>
#include "torchcal_volcomp.h"
int main(void)
{
    double q[TCVC_N_AXES], d[TCVC_N_AXES];
    int i, outside;
    for (;;) {
        for (i = 0; i < TCVC_N_AXES; i++)
            if (scanf("%lf", &q[i]) != 1) return 0;
        outside = tcvc_corrections(q, d);
        for (i = 0; i < TCVC_N_AXES; i++) printf("%.17g ", d[i]);
        printf("%d\n", outside);
    }
}
"""


@pytest.fixture(scope="module")
def run(tmp_path_factory, machine):
    """A run directory holding the bundled XYZCB machine with seeded order-4 errors (every one of the 25 f_ij)."""
    run = tmp_path_factory.mktemp("run")
    model = MachineModel(machine, XYZCB_TOOLS.double(), orders=4)
    g = torch.Generator().manual_seed(7)
    with torch.no_grad():
        ae = model.axis_errors
        ae.coef.copy_(torch.randn(ae.coef.shape, generator=g, dtype=torch.float64) * 3e-5 * ae.mask)
    save_model(run, model)
    return run


@pytest.fixture(scope="module")
def tables(run):
    return compensation_tables(load_model(run))


def quiet(fn, *a, **k):
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", TableSlopeWarning)
        return fn(*a, **k)


def compile_driver(folder):
    """gcc the driver against ``folder``'s header, strict C89 with every warning an error."""
    (folder / "driver.c").write_text(DRIVER)
    exe = folder / "driver"
    r = subprocess.run([GCC, "-std=c89", "-pedantic", "-Wall", "-Wextra", "-Werror", "-O2", "-I", str(folder),
                        "-o", str(exe), str(folder / "driver.c")], capture_output=True, text=True)
    assert r.returncode == 0, r.stderr
    return exe


def run_c(exe, q_file_units: np.ndarray):
    """The compiled corrections (B, n) and out-of-range counts (B,) at positions in mm / deg."""
    text = "\n".join(" ".join("%.17g" % v for v in row) for row in q_file_units) + "\n"
    out = subprocess.run([str(exe)], input=text, capture_output=True, text=True, check=True).stdout
    a = np.array([[float(v) for v in line.split()] for line in out.splitlines()])
    assert a.shape == (len(q_file_units), q_file_units.shape[1] + 1)
    return a[:, :-1], a[:, -1].astype(int)


def file_units(tables, n):
    pris = np.zeros(n, dtype=bool)
    for t in tables:
        pris[t.output_axis], pris[t.input_axis] = t.output_prismatic, t.input_prismatic
    return pris


def reference(tables, q_file):
    """torchcal's corrections (hold outside) at positions in mm / deg, in mm / deg."""
    pris = file_units(tables, q_file.shape[1])
    q_si = np.where(pris, q_file / 1000.0, np.deg2rad(q_file))
    d = tables_delta(tables, torch.from_numpy(q_si)).numpy()
    return np.where(pris, d * 1000.0, np.rad2deg(d))


def positions(tables, count, seed, margin=0.05):
    """``count`` random positions (mm / deg) over every axis's range and ``margin`` of it beyond each end."""
    n = 1 + max(max(t.output_axis, t.input_axis) for t in tables)
    lo, hi = np.zeros(n), np.zeros(n)
    for t in tables:
        x, _ = t.file_units()
        lo[t.input_axis], hi[t.input_axis] = float(x[0]), float(x[-1])
    span = hi - lo
    rng = np.random.default_rng(seed)
    return lo - margin * span + rng.random((count, n)) * (1 + 2 * margin) * span, lo, hi


@needs_gcc
def test_compiled_c_applies_all_25_tables_like_torchcal(tmp_path, run, tables):
    out = tmp_path / "vol"
    written = quiet(export_run_tables, run, out, "linuxcnc-volumetric")
    assert sorted(p.name for p in written.values()) == sorted(FILES)
    assert len(tables) == 25
    q, lo, hi = positions(tables, 10_000, seed=3)
    got, outside = run_c(compile_driver(out), q)
    want = reference(tables, q)
    err = np.abs(got - want).max()
    print(f"max |C - torchcal| at 10^4 positions: {err:.3g} mm|deg")
    assert err <= 1e-6
    # the cross-axis tables are really in: without them the corrections differ by far more than the tolerance
    same = reference([t for t in tables if t.output_axis == t.input_axis], q)
    assert np.abs(got - same).max() > 1e-3
    # the out-of-range count: tables whose input is beyond its grid (5 tables read each axis)
    beyond = ((q < lo) | (q > hi)).sum(axis=1) * 5
    np.testing.assert_array_equal(outside, beyond)
    assert outside.max() > 0 and (outside == 0).any()


@needs_gcc
def test_out_of_range_positions_hold_the_end_values(tmp_path, tables):
    write = quiet(write_linuxcnc_volumetric, tmp_path, tables)
    exe = compile_driver(write["header"].parent)
    q, lo, hi = positions(tables, 200, seed=5, margin=0.0)
    far = q.copy()
    far[:100] = lo - 1000.0 - q[:100]          # far below every axis
    far[100:] = hi + 1000.0 + q[100:]          # far above
    got, outside = run_c(exe, far)
    at_end = run_c(exe, np.clip(far, lo, hi))[0]
    np.testing.assert_array_equal(got, at_end)  # held: exactly the value at the end of the grid
    assert np.abs(got - reference(tables, far)).max() <= 1e-9
    assert (outside == 25).all()


@needs_gcc
def test_a_changed_table_changes_the_c_output(tmp_path, tables):
    k = 40
    i = next(n for n, t in enumerate(tables) if t.name == "Z(B)")
    changed = [t for t in tables]
    t = tables[i]
    bumped = t.correction.clone()
    bumped[k] += 0.01e-3                        # 0.01 mm more at node k of Z(B)
    changed[i] = type(t)(t.output_axis, t.input_axis, t.output_name, t.input_name, t.input, bumped,
                         t.output_prismatic, t.input_prismatic)
    a, b = tmp_path / "a", tmp_path / "b"
    exe_a = compile_driver(quiet(write_linuxcnc_volumetric, a, tables)["header"].parent)
    exe_b = compile_driver(quiet(write_linuxcnc_volumetric, b, changed)["header"].parent)
    q, _, _ = positions(tables, 3, seed=9, margin=0.0)
    xb, _ = t.file_units()
    q[0, t.input_axis] = float(xb[k])                              # on the node: the full 0.01 mm
    q[1, t.input_axis] = 0.5 * float(xb[k] + xb[k + 1])            # half way to the next: half of it
    q[2, t.input_axis] = float(xb[k + 3])                          # elsewhere: nothing
    da, db = run_c(exe_a, q)[0], run_c(exe_b, q)[0]
    diff = db - da
    np.testing.assert_allclose(diff[:, t.output_axis], [0.01, 0.005, 0.0], atol=1e-9)
    others = np.delete(diff, t.output_axis, axis=1)
    assert np.abs(others).max() == 0.0
    np.testing.assert_allclose(db, reference(changed, q), atol=1e-9)


def test_component_holds_the_header_code_and_wires_every_pin(tables):
    vc = volumetric_component(tables, joint_numbers={"X": 0, "Y": 1, "Z": 2, "C": 4, "B": 3})
    body = vc.header.split("#define TORCHCAL_VOLCOMP_H\n", 1)[1].rsplit("#endif", 1)[0]
    assert body in vc.comp.split(";;", 1)[1]                        # the .comp runs the code the tests compile
    assert vc.applied == [t.name for t in tables]
    for name, p, jn, unit in vc.axes:
        for pin in ("pos", "in", "out", "fb_in", "fb_out", "correction"):
            assert f" {p}_{pin} " in vc.comp
        assert f"joint.{jn}.pos-cmd         => torchcal-volcomp.{p}-pos" in vc.hal
        assert f"torchcal-volcomp.{p}-fb-out => joint.{jn}.motor-pos-fb" in vc.hal
        assert unit == ("mm" if name in "XYZ" else "deg")
    assert ("C", "c", 4, "deg") in vc.axes and "net tcvc-enable motion.is-all-homed" in vc.hal


@pytest.mark.skipif(shutil.which("halcompile") is None, reason="halcompile missing (Debian: linuxcnc-uspace-dev)")
def test_halcompile_builds_the_component(tmp_path, tables):
    comp = quiet(write_linuxcnc_volumetric, tmp_path, tables)["component"]
    r = subprocess.run(["halcompile", "--compile", comp.name], cwd=tmp_path, capture_output=True, text=True)
    assert r.returncode == 0, r.stdout + r.stderr
    assert (tmp_path / "torchcal_volcomp.so").exists()
    assert "warning" not in (r.stdout + r.stderr).lower()


def test_joint_comp_refuses_every_cross_axis_table_by_name(tmp_path, tables):
    with pytest.warns(TableNotWrittenWarning) as rec:
        written = quiet(write_linuxcnc_comp, tmp_path, tables)
    cross = [t.name for t in tables if t.output_axis != t.input_axis]
    assert len(cross) == 20 and list(written.refused) == cross
    assert sorted(written) == ["B", "C", "X", "Y", "Z"]            # 5 written + 20 refused = all 25
    msg = str(rec[0].message)
    assert all(name in msg for name in cross) and "--format linuxcnc-volumetric" in msg
    ini = (tmp_path / "linuxcnc_comp.ini").read_text()
    assert all(f"#   {name}: not written" in ini for name in cross)


def test_cli_writes_the_component_and_names_what_linuxcnc_leaves_out(tmp_path, run):
    runner = CliRunner()
    r = runner.invoke(app, ["export-tables", str(run), str(tmp_path / "v"), "--format", "linuxcnc-volumetric"])
    assert r.exit_code == 0, r.output
    assert all((tmp_path / "v" / f).exists() for f in FILES)
    assert "TableNotWritten" not in r.output and "not written" not in r.output
    r = runner.invoke(app, ["export-tables", str(run), str(tmp_path / "j"), "--format", "linuxcnc"])
    assert r.exit_code == 0, r.output
    assert "20 cross-axis table(s) not written" in r.output and "Z(B)" in r.output


HALRUN = shutil.which("halrun") and shutil.which("halcompile")


@pytest.mark.skipif(not HALRUN or os.environ.get("TORCHCAL_HAL_INSTALL") != "1",
                    reason="needs linuxcnc-uspace-dev and TORCHCAL_HAL_INSTALL=1 (installs the module, as root)")
def test_component_in_a_running_hal_matches_torchcal(tmp_path, tables):
    """Installed with ``halcompile --install`` and run in a (non-realtime) HAL: the correction pins after a
    servo cycle at 40 random positions, feedback taken off, and nothing applied while enable is off."""
    comp = quiet(write_linuxcnc_volumetric, tmp_path, tables)["component"]
    r = subprocess.run(["halcompile", "--install", comp.name], cwd=tmp_path, capture_output=True, text=True)
    assert r.returncode == 0, r.stdout + r.stderr
    vc = volumetric_component(tables)
    q, _, _ = positions(tables, 40, seed=11)
    hp = "torchcal-volcomp"
    lines = ["loadrt torchcal_volcomp", "loadrt threads name1=t1 period1=1000000",
             f"addf {hp}.update-feedback t1", f"addf {hp}.update-output t1", f"setp {hp}.enable 1",
             f"setp {hp}.x-fb-in 1.0", "start"]
    for row in q:
        lines += [f"setp {hp}.{p}-pos {v:.17g}" for (_n, p, _j, _u), v in zip(vc.axes, row)]
        lines += ["loadusr -w sleep 0.01"] + [f"getp {hp}.{p}-correction" for _n, p, _j, _u in vc.axes]
        lines += [f"getp {hp}.x-fb-out"]
    lines += [f"setp {hp}.enable 0", "loadusr -w sleep 0.01", f"getp {hp}.z-correction", f"getp {hp}.x-fb-out"]
    (tmp_path / "check.hal").write_text("\n".join(lines) + "\n")
    fifo = tempfile.mkdtemp(prefix="torchcal-rtapi-")   # rtapi_app drops root: a folder every user can enter
    os.chmod(fifo, 0o777)
    env = {**os.environ, "RTAPI_UID": str(os.getuid() or 65534), "RTAPI_FIFO_PATH": os.path.join(fifo, "rtapi")}
    try:
        r = subprocess.run(["halrun", "-f", "check.hal"], cwd=tmp_path, env=env, capture_output=True, text=True,
                           timeout=120)
    finally:
        shutil.rmtree(fifo, ignore_errors=True)
    assert r.returncode == 0, r.stdout + r.stderr
    vals = np.array([float(v) for v in r.stdout.split()])
    n = len(vc.axes)
    got = vals[:-2].reshape(len(q), n + 1)
    want = reference(tables, q)
    assert np.abs(got[:, :n] - want).max() <= 1e-6        # getp prints 7 significant digits
    np.testing.assert_allclose(got[:, n], 1.0 - want[:, 0], atol=1e-6)
    assert vals[-2] == 0.0 and vals[-1] == 1.0             # enable off: no correction, feedback passed through
