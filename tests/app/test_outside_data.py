"""Rows beyond the identification data's range: `torchcal predict` and `torchcal compensate` mark them
('outside_data') and say how many, since the model's error series are extrapolated there."""

import numpy as np
import pandas as pd
import pytest
from typer.testing import CliRunner

from torchcal.cli import app
from torchcal.io.rundir import load_model

runner = CliRunner()
pytestmark = pytest.mark.usefixtures("one_thread")


@pytest.fixture(scope="module")
def run(tmp_path_factory, one_thread):
    root = tmp_path_factory.mktemp("outside")
    r = runner.invoke(app, ["simulate", str(root / "sim"), "--identification", "30", "--validation", "40", "--seed", "3"])
    assert r.exit_code == 0, r.output
    r = runner.invoke(app, ["fit", str(root / "sim" / "fit.yaml"), "model.order=1", "plots=false", "report=false",
                            "data.truth=null", f"out={root / 'run'}", "-q"])
    assert r.exit_code == 0, r.output
    return root


def _expected(root, name):
    """Independently of the model: any joint of the row beyond the identification file's min / max."""
    ident = pd.read_csv(root / "sim" / "identification.csv")
    rows = pd.read_csv(root / "sim" / name)
    q = [f"q{i}" for i in range(1, 7)]
    return ((rows[q] < ident[q].min()) | (rows[q] > ident[q].max())).any(axis=1).to_numpy()


def test_the_run_keeps_its_data_range(run):
    ident = pd.read_csv(run / "sim" / "identification.csv")
    span = np.degrees(load_model(run / "run").data_span.numpy())
    q = [f"q{i}" for i in range(1, 7)]
    assert np.allclose(span[:, 0], ident[q].min().to_numpy(), atol=1e-9)
    assert np.allclose(span[:, 1], ident[q].max().to_numpy(), atol=1e-9)


def test_predict_and_compensate_mark_the_rows_beyond_it(run, tmp_path):
    want = _expected(run, "validation.csv")
    assert 0 < want.sum() < len(want)  # 30 poses do not span the 40 others: some rows lie beyond
    r = runner.invoke(app, ["predict", str(run / "run"), str(run / "sim" / "validation.csv"), str(tmp_path / "p.csv")])
    assert r.exit_code == 0, r.output
    got = pd.read_csv(tmp_path / "p.csv").outside_data.to_numpy()
    assert (got == want).all()
    assert f"{int(want.sum())} of {len(want)} rows put a joint beyond the identification data's range" in " ".join(
        r.output.split())
    r = runner.invoke(app, ["compensate", str(run / "run"), str(run / "sim" / "validation.csv"),
                            str(tmp_path / "c.csv")])
    assert r.exit_code == 0, r.output
    # compensate judges the command the model is evaluated at: the compensated one (the FANUC's error series
    # follow the commands, so its error variables are the q columns written)
    comp = pd.read_csv(tmp_path / "c.csv")
    ident = pd.read_csv(run / "sim" / "identification.csv")
    q = [f"q{i}" for i in range(1, 7)]
    at_new = ((comp[q] < ident[q].min()) | (comp[q] > ident[q].max())).any(axis=1).to_numpy()
    assert (comp.outside_data.to_numpy() == at_new).all() and at_new.any()
    assert "beyond the identification data's range" in " ".join(r.output.split())
    # the identification rows themselves are never beyond it, and nothing is said
    r = runner.invoke(app, ["predict", str(run / "run"), str(run / "sim" / "identification.csv"), str(tmp_path / "i.csv")])
    assert r.exit_code == 0 and not pd.read_csv(tmp_path / "i.csv").outside_data.any()
    assert "beyond the identification" not in r.output


def test_predict_says_when_a_backlash_model_gets_no_directions(run, tmp_path):
    val = pd.read_csv(run / "sim" / "validation.csv")
    val.drop(columns=[f"dir{i}" for i in range(1, 7)]).to_csv(tmp_path / "nodir.csv", index=False)
    r = runner.invoke(app, ["predict", str(run / "run"), str(tmp_path / "nodir.csv"), str(tmp_path / "p.csv")])
    said = " ".join(r.output.split())
    assert r.exit_code == 0 and "nodir.csv: no dir1..dir6 columns: the model's backlash terms are left out" in said
    r = runner.invoke(app, ["predict", str(run / "run"), str(run / "sim" / "validation.csv"), str(tmp_path / "q.csv")])
    assert "backlash terms are left out" not in r.output


def test_joints_whose_errors_follow_theta_are_judged_on_theta(tmp_path):
    """With error_variable 'joint' the FANUC's J3 series runs on θ3 = q2 + q3: a row whose q2 and q3 each lie
    within the data but whose sum does not is outside."""
    import torch

    from torchcal.kinematics import load_robot
    from torchcal.models.robot import RobotModel

    robot = load_robot("fanuc_lrmate200i")
    model = RobotModel(robot, torch.zeros(1, 3, dtype=torch.float64), orders=1, error_variable="joint")
    g = torch.Generator().manual_seed(0)
    q = torch.rand(50, 6, generator=g, dtype=torch.float64) * 0.6 - 0.3  # rad, every joint within +-0.3
    q[:, 2] = -q[:, 1] + 0.05 * q[:, 2]  # q2 and q3 each span +-0.3, their sum stays near 0
    model.record_data_span(q)
    inside_each = torch.tensor([[0.0, 0.2, 0.2, 0.0, 0.0, 0.0]], dtype=torch.float64)  # sum 0.4
    assert bool((inside_each >= q.amin(0)).all() and (inside_each <= q.amax(0)).all())
    out = model.outside_data(inside_each)
    assert out[0].tolist() == [False, False, True, False, False, False]
