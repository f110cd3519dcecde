"""The fleet's Gauss-Newton step in the Khatri-Rao structure of a robot model's Jacobian.

Why one module: the factored linearization, the normal matrix's contraction and the step are one layout
(the pair order, the gather into layout order, the pose slots) read by both the torch form and its compiled
twin (:mod:`.fleet_kernel`); split, each half would restate it.

Why this module exists. Profiled (12-20 FANUC units, order 6 + backlash,
250 x 3 rows, 285 parameters), the dense batched solve spent its time on two
things of the same size: forming the parameter Jacobian A (750 x 3 x 285 per
unit: the einsum of the coefficient columns, the concatenation into the
layout, the whitening and the row and gauge masks, each a pass over 5 MB per
unit; 60-70 ms a unit under vmap, more than a single fit's 37 ms) and the
Schur complement S = sum_r A_r^T M_r A_r (0.37 GFLOP per unit and iteration
as a dense (P x Rd) @ (Rd x P) product, plus its (R, d, d) @ (R, d, P)
temporaries). Batching removed no arithmetic, so 100 units cost 116 fits.

A :class:`~torchcal.models.robot.RobotModel`'s point Jacobian has structure.
The column of Chebyshev coefficient k of error term t of joint i is

    d p_r / d c_itk = J_r,i,t T_k(u_r,i)

the column J_r,i,t (d,) of the twist Jacobian of the error transform E_i
times the basis value of the joint's error variable (Paper II (34)-(45));
the backlash column of order k is s_r,i J_r,i,2 T_k(u_r,i). So a row is a
d x Q matrix E_r (Q = 7 n twist columns, 6 base and 3 T tool columns: 57 for
the FANUC with three tools) and n x K basis values Phi_r, not d x P numbers,
and the Schur complement is a sum over *poses* (the rows of one command
share their basis values; the tools of a pose are summed first):

    S[(i,a,k), (j,b,l)] = sum_p G_p[(i,a), (j,b)] Phi_p,i,k Phi_p,j,l,   G_p = sum_{r in p} E_r^T M_r E_r

one (7x7 x poses) @ (poses x 7x7) product per pair of joints i <= j (~25
MFLOP instead of 370 for the FANUC; when every unit has the same poses the
pair products of the basis values are shared and the units go through one
product per pair). The gradient, the diagonal for Marquardt's scaling, the
step's predicted residual A db and the exact products S x are formed per row
with each row's own basis values. S takes each pose's basis values at its
command; a row's joint errors v (~1e-5-1e-4 rad) move its error variable off
the command, so S differs from the Gauss-Newton matrix by that, and a few
conjugate-gradient iterations on the exact product, preconditioned by S,
make the step the Gauss-Newton step (:func:`structured_steps`): each unit
follows the separate fit's path to its optimum (the fixed point is where
the exact gradient vanishes; tests hold the step to the dense one, and S at
v = 0 to the dense J^T M J to 1e-10).

The per-row work (the linearization, each row's joint-error elimination, the
per-pose Gram matrices, the exact products) is compiled on the CPU
(:mod:`.fleet_kernel`); this module holds the torch form of the same
arithmetic (any device) and the parts that are batched products anyway.

Supported: a RobotModel without gravity compliance and fine joint tables,
point targets with an isotropic sigma, every free group one of
:data:`GROUPS`. Anything else takes the dense path of
:mod:`torchcal.identify.batched`.
"""

from __future__ import annotations

import hashlib

import numpy as np
import torch

from ..core import blas, hugepages
from ..kinematics.fk import chain_frames
from ..kinematics.transforms import small_matmul, twist_to_transform
from ..models.jacobian import chebyshev_design, joint_axis_jacobian, twist_jacobian
from .schur import Resolve
from .workspace import Workspace

GROUPS = ("joint_errors.coef", "joint_errors.backlash", "base.twist", "tools.delta")


class RobotStructure:
    """Where each free entry of a RobotModel's layout sits in the factored Jacobian.

    The *extended* parameter space has n x A x K structured columns (joint i,
    twist column a: the six error terms, then the backlash column when the
    model has one, basis order k < K = max(coef orders, backlash orders) + 1)
    followed by the Nd = 6 + 3 T base and tool columns. ``index`` (P,): the
    extended column of each layout column; ``rows`` / ``cols`` give the E
    column (i, a) or dense column of every extended one.
    """

    def __init__(self, model, layout):
        je = model.joint_errors
        n, _, Kc = je.coef.shape
        Kb = je.backlash.shape[-1] if je.has_backlash else 0
        self.n, self.Kc, self.Kb, self.K = n, Kc, Kb, max(Kc, Kb)
        self.A = 7 if Kb > 0 else 6
        self.T = model.tools.count
        self.Nd = 6 + 3 * self.T
        self.ns = n * self.A * self.K  # structured extended columns
        self.ne = n * self.A  # structured columns of E
        self.size = self.ns + self.Nd
        idx = []
        for (name, p, _), fi in zip(layout.entries, layout._flat_index()):
            flat = torch.arange(p.numel()) if fi is None else fi.cpu()
            if name == "joint_errors.coef":
                i, t, k = flat // (6 * Kc), (flat // Kc) % 6, flat % Kc
                idx.append((i * self.A + t) * self.K + k)
            elif name == "joint_errors.backlash":
                Kfull = p.shape[-1]
                i, k = flat // Kfull, flat % Kfull
                idx.append((i * self.A + 6) * self.K + k)
            elif name == "base.twist":
                idx.append(self.ns + flat)
            elif name == "tools.delta":
                idx.append(self.ns + 6 + flat)
            else:
                raise ValueError(f"no factored Jacobian for parameter group '{name}'")
        self.index = torch.cat(idx).to(model.device) if idx else torch.zeros(0, dtype=torch.long)
        self.gather = self._gather_index(self.index.cpu()).to(model.device)

    def _gather_index(self, index: torch.Tensor) -> torch.Tensor:
        """(P * P,) where each entry of the layout's normal matrix sits in the flat concatenation that
        :func:`contract` forms: the pair blocks (npair, A, A, K, K) of joints i <= j, the structured x dense
        block (n, A, Nd, K), the dense block (Nd, Nd)."""
        n, A, K, Nd = self.n, self.A, self.K, self.Nd
        pi, pj = torch.triu_indices(n, n)
        pair = torch.full((n, n), -1, dtype=torch.long)
        pair[pi, pj] = torch.arange(pi.numel())
        nblk = pi.numel() * A * A * K * K
        nsd = n * A * Nd * K
        x1, x2 = index[:, None].expand(-1, index.numel()), index[None, :].expand(index.numel(), -1)
        s1, s2 = x1 < self.ns, x2 < self.ns
        i1, a1, k1 = (x1 // (A * K)).clamp(max=n - 1), (x1 // K) % A, x1 % K
        i2, a2, k2 = (x2 // (A * K)).clamp(max=n - 1), (x2 // K) % A, x2 % K
        c1, c2 = (x1 - self.ns).clamp(min=0), (x2 - self.ns).clamp(min=0)
        # both structured: the block of (min, max) joints, transposed when i1 > i2; within a joint's own block
        # the same entry for (x1, x2) and (x2, x1), so that S is exactly symmetric
        lo = (i1 < i2) | ((i1 == i2) & (x1 <= x2))
        pr = pair[torch.minimum(i1, i2), torch.maximum(i1, i2)].clamp(min=0)
        aa, bb = torch.where(lo, a1, a2), torch.where(lo, a2, a1)
        kk, ll = torch.where(lo, k1, k2), torch.where(lo, k2, k1)
        ss = (((pr * A + aa) * A + bb) * K + kk) * K + ll
        sd = nblk + ((i1 * A + a1) * Nd + c2) * K + k1
        ds = nblk + ((i2 * A + a2) * Nd + c1) * K + k2
        dd = nblk + nsd + torch.minimum(c1, c2) * Nd + torch.maximum(c1, c2)
        out = torch.where(s1 & s2, ss, torch.where(s1, sd, torch.where(s2, ds, dd)))
        return out.reshape(-1)

    @staticmethod
    def supports(model, instrument, layout) -> bool:
        """Whether the factored path applies: a RobotModel without compliance and fine tables, isotropic point
        targets, and only the groups of :data:`GROUPS` free."""
        from ..error_models.joint import backlash_on_eps_z
        from ..measure import PointTargets
        from ..models.robot import RobotModel

        if not isinstance(model, RobotModel) or model.compliance is not None or model.fine is not None:
            return False
        if model.extended():  # a subclass's own terms: this path's closed-form columns would leave them out
            return False
        if model.backlash_coupling() is not None:  # its backlash columns are eps_z's (Paper II (13) about +z)
            return False
        je = model.joint_errors
        if je.has_backlash and not backlash_on_eps_z(je.screw, je.backlash_orders >= 0):
            return False  # backlash about another axis (a ROS-style URDF, a rail): the generic path has it
        if not isinstance(instrument, PointTargets) or getattr(instrument.weight, "sigma", None) is None:
            return False
        if type(instrument).residual is not PointTargets.residual:
            return False
        return all(name in GROUPS for name, _, _ in layout.entries)


def pose_groups(units_q: list, units_dir: list) -> list:
    """Per unit (inv (R_m,) its rows' pose, order (R_m,) its rows pose by pose (stable), counts (Pp_m,) rows a
    pose): rows with the same command and approach directions form one pose (their basis values are the same up
    to their joint errors), poses in lexicographic order of (command, directions).

    units_q: M tensors (R_m, n); units_dir: M tensors (R_m, n) or None.
    """
    groups, seen = [], {}
    for q, s in zip(units_q, units_dir):
        key = (q if s is None else torch.cat([q, s], 1)).detach().cpu().numpy()
        # a unit measured with an earlier unit's program shares its grouping
        digest = (key.shape, hashlib.sha1(np.ascontiguousarray(key).tobytes(), usedforsecurity=False).digest())
        same = seen.get(digest)
        if same is None:
            same = seen[digest] = tuple(torch.from_numpy(t).to(q.device) for t in _group_rows(key))
        groups.append(same)
    return groups


def _group_rows(key: np.ndarray):
    """(inv, order, counts) of the equal rows of key (R, c): a lexicographic sort of the rows (numpy's lexsort,
    a fifth of torch.unique(dim=0)'s 1.5 ms for a FANUC unit's 750 rows), stable, so each pose's rows keep
    their order."""
    R = key.shape[0]
    order = np.lexsort(key.T[::-1])  # the first column the primary key
    ks = key[order]
    new = np.ones(R, dtype=bool)
    new[1:] = (ks[1:] != ks[:-1]).any(1)
    pose = np.cumsum(new) - 1
    inv = np.empty(R, dtype=np.int64)
    inv[order] = pose
    return inv, order.astype(np.int64), np.diff(np.flatnonzero(np.append(new, True))).astype(np.int64)


def slots_of(groups: list, R: int) -> torch.Tensor:
    """(M, Pp, T) row of each (pose, slot) of every unit, R where empty, from the units' :func:`pose_groups`."""
    Pp = max(int(c.numel()) for _, _, c in groups)
    T = max(int(c.max()) for _, _, c in groups)
    dev = groups[0][0].device
    out = torch.full((len(groups), Pp, T), R, dtype=torch.long, device=dev)
    for m, (inv, order, counts) in enumerate(groups):
        starts = torch.cumsum(counts, 0) - counts
        slot = torch.arange(order.numel(), device=dev) - starts[inv[order]]
        out[m, inv[order], slot] = order
    return out


def regrouped(groups: list) -> list:
    """:func:`pose_groups` of units whose rows were put pose by pose (``u.subset(order)``): the same poses,
    each row's pose in the new order, rows already in order."""
    return [(inv[order], torch.arange(order.numel(), device=order.device), counts) for inv, order, counts in groups]


@torch.no_grad()
def _factored_forward(model, st: RobotStructure, params: dict, q, tool, direction, v):
    """What both the residual and the factored Jacobians need: the chain walked once for m units' rows."""
    je = model.joint_errors
    m, R, n = q.shape
    B = m * R
    K, Kc, Kb = st.K, st.Kc, st.Kb
    qv = (q + v).reshape(B, n)
    theta = model.joint_variables(qv)
    u = model.error_variables(qv)
    basis, dbasis = chebyshev_design(je.normalized(u), K, 2.0 / (je.ranges[:, 1] - je.ranges[:, 0]))
    b4, d4 = basis.view(m, R, n, K), dbasis.view(m, R, n, K)
    coef = params["joint_errors.coef"] * je.mask
    e = torch.einsum("mrnk,mntk->mrnt", b4[..., :Kc], coef)
    de = torch.einsum("mrnk,mntk->mrnt", d4[..., :Kc], coef)
    s = None
    if Kb > 0 and direction is not None:
        s = direction.to(u)
        bl = (params["joint_errors.backlash"] * je.backlash_mask)[:, None]  # (m, 1, n, Kb)
        pad = torch.nn.functional.pad
        e = e + pad(((b4[..., :Kb] * bl).sum(-1) * s)[..., None], (2, 3))
        de = de + pad(((d4[..., :Kb] * bl).sum(-1) * s)[..., None], (2, 3))
        s = s.reshape(B, n)
    e, de = e.reshape(B, n, 6), de.reshape(B, n, 6)
    twist = params["base.twist"]  # (m, 6)
    T0 = (model.base.nominal @ twist_to_transform(twist))[:, None].expand(m, R, 4, 4).reshape(B, 4, 4)
    jR, jp, F = chain_frames(model.origins, model.axes, model.prismatic, theta, twist_to_transform(e), model.tip, T0)
    pts = model.tools.nominal + params["tools.delta"]  # (m, T, 3)
    p_t = pts[torch.arange(m, device=q.device)[:, None], tool].reshape(B, 3)
    p = small_matmul(F[:, :3, :3], p_t[..., None])[..., 0] + F[:, :3, 3]
    return dict(m=m, R=R, n=n, B=B, b4=b4, e=e, de=de, s=s, twist=twist, T0=T0, jR=jR, jp=jp, F=F, p=p)


def factored_residual(model, st: RobotStructure, params: dict, q, tool, direction, v, obs) -> torch.Tensor:
    """The raw residual (m, R, 3) (model - observed) alone, as :func:`factored_linearization` gives it: a trial
    point's residual where no kernel skips the Jacobians (a GPU's geodesic acceleration)."""
    f = _factored_forward(model, st, params, q, tool, direction, v)
    return f["p"].view(f["m"], f["R"], 3) - obs


def factored_linearization(model, st: RobotStructure, params: dict, q, tool, direction, v, obs):
    """Residual and factored Jacobians of m units at once (the closed form of ``RobotModel.point_jacobians``).

    params: {name: (m, *shape)} every unit's parameters; q, v: (m, R, n); tool: (m, R) long; direction:
    (m, R, n) or None; obs: (m, R, 3). -> raw residual (m, R, 3) (model - observed), Jv (m, R, 3, n),
    E (m, R, 3, ne + Nd) and Phi (m, R, n, K): the parameter Jacobian's column (i, a, k) is
    E[..., i*A + a] * Phi[..., i, k], its base and tool columns are E[..., ne:].
    """
    f = _factored_forward(model, st, params, q, tool, direction, v)
    m, R, n, B, e, de, s, p = f["m"], f["R"], f["n"], f["B"], f["e"], f["de"], f["s"], f["p"]
    jR, jp, F, T0, twist = f["jR"], f["jp"], f["F"], f["T0"], f["twist"]
    Je = twist_jacobian(jR, jp, e, p[:, None, :])[:, :, :3, :]  # (B, n, 3, 6)
    Jax = joint_axis_jacobian(jR, jp, model.axes, model.prismatic, p)[:, :3, :]
    slope = small_matmul(Je, de[..., None])[..., 0].transpose(1, 2)  # (B, 3, n)
    Jv = Jax @ model.coupling + slope @ model.error_coupling  # (B, 3, n)
    cols = [Je.permute(0, 2, 1, 3)]  # (B, 3, n, 6)
    if st.A == 7:
        back = Je[..., 2] * s[..., None] if s is not None else torch.zeros_like(Je[..., 2])
        cols.append(back.transpose(1, 2)[..., None])
    Es = torch.cat(cols, -1).reshape(B, 3, st.ne)
    Jb = twist_jacobian(T0[:, :3, :3], T0[:, :3, 3], twist[:, None].expand(m, R, 6).reshape(B, 6), p)[:, :3, :]
    onehot = torch.nn.functional.one_hot(tool.reshape(B), st.T).to(F)
    Jt = (F[:, :3, None, :3] * onehot[:, None, :, None]).reshape(B, 3, 3 * st.T)
    E = torch.cat([Es, Jb, Jt], -1)
    return ((p.view(m, R, 3) - obs), Jv.view(m, R, 3, n), E.view(m, R, 3, -1), f["b4"])


def to_extended(h: torch.Tensor, Phi: torch.Tensor, st: RobotStructure) -> torch.Tensor:
    """sum_r of a per-row vector h (m, R, Q) over E's columns, mapped to the extended parameters (m, size):
    entry (i, a, k) is sum_r h[r, i*A + a] Phi[r, i, k], a dense entry the plain sum."""
    m, R = h.shape[:2]
    hs = h[..., :st.ne].reshape(m, R, st.n, st.A)
    struct = torch.einsum("mrna,mrnk->mnak", hs, Phi).reshape(m, st.ns)
    return torch.cat([struct, h[..., st.ne:].sum(1)], 1)


def apply_extended(E: torch.Tensor, Phi: torch.Tensor, dbx: torch.Tensor, st: RobotStructure) -> torch.Tensor:
    """A db per row (m, R, d) from the factored Jacobian and an extended step dbx (m, size)."""
    m, R = E.shape[:2]
    w = torch.einsum("mrnk,mnak->mrna", Phi, dbx[:, :st.ns].reshape(m, st.n, st.A, st.K)).reshape(m, R, st.ne)
    wq = torch.cat([w, dbx[:, None, st.ns:].expand(m, R, st.Nd)], -1)
    return (E * wq[:, :, None, :]).sum(-1)


def pose_gram(E: torch.Tensor, ME: torch.Tensor, slots: torch.Tensor) -> torch.Tensor:
    """G_p = sum_{r in pose p} E_r^T ME_r: (m, R, d, Q) twice -> (m, Pp, Q, Q)."""
    m, R, d, Q = E.shape
    ar = torch.arange(m, device=E.device)[:, None, None]
    Ez = torch.cat([E, torch.zeros_like(E[:, :1])], 1)[ar, slots]  # (m, Pp, T, d, Q)
    Mz = torch.cat([ME, torch.zeros_like(ME[:, :1])], 1)[ar, slots]
    Pp, T = slots.shape[1:]
    return Ez.reshape(m, Pp, T * d, Q).transpose(-1, -2) @ Mz.reshape(m, Pp, T * d, Q)


def gram_parts(E: torch.Tensor, ME: torch.Tensor, slots: torch.Tensor, st: RobotStructure):
    """The per-pose Gram matrices G_p = sum_{r in p} E_r^T ME_r in the contraction's layout:
    (Gs (npair, m, A, A, Pp) for the joint pairs (pi, pj), i <= j, Gsd (m, n, A, Nd, Pp), Gdd (m, Nd, Nd)
    summed over the poses, pi, pj). Compiled (:mod:`.fleet_kernel`) on the CPU, else batched products."""
    from . import fleet_kernel

    if fleet_kernel.available(E.device):
        slots = slots.cpu()
        return fleet_kernel.gram_fused(fleet_kernel.pose_last(E, slots), fleet_kernel.pose_last(ME, slots), st.n, st.A)
    m, Pp = slots.shape[:2]
    n, A, ne = st.n, st.A, st.ne
    G = pose_gram(E, ME, slots)
    pi, pj = torch.triu_indices(n, n, device=G.device)
    Gs = G[..., :ne, :ne].reshape(m, Pp, n, A, n, A).permute(2, 4, 0, 3, 5, 1)[pi, pj]
    Gsd = G[..., :ne, ne:].reshape(m, Pp, n, A, st.Nd).permute(0, 2, 3, 4, 1)
    return Gs, Gsd, G[..., ne:, ne:].sum(1), pi, pj


def pair_basis(Phi_p: torch.Tensor, n: int) -> torch.Tensor:
    """The products Phi_p,i,k Phi_p,j,l of the joint pairs i <= j from poses' basis values: one set (Pp, n, K)
    -> (npair, Pp, K K), what every unit measured with the same program shares; each unit's own (m, Pp, n, K)
    -> (npair, m, Pp, K K)."""
    pi, pj = torch.triu_indices(n, n).tolist()
    Pt = Phi_p.movedim(-2, 0)  # (n, [m,] Pp, K)
    K = Pt.shape[-1]
    # a pair at a time into one buffer on huge pages (a fleet's own programs: 2 MB a FANUC unit): half the time
    # of the gathered joints' broadcast product
    out = hugepages.empty((len(pi), *Pt.shape[1:-1], K, K), Phi_p)
    for p, (i, j) in enumerate(zip(pi, pj)):
        torch.mul(Pt[i, ..., :, None], Pt[j, ..., None, :], out=out[p])
    return out.flatten(-2)


def contract(parts, Phi_p: torch.Tensor, st: RobotStructure, pp: torch.Tensor | None = None,
             ws: Workspace | None = None) -> torch.Tensor:
    """The normal matrix (m, P, P) in layout order from :func:`gram_parts` and the poses' basis values
    Phi_p (m, Pp, n, K): S[(i,a,k),(j,b,l)] = sum_p G_p[(i,a),(j,b)] Phi_p,i,k Phi_p,j,l (pairs i <= j, one
    batched product each), S[(i,a,k), c] = sum_p G_p[(i,a), c] Phi_p,i,k, S[c, c'] = sum_p G_p[c, c'].
    pp: :func:`pair_basis`, (npair, Pp, K K) where every unit has the same poses (one product per pair for all
    the units), or each unit's own (npair, m, Pp, K K); None: formed here from Phi_p.
    ws: where the large temporaries and the result come from (:class:`Workspace`; None: allocated)."""
    ws = Workspace() if ws is None else ws
    Gs, Gsd, Gdd, pi, pj = parts
    npair, m = Gs.shape[:2]
    Pp = Gs.shape[-1]
    n, A, K, Nd = st.n, st.A, st.K, st.Nd
    nb, nsd = npair * A * A * K * K, n * A * Nd * K
    flat = ws.take("flat", (m, nb + nsd + Nd * Nd), Gs)
    if pp is not None and pp.dim() == 3:
        # products with the poses' basis values on the left and the Gram blocks on the right, pose-major as the
        # compiled kernel writes them (read as they lie; 20-30 % faster than their transposed views on the left)
        blk = blas.bmm(pp.transpose(1, 2).contiguous(), Gs.permute(0, 4, 1, 2, 3).reshape(npair, Pp, m * A * A),
                       ws.take("blk", (npair, K * K, m * A * A), Gs))
        flat[:, :nb].view(m, npair, A * A, K * K).copy_(blk.view(npair, K * K, m, A * A).permute(2, 0, 3, 1))
        # the same poses: (n, K, Pp) @ (n, Pp, m A Nd) -> (m, n, A, Nd, K)
        sd = blas.bmm(Phi_p[0].permute(1, 2, 0).contiguous(), Gsd.permute(1, 4, 0, 2, 3).reshape(n, Pp, m * A * Nd),
                      ws.take("sd", (n, K, m * A * Nd), Gs))
        flat[:, nb:nb + nsd].view(m, n, A * Nd, K).copy_(sd.view(n, K, m, A * Nd).permute(2, 0, 3, 1))
    else:
        # each unit its own poses: a product per pair (per joint), batched over the units, reading the Gram
        # blocks where they lie and writing into the normal matrix's place (100 FANUCs each with its own
        # program, one stream: the contraction 1.45-1.5 s, against 2.0 s with the blocks copied into the units'
        # order and the pair products formed in every step)
        pp = pair_basis(Phi_p, n) if pp is None else pp
        fv = flat[:, :nb].view(m, npair, A * A, K * K)
        for p in range(npair):  # (m, A A, Pp) @ (m, Pp, K K)
            blas.bmm(Gs[p].reshape(m, A * A, Pp), pp[p], fv[:, p])
        fv = flat[:, nb:nb + nsd].view(m, n, A * Nd, K)
        for i in range(n):  # (m, A Nd, Pp) @ (m, Pp, K)
            blas.bmm(Gsd[:, i].reshape(m, A * Nd, Pp), Phi_p[:, :, i], fv[:, i])
    flat[:, nb + nsd:] = Gdd.reshape(m, -1)
    P = st.index.numel()
    from . import fleet_kernel

    if fleet_kernel.available(flat.device):  # torch's indexed gather: 5 ns an entry, a tenth of a ms a unit
        out = ws.take("S", (m, P, P), flat)
        with fleet_kernel.dynamic():
            fleet_kernel.gather_rows(flat.numpy(), st.gather.numpy(), out.view(m, -1).numpy())
        return out
    return flat[:, st.gather].view(m, P, P)


def structured_steps(lin, st: RobotStructure, slots, w_v, V, lam, dx, mu, keep, refine: int = 0,
                     tol: float = 1e-6, pp: torch.Tensor | None = None, ws: Workspace | None = None,
                     shared: bool = False, again: bool = False):
    """Damped Gauss-Newton steps of m units from factored linearizations (the factored
    :func:`~torchcal.identify.schur.schur_steps`).

    lin: (f (m, R, d), C (m, R, d, n), E (m, R, d, Q), Phi (m, R, n, K), Phi_p (m, Pp, n, K)), whitened, rows
    a unit does not fit zero; slots (m, Pp, T); w_v, V (m, R, n); lam (P,); dx (m, P); mu (m,); keep (m, P).
    pp: :func:`pair_basis` of the poses where every unit has the same ones; ws: the :class:`Workspace` of
    the compiled path's large temporaries (None: allocated). refine, tol: at most ``refine`` conjugate-gradient iterations on the exact product (each row its own
    basis values, one factored pass each), preconditioned by S (the poses' basis values), until the
    residual's S^-1 norm is below tol of the right-hand side's: the rows of a pose differ in their joint
    errors (~1e-5 of the range), S by that, and one or two iterations make the step the exact one.
    The fleet takes refine=0, S's step: Levenberg-Marquardt accepts a step by the exact cost and its
    gradient is exact, so the optimum is the same, and the near-exact step costs a few iterations
    (100 FANUCs: 771 unit iterations instead of 737) but no products (9.2 -> 6.4 s; every unit's
    validation residual unchanged to the printed digit, experiments/fleet/run.py).
    shared: every unit's damped normal matrix is the first unit's (the caller vouches: the same rows, joint
    errors, parameters, damping and kept entries, as at a one-program fleet's common start): it is formed and
    factored once, and the units differ only in their right-hand sides.
    again: also return a :class:`~torchcal.identify.schur.Resolve`, the damped system (S's) solved for another
    residual (geodesic acceleration): one pass over the rows with their projectors (the compiled
    :func:`~.fleet_kernel.gradient_rows`), one triangular solve.
    -> db (m, P), dv (m, R, n), predicted linearized residual (m, R, d) (, Resolve).
    The per-row work is compiled (:mod:`.fleet_kernel`) on the CPU, batched torch elsewhere.
    """
    from . import fleet_kernel

    rows = _RowsFused(lin, slots, w_v, V, mu, st, pp, ws, shared) if fleet_kernel.available(lin[0].device) else \
        _RowsTorch(lin, slots, w_v, V, mu, st, pp, shared)
    E = lin[2]
    m = E.shape[0]
    kf = keep.to(E)
    idx = st.index
    lam_m = lam * kf
    S = rows.S  # symmetric by construction (contract); (1, P, P) where shared
    ub, uj = (~keep[:S.shape[0]]).nonzero(as_tuple=True)  # entries a unit lacks or pins: unit diagonal, zero
    S[ub, uj, :] = 0.0  # right-hand side
    S[ub, :, uj] = 0.0
    diag_bb = rows.diag_x[:, idx] * kf + lam_m
    damp = lam_m + mu[:, None] * diag_bb + (1.0 - kf)
    S.diagonal(dim1=1, dim2=2).add_(damp[:S.shape[0]])
    rhs = -(rows.gx[:, idx] + lam_m * dx) * kf
    if shared:  # one factor, every unit's right-hand side a column of one solve
        Ls, info = torch.linalg.cholesky_ex(S)
        solve = lambda r: torch.cholesky_solve(r.T, Ls[0]).T  # noqa: E731
    elif isinstance(rows, _RowsFused):
        Ls, info = rows.ws.take("L", S.shape, S), torch.empty(m, dtype=torch.int64)
        with fleet_kernel.dynamic():
            fleet_kernel.cholesky_rows(S.numpy(), Ls.numpy(), info.numpy())

        def solve(r):
            out = torch.empty_like(r)
            with fleet_kernel.dynamic():
                fleet_kernel.cholesky_solve_rows(Ls.numpy(), r.contiguous().numpy(), out.numpy())
            return out
    else:
        Ls, info = torch.linalg.cholesky_ex(S)
        solve = lambda r: torch.cholesky_solve(r[..., None], Ls)[..., 0]  # noqa: E731
    if bool((info != 0).any()):  # not positive definite: the least-squares solution (S (1, P, P) where shared)
        solve = lambda r: torch.linalg.lstsq(S.expand(r.shape[0], -1, -1), r[..., None]).solution[..., 0]  # noqa: E731
    dbx = E.new_zeros(m, st.size)

    def exact(x):  # the damped normal matrix times x, every row with its own basis values
        dbx[:, idx] = x
        return rows.product(dbx)[:, idx] * kf + damp * x

    # S holds the poses' basis values: conjugate gradients on the exact product, S preconditioning
    db = solve(rhs)
    if refine <= 0:
        dbx[:, idx] = db
        dv, lin_res = rows.finish(dbx)
        if not again:
            return db, dv, lin_res

        def resolve(r):
            return solve(-rows.gradient(r)[:, idx] * kf)

        return db, dv, lin_res, Resolve(resolve, diag_bb.sqrt())
    if again:
        raise ValueError("structured_steps: again is for refine=0 (the fleet's steps)")
    r = rhs - exact(db)
    z = solve(r)
    d = z.clone()
    rz = (r * z).sum(1)
    scale = (rhs * db).sum(1).clamp(min=1e-300)
    for _ in range(refine):
        if not bool((rz > tol * tol * scale).any()):
            break
        q = exact(d)
        alpha = rz / (d * q).sum(1).clamp(min=1e-300)
        alpha = torch.where(rz > tol * tol * scale, alpha, torch.zeros_like(alpha))
        db = db + alpha[:, None] * d
        r = r - alpha[:, None] * q
        z = solve(r)
        rz_new = (r * z).sum(1)
        d = z + (rz_new / rz.clamp(min=1e-300))[:, None] * d
        rz = rz_new
    dbx[:, idx] = db
    dv, lin_res = rows.finish(dbx)
    return db, dv, lin_res


class _RowsTorch:
    """The per-row half of :func:`structured_steps` in batched torch ops: joint errors eliminated, the normal
    matrix S (m, P, P) in layout order, the extended gradient gx and diagonal diag_x (m, size)."""

    def __init__(self, lin, slots, w_v, V, mu, st, pp=None, shared: bool = False):
        f, C, E, Phi, Phi_p = lin
        m, R, d, Q = E.shape
        n = C.shape[-1]
        self.lin, self.st = lin, st
        Ct = C.transpose(-1, -2)
        H_vv = Ct @ C + torch.diag_embed(w_v)
        g_v = (Ct @ f[..., None])[..., 0] + w_v * V
        H_vv_d = H_vv + mu[:, None, None, None] * torch.diag_embed(torch.diagonal(H_vv, dim1=-2, dim2=-1))
        L = torch.linalg.cholesky(H_vv_d)
        eye_n = torch.eye(n, dtype=E.dtype, device=E.device).expand(m, R, n, n)
        self.Li = torch.linalg.solve_triangular(L, eye_n, upper=False)
        self.W = self.Li @ Ct  # (m, R, n, d)
        self.z = self.Li @ g_v[..., None]  # (m, R, n, 1)
        self.Mm = torch.eye(d, dtype=E.dtype, device=E.device) - self.W.transpose(-1, -2) @ self.W
        y = f - (self.W.transpose(-1, -2) @ self.z)[..., 0]  # the residual with the joint errors' response out
        self.gx = to_extended((E * y[..., None]).sum(2), Phi, st)
        self.diag_x = to_extended((E * E).sum(2), Phi * Phi, st)
        g = 1 if shared else m
        self.S = contract(gram_parts(E[:g], self.Mm[:g] @ E[:g], slots[:g], st), Phi_p[:g], st, pp)

    def gradient(self, r):
        """(m, size) the extended gradient of another whitened residual r (m, R, d), the joint errors' response
        out and their prior term zero: E^T M r per row, as gx is of f."""
        f, C, E, Phi, _ = self.lin
        Mr = (self.Mm @ r[..., None])[..., 0]
        return to_extended((E * Mr[..., None]).sum(2), Phi, self.st)

    def product(self, dbx):
        """(m, size) the extended A^T M A dbx, every row with its own basis values."""
        f, C, E, Phi, _ = self.lin
        MAdb = (self.Mm @ apply_extended(E, Phi, dbx, self.st)[..., None])[..., 0]
        return to_extended((E * MAdb[..., None]).sum(2), Phi, self.st)

    def finish(self, dbx):
        f, C, E, Phi, _ = self.lin
        Adb = apply_extended(E, Phi, dbx, self.st)
        dv = -(self.Li.transpose(-1, -2) @ (self.z + self.W @ Adb[..., None]))[..., 0]
        return dv, f + Adb + (C @ dv[..., None])[..., 0]


class _RowsFused(_RowsTorch):
    """:class:`_RowsTorch` by the compiled kernels of :mod:`.fleet_kernel` (CPU)."""

    def __init__(self, lin, slots, w_v, V, mu, st, pp=None, ws: Workspace | None = None, shared: bool = False):
        from .fleet_kernel import dynamic, pose_blocks, schur_rows

        f, C, E, Phi, Phi_p = lin
        m, R, d, Q = E.shape
        n, A, Nd = C.shape[-1], st.A, st.Nd
        Pp = slots.shape[1]
        NB = pose_blocks(Pp)
        self.lin, self.st = lin, st
        self.slots = slots.contiguous()
        like = dict(dtype=E.dtype)
        # Woodbury's factors of the joint errors' elimination (fleet_kernel._eliminate_row), not the torch form's Li, W, z
        self.Dinv, self.gv = torch.empty(m, R, n, **like), torch.empty(m, R, n, **like)
        self.Mm = torch.empty(m, R, d, d, **like)
        pi, pj = torch.triu_indices(n, n)
        pair = torch.zeros(n, n, dtype=torch.long)
        pair[pi, pj] = torch.arange(pi.numel())
        self.ws = ws = Workspace() if ws is None else ws
        mg = 1 if shared else m  # the units whose Gram blocks are formed
        Gs, Gsd = ws.take("Gs", (pi.numel(), Pp, mg, A, A), E), ws.take("Gsd", (n, Pp, mg, A, Nd), E)
        Gdd, gx, dg = torch.empty(mg, NB, Nd, Nd, **like), torch.empty(m, NB, st.size, **like), \
            torch.empty(m, NB, st.size, **like)
        self.c = [t.contiguous() for t in (f, C, E, Phi)]
        args = [t.numpy() for t in self.c] + [V.contiguous().numpy(), w_v.contiguous().numpy(),
                                              mu.contiguous().numpy(), self.slots.numpy()]
        rows_out = [self.Dinv.numpy(), self.gv.numpy(), self.Mm.numpy()]
        grams = [Gs.view(-1).numpy(), Gsd.view(-1).numpy(), Gdd.numpy()]

        def run(sl, gram):
            schur_rows(*(a[sl] for a in args), n, A, pair.numpy(), gram, *(o[sl] for o in rows_out), *grams,
                       gx.numpy()[sl], dg.numpy()[sl])

        with dynamic():  # the units whose Gram blocks are formed (the first one where shared), then the others'
            run(slice(0, mg), True)
            if m > mg:
                run(slice(mg, m), False)
        self.gx, self.diag_x = gx.sum(1), dg.sum(1)
        self.S = contract((Gs.permute(0, 2, 3, 4, 1), Gsd.permute(2, 0, 3, 4, 1), Gdd.sum(1), pi, pj), Phi_p[:mg], st,
                          pp, ws)

    def gradient(self, r):
        from .fleet_kernel import dynamic, gradient_rows, pose_blocks

        f, C, E, Phi = self.c
        g = torch.empty(E.shape[0], pose_blocks(self.slots.shape[1]), self.st.size, dtype=E.dtype)
        with dynamic():
            gradient_rows(r.contiguous().numpy(), E.numpy(), Phi.numpy(), self.Mm.numpy(), self.slots.numpy(),
                          self.st.n, self.st.A, g.numpy())
        return g.sum(1)

    def _apply(self, dbx, final):
        from .fleet_kernel import apply_rows, dynamic, pose_blocks

        f, C, E, Phi = self.c
        m, R, d, _ = E.shape
        n = C.shape[-1]
        empty = E.new_zeros(1, 1, 1)
        sx = empty if final else torch.empty(m, pose_blocks(self.slots.shape[1]), self.st.size, dtype=E.dtype)
        dv, lin = (E.new_zeros(m, R, n), E.new_zeros(m, R, d)) if final else (empty, empty)
        with dynamic():
            apply_rows(E.numpy(), Phi.numpy(), dbx.contiguous().numpy(), self.slots.numpy(), n, self.st.A, final,
                       self.Mm.numpy(), self.Dinv.numpy(), self.gv.numpy(), f.numpy(), C.numpy(),
                       sx.numpy(), dv.numpy(), lin.numpy())
        return (dv, lin) if final else sx.sum(1)

    def product(self, dbx):
        return self._apply(dbx, False)

    def finish(self, dbx):
        return self._apply(dbx, True)


def dense_jacobian(E: torch.Tensor, Phi: torch.Tensor, st: RobotStructure) -> torch.Tensor:
    """The plain parameter Jacobian (m, R, d, P) in layout order from the factored one (the fleet's GPU form,
    whose normal matrix is one product of it; and the tests' reference)."""
    m, R, d, _ = E.shape
    Es = E[..., :st.ne].reshape(m, R, d, st.n, st.A)
    struct = (Es[..., None] * Phi[:, :, None, :, None, :]).reshape(m, R, d, st.ns)
    return torch.cat([struct, E[..., st.ne:]], -1)[..., st.index]


__all__ = ["GROUPS", "RobotStructure", "contract", "dense_jacobian", "factored_linearization", "factored_residual",
           "gram_parts", "pair_basis", "pose_gram", "pose_groups", "regrouped", "slots_of", "structured_steps"]
