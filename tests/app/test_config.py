"""Configs: defaults, overrides, path resolution, and unknown keys rejected with file and key named."""

import os
from pathlib import Path

import pytest

from torchcal.app.config import (ConfigError, check_config, load_config, make_config, repeated_overrides,
                                 unused_overrides)

MINIMAL = """\
robot: fanuc_lrmate200i
tools:
  - [33.06, 57.73, 161.22]
  - [57.26, -33.86, 161.22]
data:
  identification: data/ident.csv
model:
  order: 3
"""


@pytest.fixture
def cfg_file(tmp_path):
    folder = tmp_path / "exp"
    folder.mkdir()
    p = folder / "fit.yaml"
    p.write_text(MINIMAL)
    return p


def test_defaults_and_relative_paths(cfg_file):
    cfg = load_config(cfg_file)
    assert cfg.model.order == 3
    assert cfg.model.backlash is True
    # joint variances default to null: the robot's repeatability (pipeline.config_noise), not one robot's table
    assert cfg.noise.joint_var_fwd is None and cfg.noise.joint_var_bwd is None
    assert cfg.model.error_variable is None
    assert cfg.noise.sigma_m == 0.005
    assert cfg.solver.method == "lm"
    # paths written in the file resolve against the file's folder, not the working directory
    assert Path(cfg.data.identification) == cfg_file.parent.resolve() / "data" / "ident.csv"
    assert Path(cfg.out) == cfg_file.parent.resolve() / "runs"
    assert cfg.robot == "fanuc_lrmate200i"  # a bundled name is not a path
    assert cfg.data.validation is None
    assert cfg.config_file == str(cfg_file.resolve())


def test_overrides_are_applied(cfg_file, tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)
    cfg = load_config(cfg_file, ["model.order=[1,2,3,4,5,6]", "solver.method=lbfgs", "noise.sigma_m=0.01",
                                 "data.validation=val.csv", "model.backlash=false", "seed=7", "solver.max_iter=5"])
    assert list(cfg.model.order) == [1, 2, 3, 4, 5, 6]
    assert cfg.solver.method == "lbfgs" and cfg.solver.max_iter == 5
    assert cfg.noise.sigma_m == 0.01
    assert cfg.model.backlash is False
    assert cfg.seed == 7
    # an override path is a shell argument: relative to the current directory
    assert Path(cfg.data.validation) == tmp_path.resolve() / "val.csv"
    assert load_config(cfg_file, ["model.order=auto"]).model.order == "auto"


def test_unknown_key_in_file_names_key_and_file(cfg_file):
    cfg_file.write_text(MINIMAL + "  ordr: 4\n")
    with pytest.raises(ConfigError) as err:
        load_config(cfg_file)
    msg = str(err.value)
    assert str(cfg_file) in msg and "model.ordr" in msg
    assert "valid keys under model: order, backlash" in msg

    cfg_file.write_text(MINIMAL + "learning_rate: 3\n")
    with pytest.raises(ConfigError, match=r"fit\.yaml: unknown config key 'learning_rate'"):
        load_config(cfg_file)


def test_unknown_key_in_override_names_override(cfg_file):
    with pytest.raises(ConfigError) as err:
        load_config(cfg_file, ["model.order=2", "solver.maxiter=10"])
    msg = str(err.value)
    assert "override 'solver.maxiter=10'" in msg and "unknown config key 'solver.maxiter'" in msg
    with pytest.raises(ConfigError, match="expected key=value"):
        load_config(cfg_file, ["model.order"])


@pytest.mark.parametrize("override, key", [
    ("seed=abc", "seed"),
    ("model.order=11", "model.order"),
    ("model.order=six", "model.order"),
    ("solver.method=adam", "solver.method"),
    ("noise.sigma_m=0", "noise.sigma_m"),
    ("tools=[[1,2]]", "tools"),
    ("model.backlash=maybe", "model.backlash"),
    ("model.compliance=sometimes", "model.compliance"),
    ("model.folds=1", "model.folds"),
    ("model.folds=-2", "model.folds"),
    ("model.margin=-1", "model.margin"),
])
def test_bad_values_name_the_key(cfg_file, override, key):
    with pytest.raises(ConfigError, match=f"key '{key}'"):
        load_config(cfg_file, [override])


@pytest.mark.parametrize("override, key", [("model.order=11", "model.order"), ("fleet.cell=0", "fleet.cell"),
                                           ("noise.sigma_m=0", "noise.sigma_m"), ("model={order: 12}", "model.order")])
def test_a_bad_value_from_an_override_names_the_override_not_the_file(cfg_file, override, key):
    """The file holds a valid value; the message must send the user to the command line, where the bad one is."""
    with pytest.raises(ConfigError) as err:
        load_config(cfg_file, ["seed=1", override])
    assert str(err.value).startswith(f"override '{override}' (over {cfg_file}): key '{key}'")
    # the same bad value written in the file names the file
    cfg_file.write_text(MINIMAL.replace("order: 3", "order: 11"))
    with pytest.raises(ConfigError) as err:
        load_config(cfg_file, ["seed=1"])
    line = MINIMAL.splitlines().index("  order: 3") + 1  # the file's own line of the key
    assert str(err.value).startswith(f"{cfg_file}, line {line}: key 'model.order'")


def test_repeated_overrides_are_said_and_the_last_one_wins(cfg_file):
    items = ["model.order=3", "seed=2", "model.order=4", "model.order=5"]
    assert load_config(cfg_file, items).model.order == 5
    said = repeated_overrides(items)
    assert len(said) == 1 and "'model.order' is given 3 times" in said[0] and "'model.order=5'" in said[0]
    assert repeated_overrides(["model.order=3", "model.backlash=false", "seed=1"]) == []


def test_a_key_under_a_whole_value_key_replaces_a_list_or_a_word(cfg_file):
    """tools.count=3 over listed tool vectors switches to estimated tools, as {count: 3} in the file does; the
    frame's two keys given one by one over 'auto' build the mapping; a flow mapping without the space says so."""
    cfg = load_config(cfg_file, ["tools.count=3"])
    assert dict(cfg.tools) == {"count": 3}
    cfg = load_config(cfg_file, ["measurement_frame.xyz_mm=[1000,0,0]", "measurement_frame.rpy_deg=[0,0,90]"])
    assert cfg.measurement_frame == {"xyz_mm": (1000, 0, 0), "rpy_deg": (0, 0, 90)}
    with pytest.raises(ConfigError, match=r"^override 'measurement_frame.xyz_mm=\[1000,0,0\]' .*rpy_deg"):
        load_config(cfg_file, ["measurement_frame.xyz_mm=[1000,0,0]"])
    with pytest.raises(ConfigError, match=r"put a space after the colon \('\{count: 3\}'\)"):
        load_config(cfg_file, ["tools={count:3}"])


def test_a_config_not_in_utf8_names_the_file_and_line(cfg_file):
    cfg_file.write_bytes((MINIMAL + "# r\xe9glage de l'atelier\n").encode("latin-1"))
    line = MINIMAL.count("\n") + 1  # the comment after the file's lines
    with pytest.raises(ConfigError, match=rf"fit\.yaml: not a UTF-8 text file \(byte 0xe9 at line {line}\)"):
        load_config(cfg_file)


def test_override_mistakes_get_plain_words(cfg_file):
    """A misspelt key names the one meant; a section given one value and an empty value say what they are, not
    OmegaConf's internals (a merge error on '_ParsedDataConfig', 'Incompatible value None')."""
    with pytest.raises(ConfigError, match=r"unknown config key 'solver.max_itr' \(did you mean 'solver.max_iter'\?\)"):
        load_config(cfg_file, ["solver.max_itr=5"])
    with pytest.raises(ConfigError, match=r"'model.max_iter' \(did you mean one of 'solver.max_iter', "
                                          r"'compensation.max_iter'\?\)"):
        load_config(cfg_file, ["model.max_iter=5"])  # the right name in other sections
    with pytest.raises(ConfigError, match=r"'data.threshold' \(did you mean 'fleet.threshold'\?\)"):
        load_config(cfg_file, ["data.threshold=5"])
    with pytest.raises(ConfigError) as err:
        load_config(cfg_file, ["learnign_rate=3"])
    assert "did you mean" not in str(err.value) and "config_file" not in str(err.value)  # nothing close; no internals
    with pytest.raises(ConfigError, match=r"key 'data' is a section of keys \(identification, .*e\.g\. data\.identification="):
        load_config(cfg_file, ["data=foo"])
    with pytest.raises(ConfigError, match=r"override 'out=': key 'out': needs a value"):
        load_config(cfg_file, ["out="])
    assert load_config(cfg_file, ["solver={max_iter: 5}"]).solver.max_iter == 5  # a mapping for a section is fine


def test_order_selection_keys(cfg_file):
    assert load_config(cfg_file, []).model.folds == 0  # leave one pose out by default
    cfg = load_config(cfg_file, ["model.folds=5", "model.margin=0"])
    assert cfg.model.folds == 5 and cfg.model.margin == 0


def test_required_keys_and_per_joint_lengths(cfg_file, tmp_path):
    with pytest.raises(ConfigError, match="key 'robot': is required"):
        make_config({"tools": [[0, 0, 0.1]], "data": {"identification": "x.csv"}})
    cfg = load_config(cfg_file, ["model.order=[1,2,3]"])
    with pytest.raises(ConfigError, match=r"key 'model.order': has 3 entries but the robot has 6 joints"):
        check_config(cfg, str(cfg_file), n_joints=6)
    cfg = load_config(cfg_file, ["noise.joint_var_fwd=[1e-6,1e-6,1e-6,1e-6,1e-6,1e-6]", "noise.joint_var_bwd=[1e-6,1e-6]"])
    with pytest.raises(ConfigError, match=r"key 'noise.joint_var_bwd': has 2 entries"):
        check_config(cfg, str(cfg_file), n_joints=6)


def test_robot_file_paths_resolve_against_config(cfg_file):
    cfg_file.write_text(MINIMAL.replace("robot: fanuc_lrmate200i", "robot: ../robots/my_robot.yaml"))
    cfg = load_config(cfg_file)
    assert Path(cfg.robot) == (cfg_file.parent / ".." / "robots" / "my_robot.yaml").resolve()


def test_yaml_syntax_error_names_line(cfg_file):
    cfg_file.write_text("robot: [unclosed\ntools: 1\n")
    with pytest.raises(ConfigError, match=r"fit\.yaml: not valid YAML at line"):
        load_config(cfg_file)
    with pytest.raises(ConfigError, match="config file not found"):
        load_config(cfg_file.parent / "missing.yaml")
    assert os.path.exists(cfg_file)


def test_example_config_loads():
    """experiments/paper2_fanuc/fit.yaml stays valid against the schema (every key known, values checked)."""
    path = Path(__file__).resolve().parents[2] / "experiments" / "paper2_fanuc" / "fit.yaml"
    cfg = load_config(path)
    check_config(cfg, str(path), n_joints=6)
    assert cfg.model.order == 6 and cfg.robot == "fanuc_lrmate200i"
    assert Path(cfg.data.validation).name == "validation.csv"


def test_unknown_tools_and_measurement_frame(cfg_file):
    """tools: {count: T} and measurement_frame: auto / base / estimate / {xyz_mm, rpy_deg}; overrides replace them."""
    import torch

    from torchcal.app.fit import config_frame, config_tool_count, config_tools

    cfg = load_config(cfg_file)
    assert cfg.measurement_frame == "auto" and config_tool_count(cfg) == 2
    mode, frame = config_frame(cfg)  # tools listed: Paper II's tracker at the robot base
    assert mode == "base" and torch.equal(frame, torch.eye(4, dtype=torch.float64))
    assert torch.allclose(config_tools(cfg), torch.tensor([[33.06, 57.73, 161.22], [57.26, -33.86, 161.22]]) * 1e-3)

    cfg_file.write_text(MINIMAL.replace("tools:\n  - [33.06, 57.73, 161.22]\n  - [57.26, -33.86, 161.22]\n",
                                        "tools: {count: 3}\n"))
    cfg = load_config(cfg_file)
    assert config_tools(cfg) is None and config_tool_count(cfg) == 3
    assert config_frame(cfg) == ("estimate", None)  # auto: unknown tools -> estimate the frame too
    assert config_frame(load_config(cfg_file, ["measurement_frame=base"]))[0] == "base"

    # a given frame: the robot base seen in the tracker frame, p = Rot(rpy) p_base + xyz
    cfg = load_config(cfg_file, ["measurement_frame={xyz_mm: [1000, -500, 250], rpy_deg: [0, 0, 90]}"])
    mode, frame = config_frame(cfg)
    p = frame @ torch.tensor([0.2, 0.0, 0.0, 1.0], dtype=torch.float64)
    assert mode == "given" and torch.allclose(p[:3], torch.tensor([1.0, -0.3, 0.25], dtype=torch.float64), atol=1e-15)
    # overrides replace a list by a mapping and back
    cfg = load_config(cfg_file, ["tools=[[0, 0, 100]]", "measurement_frame=estimate"])
    assert config_tool_count(cfg) == 1 and config_frame(cfg) == ("estimate", None)
    assert config_tool_count(load_config(cfg_file, ["tools.count=4"])) == 4


@pytest.mark.parametrize("override, key", [
    ("tools={count: 0}", "tools.count"),
    ("tools={cnt: 3}", "tools.cnt"),
    ("tools=5", "tools"),
    ("tools=[[1,2,x]]", "tools"),
    ("measurement_frame=far", "measurement_frame"),
    ("measurement_frame=null", "measurement_frame"),
    ("measurement_frame={xyz_mm: [1, 2]}", "measurement_frame.xyz_mm"),
    ("measurement_frame={xyz_mm: [1, 2, 3], rpy_deg: [0, 0, 0], scale: 1}", "measurement_frame.scale"),
])
def test_bad_tools_and_frames_name_the_key(cfg_file, override, key):
    with pytest.raises(ConfigError, match=f"key '{key}'"):
        load_config(cfg_file, [override])


def test_joint_variances_both_or_neither_and_error_variable(cfg_file):
    with pytest.raises(ConfigError, match=r"key 'noise.joint_var_bwd': is null but noise.joint_var_fwd is set"):
        load_config(cfg_file, ["noise.joint_var_fwd=[1,1,1,1,1,1]"])
    cfg = load_config(cfg_file, ["noise.joint_var_fwd=[1,1,1,1,1,1]", "noise.joint_var_bwd=[2,2,2,2,2,2]"])
    check_config(cfg, str(cfg_file), n_joints=6)
    assert load_config(cfg_file, ["model.error_variable=joint"]).model.error_variable == "joint"
    with pytest.raises(ConfigError, match=r"key 'model.error_variable': 'encoder'"):
        load_config(cfg_file, ["model.error_variable=encoder"])
    cfg = load_config(cfg_file, ["model.error_variable=[joint,command]"])
    with pytest.raises(ConfigError, match=r"key 'model.error_variable': has 2 entries but the robot has 6 joints"):
        check_config(cfg, str(cfg_file), n_joints=6)


def test_config_error_is_a_torchcal_error():
    from torchcal.core.exceptions import TorchcalError

    assert issubclass(ConfigError, TorchcalError) and issubclass(ConfigError, ValueError)


SENSOR = """\
robot: fanuc_lrmate200i
data:
  identification: data/ident.csv
sensor:
  kind: sts
"""


@pytest.mark.parametrize("override, key", [
    ("constraint.c=-1", "constraint.c"),
    ("constraint.c=soon", "constraint.c"),
    ("constraint.border_axes=[B]", "constraint.border_axes"),
    ("constraint.sweep=[]", "constraint.sweep"),
    ("model.kind=paper4", "model.kind"),
])
def test_constraint_and_model_kind_values_are_checked(cfg_file, override, key):
    with pytest.raises(ConfigError, match=f"key '{key}'"):
        load_config(cfg_file, [override])


def test_constraint_c_takes_a_number_auto_or_null(cfg_file):
    assert load_config(cfg_file, ["constraint.c=0.05"]).constraint.c == 0.05
    assert load_config(cfg_file, ["constraint.c=auto"]).constraint.c == "auto"
    assert load_config(cfg_file).constraint.c is None


def test_sensor_run_needs_no_tools_and_checks_gravity(tmp_path):
    p = tmp_path / "fit.yaml"
    p.write_text(SENSOR)
    cfg = load_config(p)
    assert cfg.tools is None and cfg.sensor.mount == "estimate"
    with pytest.raises(ConfigError, match="sensor.gravity.*norm"):
        load_config(p, ["sensor.gravity=[0, 0.1, -1]"])
    assert load_config(p, ["sensor.gravity=[0, 0, -1]"]).sensor.gravity == (0, 0, -1)  # the frozen config holds tuples
    with pytest.raises(ConfigError, match="key 'tools'"):
        load_config(p, ["tools=[[0, 0, 100]]"])
    with pytest.raises(ConfigError, match="sensor.kind"):
        load_config(p, ["sensor.kind=camera"])
    # an override replaces the mount wholesale (a word and a mapping never merge)
    cfg = load_config(p, ["sensor.mount={xyz_mm: [0, 0, 50], rpy_deg: [0, 0, 0]}"])
    assert cfg.sensor.mount["xyz_mm"] == (0, 0, 50)  # a mapping of tuples in the frozen config


def test_sensor_gravity_pointing_up_is_reported_as_given(tmp_path):
    """sensor.gravity is gravity (points down, default [0, 0, -1]); one pointing up is named as the user wrote it,
    not negated into the level's 'up' vector (which once read "gravity [..., -0.8] must point up")."""
    p = tmp_path / "fit.yaml"
    p.write_text(SENSOR)
    assert load_config(p, ["sensor.gravity=[0, 0.6, -0.8]"]).sensor.gravity == (0, 0.6, -0.8)
    with pytest.raises(ConfigError) as err:
        load_config(p, ["sensor.gravity=[0, 0.6, 0.8]"])
    msg = str(err.value)
    assert "key 'sensor.gravity': [0.0, 0.6, 0.8] points up" in msg and "points down (g_z < 0" in msg
    assert "-0.8" not in msg and "must point up" not in msg
    with pytest.raises(ConfigError, match=r"sensor.gravity.*\[1.0, 0.0, 0.0\] points up"):  # horizontal: g_z = 0
        load_config(p, ["sensor.gravity=[1, 0, 0]"])


def test_point_target_run_still_needs_tools(cfg_file):
    cfg_file.write_text(MINIMAL.replace("tools:\n  - [33.06, 57.73, 161.22]\n  - [57.26, -33.86, 161.22]\n", ""))
    with pytest.raises(ConfigError, match="key 'tools'.*required"):
        load_config(cfg_file)


def test_the_config_is_frozen_typed_and_round_trips_through_its_yaml(tmp_path):
    """What a run gets is a frozen dataclass (no stage can change it behind another's back), per-joint lists
    are tuples, and the YAML a run directory keeps reads back to an equal config."""
    import dataclasses

    from torchcal.app.config import FitConfig, config_from_text, to_yaml, updated

    cfg = make_config({"robot": "fanuc_lrmate200i", "tools": [[0, 0, 100], [50, 0, 80]],
                       "data": {"identification": "ident.csv"}}, ["model.order=[1,2,3,4,5,6]"], base_dir=tmp_path)
    assert isinstance(cfg, FitConfig) and cfg.model.order == (1, 2, 3, 4, 5, 6)
    assert cfg.tools == ((0, 0, 100), (50, 0, 80))
    with pytest.raises(dataclasses.FrozenInstanceError):
        cfg.out = "elsewhere"
    with pytest.raises(dataclasses.FrozenInstanceError):
        cfg.model.order = 4
    assert config_from_text(to_yaml(cfg)) == cfg
    variant = updated(cfg, {"out": str(tmp_path / "cell"), "data.n_poses": 5})
    assert (variant.out, variant.data.n_poses, cfg.data.n_poses) == (str(tmp_path / "cell"), 5, None)
    with pytest.raises(ConfigError, match="unknown config key 'data.n_pose'"):
        updated(cfg, {"data.n_pose": 5})
    with pytest.raises(ConfigError, match="model.order"):  # a variant is checked like a file
        updated(cfg, {"model.order": 99})


@pytest.mark.parametrize("values, key", [
    ({"data": {"identification": "i.csv", "truth": "t.json"}}, "data.truth"),  # no validation set
    ({"model": {"kind": "axis_perturbation", "compliance": True}}, "model.compliance"),
    ({"model": {"kind": "axis_perturbation", "order": "auto", "folds": 5}}, "model.order"),
    ({"sensor": {"kind": "pose"}, "tools": None, "data": {"identification": "i.csv", "validation": "v.csv",
                                                         "truth": "t.json"}}, "data.truth"),
    ({"sensor": {"kind": "pose"}, "tools": None, "model": {"order": "auto", "folds": 3}}, "model.order"),
])
def test_keys_that_exclude_each_other_are_refused_when_the_config_is_read(values, key, tmp_path):
    """Cross-key conflicts are the config check's, at parse time, naming the key: no stage finds them later,
    after the robot and the data were read (the files named here do not even exist)."""
    base = {"robot": "fanuc_lrmate200i", "tools": [[0, 0, 100]], "data": {"identification": "i.csv"}}
    merged = {**base, **values}
    with pytest.raises(ConfigError, match=f"key '{key}'"):
        make_config(merged, base_dir=tmp_path)


def test_fleet_run_paths_resolve_against_the_config_folder(tmp_path, monkeypatch):
    """prior.fleet and fleet.baseline written in a file resolve against the file's folder, as the data paths do
    (before, against the working directory); given as overrides, against the working directory."""
    fleet = tmp_path / "fleets" / "one"
    (fleet / "units").mkdir(parents=True)
    (fleet / "summary.csv").write_text("unit,status\n")
    folder = tmp_path / "new"
    folder.mkdir()
    p = folder / "fit.yaml"
    p.write_text(MINIMAL + "prior: {fleet: ../fleets/one}\nfleet: {baseline: ../fleets/one}\n")
    monkeypatch.chdir("/")
    cfg = load_config(p)
    assert Path(cfg.prior.fleet) == fleet.resolve() and Path(cfg.fleet.baseline) == fleet.resolve()
    monkeypatch.chdir(tmp_path / "fleets")
    cfg = load_config(p, ["prior.fleet=one"])
    assert Path(cfg.prior.fleet) == fleet.resolve()


def test_a_bad_tool_row_names_its_own_line(tmp_path):
    """A config listing tools one per line: the message points at the bad row, not at 'tools:' above it."""
    text = ("robot: fanuc_lrmate200i\ntools:\n  - [0, 0, 100]\n  - [10, 0, 100]\n  - [1, 2]\n"
            "data: {identification: ident.csv}\n")
    path = tmp_path / "c.yaml"
    path.write_text(text)
    with pytest.raises(ConfigError) as err:
        load_config(path)
    assert str(err.value).startswith(f"{path}, line 5: key 'tools': tool 2 is [1, 2]")
    # given on the command line instead, the override is named
    path.write_text(text.replace("  - [1, 2]\n", ""))
    with pytest.raises(ConfigError) as err:
        load_config(path, ["tools=[[0,0,100],[1,2,'x']]"])
    assert str(err.value).startswith("override 'tools=[[0,0,100],[1,2,'x']]'")


def test_overrides_of_another_commands_section_are_named():
    items = ["model.order=4", "fleet.cell=10", "sweep.engine=ray", "prior.fleet=runs/f"]
    fit = unused_overrides(items, "fit")
    assert len(fit) == 2 and "'fleet.cell=10'" in fit[0] and "'sweep.engine=ray'" in fit[1]
    assert [w.split("'")[1] for w in unused_overrides(items, "fleet")] == ["sweep.engine=ray"]
    assert [w.split("'")[1] for w in unused_overrides(items, "sweep")] == ["fleet.cell=10"]


@pytest.mark.parametrize("seed", ["-1", "99999999999999999999999"])
def test_a_seed_no_generator_takes_is_refused_by_key(cfg_file, seed):
    """numpy's generators take no negative seed and torch none above 2**64: both were tracebacks (one after the
    data were read)."""
    with pytest.raises(ConfigError, match=r"key 'seed': .*give a whole number from 0"):
        check_config(load_config(cfg_file, [f"seed={seed}"]))
    check_config(load_config(cfg_file, ["seed=0"]))
