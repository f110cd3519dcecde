"""Gravity compliance: joint deflections that follow the arm's own weight (beyond Papers I-III).

A real arm sags under its own weight: the gearboxes of the joints that carry
the arm (for a 6R industrial arm joints 2 and 3, whose axes are horizontal)
twist by an angle proportional to the gravity torque they hold. That torque
depends on q2 and q3 *together* (the forearm's angle against the horizon),
which no single-joint Chebyshev term of (23) can express. The model here adds
a deflection to the URDF joint variables of the carrying joints,

    Δθ_j(q) = Σ_k c_{j,k} f_{j,k}(θ(q)),        θ(q) = joint_map(q) (commanded, no error terms)

exactly where a joint positioning error v acts (its effect on the points is
d p / d θ_j · Δθ_j). Two families of configuration functions f:

* ``"gravity"``: f_{j,0} = τ_j(θ), the gravity torque (N·m; N for a prismatic
  joint) on joint j from the URDF ``<inertial>`` masses of every link after
  it, on the nominal chain: τ_j = Σ_l m_l g · (z_j × (c_l - o_j)) = -dV/dθ_j
  with V = -Σ_l m_l g · c_l. One compliance c_j (rad / (N·m)) per joint.
* ``"functions"`` (when the URDF has no inertials): with the carrying joints
  j_1 < ... < j_m (parallel axes) and the arm angles φ_k = Σ_{i<=k} s_i θ_{j_i}
  (s_i = ±1: axis of j_i parallel / antiparallel to that of j_1, so φ_2 is
  θ2 + θ3 on an ABB IRB 120 and θ2 - θ3 on the FANUC of Paper II, whose URDF
  flips axis 3), the functions are (sin φ_1, cos φ_1, ..., sin φ_m, cos φ_m).
  A gravity torque is a combination of exactly these, and joint j_a only
  holds the links after it, so joint j_a uses the functions of φ_a ... φ_m:
  on a 6R arm joint 2 gets 4 coefficients (sin/cos of θ2 and of the forearm
  angle) and joint 3 gets 2 (sin/cos of the forearm angle) -- 6 in all.
  Coefficients are rad per unit function value.

"auto" picks "gravity" when every link moved by a joint of the chain has an
``<inertial>``, else "functions". The carrying joints default to the revolute
joints whose axis is horizontal (normal to gravity) at the controller's home
q = 0, leaving out a spherical wrist (the last three joints when their axes
meet in one point): joints 2 and 3 of a 6R industrial arm.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Any, Sequence

import torch
from torch import nn

from ..core.exceptions import ConfigError  # a ValueError too (library callers): a compliance the robot cannot carry
from ..kinematics.fk import chain_frames, joint_motion
from ..io import yamlio

GRAVITY = (0.0, 0.0, -9.80665)
"""Default gravity vector in the URDF root frame (m/s^2): -z is down."""

MODES = ("auto", "gravity", "functions")


# ----------------------------------------------------------------- pure functions
def arm_angle_functions(theta: torch.Tensor, joints: torch.Tensor, signs: torch.Tensor):
    """Configuration functions of the arm angles and their slopes.

    theta: (B, n) URDF joint variables; joints: (m,) long carrying joints;
    signs: (m,) ±1 (axis parallel / antiparallel to the first carrying joint's).
    -> f: (B, 2m) = (sin φ_1, cos φ_1, ..., sin φ_m, cos φ_m) with
       φ_k = Σ_{i<=k} signs_i theta[:, joints_i], and df/dtheta: (B, 2m, n).
    """
    B, n = theta.shape
    m = joints.shape[0]
    phi = torch.cumsum(theta[:, joints] * signs.to(theta), dim=1)  # (B, m)
    s, c = torch.sin(phi), torch.cos(phi)
    f = torch.stack([s, c], -1).reshape(B, 2 * m)
    # d phi_k / d theta: (m, n), row k has signs_i at joints_i for i <= k
    dphi = torch.zeros(m, n, dtype=theta.dtype, device=theta.device)
    rows = torch.arange(m, device=theta.device)
    dphi[rows, joints] = signs.to(theta)
    dphi = torch.cumsum(dphi, 0)
    dfdphi = torch.stack([c, -s], -1)  # (B, m, 2)
    df = (dfdphi[..., None] * dphi[None, :, None, :]).reshape(B, 2 * m, n)
    return f, df


def link_com_positions(origins, axes, prismatic, theta, coms, link_joint):
    """Centres of mass (B, L, 3) in the root frame and the nominal joint frames.

    origins: (n, 4, 4); axes: (n, 3); prismatic: (n,) bool; theta: (B, n);
    coms: (L, 3) centre of mass of each massive link in the child frame of
    joint link_joint[l] (L,) long. -> C (B, L, 3), z (B, n, 3) joint axes,
    o (B, n, 3) joint origins, all in the chain's root frame.
    """
    jR, jp, _ = chain_frames(origins, axes, prismatic, theta)
    mR, mp = joint_motion(axes, prismatic, theta)
    cR = jR @ mR
    cp = jp + (jR @ mp[..., None])[..., 0]
    C = cp[:, link_joint] + (cR[:, link_joint] @ coms[None, :, :, None])[..., 0]
    z = (jR @ axes[:, :, None])[..., 0]
    return C, z, jp


def gravity_torques(origins, axes, prismatic, theta, masses, coms, link_joint, gravity, derivative: bool = False):
    """Gravity torque on every joint of a serial chain, and optionally its slope.

    origins: (n, 4, 4); axes: (n, 3); prismatic: (n,) bool; theta: (B, n);
    masses: (L,) kg; coms: (L, 3) m, each in the child frame of joint
    link_joint: (L,) long; gravity: (3,) m/s^2 in the root frame.
    -> tau: (B, n), tau_j = Σ_{l after j} m_l g · (z_j × (c_l - o_j)) (N·m), or
       Σ m_l g · z_j (N) for a prismatic joint; i.e. -dV/dθ with
       V = -Σ m_l g · c_l. With derivative=True also dtau/dtheta: (B, n, n),
       closed form (symmetric: minus the Hessian of V).
    """
    B, n = theta.shape
    g = gravity.to(theta)
    C, z, o = link_com_positions(origins, axes, prismatic, theta, coms, link_joint)
    after = link_joint[None, :] >= torch.arange(n, device=theta.device)[:, None]  # (n, L)
    W = masses.to(theta)[None, :] * after  # (n, L)
    M = W.sum(1)  # (n,) mass carried by each joint
    u = torch.einsum("il,blc->bic", W, C) - M[None, :, None] * o  # (B, n, 3) first moment about o_j
    a = torch.linalg.cross(z, u, dim=-1)  # (B, n, 3)
    rev = ~prismatic
    tau = torch.where(rev[None, :], a @ g, M[None, :] * (z @ g))
    if not derivative:
        return tau
    # for p <= q (joint p before or at q): moving p turns the whole subchain after it:
    #   q, p revolute: d tau_q / d theta_p = g . (z_p x a_q);  q prismatic, p revolute: M_q g . (z_p x z_q)
    #   p prismatic: translations change no lever arm -> 0.  The slope matrix is symmetric.
    X = torch.linalg.cross(z[:, :, None, :].expand(B, n, n, 3), a[:, None, :, :].expand(B, n, n, 3), dim=-1) @ g
    Y = torch.linalg.cross(z[:, :, None, :].expand(B, n, n, 3), z[:, None, :, :].expand(B, n, n, 3), dim=-1) @ g
    V = torch.where(rev[:, None] & rev[None, :], X, torch.where(rev[:, None] & prismatic[None, :], M[None, None, :] * Y, 0.0))
    U = torch.triu(V)
    dtau = U.transpose(1, 2) + torch.triu(U, 1)
    return tau, dtau


def default_carrying_joints(origins, axes, prismatic, theta_home, gravity) -> list[int]:
    """Revolute joints whose axis is normal to gravity at theta_home (n,), spherical wrist left out."""
    n = axes.shape[0]
    jR, jp, _ = chain_frames(origins, axes, prismatic, theta_home[None])
    z = (jR[0] @ axes[:, :, None])[..., 0]
    o = jp[0]
    gh = gravity / gravity.norm()
    # tolerances fit a calibrated URDF too, whose axes are off by the identified errors (mrad, tenths of mm)
    horizontal = [(not bool(prismatic[i])) and abs(float(z[i] @ gh)) < 1e-2 for i in range(n)]
    wrist = set()
    if n >= 6 and _axes_meet(z[n - 3 :], o[n - 3 :]):
        wrist = {n - 3, n - 2, n - 1}
    return [i for i in range(n) if horizontal[i] and i not in wrist]


def _axes_meet(z: torch.Tensor, o: torch.Tensor, tol: float = 1e-3) -> bool:
    """Whether lines (o_i, z_i) (k, 3) pass through one point (within tol metres; 1 mm: a calibrated wrist still counts)."""
    P = torch.eye(3, dtype=z.dtype) - z[:, :, None] * z[:, None, :]  # (k, 3, 3)
    A = P.sum(0)
    if float(torch.linalg.svdvals(A).min()) < 1e-9:
        return False
    x = torch.linalg.solve(A, (P @ o[..., None]).sum(0))[:, 0]
    return bool(((P @ (x - o)[..., None])[..., 0].norm(dim=-1) < tol).all())


# -------------------------------------------------------------------- inertials
@dataclass
class Inertials:
    """Point masses of the links moved by a chain.

    masses: (L,) kg; coms: (L, 3) m in the child frame of joint link_joint[l];
    link_joint: (L,) long; links: their URDF link names.
    """

    masses: torch.Tensor
    coms: torch.Tensor
    link_joint: torch.Tensor
    links: list[str]

    def to_spec(self) -> dict[str, Any]:
        return {"masses": self.masses.tolist(), "coms": self.coms.tolist(), "link_joint": self.link_joint.tolist(), "links": list(self.links)}

    @classmethod
    def from_spec(cls, d: dict[str, Any]) -> "Inertials":
        return cls(torch.tensor(d["masses"], dtype=torch.float64), torch.tensor(d["coms"], dtype=torch.float64).reshape(-1, 3),
                   torch.tensor(d["link_joint"], dtype=torch.long), list(d.get("links", [])))


def robot_urdf_path(robot) -> Path | None:
    """Path of the URDF a :class:`~torchcal.kinematics.robot.Robot` was loaded from (None if unknown)."""
    from ..kinematics.robot import urdf_dir

    src = str(getattr(robot, "source", "") or "")
    if not src:
        return None
    path = Path(src)
    if path.suffix.lower() == ".urdf":
        return path if path.is_file() else None
    if not path.suffix and not path.exists():
        try:
            path = urdf_dir() / f"{src}.yaml"
        except FileNotFoundError:
            return None
    if path.suffix.lower() in (".yaml", ".yml") and path.is_file():
        spec = yamlio.safe_load(path.read_text())
        if isinstance(spec, dict) and "urdf" in spec:
            p = path.parent / spec["urdf"]
            return p if p.is_file() else None
    return None


def read_inertials(source, chain) -> tuple[Inertials | None, str]:
    """Masses and centres of mass of the links a chain moves, from a URDF.

    source: URDF path or XML text; chain: the :class:`Chain` loaded from it.
    -> (Inertials, "") when every link moved by a chain joint (the child link
    of each movable joint) has an ``<inertial>``; links fixed to those (e.g. a
    flange) count when they have one. Otherwise (None, reason).
    """
    from pytorch_kinematics.urdf_parser_py.urdf import URDF

    from ..kinematics.urdf import origin_transform, read_urdf_text

    xml, label = read_urdf_text(source)
    robot = URDF.from_xml_string(xml)
    by_child = {j.child: j for j in robot.joints}
    chain_child = {name: i for i, name in enumerate(chain.link_names)}
    chain_joints = set(chain.joint_names)
    links = {l.name: l for l in robot.links}
    missing = [name for name in chain.link_names if links.get(name) is None or links[name].inertial is None]
    if missing:
        return None, f"{label}: links {missing} have no <inertial>"
    masses, coms, owner, names = [], [], [], []
    for link in robot.links:
        inertial = link.inertial
        if inertial is None or inertial.mass is None or float(inertial.mass) == 0.0:
            continue
        xyz = inertial.origin.xyz if inertial.origin is not None and inertial.origin.xyz is not None else [0.0, 0.0, 0.0]
        T = torch.eye(4, dtype=torch.float64)
        cur, through = link.name, None
        while cur not in chain_child:
            j = by_child.get(cur)
            if j is None:
                break
            if j.type != "fixed" and j.name not in chain_joints:
                through = through or j.name
            T = origin_transform(j) @ T
            cur = j.parent
        if cur not in chain_child:
            continue  # static: below the chain's first joint
        if through is not None:
            return None, f"{label}: link '{link.name}' hangs on the chain through joint '{through}', which is not part of it"
        c = T[:3, :3] @ torch.tensor(xyz, dtype=torch.float64) + T[:3, 3]
        masses.append(float(inertial.mass))
        coms.append(c)
        owner.append(chain_child[cur])
        names.append(link.name)
    if not masses:
        return None, f"{label}: no link moved by the chain has a mass"
    return Inertials(torch.tensor(masses, dtype=torch.float64), torch.stack(coms), torch.tensor(owner, dtype=torch.long), names), ""


# ------------------------------------------------------------------------ module
class GravityCompliance(nn.Module):
    """Learnable joint deflections Δθ_j(q) = Σ_k c_{j,k} f_{j,k}(θ) of the joints that carry the arm.

    robot: the nominal :class:`Robot`; joints: carrying joints (URDF joint
    names or 0-based indices; default: see the module docstring); mode:
    'auto', 'gravity' or 'functions'; gravity: (3,) m/s^2 in the URDF root
    frame; inertials: :class:`Inertials` to use instead of reading the URDF.
    Parameter ``coef`` (m, K) starts at zero; entries outside ``mask`` (m, K)
    are unused.
    """

    def __init__(self, robot, joints: Sequence[int | str] | None = None, mode: str = "auto",
                 gravity: Sequence[float] | torch.Tensor | None = None, inertials: Inertials | dict | None = None):
        super().__init__()
        if mode not in MODES:
            raise ConfigError(f"compliance mode must be one of {MODES}, got {mode!r}")
        chain, jm = robot.chain, robot.joint_map
        n = chain.n
        self.joint_names = list(chain.joint_names)
        g = torch.as_tensor(GRAVITY if gravity is None else gravity, dtype=torch.float64).reshape(3)
        if float(g.norm()) == 0.0:
            raise ConfigError("compliance: the gravity vector is zero")
        self.register_buffer("origins", chain.origins.detach().to(torch.float64).clone())
        self.register_buffer("axes", chain.axes.detach().to(torch.float64).clone())
        self.register_buffer("prismatic", chain.prismatic.detach().clone())
        self.register_buffer("gravity", g.to(self.origins.device))
        home = jm.to_joint(torch.zeros(n, dtype=torch.float64, device=self.origins.device))
        if joints is None:
            idx = default_carrying_joints(self.origins, self.axes, self.prismatic, home, self.gravity)
            if not idx:
                raise ConfigError(f"compliance: no joint of {self.joint_names} has a horizontal axis at q = 0; pass joints=")
        else:
            idx = []
            for j in joints:
                if isinstance(j, str):
                    if j not in self.joint_names:
                        raise ConfigError(f"compliance: unknown joint '{j}' (joints: {self.joint_names})")
                    idx.append(self.joint_names.index(j))
                else:
                    if not 0 <= int(j) < n:
                        raise ConfigError(f"compliance: joint index {j} outside 0..{n - 1}")
                    idx.append(int(j))
            if len(set(idx)) != len(idx) or idx != sorted(idx) or not idx:
                raise ConfigError(f"compliance: joints must be distinct and root to tip, got {list(joints)}")
        self.register_buffer("joints", torch.tensor(idx, dtype=torch.long, device=self.origins.device))
        m = len(idx)
        if isinstance(inertials, dict):
            inertials = Inertials.from_spec(inertials)
        if mode != "functions" and inertials is None:
            path = robot_urdf_path(robot)
            inertials, why = read_inertials(path, chain) if path is not None else (None, f"robot '{robot.name}': URDF file unknown")
            if inertials is None and mode == "gravity":
                raise ConfigError(f"compliance mode 'gravity' needs the URDF inertials: {why}")
        self.mode = "gravity" if (mode != "functions" and inertials is not None) else "functions"
        if self.mode == "gravity":
            self.links = list(inertials.links)
            self.register_buffer("masses", inertials.masses.to(self.origins))
            self.register_buffer("coms", inertials.coms.to(self.origins))
            self.register_buffer("link_joint", inertials.link_joint.to(self.joints.device))
            self.register_buffer("signs", torch.ones(m, dtype=torch.float64, device=self.origins.device))
            K = 1
            mask = torch.ones(m, 1, dtype=torch.bool)
            self.function_names = ["tau"]
        else:
            if bool(self.prismatic[self.joints].any()):
                raise ConfigError("compliance mode 'functions' needs revolute carrying joints; use 'gravity' (URDF inertials)")
            jR, _, _ = chain_frames(self.origins, self.axes, self.prismatic, home[None])
            z = (jR[0] @ self.axes[:, :, None])[..., 0][self.joints]
            dots = z @ z[0]
            # 5e-5 = 1 - cos(0.57 deg): the axes of a calibrated URDF are parallel only to its identified errors
            if bool((dots.abs() < 1.0 - 5e-5).any()):
                bad = [self.joint_names[i] for i, d in zip(idx, dots.tolist()) if abs(d) < 1.0 - 5e-5]
                raise ConfigError(f"compliance: joints {bad} are not parallel to '{self.joint_names[idx[0]]}'; "
                                 "the arm-angle functions need parallel axes (pass joints= or use URDF inertials)")
            self.register_buffer("signs", torch.sign(dots))
            K = 2 * m
            a = torch.arange(m)
            mask = (torch.arange(K)[None, :] // 2) >= a[:, None]
            self.function_names = [f"{t}_phi{k + 1}" for k in range(m) for t in ("sin", "cos")]
        self.register_buffer("mask", mask.to(self.joints.device))
        self.coef = nn.Parameter(torch.zeros(m, K, dtype=torch.float64, device=self.origins.device))

    @property
    def n(self) -> int:
        return self.axes.shape[0]

    def functions(self, theta: torch.Tensor, derivative: bool = False):
        """Configuration functions at commanded joint variables theta (B, n).

        -> F: (B, m, K) (the column of joint j_a's deflection per coefficient),
        and with derivative=True dF/dtheta: (B, m, K, n).
        """
        m = self.joints.shape[0]
        if self.mode == "gravity":
            out = gravity_torques(self.origins, self.axes, self.prismatic, theta, self.masses, self.coms, self.link_joint,
                                  self.gravity, derivative)
            if not derivative:
                return out[:, self.joints, None]
            tau, dtau = out
            return tau[:, self.joints, None], dtau[:, self.joints, None, :]
        f, df = arm_angle_functions(theta, self.joints, self.signs)
        F = f[:, None, :].expand(-1, m, -1)
        if not derivative:
            return F
        return F, df[:, None].expand(-1, m, -1, -1)

    def deflection_from(self, F: torch.Tensor) -> torch.Tensor:
        """Deflection (B, n) of every joint (zero where not carrying) from functions F (B, m, K)."""
        d = (F * (self.coef * self.mask)).sum(-1)  # (B, m)
        out = torch.zeros(F.shape[0], self.n, dtype=d.dtype, device=d.device)
        return out.index_add(1, self.joints, d)

    def forward(self, theta: torch.Tensor) -> torch.Tensor:
        """Joint deflections Δθ (B, n) at commanded joint variables theta (B, n)."""
        return self.deflection_from(self.functions(theta))

    def deflection_jacobian(self, theta: torch.Tensor) -> torch.Tensor:
        """dΔθ/dθ (B, n, n) at commanded joint variables theta (B, n)."""
        _, dF = self.functions(theta, derivative=True)
        d = torch.einsum("bmkn,mk->bmn", dF, self.coef * self.mask)
        out = torch.zeros(theta.shape[0], self.n, self.n, dtype=d.dtype, device=d.device)
        return out.index_add(1, self.joints, d)

    def param_groups(self, prefix: str = "compliance") -> list:
        """Declared kind and prior scale of ``coef`` (see :class:`torchcal.core.params.ParamGroup`).

        A coefficient is a joint deflection (rad) per unit configuration
        function: per unit sin/cos in 'functions' mode, per N·m in 'gravity' mode.
        """
        from ..core.params import ANGLE, ParamGroup

        k = self.coef.numel()
        return [ParamGroup(f"{prefix}.coef", "compliance", self.parameter_names(), [ANGLE] * k,
                           torch.full((k,), 1e-2, dtype=torch.float64), self.mask.expand_as(self.coef).clone())]

    def parameter_names(self) -> list[str]:
        """Names of every entry of ``coef`` (row-major), e.g. 'compliance.joint2.sin_phi1', 'compliance.joint3.tau'."""
        return [f"compliance.{self.joint_names[j]}.{f}" for j in self.joints.tolist() for f in self.function_names]

    def spec(self) -> dict[str, Any]:
        """Structure for :meth:`RobotModel.spec` (the coefficients live in the state dict)."""
        d: dict[str, Any] = {"mode": self.mode, "joints": self.joints.tolist(), "gravity": self.gravity.tolist()}
        if self.mode == "gravity":
            d["inertials"] = Inertials(self.masses.cpu(), self.coms.cpu(), self.link_joint.cpu(), self.links).to_spec()
        return d


def build_compliance(robot, option) -> GravityCompliance | None:
    """The RobotModel ``compliance=`` argument -> module or None.

    option: False/None (off); True or 'auto'; 'gravity'; 'functions'; or a
    dict of :class:`GravityCompliance` keywords (mode, joints, gravity,
    inertials), as written by :meth:`GravityCompliance.spec`.
    """
    if option is None or option is False:
        return None
    if option is True:
        return GravityCompliance(robot)
    if isinstance(option, str):
        return GravityCompliance(robot, mode=option)
    if isinstance(option, dict):
        unknown = set(option) - {"mode", "joints", "gravity", "inertials"}
        if unknown:
            raise ConfigError(f"compliance: unknown keys {sorted(unknown)}")
        return GravityCompliance(robot, **option)
    raise TypeError(f"compliance must be a bool, a mode string or a dict, got {type(option).__name__}")
