"""A simulated physical robot with known truth, built from the error sources of Paper II.

Why one module: one simulated robot written from Paper II's Table 1 (seven error sources plus sources the model lacks); the sources share one chain walk and one set of constants.

Experiments and tests judge calibration against this truth, so it is written
independently of torchcal's Chebyshev error model: every error source of Paper
II Table 1 / (4)-(14) is its own exact rigid transform or joint-angle term, and
the joint-dependent ones are Fourier-type functions of the joint's *error
variable* u_i rather than polynomials.

Error variable. Paper II (9), (10), (13) write the gear errors of joint i as
functions of the joint command q_i, and (23)-(24) evaluate E_i on q_i
normalized over the command range: the gear of joint i turns with its own
command. On the FANUC LR Mate 200i the DH angle of joint 3 is θ3 = q2 + q3
(Table 2) while J3's gear turns with q3. Per joint, ``error_variable`` says
what the joint-dependent terms follow: ``'command'`` (default) u_i = (q + v)_i,
the controller command including its positioning error, over the command
limits; ``'joint'`` u_i = θ_i, the URDF joint variable, over its range (the
older assumption, kept for comparison and for old truth files). For URDF joint
i with joint variable θ_i (controller command q + v through the joint map) the
actual chain is

    Π_i  Trans(shift_i) · origin_i · Rxyz(tilt_i)   link length & assembly (7)-(8), Hayati β
         · Trans(c_i)                                rotating-centre offset (4)-(5)
         · R_out,i(u_i)                              out-of-plane tilt (11)-(12)
         · Trans(w_i(u_i))                           centre wobble (gearing eccentricity)
         · joint_i(θ_i + Δθ_i(u, s_i))               angle errors about the joint axis

    Δθ_i = Δq_i0                                     mastering (6)
         + u_i (κ_i + ρ_i sin(ϑ_i / 2 + φ_i))        pitch r(q) q (9)
         + Σ_{k=1,2} h_ik cos(k ϑ_i + φ_ik)          strain-wave gearing (10)
         + s_i b_i (1 + β_i sin(ϑ_i + ψ_i))          backlash (13)-(14)
         + g_i cos(m_i ϑ_i + γ_i)                    high-order gear ripple      (not in the model)
         + x_i sin(ϑ_i + ϑ_j(i) + χ_i)               load cross-coupling         (not in the model)

followed by the nominal tip, the true tool vectors (nominal + corrections, (27))
and, in front, the measurement frame ``T_0^m = base_nominal · E_base`` (26).
ϑ_i is the harmonic phase variable of u_i: u_i itself (rad, cycles per
revolution of the gear output) for a revolute joint, π λ_i for a prismatic one
(λ_i the normalized u_i, (24)), so a prismatic range spans one period like a
full-revolution revolute joint.
Rotations of the joint frame (R_out) act about two axes u, w perpendicular to
the joint axis (x, y of a DH joint frame); the wobble w_i moves the rotation
centre in that plane.

Only the counter-rotating part of a 1 cycle/rev tilt or wobble is truly
joint-dependent: a tilt or shift that turns with the output is a constant
offset of the next link. Independent random amplitudes and phases for the two
perpendicular axes keep both parts.

Unmodelled sources. A real robot has errors no order-6 E_i(q_i) represents;
the truth has two, micrometre-sized at the tool (``unmodelled=True`` in the
constructors, the default; ``False`` leaves them zero), so that a correct
model's error against the truth does not drop to zero:

- gear ripple g_i cos(m_i ϑ_i + γ_i): m_i = 9-15 cycles per output revolution
  (tooth-mesh / bearing-pass harmonics of the intermediate gear stages), at
  least 3 cycles over a joint's range, far beyond an order-6 Chebyshev
  series; 0.0006-0.0015° on the FANUC (:data:`FANUC_UNMODELLED`);
- load cross-coupling x_i sin(ϑ_i + ϑ_j + χ_i), j = i + 1 (j = n - 1 for the
  last joint): the bearing and cable load of joint i turns with the next link,
  whose direction in space depends on both commands, and the joint's angle
  error follows that load. A function of two joints' variables that no
  product of single-joint corrections E_i(u_i) reproduces; 0.0006-0.001°.

Together they move the FANUC's tool points by 9.6 µm on average (25 µm at
most; seed 0, 300 quasi-random poses); an order-6 model fitted on Paper II's
protocol (250 poses x 3 tools, Table 5 noise) is then 0.017 mm from the
noise-free truth instead of 0.015 mm without them.
"""

from __future__ import annotations

import functools
import math
from typing import Any

import numpy as np
import torch
from torch import nn

from ..core import units
from ..kinematics.fk import chain_frames
from ..kinematics.joint_map import normalize_error_variable
from ..kinematics.robot import Robot
from ..kinematics.transforms import axis_angle_to_matrix, homogeneous, so3_exp, twist_to_transform

HARMONICS = (1, 2)
"""Cycles per output revolution of the strain-wave and out-of-plane terms."""

# Paper II, Table 9: CPA-identified constant errors of the FANUC LR Mate 200i (deg, mm), DH link i = 1..5
PAPER2_THETA_OFFSET_DEG = (-0.022, -0.055, 0.381, -0.537, -0.320, 0.1)  # θ6 is not in Table 9
PAPER2_DELTA_D_MM = (-0.061, 0.0, 0.133, -0.444, -0.050)
PAPER2_DELTA_A_MM = (-0.28, 0.058, 0.177, 0.136, -0.106)
PAPER2_DELTA_ALPHA_DEG = (-0.060, 0.010, 0.008, -0.014, -0.027)
PAPER2_BETA_DEG = (0.0, -0.008, 0.0, 0.0, 0.0)

# Joint-dependent magnitudes of the simulated FANUC, per joint (deg, mm; amplitudes are
# drawn in [0.7, 1] x these). Sized so that a constant-geometry fit leaves ~20 % of the
# nominal error, Paper II's CPA result (0.705 of 3.418 mm), with the larger in-plane
# errors on joints 2-3 where the paper found them (6.2, Fig. 19).
FANUC_JOINT_DEPENDENT = dict(
    wave_deg=(0.04, 0.13, 0.25, 0.03, 0.04, 0.03),
    out_deg=(0.03, 0.03, 0.02, 0.015, 0.015, 0.015),
    pitch_deg=(0.02, 0.05, 0.08, 0.02, 0.02, 0.02),
    pitch_amp_deg=(0.02, 0.04, 0.06, 0.02, 0.02, 0.02),
    wobble_mm=(0.05, 0.05, 0.04, 0.03, 0.03, 0.02),
    center_mm=0.02,
    backlash_deg=(0.005, 0.02),
)

# Sources no order-6 E_i(q_i) represents (module docstring), per joint, deg: a few µm at the tool
FANUC_UNMODELLED = dict(
    ripple_deg=(0.0006, 0.0006, 0.0006, 0.001, 0.001, 0.0015),
    cross_deg=(0.0006, 0.0008, 0.0008, 0.0008, 0.001, 0.001),
)
RIPPLE_CYCLES = (9, 15)
"""Range of the gear ripple's cycles per output revolution (integers, drawn per joint)."""


def perpendicular_axes(axes: torch.Tensor) -> torch.Tensor:
    """Two unit axes u, w with (u, w, axis) right-handed.  axes: (n, 3) unit -> (n, 2, 3).

    For a z axis this is (x, y), the DH joint frame's own axes.
    """
    eye = torch.eye(3, dtype=axes.dtype, device=axes.device)
    # the coordinate axis least aligned with the joint axis; ties go to the earlier one (x before y)
    e = eye[(axes.abs() + 1e-9 * torch.arange(3, dtype=axes.dtype, device=axes.device)).argmin(-1)]
    u = e - (e * axes).sum(-1, keepdim=True) * axes
    u = u / u.norm(dim=-1, keepdim=True)
    return torch.stack([u, torch.linalg.cross(axes, u, dim=-1)], 1)


@functools.lru_cache(maxsize=256)
def harmonic_limit(span: float, k: int, order: int = 6, tol: float = 0.02) -> float:
    """Amplitude factor that keeps k cycles/rev over a range of ``span`` rad polynomial enough.

    Returns min(1, tol / r) where r is the largest error of the best order-``order``
    Chebyshev least-squares fit of cos(k ϑ + φ) over the range (worst phase): a
    2nd harmonic over a full revolution is ~75 % beyond order 6, so it must stay
    small for the product's order-6 model to reach the noise floor.
    """
    from numpy.polynomial import chebyshev as C

    lam = np.linspace(-1.0, 1.0, 801)
    worst = 0.0
    for phi in np.linspace(0.0, np.pi, 9):
        f = np.cos(k * lam * span / 2.0 + phi)
        worst = max(worst, float(np.abs(C.chebval(lam, C.chebfit(lam, f, order)) - f).max()))
    return min(1.0, tol / max(worst, 1e-300))


def _trans(p: torch.Tensor) -> torch.Tensor:
    """Pure translations.  (..., 3) -> (..., 4, 4)."""
    eye = torch.eye(3, dtype=p.dtype, device=p.device).expand(p.shape[:-1] + (3, 3))
    return homogeneous(eye, p)


class TruthRobot(nn.Module):
    """The actual robot: nominal chain + the seven error sources of Paper II Table 1.

    robot: nominal machine; tools: (T, 3) nominal tool vectors in the flange
    frame (m); base_nominal: (4, 4) nominal measurement frame -> robot base
    (identity by default, as for :class:`torchcal.models.robot.RobotModel`);
    error_variable: what each joint's joint-dependent errors follow, 'command'
    (Paper II (24), default) or 'joint' (URDF θ_i), one word or one per joint
    (kept as the list ``error_variable``; it fixes ``ranges`` and the draws of
    the constructors, so it is not changed afterwards).

    Built with every error zero (the nominal robot); fill the buffers below
    directly or use :meth:`fanuc_paper2` / :meth:`random`. SI units, float64:

    - ``origin_shift`` (n, 3): translation of origin_i in its parent frame (Δa, 0, Δd for DH)
    - ``origin_tilt`` (n, 3): rotations Rx Ry Rz after origin_i, in the joint frame (Δα, β, 0 for DH)
    - ``center`` (n, 3): rotating-centre offset c_i in the joint frame
    - ``mastering`` (n,): Δq_i0
    - ``pitch_scale``, ``pitch_amp``, ``pitch_phase`` (n,): κ_i, ρ_i, φ_i of the pitch term
    - ``wave_amp``, ``wave_phase`` (n, 2): h_ik, φ_ik for k in :data:`HARMONICS`
    - ``out_amp``, ``out_phase`` (n, 2, 2): tilt about [u, w] x harmonic k
    - ``wobble`` (n, 2, 2): centre wobble along [u, w] x [cos ϑ, sin ϑ] coefficients
    - ``backlash``, ``backlash_var``, ``backlash_phase`` (n,): b_i, β_i, ψ_i
    - ``ripple_amp``, ``ripple_freq``, ``ripple_phase`` (n,): g_i, m_i, γ_i (unmodelled)
    - ``cross_amp``, ``cross_phase`` (n,): x_i, χ_i of the coupling with joint
      ``cross_joint[i]`` (unmodelled)
    - ``base_twist`` (6,): E_base as (eps, delta), applied after base_nominal
    - ``tools_delta`` (T, 3): true tool vector minus nominal

    Example:
        >>> import torch, torchcal
        >>> robot = torchcal.load_robot("fanuc_lrmate200i")
        >>> truth = TruthRobot.fanuc_paper2(robot, torch.tensor([[0.0, 0.0, 0.1]], dtype=torch.float64), seed=0)
        >>> truth.error_variable[2], truth.points(torch.zeros(2, 6, dtype=torch.float64), torch.zeros(2, dtype=torch.long)).shape
        ('command', torch.Size([2, 3]))
    """

    def __init__(self, robot: Robot, tools, base_nominal: torch.Tensor | None = None, error_variable="command",
                 backlash_on: str = "joint"):
        super().__init__()
        chain, jm = robot.chain, robot.joint_map
        n = chain.n
        self.robot = robot
        if backlash_on not in ("joint", "command"):
            raise ValueError(f"backlash_on: {backlash_on!r} is not 'joint' or 'command'")
        # 'command': a gear's lost motion is an error of the controller joint it drives, moved to the URDF joints
        # by the coupling (a parallelogram's motor-side J2 backlash also turns θ3); 'joint': Paper II (13)
        self.backlash_on = backlash_on
        self.error_variable = normalize_error_variable(error_variable, n, list(chain.joint_names))
        f64 = dict(dtype=torch.float64, device=chain.device)
        self.register_buffer("origins", chain.origins.to(torch.float64).clone())
        self.register_buffer("axes", chain.axes.to(torch.float64).clone())
        self.register_buffer("prismatic", chain.prismatic.clone())
        self.register_buffer("tip", chain.tip.to(torch.float64).clone())
        self.register_buffer("coupling", jm.coupling.to(**f64).clone())
        self.register_buffer("offset", jm.offset.to(**f64).clone())
        # u = error_coupling @ (q + v) + error_offset: the command itself, or θ (Paper II (24) vs URDF)
        follow = torch.tensor([e == "joint" for e in self.error_variable], dtype=torch.bool, device=chain.device)
        eye = torch.eye(n, **f64)
        self.register_buffer("error_coupling", torch.where(follow[:, None], self.coupling, eye))
        self.register_buffer("error_offset", torch.where(follow, self.offset, torch.zeros_like(self.offset)))
        # range of each error variable: the URDF variable's over the limit box, or the command limits
        self.register_buffer("ranges", torch.where(follow[:, None], jm.joint_ranges().to(**f64),
                                                   jm.limits.to(**f64)).clone())
        # the neighbour whose link direction loads joint i (cross-coupling): the next joint, the last one's previous
        nb = [i + 1 if i + 1 < n else max(i - 1, 0) for i in range(n)]
        self.register_buffer("cross_joint", torch.tensor(nb, dtype=torch.long, device=chain.device))
        self.register_buffer("perp", perpendicular_axes(self.axes))
        tools = torch.as_tensor(tools, **f64)
        if tools.ndim != 2 or tools.shape[1] != 3:
            raise ValueError(f"TruthRobot: tool vectors must have shape (T, 3), got {tuple(tools.shape)}")
        self.register_buffer("tools_nominal", tools.clone())
        self.register_buffer("tools_delta", torch.zeros_like(tools))
        bn = torch.eye(4, **f64) if base_nominal is None else torch.as_tensor(base_nominal, **f64)
        self.register_buffer("base_nominal", bn.clone())
        self.register_buffer("base_twist", torch.zeros(6, **f64))
        for name, shape in [
            ("origin_shift", (n, 3)), ("origin_tilt", (n, 3)), ("center", (n, 3)),
            ("mastering", (n,)), ("pitch_scale", (n,)), ("pitch_amp", (n,)), ("pitch_phase", (n,)),
            ("wave_amp", (n, len(HARMONICS))), ("wave_phase", (n, len(HARMONICS))),
            ("out_amp", (n, 2, len(HARMONICS))), ("out_phase", (n, 2, len(HARMONICS))),
            ("wobble", (n, 2, 2)),
            ("backlash", (n,)), ("backlash_var", (n,)), ("backlash_phase", (n,)),
            ("ripple_amp", (n,)), ("ripple_freq", (n,)), ("ripple_phase", (n,)),
            ("cross_amp", (n,)), ("cross_phase", (n,)),
        ]:
            self.register_buffer(name, torch.zeros(shape, **f64))

    # ------------------------------------------------------------------ shapes
    @property
    def n(self) -> int:
        return self.origins.shape[0]

    def joint_variables(self, q: torch.Tensor) -> torch.Tensor:
        """Controller commands (B, n) -> URDF joint variables (B, n)."""
        return q @ self.coupling.T.to(q) + self.offset.to(q)

    def error_variables(self, q: torch.Tensor) -> torch.Tensor:
        """Controller commands (B, n) (including positioning errors v) -> error variables u (B, n).

        u_i = q_i for 'command' joints, θ_i for 'joint' joints.
        """
        return q @ self.error_coupling.T.to(q) + self.error_offset.to(q)

    def phase_variable(self, u: torch.Tensor) -> torch.Tensor:
        """Argument of the harmonic terms (B, n): u (rad) for revolute joints, π λ for prismatic ones.

        λ is u normalized over ``ranges`` (the error variable's range), (24).
        """
        lo, hi = self.ranges[:, 0].to(u), self.ranges[:, 1].to(u)
        lam = 2.0 * (u - lo) / (hi - lo) - 1.0
        return torch.where(self.prismatic.to(u.device), math.pi * lam, u)

    # ------------------------------------------------------- error functions
    def error_functions(self, u: torch.Tensor) -> dict[str, torch.Tensor]:
        """Each error source as a function of the error variables.

        u: (B, n) error variables (:meth:`error_variables`; the URDF joint
        variables θ for 'joint' joints) -> dict of (B, n) tensors (rad, or m
        for prismatic angle terms / wobble): 'mastering', 'pitch', 'wave',
        'backlash' (the magnitude Δq_ib(u), to be multiplied by s_i),
        'tilt_u', 'tilt_w' (R_out about u, w), 'wobble_u', 'wobble_w', and
        the unmodelled angle terms 'ripple' and 'cross' (the latter reads
        column ``cross_joint[i]`` of u too).
        """
        theta = u
        t = lambda b: b.to(theta)  # noqa: E731
        ph = self.phase_variable(theta)
        k = torch.tensor(HARMONICS, dtype=theta.dtype, device=theta.device)
        arg = ph[..., None] * k  # (B, n, K)
        wave = (t(self.wave_amp) * torch.cos(arg + t(self.wave_phase))).sum(-1)
        tilt = (t(self.out_amp) * torch.cos(arg[..., None, :] + t(self.out_phase))).sum(-1)  # (B, n, 2)
        cs = torch.stack([torch.cos(ph), torch.sin(ph)], -1)  # (B, n, 2)
        wob = (t(self.wobble) * cs[..., None, :]).sum(-1)  # (B, n, 2)
        pitch = theta * (t(self.pitch_scale) + t(self.pitch_amp) * torch.sin(0.5 * ph + t(self.pitch_phase)))
        back = t(self.backlash) * (1.0 + t(self.backlash_var) * torch.sin(ph + t(self.backlash_phase)))
        ripple = t(self.ripple_amp) * torch.cos(t(self.ripple_freq) * ph + t(self.ripple_phase))
        cross = t(self.cross_amp) * torch.sin(ph + ph[..., self.cross_joint.to(theta.device)] + t(self.cross_phase))
        return {
            "mastering": t(self.mastering).expand_as(theta),
            "pitch": pitch,
            "wave": wave,
            "backlash": back,
            "tilt_u": tilt[..., 0],
            "tilt_w": tilt[..., 1],
            "wobble_u": wob[..., 0],
            "wobble_w": wob[..., 1],
            "ripple": ripple,
            "cross": cross,
        }

    def angle_error(self, u: torch.Tensor, direction: torch.Tensor | None = None) -> torch.Tensor:
        """Δθ (B, n) about (or along) each joint axis for error variables u (B, n).

        Mastering + pitch + strain wave + ripple + cross-coupling (+ s_i backlash).
        """
        f = self.error_functions(u)
        d = f["mastering"] + f["pitch"] + f["wave"] + f["ripple"] + f["cross"]
        if direction is not None:
            d = d + direction.to(u) * f["backlash"]
        return d

    def true_origins(self, like: torch.Tensor | None = None) -> torch.Tensor:
        """Actual joint origins (n, 4, 4): Trans(shift_i) · origin_i · Rx(t_x) Ry(t_y) Rz(t_z).

        The tilt is composed about x, then the new y (then z) so that a DH origin
        Tz(d) Tx(a) Rx(α) becomes exactly Tz(d+Δd) Tx(a+Δa) Rx(α+Δα) Ry(β), (7)-(8)
        with Hayati's β.
        """
        o = self.origins if like is None else self.origins.to(like)
        shift = self.origin_shift.to(o)
        tilt = self.origin_tilt.to(o)
        eye = torch.eye(3, dtype=o.dtype, device=o.device)
        R = (axis_angle_to_matrix(eye[0], tilt[:, 0]) @ axis_angle_to_matrix(eye[1], tilt[:, 1])
             @ axis_angle_to_matrix(eye[2], tilt[:, 2]))
        return _trans(shift) @ o @ homogeneous(R, torch.zeros_like(shift))

    def joint_transforms(self, u: torch.Tensor) -> torch.Tensor:
        """Per-joint error transform in the joint frame, before the joint moves.

        u: (B, n) error variables -> (B, n, 4, 4) = Trans(c_i) · R_out(u_i) · Trans(wobble(u_i)).
        """
        theta = u
        f = self.error_functions(theta)
        perp = self.perp.to(theta)  # (n, 2, 3)
        rotvec = f["tilt_u"][..., None] * perp[:, 0] + f["tilt_w"][..., None] * perp[:, 1]
        wob = f["wobble_u"][..., None] * perp[:, 0] + f["wobble_w"][..., None] * perp[:, 1]
        R = so3_exp(rotvec)
        p = self.center.to(theta) + (R @ wob[..., None])[..., 0]
        return homogeneous(R, p)

    # -------------------------------------------------------------- kinematics
    def base_frame(self, base: bool = True, like: torch.Tensor | None = None) -> torch.Tensor:
        """T_0^m = base_nominal · E_base (base=True) or E_base alone (4, 4)."""
        E = twist_to_transform(self.base_twist if like is None else self.base_twist.to(like))
        return (self.base_nominal.to(E) @ E) if base else E

    def frames(self, q: torch.Tensor, direction: torch.Tensor | None = None, v: torch.Tensor | None = None, base: bool = True):
        """Actual joint frames and flange pose, see :func:`torchcal.kinematics.fk.chain_frames`.

        q: (B, n) commands; direction: (B, n) approach directions s_i (0: no
        backlash) or None; v: (B, n) joint positioning errors (controller space)
        or None; base: measurement frame (True) or robot nominal base frame
        with E_base included (False).
        """
        qa = q if v is None else q + v  # the gears turn with the command the joint really received
        theta = self.joint_variables(qa)
        u = self.error_variables(qa)
        if self.backlash_on == "command" and direction is not None:
            back = direction.to(u) * self.error_functions(u)["backlash"]
            actual = theta + self.angle_error(u, None) + back @ self.coupling.T.to(u)
        else:
            actual = theta + self.angle_error(u, direction)
        E = self.joint_transforms(u)
        return chain_frames(self.true_origins(theta), self.axes.to(theta), self.prismatic.to(theta.device),
                            actual, E, self.tip.to(theta), self.base_frame(base, theta))

    def flange(self, q, direction=None, v=None, base: bool = False) -> torch.Tensor:
        """Actual flange pose (B, 4, 4).

        base=False: E_base · F_a in the robot's nominal base frame, the convention of
        ``RobotModel.flange(base=False)``; base=True: base_nominal · E_base · F_a,
        the measurement frame. Note the default differs from RobotModel's (base=True).
        """
        return self.frames(q, direction, v, base)[2]

    def nominal_flange(self, q: torch.Tensor) -> torch.Tensor:
        """Nominal flange pose F_n(q) (B, 4, 4) in the robot's nominal base frame."""
        return chain_frames(self.origins.to(q), self.axes.to(q), self.prismatic.to(q.device),
                            self.joint_variables(q), None, self.tip.to(q))[2]

    def tools(self) -> torch.Tensor:
        """True tool vectors (T, 3) in the flange frame."""
        return self.tools_nominal + self.tools_delta

    def points(self, q, tool, direction=None, v=None) -> torch.Tensor:
        """True tool positions (B, 3) m in the measurement frame, (25) without ξ.

        q: (B, n) rad / m; tool: (B,) long; direction: (B, n) in {-1, 0, +1} or None; v: (B, n) or None.
        """
        F = self.frames(q, direction, v, base=True)[2]
        p_t = self.tools().to(q)[torch.as_tensor(tool, device=q.device)]
        return (F[:, :3, :3] @ p_t[..., None])[..., 0] + F[:, :3, 3]

    def forward(self, q, tool, direction=None, v=None) -> torch.Tensor:
        """Same as :meth:`points`."""
        return self.points(q, tool, direction, v)

    def nominal_points(self, q, tool) -> torch.Tensor:
        """Nominal prediction (B, 3): nominal chain, nominal tools, nominal measurement frame."""
        F = self.base_nominal.to(q) @ self.nominal_flange(q)
        p_t = self.tools_nominal.to(q)[torch.as_tensor(tool, device=q.device)]
        return (F[:, :3, :3] @ p_t[..., None])[..., 0] + F[:, :3, 3]

    # ------------------------------------------------------------ constructors
    @classmethod
    def fanuc_paper2(cls, robot: Robot, tools, seed: int, base_nominal: torch.Tensor | None = None,
                     error_variable="command", unmodelled: bool = True) -> "TruthRobot":
        """The FANUC LR Mate 200i of Paper II: Table 9 constants + seeded joint-dependent errors.

        robot: a 6-joint DH chain like ``load_robot("fanuc_lrmate200i")`` (origin_{i+1}
        = Tz(d_i) Tx(a_i) Rx(α_i)); tools: (T, 3) m. Constant errors are Table 9's
        CPA values with their signs (θ6's offset, not in the table, is 0.1°);
        joint-dependent errors are drawn from ``seed`` (:data:`FANUC_JOINT_DEPENDENT`):
        strain-wave amplitudes of 0.03-0.04° on joints 1 and 4-6 and 0.13° / 0.25°
        on joints 2 / 3, where the paper's CPA left 0.8 / 2.4 mm (Table 10, Fig. 19);
        pitch 0.02-0.08° at the range ends; out of plane 0.015-0.03°; centre
        wobble tens of µm; backlash 0.005-0.02° varying by 15-30 % with the angle;
        base ~0.3 mm / 0.01°; tool corrections 0.05-0.2 mm.

        error_variable: 'command' (default: J3's gear errors follow q3, Paper II
        (24)) or 'joint' (they follow θ3 = q2 + q3), or one per joint; the
        joint-dependent draws are scaled over that variable's range.
        unmodelled: add the gear ripple and load cross-coupling of
        :data:`FANUC_UNMODELLED` (module docstring; drawn from their own stream
        of ``seed``, so switching them off leaves every other error as it was).

        Over the Table 3 workspace with the Table 4 tools the nominal model is off
        by ~3.4-5.6 mm in the nominal measurement frame and ~2.8-4.2 mm after a
        best rigid alignment of that frame (as a tracker user must do; Paper II:
        3.4 mm), and a constant-geometry fit leaves ~15-30 % of the latter
        (Paper II's CPA: 0.705 of 3.418 mm).
        """
        truth = cls(robot, tools, base_nominal, error_variable)
        n = truth.n
        if n != 6:
            raise ValueError(f"fanuc_paper2: robot '{robot.name}' has {n} joints, Table 9 describes 6")
        o = truth.origins
        for i in range(1, 6):
            R = o[i, :3, :3]
            if abs(float(o[i, 1, 3])) > 1e-9 or float((R[0] - R.new_tensor([1.0, 0.0, 0.0])).abs().max()) > 1e-9:
                name = robot.chain.joint_names[i]
                raise ValueError(f"fanuc_paper2: origin of joint '{name}' is not DH form Tz(d) Tx(a) Rx(alpha)")
        g = np.random.default_rng(seed)
        deg, mm = units.DEG, units.MM
        with torch.no_grad():
            truth.mastering.copy_(torch.tensor(PAPER2_THETA_OFFSET_DEG) * deg)
            truth.origin_shift[1:].copy_(torch.tensor([PAPER2_DELTA_A_MM, [0.0] * 5, PAPER2_DELTA_D_MM]).T * mm)
            truth.origin_tilt[1:].copy_(torch.tensor([PAPER2_DELTA_ALPHA_DEG, PAPER2_BETA_DEG, [0.0] * 5]).T * deg)
            # magnitudes per joint (deg / mm): larger in-plane errors on joints 2-3 (Paper II 6.2)
            truth._draw_joint_dependent(g, **FANUC_JOINT_DEPENDENT)
            truth._draw_frames(g, base_mm=0.3, base_deg=0.01, tool_mm=(0.05, 0.2))
            if unmodelled:
                truth._draw_unmodelled(np.random.default_rng([int(seed), 1]), **FANUC_UNMODELLED)
        return truth

    @classmethod
    def random(cls, robot: Robot, tools, seed: int, scale: float = 1.0, base_nominal: torch.Tensor | None = None,
               error_variable="command", unmodelled: bool = True) -> "TruthRobot":
        """Any robot with seeded errors of industrial size, lengths relative to its reach.

        With L the sum of the chain's link offsets (its reach, m), constant link
        errors are ~3e-4 L, mastering ~0.2°, assembly tilts ~0.03°, strain-wave
        terms ~0.03°, out-of-plane ~0.01°, centre wobble ~3e-5 L, backlash
        0.005-0.02°, base ~3e-4 L and 0.01°, tools 0.05-0.2 mm. Along a prismatic
        axis an angle-type error of x° becomes a length of x · 1.5e-3 L
        (0.2° -> 0.3 mm at 1 m). Everything is multiplied by ``scale`` (0: nominal).
        error_variable: as for :meth:`fanuc_paper2`; unmodelled: gear ripple and
        load cross-coupling of 0.0008° each (module docstring), own stream of ``seed``.
        """
        truth = cls(robot, tools, base_nominal, error_variable)
        n = truth.n
        g = np.random.default_rng(seed)
        reach = float(truth.origins[:, :3, 3].norm(dim=-1).sum() + truth.tip[:3, 3].norm())
        reach = reach if reach > 0 else 1.0
        unit = np.where(truth.prismatic.cpu().numpy(), 1.5e-3 * reach, units.DEG)  # SI per "degree"
        with torch.no_grad():
            truth.origin_shift.copy_(torch.from_numpy(g.normal(0.0, 3e-4 * reach * scale, (n, 3))))
            tilt = torch.from_numpy(g.normal(0.0, 0.03 * units.DEG * scale, (n, 3))).to(truth.axes)
            ax = truth.axes
            truth.origin_tilt.copy_(tilt - (tilt * ax).sum(-1, keepdim=True) * ax)  # about the axis it is mastering
            truth.mastering.copy_(torch.from_numpy(g.normal(0.0, 0.2 * scale, n) * unit))
            truth._draw_joint_dependent(
                g,
                wave_deg=(0.03 * scale,) * n,
                out_deg=(0.01 * scale,) * n,
                pitch_deg=(0.02 * scale,) * n,
                pitch_amp_deg=(0.02 * scale,) * n,
                wobble_mm=(0.03 * reach * scale,) * n,
                center_mm=0.02 * reach * scale,
                backlash_deg=(0.005 * scale, 0.02 * scale),
                angle_unit=unit,
            )
            truth._draw_frames(g, base_mm=0.3 * reach * scale, base_deg=0.01 * scale, tool_mm=(0.05 * scale, 0.2 * scale))
            if unmodelled:
                truth._draw_unmodelled(np.random.default_rng([int(seed), 1]), ripple_deg=(0.0008 * scale,) * n,
                                       cross_deg=(0.0008 * scale,) * n, angle_unit=unit)
        return truth

    def _draw_joint_dependent(self, g, wave_deg, out_deg, pitch_deg, pitch_amp_deg, wobble_mm, center_mm,
                              backlash_deg, angle_unit=None) -> None:
        """Fill the joint-dependent buffers from ``g`` (numpy Generator); magnitudes per joint.

        wave_deg / backlash_deg / pitch_deg / pitch_amp_deg are angle-type terms,
        converted with ``angle_unit`` (n,) SI per degree (default: rad per degree
        for every joint); the pitch ratios κ, ρ are set so that |κ θ| and |ρ θ|
        reach pitch_deg / pitch_amp_deg at the end of the joint range farther
        from zero (r(q) q grows with |q|); out_deg are true tilts; wobble_mm /
        center_mm lengths.
        """
        n = self.n
        K = len(HARMONICS)
        au = np.full(n, units.DEG) if angle_unit is None else np.asarray(angle_unit, dtype=np.float64)
        span = (self.ranges[:, 1] - self.ranges[:, 0]).cpu().numpy()
        span = np.where(self.prismatic.cpu().numpy(), 2.0 * np.pi, span)  # harmonic variable π λ
        # damp each harmonic so that its part beyond order 6 stays ~2 % of its nominal size
        lim = np.array([[harmonic_limit(float(s), k) for k in HARMONICS] for s in span])  # (n, K)
        # the 2nd harmonic is the smaller one: gearing errors fall off with frequency
        kfac = np.array([1.0, 0.5])[:K]
        two_pi = 2.0 * np.pi
        t = lambda a: torch.from_numpy(np.asarray(a, dtype=np.float64)).to(self.wave_amp.device)  # noqa: E731
        amp = (np.asarray(wave_deg) * au)[:, None] * kfac * lim * g.uniform(0.7, 1.0, (n, K))
        self.wave_amp.copy_(t(amp))
        self.wave_phase.copy_(t(g.uniform(0.0, two_pi, (n, K))))
        oamp = np.asarray(out_deg)[:, None, None] * units.DEG * kfac * lim[:, None, :] * g.uniform(0.7, 1.0, (n, 2, K))
        self.out_amp.copy_(t(oamp))
        self.out_phase.copy_(t(g.uniform(0.0, two_pi, (n, 2, K))))
        peak = self.ranges.abs().max(1).values.cpu().numpy()
        peak = np.where(peak > 0, peak, 1.0)
        kappa = np.asarray(pitch_deg) * au / peak
        self.pitch_scale.copy_(t(kappa * g.choice([-1.0, 1.0], n) * g.uniform(0.7, 1.0, n)))
        self.pitch_amp.copy_(t(np.asarray(pitch_amp_deg) * au / peak * g.uniform(0.7, 1.0, n)))
        self.pitch_phase.copy_(t(g.uniform(0.0, two_pi, n)))
        wob = np.asarray(wobble_mm)[:, None, None] * units.MM * lim[:, None, :1] * g.uniform(-1.0, 1.0, (n, 2, 2))
        self.wobble.copy_(t(wob))
        c = g.normal(0.0, 1.0, (n, 3))
        self.center.copy_(t(c / np.linalg.norm(c, axis=1, keepdims=True) * center_mm * units.MM * g.uniform(0.7, 1.0, (n, 1))))
        self.backlash.copy_(t(g.uniform(backlash_deg[0], backlash_deg[1], n) * au))
        self.backlash_var.copy_(t(g.uniform(0.15, 0.3, n)))
        self.backlash_phase.copy_(t(g.uniform(0.0, two_pi, n)))

    def _draw_unmodelled(self, g, ripple_deg, cross_deg, angle_unit=None) -> None:
        """Fill the gear-ripple and cross-coupling buffers from ``g``; magnitudes (deg) per joint, x [0.7, 1].

        Ripple frequencies are integers in :data:`RIPPLE_CYCLES` cycles per
        revolution of the phase variable; a robot with one joint has no
        neighbour and no cross-coupling.
        """
        n = self.n
        au = np.full(n, units.DEG) if angle_unit is None else np.asarray(angle_unit, dtype=np.float64)
        t = lambda a: torch.from_numpy(np.asarray(a, dtype=np.float64)).to(self.ripple_amp.device)  # noqa: E731
        two_pi = 2.0 * np.pi
        self.ripple_amp.copy_(t(np.asarray(ripple_deg) * au * g.uniform(0.7, 1.0, n)))
        self.ripple_freq.copy_(t(g.integers(RIPPLE_CYCLES[0], RIPPLE_CYCLES[1] + 1, n)))
        self.ripple_phase.copy_(t(g.uniform(0.0, two_pi, n)))
        cross = np.asarray(cross_deg) * au * g.uniform(0.7, 1.0, n) * (1.0 if n > 1 else 0.0)
        self.cross_amp.copy_(t(cross))
        self.cross_phase.copy_(t(g.uniform(0.0, two_pi, n)))

    def _draw_frames(self, g, base_mm: float, base_deg: float, tool_mm: tuple[float, float]) -> None:
        """Base error of ~base_mm / base_deg (norms) and tool corrections of tool_mm[0]..[1] (norms)."""
        def unit(shape):
            x = g.normal(0.0, 1.0, shape)
            return x / np.linalg.norm(x, axis=-1, keepdims=True)

        rot = unit(3) * base_deg * units.DEG * g.uniform(0.7, 1.3)
        trans = unit(3) * base_mm * units.MM * g.uniform(0.7, 1.3)
        self.base_twist.copy_(torch.from_numpy(np.concatenate([rot, trans])))
        T = self.tools_delta.shape[0]
        d = unit((T, 3)) * g.uniform(tool_mm[0], tool_mm[1], (T, 1)) * units.MM
        self.tools_delta.copy_(torch.from_numpy(d))

    # --------------------------------------------------------------- summary
    def _file_units(self, x: torch.Tensor) -> torch.Tensor:
        """(n, ...) joint values SI -> deg (revolute) / mm (prismatic)."""
        scale = torch.where(self.prismatic.cpu(), 1.0 / units.MM, 1.0 / units.DEG).to(x)
        return x * scale.reshape((-1,) + (1,) * (x.ndim - 1))

    def chebyshev_fit_error(self, order: int = 6, points: int = 1001) -> dict[str, dict[str, list[float]]]:
        """How well an order-``order`` series in λ (24) fits each joint-dependent error function.

        Least-squares Chebyshev fit (numpy, independent of :mod:`torchcal.core.basis`)
        of each function over the joint range (``joint_map.joint_ranges()``) on
        ``points`` samples. -> {function: {'max_abs': (n,), 'rel': (n,)}} with
        max_abs in deg (angle terms; mm along prismatic axes) or mm (wobble), and
        rel = max_abs / max |f - mean f| (0 where the function is constant).
        Functions of ``ranges`` (the error variables' range): 'in_plane' (pitch +
        strain wave), 'backlash', 'tilt_u', 'tilt_w', 'wobble_u', 'wobble_w'
        (the modelled sources, sized to be representable), and 'ripple' (the
        unmodelled gear ripple, by design not representable). The cross-coupling
        depends on two joints and has no one-variable fit.
        """
        from numpy.polynomial import chebyshev as C

        lam = torch.linspace(-1.0, 1.0, points, dtype=torch.float64, device=self.ranges.device)[:, None]
        theta = self.ranges[:, 0] + 0.5 * (lam + 1.0) * (self.ranges[:, 1] - self.ranges[:, 0])
        f = self.error_functions(theta)
        pri = self.prismatic.cpu().numpy()
        au = np.where(pri, 1.0 / units.MM, 1.0 / units.DEG)
        funcs = {
            "in_plane": ((f["pitch"] + f["wave"]).cpu().numpy(), au),
            "backlash": (f["backlash"].cpu().numpy(), au),
            "tilt_u": (f["tilt_u"].cpu().numpy(), np.full(self.n, 1.0 / units.DEG)),
            "tilt_w": (f["tilt_w"].cpu().numpy(), np.full(self.n, 1.0 / units.DEG)),
            "wobble_u": (f["wobble_u"].cpu().numpy(), np.full(self.n, 1.0 / units.MM)),
            "wobble_w": (f["wobble_w"].cpu().numpy(), np.full(self.n, 1.0 / units.MM)),
            "ripple": (f["ripple"].cpu().numpy(), au),
        }
        x = lam[:, 0].cpu().numpy()
        out = {}
        for name, (y, scale) in funcs.items():
            fitted = C.chebval(x, C.chebfit(x, y, order)).T  # (points, n)
            err = np.abs(fitted - y).max(0)
            spread = np.abs(y - y.mean(0)).max(0)
            rel = np.where(spread > 0, err / np.where(spread > 0, spread, 1.0), 0.0)
            out[name] = {"max_abs": [float(a) for a in err * scale], "rel": [float(a) for a in rel]}
        return out

    def describe(self) -> dict[str, Any]:
        """True error magnitudes per joint in file units (deg, mm; mm for prismatic angle terms).

        Constants as values; joint-dependent sources as their peak-to-peak over
        the error variable's range ``ranges`` (backlash: its mean magnitude and
        relative variation); ``error_variable`` per joint; the unmodelled
        sources as gear ripple peak-to-peak and cycles per revolution, and the
        cross-coupling amplitude with the joint it couples to.
        """
        pri = self.prismatic.cpu()
        au = torch.where(pri, 1.0 / units.MM, 1.0 / units.DEG)  # angle-type terms in deg or mm
        grid = torch.linspace(0.0, 1.0, 721, dtype=torch.float64, device=self.ranges.device)[:, None]
        theta = self.ranges[:, 0] + grid * (self.ranges[:, 1] - self.ranges[:, 0])
        f = {k: v.cpu() for k, v in self.error_functions(theta).items()}
        ptp = lambda x: (x.max(0).values - x.min(0).values)  # noqa: E731
        r = lambda x: [round(float(a), 6) for a in x]  # noqa: E731
        names = list(self.robot.chain.joint_names)
        return {
            "joints": names,
            # the '_deg' entries of a prismatic joint (a rail) are mm: say so beside them, joint by joint
            "angle_terms_unit": ["mm" if bool(p) else "deg" for p in pri],
            "error_variable": list(self.error_variable),
            "error_range": [r(x) for x in self._file_units(self.ranges.cpu())],
            "mastering_deg": r(self.mastering.cpu() * au),
            "origin_shift_mm": [r(x) for x in units.m_to_mm(self.origin_shift.cpu())],
            "origin_tilt_deg": [r(x) for x in units.rad_to_deg(self.origin_tilt.cpu())],
            "center_offset_mm": r(units.m_to_mm(self.center.cpu().norm(dim=-1))),
            "pitch_ptp_deg": r(ptp(f["pitch"]) * au),
            "wave_ptp_deg": r(ptp(f["wave"]) * au),
            "tilt_u_ptp_deg": r(units.rad_to_deg(ptp(f["tilt_u"]))),
            "tilt_w_ptp_deg": r(units.rad_to_deg(ptp(f["tilt_w"]))),
            "wobble_ptp_mm": r(units.m_to_mm(torch.maximum(ptp(f["wobble_u"]), ptp(f["wobble_w"])))),
            "backlash_deg": r(self.backlash.cpu() * au),
            "backlash_variation": r(self.backlash_var.cpu()),
            "ripple_ptp_deg": r(ptp(f["ripple"]) * au),
            "ripple_cycles_per_rev": r(self.ripple_freq.cpu()),
            "cross_coupling_deg": r(self.cross_amp.cpu() * au),
            "cross_coupling_with": [names[int(j)] for j in self.cross_joint.cpu()],
            "base_rotation_deg": round(float(units.rad_to_deg(self.base_twist[:3].norm())), 6),
            "base_translation_mm": round(float(units.m_to_mm(self.base_twist[3:].norm())), 6),
            "tool_correction_mm": r(units.m_to_mm(self.tools_delta.cpu().norm(dim=-1))),
        }
