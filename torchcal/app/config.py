"""Config-driven runs: YAML files and dotted ``key=value`` overrides, parsed once into frozen, typed objects.

Why one module: the config schema (every key with its default and doc), its parsing and the checks of every
key; the one place a user reads to write a config.

:func:`load_config` / :func:`make_config` merge the file and the overrides over the defaults (OmegaConf, which
names unknown keys), resolve paths, and return a :class:`FitConfig`: a frozen dataclass whose every field has
its precise type (``model.order`` an int, a per-joint tuple or "auto"), checked once by :func:`check_config`
(every key, and keys that exclude each other; per-joint lengths again once the robot is loaded). The stages get
that object; nothing below this module imports omegaconf (an import contract in pyproject.toml). A variant of
a config is :func:`updated`; a run directory's ``config.yaml`` reads back with :func:`run_config`.

Every value in a config is in the calibration engineer's units (mm, deg,
deg²); :mod:`torchcal.app.fit` converts them with :mod:`torchcal.core.units`.
Unknown keys, in the file or in an override, are an error naming the key and
the file (OmegaConf struct mode), so a typo never silently falls back to a
default.

Relative paths: those written in the config file (``robot`` when it is a
file, ``data.*``, ``out``, and defaults) resolve against the config file's
folder, so a config and its data travel together; those given as command-line
overrides resolve against the current directory, like any other shell argument.
"""

from __future__ import annotations

import copy
import difflib
import dataclasses
import functools
import typing
from dataclasses import dataclass, field, fields, is_dataclass
from pathlib import Path
from typing import Any, Mapping, Optional, Sequence, Union

import yaml
from omegaconf import MISSING, DictConfig, OmegaConf
from omegaconf.errors import ConfigKeyError, MissingMandatoryValue, OmegaConfBaseException

from ..core import units
from ..core.exceptions import ConfigError  # defined low (torchcal.core.exceptions) so that any layer can raise it
from ..error_models.joint import MAX_ORDER
from ..identify import SOLVERS, Prior
from ..io import yamlio
from .engines import ENGINES


_PRIOR = Prior()


@dataclass(frozen=True)
class DataConfig:
    """CSV files in the contract of :mod:`torchcal.io.csv`."""

    identification: str = MISSING
    """Measurements to identify the model from (all tools)."""
    validation: Optional[str] = None
    """Separate measurements to judge the model on (Tables 6-7); optional."""
    truth: Optional[str] = None
    """Simulated runs only: ``truth.json`` from ``torchcal simulate``; enables the compensation check (Table 7, Fig. 16)."""
    n_poses: Optional[int] = None
    """Identify from the first N poses of the identification file only (file order; Figure 11's 150 / 250 / 350); null: all."""
    units_checked: bool = False
    """true: skip the unit-slip checks (joints that look like radians, x, y, z that look like metres); see
    :mod:`torchcal.io.unit_checks`."""


MODEL_KINDS = ("joint_dependent", "axis_perturbation")
"""``model.kind``: Paper II's joint-dependent error model (robots) or Paper I's axis perturbation model (machine tools)."""

SENSOR_KINDS = ("sts", "pose")
"""``sensor.kind``: Paper III's SmartTrack sensor (position + yaw, roll, level angles) or a generic 6-DOF probe."""


@dataclass(frozen=True)
class ModelConfig:
    order: Union[int, tuple[int, ...], str] = 6
    """Chebyshev order: an int (all joints), a per-joint list, or "auto" (chosen by validation / cross-validation)."""
    backlash: Union[bool, int, tuple[int, ...]] = True
    """Backlash term on eps_z: true (its own default order, 2; with order: auto chosen per joint after the
    joint orders), false, or its order (int or per-joint list, -1 switches a joint's off)."""
    candidates: tuple[int, ...] = tuple(range(0, MAX_ORDER + 1))
    """Orders tried by order: auto."""
    folds: int = 0
    """order: auto without a validation set: 0 = leave-one-pose-out residuals of one fit per trial
    (no training-size bias), K >= 2 = K-fold cross-validation by pose (K fits per trial)."""
    margin: float = 1.0
    """order: auto, per-joint stage: keep a change only if it lowers the held-out error by more than this many
    standard errors of the paired (per-pose) difference."""
    compliance: Union[bool, str, Mapping[str, Any]] = False
    """Gravity compliance (arm sag): false, true (torques from the URDF inertials when every moving link has
    one, else arm-angle functions), "gravity" or "functions", or {mode: ..., joints: [joint names]}."""
    fine: Optional[Mapping[str, Any]] = None
    """Fine-grained joint-angle error tables (torchcal.error_models.fine, sensor runs): null (off) or
    {spacing_deg: knot spacing, smoothness_deg: sigma of a knot's second difference (number or per joint),
    prior_deg: sigma of each value, warm_start: fit without the tables first}."""
    error_variable: Union[None, str, tuple[str, ...]] = None
    """The variable each joint's error series is evaluated on: null (the robot's ``error_variable:``, 'command'
    by default), 'command' (the controller command q_i, Paper II (24)), 'joint' (the URDF joint variable), or a
    per-joint list of those."""
    backlash_on: str = "joint"
    """Where backlash acts: 'joint' (Paper II (13): about the URDF joint's own axis) or 'command' (on the controller
    command, carried to the URDF joints by the joint map's coupling: a parallelogram arm whose J2 backlash also
    turns θ3; the same as 'joint' for a robot whose controller commands its URDF joints)."""
    kind: str = "joint_dependent"
    """'joint_dependent' (Paper II: 6-DOF Chebyshev errors per joint, robots) or 'axis_perturbation' (Paper I:
    δq_i = Σ_j f_ij(q_j), machine tools, any serial chain)."""


@dataclass(frozen=True)
class NoiseConfig:
    sigma_m: float = 0.005
    """Tracker standard deviation per axis, mm (Paper II 5.2): a property of the tracker, not of the robot."""
    joint_var_fwd: Optional[tuple[float, ...]] = None
    """Joint variance per joint, forward approach, deg² (mm² for prismatic joints); null = the robot's
    ``repeatability:`` (its YAML; e.g. Paper II Table 5 for the bundled FANUC). Give both or neither."""
    joint_var_bwd: Optional[tuple[float, ...]] = None
    """Joint variance per joint, backward approach, deg² (mm²); null = the robot's ``repeatability:``."""


@dataclass(frozen=True)
class PriorConfig:
    enabled: bool = True
    """False: no prior (redundant combinations are left to the solver's damping)."""
    rotation_deg: float = units.rad_to_deg(_PRIOR.rotation)
    """Prior sigma of the joint error rotation terms, deg."""
    translation_mm: float = units.m_to_mm(_PRIOR.translation)
    """Prior sigma of the joint error translation terms, mm."""
    frame_rotation_deg: float = units.rad_to_deg(_PRIOR.frame_rotation)
    """Prior sigma of the base-frame and tool rotation corrections, deg."""
    frame_translation_mm: float = units.m_to_mm(_PRIOR.frame_translation)
    """Prior sigma of the base-frame and tool translation corrections, mm."""
    backlash_deg: Optional[float] = None
    """Prior sigma of every backlash coefficient, deg; null keeps the declared ones (c0 wide, c1.. 0.0017 deg)."""
    compliance_deg: Optional[float] = None
    """Prior sigma of the compliance coefficients, deg per unit configuration function; null: the default."""
    fleet: Optional[str] = None
    """A fleet's run directory (``torchcal fleet``): the parameter distribution of its fitted units (failed and
    flagged ones left out) as the prior of this unit, for a unit measured with few poses (issue #18). The model
    must have the fleet's structure (its orders and backlash orders: not 'auto')."""
    fleet_method: str = "shrunk"
    """How the fleet's covariance is regularized: 'shrunk' (Schaefer-Strimmer), 'ledoit-wolf', 'factor' (low rank
    + diagonal), 'block' (per joint, base and tool) or 'sample' (more units than parameters only)."""


@dataclass(frozen=True)
class ConstraintConfig:
    """Paper I's slope constraint (13)-(31): ‖h̄_i‖ ≤ c over the whole axis (joint) space."""

    c: Union[None, float, str] = None
    """null (unconstrained), a number (mm per half axis range), or auto (BORDER + constraint sweep, the knee)."""
    points: int = 2048
    """Quasi-random points over the whole command box (plus its corners) where the bound is enforced."""
    check_points: int = 4096
    """Fresh points, never seen by the penalty, where the bound is checked and reported."""
    tol: float = 0.01
    """Relative tolerance of the bound at the penalty points: max slope ≤ c (1 + tol)."""
    border_axes: Optional[tuple[str, ...]] = None
    """c: auto, the two axes (joint names) of the BORDER space; null: B and Z for the XYZCB machine (Paper I),
    else the two joints whose data span least of their range."""
    border_k: int = 30
    """c: auto, k of the reverse k-nearest-neighbour counts (Paper I 3.4)."""
    border_n: int = 10
    """c: auto, number of boundary points held out as the extrapolation check."""
    sweep: Optional[tuple[float, ...]] = None
    """c: auto, the c values tried (mm); null: a geometric grid below the unconstrained model's largest slope."""
    knee_tol_mm: float = 0.01
    """c: auto, the knee: the smallest c before the boundary max or the sub-identification mean rises by more than this."""
    reference: str = "nominal"
    """What the slope is of: the modeled error against the nominal chain (Paper I), or, for robots, 'constant':
    against the chain with the constant error terms, i.e. the joint-dependent part only (constant DH-like
    errors have large, legitimate slopes on a robot)."""


@dataclass(frozen=True)
class SensorConfig:
    """Paper III: a 6-DOF sensor on the flange instead of point targets (the CSV then carries r11..r33)."""

    kind: Optional[str] = None
    """null (point targets, the tools), 'sts' (Paper III's tracking sensor) or 'pose' (a generic 6-DOF probe)."""
    mount: Union[str, Mapping[str, tuple[float, ...]]] = "estimate"
    """Nominal flange -> sensor frame {xyz_mm: [...], rpy_deg: [...]}, or estimate (from the data, no guess)."""
    gravity: Optional[tuple[float, ...]] = None
    """sts only: the unit gravity vector in the tracker frame (first guess; refined); null: [0, 0, -1]."""
    position_only: bool = False
    """Fit the sensor origin only (the orientation is still evaluated)."""
    pose_std: Optional[tuple[float, ...]] = None
    """pose only: per-axis standard deviations [sx, sy, sz (mm), srx, sry, srz (deg)] weighting every row,
    instead of the file's sx..srz columns (or the default)."""


@dataclass(frozen=True)
class SolverConfig:
    method: str = "lm"
    """'lm' (Levenberg-Marquardt, joint errors eliminated per row) or 'lbfgs'."""
    max_iter: Optional[int] = None
    """Iteration limit; null = the solver's default (lm 100, lbfgs 20000)."""
    ftol: float = 1e-8
    """Stop when the relative cost reduction falls below this."""


@dataclass(frozen=True)
class CompensationConfig:
    tol_deg: Optional[float] = None
    """Stopping tolerance on |dq| (deg; mm for prismatic joints), e.g. the encoder resolution (Paper II (51));
    null = torchcal.compensate's default."""
    max_iter: Optional[int] = None
    """Fixed-Jacobian iterations before a command goes to the damped solver; null = the default."""


FLEET_ENGINES = ENGINES
"""``fleet.engine`` / ``sweep.engine``: where the cells are fitted (:mod:`torchcal.app.engines`)."""


@dataclass(frozen=True)
class FleetConfig:
    """``torchcal fleet CONFIG``: one identification file per unit (``data.identification`` a folder)."""

    engine: str = "local"
    """local (this process) or ray (each cell of units a Ray task: ``pip install torchcal[ray]``)."""
    address: Optional[str] = None
    """engine: ray: the cluster's address (null: a local Ray started for the run, or RAY_ADDRESS)."""
    cell: int = 50
    """Units fitted together in one batched solve; the cells are what an engine sends out (every engine forms
    the same cells, so local and Ray compute the same numbers)."""
    threshold: float = 5.0
    """Robust z above which a unit's joint is flagged, when it is also 3x the fleet median or more
    (torchcal.identify.fleet.parameter_outliers)."""
    ftol: float = 1e-4
    """Relative cost reduction at which every unit's fit stops (torchcal.identify.fleet.FLEET_FTOL: each unit
    within a few hundredths of a percent of its own fit's residuals). solver.ftol is a single fit's and is not
    used here; 1e-8 gives the single fit's stopping point."""
    baseline: Optional[str] = None
    """An earlier ``torchcal fleet`` run directory of the same units: each unit fitted in both is compared with
    its earlier model (the change at the tool, the joints that changed), and the units that changed far beyond
    the fleet's own changes are named (torchcal.identify.fleet_change: a crash, a gearbox swap)."""
    reuse: Optional[str] = None
    """An earlier ``torchcal fleet`` run of these units with the same settings: a unit it fitted whose data files
    are unchanged is taken as fitted there; only the others (failed, interrupted, new, re-measured) are fitted
    (torchcal.app.fleet_reuse). Every unit is scored, compared and written as in a fresh run."""


@dataclass(frozen=True)
class SweepConfig:
    """``torchcal sweep CONFIG key=a,b,c``: where the grid's independent cells run."""

    engine: str = "local"
    """local (this process, one cell group after the other) or ray (each group of cells a Ray task: ``pip install
    torchcal[ray]``). On a cluster, the data files and the sweep's run directory must be on storage every node
    reaches (as Ray Tune's storage_path): the cells write their own folders."""
    address: Optional[str] = None
    """engine: ray: the cluster's address (null: a local Ray started for the run, or RAY_ADDRESS)."""


@dataclass(frozen=True)
class FitConfig:
    """The schema of ``torchcal fit CONFIG.yaml``."""

    robot: str = MISSING
    """Bundled robot name (e.g. fanuc_lrmate200i), a joint-map YAML or a URDF."""
    tools: Union[None, tuple[tuple[float, ...], ...], Mapping[str, int]] = None
    """Nominal tool vectors [x, y, z] in the flange frame, mm (a list; the CSV 'tool' column indexes it),
    or ``{count: T}`` when they are not known (e.g. reflectors glued on the flange): the fit then estimates
    them from the data first (:mod:`torchcal.identify.alignment`)."""
    measurement_frame: Union[str, Mapping[str, tuple[float, ...]]] = "auto"
    """The robot base seen in the measurement (tracker) frame, the model's nominal T_0^m (26):
    ``base`` (identity: the tracker frame is at the robot base, as Paper II assumes), ``estimate``
    (from the data, no guess needed: :mod:`torchcal.identify.alignment`), ``auto`` (``base`` when the
    tool vectors are listed, ``estimate`` when they are only counted), or
    ``{xyz_mm: [x, y, z], rpy_deg: [roll, pitch, yaw]}`` (p_tracker = Rot(rpy) p_base + xyz, URDF
    roll-pitch-yaw). The fit refines it either way (base-frame corrections)."""
    data: DataConfig = field(default_factory=DataConfig)
    model: ModelConfig = field(default_factory=ModelConfig)
    noise: NoiseConfig = field(default_factory=NoiseConfig)
    prior: PriorConfig = field(default_factory=PriorConfig)
    solver: SolverConfig = field(default_factory=SolverConfig)
    constraint: ConstraintConfig = field(default_factory=ConstraintConfig)
    sensor: SensorConfig = field(default_factory=SensorConfig)
    compensation: CompensationConfig = field(default_factory=CompensationConfig)
    fleet: FleetConfig = field(default_factory=FleetConfig)
    sweep: SweepConfig = field(default_factory=SweepConfig)
    seed: int = 0
    device: str = "cpu"
    """torch device, e.g. cpu, cuda, cuda:1."""
    threads: Optional[int] = None
    """CPU threads of every stage (torch, its BLAS and numba); null: chosen per stage by work size and the CPUs this process may use (torchcal.core.threads)."""
    out: str = "runs"
    """Run directory; if it already holds a run, the run goes beside it (<out>-2, ...); if it is another
    non-empty folder, to <out>/<timestamp> (see torchcal.io.rundir.make_run_dir)."""
    plots: bool = True
    report: bool = True
    """Write report.html (torchcal.report: a self-contained calibration report) at the end of the run."""
    config_file: Optional[str] = None
    """Set by load_config: the YAML this config came from (provenance)."""
    overrides: tuple[str, ...] = ()
    """Set by load_config / make_config: the ``key=value`` overrides applied over the file, in order
    (provenance; a check that fails on one of their keys names the override, not the file)."""


FRAME_MODES = ("auto", "base", "estimate")
"""The string values of ``measurement_frame``."""

PROVENANCE_KEYS = ("config_file", "overrides")
"""Keys load_config sets itself (where the config came from); not offered as valid keys to type."""

WHOLE_VALUE_KEYS = ("tools", "measurement_frame", "sensor.mount", "constraint.c")
"""Keys whose override replaces the whole value (their values change type: list, mapping or word)."""

PATH_KEYS = ("data.identification", "data.validation", "data.truth", "out", "prior.fleet", "fleet.baseline",
             "fleet.reuse")
"""Config keys naming files or folders: relative values resolve against the config file's folder (overrides: the
working directory)."""


# ------------------------------------------------------------- parsing vs. the typed objects
# The classes above are what a run gets: frozen, precisely typed (a value may be an int, a per-joint tuple or
# "auto"). OmegaConf, which merges files and overrides and names unknown keys, takes no unions of containers
# and no tuples; it parses against a mirror of these classes derived here (such fields become Any there), and
# check_config then pins down what the unions allow. One definition of every key, its default and its doc.
_PRIMITIVES = (int, float, bool, str)


def _parse_type(hint):
    """The OmegaConf-compatible annotation for a field's precise one (Any where OmegaConf cannot express it)."""
    if is_dataclass(hint):
        return _parse_class(hint)
    if hint in _PRIMITIVES:
        return hint
    origin, args = typing.get_origin(hint), typing.get_args(hint)
    if origin is Union and len(args) == 2 and type(None) in args:
        inner = _parse_type(next(a for a in args if a is not type(None)))
        return Any if inner is Any else Optional[inner]
    if origin is tuple and len(args) == 2 and args[1] is Ellipsis and args[0] in _PRIMITIVES:
        return list[args[0]]
    return Any


@functools.cache
def _parse_class(cls):
    """A mutable dataclass mirroring ``cls`` with OmegaConf-compatible annotations (tuples as lists)."""
    hints = typing.get_type_hints(cls)
    specs = []
    for f in fields(cls):
        typ = _parse_type(hints[f.name])
        if f.default_factory is not dataclasses.MISSING:  # a section
            specs.append((f.name, typ, field(default_factory=_parse_class(f.default_factory))))
        elif isinstance(f.default, tuple):
            specs.append((f.name, typ, field(default_factory=functools.partial(list, f.default))))
        else:
            specs.append((f.name, typ, field(default=f.default)))
    return dataclasses.make_dataclass(f"_Parsed{cls.__name__}", specs)


def _frozen_value(v):
    """Lists -> tuples, all the way down (mappings keep their keys)."""
    if isinstance(v, (list, tuple)):
        return tuple(_frozen_value(x) for x in v)
    if isinstance(v, dict):
        return {k: _frozen_value(x) for k, x in v.items()}
    return v


def _freeze(cls, values: Mapping):
    """``cls`` (a frozen config class) from plain containers; unknown keys were refused by the parse before."""
    kwargs = {}
    for f in fields(cls):
        if f.name not in values:
            continue
        v = values[f.name]
        sub = f.default_factory if f.default_factory is not dataclasses.MISSING else None
        kwargs[f.name] = _freeze(sub, v or {}) if sub is not None and is_dataclass(sub) else _frozen_value(v)
    return cls(**kwargs)


def _plain_value(v):
    """Tuples -> lists, sections -> dicts: the YAML / JSON / check view of a config value."""
    if is_dataclass(v):
        return {f.name: _plain_value(getattr(v, f.name)) for f in fields(v)}
    if isinstance(v, (list, tuple)):
        return [_plain_value(x) for x in v]
    if isinstance(v, Mapping):
        return {k: _plain_value(x) for k, x in v.items()}
    return v


def schema() -> DictConfig:
    """A fresh structured (struct-mode) config holding every default: what files and overrides are parsed into."""
    # a copy of one built template: OmegaConf builds a structured config in ~25 ms, and a sweep or a fleet
    # loads one per cell
    return copy.deepcopy(_schema_template())


@functools.lru_cache(maxsize=1)
def _schema_template() -> DictConfig:
    return OmegaConf.structured(_parse_class(FitConfig))


def _keys_at(node_type, parts: list[str]) -> list[str]:
    """Valid keys of the schema section ``parts`` (for 'did you mean' lists)."""
    t = node_type
    for p in parts:
        match = [f for f in fields(t) if f.name == p]
        if not match:
            return []
        t = match[0].type
        if isinstance(t, str):  # postponed annotations: resolve by name
            t = globals().get(t)
        if t is None or not is_dataclass(t):
            return []
    return [f.name for f in fields(t)] if t is not None and is_dataclass(t) else []


@functools.lru_cache(maxsize=1)
def _all_keys() -> tuple[str, ...]:
    """Every dotted key of the schema (sections' keys included), for suggestions."""
    out: list[str] = []

    def walk(cls, prefix):
        for f in fields(cls):
            t = typing.get_type_hints(cls).get(f.name)
            key = prefix + f.name
            if f.name not in PROVENANCE_KEYS:
                out.append(key)
            if isinstance(t, type) and is_dataclass(t):
                walk(t, key + ".")

    walk(FitConfig, "")
    return tuple(out)


def _explain(exc: OmegaConfBaseException, where: str) -> ConfigError:
    """One readable sentence from an OmegaConf error; ``where`` is the file or the override."""
    key = getattr(exc, "full_key", None) or getattr(exc, "key", None) or "?"
    if isinstance(exc, ConfigKeyError):
        parts = str(key).split(".")
        valid = [k for k in _keys_at(FitConfig, parts[:-1]) if k not in PROVENANCE_KEYS]
        hint = f"; valid keys{' under ' + '.'.join(parts[:-1]) if len(parts) > 1 else ''}: {', '.join(valid)}" if valid else ""
        close = difflib.get_close_matches(parts[-1], valid, n=1, cutoff=0.7)
        if close:
            mean = f" (did you mean '{'.'.join([*parts[:-1], close[0]])}'?)"
        else:  # the right name in another section (model.max_iter for solver.max_iter)
            other = [k for k in _all_keys() if k.rsplit(".", 1)[-1] == parts[-1] and k != str(key)]
            mean = (f" (did you mean '{other[0]}'?)" if len(other) == 1 else
                    f" (did you mean one of {', '.join(repr(k) for k in other)}?)" if 1 < len(other) <= 3 else "")
        return ConfigError(f"{where}: unknown config key '{key}'{mean}{hint}")
    msg = str(exc).split("\n")[0]
    if msg.startswith("Incompatible value 'None'"):  # OmegaConf's words for `key=` on a key that takes no null
        msg = "needs a value (it cannot be empty or null)"
    return ConfigError(f"{where}: key '{key}': {msg}")


def _resolve_path(value: str | None, base: Path) -> str | None:
    if value is None or value == "":
        return value
    p = Path(value).expanduser()
    return str(p if p.is_absolute() else (base / p).resolve())


def _is_robot_file(spec: str) -> bool:
    """Same rule as :func:`torchcal.kinematics.load_robot`: a name without a suffix is a bundled robot."""
    return bool(Path(spec).suffix)


def _resolve_paths(cfg: DictConfig, base: Path, keys: Sequence[str]) -> None:
    for key in keys:
        if key == "robot":
            if not OmegaConf.is_missing(cfg, "robot") and _is_robot_file(cfg.robot):
                cfg.robot = _resolve_path(cfg.robot, base)
            continue
        section, _, name = key.rpartition(".")
        node = OmegaConf.select(cfg, section) if section else cfg
        if not OmegaConf.is_missing(node, name):
            node[name] = _resolve_path(node[name], base)


_KEY_LINES: dict[str, dict[str, int]] = {}
"""{config file: {dotted key: line}} of the files load_config read: a value's check, made after parsing, can name
its line (a cache rebuilt on every read of that file, so an edited file is never mislabelled for long)."""


def _key_lines(text: str) -> dict[str, int]:
    """Every mapping key and list item of a YAML text, dotted (``tools.2`` for a list's third item), with its
    1-based line (nothing where the text does not compose)."""
    try:
        root = yaml.compose(text, Loader=yaml.SafeLoader)
    except yaml.YAMLError:
        return {}
    out: dict[str, int] = {}

    def walk(node, prefix):
        if isinstance(node, yaml.MappingNode):
            for k, v in node.value:
                if isinstance(k, yaml.ScalarNode):
                    key = f"{prefix}{k.value}"
                    out.setdefault(key, k.start_mark.line + 1)
                    walk(v, key + ".")
        elif isinstance(node, yaml.SequenceNode):
            for i, v in enumerate(node.value):
                out.setdefault(f"{prefix}{i}", v.start_mark.line + 1)
                walk(v, f"{prefix}{i}.")

    walk(root, "")
    return out


def _with_line(label: str, key: str, config_file: str | None) -> str:
    lines = _KEY_LINES.get(config_file or "", {})
    parts = key.split(".")
    for i in range(len(parts), 0, -1):  # the key itself, else the nearest key above it the file has
        line = lines.get(".".join(parts[:i]))
        if line is not None:
            return f"{label}, line {line}"
    return label


def source_of(cfg: "FitConfig", key: str, label: str) -> str:
    """Where ``key``'s value came from, for a message: the last override setting it (or a key above or below
    it), else ``label`` (the file, with the key's line where the file has it)."""
    whole = next((w for w in WHOLE_VALUE_KEYS if key == w or key.startswith(w + ".")), None)
    for item in reversed(tuple(getattr(cfg, "overrides", ()) or ())):
        k = item.partition("=")[0].strip()
        if k == key or key.startswith(k + ".") or k.startswith(key + ".") or (
                whole is not None and k.startswith(whole + ".")):  # the override replaced the whole value
            return f"override '{item}' (over {label})"
    return _with_line(label, key, getattr(cfg, "config_file", None))


def repeated_overrides(overrides: Sequence[str]) -> list[str]:
    """One sentence per key given more than once in ``overrides``: the last one is used (a script appending to
    a common list relies on that), but a command line typed twice over reads the same, so it is said."""
    seen: dict[str, list[str]] = {}
    for item in overrides:
        if "=" in item:
            seen.setdefault(item.partition("=")[0].strip(), []).append(item)
    return [f"override key '{k}' is given {len(v)} times ({', '.join(repr(i) for i in v)}): the last one is used"
            for k, v in seen.items() if len(v) > 1]


SECTION_COMMANDS = {"fleet": "fleet", "sweep": "sweep"}
"""Config sections that only one command reads: {section: that command}."""


def unused_overrides(overrides: Sequence[str], command: str) -> list[str]:
    """One sentence per override that sets a section only another command reads (``fleet.engine=ray`` given to
    ``torchcal fit``): the run would go ahead without it, so the user who meant it is told."""
    out = []
    for item in overrides:
        section = item.partition("=")[0].strip().split(".")[0]
        other = SECTION_COMMANDS.get(section)
        if other is not None and other != command:
            out.append(f"override '{item}' has no effect on `torchcal {command}`: the {section}: section is read "
                       f"only by `torchcal {other}`")
    return out


def _split_override(item: str) -> tuple[str, str]:
    if "=" not in item:
        raise ConfigError(f"override '{item}': expected key=value (e.g. model.order=4)")
    key, _, value = item.partition("=")
    key = key.strip()
    if not key:
        raise ConfigError(f"override '{item}': empty key")
    return key, value


def apply_overrides(cfg: DictConfig, overrides: Sequence[str], base: Path | None = None) -> DictConfig:
    """Merge dotted ``key=value`` overrides (values parsed as YAML: 4, [1,2], auto, null) into ``cfg``.

    Paths among them resolve against ``base`` (default: the current directory).
    Raises :class:`ConfigError` naming the override and key.
    """
    base = Path.cwd() if base is None else base
    for item in overrides:
        key, value = _split_override(item)
        section = _keys_at(FitConfig, key.split("."))
        if section and key not in WHOLE_VALUE_KEYS and not value.strip().startswith("{"):
            raise ConfigError(f"override '{item}': key '{key}' is a section of keys ({', '.join(section)}), not one "
                              f"value: set one of them, e.g. {key}.{section[0]}=...")
        whole = next((w for w in WHOLE_VALUE_KEYS if key.startswith(w + ".")), None)
        try:
            new = OmegaConf.from_dotlist([item])
            if whole is not None and not OmegaConf.is_dict(OmegaConf.select(cfg, whole)):
                # tools.count=3 over a list of tool vectors, measurement_frame.xyz_mm=[..] over 'auto': the
                # mapping replaces the value (merging a key into a list or a word has no meaning)
                OmegaConf.update(cfg, whole, OmegaConf.select(new, whole), merge=False)
            elif key in WHOLE_VALUE_KEYS:
                # these take a list, a mapping or a word: an override replaces the value, never merges into it
                OmegaConf.update(cfg, key, OmegaConf.select(new, key), merge=False)
            else:
                cfg = OmegaConf.merge(cfg, new)
        except OmegaConfBaseException as exc:
            raise _explain(exc, f"override '{item}'") from None
        except TypeError as exc:  # e.g. merging a mapping into a list
            raise ConfigError(f"override '{item}': key '{key}': {exc}") from None
        touched = [k for k in ("robot",) + PATH_KEYS if k == key or k.startswith(key + ".")]
        _resolve_paths(cfg, base, touched)
    return cfg


def make_config(values: dict | None = None, overrides: Sequence[str] = (), base_dir=".", label: str = "config",
                check_device: bool = True) -> FitConfig:
    """Build a checked config from a mapping (programmatic runs, experiments), like :func:`load_config` does from a file.

    values: nested dict in the schema's keys; base_dir: folder relative paths in
    ``values`` resolve against; label: names the source in messages.
    """
    base = Path(base_dir).resolve()
    try:
        cfg = OmegaConf.merge(schema(), OmegaConf.create(values or {}))
    except OmegaConfBaseException as exc:
        raise _explain(exc, label) from None
    _resolve_paths(cfg, base, ("robot",) + PATH_KEYS)
    cfg = apply_overrides(cfg, overrides)
    cfg.overrides = [*cfg.overrides, *overrides]  # a run's config.yaml read back keeps its own
    return _finish(cfg, label, check_device)


def _finish(cfg: DictConfig, label: str, check_device: bool = True) -> FitConfig:
    """The parsed config -> the frozen, typed :class:`FitConfig`, checked once (:func:`check_config`)."""
    for key in ("robot", "data.identification"):
        try:
            OmegaConf.select(cfg, key, throw_on_missing=True)
        except MissingMandatoryValue:
            raise ConfigError(f"{label}: key '{key}': is required but not set") from None
        except OmegaConfBaseException as exc:  # interpolation errors and the like
            raise _explain(exc, label) from None
    try:
        values = OmegaConf.to_container(cfg, resolve=True)
    except OmegaConfBaseException as exc:
        raise _explain(exc, label) from None
    frozen = _freeze(FitConfig, values)
    check_config(frozen, label, check_device=check_device)
    return frozen


def updated(cfg: FitConfig, changes: Mapping[str, Any], label: str = "config") -> FitConfig:
    """A copy of ``cfg`` with dotted keys replaced (``{"out": ..., "data.n_poses": None}``), checked again.

    The frozen config's one way to a variant (sweep cells, fleet units): a key that does not exist is an error.
    """
    values = to_dict(cfg)
    for key, value in changes.items():
        node, parts = values, key.split(".")
        for part in parts[:-1]:
            node = node[part]
        if parts[-1] not in node:
            raise ConfigError(f"{label}: unknown config key '{key}'")
        node[parts[-1]] = _plain_value(value)
    frozen = _freeze(FitConfig, values)
    check_config(frozen, label, check_device=False)
    return frozen


def config_from_text(text: str, label: str = "config", check_device: bool = True) -> FitConfig:
    """A resolved config's YAML (a run directory's ``config.yaml``, what :func:`to_yaml` wrote) -> FitConfig.

    Paths in it are absolute already. check_device=False: a run fitted on CUDA still loads on a CPU machine.
    """
    try:
        raw = yamlio.safe_load(text) or {}
    except yaml.YAMLError as exc:
        raise ConfigError(f"{label}: not valid YAML: {exc}") from None
    if not isinstance(raw, dict):
        raise ConfigError(f"{label}: a config must be a mapping of keys, got {type(raw).__name__}")
    return make_config(raw, label=label, check_device=check_device)


def run_config(run_dir) -> FitConfig:
    """The frozen config a run directory was made with (its ``config.yaml``); RunDirError-style message if absent."""
    path = Path(run_dir) / "config.yaml"
    if not path.is_file():
        raise ConfigError(f"{path}: no config.yaml; is {run_dir} a run directory?")
    return config_from_text(path.read_text(encoding="utf-8"), str(path), check_device=False)


class _UniqueKeyLoader(yaml.SafeLoader):
    """SafeLoader that refuses a key given twice in one mapping (plain YAML keeps the last one silently)."""

    def construct_mapping(self, node, deep=False):
        seen: dict = {}
        for key_node, _ in node.value:
            if key_node.tag == "tag:yaml.org,2002:merge":
                continue
            key = self.construct_object(key_node, deep=True)
            line = key_node.start_mark.line + 1
            try:
                if key in seen:
                    raise _DuplicateKey(key, seen[key], line)
                seen[key] = line
            except TypeError:  # an unhashable key: SafeLoader's own error follows
                continue
        return super().construct_mapping(node, deep=deep)


class _DuplicateKey(ConfigError):
    """Raised by :class:`_UniqueKeyLoader`; load_config turns it into a ConfigError naming the file."""

    def __init__(self, key, first: int, second: int):
        super().__init__(key, first, second)
        self.key, self.first, self.second = key, first, second


def load_config(path, overrides: Sequence[str] = ()) -> FitConfig:
    """Read a YAML config, merge it over the schema's defaults, then apply ``overrides`` (``["model.order=4"]``).

    -> the frozen, typed :class:`FitConfig` (checked; per-joint lists are checked against the robot by
    :func:`check_config` with ``n_joints`` once it is loaded).
    Raises :class:`ConfigError` naming the file / override and the key.

    Example:
        >>> import pathlib, tempfile
        >>> path = pathlib.Path(tempfile.mkdtemp()) / "fit.yaml"
        >>> _ = path.write_text("robot: fanuc_lrmate200i\\ntools: [[0, 0, 100]]\\ndata: {identification: ident.csv}\\n")
        >>> cfg = load_config(path, ["model.order=4"])
        >>> cfg.model.order, cfg.noise.sigma_m, cfg.noise.joint_var_fwd    # null: the robot's repeatability
        (4, 0.005, None)
    """
    path = Path(path)
    if not path.is_file():
        raise ConfigError(f"{path}: " + ("is a directory, not a config file" if path.is_dir() else "config file not found"))
    try:
        text = path.read_text(encoding="utf-8")
    except UnicodeDecodeError as exc:
        line = path.read_bytes()[:exc.start].count(b"\n") + 1
        raise ConfigError(f"{path}: not a UTF-8 text file (byte 0x{exc.object[exc.start]:02x} at line {line}); save "
                          "it as UTF-8") from None
    _KEY_LINES[str(path.resolve())] = _key_lines(text)
    try:
        raw = yaml.load(text, Loader=_UniqueKeyLoader)
    except _DuplicateKey as exc:
        raise ConfigError(f"{path}: key '{exc.key}' is given twice (lines {exc.first} and {exc.second}) in one mapping; "
                          f"keep one") from None
    except yaml.YAMLError as exc:
        mark = getattr(exc, "problem_mark", None)
        where = f" at line {mark.line + 1}, column {mark.column + 1}" if mark is not None else ""
        raise ConfigError(f"{path}: not valid YAML{where}: {getattr(exc, 'problem', exc)}") from None
    if raw is None:
        raw = {}
    if not isinstance(raw, dict):
        raise ConfigError(f"{path}: a config must be a mapping of keys (robot:, tools:, data:, ...), got {type(raw).__name__}")
    try:
        cfg = OmegaConf.merge(schema(), OmegaConf.create(raw))
    except OmegaConfBaseException as exc:
        raise _explain(exc, str(path)) from None
    _resolve_paths(cfg, path.parent.resolve(), ("robot",) + PATH_KEYS)
    cfg = apply_overrides(cfg, overrides)
    cfg.config_file = str(path.resolve())
    cfg.overrides = list(overrides)  # only these: the file itself is the source of the rest
    return _finish(cfg, str(path))


# ------------------------------------------------------------------------ checks
def _is_int(x) -> bool:
    return isinstance(x, int) and not isinstance(x, bool)


def _is_number(x) -> bool:
    return isinstance(x, (int, float)) and not isinstance(x, bool) and x == x and abs(x) != float("inf")


_plain = _plain_value  # the checks read plain lists and dicts


def _check_frame(frame: dict, key: str, fail) -> None:
    """A {xyz_mm: [x, y, z], rpy_deg: [r, p, y]} frame."""
    extra = sorted(set(frame) - {"xyz_mm", "rpy_deg"})
    if extra:
        fail(f"{key}.{extra[0]}", "unknown key; valid keys: xyz_mm, rpy_deg")
    for sub, what in (("xyz_mm", "[x, y, z] in mm"), ("rpy_deg", "[roll, pitch, yaw] in deg")):
        v = frame.get(sub)
        if not isinstance(v, list) or len(v) != 3 or not all(_is_number(x) for x in v):
            fail(f"{key}.{sub}", f"{v!r}: give {what}")


MAX_SEED = 2**63 - 1
"""The largest seed: every random draw (torch, numpy) takes it."""


def check_config(cfg: FitConfig, label: str = "config", n_joints: int | None = None, check_device: bool = True) -> None:
    """Values that the types alone do not pin down; ``n_joints`` (once the robot is loaded) checks per-joint lists.

    Raises :class:`ConfigError` naming ``label`` and the key.
    """
    def fail(key, msg, at=None):
        # at: a finer key than the one named (a list item, tools.2) whose own line the message should give
        raise ConfigError(f"{source_of(cfg, at or key, label)}: key '{key}': {msg}")

    for key, value in (("robot", cfg.robot), ("data.identification", cfg.data.identification)):
        if value in (MISSING, None, ""):
            fail(key, "is required but not set")
    fleet = cfg.fleet
    for key, engine in (("fleet.engine", fleet.engine), ("sweep.engine", cfg.sweep.engine)):
        if engine not in FLEET_ENGINES:
            fail(key, f"must be one of {', '.join(FLEET_ENGINES)}, got {engine!r}")
    if int(fleet.cell) < 1:
        fail("fleet.cell", f"must be a positive number of units, got {fleet.cell}")
    if not float(fleet.threshold) > 0:
        fail("fleet.threshold", f"must be positive, got {fleet.threshold}")
    if not 0 < float(fleet.ftol) < 1:
        fail("fleet.ftol", f"must be between 0 and 1 (a relative cost reduction), got {fleet.ftol}")
    if not 0 <= int(cfg.seed) <= MAX_SEED:  # numpy's generators take no negative seed, torch none above 2**64
        fail("seed", f"{cfg.seed}: give a whole number from 0 to {MAX_SEED}")
    n_poses = cfg.data.n_poses
    if n_poses is not None and (not _is_int(n_poses) or n_poses < 1):
        fail("data.n_poses", f"{n_poses!r}: give a positive number of poses (or null for all)")
    tools = _plain(cfg.tools)
    sensor = _plain(cfg.sensor)
    if sensor["kind"] is not None and sensor["kind"] not in SENSOR_KINDS:
        fail("sensor.kind", f"{sensor['kind']!r}: give null (point targets), {' or '.join(SENSOR_KINDS)}")
    if sensor["kind"] is not None:
        if tools is not None:
            fail("tools", "a sensor run measures the sensor frame, not tools: leave tools unset (null)")
        mount = sensor["mount"]
        if isinstance(mount, dict):
            _check_frame(mount, "sensor.mount", fail)
        elif mount != "estimate":
            fail("sensor.mount", f"{mount!r}: give estimate or {{xyz_mm: [x, y, z], rpy_deg: [r, p, y]}}")
        g = sensor["gravity"]
        if g is not None:
            if sensor["kind"] != "sts":
                fail("sensor.gravity", "only the sts sensor measures against gravity")
            if not isinstance(g, list) or len(g) != 3 or not all(_is_number(v) for v in g):
                fail("sensor.gravity", f"{g!r}: give a unit vector [gx, gy, gz] in the tracker frame")
            norm = sum(v * v for v in g) ** 0.5
            if abs(norm - 1.0) > 1e-6:
                fail("sensor.gravity", f"{g!r} has norm {norm:.6g}: give a unit vector (normalize it)")
            if not g[2] < 0:
                fail("sensor.gravity", f"{g!r} points up (g_z >= 0): give the direction of gravity in the tracker "
                     "frame, which points down (g_z < 0; null: [0, 0, -1]); the level's 'up' is its negative")
    elif tools is None:
        fail("tools", "is required but not set (tool vectors [[x, y, z], ...] in mm, or {count: T})")
    elif sensor["position_only"]:
        fail("sensor.position_only", "applies to sensor runs only (set sensor.kind)")
    if sensor["kind"] is not None:
        pass  # the tool checks below are for point-target runs
    elif isinstance(tools, dict):
        extra = sorted(set(tools) - {"count"})
        if extra:
            colon = "; in a one-line mapping put a space after the colon ('{count: 3}')" if ":" in str(extra[0]) else ""
            fail(f"tools.{extra[0]}", "unknown key; unknown tool vectors are given as {count: T} (valid keys: count)"
                 + colon)
        if "count" not in tools or not _is_int(tools["count"]) or tools["count"] < 1:
            fail("tools.count", f"{tools.get('count')!r}: give the number of tools (an int >= 1)")
    elif isinstance(tools, list):
        if not tools:
            fail("tools", "needs at least one tool vector [x, y, z] (mm), or {count: T} when they are unknown")
        for i, t in enumerate(tools):
            if not isinstance(t, list) or len(t) != 3:
                fail("tools", f"tool {i} is {t!r}; each tool is [x, y, z] in mm", at=f"tools.{i}")
            if not all(_is_number(v) for v in t):
                fail("tools", f"tool {i} {t!r}: the values must be numbers (mm)", at=f"tools.{i}")
    else:
        fail("tools", f"{tools!r}: give a list of tool vectors [[x, y, z], ...] (mm) or {{count: T}} when they are unknown")

    frame = _plain(cfg.measurement_frame)
    if isinstance(frame, dict):
        _check_frame(frame, "measurement_frame", fail)
    elif frame not in FRAME_MODES:
        fail("measurement_frame", f"{frame!r}: give one of {', '.join(FRAME_MODES)} or {{xyz_mm: [x, y, z], rpy_deg: [r, p, y]}}")

    if cfg.model.kind not in MODEL_KINDS:
        fail("model.kind", f"{cfg.model.kind!r}: give one of {', '.join(MODEL_KINDS)}")
    # keys that exclude each other: checked here, with the rest, not by the stage that would trip over them
    auto = isinstance(_plain(cfg.model.order), str)
    if cfg.data.truth and not cfg.data.validation:
        fail("data.truth", "the compensation check runs on the validation set; set data.validation")
    if sensor["kind"] is not None:
        if auto and (int(cfg.model.folds) > 0 or cfg.model.fine is not None):
            fail("model.order", "auto on a sensor run chooses by leave-one-pose-out or the validation set "
                 "(model.folds: 0) and without fine tables (model.fine: null)")
        if cfg.constraint.c is not None and cfg.model.fine is not None:
            fail("constraint.c", "the slope bound is not available with model.fine (fine tables) for sensor runs")
        if cfg.data.truth:
            fail("data.truth", "the compensation check is for point-target runs")
    if cfg.model.kind == "axis_perturbation":
        for key, bad, why in (("model.order", auto and int(cfg.model.folds) > 0,
                               "auto on a machine tool chooses by leave-one-pose-out or the validation set "
                               "(model.folds: 0)"),
                              ("data.truth", bool(cfg.data.truth), "the compensation check simulates robots; run "
                               "experiments/paper1_machine_tool for machine tools"),
                              ("model.compliance", cfg.model.compliance not in (False, None),
                               "gravity compliance belongs to model.kind=joint_dependent")):
            if bad:
                fail(key, f"not with model.kind=axis_perturbation: {why}")
    c = _plain(cfg.constraint.c)
    if not (c is None or c == "auto" or (_is_number(c) and c > 0)):
        fail("constraint.c", f"{c!r}: give null (unconstrained), a positive number (mm per half axis range) or auto")
    for key in ("points", "check_points", "border_k", "border_n"):
        if not _is_int(getattr(cfg.constraint, key)) or getattr(cfg.constraint, key) < 1:
            fail(f"constraint.{key}", f"{getattr(cfg.constraint, key)!r}: give a positive integer")
    if not cfg.constraint.tol > 0 or not cfg.constraint.knee_tol_mm > 0:
        fail("constraint.tol" if not cfg.constraint.tol > 0 else "constraint.knee_tol_mm", "must be positive")
    if cfg.constraint.reference not in ("nominal", "constant"):
        fail("constraint.reference", f"{cfg.constraint.reference!r}: give nominal or constant")
    axes = _plain(cfg.constraint.border_axes)
    if axes is not None and (not isinstance(axes, list) or len(axes) != 2 or len(set(axes)) != 2):
        fail("constraint.border_axes", f"{axes!r}: give two different axis (joint) names")
    sweep = _plain(cfg.constraint.sweep)
    if sweep is not None and (not sweep or not all(_is_number(v) and v > 0 for v in sweep)):
        fail("constraint.sweep", f"{sweep!r}: give a list of positive c values (mm)")

    order = _plain(cfg.model.order)
    if isinstance(order, str):
        if order != "auto":
            fail("model.order", f"'{order}' is not an order; give an int 0..{MAX_ORDER}, a per-joint list, or auto")
    elif _is_int(order):
        if not 0 <= order <= MAX_ORDER:
            fail("model.order", f"{order} is outside 0..{MAX_ORDER}")
    elif isinstance(order, list):
        if not order or not all(_is_int(o) and 0 <= o <= MAX_ORDER for o in order):
            fail("model.order", f"{order}: a per-joint list must hold ints in 0..{MAX_ORDER}")
        if n_joints is not None and len(order) != n_joints:
            fail("model.order", f"has {len(order)} entries but the robot has {n_joints} joints")
    else:
        fail("model.order", f"{order!r}: give an int 0..{MAX_ORDER}, a per-joint list, or auto")

    compliance = _plain(cfg.model.compliance)
    if isinstance(compliance, dict):
        extra = sorted(set(compliance) - {"mode", "joints"})
        if extra:
            fail(f"model.compliance.{extra[0]}", "unknown key; valid keys: mode, joints")
        if compliance.get("mode", "functions") not in ("gravity", "functions"):
            fail("model.compliance.mode", f"{compliance.get('mode')!r}: give \"gravity\" or \"functions\"")
    elif not (isinstance(compliance, bool) or compliance in ("auto", "gravity", "functions")):
        fail("model.compliance", f"{compliance!r}: give true, false, \"gravity\", \"functions\" or {{mode, joints}}")
    fine = _plain(cfg.model.fine)
    if fine is not None:
        if not isinstance(fine, dict):
            fail("model.fine", f"{fine!r}: give null or {{spacing_deg, smoothness_deg, prior_deg, warm_start}}")
        extra = sorted(set(fine) - {"spacing_deg", "smoothness_deg", "prior_deg", "warm_start"})
        if extra:
            fail(f"model.fine.{extra[0]}", "unknown key; valid keys: spacing_deg, smoothness_deg, prior_deg, warm_start")
        for key in ("spacing_deg", "prior_deg"):
            if key in fine and not (_is_number(fine[key]) and fine[key] > 0):
                fail(f"model.fine.{key}", f"{fine[key]!r}: give a positive number (deg)")
        sm = fine.get("smoothness_deg")
        if sm is not None and not ((_is_number(sm) and sm > 0) or (isinstance(sm, list) and all(_is_number(v) and v > 0 for v in sm))):
            fail("model.fine.smoothness_deg", f"{sm!r}: give a positive number or one per joint (deg)")
        if sensor["kind"] is None:
            fail("model.fine", "fine joint tables are offered for sensor runs (sensor.kind) only")
    pstd = sensor["pose_std"]
    if pstd is not None:
        if sensor["kind"] != "pose":
            fail("sensor.pose_std", "applies to sensor.kind=pose")
        if not isinstance(pstd, list) or len(pstd) != 6 or not all(_is_number(v) and v > 0 for v in pstd):
            fail("sensor.pose_std", f"{pstd!r}: give six positive values [sx, sy, sz (mm), srx, sry, srz (deg)]")
    backlash = _plain(cfg.model.backlash)
    if isinstance(backlash, list):
        if not all(_is_int(b) and -1 <= b <= MAX_ORDER for b in backlash):
            fail("model.backlash", f"{backlash}: a per-joint list must hold orders in -1..{MAX_ORDER} (-1: off)")
        if n_joints is not None and len(backlash) != n_joints:
            fail("model.backlash", f"has {len(backlash)} entries but the robot has {n_joints} joints")
    elif not (isinstance(backlash, bool) or (_is_int(backlash) and -1 <= backlash <= MAX_ORDER)):
        fail("model.backlash", f"{backlash!r}: give true, false, or an order 0..{MAX_ORDER}")

    cands = _plain(cfg.model.candidates)
    if not cands or not all(0 <= c <= MAX_ORDER for c in cands):
        fail("model.candidates", f"{cands}: give a non-empty list of orders in 0..{MAX_ORDER}")
    if not _is_int(cfg.model.folds) or cfg.model.folds < 0 or cfg.model.folds == 1:
        fail("model.folds", f"{cfg.model.folds}: give 0 (leave one pose out) or a number of folds >= 2")
    if not cfg.model.margin >= 0:
        fail("model.margin", f"{cfg.model.margin}: give a number of standard errors >= 0")

    if not cfg.noise.sigma_m > 0:
        fail("noise.sigma_m", f"{cfg.noise.sigma_m}: the tracker sigma (mm) must be positive")
    given = [key for key in ("joint_var_fwd", "joint_var_bwd") if getattr(cfg.noise, key) is not None]
    if len(given) == 1:
        other = ({"joint_var_fwd", "joint_var_bwd"} - set(given)).pop()
        fail(f"noise.{other}", f"is null but noise.{given[0]} is set: give both joint variance lists, or neither "
                               "(then the robot's repeatability is used)")
    for key in given:
        var = _plain(getattr(cfg.noise, key))
        if any(v < 0 for v in var):
            fail(f"noise.{key}", f"{var}: variances (deg²) cannot be negative")
        if n_joints is not None and len(var) != n_joints:
            fail(f"noise.{key}", f"has {len(var)} entries but the robot has {n_joints} joints (set one variance per joint)")
    ev = _plain(cfg.model.error_variable)
    choices = ("command", "joint")
    if isinstance(ev, list):
        if not all(e in choices for e in ev):
            fail("model.error_variable", f"{ev}: a per-joint list must hold 'command' or 'joint'")
        if n_joints is not None and len(ev) != n_joints:
            fail("model.error_variable", f"has {len(ev)} entries but the robot has {n_joints} joints")
    elif ev is not None and ev not in choices:
        fail("model.error_variable", f"{ev!r}: give null (the robot's), 'command', 'joint' or a per-joint list")
    if cfg.model.backlash_on not in choices:
        fail("model.backlash_on", f"{cfg.model.backlash_on!r}: give 'joint' (Paper II (13)) or 'command' (through the "
                                  "joint map's coupling)")
    if cfg.model.backlash_on != "joint" and cfg.model.kind == "axis_perturbation":
        fail("model.backlash_on", "a machine tool's axis perturbation model has no backlash term")

    if cfg.prior.enabled:
        for key in ("rotation_deg", "translation_mm", "frame_rotation_deg", "frame_translation_mm"):
            if not getattr(cfg.prior, key) > 0:
                fail(f"prior.{key}", f"{getattr(cfg.prior, key)}: a prior sigma must be positive (or set prior.enabled=false)")
        if cfg.prior.compliance_deg is not None and not cfg.prior.compliance_deg > 0:
            fail("prior.compliance_deg", f"{cfg.prior.compliance_deg}: a prior sigma must be positive (or null)")
        if cfg.prior.backlash_deg is not None and not cfg.prior.backlash_deg > 0:
            fail("prior.backlash_deg", f"{cfg.prior.backlash_deg}: a prior sigma must be positive (or null for the declared ones)")
    if cfg.prior.fleet is not None:
        from ..identify.fleet_prior import METHODS as _FLEET_METHODS

        from ..io.rundir import is_fleet_run

        where = Path(str(cfg.prior.fleet))
        if not is_fleet_run(where):
            fail("prior.fleet", f"{str(where)!r} is not a fleet's run directory (no summary.csv and units/: the folder "
                                "`torchcal fleet` wrote)")
        if cfg.prior.fleet_method not in _FLEET_METHODS:
            fail("prior.fleet_method", f"{cfg.prior.fleet_method!r}: choose from {list(_FLEET_METHODS)}")
        if isinstance(cfg.model.order, str):
            fail("model.order", f"{cfg.model.order!r} with prior.fleet: the unit takes the fleet's orders (give them)")
        if cfg.constraint.c is not None:
            fail("prior.fleet", "not combined with constraint.c (the slope-constrained fit takes no prior blocks yet)")
        if not cfg.prior.enabled:
            fail("prior.fleet", "given with prior.enabled=false: the fleet's distribution is a prior; drop one of them")

    if cfg.solver.method not in SOLVERS:
        fail("solver.method", f"'{cfg.solver.method}' is not a solver; choose from {sorted(SOLVERS)}")
    if cfg.solver.max_iter is not None and cfg.solver.max_iter < 1:
        fail("solver.max_iter", f"{cfg.solver.max_iter}: must be at least 1 (or null for the solver's default)")
    if not cfg.solver.ftol > 0:
        fail("solver.ftol", f"{cfg.solver.ftol}: must be positive")
    if cfg.compensation.tol_deg is not None and not cfg.compensation.tol_deg > 0:
        fail("compensation.tol_deg", f"{cfg.compensation.tol_deg}: must be positive (or null for the default)")
    if cfg.compensation.max_iter is not None and cfg.compensation.max_iter < 1:
        fail("compensation.max_iter", f"{cfg.compensation.max_iter}: must be at least 1 (or null for the default)")

    import torch

    try:
        dev = torch.device(cfg.device)
    except (RuntimeError, ValueError) as exc:
        fail("device", f"'{cfg.device}' is not a torch device ({exc})")
    if check_device and dev.type == "cuda" and not torch.cuda.is_available():
        fail("device", f"'{cfg.device}' requested but CUDA is not available here (use device=cpu)")
    if cfg.threads is not None and cfg.threads < 1:
        fail("threads", f"{cfg.threads}: must be at least 1 (or null to choose by work size)")
    if cfg.out in (None, ""):
        fail("out", "needs a folder for the run directory")


def to_yaml(cfg: FitConfig) -> str:
    """The fully resolved config as YAML (what a run directory's config.yaml holds; :func:`config_from_text`
    reads it back)."""
    # libyaml's emitter where PyYAML has it (the same text; the pure-Python one took ~3 ms a config, a fleet's
    # run writes one per unit)
    return yaml.dump(to_dict(cfg), Dumper=getattr(yaml, "CSafeDumper", yaml.SafeDumper), sort_keys=False,
                     allow_unicode=True)


def to_dict(cfg: FitConfig) -> dict:
    """The fully resolved config as plain Python containers (lists, dicts)."""
    return _plain_value(cfg)


__all__ = [
    "CompensationConfig",
    "ConfigError",
    "DataConfig",
    "FitConfig",
    "ModelConfig",
    "NoiseConfig",
    "PriorConfig",
    "SolverConfig",
    "apply_overrides",
    "repeated_overrides",
    "source_of",
    "check_config",
    "config_from_text",
    "load_config",
    "make_config",
    "run_config",
    "schema",
    "to_dict",
    "to_yaml",
    "updated",
]
