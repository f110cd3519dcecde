"""A simulated five-axis machine tool (axis sequence XYZCB) with known truth, from Paper I's text.

Experiments judge the axis perturbation model (Paper I (2)-(7)) against this
machine, so it is written from the paper's description of a machine tool's
errors, not from torchcal's model: the paper's 2.1 (and its references [1-3],
[14]) describe a machine whose every axis carries six component errors as
functions of its own position and whose axes are misplaced against each other
by location errors; the measured point is the tool tip through the real chain
((8): tracker frame, machine, tool, positioning and tracker noise).

Chain (zero-reference model, Paper I (1); nominal F_nom = Trans(X, Y, Z) Rz(C) Ry(B),
tools [0, 0, l_t] in the last frame, (10)):

    p = E_mf . D(t) . Π_{i = X, Y, Z, C, B} [ L_i . M_i(q_i + v_i) . E_i(u_i) ] . (p_tool(l_t) + s(t) z)
        + g(l_t, R) + ξ

- M_i: the nominal motion (translation along x / y / z, rotation about z / y).
- E_i(u_i) = Trans(δ_x, δ_y, δ_z) . Rz(ε_z) Ry(ε_y) Rx(ε_x): the six component
  errors of axis i (ISO 230-1): for a linear axis the positioning error (δ
  along its own direction), two straightness errors and roll, pitch, yaw; for
  a rotary axis the angular positioning error (ε about its own axis), two tilt
  (wobble) errors, two radial and one axial motion error. Each is a smooth,
  non-polynomial function of the axis's own position: for a linear axis, a sum
  of three sines with seeded amplitudes, periods (3.3-16 half ranges: at most about half a
  period over the travel, the bow and wave shapes of ball-screw and guideway errors) and phases, plus a
  linear scale term and, for the positioning error, an exponential end term
  (ball-screw heating near the motor); for a rotary axis, harmonics of once
  and twice per revolution of the angle itself (errors of a rotary axis repeat
  every turn).
- L_i: location errors between the axes (ISO 230-7 / squareness): small
  constant rotations of each axis's frame (squareness of Y to X, Z to X and
  Y; tilts of the C and B axis lines) and, for the rotary axes, offsets of the
  axis line (Trans(o) . M . Trans(-o), the error moves with the angle).
- E_mf: the tracker (measurement) frame error, (9): a fixed small rigid motion.
- p_tool(l_t): the true tool vector: nominal length plus a tool setting error
  growing with the length, and a lateral offset of the retroreflector mount
  proportional to the length (outside the paper's model, which corrects
  the length only, (10)).

Error sources the paper's model lacks (so that a correct model's residual
does not vanish, as Table 5's 0.038 mm does not):

- a two-axis interaction: the bridge sags in z by an amount that depends on
  X and Y together, sin(π x̂) sin(π ŷ) (x̂, ŷ in [0, 1]): no sum of
  single-axis functions (3) represents it;
- a slow thermal drift along the pose order t (0 = first measurement, 1 =
  last): spindle growth s(t) = s_∞ (1 - exp(-t / τ)) along the tool axis and
  a drift D(t) of the whole machine in x;
- a tool-length-dependent term: gravity bends the tool, g = k l_t³ g_⊥ (g_⊥
  the component of gravity across the tool direction);
- the lateral retroreflector mount offset above;
- axis repeatability noise v on the commands (σ from the machine's YAML:
  3 µm linear, 0.001 deg rotary) and isotropic tracker noise ξ (σ = 20 µm by
  default: Paper I 4.1 gives 5 µm/m for the tracker, i.e. 15-30 µm at the
  3-6 m of this machine's travel, plus 12.5 µm for the active target).

Magnitudes. Paper I Table 5: the nominal model's residual is 0.307 mm mean,
0.739 mm max on the identification set. The amplitudes below are physical
(tens of µm, tens of µrad) and were scaled once, globally (``scale``), so
that the residual of the nominal kinematics after a rigid best fit (Kabsch)
over the measured region is close to that (seed 0: 0.26 mm mean, 0.65 mm max;
seeds 0-2: 0.24-0.32 mm). The split between the groups follows two facts of
the paper's machine: its knee c = 0.4 mm per half axis motion (3.4) means the
true tool-tip error changes by well under a millimetre over half of any
axis's travel, the C axis's 540 deg included, so the rotary head's location
errors are those of a commissioned head (15 µm axis-line offsets, 15 µrad
tilts: pivot lengths are measured at commissioning) while most of the
volumetric error comes from the long linear axes (positioning, straightness,
squareness). Exact slopes of this truth per half axis motion, seed 0, 0.5 m
tool: X 0.54, Y 0.46, Z 0.36, C 1.25, B 0.49 mm at most (the C value is the
upstream angular errors times the tool, turned with C). No individual term
was tuned against torchcal's model.

Measured region (Figures 2, 3, 11; :func:`measured_region_floor`). Paper I
measures with a laser tracker on the table: with the spindle tilted far (large
|B|) the head comes close to the table at low Z and blocks the beam or
collides (Figure 3), so the data lack low Z at large |B|, and the 25
extrapolation points are "at the bottom border of the BZ space" (Figure 11).
The reading used here: the measured region's floor rises with |B| as
Z_floor(B) = Z_min + h ΔZ (|B| / B_max)², h = 0.35; the extrapolation band
is the bottom g ΔZ (g = 0.3, 294 mm of Paper I's Z travel) of the region
above that floor, and the identification / interpolation points lie above
the band. The paper does not give the band's depth (Figure 11 is not in the
text); 0.3 is this simulation's design choice. At B = 0 the band
holds the lowest Z of all (Table 3's Z_min = 7.4 mm), below every
identification point: there the model's Z functions are truly extrapolated.
"""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pandas as pd
import torch

from ..core import units
from ..core.measurements import Measurements

AXES = ("X", "Y", "Z", "C", "B")
PRISMATIC = (True, True, True, False, False)
PAPER1_LIMITS = ((83.2, 6081.1), (37.2, 2557.1), (7.4, 988.2), (-269.7, 269.9), (-109.5, 109.9))
"""Paper I Table 3: min / max axis commands (mm, deg)."""
PAPER1_TOOLS_MM = (402.9, 500.9)
"""Paper I (32): total tool lengths l_Bs + l_st, mm."""

FLOOR_H = 0.35
"""Rise of the measured region's Z floor at |B| = B_max, fraction of the Z range."""
BAND_G = 0.3
"""Depth of the extrapolation band at the bottom border, fraction of the Z range."""

SET_CODES = {"identification": 0, "interpolation": 1, "extrapolation": 2}

# component amplitudes: linear axes (δ in m, ε in rad), rotary axes
_LIN_POS = 70e-6      # positioning error (sum of sines), m
_LIN_SCALE = 15e-6    # scale error per metre of travel
_LIN_EXP = 25e-6      # ball-screw end term, m
_LIN_STR = 50e-6      # straightness, m
_LIN_ANG = {"X": 5e-6, "Y": 8e-6, "Z": 15e-6}   # roll / pitch / yaw, rad: the arm to the tool shrinks X -> Z
_ROT_POS = 12e-6      # angular positioning, rad
_ROT_TILT = 8e-6      # wobble, rad
_ROT_RAD = 5e-6       # radial / axial motion, m
_SQUARE = 40e-6       # squareness of the linear axes, rad
_ROT_SQUARE = 15e-6   # tilt of the rotary axis lines, rad
_ROT_OFFSET = 15e-6   # rotary axis line offsets, m (a commissioned head: pivot lengths measured)
_BASE_T, _BASE_R = 0.5e-3, 2e-4   # tracker frame error E_mf
_SAG = 12e-6          # X-Y bridge sag, m
_THERMAL_Z, _THERMAL_X, _TAU = 15e-6, 6e-6, 0.3
_TOOL_LEN = 30e-6     # tool setting error per 0.5 m, m
_TOOL_LAT = 12e-6     # lateral mount offset per 0.5 m, m
_GRAVITY = 6e-6       # tool bending at 0.5 m, horizontal tool, m
DEFAULT_SCALE = 2.8
"""Global factor on every systematic amplitude: nominal residual ≈ 0.3 mm mean after a rigid fit (Table 5)."""


def limits_si(device=None) -> torch.Tensor:
    """Paper I Table 3 command limits (5, 2), SI (m, rad)."""
    lim = torch.tensor(PAPER1_LIMITS, dtype=torch.float64)
    return units.joints_to_si(lim.T, torch.tensor(PRISMATIC)).T.contiguous().to(device)


def _rx(a):
    c, s = a.cos(), a.sin()
    o, z = torch.ones_like(a), torch.zeros_like(a)
    return torch.stack([o, z, z, z, c, -s, z, s, c], -1).reshape(*a.shape, 3, 3)


def _ry(a):
    c, s = a.cos(), a.sin()
    o, z = torch.ones_like(a), torch.zeros_like(a)
    return torch.stack([c, z, s, z, o, z, -s, z, c], -1).reshape(*a.shape, 3, 3)


def _rz(a):
    c, s = a.cos(), a.sin()
    o, z = torch.ones_like(a), torch.zeros_like(a)
    return torch.stack([c, -s, z, s, c, z, z, z, o], -1).reshape(*a.shape, 3, 3)


def _hom(R, p):
    """(..., 3, 3), (..., 3) -> (..., 4, 4)."""
    T = torch.zeros(*R.shape[:-2], 4, 4, dtype=R.dtype, device=R.device)
    T[..., :3, :3] = R
    T[..., :3, 3] = p
    T[..., 3, 3] = 1.0
    return T


def _small(eps, delta):
    """Component-error transform Trans(δ) Rz Ry Rx (exact rotations). eps, delta (..., 3) -> (..., 4, 4)."""
    R = _rz(eps[..., 2]) @ _ry(eps[..., 1]) @ _rx(eps[..., 0])
    return _hom(R, delta)


def measured_region_floor(b: torch.Tensor, limits: torch.Tensor | None = None, h: float = FLOOR_H) -> torch.Tensor:
    """Lowest Z (m) of the measured region at B = b (rad): Z_min + h ΔZ (|b| / B_max)². (...,) -> (...,)."""
    lim = limits_si(b.device) if limits is None else limits
    zmin, zspan = lim[2, 0], lim[2, 1] - lim[2, 0]
    bmax = lim[4].abs().max()
    return zmin + h * zspan * (b.abs() / bmax) ** 2


class MachineTruth:
    """The simulated XYZCB machine tool of Paper I (see the module docstring for every error source).

    seed: draws every error function and constant; scale: global factor on the
    systematic amplitudes (:data:`DEFAULT_SCALE`); unmodelled: include the
    sources the paper's model lacks (interaction, thermal drift, tool bending,
    lateral mount offset); limits: (5, 2) SI axis ranges that normalize the
    error functions (default Table 3).

    Example:
        >>> truth = MachineTruth(seed=0)
        >>> q = limits_si().mean(1).expand(2, 5)
        >>> tool = torch.tensor([0.0, 0.0, 0.5009], dtype=torch.float64)
        >>> err = truth.points(q, tool) - truth.nominal_points(q, tool)
        >>> err.shape, bool(err.norm(dim=1).max() < 2e-3)
        (torch.Size([2, 3]), True)
    """

    def __init__(self, seed: int = 0, scale: float = DEFAULT_SCALE, unmodelled: bool = True,
                 limits: torch.Tensor | None = None):
        self.seed = int(seed)
        self.scale = float(scale)
        self.unmodelled = bool(unmodelled)
        self.limits = (limits_si() if limits is None else torch.as_tensor(limits, dtype=torch.float64)).clone()
        g = torch.Generator().manual_seed(self.seed)

        def n(*shape):
            return torch.randn(*shape, generator=g, dtype=torch.float64)

        def u(*shape, lo=0.0, hi=1.0):
            return lo + (hi - lo) * torch.rand(*shape, generator=g, dtype=torch.float64)

        s = self.scale
        # linear axes: (3 axes, 6 components, 3 sines); components order δx δy δz εx εy εz
        amp = torch.zeros(3, 6)
        for a, name in enumerate(AXES[:3]):
            for c in range(3):
                amp[a, c] = _LIN_POS if c == a else _LIN_STR
            amp[a, 3:] = _LIN_ANG[name]
        self.lin_amp = s * amp.double()[..., None] * n(3, 6, 3) / math.sqrt(3)
        self.lin_w = u(3, 6, 3, lo=math.pi / 8, hi=math.pi * 0.6)          # rad per unit of u in [-1, 1]
        self.lin_phase = u(3, 6, 3, hi=2 * math.pi)
        half = (self.limits[:3, 1] - self.limits[:3, 0]) / 2
        self.lin_scale = s * _LIN_SCALE * n(3) * half                       # δ along the axis at u = 1
        self.lin_exp = s * _LIN_EXP * n(3)
        self.lin_kappa = u(3, lo=2.0, hi=4.0)
        # rotary axes C, B: (2 axes, 6 components, harmonics 1 and 2 of the angle)
        ramp = torch.tensor([_ROT_RAD] * 3 + [_ROT_TILT] * 3, dtype=torch.float64).expand(2, 6).clone()
        ramp[0, 5] = _ROT_POS   # C: angular positioning about z
        ramp[1, 4] = _ROT_POS   # B: angular positioning about y
        self.rot_amp = s * ramp[..., None] * n(2, 6, 2) * torch.tensor([1.0, 0.4], dtype=torch.float64)
        self.rot_phase = u(2, 6, 2, hi=2 * math.pi)
        # location errors: rotations of each axis frame (3 angles) and rotary axis-line offsets
        self.loc_rot = s * _SQUARE * n(5, 3)
        self.loc_rot[3:] *= _ROT_SQUARE / _SQUARE
        self.loc_rot[0] = 0.0   # X is the reference axis; its orientation is the base frame's
        self.rot_offset = s * _ROT_OFFSET * n(2, 3)
        self.base_eps = _BASE_R * n(3)
        self.base_delta = _BASE_T * n(3)
        # unmodelled
        self.sag = s * _SAG * (1 + 0.3 * n(()).abs())
        self.thermal_z = s * _THERMAL_Z * (1 + 0.2 * n(()))
        self.thermal_x = s * _THERMAL_X * n(())
        self.tool_len = s * _TOOL_LEN * n(())
        self.tool_lat = s * _TOOL_LAT * n(2)
        self.gravity = s * _GRAVITY * (1 + 0.2 * n(()).abs())

    # ---------------------------------------------------------------- error functions
    def normalized(self, q: torch.Tensor) -> torch.Tensor:
        """Axis positions (..., 5) SI -> u (..., 5) in [-1, 1] over the limits (the error functions' variable)."""
        lim = self.limits.to(q)
        return 2 * (q - lim[:, 0]) / (lim[:, 1] - lim[:, 0]) - 1

    def component_errors(self, q: torch.Tensor) -> torch.Tensor:
        """The six component errors of every axis at positions q (B, 5) SI -> (B, 5, 6): [δx, δy, δz, εx, εy, εz] (m, rad)."""
        dev = q.device
        u = self.normalized(q)
        ul = u[:, :3, None, None]                                              # (B, 3, 1, 1)
        lin = (self.lin_amp.to(dev) * torch.sin(self.lin_w.to(dev) * ul + self.lin_phase.to(dev))).sum(-1)  # (B, 3, 6)
        idx = torch.arange(3, device=dev)
        pos = self.lin_scale.to(dev) * u[:, :3] + self.lin_exp.to(dev) * torch.exp(self.lin_kappa.to(dev) * (u[:, :3] - 1))
        lin[:, idx, idx] = lin[:, idx, idx] + pos
        k = torch.tensor([1.0, 2.0], dtype=q.dtype, device=dev)
        ang = q[:, 3:, None, None] * k                                          # (B, 2, 1, 2)
        rot = (self.rot_amp.to(dev) * torch.sin(ang + self.rot_phase.to(dev))).sum(-1)   # (B, 2, 6)
        return torch.cat([lin, rot], 1)

    # ---------------------------------------------------------------------- the chain
    def frames(self, q: torch.Tensor, t: torch.Tensor | None = None) -> torch.Tensor:
        """True last-frame pose (B, 4, 4) in the tracker frame for the axis positions q (B, 5) SI (incl. noise if any)."""
        B, dev, dt = q.shape[0], q.device, q.dtype
        e = self.component_errors(q)
        eye = torch.eye(3, dtype=dt, device=dev).expand(B, 3, 3)
        zero = torch.zeros(B, 3, dtype=dt, device=dev)
        unit = torch.eye(3, dtype=dt, device=dev)
        T = _small(self.base_eps.to(dev).expand(B, 3), self.base_delta.to(dev).expand(B, 3))
        if self.unmodelled and t is not None:
            drift = torch.zeros(B, 3, dtype=dt, device=dev)
            drift[:, 0] = self.thermal_x.to(dev) * t
            T = T @ _hom(eye, drift)
        for i in range(3):   # X, Y, Z: L_i . Trans(q_i e_i) . E_i
            L = _small(self.loc_rot[i].to(dev).expand(B, 3), zero)
            M = _hom(eye, q[:, i, None] * unit[i])
            T = T @ L @ M @ _small(e[:, i, 3:], e[:, i, :3])
            if i == 1 and self.unmodelled:   # bridge sag: a function of X and Y together
                xh = (q[:, 0] - self.limits[0, 0].to(dev)) / (self.limits[0, 1] - self.limits[0, 0]).to(dev)
                yh = (q[:, 1] - self.limits[1, 0].to(dev)) / (self.limits[1, 1] - self.limits[1, 0]).to(dev)
                sag = torch.zeros(B, 3, dtype=dt, device=dev)
                sag[:, 2] = -self.sag.to(dev) * torch.sin(math.pi * xh) * torch.sin(math.pi * yh)
                T = T @ _hom(eye, sag)
        for r, (i, rot) in enumerate(((3, _rz), (4, _ry))):   # C, B: L_i . Trans(o) . R(q_i) . Trans(-o) . E_i
            o = self.rot_offset[r].to(dev).expand(B, 3)
            L = _small(self.loc_rot[i].to(dev).expand(B, 3), o)
            M = _hom(rot(q[:, i]), zero) @ _hom(eye, -o)
            T = T @ L @ M @ _small(e[:, i, 3:], e[:, i, :3])
        return T

    def true_tool(self, tool_vectors: torch.Tensor) -> torch.Tensor:
        """True tool vectors (B, 3) in the last frame for nominal ones (B, 3): length error and lateral mount offset."""
        l = tool_vectors.norm(dim=-1, keepdim=True)
        out = tool_vectors + tool_vectors / l.clamp_min(1e-12) * self.tool_len.to(tool_vectors) * (l / 0.5)
        if self.unmodelled:
            lat = torch.zeros_like(tool_vectors)
            lat[..., :2] = self.tool_lat.to(tool_vectors) * (l / 0.5)
            out = out + lat
        return out

    def points(self, q: torch.Tensor, tool_vectors: torch.Tensor, t: torch.Tensor | None = None,
               v: torch.Tensor | None = None) -> torch.Tensor:
        """Noise-free tool points (B, 3) in the tracker frame, m.

        q: (B, 5) commands, SI; tool_vectors: (3,) or (B, 3) nominal tool
        vectors in the last frame, m (Paper I: [0, 0, l_t]); t: (B,) pose order
        in [0, 1] for the thermal drift (None: no drift, a cold machine); v:
        (B, 5) axis positioning errors added to the commands.
        """
        q = torch.as_tensor(q, dtype=torch.float64)
        B = q.shape[0]
        pt = torch.as_tensor(tool_vectors, dtype=q.dtype, device=q.device).expand(B, 3)
        a = q if v is None else q + v
        F = self.frames(a, t)
        ptool = self.true_tool(pt)
        if self.unmodelled and t is not None:   # spindle growth along the tool axis
            l = pt.norm(dim=-1, keepdim=True).clamp_min(1e-12)
            growth = self.thermal_z.to(q) * (1 - torch.exp(-t / _TAU))
            ptool = ptool + pt / l * growth[:, None]
        p = (F[:, :3, :3] @ ptool[..., None])[..., 0] + F[:, :3, 3]
        if self.unmodelled:   # gravity bends the tool across its direction: k l^3 g_perp
            d = F[:, :3, :3] @ (pt / pt.norm(dim=-1, keepdim=True).clamp_min(1e-12))[..., None]
            d = d[..., 0]
            grav = torch.tensor([0.0, 0.0, -1.0], dtype=q.dtype, device=q.device)
            gperp = grav - (d @ grav)[:, None] * d
            p = p + self.gravity.to(q) * (pt.norm(dim=-1, keepdim=True) / 0.5) ** 3 * gperp
        return p

    def nominal_points(self, q: torch.Tensor, tool_vectors: torch.Tensor) -> torch.Tensor:
        """Nominal tool points (B, 3): F_nom = Trans(X, Y, Z) Rz(C) Ry(B), nominal tools, no frame error."""
        q = torch.as_tensor(q, dtype=torch.float64)
        pt = torch.as_tensor(tool_vectors, dtype=q.dtype, device=q.device).expand(q.shape[0], 3)
        R = _rz(q[:, 3]) @ _ry(q[:, 4])
        return (R @ pt[..., None])[..., 0] + q[:, :3]

    def describe(self) -> dict:
        """Seed, scale and the size of every error group (file units: mm, µrad) for reports."""
        e = self.component_errors(self.limits[:, 0] + (self.limits[:, 1] - self.limits[:, 0])
                                  * torch.linspace(0, 1, 201, dtype=torch.float64)[:, None])
        peak = e.abs().max(0).values   # (5, 6)
        return {
            "seed": self.seed, "scale": self.scale, "unmodelled": self.unmodelled,
            "component_peak_mm_or_urad": {a: [round(float(v) * 1e3, 4) for v in peak[i, :3]]
                                          + [round(float(v) * 1e6, 2) for v in peak[i, 3:]] for i, a in enumerate(AXES)},
        }


def _rigid_fit_residuals(p: torch.Tensor, q: torch.Tensor) -> torch.Tensor:
    """|R p + t - q| per point after the least-squares rigid fit (Kabsch). (N, 3), (N, 3) -> (N,)."""
    pc, qc = p - p.mean(0), q - q.mean(0)
    U, _, Vt = torch.linalg.svd(pc.T @ qc)
    d = torch.sign(torch.linalg.det(Vt.T @ U.T))
    D = torch.diag(torch.tensor([1.0, 1.0, float(d)], dtype=p.dtype, device=p.device))
    R = Vt.T @ D @ U.T
    return (pc @ R.T - qc).norm(dim=1)


def region_commands(n: int, seed: int, band: bool, limits: torch.Tensor | None = None, skip: int = 0,
                    floor_h: float = FLOOR_H, band_g: float = BAND_G) -> torch.Tensor:
    """n quasi-random commands (n, 5) SI in the measured region (band=False: above the extrapolation band;
    band=True: in the band at the bottom border of BZ space). Scrambled Sobol, seeded. floor_h, band_g:
    the region's shape (module docstring)."""
    from scipy.stats import qmc  # 1-3 s to import: only where machine commands are drawn, not on import of torchcal.sim

    lim = limits_si() if limits is None else limits
    sampler = qmc.Sobol(d=5, scramble=True, seed=np.random.default_rng(seed))
    import warnings

    with warnings.catch_warnings():
        warnings.simplefilter("ignore", UserWarning)
        if skip:
            sampler.fast_forward(skip)
        uu = torch.from_numpy(sampler.random(n))
    q = lim[:, 0] + uu * (lim[:, 1] - lim[:, 0])
    floor = measured_region_floor(q[:, 4], lim, floor_h)
    g = band_g * (lim[2, 1] - lim[2, 0])
    if band:
        q[:, 2] = floor + uu[:, 2] * g
    else:
        lo = floor + g
        q[:, 2] = lo + uu[:, 2] * (lim[2, 1] - lo)
    return q


def simulate_machine_dataset(truth: MachineTruth, n_commands: int = 295, tools=PAPER1_TOOLS_MM, seed: int = 0,
                             n_interpolation: int = 25, n_extrapolation: int = 25, tracker_sigma_mm: float = 0.020,
                             axis_sigma=(0.003, 0.001), csv_path=None, floor_h: float = FLOOR_H,
                             band_g: float = BAND_G) -> tuple[Measurements, dict]:
    """Paper I's data set (4.1) measured on the simulated machine.

    n_commands quasi-random commands in the measured region (module docstring),
    n_extrapolation of them in the band at the bottom border of BZ space, the
    rest above it, of which n_interpolation are picked at random (seeded) for
    interpolation validation; every command is measured with every tool (mm,
    total lengths l_t, tool vector [0, 0, l_t]). The poses are visited in a
    seeded random order (pose id = visiting order, the thermal drift follows
    it). floor_h, band_g: the measured region's shape (module docstring). tracker_sigma_mm: isotropic tracker noise per coordinate; axis_sigma:
    (mm, deg) repeatability sigma of the linear and rotary axes, drawn anew
    for every row.

    Returns (Measurements (R = n_commands x tools rows, pose-major: pose k's
    tools are rows k T .. k T + T - 1), split {'identification',
    'interpolation', 'extrapolation': row indices (long)}). ``extra`` holds
    'set' (R,) codes :data:`SET_CODES`, 'v' (R, 5) the drawn axis errors,
    'xyz_exact' (R, 3) the noise-free points, 't' (R,) the pose order. csv_path:
    also write the CSV contract (pose, tool, q1..q5, x, y, z in mm / deg,
    plus 'set') there.

    Example:
        >>> data, split = simulate_machine_dataset(MachineTruth(seed=0), n_commands=40, n_interpolation=5,
        ...                                        n_extrapolation=5, seed=1)
        >>> len(data), [len(split[k]) for k in ("identification", "interpolation", "extrapolation")]
        (80, [60, 10, 10])
    """
    n_main = n_commands - n_extrapolation
    if n_main - n_interpolation < 1 or n_extrapolation < 0 or n_interpolation < 0:
        raise ValueError(f"simulate_machine_dataset: {n_commands} commands cannot hold {n_interpolation} interpolation "
                         f"and {n_extrapolation} extrapolation points and an identification set")
    lim = truth.limits
    main = region_commands(n_main, seed, band=False, limits=lim, floor_h=floor_h, band_g=band_g)
    ext = (region_commands(n_extrapolation, seed + 7919, band=True, limits=lim, floor_h=floor_h, band_g=band_g)
           if n_extrapolation else main[:0])
    g = torch.Generator().manual_seed(seed)
    codes = torch.zeros(n_commands, dtype=torch.long)
    interp = torch.randperm(n_main, generator=g)[:n_interpolation]
    codes[interp] = SET_CODES["interpolation"]
    codes[n_main:] = SET_CODES["extrapolation"]
    q_all = torch.cat([main, ext])
    order = torch.randperm(n_commands, generator=g)          # visiting order
    q_all, codes = q_all[order], codes[order]
    tl = torch.as_tensor(tools, dtype=torch.float64) * units.MM
    T = tl.numel()
    q = q_all.repeat_interleave(T, 0)
    tool = torch.arange(T).repeat(n_commands)
    pose = torch.arange(n_commands).repeat_interleave(T)
    R = q.shape[0]
    t = torch.arange(R, dtype=torch.float64) / max(R - 1, 1)
    tvec = torch.zeros(R, 3, dtype=torch.float64)
    tvec[:, 2] = tl[tool]
    sig = torch.tensor([axis_sigma[0] * units.MM] * 3 + [axis_sigma[1] * units.DEG] * 2, dtype=torch.float64)
    v = torch.randn(R, 5, generator=g, dtype=torch.float64) * sig
    exact = truth.points(q, tvec, t=t)
    xyz = truth.points(q, tvec, t=t, v=v) + torch.randn(R, 3, generator=g, dtype=torch.float64) * tracker_sigma_mm * units.MM
    data = Measurements.from_tensors(q, tool, xyz, pose=pose, source="simulated machine (torchcal.sim.machine_truth)")
    row_codes = codes.repeat_interleave(T)
    data.extra = {"set": row_codes, "v": v, "xyz_exact": exact, "t": t}
    split = {k: (row_codes == c).nonzero()[:, 0] for k, c in SET_CODES.items()}
    if csv_path is not None:
        write_machine_csv(csv_path, data)
    return data, split


def write_machine_csv(path, data: Measurements) -> Path:
    """The CSV contract for machine data: pose, tool, q1..q5 (mm, mm, mm, deg, deg), x, y, z (mm), then 'set' if present."""
    from ..io.csv import write_table

    qf = units.joints_from_si(data.q.detach().cpu(), torch.tensor(PRISMATIC)).numpy()
    cols = {"pose": data.pose.cpu().numpy(), "tool": data.tool.cpu().numpy()}
    for i in range(qf.shape[1]):
        cols[f"q{i + 1}"] = qf[:, i]
    xyz = units.m_to_mm(data.xyz.detach().cpu()).numpy()
    for i, c in enumerate("xyz"):
        cols[c] = xyz[:, i]
    if "set" in data.extra:
        cols["set"] = data.extra["set"].cpu().numpy()
    return write_table(path, pd.DataFrame(cols))


__all__ = [
    "AXES",
    "BAND_G",
    "DEFAULT_SCALE",
    "FLOOR_H",
    "PAPER1_LIMITS",
    "PAPER1_TOOLS_MM",
    "PRISMATIC",
    "SET_CODES",
    "MachineTruth",
    "limits_si",
    "measured_region_floor",
    "region_commands",
    "simulate_machine_dataset",
    "write_machine_csv",
]
