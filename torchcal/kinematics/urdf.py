"""URDF -> :class:`Chain` in float64, validated with yourdfpy.

pytorch-kinematics' parser reads the XML; we build our own float64 tensors
because its chain builder rounds joint origins to float32 (FK off by ~3e-8 m
even after ``.to(float64)``) and its static offsets cannot carry per-pose
error transforms. pytorch-kinematics' chain stays a cross-check in the tests.
"""

from __future__ import annotations

import importlib
import importlib.util
import io
import logging
import math
import sys
from pathlib import Path

import numpy as np
import torch

from ..core.exceptions import TorchcalError
from .chain import Chain
from .transforms import homogeneous, rpy_to_matrix


class URDFError(TorchcalError, ValueError):
    """A URDF that cannot be used; the message names the file and the joints at fault."""


_PARSER_ALIAS = "torchcal.kinematics._pk_urdf_parser_py"
_PARSER_MODULE = "pytorch_kinematics.urdf_parser_py.urdf"


def urdf_parser():
    """pytorch-kinematics' URDF parser (the module ``pytorch_kinematics.urdf_parser_py.urdf``), imported fast.

    ``import pytorch_kinematics`` runs the package's ``__init__``, which loads the
    whole library (chains, IK, arm_pytorch_utilities and with it matplotlib): about
    1 s of every command, for a parser that needs only lxml and yaml. So the
    parser's own files are loaded once under a private name; where pytorch_kinematics
    is imported already, or its files are not laid out as expected, the regular
    import serves. The code that parses is pytorch-kinematics' either way.
    """
    for name in (_PARSER_MODULE, _PARSER_ALIAS + ".urdf"):
        if name in sys.modules:
            return sys.modules[name]
    if "pytorch_kinematics" not in sys.modules:
        try:
            spec = importlib.util.find_spec("pytorch_kinematics")  # finds the package without running its __init__
            root = Path(next(iter(spec.submodule_search_locations))) / "urdf_parser_py"
            pkg_spec = importlib.util.spec_from_file_location(_PARSER_ALIAS, root / "__init__.py",
                                                              submodule_search_locations=[str(root)])
            pkg = importlib.util.module_from_spec(pkg_spec)
            sys.modules[_PARSER_ALIAS] = pkg
            pkg_spec.loader.exec_module(pkg)
            return sys.modules[_PARSER_ALIAS + ".urdf"]
        except Exception:  # another layout: forget the partial copy, import the regular way
            for name in [m for m in sys.modules if m == _PARSER_ALIAS or m.startswith(_PARSER_ALIAS + ".")]:
                del sys.modules[name]
    return importlib.import_module(_PARSER_MODULE)


def read_urdf_text(source: str | Path) -> tuple[str, str]:
    """(xml text, label for messages) from a path or an XML string."""
    if isinstance(source, Path) or (isinstance(source, str) and not source.lstrip().startswith("<")):
        path = Path(source)
        if not path.is_file():
            raise URDFError(f"{path}: " + ("is a directory, not a URDF file" if path.is_dir() else "URDF file not found"))
        return path.read_text(), str(path)
    return str(source), "<urdf string>"


def _validated_marker(xml: str) -> Path | None:
    """Where a passed validation of exactly this text is remembered (None: no cache directory).

    yourdfpy pulls trimesh, networkx and scipy: 1-3 s of imports on every
    CLI run for a URDF that passed before. The key is the text's hash with
    the torchcal and yourdfpy versions, so an edit or an upgrade validates
    again; ``TORCHCAL_CACHE`` moves the directory (default
    ``~/.cache/torchcal``), ``TORCHCAL_CACHE=off`` disables it.
    """
    import hashlib
    import os
    from importlib.metadata import PackageNotFoundError, version

    root = os.environ.get("TORCHCAL_CACHE") or str(Path.home() / ".cache" / "torchcal")
    if root.lower() == "off":
        return None
    try:
        versions = f"{version('torchcal')}|{version('yourdfpy')}|rules {VALIDATION_RULES}"
    except PackageNotFoundError:
        return None
    key = hashlib.sha256((versions + "\0" + xml).encode()).hexdigest()
    return Path(root) / "urdf-valid" / key


VALIDATION_RULES = 2
"""Raised when :func:`_validate_urdf` checks more, so that texts validated under the older rules are checked again
(2: finite origins, axes and limits)."""


def validate_urdf(xml: str, label: str = "<urdf string>") -> list[str]:
    """Problems found by yourdfpy's validator plus our own kinematic checks, each naming its joint.

    A text that passed once is not validated again (:func:`_validated_marker`)."""
    marker = _validated_marker(xml)
    if marker is not None and marker.is_file():
        return []
    problems = _validate_urdf(xml)
    if not problems and marker is not None:
        try:
            marker.parent.mkdir(parents=True, exist_ok=True)
            marker.touch()
        except OSError:  # a read-only home only costs the next run the validation
            pass
    return problems


def _validate_urdf(xml: str) -> list[str]:
    import yourdfpy

    problems: list[str] = []
    try:
        # yourdfpy logs parse warnings for every missing optional tag; keep the console quiet
        logging.getLogger("yourdfpy").setLevel(logging.ERROR)
        model = yourdfpy.URDF.load(io.StringIO(xml), build_scene_graph=False, load_meshes=False)
    except Exception as exc:  # lxml / yourdfpy raise many types for malformed XML
        return [f"not a readable URDF ({type(exc).__name__}: {exc})"]
    robot = model.robot
    for joint in robot.joints:
        model._errors = []
        model._validate_joint(joint)
        problems += [f"joint '{joint.name}': {err}" for err in model._errors]
        # a NaN origin or axis passed (a zero-vector test is False for NaN) and made a chain that planned poses
        # and crashed the fit in a Cholesky factorization
        if joint.origin is not None and not np.isfinite(np.asarray(joint.origin, dtype=float)).all():
            problems.append(f"joint '{joint.name}': <origin> holds a value that is not a finite number")
        if joint.axis is not None and not np.isfinite(np.asarray(joint.axis, dtype=float)).all():
            problems.append(f"joint '{joint.name}': <axis> holds a value that is not a finite number")
        if joint.limit is not None and any(v is not None and not math.isfinite(float(v))
                                             for v in (joint.limit.lower, joint.limit.upper)):
            problems.append(f"joint '{joint.name}': <limit> lower / upper must be finite numbers")
        if joint.type in ("revolute", "prismatic", "continuous") and joint.axis is not None:
            if float(sum(a * a for a in joint.axis)) < 1e-24:
                problems.append(f"joint '{joint.name}': axis is the zero vector")
        if joint.type in ("floating", "planar"):
            problems.append(f"joint '{joint.name}': type '{joint.type}' is not a serial-chain joint torchcal supports")
        if joint.mimic is not None:
            problems.append(f"joint '{joint.name}': <mimic> joints are not supported; express coupling in the joint map")
    for link in robot.links:
        model._errors = []
        model._validate_link(link)
        problems += [f"link '{link.name}': {err}" for err in model._errors if "geometry" not in str(err).lower()]
    names = [j.name for j in robot.joints]
    dup = {n for n in names if names.count(n) > 1}
    problems += [f"joint '{n}': name used more than once" for n in sorted(dup)]
    return problems


def _check_well_formed(xml: str, label: str):
    """A strict XML parse first: the URDF parsers recover from a truncated file and fail later with a TypeError.
    -> the parsed root element."""
    import xml.etree.ElementTree as ET

    try:
        root = ET.fromstring(xml.encode() if isinstance(xml, str) else xml)
    except ET.ParseError as exc:
        tail = "" if xml.rstrip().endswith("</robot>") else "; the file does not end with </robot>: is it truncated?"
        raise URDFError(f"{label}: not a readable URDF: not well-formed XML ({exc}){tail}") from None
    if root.tag != "robot":
        raise URDFError(f"{label}: the root element is <{root.tag}>, a URDF's is <robot>")
    missing = []
    for owner in root:
        if owner.tag not in ("joint", "link"):
            continue
        for el in owner.iter():
            lack = [a for a in _REQUIRED_ATTRIBUTES.get(el.tag, ()) if el.get(a) is None]
            if lack:
                missing.append(f"{owner.tag} '{owner.get('name')}': <{el.tag}> has no {', '.join(lack)}")
    if missing:
        raise URDFError(f"{label}: incomplete URDF (a line cut or deleted?): " + "; ".join(missing))
    return root


_REQUIRED_ATTRIBUTES = {"joint": ("name", "type"), "link": ("name",), "parent": ("link",), "child": ("link",),
                        "axis": ("xyz",), "mass": ("value",), "inertia": ("ixx", "ixy", "ixz", "iyy", "iyz", "izz")}
"""Attributes the URDF spec requires and the parsers dereference without checking (a TypeError otherwise)."""


def _joints_without_axis(root) -> set[str]:
    """Names of the joints of the parsed URDF ``root`` that have no <axis> element (URDF default: x)."""
    return {j.get("name") for j in root.iter("joint") if j.find("axis") is None}


def origin_transform(joint) -> torch.Tensor:
    xyz = torch.tensor(joint.origin.xyz if joint.origin is not None and joint.origin.xyz is not None else [0.0, 0.0, 0.0], dtype=torch.float64)
    rpy = torch.tensor(joint.origin.rpy if joint.origin is not None and joint.origin.rpy is not None else [0.0, 0.0, 0.0], dtype=torch.float64)
    return homogeneous(rpy_to_matrix(rpy), xyz)


def load_urdf(source: str | Path, end_link: str | None = None, root_link: str | None = None) -> Chain:
    """Parse and validate a URDF into a float64 :class:`Chain`.

    source: path to a .urdf file or the XML text. end_link: the link the chain
    ends at (default: the only leaf). root_link: default the tree's root.
    Raises URDFError naming the file and each faulty joint.
    """
    URDF = urdf_parser().URDF

    xml, label = read_urdf_text(source)
    tree = _check_well_formed(xml, label)
    problems = validate_urdf(xml, label)
    if problems:
        raise URDFError(f"{label}: URDF failed validation:\n  " + "\n  ".join(problems))
    try:
        robot = URDF.from_xml_string(xml)
    except Exception as exc:  # the parser dereferences what it does not check: TypeError, AttributeError, its ParseError
        raise URDFError(f"{label}: not a readable URDF ({type(exc).__name__}: {' '.join(str(exc).split())})") from None
    by_child = {j.child: j for j in robot.joints}
    links = [l.name for l in robot.links]
    roots = [l for l in links if l not in by_child]
    undefined = [f"joint '{j.name}' names {what} link '{l}', which is not defined in the URDF"
                 for j in robot.joints for what, l in (("parent", j.parent), ("child", j.child)) if l not in links]
    if undefined:
        raise URDFError(f"{label}: " + "; ".join(undefined) + " (check the <parent link=...> / <child link=...> names)")
    if root_link is None:
        if len(roots) != 1:
            raise URDFError(f"{label}: expected one root link, found {roots}: the links after the first are the "
                            "child of no joint (is a joint's <parent> or <child> misspelled, or a joint missing?)")
        root_link = roots[0]
    parents = {j.parent for j in robot.joints}
    if end_link is None:
        leaves = [l for l in links if l not in parents and l != root_link]
        if len(leaves) != 1:
            raise URDFError(f"{label}: several leaf links {leaves}; name the end link")
        end_link = leaves[0]
    if end_link not in links:
        raise URDFError(f"{label}: end link '{end_link}' not in the URDF (links: {links})")
    path = []
    link, prev_link = end_link, None
    while link != root_link:
        if link not in by_child:
            if link == end_link:
                raise URDFError(f"{label}: end link '{end_link}' is not below root link '{root_link}' (no joint has it as child)")
            below = by_child[prev_link] if prev_link is not None else None
            what = "is not defined in the URDF" if link not in links else \
                f"is a root of its own: no joint connects it to root link '{root_link}'"
            raise URDFError(f"{label}: joint '{below.name}' names parent link '{link}', which {what} "
                            f"(chain from '{end_link}' up to '{root_link}'); check the joint's <parent link=...>")
        prev_link = link
        joint = by_child[link]
        path.append(joint)
        link = joint.parent
        if len(path) > len(robot.joints):
            raise URDFError(f"{label}: kinematic loop through joint '{joint.name}'")
    path.reverse()
    no_axis = _joints_without_axis(tree)
    for joint in path:
        if joint.name in no_axis and joint.type != "fixed":
            # legal URDF, but often a mistake: the pipeline warns again if the nominal residual is implausible
            logging.getLogger("torchcal").warning(
                "%s: joint '%s' has no <axis>; it turns about x (1 0 0), the URDF default", label, joint.name)

    names, origins, axes, prismatic, limits = [], [], [], [], []
    pending = torch.eye(4, dtype=torch.float64)  # fixed joints fold into the next origin
    link_names = []
    for joint in path:
        T = pending @ origin_transform(joint)
        if joint.type == "fixed":
            pending = T
            continue
        axis = torch.tensor(joint.axis if joint.axis is not None else [1.0, 0.0, 0.0], dtype=torch.float64)
        axes.append(axis / axis.norm())
        origins.append(T)
        names.append(joint.name)
        link_names.append(joint.child)
        prismatic.append(joint.type == "prismatic")
        lim = getattr(joint, "limit", None)
        lo = lim.lower if lim is not None and lim.lower is not None and joint.type != "continuous" else float("nan")
        hi = lim.upper if lim is not None and lim.upper is not None and joint.type != "continuous" else float("nan")
        if lo == lo and hi == hi and lo >= hi:
            raise URDFError(f"{label}: joint '{joint.name}': lower limit {lo} is not below upper limit {hi}")
        limits.append([lo, hi])
        pending = torch.eye(4, dtype=torch.float64)
    if not names:
        raise URDFError(f"{label}: no movable joint between '{root_link}' and '{end_link}'")
    return Chain(
        joint_names=names,
        origins=torch.stack(origins),
        axes=torch.stack(axes),
        prismatic=torch.tensor(prismatic, dtype=torch.bool),
        limits=torch.tensor(limits, dtype=torch.float64),
        tip=pending,
        root_link=root_link,
        end_link=end_link,
        name=robot.name,
        link_names=link_names,
    )
