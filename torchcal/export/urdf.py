"""A calibrated URDF: the constant part of the identified errors folded into the joint origins.

The model's chain is ``T_0 · Π_i origin_i · E_i(θ_i, s_i) · joint_i(θ_i)`` (Paper II (19), (26);
:func:`torchcal.kinematics.fk.chain_frames`). A URDF can only hold fixed
transforms, so the export keeps

    origin_i' = origin_i · E_i^0,      E_i^0 = twist_to_transform(coef[i, :, 0])

the error transform with only its order-0 Chebyshev coefficients (the constant
of each series, not its value at any particular joint angle), and puts the base
correction E(b) (26) in front of the first joint (``base='joint'``) or on a new
fixed root joint (``base='link'``). Everything that depends on the joint
variables (orders >= 1), backlash (depends on the approach direction), the tool
corrections (not part of the robot) and any joint compliance stay in the
torchcal model; :func:`compare_urdf` states what leaving them out costs on
measured data. The joint map (controller -> URDF coupling, offsets, limits) is
written unchanged next to the URDF when the robot has one.
"""

from __future__ import annotations

import copy
import xml.etree.ElementTree as ET
from dataclasses import dataclass
from pathlib import Path

import torch
import yaml

from ..core import units
from ..io.atomic import atomic_write_text
from ..analysis.stats import ResidualStats, point_residuals, residual_stats, stats_table
from ..kinematics.robot import Robot, load_robot, urdf_dir
from ..kinematics.transforms import homogeneous, invert, matrix_to_rpy, rpy_to_matrix, twist_to_transform
from ..kinematics.urdf import URDFError, validate_urdf
from ..io import yamlio


# ------------------------------------------------------------------ transforms
def constant_origins(model, base: bool = True, measurement_frame: bool = False) -> torch.Tensor:
    """Chain-level joint origins with the constant errors folded in, (n, 4, 4).

    origins[i] · E_i^0 for every joint; with ``base`` the base correction E(b)
    (and with ``measurement_frame`` also the nominal measurement frame
    T_0^m's nominal part) is multiplied in front of the first one, so that
    ``chain_fk(result, axes, prismatic, θ, None, tip)`` is the model with every
    order >= 1 coefficient and backlash zeroed, in the robot's nominal base
    frame (or the measurement frame).
    """
    je = model.joint_errors
    with torch.no_grad():
        c0 = (je.coef * je.mask)[..., 0]  # (n, 6)
        out = model.origins @ twist_to_transform(c0)
        front = None
        if base:
            front = model.base.correction()
        if measurement_frame:
            front = model.base.nominal if front is None else model.base.nominal @ front
        if front is not None:
            out = torch.cat([(front @ out[0])[None], out[1:]])
    return out.detach()


def _fmt(values) -> str:
    return " ".join(repr(float(v)) for v in values)


def _element_origin(joint: ET.Element) -> torch.Tensor:
    o = joint.find("origin")
    xyz = [0.0, 0.0, 0.0] if o is None or o.get("xyz") is None else [float(v) for v in o.get("xyz").split()]
    rpy = [0.0, 0.0, 0.0] if o is None or o.get("rpy") is None else [float(v) for v in o.get("rpy").split()]
    return homogeneous(rpy_to_matrix(torch.tensor(rpy, dtype=torch.float64)), torch.tensor(xyz, dtype=torch.float64))


def _set_origin(joint: ET.Element, T: torch.Tensor) -> None:
    o = joint.find("origin")
    if o is None:
        o = ET.Element("origin")
        joint.insert(0, o)
    o.set("xyz", _fmt(T[:3, 3].tolist()))
    o.set("rpy", _fmt(matrix_to_rpy(T[:3, :3].detach().to("cpu", torch.float64)).tolist()))


# ---------------------------------------------------------------------- sources
def _source_files(robot: Robot, source_urdf=None) -> tuple[Path, dict | None, Path | None]:
    """(URDF path, joint-map YAML dict or None, YAML path or None) the robot was loaded from."""
    if source_urdf is not None:
        return Path(source_urdf), None, None
    src = robot.source or robot.name
    path = Path(src)
    if not path.suffix and not path.exists():
        path = urdf_dir() / f"{src}.yaml"
    if path.suffix.lower() == ".urdf":
        return path, None, None
    if path.suffix.lower() in (".yaml", ".yml") and path.is_file():
        spec = yamlio.safe_load(path.read_text())
        return (path.parent / spec["urdf"]).resolve(), spec, path
    raise URDFError(f"export: cannot find the source URDF of robot '{robot.name}' (source {src!r}); pass source_urdf=")


def _chain_path(root: ET.Element, root_link: str, end_link: str, label: str) -> list[ET.Element]:
    """Joint elements from root_link to end_link, in order."""
    by_child = {j.find("child").get("link"): j for j in root.findall("joint")}
    path, link = [], end_link
    while link != root_link:
        if link not in by_child:
            raise URDFError(f"{label}: link '{end_link}' is not below root link '{root_link}'")
        j = by_child[link]
        path.append(j)
        link = j.find("parent").get("link")
        if len(path) > len(by_child):
            raise URDFError(f"{label}: kinematic loop through joint '{j.get('name')}'")
    return path[::-1]


# ----------------------------------------------------------------------- export
@dataclass
class UrdfExport:
    """What :func:`export_urdf` wrote.

    urdf: the calibrated URDF; joint_map: the joint-map YAML next to it (None
    when the source was a bare URDF: the identity map then comes from the URDF's
    limits, as before); robot: the written robot loaded back with
    :func:`torchcal.kinematics.load_robot`; base: 'joint', 'link' or 'none';
    measurement_frame: whether the nominal measurement frame is in the URDF.
    """

    urdf: Path
    joint_map: Path | None
    robot: Robot
    base: str
    measurement_frame: bool

    @property
    def path(self) -> Path:
        """What to hand to :func:`load_robot`: the YAML when there is one, else the URDF."""
        return self.joint_map or self.urdf


def export_urdf(model, path, base: str = "joint", measurement_frame: bool = False, source_urdf=None,
                name: str | None = None) -> UrdfExport:
    """Write a calibrated URDF (and its joint-map YAML) for ``model``.

    model: a fitted :class:`torchcal.models.robot.RobotModel`; path: the .urdf to
    write (a joint-map YAML with the same stem is written next to it when the
    robot has one); base: 'joint' (fold the base correction into the first
    movable joint's origin), 'link' (a new root link '<root>_nominal' with a
    fixed joint carrying it; a YAML root_link is updated) or 'none' (leave it
    out); measurement_frame: also fold in the model's nominal measurement frame,
    so the URDF's root is the tracker frame; source_urdf: the URDF to start from
    when the robot does not record it; name: robot name in the file.
    Only joint origins change (and the root link with base='link'); links,
    limits, meshes and every other element are copied. The result is
    validated and loaded back with torchcal's loader and yourdfpy.
    """
    if base not in ("joint", "link", "none"):
        raise ValueError(f"export_urdf: base must be 'joint', 'link' or 'none', got {base!r}")
    robot = model.robot
    chain = robot.chain
    src, spec, spec_path = _source_files(robot, source_urdf)
    label = str(src)
    tree = ET.parse(src, parser=ET.XMLParser(target=ET.TreeBuilder(insert_comments=True)))
    root = tree.getroot()
    if name is not None:
        root.set("name", name)
    joints = _chain_path(root, chain.root_link, chain.end_link, label)
    movable = [j for j in joints if j.get("type") != "fixed"]
    if [j.get("name") for j in movable] != list(chain.joint_names):
        raise URDFError(f"{label}: movable joints {[j.get('name') for j in movable]} do not match the model's {chain.joint_names}")
    if not torch.allclose(_chain_origins(joints), chain.origins.cpu(), atol=1e-12):
        raise URDFError(f"{label}: this URDF's joint origins differ from the model's nominal chain; pass the robot's source_urdf")

    front_in_joint = base == "joint"
    target = constant_origins(model, base=front_in_joint, measurement_frame=measurement_frame and front_in_joint).cpu()
    pending = torch.eye(4, dtype=torch.float64)
    i = 0
    for j in joints:
        if j.get("type") == "fixed":
            pending = pending @ _element_origin(j)
            continue
        _set_origin(j, invert(pending) @ target[i])
        pending = torch.eye(4, dtype=torch.float64)
        i += 1

    root_link = chain.root_link
    if base == "link" or (measurement_frame and not front_in_joint):
        front = torch.eye(4, dtype=torch.float64)
        with torch.no_grad():
            if base == "link":
                front = model.base.correction().detach().cpu()
            if measurement_frame:
                front = model.base.nominal.cpu() @ front
        new_root = f"{chain.root_link}_nominal" if not measurement_frame else f"{chain.root_link}_measurement"
        link = ET.Element("link", {"name": new_root})
        fixed = ET.Element("joint", {"name": f"{chain.root_link}_calibration", "type": "fixed"})
        ET.SubElement(fixed, "parent", {"link": new_root})
        ET.SubElement(fixed, "child", {"link": chain.root_link})
        _set_origin(fixed, front)
        first = next(k for k, e in enumerate(list(root)) if e.tag in ("link", "joint"))
        root.insert(first, link)
        root.insert(first + 1, fixed)
        root_link = new_root
    root.insert(0, ET.Comment(
        f" calibrated by torchcal: joint origins carry the constant (order-0) error terms"
        f"{', base correction as ' + base if base != 'none' else ''}"
        f"{', measurement frame included' if measurement_frame else ''};"
        " joint-dependent terms, backlash and tool corrections are not in this file "))

    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    ET.indent(tree)
    xml = '<?xml version="1.0"?>\n' + ET.tostring(root, encoding="unicode") + "\n"
    problems = validate_urdf(xml, str(path))
    if problems:
        raise URDFError(f"{path}: exported URDF failed validation:\n  " + "\n  ".join(problems))
    atomic_write_text(path, xml)

    yaml_path = None
    if spec is not None:
        out = copy.deepcopy(spec)
        out["urdf"] = path.name
        # the remainder's series follow the model's error variables, whatever the source YAML said
        ev = list(getattr(model, "error_variable", robot.joint_map.error_variable))
        out["error_variable"] = ev[0] if len(set(ev)) == 1 else ev
        if "root_link" in out or root_link != chain.root_link:
            out["root_link"] = root_link
        out.setdefault("end_link", chain.end_link)
        yaml_path = path.with_suffix(".yaml")
        header = f"# joint map of {robot.name}, unchanged; the URDF carries torchcal's calibrated joint origins\n"
        atomic_write_text(yaml_path, header + yaml.safe_dump(out, sort_keys=False, default_flow_style=None))
    loaded = load_robot(yaml_path or path)
    _check_joint_map(robot, loaded)
    return UrdfExport(path, yaml_path, loaded, base, measurement_frame)


def _chain_origins(joints: list[ET.Element]) -> torch.Tensor:
    """Chain-level origins (fixed joints folded into the next movable one) of a joint path."""
    pending, out = torch.eye(4, dtype=torch.float64), []
    for j in joints:
        T = pending @ _element_origin(j)
        if j.get("type") == "fixed":
            pending = T
        else:
            out.append(T)
            pending = torch.eye(4, dtype=torch.float64)
    return torch.stack(out)


def _check_joint_map(robot: Robot, loaded: Robot) -> None:
    a, b = robot.joint_map, loaded.joint_map
    for key in ("coupling", "offset", "limits"):
        if not torch.allclose(getattr(a, key).cpu(), getattr(b, key).cpu(), rtol=0, atol=1e-12):
            raise URDFError(f"export: the written joint map's {key} differs from the model's")


# ------------------------------------------------------------------ comparison
def urdf_only_model(model, export: UrdfExport):
    """A :class:`RobotModel` of the exported URDF with no error terms: what a URDF-only user gets.

    Keeps the model's identified tool vectors and (unless the URDF holds it)
    its nominal measurement frame; joint errors, backlash and compliance are zero.
    """
    from ..models.robot import RobotModel

    with torch.no_grad():
        tools = model.tools().detach().clone()
    base_nominal = None if export.measurement_frame else model.base.nominal.detach().clone()
    out = RobotModel(export.robot.to(model.device), tools, orders=0, backlash=None, base_nominal=base_nominal,
                     error_variable=getattr(model, "error_variable", None))
    return out.to(model.device)


@dataclass
class UrdfComparison:
    """Residual statistics (mm) on one data set: nominal, URDF-only and full model.

    urdf: the exported URDF (constant terms + base) with the model's tools; full:
    the torchcal model with every term. Residuals are |p - xyz| with the joint
    errors v at zero (:func:`torchcal.analysis.stats.point_residuals`).
    """

    nominal: ResidualStats
    urdf: ResidualStats
    full: ResidualStats
    residuals_mm: dict

    def table(self) -> list[dict]:
        """Table rows (mm) with the decrease against the nominal model, see :func:`stats_table`."""
        return stats_table({"Nominal": self.nominal, "URDF (constant terms)": self.urdf, "Full model": self.full}, "Nominal")

    def summary(self) -> dict:
        return {row["label"]: {k: v for k, v in row.items() if k != "label"} for row in self.table()}


def compare_urdf(model, export: UrdfExport, data) -> UrdfComparison:
    """Residuals of the nominal robot, the exported URDF alone and the full model on ``data``, in mm."""
    urdf_model = urdf_only_model(model, export)
    res = {
        "nominal": point_residuals(model, data, nominal=True),
        "urdf": point_residuals(urdf_model, data),
        "full": point_residuals(model, data),
    }
    mm = {k: units.m_to_mm(v) for k, v in res.items()}
    return UrdfComparison(residual_stats(mm["nominal"]), residual_stats(mm["urdf"]), residual_stats(mm["full"]), mm)
