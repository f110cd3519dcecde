"""The top-level facade: ``import torchcal`` exposes the main API, stays light, and one error root covers bad input."""

import doctest
import importlib
import subprocess
import sys
from importlib import metadata

import pytest
import torch

import torchcal

F64 = torch.float64

MAIN_API = ["load_robot", "RobotModel", "read_measurements", "fit", "compensate", "NoiseModel", "Prior",
            "Measurements", "TorchcalError", "__version__", "simulate", "run_fit", "load_config", "load_model"]


def test_main_api_is_at_the_top_level():
    for name in MAIN_API:
        assert hasattr(torchcal, name), name
    for name in torchcal.__all__:
        getattr(torchcal, name)  # every advertised name resolves
    assert set(MAIN_API) <= set(torchcal.__all__) and set(MAIN_API) <= set(dir(torchcal))
    from torchcal.identify import NoiseModel, Prior, fit
    from torchcal.io.csv import read_measurements
    from torchcal.kinematics import load_robot
    from torchcal.core.measurements import Measurements
    from torchcal.models.robot import RobotModel

    assert torchcal.load_robot is load_robot and torchcal.RobotModel is RobotModel and torchcal.fit is fit
    assert torchcal.NoiseModel is NoiseModel and torchcal.Prior is Prior and torchcal.Measurements is Measurements
    assert torchcal.read_measurements is read_measurements
    with pytest.raises(AttributeError, match="no attribute 'no_such_thing'"):
        torchcal.no_such_thing


def test_compensate_is_callable_as_the_function_and_still_the_subpackage(monkeypatch):
    import inspect

    import torchcal.compensate as sub
    from torchcal.compensate import compensate, fused  # noqa: F401  the subpackage's names still import

    assert torchcal.compensate is sub is sys.modules["torchcal.compensate"]
    assert inspect.signature(torchcal.compensate) == inspect.signature(compensate)
    calls = []
    monkeypatch.setattr(sub, "compensate", lambda *a, **k: calls.append((a, k)) or "result")
    assert torchcal.compensate("model", "q", tol=1e-9) == "result"
    assert calls == [(("model", "q"), {"tol": 1e-9})]


def test_version_comes_from_the_package_metadata():
    try:
        expected = metadata.version("torchcal")
    except metadata.PackageNotFoundError:
        expected = "0+unknown"
    assert torchcal.__version__ == expected


def test_plan_poses_when_the_planner_exists():
    try:
        planning = importlib.import_module("torchcal.analysis.planning")
    except ImportError:
        pytest.skip("torchcal.analysis.planning not available")
    assert torchcal.plan_poses is planning.plan_poses


def test_import_is_light():
    """`import torchcal` (what the console script does first) loads neither torch nor the submodules,
    except torchcal.core.threads, which must set the OpenMP wait policy before torch loads."""
    code = ("import os; os.environ.pop('OMP_WAIT_POLICY', None); import sys, torchcal; "
            "print(sorted(m for m in sys.modules if m.split('.')[0] in ('torch', 'torchcal'))); "
            "print(os.environ.get('OMP_WAIT_POLICY'))")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120, check=True).stdout
    modules, policy = out.splitlines()
    assert eval(modules) == ["torchcal", "torchcal.core", "torchcal.core.exceptions", "torchcal.core.threads"]
    assert policy == "PASSIVE"


@pytest.mark.parametrize("module, cls", [("torchcal.kinematics.urdf", "URDFError"), ("torchcal.app.config", "ConfigError"),
                                         ("torchcal.io.rundir", "RunDirError"), ("torchcal.io.csv", "DataError")])
def test_every_error_is_a_torchcal_error_and_a_value_error(module, cls):
    err = getattr(importlib.import_module(module), cls)
    assert issubclass(err, torchcal.TorchcalError) and issubclass(err, ValueError)
    assert getattr(torchcal, cls) is err


def test_one_except_catches_bad_input_of_every_kind(tmp_path):
    bad_csv = tmp_path / "bad.csv"
    bad_csv.write_text("pose;tool\n0;0\n")
    robot = torchcal.load_robot("fanuc_lrmate200i")
    attempts = [
        lambda: torchcal.load_robot("no_such_robot"),
        lambda: torchcal.read_measurements(bad_csv, robot, n_tools=1),
        lambda: torchcal.load_config(tmp_path / "missing.yaml"),
        lambda: torchcal.load_model(tmp_path),
    ]
    for attempt in attempts:
        with pytest.raises(torchcal.TorchcalError):
            attempt()


def test_facade_calibrates_a_simulated_robot(fanuc, tools_m, one_thread):
    """The README's Python example through the facade alone: simulate, fit (compensation: see tests/compensate)."""
    from torchcal.sim import quasi_random_commands

    truth = torchcal.TruthRobot.fanuc_paper2(fanuc, tools_m, 0)
    noise = torchcal.NoiseModel.paper2()
    data = torchcal.simulate(truth, quasi_random_commands(fanuc.joint_map.limits, 40, 0), [0, 1, 2], noise, 0)
    assert isinstance(data, torchcal.Measurements)
    model = torchcal.RobotModel(fanuc, tools_m, orders=0, backlash=None)
    result = torchcal.fit(model, data, noise)
    assert isinstance(result, torchcal.FitResult) and result.success
    nominal = torch.linalg.norm(model.nominal_points(data.q, data.tool) - data.xyz, dim=-1).mean()
    modeled = torch.linalg.norm(model.points(data.q, data.tool) - data.xyz, dim=-1).mean()
    assert modeled < 0.5 * nominal


@pytest.mark.parametrize("module", ["torchcal.core.exceptions", "torchcal.io.csv", "torchcal.app.config", "torchcal.io.rundir",
                                    "torchcal.app.fit", "torchcal.analysis.cpa"])
def test_docstring_examples_run(module):
    result = doctest.testmod(importlib.import_module(module), optionflags=doctest.ELLIPSIS)
    assert result.failed == 0


def test_every_torchcal_exception_derives_from_torchcalerror():
    """Scan every module: an exception class defined in torchcal must be catchable as TorchcalError."""
    import importlib
    import inspect
    import pkgutil

    import torchcal

    found = []
    for info in pkgutil.walk_packages(torchcal.__path__, "torchcal."):
        if info.name.endswith("fused"):  # compiles numba kernels on import of their users only; no exceptions there
            continue
        mod = importlib.import_module(info.name)
        for _, obj in inspect.getmembers(mod, inspect.isclass):
            if obj.__module__ == mod.__name__ and issubclass(obj, BaseException):
                found.append(obj)
    assert len(found) >= 6  # URDFError, ConfigError, DataError, RunDirError, TruthError, AlignmentError, PlanningError
    bad = [c.__qualname__ for c in found if not issubclass(c, torchcal.TorchcalError)]
    assert bad == []


def test_fit_path_modules_do_not_import_scipy_stats():
    """scipy.stats costs 1-3 s to import on a 2-core machine: the modules every `torchcal fit` loads (truth
    files, the simulators' package, the pipeline) must not pull it in at import."""
    code = ("import sys, torchcal, torchcal.sim, torchcal.io.truth, torchcal.app.fit, torchcal.app.sensor; "
            "print('scipy.stats' in sys.modules)")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=300, check=True).stdout
    assert out.strip() == "False"


def test_wrong_inputs_to_the_python_api_are_named_torchcal_errors():
    """Shapes, dtypes, indices and names a researcher gets wrong: each a TorchcalError naming the call and the
    argument (torch's own messages name neither), and nothing silently taken."""
    import numpy as np
    import pytest
    import torch

    import torchcal
    from torchcal.core.exceptions import InputError

    robot = torchcal.load_robot("fanuc_lrmate200i")
    model = torchcal.RobotModel(robot, torch.zeros(2, 3, dtype=torch.float64), orders=1)
    tool = torch.zeros(4, dtype=torch.long)
    for q, said in ((torch.zeros(4, 5, dtype=torch.float64), "(B, 6) commands, got shape (4, 5)"),
                    (torch.zeros(6, dtype=torch.float64), "q[None] makes one pose a batch"),
                    (torch.zeros(4, 6, dtype=torch.float32), "q is torch.float32, the model torch.float64"),
                    (np.zeros((4, 6)), "got ndarray")):
        with pytest.raises(InputError, match=r"RobotModel\.points: ") as err:
            model.points(q, tool)
        assert said in str(err.value)
    with pytest.raises(torchcal.TorchcalError, match="tool indices must be >= 0"):
        torchcal.Measurements.from_tensors(torch.zeros(4, 6), tool=-1)
    with pytest.raises(torchcal.TorchcalError, match="direction must be -1, 0 or \\+1, got 2.0 at row 0, joint 1"):
        torchcal.Measurements.from_tensors(torch.zeros(4, 6), tool=0, direction=torch.full((4, 6), 2.0))
    with pytest.raises(torchcal.TorchcalError, match="direction must have q's shape"):
        torchcal.Measurements.from_tensors(torch.zeros(4, 6), tool=0, direction=torch.ones(4, 5))
    with pytest.raises(torchcal.TorchcalError, match="compensate: q_nom must be a \\(B, 6\\)"):
        torchcal.compensate(model, torch.zeros(4, 5, dtype=torch.float64))
    # a misspelt group to hold fixed would fit what the user meant to hold: refused, the valid names listed
    data = torchcal.Measurements.from_tensors(torch.zeros(4, 6, dtype=torch.float64), tool=0,
                                              xyz=torch.zeros(4, 3, dtype=torch.float64))
    with pytest.raises(torchcal.TorchcalError, match="fixed: 'tool' names no parameter group.*tools"):
        torchcal.fit(model, data, fixed=("tool",))


def test_measurements_repr_is_a_summary():
    """A notebook's repr of 100 000 rows is one line, not every tensor."""
    import torch

    m = torchcal.Measurements.from_tensors(torch.zeros(100000, 6), tool=torch.arange(100000) % 3,
                                           direction=torch.ones(100000, 6), source="ident.csv")
    text = repr(m)
    assert text == ("Measurements(100000 rows, 100000 poses, 6 joints, tools [0, 1, 2], directions yes, torch.float64, "
                    "cpu, source 'ident.csv')")
