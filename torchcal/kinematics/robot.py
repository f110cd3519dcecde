"""Bundled and user robots: a URDF chain plus its controller joint map."""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import torch
import yaml

from .. import units
from .chain import Chain
from .joint_map import JointMap
from .urdf import URDFError, load_urdf


@dataclass
class Robot:
    """A nominal machine: URDF chain + controller joint map (+ where it came from)."""

    name: str
    chain: Chain
    joint_map: JointMap
    source: str = ""

    @property
    def n(self) -> int:
        return self.chain.n

    def to(self, device=None) -> "Robot":
        return Robot(self.name, self.chain.to(device), self.joint_map.to(device), self.source)


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


def _joint_map_from_yaml(spec: dict, chain: Chain, label: str) -> JointMap:
    joints = spec.get("joints")
    if not isinstance(joints, list) or len(joints) != chain.n:
        raise URDFError(f"{label}: 'joints' must list {chain.n} controller joints (the URDF has {chain.joint_names})")
    names, lims, prismatic = [], [], []
    for i, j in enumerate(joints):
        for key in ("name", "unit", "lower", "upper"):
            if key not in j:
                raise URDFError(f"{label}: joints[{i}] is missing '{key}'")
        if j["unit"] not in ("deg", "mm"):
            raise URDFError(f"{label}: joints[{i}] ('{j['name']}') unit must be 'deg' or 'mm', got {j['unit']!r}")
        names.append(str(j["name"]))
        prismatic.append(j["unit"] == "mm")
        lims.append([float(j["lower"]), float(j["upper"])])
    prismatic_t = torch.tensor(prismatic)
    if not torch.equal(prismatic_t, chain.prismatic):
        raise URDFError(f"{label}: controller units {[j['unit'] for j in joints]} do not match the URDF joint types")
    scale = units.joint_scale(prismatic_t)
    limits = torch.tensor(lims, dtype=torch.float64) * scale[:, None]
    coupling = torch.tensor(spec.get("coupling", torch.eye(chain.n).tolist()), dtype=torch.float64)
    if coupling.shape != (chain.n, chain.n):
        raise URDFError(f"{label}: coupling must be {chain.n}x{chain.n}, got {tuple(coupling.shape)}")
    # coupling maps controller units to joint units; both scale the same way per joint type
    coupling = coupling * scale[:, None] / scale[None, :]
    offset = torch.tensor(spec.get("offset", [0.0] * chain.n), dtype=torch.float64) * scale
    try:
        return JointMap(names, coupling, offset, limits, prismatic_t)
    except ValueError as exc:
        raise URDFError(f"{label}: {exc}") from None


def load_robot(spec: str | Path) -> Robot:
    """Load a bundled robot by name, a joint-map YAML, or a bare URDF.

    - ``"fanuc_lrmate200i"``: bundled ``urdf/<name>.yaml`` (+ its URDF);
    - ``path/to/robot.yaml``: a joint map naming its URDF (relative to the YAML);
    - ``path/to/robot.urdf``: identity joint map, limits from the URDF.
    """
    spec_s = str(spec)
    path = Path(spec_s)
    bundled = not path.suffix and not path.exists()
    if bundled:
        path = urdf_dir() / f"{spec_s}.yaml"
        if not path.is_file():
            raise URDFError(f"unknown robot '{spec_s}'; bundled robots: {bundled_robots()}")
    if path.suffix.lower() == ".urdf":
        chain = load_urdf(path)
        if torch.isnan(chain.limits).any():
            missing = [n for n, l in zip(chain.joint_names, chain.limits) if torch.isnan(l).any()]
            raise URDFError(f"{path}: joints {missing} have no limits; give a joint-map YAML with the controller range")
        return Robot(chain.name or path.stem, chain, JointMap.identity(chain.limits, chain.prismatic, list(chain.joint_names)), str(path))
    if not path.is_file():
        raise URDFError(f"{path}: robot file not found")
    spec_d = yaml.safe_load(path.read_text())
    if not isinstance(spec_d, dict) or "urdf" not in spec_d:
        raise URDFError(f"{path}: a joint-map YAML needs a 'urdf' key")
    chain = load_urdf(path.parent / spec_d["urdf"], end_link=spec_d.get("end_link"), root_link=spec_d.get("root_link"))
    # a bundled robot is recorded by name so that saved models reload on any install
    return Robot(path.stem, chain, _joint_map_from_yaml(spec_d, chain, str(path)), spec_s if bundled else str(path.resolve()))
