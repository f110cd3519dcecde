"""The calibrated URDF's constants: fitted to the full model (constants='fit') rather than its c0 coefficients.

c0 is not the best constant of a joint-dependent series: Chebyshev T_k of even k has a nonzero mean over the
range, so a model whose c0 carries the even terms' means writes a URDF worse than the nominal robot. The model
below is built that way (a real constant part, plus even terms whose mean c0 cancels).
"""

import pytest
import torch
from typer.testing import CliRunner

from conftest import random_commands, randomize
from torchcal.cli import app
from torchcal.core.measurements import Measurements
from torchcal.export import c0_model, compare_urdf, constant_projection, export_urdf, projection_commands, projection_misfit
from torchcal.models.robot import RobotModel

EVEN_SHAPE = torch.tensor([-2.594, -1.635, -0.932])
"""c2, c4, c6 of the even series with the smallest spread around its mean over [-1, 1] (per unit mean)."""


def even_heavy_model(robot, tools_m, seed, amp=1.5e-3, const=1e-3):
    """Order 6: small random errors, a constant part (rad / 10 m per rad), and per term an even series of
    mean ``amp`` (rad; lengths amp / 10 m) whose mean c0 cancels: the identified c0 is not the constant."""
    m = randomize(RobotModel(robot, tools_m, orders=6, backlash=False), seed, rot=1e-4, trans=1e-5)
    g = torch.Generator().manual_seed(seed + 1000)
    je = m.joint_errors
    scale = torch.tensor([1.0] * 3 + [0.1] * 3)
    with torch.no_grad():
        a = torch.randn(robot.n, 6, generator=g) * scale * amp
        je.coef[..., 2::2] = a[..., None] * EVEN_SHAPE
        je.coef[..., 0] += -a + torch.randn(robot.n, 6, generator=g) * scale * const
    return m


def held_out(model, robot, count, seed):
    """Points of ``model`` at uniformly random commands (not the projection's Sobol ones), every tool in turn."""
    q = random_commands(robot, count, seed)
    tool = torch.arange(count) % model.tools.count
    with torch.no_grad():
        xyz = model.points(q, tool)
    return Measurements.from_tensors(q, tool, xyz)


def rms(x):
    return float(x.square().mean().sqrt())


def test_fit_beats_c0_and_nominal_on_held_out_commands(tmp_path, fanuc, tools_m):
    model = even_heavy_model(fanuc, tools_m, 3)
    data = held_out(model, fanuc, 240, 17)
    out = {c: export_urdf(model, tmp_path / f"{c}.urdf", constants=c, count=128) for c in ("c0", "fit")}
    cmp = {c: compare_urdf(model, e, data) for c, e in out.items()}
    nominal = cmp["fit"].nominal
    assert cmp["fit"].full.max < 1e-9
    # the bug this guards against: c0 alone is worse than doing nothing
    assert cmp["c0"].urdf.mean > 1.2 * nominal.mean
    assert rms(cmp["c0"].residuals_mm["urdf"]) > rms(cmp["c0"].residuals_mm["nominal"])
    # the projection is better than both, in mean and RMS (README: nominal 2.93, c0 4.30, fit 2.36 mm mean)
    assert cmp["fit"].urdf.mean < 0.85 * nominal.mean
    assert cmp["fit"].urdf.mean < 0.6 * cmp["c0"].urdf.mean
    assert rms(cmp["fit"].residuals_mm["urdf"]) < rms(cmp["fit"].residuals_mm["nominal"])
    # what the export says about itself: the misfit at its own commands, smaller for the fit (least squares)
    assert out["fit"].constants == "fit" and out["c0"].constants == "c0" and out["fit"].commands == 128
    assert out["fit"].misfit_rms_mm < 0.7 * out["c0"].misfit_rms_mm
    assert out["fit"].misfit_max_mm >= out["fit"].misfit_rms_mm > 0.5
    # the written file is the projection: its URDF-only model predicts what the projection model predicts
    m0 = out["fit"].model
    p_urdf = cmp["fit"].residuals_mm["urdf"]
    with torch.no_grad():
        p_m0 = (m0.points(data.q, data.tool) - data.xyz).norm(dim=1) * 1e3
    assert torch.allclose(p_urdf, p_m0, atol=1e-9, rtol=0)


def test_projection_is_least_squares_at_its_commands(fanuc, tools_m):
    """No constant change lowers the misfit at the projection commands (a stationary point), and the tool
    vectors are the full model's, untouched."""
    model = even_heavy_model(fanuc, tools_m, 5)
    q = projection_commands(fanuc, 64, seed=2)
    m0 = constant_projection(model, q)
    rms0 = projection_misfit(model, m0, q)[0]
    assert rms0 < projection_misfit(model, c0_model(model), q)[0]
    g = torch.Generator().manual_seed(0)
    for _ in range(4):
        trial = constant_projection(model, q)
        with torch.no_grad():
            trial.joint_errors.coef.add_(torch.randn(trial.joint_errors.coef.shape, generator=g) * 1e-5)
            trial.base.twist.add_(torch.randn(6, generator=g) * 1e-5)
        assert projection_misfit(model, trial, q)[0] > rms0
    assert torch.equal(m0.tools(), model.tools()) and m0.tools.delta.abs().max() == 0
    assert m0.joint_errors.coef.shape[-1] == 1 and not m0.joint_errors.has_backlash
    # base=False keeps the model's base correction
    assert torch.equal(constant_projection(model, q, base=False).base.twist, model.base.twist)


@pytest.mark.parametrize("base", ["joint", "link"])
def test_order_zero_model_round_trips(tmp_path, fanuc, tools_m, base):
    """Known truth: an order-0 model (tool corrections included) is its own best constant; the URDF alone
    reproduces it."""
    model = randomize(RobotModel(fanuc, tools_m, orders=0, backlash=False), 21, rot=3e-3, trans=3e-4)
    assert model.tools.delta.abs().max() > 1e-5
    out = export_urdf(model, tmp_path / "cal.urdf", base=base, count=64)
    assert out.misfit_max_mm < 1e-6
    assert torch.allclose(out.model.joint_errors.coef[..., 0], model.joint_errors.coef[..., 0], atol=1e-10, rtol=0)
    data = held_out(model, fanuc, 60, 22)
    cmp = compare_urdf(model, out, data)
    assert cmp.urdf.max < 1e-6 and cmp.nominal.mean > 0.5


def _run_dir(tmp_path, model, robot):
    from torchcal.app.config import make_config, to_yaml
    from torchcal.io.csv import write_measurements
    from torchcal.io.rundir import save_model

    run = tmp_path / "run"
    run.mkdir()
    save_model(run, model)
    write_measurements(tmp_path / "ident.csv", held_out(model, robot, 60, 31), robot)
    write_measurements(tmp_path / "val.csv", held_out(model, robot, 90, 32), robot)
    cfg = make_config({"robot": "fanuc_lrmate200i", "tools": (model.tools.nominal * 1e3).tolist(),
                       "data": {"identification": str(tmp_path / "ident.csv"), "validation": str(tmp_path / "val.csv")}})
    (run / "config.yaml").write_text(to_yaml(cfg))
    return run


def test_cli_export_urdf(tmp_path, fanuc, tools_m):
    model = even_heavy_model(fanuc, tools_m, 3)
    run = _run_dir(tmp_path, model, fanuc)
    runner = CliRunner()
    out = tmp_path / "out" / "cal.urdf"
    r = runner.invoke(app, ["export-urdf", str(run), str(out)])
    assert r.exit_code == 0, r.output
    assert out.is_file() and out.with_suffix(".yaml").is_file()
    assert "validation data" in r.output and str(tmp_path / "val.csv") in r.output
    for label in ("Nominal", "URDF alone", "Full model"):
        assert label in r.output
    assert "warning" not in r.output
    # the numbers printed are compare_urdf's on the validation set
    from torchcal.io.csv import read_measurements
    from torchcal.io.rundir import load_model
    from torchcal.kinematics import load_robot

    loaded = load_model(run)
    val = read_measurements(tmp_path / "val.csv", fanuc, 3)
    # the constants are fitted at the identification data's poses (each once), where the model is known
    import pandas as pd

    poses = pd.read_csv(tmp_path / "ident.csv").drop_duplicates("pose")
    q_ident = torch.deg2rad(torch.tensor(poses[[f"q{i}" for i in range(1, 7)]].to_numpy()))
    assert f"at {q_ident.shape[0]} commands (the identification data's poses)" in r.output
    cmp = compare_urdf(loaded, export_urdf(loaded, tmp_path / "again.urdf", commands=q_ident), val)
    assert f"{cmp.urdf.mean:.4f}" in r.output and f"{cmp.nominal.mean:.4f}" in r.output
    # the joint map goes beside the URDF under its stem: a YAML there that is no joint map (the user's fit
    # config) is never replaced, --force or not
    cfg = tmp_path / "out" / "mine.yaml"
    cfg.write_text("robot: fanuc_lrmate200i\ndata: {identification: ident.csv}\n")
    r = runner.invoke(app, ["export-urdf", str(run), str(cfg.with_suffix(".urdf")), "--force"])
    assert r.exit_code == 2 and "is no joint map" in r.output and "mine_calibrated.urdf" in " ".join(r.output.split())
    assert cfg.read_text().startswith("robot: fanuc_lrmate200i") and not cfg.with_suffix(".urdf").exists()
    assert load_robot(out.with_suffix(".yaml")).chain.joint_names == fanuc.chain.joint_names
    # an existing output is refused without --force, and left alone
    before = out.read_text()
    r = runner.invoke(app, ["export-urdf", str(run), str(out), "--constants", "c0"])
    assert r.exit_code == 2 and "already exists" in r.output and "--force" in r.output
    assert out.read_text() == before
    # --force with c0: replaced, and the URDF alone is worse than the nominal robot: said
    r = runner.invoke(app, ["export-urdf", str(run), str(out), "--constants", "c0", "--force", "--base", "link"])
    assert r.exit_code == 0, r.output
    assert out.read_text() != before
    assert "warning: the URDF alone is worse than the nominal robot" in " ".join(r.output.split())
    # bad options and outputs are user errors
    r = runner.invoke(app, ["export-urdf", str(run), str(tmp_path / "x.urdf"), "--constants", "c1"])
    assert r.exit_code == 2 and "--constants" in r.output
    r = runner.invoke(app, ["export-urdf", str(run), str(tmp_path / "x.yaml")])
    assert r.exit_code == 2 and ".urdf" in r.output


def test_projection_commands_stay_in_the_data_span(fanuc, tools_m):
    """A model that records its identification data's span is projected there (a series extrapolates beyond
    it); one that records none, over the joint limits."""
    model = RobotModel(fanuc, tools_m, orders=2)
    lim = fanuc.joint_map.limits
    q = projection_commands(fanuc, 256, 0, model=model)
    assert bool(((q >= lim[:, 0]) & (q <= lim[:, 1])).all())
    spread = (q.amax(0) - q.amin(0)) / (lim[:, 1] - lim[:, 0])
    assert float(spread.min()) > 0.9  # no span recorded: the whole range
    data_q = random_commands(fanuc, 40, 3) * 0.3
    model.record_data_span(data_q)
    q = projection_commands(fanuc, 256, 0, model=model)
    outside = model.outside_data(q)
    assert not bool(outside.any())
    span = model.data_span
    u = model.error_variables(q)
    assert bool(((u.amax(0) - u.amin(0)) > 0.9 * (span[:, 1] - span[:, 0])).all())  # and it fills it
