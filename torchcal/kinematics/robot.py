"""Bundled and user robots: a URDF chain plus its controller joint map."""

from __future__ import annotations

import logging
import math
from dataclasses import dataclass
from pathlib import Path

import torch

from ..core import units
from .chain import Chain
from .joint_map import JointMap
from .urdf import URDFError, load_urdf
from ..io import yamlio


@dataclass
class Repeatability:
    """A robot's joint positioning repeatability, the Σ_v of Paper II (32), SI.

    var_fwd / var_bwd: (n,) joint variances (rad², m² for prismatic joints) for
    forward / backward approach (Paper II, Table 5); source: where they come
    from (logged with every fit that uses them).
    """

    var_fwd: torch.Tensor
    var_bwd: torch.Tensor
    source: str = ""

    def to(self, device=None) -> "Repeatability":
        return Repeatability(self.var_fwd.to(device), self.var_bwd.to(device), self.source)


@dataclass
class Robot:
    """A nominal machine: URDF chain + controller joint map (+ where it came from).

    repeatability: the joint variances of its YAML (``repeatability:``), or None.
    """

    name: str
    chain: Chain
    joint_map: JointMap
    source: str = ""
    repeatability: Repeatability | None = None

    @property
    def n(self) -> int:
        return self.chain.n

    def to(self, device=None) -> "Robot":
        rep = None if self.repeatability is None else self.repeatability.to(device)
        return Robot(self.name, self.chain.to(device), self.joint_map.to(device), self.source, rep)

    def with_error_variable(self, error_variable) -> "Robot":
        """The same robot with its joint errors on another variable ('command', 'joint', per-joint list)."""
        return Robot(self.name, self.chain, self.joint_map.with_error_variable(error_variable), self.source,
                     self.repeatability)


def urdf_dir() -> Path:
    """Folder of the bundled URDFs (installed copy first, then the source tree)."""
    here = Path(__file__).resolve().parent.parent
    for candidate in (here / "_urdf", here.parent / "urdf"):
        if candidate.is_dir():
            return candidate
    raise FileNotFoundError("bundled URDF folder not found (expected torchcal/_urdf or ./urdf)")


def bundled_robots() -> list[str]:
    """Names accepted by :func:`load_robot`."""
    return sorted(p.stem for p in urdf_dir().glob("*.yaml"))


LIMIT_TURN = 2 * math.pi + 0.05
"""Limits (in a unit's numbers) within which a joint turns at most about once either way."""


def _refuse_degree_limits(chain: Chain, path) -> None:
    """URDF limits are radians. When most revolute joints reach beyond a full turn either way, they are degrees
    (170 read as 170 rad): the joint ranges, and with them the error polynomials' domain, would be 57x too wide."""
    rev = [i for i in range(chain.n) if not bool(chain.prismatic[i])]
    wide = [i for i in rev if float(chain.limits[i].abs().max()) > LIMIT_TURN]
    if len(wide) >= 2 and 2 * len(wide) >= len(rev):
        shown = ", ".join(f"'{chain.joint_names[i]}' [{float(chain.limits[i, 0]):g}, {float(chain.limits[i, 1]):g}]"
                          for i in wide[:3])
        raise URDFError(f"{path}: {len(wide)} of {len(rev)} revolute joints have limits beyond one turn ({shown}"
                        f"{', ...' if len(wide) > 3 else ''}): URDF limits are radians and these look like degrees "
                        "(rad = deg * pi / 180); or give a joint-map YAML with the controller range in degrees")


REACH_MAX_M = 50.0
"""m: a chain whose link offsets add up to more than this is not a robot or machine in metres (URDF lengths are
SI): a URDF written in millimetres puts a 1 m arm at 1000 m, and every data file would then look 'in metres'."""


def _refuse_mm_lengths(chain: Chain, path) -> None:
    """A URDFError naming the file where the chain's lengths look like millimetres."""
    reach = float(chain.origins[:, :3, 3].norm(dim=-1).sum()) + (0.0 if chain.tip is None else
                                                                  float(chain.tip[:3, 3].norm()))
    if reach > REACH_MAX_M:
        raise URDFError(f"{path}: the link offsets add up to {reach:.4g} m: URDF lengths are metres, and these look "
                        "like millimetres (m = mm / 1000); a robot of that size would be the first")


YAML_KEYS = ("urdf", "end_link", "root_link", "joints", "coupling", "offset", "error_variable", "repeatability")
"""The keys a joint-map YAML may hold (a misspelt one would otherwise be ignored without a word)."""


def _number(value, where: str, label: str) -> float:
    """A YAML entry as a finite float, else a URDFError naming the file and the entry."""
    try:
        out = float(value)
    except (TypeError, ValueError):
        raise URDFError(f"{label}: {where}: {value!r} is not a number") from None
    if out != out or out in (float("inf"), float("-inf")):
        raise URDFError(f"{label}: {where}: {value!r} is not a finite number")
    return out


def _matrix(value, rows: int, cols: int, key: str, label: str) -> list:
    """A YAML list of ``rows`` lists of ``cols`` numbers (cols 0: a flat list of ``rows``), checked entry by entry."""
    if not isinstance(value, list) or len(value) != rows:
        shape = f"{rows} rows of {cols} numbers" if cols else f"{rows} numbers"
        got = f"{len(value)} entries" if isinstance(value, list) else repr(value)
        raise URDFError(f"{label}: '{key}' must hold {shape} (one per joint), got {got}")
    if not cols:
        return [_number(v, f"{key}[{i}]", label) for i, v in enumerate(value)]
    out = []
    for i, row in enumerate(value):
        if not isinstance(row, list) or len(row) != cols:
            got = f"{len(row)} numbers" if isinstance(row, list) else repr(row)
            raise URDFError(f"{label}: {key}[{i}] (URDF joint {i + 1}) must hold {cols} numbers (one per controller "
                            f"joint), got {got}")
        out.append([_number(v, f"{key}[{i}][{j}]", label) for j, v in enumerate(row)])
    return out


def _joint_map_from_yaml(spec: dict, chain: Chain, label: str) -> JointMap:
    unknown = sorted(str(k) for k in spec if k not in YAML_KEYS)
    if unknown:
        import difflib

        hints = [f"'{k}'" + (f" (did you mean '{m[0]}'?)" if (m := difflib.get_close_matches(k, YAML_KEYS, 1)) else "")
                 for k in unknown]
        raise URDFError(f"{label}: unknown key{'s' if len(unknown) > 1 else ''} {', '.join(hints)}; a joint-map YAML "
                        f"holds {', '.join(YAML_KEYS)}")
    joints = spec.get("joints")
    if not isinstance(joints, list) or len(joints) != chain.n:
        raise URDFError(f"{label}: 'joints' must list {chain.n} controller joints (the URDF has {chain.joint_names})")
    names, lims, prismatic = [], [], []
    # every joint's missing keys at once, as a CSV's problems are: a datasheet is typed in one go
    missing = [f"joints[{i}] is missing {', '.join(repr(k) for k in keys)}"
               for i, j in enumerate(joints)
               for keys in [[k for k in ("name", "unit", "lower", "upper") if not isinstance(j, dict) or k not in j]]
               if keys]
    if missing:
        raise URDFError(f"{label}: " + "; ".join(missing))
    for i, j in enumerate(joints):
        if j["unit"] not in ("deg", "mm"):
            raise URDFError(f"{label}: joints[{i}] ('{j['name']}') unit must be 'deg' or 'mm', got {j['unit']!r}")
        names.append(str(j["name"]))
        prismatic.append(j["unit"] == "mm")
        lims.append([_number(j["lower"], f"joints[{i}] ('{j['name']}') lower", label),
                     _number(j["upper"], f"joints[{i}] ('{j['name']}') upper", label)])
    twice = sorted({n for n in names if names.count(n) > 1})
    if twice:
        raise URDFError(f"{label}: joint name{'s' if len(twice) > 1 else ''} {twice} given twice in 'joints'; each "
                        "controller joint needs its own (the files' q1..qN columns and the reports use them)")
    prismatic_t = torch.tensor(prismatic)
    if not torch.equal(prismatic_t, chain.prismatic):
        bad = [f"joints[{i}] '{names[i]}' (URDF joint '{chain.joint_names[i]}'): unit "
               f"'{joints[i]['unit']}' ({'prismatic' if prismatic[i] else 'revolute'}) but the URDF joint is "
               f"{'prismatic' if bool(chain.prismatic[i]) else 'revolute'}"
               for i in range(chain.n) if prismatic[i] != bool(chain.prismatic[i])]
        raise URDFError(f"{label}: controller units do not match the URDF joint types: " + "; ".join(bad)
                        + " (unit 'mm' = prismatic, 'deg' = revolute)")
    turn = [f"'{names[i]}' [{lims[i][0]:g}, {lims[i][1]:g}]" for i in range(chain.n) if not prismatic[i]]
    if turn and all(max(abs(v) for v in lims[i]) <= LIMIT_TURN for i in range(chain.n) if not prismatic[i]):
        raise URDFError(f"{label}: every revolute joint's limits lie within +-{LIMIT_TURN:.2f} ({', '.join(turn[:3])}"
                        f"{', ...' if len(turn) > 3 else ''}): they look like radians; a joint map's limits are the "
                        "controller's, in degrees (deg = rad * 180 / pi)")
    narrow = [f"joints[{i}] '{names[i]}' [{lims[i][0]:g}, {lims[i][1]:g}]" for i in range(chain.n)
              if not prismatic[i] and max(abs(v) for v in lims[i]) <= LIMIT_TURN]
    if narrow:  # one joint typed in radians among degrees: the robot would be held within a few degrees there
        logging.getLogger("torchcal").warning(
            "%s: %s: limits within +-%.2f deg, narrow for a robot joint; a joint map's limits are degrees "
            "(radians typed here?)", label, ", ".join(narrow), LIMIT_TURN)
    scale = units.joint_scale(prismatic_t)
    limits = torch.tensor(lims, dtype=torch.float64) * scale[:, None]
    coupling = torch.tensor(_matrix(spec.get("coupling", torch.eye(chain.n).tolist()), chain.n, chain.n, "coupling",
                                    label), dtype=torch.float64)
    # coupling maps controller units to joint units; both scale the same way per joint type
    coupling = coupling * scale[:, None] / scale[None, :]
    offset = torch.tensor(_matrix(spec.get("offset", [0.0] * chain.n), chain.n, 0, "offset", label),
                          dtype=torch.float64) * scale
    try:
        return JointMap(names, coupling, offset, limits, prismatic_t, spec.get("error_variable", "command"))
    except ValueError as exc:
        raise URDFError(f"{label}: {exc}") from None


def _repeatability_from_yaml(spec: dict, jm: JointMap, label: str) -> Repeatability | None:
    rep = spec.get("repeatability")
    if rep is None:
        return None
    if not isinstance(rep, dict):
        raise URDFError(f"{label}: 'repeatability' must be a mapping with joint_var_fwd, joint_var_bwd (deg², mm²) and source")
    out = []
    for key in ("joint_var_fwd", "joint_var_bwd"):
        var = rep.get(key)
        if not isinstance(var, list) or len(var) != jm.n:
            raise URDFError(f"{label}: repeatability.{key} must list {jm.n} variances (deg², mm² for prismatic joints)")
        try:
            t = torch.tensor([float(x) for x in var], dtype=torch.float64)
        except (TypeError, ValueError):
            raise URDFError(f"{label}: repeatability.{key}: {var} is not a list of numbers") from None
        if (t < 0).any() or not torch.isfinite(t).all():
            raise URDFError(f"{label}: repeatability.{key}: variances must be finite and non-negative, got {var}")
        out.append(t * units.joint_scale(jm.prismatic) ** 2)
    return Repeatability(out[0], out[1], str(rep.get("source", label)))


def load_robot(spec: str | Path) -> Robot:
    """Load a bundled robot by name, a joint-map YAML, or a bare URDF.

    - ``"fanuc_lrmate200i"``: bundled ``urdf/<name>.yaml`` (+ its URDF);
    - ``path/to/robot.yaml``: a joint map naming its URDF (relative to the YAML);
    - ``path/to/robot.urdf``: identity joint map, limits from the URDF.

    Example:
        >>> robot = load_robot("fanuc_lrmate200i")
        >>> robot.n, robot.joint_map.names[2], robot.joint_map.error_variable[2], robot.repeatability is not None
        (6, 'J3', 'command', True)
    """
    spec_s = str(spec)
    path = Path(spec_s)
    bundled = not path.suffix and not path.exists()
    if not path.suffix and path.is_dir() and (urdf_dir() / f"{spec_s}.yaml").is_file():
        # a local folder that happens to share a bundled robot's name (e.g. a data folder 'ur10') is not a robot file
        found = sorted(p.name for p in path.glob("*.urdf"))
        if not found:
            bundled = True
            logging.getLogger("torchcal").warning(
                "robot '%s': the local folder './%s' holds no URDF; using the bundled robot '%s'", spec_s, spec_s, spec_s)
        else:
            raise URDFError(f"robot '{spec_s}': './{spec_s}' is a local folder (holding {found[:5]}), which hides the "
                            f"bundled robot of that name; give the file inside it (e.g. {path / found[0]}) or run "
                            f"from another folder to use the bundled '{spec_s}'")
    if bundled:
        path = urdf_dir() / f"{spec_s}.yaml"
        if not path.is_file():
            raise URDFError(f"unknown robot '{spec_s}'; bundled robots: {bundled_robots()}")
    if path.suffix.lower() == ".urdf":
        chain = load_urdf(path)
        if torch.isnan(chain.limits).any():
            missing = [n for n, l in zip(chain.joint_names, chain.limits) if torch.isnan(l).any()]
            raise URDFError(f"{path}: joints {missing} have no limits; give a joint-map YAML with the controller range")
        _refuse_degree_limits(chain, path)
        _refuse_mm_lengths(chain, path)
        return Robot(chain.name or path.stem, chain, JointMap.identity(chain.limits, chain.prismatic, list(chain.joint_names)), str(path))
    if not path.is_file():
        raise URDFError(f"{path}: " + ("is a directory, not a robot file (joint-map .yaml or .urdf)" if path.is_dir()
                                       else "robot file not found"))
    spec_d = yamlio.safe_load(path.read_text())
    if not isinstance(spec_d, dict) or "urdf" not in spec_d:
        raise URDFError(f"{path}: a joint-map YAML needs a 'urdf' key")
    chain = load_urdf(path.parent / spec_d["urdf"], end_link=spec_d.get("end_link"), root_link=spec_d.get("root_link"))
    _refuse_mm_lengths(chain, path.parent / spec_d["urdf"])
    # a bundled robot is recorded by name so that saved models reload on any install
    jm = _joint_map_from_yaml(spec_d, chain, str(path))
    return Robot(path.stem, chain, jm, spec_s if bundled else str(path.resolve()),
                 _repeatability_from_yaml(spec_d, jm, str(path)))


class ChainBuffers:
    """Mixin for ``nn.Module`` models of a robot or machine: the nominal chain and joint map as buffers.

    :meth:`register_chain` stores origins, axes, prismatic, tip, coupling, offset and
    command_limits (what the functional FK and the joint map need, moved by ``.to()``);
    ``n``, ``dtype`` and ``device`` follow them.
    """

    def register_chain(self, robot: Robot) -> None:
        chain, jm = robot.chain, robot.joint_map
        for name, t in (("origins", chain.origins), ("axes", chain.axes), ("prismatic", chain.prismatic),
                        ("tip", chain.tip), ("coupling", jm.coupling), ("offset", jm.offset),
                        ("command_limits", jm.limits)):
            self.register_buffer(name, t.clone())

    @property
    def n(self) -> int:
        return self.origins.shape[0]

    @property
    def dtype(self) -> torch.dtype:
        return self.origins.dtype

    @property
    def device(self) -> torch.device:
        return self.origins.device

    def check_commands(self, q, where: str) -> None:
        """Raise :class:`~torchcal.core.exceptions.InputError` naming ``where`` for commands that are not a
        (B, n) tensor of the model's dtype and device (torch's own message names none of them). Shapes and
        dtypes only, no values: nothing here waits for a GPU. Inside a torch.func transform (rows vmapped one
        by one) the shape is the transform's business."""
        from ..core.exceptions import InputError

        if not isinstance(q, torch.Tensor):
            raise InputError(f"{where}: q must be a torch tensor (B, {self.n}) of commands (rad / m), got "
                             f"{type(q).__name__}; torch.as_tensor(q, dtype={self.dtype}) converts an array")
        if torch._C._functorch.peek_interpreter_stack() is not None:
            return
        if q.ndim != 2 or q.shape[1] != self.n:
            raise InputError(f"{where}: q must be (B, {self.n}) commands, got shape {tuple(q.shape)}"
                             + ("; q[None] makes one pose a batch" if q.ndim == 1 and q.shape[0] == self.n else ""))
        if q.dtype != self.dtype:
            raise InputError(f"{where}: q is {q.dtype}, the model {self.dtype}: convert one of them "
                             f"(q.to({self.dtype}) or model.to({q.dtype}))")
        if q.device != self.device:
            raise InputError(f"{where}: q is on {q.device}, the model on {self.device}: move one of them")
