"""Identifiability and uncertainty of a fitted model: what the data determine, and how well.

At a solution of the MLE problem (Paper II (31)-(33), :class:`CalibrationProblem`)
the Gauss-Newton Hessian of V in the model parameters b, with every row's joint
errors v_r eliminated by the Schur complement exactly as
:mod:`torchcal.identify.lm` does, is

    S = A^T A - sum_r A_r^T C_r (C_r^T C_r + W_v)^-1 C_r^T A_r
      = sum_r A_r^T (I + C_r W_v^-1 C_r^T)^-1 A_r            (Woodbury)

(A: whitened parameter Jacobian, C: whitened joint-error Jacobian, W_v: joint
precisions). The second form shows that S is the Gram matrix of the *reduced
whitened Jacobian* A~_r = L_r^-1 A_r with L_r L_r^T = I + C_r W_v^-1 C_r^T, a
3x3 Cholesky per row (batched): each row's joint noise is folded into its
measurement covariance. From A~ we get

- the singular values of the data alone and with the prior rows diag(sqrt(Λ)) appended;
- the parameter combinations the data cannot determine: right singular vectors of
  the column-equilibrated A~ (unit-invariant, like the gauge fixing) whose
  singular value is below ``rtol`` of the largest;
- the Laplace covariance Σ_b = (S + Λ)^-1 (prior included, joint errors
  marginalized), computed from the SVD of the augmented A~ (no squaring of the
  condition number), its standard deviations and correlations;
- the propagated position uncertainty of a tool point, Σ_p = J_p Σ_b J_p^T, with
  J_p = d p / d b from :meth:`RobotModel.point_jacobians`, batched over poses.

The propagation is linear. Combinations the data barely determine keep a
posterior as wide as the prior (default 1e-2 rad); a Gaussian that wide leaves
the curved valley along which the predictions stay put, so Monte-Carlo draws
from it spread the points more than Σ_p says (by tens of percent with
:class:`Prior`'s defaults on 30-100 poses). Σ_p is the first-order answer;
draws agree with it when the prior keeps the posterior in the linear regime.

Everything is SI inside; :meth:`Identifiability.summary`, :meth:`Identifiability.table`
and :func:`plot_position_std` report mm and degrees.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import torch

from ..core import units
from ..identify.gauge import fix_gauge
from ..identify.layout import ParameterLayout
from ..identify.problem import CalibrationProblem, NoiseModel, Prior
from ..core.measurements import Measurements

UNDETERMINED_RTOL = 1e-6
"""Default relative singular-value threshold below which a combination counts as undetermined."""

CORRELATION_THRESHOLD = 0.95


@dataclass
class Combination:
    """A parameter combination the data do not determine (a right singular vector).

    singular_value: of the column-equilibrated reduced Jacobian, relative to its
    largest; components: [(name, weight)] largest |weight| first (unit vector
    in equilibrated units: each parameter scaled by its column norm).
    """

    singular_value: float
    components: list[tuple[str, float]]
    direction: torch.Tensor | None = field(default=None, repr=False)
    """(P,) the same combination in parameter units (rad, m), scaled to max |entry| = 1:
    moving the free parameters along it leaves the data's predictions unchanged to first order."""

    def names(self) -> list[str]:
        return [n for n, _ in self.components]

    def __str__(self) -> str:
        terms = " ".join(f"{w:+.3f}*{n}" for n, w in self.components)
        return f"s/s_max={self.singular_value:.2e}: {terms}"


@dataclass
class CorrelatedPair:
    """Two parameters whose posterior correlation exceeds the threshold."""

    first: str
    second: str
    correlation: float


@dataclass
class Identifiability:
    """Identifiability and Laplace uncertainty of a model's free parameters at a solution.

    names: (P,) free parameter names (layout order); x: (P,) their values (SI);
    singular_values: (P,) of the reduced whitened Jacobian (v eliminated), data only;
    singular_values_prior: (P,) with the prior rows appended;
    relative_singular_values: (P,) of the column-equilibrated data-only Jacobian, / largest;
    covariance: (P, P) Laplace covariance (S + Λ)^-1 in SI (rad, m);
    std: (P,); correlation: (P, P); undetermined: combinations below ``rtol``;
    correlated: pairs with |corr| > ``corr_threshold``; pinned: names the gauge held fixed;
    chi2_dof: min_v V / (3R - P) at the solution, joint errors marginalized
    (≈ 1 when the noise model is right; the covariance is *not* rescaled by it).
    """

    names: list[str]
    x: torch.Tensor
    singular_values: torch.Tensor
    singular_values_prior: torch.Tensor
    relative_singular_values: torch.Tensor
    covariance: torch.Tensor
    std: torch.Tensor
    correlation: torch.Tensor
    undetermined: list[Combination]
    correlated: list[CorrelatedPair]
    pinned: list[str]
    chi2_dof: float
    rtol: float
    corr_threshold: float
    model: object = field(repr=False, default=None)
    layout: ParameterLayout | None = field(repr=False, default=None)
    joint_variance: torch.Tensor | None = field(repr=False, default=None)

    @property
    def rank(self) -> int:
        """Number of combinations the data determine (relative singular value >= rtol)."""
        return int((self.relative_singular_values >= self.rtol).sum())

    @property
    def condition_number(self) -> float:
        """Largest / smallest relative singular value of the data-only equilibrated Jacobian."""
        s = self.relative_singular_values
        return float(s[0] / s[-1]) if float(s[-1]) > 0 else float("inf")

    # ---------------------------------------------------------- propagation
    def point_covariance(self, q, tool, direction=None, repeatability: bool = False) -> torch.Tensor:
        """Covariance (B, 3, 3) m^2 of the predicted tool point from the parameter uncertainty.

        q: (B, n) controller commands (rad / m); tool: (B,) long or int;
        direction: (B, n) approach directions or None; repeatability: also add
        the joint positioning noise J_v Σ_v(s) J_v^T of one execution.
        """
        model, layout = self.model, self.layout
        q = torch.as_tensor(q, dtype=model.dtype, device=model.device)
        tool = torch.as_tensor(tool, dtype=torch.long, device=model.device).expand(q.shape[0])
        saved = layout.get()
        try:
            layout.set(self.x)
            with torch.no_grad():
                _, J = model.point_jacobians(q, tool, direction)
        finally:
            layout.set(saved)
        Jb = layout.flatten_jacobian(J, q.shape[0])  # (B, 3, P)
        cov = Jb @ self.covariance.to(Jb) @ Jb.transpose(1, 2)
        if repeatability:
            if self.joint_variance is None:
                raise ValueError("point_covariance: no joint variances known (build with a NoiseModel)")
            d = torch.zeros_like(q) if direction is None else torch.as_tensor(direction).to(q)
            fwd, bwd = self.joint_variance.to(q)
            var = torch.where(d > 0, fwd, torch.where(d < 0, bwd, 0.5 * (fwd + bwd)))
            Jv = J["v"]
            cov = cov + (Jv * var[:, None, :]) @ Jv.transpose(1, 2)
        return cov

    def point_std(self, q, tool, direction=None, repeatability: bool = False) -> torch.Tensor:
        """Predicted position standard deviation (B,) in metres: sqrt(trace Σ_p), the RMS 3-D error.

        Shapes as in :meth:`point_covariance`; per-axis values are
        ``point_covariance(...).diagonal(dim1=1, dim2=2).sqrt()``.
        """
        cov = self.point_covariance(q, tool, direction, repeatability)
        return torch.diagonal(cov, dim1=1, dim2=2).sum(-1).clamp(min=0).sqrt()

    # -------------------------------------------------------------- reports
    def summary(self) -> dict:
        """JSON-ready overview (standard deviations in mm / deg)."""
        return {
            "parameters": len(self.names),
            "pinned": len(self.pinned),
            "rank": self.rank,
            "undetermined": [str(c) for c in self.undetermined],
            "condition_number": self.condition_number,
            "correlated_pairs": [(p.first, p.second, round(p.correlation, 4)) for p in self.correlated],
            "chi2_dof": self.chi2_dof,
            "max_std_mm": float(units.m_to_mm(self._std_file(rot=False).max())) if (~self._rot()).any() else None,
            "max_std_deg": float(units.rad_to_deg(self._std_file(rot=True).max())) if self._rot().any() else None,
        }

    def _rot(self) -> torch.Tensor:
        return self.layout.is_rotation() if self.layout is not None else torch.zeros(len(self.names), dtype=torch.bool)

    def _std_file(self, rot: bool) -> torch.Tensor:
        m = self._rot() == rot
        return self.std.cpu()[m]

    def table(self) -> list[dict]:
        """One row per free parameter: name, value, std (mm or deg), unit, largest |correlation| and its partner."""
        rot = self._rot().tolist()
        corr = self.correlation.detach().cpu().clone()
        corr.fill_diagonal_(0.0)
        rows = []
        x, s = self.x.detach().cpu(), self.std.detach().cpu()
        for i, name in enumerate(self.names):
            conv = units.rad_to_deg if rot[i] else units.m_to_mm
            j = int(corr[i].abs().argmax()) if len(self.names) > 1 else i
            rows.append({
                "name": name,
                "value": float(conv(float(x[i]))),
                "std": float(conv(float(s[i]))),
                "unit": "deg" if rot[i] else "mm",
                "max_abs_corr": float(corr[i, j].abs()) if j != i else 0.0,
                "corr_with": self.names[j] if j != i else "",
            })
        return rows


# --------------------------------------------------------------------- core
def reduced_jacobian(A: torch.Tensor, C: torch.Tensor, w_v: torch.Tensor, f: torch.Tensor | None = None):
    """Whitened Jacobian (and residual) with each row's joint errors marginalized.

    A: (R, d, P) whitened parameter Jacobian; C: (R, d, n) whitened joint-error
    Jacobian; w_v: (R, n) joint-error precisions; f: optional (R, d) whitened
    residual at v = 0 (d = 3 for position targets, any d for other instruments).
    -> (R, d, P) A~ (and (R, d) f~ = L_r^-1 f_r when f is given) with A~_r = L_r^-1 A_r, L_r L_r^T = I + C_r W_v,r^-1 C_r^T, so that
    A~^T A~ equals the Schur complement H_bb - H_bv H_vv^-1 H_vb of :mod:`torchcal.identify.lm`.
    """
    eye = torch.eye(A.shape[1], dtype=A.dtype, device=A.device)
    Sigma = eye + (C / w_v[:, None, :]) @ C.transpose(1, 2)
    # d x d per row: an explicit inverse of the factor and one batched product beat R triangular solves
    Linv = torch.linalg.inv(torch.linalg.cholesky(Sigma))
    At = Linv @ A
    if f is None:
        return At
    return At, (Linv @ f[..., None])[..., 0]


def pin_entries(problem: CalibrationProblem, names) -> list[str]:
    """Hold the named entries (a fit's ``FitResult.pinned``) out of ``problem``'s layout; its prior follows
    (:meth:`CalibrationProblem.set_layout`). Raises ValueError naming any that is not a free entry."""
    names = list(names)
    have = problem.layout.names()
    missing = [n for n in names if n not in have]
    if missing:
        raise ValueError(f"identifiability: pinned parameters {missing} are not free parameters of the model")
    drop = torch.tensor([n in set(names) for n in have], dtype=torch.bool)
    problem.set_layout(problem.layout.without(drop))
    return names


def identifiability(
    model,
    data: Measurements,
    noise: NoiseModel | None = None,
    prior: Prior | None = Prior(),
    fixed=(),
    gauge: bool = True,
    pinned=None,
    v: torch.Tensor | None = None,
    rtol: float = UNDETERMINED_RTOL,
    corr_threshold: float = CORRELATION_THRESHOLD,
    top: int = 6,
) -> Identifiability:
    """Identifiability and Laplace covariance of ``model``'s free parameters on ``data``.

    Arguments as for :func:`torchcal.identify.fit`, at the model's current
    (fitted) values. pinned: names held fixed, e.g. ``FitResult.pinned`` (then
    ``gauge`` is ignored); else gauge=True pins the exactly redundant
    parameters like fit() does and gauge=False leaves every entry free.
    v: (R, n) joint errors to linearize at (``FitResult.v``), default zero.
    rtol: relative singular value below which a combination is undetermined;
    corr_threshold: |correlation| reported as a pair; top: components listed
    per undetermined combination. The model's values are left unchanged.
    
    Example:
        >>> import torch, torchcal
        >>> robot = torchcal.load_robot("fanuc_lrmate200i")
        >>> tools = torch.tensor([[0.033, 0.058, 0.161], [0.057, -0.034, 0.161], [-0.034, -0.057, 0.161]], dtype=torch.float64)
        >>> truth = torchcal.TruthRobot.fanuc_paper2(robot, tools, 0)
        >>> data = torchcal.simulate(truth, torchcal.sim.quasi_random_commands(robot.joint_map.limits, 30, 0), [0, 1, 2], None, 0)
        >>> model = torchcal.RobotModel(robot, tools, orders=0)
        >>> ia = identifiability(model, data)  # the robot's repeatability; gauge pinned as fit() does
        >>> ia.rank == len(ia.names)
        True
    """
    from ..identify.fit import resolve_noise

    noise = resolve_noise(model, noise)  # the robot's repeatability unless given
    problem = CalibrationProblem(model, data, noise, prior, fixed)
    if pinned is not None:
        pinned = pin_entries(problem, pinned)
    elif gauge:
        pinned = fix_gauge(problem)
    else:
        pinned = []
    layout = problem.layout
    x = layout.get().to(model.device)  # the current values: linearize writes them back unchanged
    v = problem.v_zero() if v is None else torch.as_tensor(v).to(problem.data.q)
    if v.shape != problem.data.q.shape:
        raise ValueError(f"identifiability: v has shape {tuple(v.shape)}, the data need {tuple(problem.data.q.shape)}")
    f, A, C = problem.linearize(x, v)
    prior_precision, prior_mean = problem.prior_precision, problem.prior_mean  # set_layout re-indexed them
    Ared3, fred = reduced_jacobian(A, C, problem.w_v, f - (C @ v[..., None])[..., 0])
    Ared = Ared3.reshape(-1, layout.size)
    dx = x - prior_mean
    cost = float((fred * fred).sum() + (prior_precision * dx * dx).sum())
    P = layout.size
    names = layout.names()

    # Ared = Q R with orthonormal Q: R (P, P) has Ared's singular values and right vectors, and so has every
    # matrix below with Ared replaced by R (the prior rows, the column scaling act on the right); one QR of the
    # tall matrix instead of three SVDs of it
    Rq = torch.linalg.qr(Ared, mode="r")[1] if Ared.shape[0] > P else Ared
    sv = torch.linalg.svdvals(Rq)
    prior_rows = torch.diag(prior_precision.sqrt())
    _, sp, Vh = torch.linalg.svd(torch.cat([Rq, prior_rows]), full_matrices=False)
    inv = torch.where(sp > sp[0] * 1e-15, 1.0 / sp.clamp(min=1e-300) ** 2, torch.zeros_like(sp))
    cov = (Vh.T * inv) @ Vh
    std = torch.diagonal(cov).clamp(min=0).sqrt()
    corr = cov / (std[:, None] * std[None, :]).clamp(min=1e-300)

    # undetermined combinations: equilibrated (unit-invariant) data-only Jacobian
    scale = Ared.norm(dim=0)
    _, se, Vhe = torch.linalg.svd(Rq / scale.clamp(min=1e-300), full_matrices=False)
    rel = se / se[0] if float(se[0]) > 0 else se
    combos = []
    for k in reversed((rel < rtol).nonzero()[:, 0].tolist()):  # least determined first
        u = Vhe[k] * (1.0 if float(Vhe[k][Vhe[k].abs().argmax()]) > 0 else -1.0)
        dirn = u / scale.clamp(min=1e-300)
        vec = u.cpu()
        idx = vec.abs().argsort(descending=True)[:top].tolist()
        combos.append(Combination(float(rel[k]), [(names[i], float(vec[i])) for i in idx if abs(float(vec[i])) > 1e-3],
                                  dirn / dirn.abs().max()))

    pairs = []
    c = corr.detach().cpu().triu(1)
    for i, j in (c.abs() > corr_threshold).nonzero().tolist():
        pairs.append(CorrelatedPair(names[i], names[j], float(c[i, j])))
    pairs.sort(key=lambda p: -abs(p.correlation))

    dof = max(3 * problem.rows - P, 1)
    return Identifiability(
        names=names, x=x.detach().clone(), singular_values=sv, singular_values_prior=sp,
        relative_singular_values=rel, covariance=cov, std=std, correlation=corr,
        undetermined=combos, correlated=pairs, pinned=list(pinned), chi2_dof=cost / dof,
        rtol=rtol, corr_threshold=corr_threshold, model=model, layout=layout,
        joint_variance=torch.stack([noise.joint_var_fwd, noise.joint_var_bwd]).to(torch.float64),
    )


# --------------------------------------------------------------------- sweeps
def joint_sweeps(limits: torch.Tensor, home: torch.Tensor, steps: int = 61) -> torch.Tensor:
    """Commands sweeping one joint at a time over its range from a home pose.

    limits: (n, 2) controller range (SI); home: (n,) -> (n, steps, n): block j
    moves joint j from its lower to its upper limit, the others stay at home.
    """
    n = limits.shape[0]
    t = torch.linspace(0.0, 1.0, steps, dtype=limits.dtype, device=limits.device)
    values = limits[:, :1] + t[None, :] * (limits[:, 1:] - limits[:, :1])  # (n, steps)
    q = home.to(limits).expand(n, steps, n).clone()
    idx = torch.arange(n, device=limits.device)
    q[idx, :, idx] = values
    return q


def position_std_sweeps(ident: Identifiability, home=None, tool: int = 0, steps: int = 61, repeatability: bool = False):
    """Predicted position std along one-joint sweeps, batched in one call.

    home: (n,) controller pose (SI), default the middle of the range;
    -> q: (n, steps, n) commands and std: (n, steps) metres.
    """
    limits = ident.model.command_limits
    home = limits.mean(1) if home is None else torch.as_tensor(home).to(limits)
    q = joint_sweeps(limits, home, steps)
    n = limits.shape[0]
    std = ident.point_std(q.reshape(n * steps, n), torch.full((n * steps,), tool, dtype=torch.long), None, repeatability)
    return q, std.reshape(n, steps)


def plot_position_std(ident: Identifiability, path=None, home=None, tool: int = 0, steps: int = 61,
                      data: Measurements | None = None, random_poses: int = 0, seed: int = 0, repeatability: bool = False):
    """Figure: predicted position std (mm) over each joint's range.

    Solid line: one joint swept from ``home`` (default mid-range) with the
    others fixed. With random_poses > 0, also the median and 90 % quantile of
    the std over that many seeded random poses binned by each joint's value.
    With ``data``, the measured range of each joint is shaded. Writes a PNG
    when ``path`` is given; returns the matplotlib figure.
    """
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    limits = ident.model.command_limits
    n = limits.shape[0]
    q, std = position_std_sweeps(ident, home, tool, steps, repeatability)
    prismatic = ident.model.robot.joint_map.prismatic
    names = ident.model.robot.joint_map.names
    cols = min(n, 3)
    rows = (n + cols - 1) // cols
    fig, axes = plt.subplots(rows, cols, figsize=(4.2 * cols, 3.0 * rows), squeeze=False)
    rand = None
    if random_poses > 0:
        g = torch.Generator().manual_seed(seed)
        lo, hi = limits[:, 0].cpu(), limits[:, 1].cpu()
        qr = (lo + torch.rand(random_poses, n, generator=g, dtype=torch.float64) * (hi - lo)).to(limits)
        sr = ident.point_std(qr, torch.full((random_poses,), tool, dtype=torch.long))
        rand = (qr.cpu(), units.m_to_mm(sr.cpu()))
    for j in range(n):
        ax = axes[j // cols][j % cols]
        conv = units.m_to_mm if bool(prismatic[j]) else units.rad_to_deg
        xs = conv(q[j, :, j].cpu()).numpy()
        ax.plot(xs, units.m_to_mm(std[j].cpu()).numpy(), color="#1f77b4", label="sweep from home")
        if rand is not None:
            qr, sr = rand
            edges = torch.linspace(float(limits[j, 0]), float(limits[j, 1]), 13)
            b = torch.bucketize(qr[:, j].contiguous(), edges[1:-1])
            centres, med, p90 = [], [], []
            for k in range(12):  # 12 bins of one joint: a loop over bins, not poses
                s = sr[b == k]
                if s.numel():
                    centres.append(float(conv(0.5 * (edges[k] + edges[k + 1]))))
                    med.append(float(s.median()))
                    p90.append(float(torch.quantile(s, 0.9)))
            ax.plot(centres, med, "o-", color="#2ca02c", ms=3, label="random poses, median")
            ax.plot(centres, p90, "o--", color="#2ca02c", ms=3, alpha=0.6, label="random poses, 90 %")
        if data is not None:
            dq = data.q[:, j].cpu()
            ax.axvspan(float(conv(dq.min())), float(conv(dq.max())), color="#b0b0b0", alpha=0.25, label="measured range")
        ax.set_xlabel(f"{names[j]} ({'mm' if bool(prismatic[j]) else 'deg'})")
        ax.set_ylabel("predicted position std (mm)")
        ax.set_ylim(bottom=0)
        ax.grid(alpha=0.3)
    for k in range(n, rows * cols):
        axes[k // cols][k % cols].axis("off")
    axes[0][0].legend(fontsize=7)
    fig.tight_layout()
    if path is not None:
        from ..io.atomic import atomic_path

        with atomic_path(path) as tmp:
            fig.savefig(tmp, dpi=120)
    return fig
