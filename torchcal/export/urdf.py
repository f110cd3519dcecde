"""A calibrated URDF: the best constant joint origins for a calibrated model.

The model's chain is ``T_0 · Π_i origin_i · E_i(θ_i, s_i) · joint_i(θ_i)`` (Paper II (19), (26);
:func:`torchcal.kinematics.fk.chain_frames`). A URDF can only hold fixed
transforms, so the export writes

    origin_i' = origin_i · E_i^0,      E_i^0 = twist_to_transform(c_i)

with one constant error twist c_i per joint, and puts a base correction E(b)
(26) in front of the first joint (``base='joint'``) or on a new fixed root
joint (``base='link'``). What the constants are (``constants=``):

- ``'fit'`` (the default): :func:`constant_projection`, the order-0 model (c_i, b)
  fitted by least squares to the full model's tool points (every tool, the
  full model's own tool vectors, held fixed) at several hundred quasi-random
  commands over the span of the identification data (the joint limits for a
  model that records none). This is the best constant approximation of the
  model where it was identified: beyond the data a series extrapolates, and
  a constant fitted there follows the extrapolation (a real IRB 120 fitted at
  order 6: over the joint limits the URDF came out at 6.9 mm on held-out
  points, worse than the nominal 0.73 mm).
- ``'c0'``: the order-0 Chebyshev coefficients of each series and the model's
  base correction, unchanged. Exact for a model fitted with order 0; for a
  model with joint-dependent terms it is *not* the best constant: the
  Chebyshev polynomials T_k of even k have a nonzero mean over the range, and
  the errors of neighbouring joints couple through the chain, so the URDF can
  come out worse than the nominal robot (a 6-axis robot fitted with order 6:
  nominal 0.94 mm, c0 URDF 2.5 mm mean on its measurements).

Either way, what depends on the joint variables (orders >= 1), backlash
(depends on the approach direction), the tool corrections (not part of the
robot), joint compliance and fine tables stay in the torchcal model;
:class:`UrdfExport` carries the misfit of the written constants against the
full model at the projection commands, and :func:`compare_urdf` states what
leaving them out costs on measured data. The joint map (controller -> URDF
coupling, offsets, limits) is written unchanged next to the URDF when the
robot has one.

Why one module: what the file holds (the order-0 model, fitted or c0), the
writing of it and the statement of what it leaves out (misfit, comparison)
are one feature that changes together; each part is short.
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


# ------------------------------------------------------------------- projection
FIT_DATA_POSES = 4096
"""At most this many of the identification data's commands are used by :func:`export_run_urdf`'s projection."""

PROJECTION_COUNT = 512
"""Default number of quasi-random commands :func:`constant_projection` fits at (a power of two, Sobol)."""


def projection_commands(robot: Robot, count: int = PROJECTION_COUNT, seed: int = 0, device=None,
                        model=None) -> torch.Tensor:
    """``count`` scrambled Sobol commands (count, n), rad / m, seeded: over the span of the identification data
    when ``model`` records it (``model.data_span``, the error variables' range: a series fitted inside the
    data extrapolates beyond it, where joint 6's order-6 terms of a real IRB 120 moved the tool 100 mm, and a
    constant fitted there would follow them), else over the robot's controller limits."""
    lim = robot.joint_map.limits.detach().to("cpu", torch.float64)
    s = torch.quasirandom.SobolEngine(lim.shape[0], scramble=True, seed=int(seed)).draw(int(count), dtype=torch.float64)
    span = None if model is None else getattr(model, "data_span", None)
    if span is None:
        q = lim[:, 0] + s * (lim[:, 1] - lim[:, 0])
    else:  # uniform in the error variables' box, mapped back to commands (u = E q + e0), kept inside the limits
        span = torch.as_tensor(span).detach().to("cpu", torch.float64)
        u = span[:, 0] + s * (span[:, 1] - span[:, 0])
        E = model.error_coupling.detach().to("cpu", torch.float64)
        e0 = model.error_offset.detach().to("cpu", torch.float64)
        q = torch.linalg.solve(E, (u - e0).T).T
        q = torch.minimum(torch.maximum(q, lim[:, 0]), lim[:, 1])
    return q if device is None else q.to(device)


def c0_model(model):
    """The part of ``model`` a URDF can hold, as a :class:`RobotModel`: joint-error orders 0, no backlash,
    compliance or fine tables, the same robot, error variables and measurement frame, the full model's tool
    vectors as nominal ones (no tool correction left to fit); values: the order-0 coefficients c0 and the base
    correction, unchanged (what ``constants='c0'`` exports). Joint-error terms switched off stay off."""
    from ..models.robot import RobotModel

    je = model.joint_errors
    with torch.no_grad():
        tools = model.tools().detach().clone()
        out = RobotModel(model.robot, tools.cpu(), orders=je.orders.clamp(max=0).cpu(), backlash=None,
                         base_nominal=model.base.nominal.detach().cpu().clone(),
                         error_variable=list(getattr(model, "error_variable", model.robot.joint_map.error_variable)))
        out = out.to(model.device)
        out.joint_errors.coef.copy_((je.coef * je.mask)[..., :1])
        out.base.twist.copy_(model.base.twist)
    return out


def _tool_points(model, commands: torch.Tensor, F: torch.Tensor | None = None) -> torch.Tensor:
    """Every tool's point at every command, (B, T, 3): one chain evaluation per command, not per tool."""
    if F is None:
        F = model.flange(commands)
    return F[:, None, :3, 3] + torch.einsum("bij,tj->bti", F[:, :3, :3], model.tools())


def _constant_jacobian(m0, commands: torch.Tensor, on: torch.Tensor, base: bool):
    """Every tool's point (B, T, 3) of the order-0 model m0 and its Jacobian (B, T, 3, P) w.r.t. the free
    constants (the c0 entries ``on``, then with ``base`` the base twist): the chain's 6-row Jacobian at the
    flange origin o, moved to each tool point p = o + r by v_p = v_o + ω × r."""
    d = m0._parts(commands, None, None)
    F = d["F"]
    J = m0.chain_jacobians(d, commands, F[:, :3, 3], rows=6)
    cols = [J["joint_errors.coef"][..., 0][:, :, on]]  # (B, 6, m)
    if base:
        cols.append(J["base.twist"])
    A = torch.cat(cols, -1)  # (B, 6, P)
    r = torch.einsum("bij,tj->bti", F[:, :3, :3], m0.tools())  # (B, T, 3)
    w = A[:, None, 3:].expand(-1, r.shape[1], -1, -1)
    Jp = A[:, None, :3] + torch.linalg.cross(w, r[..., None].expand_as(w), dim=-2)
    return F[:, None, :3, 3] + r, Jp


def constant_projection(model, commands: torch.Tensor | None = None, seed: int = 0, count: int = PROJECTION_COUNT,
                        base: bool = True, max_iter: int = 20):
    """The best constant model: :func:`c0_model` with its constants fitted to the full model.

    model: a fitted :class:`RobotModel`; commands: (B, n) controller commands (rad / m) to fit at (None:
    :func:`projection_commands` with ``count`` and ``seed``, quasi-random over the identification data's span,
    else over the joint limits); base: fit
    the base correction too (False: keep the model's, e.g. when the URDF leaves it out).
    -> an order-0 RobotModel whose c0 coefficients (and base correction) minimize Σ |p0 - p|² over every
    tool at every command, p the full model's points without approach directions (backlash averaged out),
    its tool vectors the full model's, held fixed. Gauss-Newton on the closed-form chain Jacobians, the
    whole batch at once, from c0 and from the nominal constants (the better end is kept); each step is the minimum-norm one in column-scaled units, so directions
    the points cannot see (e.g. a constant along a joint axis that the next one repeats) keep their c0
    values. For an order-0 model without backlash or compliance it is the model itself (to rounding).
    """
    m0 = c0_model(model)
    n = model.robot.joint_map.n
    q = (projection_commands(model.robot, count, seed, model.device, model) if commands is None
         else torch.as_tensor(commands).to(model.device, torch.float64))
    if q.ndim != 2 or q.shape[1] != n or q.shape[0] == 0:
        raise ValueError(f"constant_projection: commands must be (B, {n}) with B >= 1, got {tuple(q.shape)}")
    je = m0.joint_errors
    on = je.mask[..., 0]  # (n, 6) the terms the model has
    k = int(on.sum())
    with torch.no_grad():
        target = _tool_points(model, q)

        def get():
            c = je.coef[..., 0][on]
            return torch.cat([c, m0.base.twist]) if base else c

        def put(x):
            c = je.coef[..., 0].clone()
            c[on] = x[:k]
            je.coef[..., 0] = c
            if base:
                m0.base.twist.copy_(x[k:])

        def descend() -> float:
            """Gauss-Newton from the current constants -> the cost reached."""
            r = (_tool_points(m0, q) - target).reshape(-1)
            cost = float(r @ r)
            for _ in range(int(max_iter)):
                if cost == 0.0:
                    break
                p, Jp = _constant_jacobian(m0, q, on, base)
                r = (p - target).reshape(-1)
                A = Jp.reshape(r.shape[0], -1)
                scale = A.norm(dim=0)
                scale = torch.where(scale > 0, scale, torch.ones_like(scale))
                U, S, Vh = torch.linalg.svd(A / scale, full_matrices=False)
                keep = S > S[0] * 1e-10
                step = -(Vh[keep].T @ ((U[:, keep].T @ r) / S[keep])) / scale
                x0, t = get(), 1.0
                for _ in range(30):  # halve until the cost goes down (a full step nearly always does)
                    put(x0 + t * step)
                    r_new = (_tool_points(m0, q) - target).reshape(-1)
                    cost_new = float(r_new @ r_new)
                    if cost_new <= cost:
                        break
                    t *= 0.5
                else:
                    put(x0)
                    break
                done = cost - cost_new <= 1e-10 * cost
                cost = cost_new
                if done:
                    break
            return cost

        # two starts: the identified c0 and the nominal robot (zero joint constants, the model's base). A
        # high-order fit can carry large c0s that its higher terms cancel inside the data (a real IRB 120 at
        # order 6: 36 mm); from there Gauss-Newton can stall far from the best constants
        x_c0 = get()
        cost_c0 = descend()
        x_a = get()
        zero = x_c0.clone()
        zero[:k] = 0.0
        put(zero)
        if float(descend()) > cost_c0:
            put(x_a)
    return m0


def projection_misfit(model, constants, commands: torch.Tensor) -> tuple[float, float]:
    """RMS and max distance (mm) between ``constants``' and ``model``'s tool points, every tool at ``commands``."""
    q = commands.to(model.device, torch.float64)
    with torch.no_grad():
        d = units.m_to_mm((_tool_points(constants, q) - _tool_points(model, q)).norm(dim=-1))
    return float(d.square().mean().sqrt()), float(d.max())


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
def _check_joint_map_output(path: Path, urdf: Path, force: bool, inputs) -> None:
    """The joint map goes beside the URDF under its stem (load_robot reads the pair): a YAML there that is no
    joint map (a fit config, say) is never replaced, --force or not; one that is, only with --force."""
    from ..io.atomic import OutputExistsError, check_output

    if path.exists() and not _is_joint_map(path):
        raise OutputExistsError(f"{path}: exists and is no joint map (no 'urdf:' and 'joints:' keys), but the URDF "
                                f"{urdf.name} needs its joint map under that name: choose another name for the .urdf "
                                f"(e.g. {urdf.stem}_calibrated.urdf); --force never replaces it")
    try:
        check_output(path, force, inputs)
    except OutputExistsError:
        if path.exists() and not force:
            raise OutputExistsError(f"{path}: already exists (the joint map written beside {urdf.name}); pass "
                                    "--force to overwrite it or choose another name for the .urdf") from None
        raise


def _is_joint_map(path: Path) -> bool:
    try:
        data = yaml.safe_load(path.read_text(encoding="utf-8"))
    except (OSError, UnicodeDecodeError, yaml.YAMLError):
        return False
    return isinstance(data, dict) and "urdf" in data and "joints" in data


@dataclass
class UrdfExport:
    """What :func:`export_urdf` wrote.

    urdf: the calibrated URDF; joint_map: the joint-map YAML next to it (None
    when the source was a bare URDF: the identity map then comes from the URDF's
    limits, as before); robot: the written robot loaded back with
    :func:`torchcal.kinematics.load_robot`; base: 'joint', 'link' or 'none';
    measurement_frame: whether the nominal measurement frame is in the URDF;
    constants: 'fit' (:func:`constant_projection`) or 'c0' (the order-0 coefficients);
    model: the order-0 model whose constants were written (:func:`c0_model` or the projection);
    misfit_rms_mm, misfit_max_mm: how far its tool points are from the full model's (every tool) at the
    projection commands, mm: what a URDF of this model cannot hold, over the workspace;
    commands: how many commands that is; region: where they lie, in words (the identification data's poses,
    quasi-random over its span or over the joint limits: :func:`projection_commands`).
    """

    urdf: Path
    joint_map: Path | None
    robot: Robot
    base: str
    measurement_frame: bool
    constants: str = "c0"
    model: object = None
    misfit_rms_mm: float | None = None
    misfit_max_mm: float | None = None
    commands: int = 0
    region: str = "quasi-random over the joint limits"

    @property
    def path(self) -> Path:
        """What to hand to :func:`load_robot`: the YAML when there is one, else the URDF."""
        return self.joint_map or self.urdf


def export_urdf(model, path, base: str = "joint", measurement_frame: bool = False, source_urdf=None,
                name: str | None = None, constants: str = "fit", commands: torch.Tensor | None = None,
                seed: int = 0, count: int = PROJECTION_COUNT, region: str | None = None) -> UrdfExport:
    """Write a calibrated URDF (and its joint-map YAML) for ``model``.

    model: a fitted :class:`torchcal.models.robot.RobotModel`; path: the .urdf to
    write (a joint-map YAML with the same stem is written next to it when the
    robot has one); base: 'joint' (fold the base correction into the first
    movable joint's origin), 'link' (a new root link '<root>_nominal' with a
    fixed joint carrying it; a YAML root_link is updated) or 'none' (leave it
    out); measurement_frame: also fold in the model's nominal measurement frame,
    so the URDF's root is the tracker frame; source_urdf: the URDF to start from
    when the robot does not record it; name: robot name in the file;
    constants: 'fit' (the default: the constants and base correction of
    :func:`constant_projection`, fitted to the full model's tool points at
    ``commands``, default ``count`` Sobol commands over the identification data's
    span (:func:`projection_commands`) drawn with ``seed``) or 'c0' (the order-0 coefficients and the base correction as
    identified; exact only for an order-0 model). With base='none' the
    projection keeps the model's base correction.
    Only joint origins change (and the root link with base='link'); links,
    limits, meshes and every other element are copied. The result is
    validated and loaded back with torchcal's loader and yourdfpy.
    """
    if base not in ("joint", "link", "none"):
        raise ValueError(f"export_urdf: base must be 'joint', 'link' or 'none', got {base!r}")
    if constants not in ("fit", "c0"):
        raise ValueError(f"export_urdf: constants must be 'fit' or 'c0', got {constants!r}")
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

    q_fit = projection_commands(robot, count, seed, model.device, model) if commands is None else torch.as_tensor(commands).to(model.device, torch.float64)
    if constants == "fit":
        written = constant_projection(model, q_fit, base=base != "none")
    else:
        written = c0_model(model)
    misfit = projection_misfit(model, written, q_fit)
    front_in_joint = base == "joint"
    target = constant_origins(written, base=front_in_joint, measurement_frame=measurement_frame and front_in_joint).cpu()
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
                front = written.base.correction().detach().cpu()
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
    what = ("constant error terms fitted to the full model's tool points over the identification data's span"
            if constants == "fit" else "order-0 error coefficients")
    root.insert(0, ET.Comment(
        f" calibrated by torchcal: joint origins carry the {what}"
        f" (RMS {misfit[0]:.3f} mm, max {misfit[1]:.3f} mm from the full model at {q_fit.shape[0]} commands)"
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
    region = region or ("as given" if commands is not None else "quasi-random over the identification data's span"
                        if getattr(model, "data_span", None) is not None else "quasi-random over the joint limits")
    return UrdfExport(path, yaml_path, loaded, base, measurement_frame, constants, written, misfit[0], misfit[1],
                      int(q_fit.shape[0]), region)


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


# ------------------------------------------------------------------ run export
@dataclass
class RunUrdfExport:
    """What :func:`export_run_urdf` did: the export, and the comparison on a data set of the run (or None).

    data: the measurement file compared on (None: no comparison); rms_mm: RMS of the three residual sets
    ('nominal', 'urdf', 'full'), mm, None without a comparison.
    """

    export: UrdfExport
    comparison: UrdfComparison | None = None
    data: Path | None = None

    @property
    def rms_mm(self) -> dict | None:
        if self.comparison is None:
            return None
        return {k: float(v.square().mean().sqrt()) for k, v in self.comparison.residuals_mm.items()}

    @property
    def urdf_worse_than_nominal(self) -> bool:
        """Whether the URDF alone misses the compared points by more than the nominal robot (mean or RMS)."""
        c, rms = self.comparison, self.rms_mm
        return c is not None and (c.urdf.mean > c.nominal.mean or rms["urdf"] > rms["nominal"])


def export_run_urdf(run_dir, out, base: str = "joint", measurement_frame: bool = False, constants: str = "fit",
                    data=None, force: bool = False, fit_data=None) -> RunUrdfExport:
    """``torchcal export-urdf``: a robot run's calibrated URDF (:func:`export_urdf`), compared on ``data``.

    run_dir: written by ``torchcal fit`` (a robot model); out: the .urdf to write (its joint-map YAML goes
    next to it); data: a measurement CSV of the run (mm, deg) to compare the nominal robot, the URDF alone
    and the full model on (:func:`compare_urdf`), or None; force: replace existing outputs (never an input:
    the run's files or the robot's source URDF / YAML); fit_data: the run's identification CSV, whose commands
    (every pose once, at most :data:`FIT_DATA_POSES`) the constants are fitted at: the model is known there,
    while a box over the data's span also holds joint combinations no pose had (None: that box, else the
    joint limits). Raises RunDirError for a run without a robot model.
    """
    from ..core.exceptions import ConfigError
    from ..io.atomic import check_output
    from ..core.measurements import pose_first_rows
    from ..io.csv import read_measurements
    from ..io.rundir import RunDirError, load_model
    from ..models.robot import RobotModel

    out = Path(out)
    if out.suffix.lower() != ".urdf":
        raise ConfigError(f"{out}: the output must be a .urdf file (the robot's joint-map YAML is written next to it)")
    model = load_model(run_dir)
    if not isinstance(model, RobotModel):
        raise RunDirError(f"{run_dir}: its model is a {type(model).__name__}; a calibrated URDF is written for robot "
                          "runs (point targets, model.kind: joint_dependent)")
    src, spec, spec_path = _source_files(model.robot)
    inputs = [Path(run_dir), Path(run_dir) / "model.pt", Path(run_dir) / "config.yaml", src, spec_path, data]
    check_output(out, force, inputs)
    if spec is not None:
        _check_joint_map_output(out.with_suffix(".yaml"), out, force, inputs)
    commands, region = None, None
    if fit_data is not None:
        fitted_on = read_measurements(fit_data, model.robot, int(model.tools.count))
        q = fitted_on.q[pose_first_rows(fitted_on.pose)[1]]
        if q.shape[0] > FIT_DATA_POSES:  # evenly over the file
            q = q[torch.linspace(0, q.shape[0] - 1, FIT_DATA_POSES).round().long()]
        commands, region = q.to(model.device), "the identification data's poses"
    exp = export_urdf(model, out, base=base, measurement_frame=measurement_frame, constants=constants,
                      commands=commands, region=region)
    if data is None:
        return RunUrdfExport(exp)
    measured = read_measurements(data, model.robot, int(model.tools.count)).to(model.device)
    return RunUrdfExport(exp, compare_urdf(model, exp, measured), Path(data))
