"""The examples in the public docstrings run and print what they say (kornia-style sectioned docstrings)."""

import doctest
import importlib

import pytest

MODULES = [
    "torchcal.core.exceptions",
    "torchcal.core.params",
    "torchcal.kinematics.robot",
    "torchcal.models.robot",
    "torchcal.error_models.joint",
    "torchcal.core.measurements",
    "torchcal.identify.fit",
    "torchcal.identify.problem",
    "torchcal.compensate.newton",
    "torchcal.sim.measure",
    "torchcal.sim.truth",
    "torchcal.analysis.planning",
    "torchcal.analysis.identifiability",
    "torchcal.analysis.cpa",
    "torchcal.io.csv",
    "torchcal.app.config",
    "torchcal.io.rundir",
    "torchcal.measure.tracker",
    "torchcal.measure.triangle",
    "torchcal.analysis.orientation",
    "torchcal.models.sensor_rig",
    "torchcal.measure.sts",
    "torchcal.measure.pose",
    "torchcal.io.sensor_csv",
    "torchcal.measure.gravity",
    "torchcal.identify.hand_eye",
    "torchcal.identify.online",
    "torchcal.sim.sensor_truth",
    "torchcal.sim.machine_truth",
    "torchcal.compensate.tables",
    "torchcal.compensate.toolset",
    "torchcal.export.controller",
    "torchcal.analysis.border",
    "torchcal.core.progress",
]


@pytest.mark.parametrize("name", MODULES)
def test_docstring_examples(name):
    mod = importlib.import_module(name)
    res = doctest.testmod(mod, optionflags=doctest.ELLIPSIS | doctest.NORMALIZE_WHITESPACE, verbose=False)
    assert res.failed == 0
    assert res.attempted > 0  # each listed module has at least one example


def _facade_names():
    import torchcal

    return [n for n in torchcal.__all__ if n != "__version__"]


@pytest.mark.parametrize("name", _facade_names())
def test_facade_examples_run_as_copied(name):
    """A user copies an example from a facade name's docstring: only what the example imports (and the name
    itself) may be used, not the defining module's globals (which testmod above lends them)."""
    import torchcal

    obj = getattr(torchcal, name)
    if name == "compensate":
        obj = torchcal.compensate.compensate
    finder = doctest.DocTestFinder(recurse=False)
    runner = doctest.DocTestRunner(optionflags=doctest.ELLIPSIS | doctest.NORMALIZE_WHITESPACE)
    for test in finder.find(obj, name, globs={name: obj}):
        if test.examples:
            runner.run(test, out=lambda s: None)
    assert runner.summarize(verbose=False).failed == 0
