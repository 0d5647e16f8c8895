"""The virtual-leader motion of coordinated groups (paper 004 eqs. 1-16, 27, 38): the exact
discretisation, a configuration's affine transition, and the per-axis layouts.

Paper 004's model as a whole, its state layouts and notation: the docstring of :mod:`torchmcmcpf.models.group`.
"""

from __future__ import annotations

import math
from typing import NamedTuple

import torch

from ..._native.select import where
from ..._validation import check_positive, check_positive_int
from ...runtime import squared_norm
from ...typing import Tensor
from ..base import Motion
from .existence import GroupExistence
from .structures import _same_group

__all__ = ["VirtualLeaderMotion", "AffineTransition", "to_axes", "from_axes"]

LOG_2PI = math.log(2 * math.pi)


# ----------------------------------------------------------------------------------------
# layouts
# ----------------------------------------------------------------------------------------
def to_axes(x: Tensor, v: Tensor) -> Tensor:
    """Per-axis state of a configuration: targets ``x (*S, K, 4)`` and leaders ``v (*S, K, 4)``
    in the ``[x, vx, y, vy]`` layout -> ``(*S, 2, 4K)`` with, per axis,
    ``[pos_1..pos_K, vel_1..vel_K, leader pos_1..K, leader vel_1..K]``.
    """
    parts = [x[..., 0::2], x[..., 1::2], v[..., 0::2], v[..., 1::2]]  # each (*S, K, 2)
    return torch.cat([p.transpose(-1, -2) for p in parts], -1)


def from_axes(s: Tensor) -> tuple[Tensor, Tensor]:
    """Inverse of :func:`to_axes`: ``(*S, 2, 4K) -> x (*S, K, 4), v (*S, K, 4)``."""
    k = s.shape[-1] // 4
    p, u, lp, lu = (s[..., j * k:(j + 1) * k].transpose(-1, -2) for j in range(4))  # (*S, K, 2)

    def interleave(a: Tensor, b: Tensor) -> Tensor:
        return torch.stack([a[..., 0], b[..., 0], a[..., 1], b[..., 1]], -1)

    return interleave(p, u), interleave(lp, lu)



# ----------------------------------------------------------------------------------------
# virtual-leader motion (eqs. 1-16, 27, 38)
# ----------------------------------------------------------------------------------------
class AffineTransition(NamedTuple):
    """``s_t = Psi s_{t-1} + r + b``, ``b ~ N(0, Q)``, per axis on ``[pos, vel, leader pos,
    leader vel]`` (``4K``) of a whole configuration (eqs. 13, 27, 38, 42).

    Attributes
    ----------
    Psi : (*S, 4K, 4K) shared by both axes.
    r : (*S, 2, 4K) offset per axis (repulsion ``R h``, ``x_death``, ``v_death``).
    Q : (*S, 4K, 4K) noise covariance, shared by both axes (zero rows where deterministic).
    random : (*S, 4K) bool, components with noise (``Q`` is positive definite on them).
    observed : (*S, K) bool, positions modelled by the Gaussian (``Upsilon~`` of eq. 42 less
        the dead slots): survivors and group births.
    free_birth : (*S, K) bool, independent births ``Upsilon_2^1`` (position from ``p_0``).
    born_gain : (*S, 4K, K) how those newborns' positions (per axis) enter the mean: the new
        leaders of eq. 35 (the offset ``r`` holds ``born_gain @ pos_born``).

    Example
    -------
    >>> import torch
    >>> from torchmcmcpf.models.group import GroupExistence, VirtualLeaderMotion
    >>> motion = VirtualLeaderMotion(alpha=0.0006, beta=0.05, gamma1=0.001, gamma2=0.001, sigma_x=0.2,
    ...                              sigma_g=0.5, dt=5.0)          # paper 004 Table 1
    >>> existence = GroupExistence(0.2, 0.05, ((0.0, 1000.0), (0.0, 1000.0)))
    >>> x = torch.tensor([[[100.0, 1.0, 100.0, 0.0], [120.0, 1.0, 100.0, 0.0]]], dtype=torch.float64)
    >>> v = torch.tensor([[[110.0, 1.0, 100.0, 0.0], [0.0, 0.0, 0.0, 0.0]]], dtype=torch.float64)
    >>> labels, alive = torch.tensor([[0, 0]]), torch.tensor([[True, True]])   # (S, K): one group of two
    >>> tr = motion.transition(x[..., 0::2], labels, labels, alive, alive, existence=existence)
    >>> tr.Psi.shape, tr.r.shape, tr.Q.shape                # 4K = 8 per axis
    (torch.Size([1, 8, 8]), torch.Size([1, 2, 8]), torch.Size([1, 8, 8]))
    >>> tr.random            # [pos, vel, leader pos, leader vel] x 2 slots: group 1 has no leader
    tensor([[ True,  True,  True,  True,  True, False,  True, False]])
    >>> tr.observed, tr.free_birth                          # two survivors, no independent birth
    (tensor([[True, True]]), tensor([[False, False]]))
    """

    Psi: Tensor
    r: Tensor
    Q: Tensor
    random: Tensor
    observed: Tensor
    free_birth: Tensor
    born_gain: Tensor


class VirtualLeaderMotion(Motion):
    """The virtual-leader group model of eqs. 1-16 with the repulsion of eqs. 8-11: a
    whole-configuration :class:`~torchmcmcpf.models.base.Motion` (the slots move jointly
    through their leaders, eq. 13), not a per-slot :class:`~torchmcmcpf.models.base.MotionModel`;
    a slot's label is its place in the group structure, so its slots are not exchangeable
    (:attr:`exchangeable_slots` False: the filter's estimate never relabels them).

    Parameters
    ----------
    alpha, beta, gamma1, gamma2 : positive model constants (Table 1: 0.0006, 0.05, 0.001,
        0.001).
    sigma_x : individual motion noise (Table 1: 0.2); ``sigma_y = sigma_x``.
    sigma_g : leader noise (Table 1: 0.5); 0 makes the leaders deterministic.
    dt : ``tau`` [s] (Table 1: 5).
    r1, r2 : repulsion constants ``R_1``, ``R_2`` of eq. 11 (Table 1: 8, 12); ``None`` (default)
        switches the repulsion off.

    Example
    -------
    Two targets (``x (S, K, 4)``) in one group led by leader slot 0 (``v (S, K, 4)``):

    >>> import torch
    >>> from torchmcmcpf.models.group import GroupExistence, VirtualLeaderMotion
    >>> motion = VirtualLeaderMotion(alpha=0.0006, beta=0.05, gamma1=0.001, gamma2=0.001, sigma_x=0.2,
    ...                              sigma_g=0.5, dt=5.0)          # paper 004 Table 1
    >>> existence = GroupExistence(0.2, 0.05, ((0.0, 1000.0), (0.0, 1000.0)))
    >>> x = torch.tensor([[[100.0, 1.0, 100.0, 0.0], [120.0, 1.0, 100.0, 0.0]]], dtype=torch.float64)
    >>> v = torch.tensor([[[110.0, 1.0, 100.0, 0.0], [0.0, 0.0, 0.0, 0.0]]], dtype=torch.float64)
    >>> labels, alive = torch.tensor([[0, 0]]), torch.tensor([[True, True]])   # (S, K): one group of two
    >>> x_next, v_next = motion.sample(x, v, labels, labels, alive, alive, existence=existence,
    ...                                generator=torch.Generator().manual_seed(0))
    >>> x_next.shape, v_next.shape
    (torch.Size([1, 2, 4]), torch.Size([1, 2, 4]))
    >>> motion.log_prob(x_next, v_next, x, v, labels, labels, alive, alive, existence=existence).shape   # (S,)
    torch.Size([1])
    """

    #: per-target state size of the ``[x, vx, y, vy]`` layout (the filters' ``motion.dim``)
    dim = 4
    #: a slot's label is its place in the group structure (:class:`~torchmcmcpf.models.base.Motion`)
    exchangeable_slots = False
    # per-axis 2 x 2 blocks ([pos, vel]) of F, R, Q read from ``matrices(2)`` (module docstring)
    F_ss: Tensor  # member <- itself
    F_sl: Tensor  # member <- its leader
    F_ll: Tensor  # leader <- itself
    R_s: Tensor  # (2,) member (pos, vel) <- its acceleration
    Q_self: Tensor
    Q_cross: Tensor
    Q_sl: Tensor
    Q_ll: Tensor

    def __init__(self, alpha: float, beta: float, gamma1: float, gamma2: float, sigma_x: float,
                 sigma_g: float, dt: float, r1: float | None = None, r2: float | None = None) -> None:
        super().__init__()
        self.alpha = check_positive(alpha, "alpha")
        self.beta = check_positive(beta, "beta", allow_zero=True)
        self.gamma1 = check_positive(gamma1, "gamma1", allow_zero=True)
        self.gamma2 = check_positive(gamma2, "gamma2", allow_zero=True)
        self.sigma_x = check_positive(sigma_x, "sigma_x")
        self.sigma_g = check_positive(sigma_g, "sigma_g", allow_zero=True)
        self.dt = check_positive(dt, "dt")
        if (r1 is None) != (r2 is None):
            raise ValueError(f"give both r1 and r2 or neither, got r1={r1!r}, r2={r2!r}")
        self.r1 = None if r1 is None else check_positive(r1, "r1", allow_zero=True)
        self.r2 = None if r2 is None else check_positive(r2, "r2")
        # per-axis blocks from the two-member group, state [x1, x2, y1, y2, xd1, xd2, yd1, yd2,
        # vx, vy, vdx, vdy]: member 1 x-axis is (0, 4), member 2 (1, 5), leader (8, 10)
        F, R, Q = self.matrices(2)
        m1, m2, ld = [0, 4], [1, 5], [8, 10]

        def blk(M: Tensor, a: list[int], b: list[int]) -> Tensor:
            return M[a][:, b].clone()

        self.register_buffer("F_ss", blk(F, m1, m1))   # member <- itself
        self.register_buffer("F_sl", blk(F, m1, ld))   # member <- its leader
        self.register_buffer("F_ll", blk(F, ld, ld))   # leader <- itself
        self.register_buffer("R_s", blk(R, m1, m1)[:, 1])  # member (pos, vel) <- its acceleration
        self.register_buffer("Q_self", blk(Q, m1, m1))
        self.register_buffer("Q_cross", blk(Q, m1, m2))
        self.register_buffer("Q_sl", blk(Q, m1, ld))
        self.register_buffer("Q_ll", blk(Q, ld, ld))

    # -- eqs. 3-7, 14-16 ------------------------------------------------------------------
    def generator_matrices(self, n: int) -> tuple[Tensor, Tensor]:
        """``A`` (eq. 4) and ``D Q_c D^T`` (eq. 7) of a group of ``n`` members, float64,
        ``(4(n+1), 4(n+1))`` each, in the state order of eq. 3.
        """
        n = check_positive_int(n, "n")
        d = 4 * (n + 1)
        f64 = torch.float64
        A = torch.zeros(d, d, dtype=f64)
        I2n = torch.eye(2 * n, dtype=f64)
        A[:2 * n, 2 * n:4 * n] = I2n
        A[2 * n:4 * n, :2 * n] = -self.alpha * I2n
        A[2 * n:4 * n, 2 * n:4 * n] = -(self.beta + self.gamma1) * I2n
        ones = torch.ones(n, dtype=f64)
        o = 4 * n  # leader block starts here: [v^x, v^y, vdot^x, vdot^y]
        A[2 * n:3 * n, o + 0] = self.alpha * ones   # Lambda_a (eq. 5)
        A[3 * n:4 * n, o + 1] = self.alpha * ones
        A[2 * n:3 * n, o + 2] = self.beta * ones
        A[3 * n:4 * n, o + 3] = self.beta * ones
        A[o:, o:] = torch.tensor([[0, 0, 1, 0], [0, 0, 0, 1], [0, 0, -self.gamma2, 0],
                                  [0, 0, 0, -self.gamma2]], dtype=f64)  # Lambda_b (eq. 6)
        qc = torch.zeros(d, dtype=f64)
        qc[2 * n:4 * n] = self.sigma_x**2
        qc[o + 2:] = self.sigma_g**2
        return A, torch.diag(qc)

    def matrices(self, n: int) -> tuple[Tensor, Tensor, Tensor]:
        """Exact discretisation over ``tau`` of one group of ``n`` members and its leader.

        ``F = expm(A tau)`` (eq. 14), ``R = int_0^tau expm(A s) ds`` (eq. 15) and
        ``Q = int_0^tau expm(A s) D Q_c D^T expm(A s)^T ds`` (eq. 16), by the matrix-fraction
        / Van Loan construction: ``expm([[A, I], [0, 0]] tau) = [[F, R], [0, I]]`` and
        ``expm([[-A, D Q_c D^T], [0, A^T]] tau) = [[., F^{-1} Q], [0, F^T]]``.

        Parameters
        ----------
        n : number of members.

        Returns
        -------
        F, R, Q : (4(n+1), 4(n+1)) float64 each, state order of eq. 3.
        """
        A, L = self.generator_matrices(n)
        d = A.shape[0]
        Z = torch.zeros(d, d, dtype=torch.float64)
        E1 = torch.linalg.matrix_exp(torch.cat([torch.cat([A, torch.eye(d, dtype=A.dtype)], 1),
                                                torch.cat([Z, Z], 1)], 0) * self.dt)
        F, R = E1[:d, :d], E1[:d, d:]
        E2 = torch.linalg.matrix_exp(torch.cat([torch.cat([-A, L], 1), torch.cat([Z, A.T], 1)], 0) * self.dt)
        Q = E2[d:, d:].T @ E2[:d, d:]
        return F, R, 0.5 * (Q + Q.T)

    # -- eqs. 8-11 --------------------------------------------------------------------------
    def repulsion(self, pos: Tensor, labels: Tensor, active: Tensor) -> Tensor:
        """Repulsive acceleration on each member (eqs. 8-11), summed over the other active
        members of its group: ``r_i = sum_j f_ij / d_ij (p_i - p_j)``,
        ``f_ij = R_1 / (d_ij + R_2)``; zero when the repulsion is off.

        Parameters
        ----------
        pos : (*S, K, 2) positions at ``t - 1``; labels : (*S, K) structure at ``t``;
        active : (*S, K) bool, the members that take part (survivors).

        Returns
        -------
        (*S, K, 2).
        """
        if self.r1 is None or self.r2 is None:  # both or neither (__init__)
            return torch.zeros_like(pos)
        diff = pos.unsqueeze(-2) - pos.unsqueeze(-3)  # (*S, K, K, 2): p_i - p_j
        d = squared_norm(diff).clamp(min=torch.finfo(pos.dtype).tiny).sqrt()  # coincident: 0 force
        pair = _same_group(labels) & active.unsqueeze(-1) & active.unsqueeze(-2)
        pair = pair & ~torch.eye(pos.shape[-2], dtype=torch.bool, device=pos.device)
        coef = where(pair, self.r1 / ((d + self.r2) * d), torch.zeros_like(d))
        return (coef.unsqueeze(-1) * diff).sum(-2)

    # -- whole configuration (eqs. 13, 24-38) ----------------------------------------------
    def transition(self, pos_prev: Tensor, labels_prev: Tensor, labels: Tensor, exists_prev: Tensor,
                   exists: Tensor, *, existence: GroupExistence,
                   pos_born: Tensor | None = None) -> AffineTransition:
        """The affine Gaussian transition of a whole configuration, per axis (eqs. 27, 42).

        Slots and groups are partitioned as in eq. 26: survivors ``Upsilon_3`` move by eq. 13
        with the repulsion of their group; a group's leader at ``t - 1`` is the average of the
        leaders (at ``t - 1``) of the groups its survivors came from: the merge rule of
        eq. 38, which also gives the split rule (each part keeps the common previous leader);
        group births ``Upsilon_2^2`` follow eqs. 29-31 from that leader and the mean of the
        group's survivors; independent births ``Upsilon_2^1`` take their position from
        ``pos_born`` (drawn from ``p_0`` elsewhere) and a ``N(0, sigma_Vmax^2)`` velocity;
        a group of newborns only (``Upsilon_6``) gets a new leader by eq. 35; dead slots and
        leaders of groups with no live member (``Upsilon_4``, unused labels) sit at
        ``x_death`` / ``v_death`` (eqs. 36-37). The repulsion acts between survivors of one
        group under ``g_t``, from the positions at ``t - 1``.

        Parameters
        ----------
        pos_prev : (*S, K, 2) positions at ``t - 1``.
        labels_prev, labels : (*S, K) int64 structures at ``t - 1`` and ``t`` (labels in
            ``[0, K)``; group ``h`` owns leader slot ``h``).
        exists_prev, exists : (*S, K) bool.
        existence : GroupExistence (births, death states).
        pos_born : (*S, K, 2) positions at ``t`` of the independent newborns (other rows
            ignored); ``None`` leaves them out of ``r`` (add ``born_gain @ pos`` later).

        Returns
        -------
        AffineTransition.
        """
        dtype, dev = pos_prev.dtype, pos_prev.device
        k = labels.shape[-1]
        batch = labels.shape[:-1]
        surv = exists_prev & exists
        born = ~exists_prev & exists
        G = torch.nn.functional.one_hot(labels, k).to(dtype)  # (*S, K, K): G[i, h] = g_i == h
        Gp = torch.nn.functional.one_hot(labels_prev, k).to(dtype)
        sv = surv.to(dtype)
        n_surv = torch.einsum("...ih,...i->...h", G, sv)  # survivors per new group
        grp_surv = n_surv > 0  # Upsilon_5
        grp_born = torch.einsum("...ih,...i->...h", G, born.to(dtype)) > 0
        grp_new = grp_born & ~grp_surv  # Upsilon_6
        member_gs = torch.einsum("...ih,...h->...i", G, grp_surv.to(dtype)) > 0
        born22 = born & member_gs
        born21 = born & ~member_gs
        # merge / split rule (eq. 38): previous leader of new group h' = mean of the previous
        # leaders of the groups its survivors come from
        M = (torch.einsum("...ia,...i,...ib->...ab", G, sv, Gp) > 0).to(dtype)  # (*S, K', K)
        M = M / M.sum(-1, keepdim=True).clamp(min=1)
        # mean of the survivors of each new group (eq. 30)
        Amean = G.transpose(-1, -2) * sv.unsqueeze(-2) / n_surv.clamp(min=1).unsqueeze(-1)  # (*S, K', K)
        src = torch.diag_embed(sv) + born22.to(dtype).unsqueeze(-1) * (G @ Amean)  # (*S, K, K)
        lsrc = (surv | born22).to(dtype).unsqueeze(-1) * (G @ M)  # (*S, K, K): member <- leaders
        lead = grp_surv.to(dtype).unsqueeze(-1) * M  # (*S, K, K): leader <- leaders

        # new leaders (eq. 35): leader h of a group of newborns only = mean of its newborns
        Bm = G.transpose(-1, -2) * born21.to(dtype).unsqueeze(-2)
        Bm = Bm / Bm.sum(-1, keepdim=True).clamp(min=1) * grp_new.to(dtype).unsqueeze(-1)  # (*S, K', K)
        # Psi and Q = sum over block types of (4 x 4 per-axis coefficients) x (K x K weights):
        # one einsum each, no per-block concatenation
        eye = torch.eye(k, dtype=dtype, device=dev)
        same = _same_group(labels).to(dtype) * sv.unsqueeze(-1) * sv.unsqueeze(-2)
        sG = sv.unsqueeze(-1) * G
        W_psi = torch.stack([src, lsrc, lead], -3)  # (*S, 3, K, K)
        W_q = torch.stack([same, eye * sv.unsqueeze(-1), eye * born22.to(dtype).unsqueeze(-1),
                           eye * born21.to(dtype).unsqueeze(-1), sG, sG.transpose(-1, -2),
                           torch.diag_embed(grp_surv.to(dtype)), torch.diag_embed(grp_new.to(dtype)),
                           Bm.transpose(-1, -2), Bm, Bm @ Bm.transpose(-1, -2)], -3)  # (*S, 11, K, K)
        C_psi, C_q = self._coefficients(existence, dtype=dtype, device=dev)
        Psi = torch.einsum("tab,...tij->...aibj", C_psi, W_psi).reshape(batch + (4 * k, 4 * k))
        Q = torch.einsum("tab,...tij->...aibj", C_q, W_q).reshape(batch + (4 * k, 4 * k))
        # offsets per axis: repulsion R h (eqs. 8, 13), death states (eqs. 36-37)
        rep = self.repulsion(pos_prev, labels, surv)  # (*S, K, 2)
        dead = (~exists).to(dtype).unsqueeze(-1)  # (*S, K, 1)
        lead_dead = (~grp_surv & ~grp_new).to(dtype).unsqueeze(-1)
        xd, vd = existence.x_death.to(dtype=dtype, device=dev), existence.v_death.to(dtype=dtype, device=dev)
        r_pos = self.R_s[0].to(dtype=dtype, device=dev) * rep * sv.unsqueeze(-1) + dead * xd[0::2]
        r_vel = self.R_s[1].to(dtype=dtype, device=dev) * rep * sv.unsqueeze(-1) + dead * xd[1::2]
        r = torch.cat([r_pos, r_vel, lead_dead * vd[0::2], lead_dead * vd[1::2]], -2).transpose(-1, -2)
        # independent newborns: position given (p_0), enters its own row and its new leader's
        zk = torch.zeros(batch + (k, k), dtype=dtype, device=dev)
        born_gain = torch.cat([torch.diag_embed(born21.to(dtype)), zk, Bm, zk], -2)  # (*S, 4K, K)
        if pos_born is not None:
            r = r + (born_gain @ pos_born.to(dtype)).transpose(-1, -2)
        random = torch.cat([surv | born22, exists, grp_surv | grp_new, grp_surv | grp_new], -1)
        if self.sigma_g == 0:  # deterministic leaders: their noise rows vanish
            random = random & torch.cat([torch.ones(batch + (2 * k,), dtype=torch.bool, device=dev),
                                         grp_new, grp_new], -1)
        return AffineTransition(Psi, r, Q, random, surv | born22, born21, born_gain)

    def _coefficients(self, existence: GroupExistence, *, dtype: torch.dtype,
                      device: torch.device) -> tuple[Tensor, Tensor]:
        """Per-axis 4 x 4 coefficients (``[pos, vel, leader pos, leader vel]``) of each block
        type of :meth:`transition`: ``Psi`` (3 types) and ``Q`` (11 types).
        """
        z = torch.zeros(2, 2, dtype=dtype, device=device)
        sv2 = existence.velocity_std ** 2

        def place(B: Tensor, row: int, col: int) -> Tensor:
            out = torch.zeros(4, 4, dtype=dtype, device=device)
            out[2 * row:2 * row + 2, 2 * col:2 * col + 2] = B.to(dtype=dtype, device=device)
            return out

        c_psi = torch.stack([place(self.F_ss, 0, 0), place(self.F_sl, 0, 1), place(self.F_ll, 1, 1)])
        u_lu = torch.zeros(4, 4, dtype=dtype, device=device)
        u_lu[1, 3] = sv2
        c_q = torch.stack([
            place(self.Q_cross, 0, 0),                    # survivors of one group
            place(self.Q_self - self.Q_cross, 0, 0),      # each survivor's own noise
            place(existence.group_birth_cov, 0, 0),       # group births, Q_bT (eq. 29)
            place(torch.diag(torch.stack([z[0, 0], z[0, 0] + sv2])), 0, 0),  # independent births' velocity
            place(self.Q_sl, 0, 1),                       # survivor - its leader
            place(self.Q_sl.T, 1, 0),
            place(self.Q_ll, 1, 1),                       # surviving leaders
            place(existence.leader_birth_cov, 1, 1),      # new leaders, Q_bVL (eq. 35)
            u_lu,                                         # newborn velocity - its new leader's
            u_lu.T,
            place(torch.diag(torch.stack([z[0, 0], z[0, 0] + sv2])), 1, 1),  # new leader <- newborns
        ])
        return c_psi, c_q

    def sample(self, x: Tensor, v: Tensor, labels_prev: Tensor, labels: Tensor, exists_prev: Tensor,
               exists: Tensor, *, existence: GroupExistence, generator: torch.Generator
               ) -> tuple[Tensor, Tensor]:
        """Draw the next configuration's kinematics (eqs. 13, 27-38) given the discrete
        configuration ``(g_{t-1}, g_t, e_{t-1}, e_t)``.

        Parameters
        ----------
        x, v : (*S, K, 4) targets and leaders at ``t - 1`` (``[x, vx, y, vy]``).
        labels_prev, labels : (*S, K) int64; exists_prev, exists : (*S, K) bool.
        existence : GroupExistence; generator : source of randomness.

        Returns
        -------
        x_next, v_next : (*S, K, 4).
        """
        pos_prev = x[..., 0::2]
        pos_born = existence.sample_p0_position(x.shape[:-1], generator=generator, dtype=x.dtype,
                                                device=x.device)
        tr = self.transition(pos_prev, labels_prev, labels, exists_prev, exists, existence=existence,
                             pos_born=pos_born)
        s = to_axes(x, v)
        mean = s @ tr.Psi.transpose(-1, -2) + tr.r
        L = _masked_cholesky(tr.Q, tr.random)
        eps = torch.randn(mean.shape, generator=generator, dtype=x.dtype, device=x.device)
        return from_axes(mean + eps @ L.transpose(-1, -2))

    def log_prob(self, x_next: Tensor, v_next: Tensor, x: Tensor, v: Tensor, labels_prev: Tensor,
                 labels: Tensor, exists_prev: Tensor, exists: Tensor, *, existence: GroupExistence) -> Tensor:
        """``log p(x_t, v_t | x_{t-1}, v_{t-1}, g_{t-1:t}, e_{t-1:t})`` (eq. 27): the Gaussian
        of eqs. 13/38 over the random components plus ``log p_0`` of the independent
        newborns' positions (eq. 33; the velocity is in the Gaussian); the point masses of
        eqs. 36-37 contribute nothing.

        Parameters: as :meth:`sample` plus ``x_next, v_next (*S, K, 4)``. Returns ``(*S,)``.
        """
        tr = self.transition(x[..., 0::2], labels_prev, labels, exists_prev, exists, existence=existence,
                             pos_born=x_next[..., 0::2])
        resid = to_axes(x_next, v_next) - (to_axes(x, v) @ tr.Psi.transpose(-1, -2) + tr.r)
        log_g = _masked_gaussian(resid, tr.Q, tr.random)
        log_p0 = where(tr.free_birth, existence.log_p0_position(x_next[..., 0::2]),
                             torch.zeros((), dtype=x.dtype, device=x.device)).sum(-1)
        return log_g + log_p0


def _masked_cholesky(Q: Tensor, mask: Tensor) -> Tensor:
    """Cholesky factor of ``Q`` restricted to ``mask``, zero rows/columns elsewhere:
    ``(*S, d, d), (*S, d) -> (*S, d, d)``.
    """
    m = mask.to(Q.dtype)
    Qm = Q * m.unsqueeze(-1) * m.unsqueeze(-2) + torch.diag_embed(1.0 - m)
    return torch.linalg.cholesky(Qm) * m.unsqueeze(-1) * m.unsqueeze(-2)


def _masked_gaussian(resid: Tensor, Q: Tensor, mask: Tensor) -> Tensor:
    """``log N(resid; 0, Q)`` over the masked components, both axes: ``resid (*S, 2, d)``,
    ``Q (*S, d, d)``, ``mask (*S, d)`` -> ``(*S,)``.
    """
    m = mask.to(Q.dtype)
    L = torch.linalg.cholesky(Q * m.unsqueeze(-1) * m.unsqueeze(-2) + torch.diag_embed(1.0 - m))
    y = torch.linalg.solve_triangular(L, (resid * m.unsqueeze(-2)).transpose(-1, -2), upper=False)
    quad = y.square().sum((-1, -2))
    logdet = 2 * torch.log(torch.diagonal(L, dim1=-2, dim2=-1)).sum(-1)  # masked diag is 1
    return -0.5 * quad - logdet - m.sum(-1) * LOG_2PI
