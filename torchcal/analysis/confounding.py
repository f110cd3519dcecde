"""Is backlash confounded with position in a data set? Per joint and per backlash parameter.

Paper II's backlash term s_i * Δq_ib(q_i) (13)-(14) is identifiable only if a
joint's approach direction s_i varies independently of its position q_i. In a
data set where s_i is (nearly) a function of q_i, the column of a backlash
coefficient in the Jacobian lies (nearly) in the span of the position terms
eps_z(q_i) of the same joint: the fit splits the error between them
arbitrarily, and the model is then wrong for poses approached the other way.

Two looks at it:

- data only (:attr:`ConfoundingReport.correlation`, :attr:`~ConfoundingReport.r2`):
  per joint, the Pearson correlation of s_i with q_i and the R² of a least
  squares regression of s_i on a low-order Chebyshev basis of q_i (default
  cubic). Note that *any* visiting order has some: s_k = sign(q_k - q_k-1), so
  a high q_k is more likely approached from below. For independent uniform
  positions in random order E[s | q] = 2u - 1 (u the position's quantile), so
  a plain shuffle leaves corr ≈ 0.58, R² ≈ 1/3; sequence-ordered Sobol points
  reach R² 0.6-0.9 (FANUC, 250 poses). :func:`torchcal.analysis.planning.plan_poses`
  chooses the order to bring it near 0.
- with a model (:attr:`ConfoundingReport.parameters`): per backlash coefficient, the
  fraction R² of its (whitened, joint-noise-reduced when a NoiseModel is given)
  Jacobian column that the other, position-dependent columns explain
  (uncentred least squares: the geometry of the fit), the variance inflation
  1 / (1 - R²), the same against only its own joint's position terms, and the
  largest single |cosine| with a position column and that column's name.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import torch

from ..core.basis import chebyshev, normalize
from ..core.measurements import Measurements

R2_THRESHOLD = 0.5
"""Default data R² (direction explained by position) above which :meth:`ConfoundingReport.warnings` warns."""

VIF_THRESHOLD = 10.0
"""Default variance inflation of a backlash coefficient above which :meth:`ConfoundingReport.warnings` warns."""


@dataclass
class BacklashTerm:
    """Identifiability of one backlash coefficient against the position terms.

    r2_position: fraction of its column's squared norm explained by all non-backlash
    columns; vif: 1 / (1 - r2_position); r2_joint: the same, by its own joint's
    position terms only; max_corr / corr_with: largest |cosine| with a single
    non-backlash column and that column's name. NaN where the column is zero (no
    known directions).
    """

    name: str
    joint: int
    r2_position: float
    vif: float
    r2_joint: float
    max_corr: float
    corr_with: str


def adjusted_r2(r2: float, rows: int, order: int) -> float:
    """R² less what ``order`` predictors fit in ``rows`` rows by chance: 1 - (1 - R²)(rows - 1)/(rows - order - 1).

    A shuffled visiting order leaves R² ≈ 1/3 (module docstring); on 30 poses a cubic adds ~0.1 by chance, and a
    draw of 0.51 read as confounded (the adjusted value is 0.45). The plain R² where the rows are too few to adjust."""
    if rows <= order + 1 or r2 != r2:
        return r2
    return 1.0 - (1.0 - r2) * (rows - 1) / (rows - order - 1)


@dataclass
class ConfoundingReport:
    """Per joint direction/position dependence (+ per backlash coefficient identifiability).

    joint_names: (n,); rows: (n,) rows with a known direction; correlation: (n,)
    Pearson corr(s_i, q_i) (NaN when s_i is constant); r2: (n,) R² of s_i on
    Chebyshev c_0..c_order of q_i (1 when s_i is constant: a one-sided joint's
    backlash is a constant offset); plus_fraction: (n,) share of +1;
    one_sided_bins: (n,) position bins (of ``bins`` over the limits) with data
    from only one direction; parameters: per backlash coefficient, when a model
    with backlash was given.
    """

    joint_names: list[str]
    rows: torch.Tensor
    correlation: torch.Tensor
    r2: torch.Tensor
    plus_fraction: torch.Tensor
    one_sided_bins: torch.Tensor
    order: int
    bins: int
    parameters: list[BacklashTerm] = field(default_factory=list)

    def warnings(self, threshold: float = R2_THRESHOLD, vif_threshold: float = VIF_THRESHOLD) -> list[str]:
        """Readable warnings for joints whose direction R², adjusted for the rows (:func:`adjusted_r2`), > threshold
        (or that are one-sided)
        and for backlash coefficients whose variance inflation > vif_threshold."""
        out = []
        for j, name in enumerate(self.joint_names):
            rows, r2, c = int(self.rows[j]), float(self.r2[j]), float(self.correlation[j])
            if rows == 0:
                continue
            if c != c:  # NaN: constant direction
                side = "+1" if float(self.plus_fraction[j]) > 0.5 else "-1"
                out.append(f"{name}: every row approaches from {side}; its backlash cannot be told from a "
                           f"position (constant) error")
            elif adjusted_r2(r2, rows, self.order) > threshold:
                out.append(f"{name}: the approach direction is largely a function of position "
                           f"(R² {r2:.2f} on a Chebyshev order-{self.order} basis, "
                           f"{adjusted_r2(r2, rows, self.order):.2f} adjusted for {rows} rows, corr {c:+.2f}); backlash and "
                           f"position errors of this joint are confounded, and a model fitted on these data may be "
                           f"off for poses approached the other way. Visit the poses in a decorrelated order "
                           f"(torchcal plan-poses).")
        for p in self.parameters:
            if p.vif == p.vif and p.vif > vif_threshold:
                out.append(f"{p.name}: {100 * p.r2_position:.1f} % of its Jacobian column is explained by position "
                           f"terms (variance inflation {p.vif:.3g}; {100 * p.r2_joint:.1f} % by {self.joint_names[p.joint]}'s "
                           f"own; largest single |corr| {p.max_corr:.2f} with {p.corr_with}): poorly identifiable")
        return out

    def table(self) -> list[dict]:
        """One row per joint: name, rows, corr, r2, plus_fraction, one_sided_bins, and the largest backlash VIF."""
        rows = []
        for j, name in enumerate(self.joint_names):
            vifs = [p.vif for p in self.parameters if p.joint == j and p.vif == p.vif]
            rows.append({
                "joint": name,
                "rows": int(self.rows[j]),
                "corr": float(self.correlation[j]),
                "r2": float(self.r2[j]),
                "plus_fraction": float(self.plus_fraction[j]),
                "one_sided_bins": int(self.one_sided_bins[j]),
                "backlash_vif": max(vifs) if vifs else None,
            })
        return rows

    def parameter_table(self) -> list[dict]:
        """One row per backlash coefficient (empty without a model)."""
        return [{"name": p.name, "joint": self.joint_names[p.joint], "r2_position": p.r2_position, "vif": p.vif,
                 "r2_joint": p.r2_joint, "max_corr": p.max_corr, "corr_with": p.corr_with} for p in self.parameters]

    def to_dict(self) -> dict:
        """JSON-able summary (NaN stays NaN: json writes it as NaN)."""
        return {"order": self.order, "bins": self.bins, "joints": self.table(), "parameters": self.parameter_table()}


# ----------------------------------------------------------------- data only
def direction_position_dependence(q: torch.Tensor, direction: torch.Tensor, limits: torch.Tensor, order: int = 3):
    """Per joint corr(s, q) and R² of s on a Chebyshev basis of q, over the rows where s != 0.

    q, direction: (R, n); limits: (n, 2) for the normalization (24).
    -> rows (n,) long, corr (n,), r2 (n,), plus_fraction (n,), all on q's device; batched over joints.
    """
    q = q.to(torch.float64)
    s = direction.to(q)
    lim = torch.as_tensor(limits, dtype=torch.float64, device=q.device)
    w = (s != 0).to(q)                                                 # (R, n) rows that count
    rows = w.sum(0)
    cnt = rows.clamp(min=1)
    mq, ms = (w * q).sum(0) / cnt, (w * s).sum(0) / cnt
    dq, ds = w * (q - mq), w * (s - ms)
    vq, vs = (dq * dq).sum(0), (ds * ds).sum(0)
    tiny = 1e-12 * cnt
    corr = torch.where((vq > tiny * lim.diff(dim=1)[:, 0] ** 2) & (vs > tiny), (dq * ds).sum(0) / (vq * vs).clamp(min=1e-300).sqrt(),
                       torch.full_like(vq, float("nan")))
    lam = normalize(q, lim[:, 0], lim[:, 1]).clamp(-1.0, 1.0)
    X = chebyshev(lam, order).transpose(0, 1) * w.T[..., None]          # (n, R, m+1), zero rows where s unknown
    y = (s * w).T[..., None]                                           # (n, R, 1)
    # least squares per joint via the (m+1)x(m+1) normal equations (Chebyshev on [-1, 1]: well conditioned);
    # pinv keeps a joint with few distinct positions (rank deficient) working
    XT = X.transpose(1, 2)
    beta = torch.linalg.pinv(XT @ X, rtol=1e-12, hermitian=True) @ (XT @ y)
    res = (y - X @ beta)[..., 0]
    r2 = torch.where(vs > tiny, 1.0 - (res * res).sum(1) / vs.clamp(min=1e-300), torch.ones_like(vs))
    r2 = torch.where(rows > 0, r2.clamp(0.0, 1.0), torch.full_like(r2, float("nan")))
    plus = ((s > 0).to(q) * w).sum(0) / cnt
    return rows.long(), corr, r2, plus


# ----------------------------------------------------------------- with a model
def _span_r2(gram: torch.Tensor, cross: torch.Tensor, rtol: float = 1e-12) -> torch.Tensor:
    """Fraction of each unit column a_c explained by the span of the unit columns B: a^T B (B^T B)^+ B^T a.

    gram: (p, p) B^T B; cross: (p, k) B^T a_c. Through the Gram matrix (eigh, not an SVD of the tall B):
    a few ms instead of seconds for thousands of rows; eigenvalues below rtol x the largest (singular
    values below 1e-6 x) count as zero.
    """
    if gram.shape[0] == 0:
        return torch.zeros(cross.shape[1], dtype=cross.dtype, device=cross.device)
    return (cross * (torch.linalg.pinv(gram, rtol=rtol, hermitian=True) @ cross)).sum(0)


def _fold_joint_noise(A: torch.Tensor, C: torch.Tensor, w_v: torch.Tensor) -> torch.Tensor:
    """L_r^-1 A_r with L_r L_r^T = I + C_r W_v,r^-1 C_r^T, as
    :func:`torchcal.analysis.identifiability.reduced_jacobian`; the 3x3 inverses are formed first
    (a batched triangular solve with P right-hand sides is slow on the CPU)."""
    eye = torch.eye(3, dtype=A.dtype, device=A.device)
    L = torch.linalg.cholesky(eye + (C / w_v[:, None, :]) @ C.transpose(1, 2))
    Linv = torch.linalg.solve_triangular(L, eye.expand_as(L), upper=False)
    return Linv @ A


def backlash_terms(model, data: Measurements, noise=None, fixed=()) -> list[BacklashTerm]:
    """Identifiability of each free backlash coefficient of ``model`` on ``data`` (see module doc)."""
    from ..identify.layout import ParameterLayout

    data = data.to(model.device)
    direction = data.direction if data.has_direction else torch.zeros_like(data.q)
    layout = ParameterLayout(model, fixed)
    names = layout.names()
    with torch.no_grad():
        _, J = model.point_jacobians(data.q, data.tool, direction)
        A = layout.flatten_jacobian(J, data.q.shape[0])               # (R, 3, P)
        if noise is not None:
            A = A / noise.sigma_m
            var = noise.joint_variance(direction)
            if bool((var > 0).all()):
                A = _fold_joint_noise(A, J["v"] / noise.sigma_m, 1.0 / var)
    A = A.reshape(-1, A.shape[-1])
    is_bl = torch.tensor([".backlash." in n for n in names], dtype=torch.bool)
    if not bool(is_bl.any()):
        return []
    norm = A.norm(dim=0)
    other = (~is_bl) & (norm > 0).cpu()
    An = A / norm.clamp(min=1e-300)
    bl_idx = is_bl.nonzero()[:, 0].tolist()
    other_idx = other.nonzero()[:, 0]
    cols = An[:, bl_idx]
    Bo = An[:, other_idx.to(A.device)]
    gram = Bo.T @ Bo                                                   # (P_o, P_o)
    cross = Bo.T @ cols                                                # (P_o, k) cosines
    r2_all = _span_r2(gram, cross)
    cos = cross.abs()
    other_names = [names[int(k)] for k in other_idx]
    joint_names = list(model.joint_errors.joint_names)
    out = []
    for c, i in enumerate(bl_idx):
        name = names[i]
        j = joint_names.index(name.split(".backlash.")[0]) if name.split(".backlash.")[0] in joint_names else -1
        if float(norm[i]) == 0.0:
            out.append(BacklashTerm(name, j, float("nan"), float("nan"), float("nan"), float("nan"), ""))
            continue
        prefix = name.split(".backlash.")[0] + "."
        own = torch.tensor([nm.startswith(prefix) for nm in other_names], dtype=torch.bool).nonzero()[:, 0].to(A.device)
        r2_own = float(_span_r2(gram[own][:, own], cross[own, c : c + 1])[0])
        r2 = min(max(float(r2_all[c]), 0.0), 1.0)
        k = int(cos[:, c].argmax()) if cos.shape[0] else -1
        out.append(BacklashTerm(
            name, j, r2, 1.0 / max(1.0 - r2, 1e-16), min(max(r2_own, 0.0), 1.0),
            float(cos[k, c]) if k >= 0 else 0.0, names[int(other_idx[k])] if k >= 0 else ""))
    return out


def backlash_confounding(data: Measurements, names: list[str] | None = None, model=None, noise=None,
                         limits=None, order: int = 3, bins: int = 8) -> ConfoundingReport:
    """How far each joint's approach direction is confounded with its position in ``data``.

    data: measurements (q rad / m, direction ±1 / 0); names: joint names for the
    report (default the model's, else 'J1'..); model: a (fitted) RobotModel;
    with backlash, each free backlash coefficient's identifiability is added
    (its Jacobian at the data, whitened and with joint noise folded in when
    ``noise`` is given); limits: (n, 2) position range for the Chebyshev basis
    and the bins (default the model's command limits, else the data's range);
    order: Chebyshev order of the direction-on-position regression; bins: for
    the one-sided-bin count (:class:`DirectionCoverage`).
    Rows whose direction is 0 (unknown) are left out of the data-only measures.
    """
    from .coverage import DirectionCoverage

    q, s = data.q.to(torch.float64), data.direction.to(torch.float64)
    n = q.shape[1]
    if limits is None and model is not None:
        limits = model.command_limits
    if limits is None:
        lo, hi = (q.min(0).values, q.max(0).values) if q.shape[0] else (torch.zeros(n), torch.ones(n))
        pad = ((hi - lo) * 1e-9).clamp(min=1e-9)
        limits = torch.stack([lo - pad, hi + pad], 1)
    limits = torch.as_tensor(limits, dtype=torch.float64)
    if limits.shape != (n, 2):
        raise ValueError(f"backlash_confounding: limits must have shape ({n}, 2), got {tuple(limits.shape)}")
    if names is None:
        names = list(model.joint_errors.joint_names) if model is not None else [f"J{j + 1}" for j in range(n)]
    if len(names) != n:
        raise ValueError(f"backlash_confounding: {len(names)} names for {n} joints")
    if not data.has_direction:
        s = torch.zeros_like(q)
    rows, corr, r2, plus = direction_position_dependence(q, s, limits.to(q.device), order)
    cov = DirectionCoverage.from_data(q, s, limits, bins=bins)
    seen = cov.seen()
    known_bins = seen.any(-1)
    one_sided = (known_bins & ~seen.all(-1)).sum(1)
    params = []
    if model is not None and model.joint_errors.has_backlash and data.has_direction:
        params = backlash_terms(model, data, noise)
    return ConfoundingReport(list(names), rows.cpu(), corr.cpu(), r2.cpu(), plus.cpu(), one_sided.cpu(), int(order),
                             int(bins), params)
