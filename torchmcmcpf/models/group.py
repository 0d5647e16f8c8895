"""Coordinated groups: virtual-leader motion, group structures, group births and the
pairwise Kalman statistics of Septier, Pang, Godsill and Carmi (2009, paper 004).

Continuous-time model (eqs. 1-7)
--------------------------------
Each member ``i`` of group ``g`` follows, per axis,
``d xdot_i = {-alpha (x_i - v) - gamma1 xdot_i - beta (xdot_i - vdot)} dt + sigma_x dW_i`` and
its virtual leader ``d vdot = -gamma2 vdot dt + sigma_g dG`` (eqs. 1-2). In the paper's state
order of eq. 3, ``s = [x_1..x_n, y_1..y_n, xdot_1..xdot_n, ydot_1..ydot_n, v^x, v^y, vdot^x,
vdot^y]``, ``ds = A s dt + h dt + D dn`` (eqs. 3-8) with the exact discretisation
``s_t = F s_{t-1} + R h + b``, ``b ~ N(0, Q)`` (eqs. 12-16), computed by
:meth:`VirtualLeaderMotion.matrices` with ``torch.linalg.matrix_exp`` (Van Loan 1978).

Whole configurations (``K = N_max`` slots)
-----------------------------------------
A configuration is

- target states ``x (*S, K, 4)`` in the library layout ``[x, vx, y, vy]``;
- leader states ``v (*S, K, 4)``, same layout: leader slot ``h`` belongs to group label ``h``;
- structure labels ``g (*S, K)`` int64, a restricted-growth string (first target in group 0,
  :func:`group_structures`), or equivalently the index of its row in that table;
- existence ``e (*S, K)`` bool.

Members do not interact with each other except through their leader (and the repulsion,
an input), so every ``F_n``, ``R_n``, ``Q_n`` is made of the same few blocks whatever ``n``:
member-member (self and cross), member-leader and leader-leader. :class:`VirtualLeaderMotion`
reads them once from ``matrices(2)``; a configuration's transition is then assembled by
broadcasting these blocks against one-hot membership matrices: no Python loop over
particles, groups or configurations. Both axes share the dynamics and the noise
(``sigma_y = sigma_x``), so the transition of the per-axis state
``[x_1..x_K, xdot_1..xdot_K, v_1..v_K, vdot_1..vdot_K]`` (``4K``) has one ``Psi`` and one
covariance for both axes and an offset per axis (:class:`AffineTransition`).

Marginalisation (eqs. 42-58)
----------------------------
The velocities and leaders ``w = [x_v, v]`` (``3K`` per axis) are integrated out: each
particle carries ``N(w_{t-1}; mean, cov)`` given its positions ``x_{p,0:t-1}``
(:class:`KalmanStats`, one covariance for both axes), :func:`pairwise_kalman_predict` gives
the joint Gaussian of ``(x_{p,t}, w_t)`` and :func:`pairwise_kalman_update` conditions it on
the new positions: the log of eq. 58 and the statistics of eqs. 56-57.
"""

from __future__ import annotations

import functools
import math
from collections.abc import Callable, Sequence
from typing import NamedTuple

import torch
from torch import nn

from .._validation import check_positive, check_positive_int
from ..resampling import cdf, inverse_cdf
from ..typing import Tensor
from .existence import BirthDeath, _probability
from .sensors.points import AreaLike

__all__ = [
    "VirtualLeaderMotion",
    "GroupExistence",
    "GroupStructurePrior",
    "AffineTransition",
    "KalmanStats",
    "GroupPrediction",
    "group_structures",
    "structure_index",
    "bell_number",
    "pairwise_kalman_init",
    "pairwise_kalman_predict",
    "pairwise_kalman_update",
    "pairwise_kalman_sample",
    "canonical_labels",
    "gaussian_closeness",
    "to_axes",
    "from_axes",
    "ExistenceLimit",
    "localised_existence",
    "existence_limit",
]

LOG_2PI = math.log(2 * math.pi)


# ----------------------------------------------------------------------------------------
# group structures (eqs. 19-23, Table 2)
# ----------------------------------------------------------------------------------------
@functools.cache
def bell_number(n: int) -> int:
    """Number of partitions of ``n`` items (Bell numbers 1, 1, 2, 5, 15, 52, ...)."""
    check_positive_int(n, "n", minimum=0)
    row = [1]
    for _ in range(n):
        nxt = [row[-1]]
        for v in row:
            nxt.append(nxt[-1] + v)
        row = nxt
    return row[0]


@functools.cache
def _structures(n: int) -> tuple[tuple[int, ...], ...]:
    rows: list[tuple[int, ...]] = [(0,)]
    for _ in range(n - 1):
        rows = [r + (j,) for r in rows for j in range(max(r) + 2)]
    return tuple(rows)


def group_structures(n: int, *, device: torch.device | str | None = None) -> Tensor:
    """Every partition of ``n`` targets once, as canonical labels (paper 004, Table 2).

    A row is a restricted-growth string: target 0 is in group 0 and each target's label is
    at most one more than the largest label before it; group ``h`` of a row owns leader slot
    ``h``. Rows are in lexicographic order, so for ``n = 4`` they are the 15 columns of
    Table 2 (labels minus one).

    Parameters
    ----------
    n : number of targets ``N_max >= 1``.
    device : where the table is made (default the CPU).

    Returns
    -------
    (Bell(n), n) int64.
    """
    check_positive_int(n, "n")
    return torch.tensor(_structures(n), dtype=torch.int64, device=device)


def structure_index(labels: Tensor) -> Tensor:
    """Row of :func:`group_structures` that a labelling describes: ``(*S, K) -> (*S,)``.

    ``labels`` need not be canonical (any integers in ``[0, K)`` naming the groups); they
    are relabelled in order of first appearance first.
    """
    k = labels.shape[-1]
    table = group_structures(k, device=labels.device)
    canon = canonical_labels(labels)
    # encode in base K and look up (the table is sorted lexicographically, so its codes are)
    powers = k ** torch.arange(k - 1, -1, -1, device=labels.device)
    codes = (table * powers).sum(-1)
    return torch.searchsorted(codes, (canon * powers).sum(-1).contiguous())


def canonical_labels(labels: Tensor) -> Tensor:
    """Relabel groups in order of first appearance: ``(*S, K) -> (*S, K)`` int64."""
    k = labels.shape[-1]
    same = labels.unsqueeze(-1) == labels.unsqueeze(-2)  # (*S, K, K)
    idx = torch.arange(k, device=labels.device)
    first = torch.where(same, idx, k).amin(-1)  # first member of each target's group
    is_first = first == idx  # (*S, K)
    rank = is_first.long().cumsum(-1) - 1  # rank of each first member
    return torch.gather(rank, -1, first)


def _same_group(labels: Tensor) -> Tensor:
    return labels.unsqueeze(-1) == labels.unsqueeze(-2)


def gaussian_closeness(scale: float, power: float = 2.0) -> Callable[[Tensor, Tensor], Tensor]:
    """``h(x_i, x_j) = exp(-(|x_i - x_j| / scale)^power / 2)``, a closeness in (0, 1] (eq. 23):
    the Gaussian for ``power = 2``, a generalised Gaussian (flatter near 0, sharper at
    ``|x_i - x_j| ~ scale``) for larger powers. ``h = e^{-1/2}`` at distance ``scale``.
    """
    s = check_positive(scale, "scale")
    p = check_positive(power, "power")

    def closeness(pi: Tensor, pj: Tensor) -> Tensor:
        d2 = (pi - pj).square().sum(-1) / s**2
        return torch.exp(-0.5 * d2 if p == 2.0 else -0.5 * d2.pow(0.5 * p))

    return closeness


class GroupStructurePrior(nn.Module):
    """Group structure transition of eqs. 19-23.

    ``p(g_t | x_{p,t-1}, g_{t-1}, e_{t-1}) = P_NC delta(g_t - g_{t-1}) + (1 - P_NC) pi(g_t)``
    (eq. 19) with ``pi(h) propto prod_{(i,j) in Delta_h} q_ij prod_{(i,j) not in Delta_h}
    (1 - q_ij)`` (eqs. 21-22) over unordered pairs ``i < j``, ``Delta_h`` the pairs in one
    group of ``h``, and ``q_ij = P_Q`` if ``e_{t-1,i} = 0`` or ``e_{t-1,j} = 0``, else
    ``closeness(x_{p,t-1,i}, x_{p,t-1,j})`` (eq. 23; the paper writes ``e_t`` in eq. 23 but
    eq. 20 and Algorithm 1, which draws ``g_t`` before ``e_t``, condition on ``e_{t-1}``).
    ``q`` is clipped to ``[1e-12, 1 - 1e-12]`` so that no structure has probability exactly
    zero under ``pi`` (two pairs at distance 0 and a third far apart would otherwise leave
    no structure). Normalised over all ``Bell(K)`` structures in log space.

    Parameters
    ----------
    p_nc : ``P_NC`` in [0, 1], probability of no change (paper: 0.6).
    p_q : ``P_Q`` in (0, 1), pair score involving an inactive target (paper: 0.05).
    closeness : ``h(p_i (*S, 2), p_j (*S, 2)) -> (*S,)`` in [0, 1]; default
        :func:`gaussian_closeness` with ``scale`` (the paper gives no ``h``).
    scale, power : of the default closeness (default 300 m and 2: two targets 300 m apart are
        in one group with score ``e^{-1/2}``); the group-merge scenario sets them from its
        geometry (:func:`~torchmcmcpf.scenarios.group_merge.group_merge`).

    Example
    -------
    >>> import torch
    >>> from torchmcmcpf.models.group import GroupStructurePrior, group_structures
    >>> prior = GroupStructurePrior(p_nc=0.6, p_q=0.05)
    >>> group_structures(2)                                  # Bell(2) = 2 structures: together, apart
    tensor([[0, 0],
            [0, 1]])
    >>> pos = torch.tensor([[[0.0, 0.0], [20.0, 0.0]]], dtype=torch.float64)   # (S, K, 2): 20 m apart
    >>> prior.log_scores(pos, torch.tensor([[True, True]])).exp().round(decimals=3)
    tensor([[0.9980, 0.0020]], dtype=torch.float64)
    >>> prior.sample(torch.tensor([1]), pos, torch.tensor([[True, True]]), generator=torch.Generator()).shape
    torch.Size([1])
    """

    def __init__(self, p_nc: float, p_q: float, closeness: Callable[[Tensor, Tensor], Tensor] | None = None, *,
                 scale: float = 300.0, power: float = 2.0) -> None:
        super().__init__()
        self.p_nc = _probability(p_nc, "p_nc")
        self.p_q = _probability(p_q, "p_q")
        if not 0.0 < self.p_q < 1.0:
            raise ValueError(f"p_q must be in (0, 1), got {p_q!r}")
        self.closeness = gaussian_closeness(scale, power) if closeness is None else closeness

    def log_scores(self, pos: Tensor, exists: Tensor) -> Tensor:
        """``log pi(h | x_{p,t-1}, e_{t-1})`` for every structure ``h`` (eqs. 21-23).

        Parameters
        ----------
        pos : (*S, K, 2) positions at ``t - 1``; exists : (*S, K) bool at ``t - 1``.

        Returns
        -------
        (*S, Bell(K)), normalised: ``logsumexp(-1) == 0``.
        """
        k = pos.shape[-2]
        h = self.closeness(pos.unsqueeze(-2), pos.unsqueeze(-3))  # (*S, K, K)
        both = exists.unsqueeze(-1) & exists.unsqueeze(-2)
        q = torch.where(both, h.to(pos.dtype), torch.full_like(h, self.p_q, dtype=pos.dtype))
        q = q.clamp(1e-12, 1 - 1e-12)
        same = _same_group(group_structures(k, device=pos.device)).to(pos.dtype)  # (G, K, K)
        upper = torch.triu(torch.ones(k, k, dtype=pos.dtype, device=pos.device), 1)
        lq, l1q = (q.log() * upper), (torch.log1p(-q) * upper)  # (*S, K, K)
        score = torch.einsum("...ij,gij->...g", lq - l1q, same) + l1q.sum((-1, -2)).unsqueeze(-1)
        return score - torch.logsumexp(score, -1, keepdim=True)

    def log_probs(self, structure_prev: Tensor, pos: Tensor, exists: Tensor) -> Tensor:
        """``log p(g_t = h | ...)`` for every ``h`` (eq. 19): ``(*S,), (*S, K, 2), (*S, K)
        -> (*S, Bell(K))``; ``structure_prev`` is the row index of ``g_{t-1}``.
        """
        log_pi = self.log_scores(pos, exists)
        stay = torch.nn.functional.one_hot(structure_prev, log_pi.shape[-1]).bool()
        log_nc = math.log(self.p_nc) if self.p_nc > 0 else -math.inf
        log_c = math.log1p(-self.p_nc) if self.p_nc < 1 else -math.inf
        dtype, dev = log_pi.dtype, log_pi.device
        return torch.logaddexp(log_c + log_pi,
                               torch.where(stay, torch.tensor(log_nc, dtype=dtype, device=dev),
                                           torch.tensor(-math.inf, dtype=dtype, device=dev)))

    def log_prob(self, structure: Tensor, structure_prev: Tensor, pos: Tensor, exists: Tensor) -> Tensor:
        """``log p(g_t | x_{p,t-1}, g_{t-1}, e_{t-1})`` of row indices ``structure (*S,)``."""
        lp = self.log_probs(structure_prev, pos, exists)
        return torch.gather(lp, -1, structure.unsqueeze(-1)).squeeze(-1)

    def sample(self, structure_prev: Tensor, pos: Tensor, exists: Tensor, *,
               generator: torch.Generator) -> Tensor:
        """Draw row indices ``g_t (*S,)`` int64 from eq. 19 (inverse CDF, one uniform each)."""
        log_p = self.log_probs(structure_prev, pos, exists)
        u = torch.rand(log_p.shape[:-1] + (1,), generator=generator, device=log_p.device, dtype=torch.float64)
        return inverse_cdf(cdf(log_p), u).squeeze(-1)


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
# existence and births (eqs. 24-37)
# ----------------------------------------------------------------------------------------
class GroupExistence(BirthDeath):
    """Existence chain and birth/death densities of a group configuration (eqs. 24-37).

    A :class:`~torchmcmcpf.models.existence.BirthDeath` (the library's one birth/death law:
    the existence chain of eq. 25, its draws, the area and the uniform birth position of
    eqs. 32-33) with the group model's extra birth densities:

    - independent birth (``Upsilon_2^1``: newborn in a group with no survivor), eqs. 32-33:
      position uniform over ``area``, velocity ``N(0, velocity_std^2 I)``;
    - group birth (``Upsilon_2^2``), eqs. 29-31: ``N(F~_1 s_bar_{t-1}, Q_bT)``, ``s_bar`` the
      mean state of the group's survivors and the group's (merged / kept) leader at ``t-1``,
      ``F~_1`` the member rows of ``F_1``; ``Q_bT = diag(s_p^2, s_v^2)`` per axis with
      ``(s_p, s_v) = group_birth_std``;
    - new leader of a group with newborns only (``Upsilon_6``), eq. 35:
      ``N(mean of the newborns' states, Q_bVL)``, ``Q_bVL = diag(s_p^2, s_v^2)`` per axis,
      ``(s_p, s_v) = leader_birth_std``;
    - dead target at ``x_death``, dead leader (group with no live member, or unused label) at
      ``v_death`` (eqs. 36-37), both ``(4,)`` in the ``[x, vx, y, vy]`` layout.

    The paper gives no numbers for ``sigma_Vmax``, ``Q_bT``, ``Q_bVL``; the defaults are ours.

    Parameters
    ----------
    p_birth, p_death : ``P_B``, ``P_D`` (paper: 0.2, 0.05).
    area : ``((x_lo, x_hi), (y_lo, y_hi))`` [m].
    velocity_std : ``sigma_Vmax`` [m/s] (default 5).
    group_birth_std : ``(s_p [m], s_v [m/s])`` of ``Q_bT`` (default (50, 2)).
    leader_birth_std : ``(s_p, s_v)`` of ``Q_bVL`` (default (50, 2)).
    x_death, v_death : (4,) (default zeros).

    Example
    -------
    >>> import torch
    >>> from torchmcmcpf.models.group import GroupExistence
    >>> existence = GroupExistence(0.2, 0.05, ((0.0, 1000.0), (0.0, 2000.0)))   # P_B, P_D, area
    >>> pos = torch.tensor([[500.0, 500.0], [1500.0, 500.0]])    # (K, 2): inside, outside
    >>> existence.log_p0_position(pos)                      # uniform: -log(1000 * 2000) inside
    tensor([-14.5087,     -inf])
    >>> existence.sample_p0_position((3, 2), generator=torch.Generator()).shape
    torch.Size([3, 2, 2])
    >>> existence.group_birth_cov                           # Q_bT per axis, diag(50^2, 2^2)
    tensor([[2500.,    0.],
            [   0.,    4.]], dtype=torch.float64)
    """

    group_birth_cov: Tensor  # (2, 2) Q_bT per axis
    leader_birth_cov: Tensor  # (2, 2) Q_bVL per axis
    v_death: Tensor  # (4,)

    def __init__(self, p_birth: float, p_death: float, area: AreaLike, *, velocity_std: float = 5.0,
                 group_birth_std: Sequence[float] = (50.0, 2.0),
                 leader_birth_std: Sequence[float] = (50.0, 2.0),
                 x_death: Tensor | None = None, v_death: Tensor | None = None) -> None:
        super().__init__(p_birth, p_death, area, velocity_std=velocity_std, dim=4, x_death=x_death)
        dtype = torch.float64
        for name, std in (("group_birth_std", group_birth_std), ("leader_birth_std", leader_birth_std)):
            if len(std) != 2:
                raise ValueError(f"{name} must be (position std, velocity std), got {std!r}")
            sp, sv = check_positive(std[0], name), check_positive(std[1], name)
            self.register_buffer(name.replace("_std", "_cov"), torch.diag(torch.tensor([sp**2, sv**2], dtype=dtype)))
        val = torch.zeros(4, dtype=dtype) if v_death is None else torch.as_tensor(v_death, dtype=dtype)
        if val.shape != (4,) or not bool(torch.isfinite(val).all()):
            raise ValueError(f"v_death must be a finite (4,) vector, got shape {tuple(val.shape)}")
        self.register_buffer("v_death", val)

    def log_p0_position(self, pos: Tensor) -> Tensor:
        """Log density of the uniform birth position (eq. 32): ``(*S, K, 2) -> (*S, K)``,
        ``-inf`` outside the area (the area check of :class:`BirthDeath`, in ``pos``'s dtype).
        """
        return torch.where(self._in_area(pos), pos.new_full((), -self.log_volume), pos.new_full((), -math.inf))

    def sample_p0_position(self, shape: Sequence[int], *, generator: torch.Generator,
                           dtype: torch.dtype = torch.float64,
                           device: torch.device | str | None = None) -> Tensor:
        """Uniform birth positions (eq. 32): ``-> (*shape, 2)``."""
        return self.uniform_position(torch.rand(tuple(shape) + (2,), generator=generator, dtype=dtype,
                                                device=device))


# ----------------------------------------------------------------------------------------
# the Bayes limit of detection: one perfectly localised target (eqs. 25, 33, 41)
# ----------------------------------------------------------------------------------------
class ExistenceLimit(NamedTuple):
    """What the existence model allows for one target whose position is known exactly
    (:func:`existence_limit`).

    Attributes
    ----------
    per_step : (T,) float64 ``E[P(alive at t | d_1:t)]`` over the detections of a target that
        is alive from step 1 on, starting from ``P(alive) = 0`` (an all-inactive start).
    per_step_error : (T,) half-width of the bracket around ``per_step`` (0 where the
        expectation is an exact enumeration, ``t <= window``).
    stationary : the long-run mean of the posterior, ``lim_t E[P(alive at t | d_1:t)]``.
    stationary_error : half-width of its bracket.

    Example
    -------
    >>> from torchmcmcpf.models.group import existence_limit
    >>> limit = existence_limit(30, p_birth=0.2, p_death=0.05, p_d1=0.9, p_fa=0.01, window=8)
    >>> limit.per_step[:3]                                  # exact for t <= window
    tensor([0.8642, 0.9438, 0.9576], dtype=torch.float64)
    >>> round(limit.stationary, 4), limit.stationary_error < 1e-6   # x K targets: the count's ceiling
    (0.9594, True)
    """

    per_step: Tensor
    per_step_error: Tensor
    stationary: float
    stationary_error: float


def _check_existence_law(p_birth: float, p_death: float, p_d1: float, p_fa: float, p_here: float) -> None:
    for name, v in (("p_birth", p_birth), ("p_death", p_death), ("p_here", p_here)):
        if not 0.0 <= float(v) <= 1.0:
            raise ValueError(f"{name} must be a probability in [0, 1], got {v!r}")
    if not 0.0 < float(p_fa) < float(p_d1) < 1.0:
        raise ValueError(f"need 0 < p_fa < p_d1 < 1, got p_fa={p_fa!r}, p_d1={p_d1!r}")


def localised_existence(detected: Tensor, *, p_birth: float, p_death: float, p_d1: float, p_fa: float,
                        p_here: float = 1.0, p_alive: float | Tensor = 0.0) -> Tensor:
    """Exact posterior existence of one target at a known pixel: a two-state hidden Markov
    model over its detection sequence (paper 004 eqs. 25, 33, 41).

    The hidden state is "the target is alive at the pixel" (1) or not (0). From 1 it stays
    with ``1 - P_D`` (eq. 25); from 0 it appears at the pixel with ``P_B p_here``, ``p_here``
    the chance that a newborn's uniform position (eq. 33) falls in this pixel (pixel area
    over scene area: 1e-4 for paper 004's 100 x 100 pixels; 1 if newborns appear at the
    known pixel). The pixel fires with ``P_d,1`` in state 1 and ``P_fa`` in state 0 (eq. 41).
    The forward recursion, in probability space (two states, renormalised every step)::

        prior_t = p_{t-1} (1 - P_D) + (1 - p_{t-1}) P_B p_here
        p_t = prior_t l_1(d_t) / (prior_t l_1(d_t) + (1 - prior_t) l_0(d_t)).

    Every filter of the group model that knows the target's pixel perfectly can do no better
    than this; a real filter, which must also find the pixel, does worse on the target (its
    expected count can still exceed ``K p_t`` through targets it believes born on false
    alarms).

    Parameters
    ----------
    detected : (*S, T) bool, the pixel's value in frames 1..T.
    p_birth, p_death, p_d1, p_fa, p_here : the model above.
    p_alive : ``P(alive)`` before frame 1, a float or ``(*S,)`` (default 0: inactive).

    Returns
    -------
    (*S, T) float64, ``P(alive at t | d_1:t)``.
    """
    _check_existence_law(p_birth, p_death, p_d1, p_fa, p_here)
    d = torch.as_tensor(detected).to(torch.bool)
    p = torch.as_tensor(p_alive, dtype=torch.float64, device=d.device).expand(d.shape[:-1])
    one = torch.ones((), dtype=torch.float64, device=d.device)  # float64 probabilities (not torch.where's float32)
    out = []
    for t in range(d.shape[-1]):
        prior = p * (1.0 - p_death) + (1.0 - p) * (p_birth * p_here)
        l1 = torch.where(d[..., t], one * p_d1, one - p_d1)
        l0 = torch.where(d[..., t], one * p_fa, one - p_fa)
        p = prior * l1 / (prior * l1 + (1.0 - prior) * l0)
        out.append(p)
    return torch.stack(out, -1) if out else p.new_zeros(d.shape)


def existence_limit(num_steps: int, *, p_birth: float, p_death: float, p_d1: float, p_fa: float,
                    p_here: float = 1.0, window: int = 20) -> ExistenceLimit:
    """The mean posterior existence of a perfectly localised target that is alive from step 1
    on (:func:`localised_existence`), per step and in the long run: multiply by the number
    of targets for the ceiling of the expected number of targets.

    The expectation is over the target's detections, independent ``Bernoulli(P_d,1)``. For
    ``t <= window`` it is an exact sum over all ``2^t`` sequences (from ``P(alive) = 0``).
    Beyond, the posterior depends on the last ``window`` detections and on ``p_{t-window}``,
    and it increases with ``p_{t-window}``, so the sums over the last ``window`` detections
    started from 0 and from 1 bracket it; ``per_step`` is the midpoint and
    ``per_step_error`` the half-width (below 1e-5 for paper 004's numbers at the default
    window). The stationary mean has the same bracket.

    Parameters
    ----------
    num_steps : T >= 1; p_birth, p_death, p_d1, p_fa, p_here : as :func:`localised_existence`.
    window : enumeration length (``2^window`` sequences; default 20, about 1e6).

    Returns
    -------
    ExistenceLimit.
    """
    t_max = check_positive_int(num_steps, "num_steps")
    w = check_positive_int(window, "window")
    if w > 24:
        raise ValueError(f"window must be <= 24 (2^window sequences are enumerated), got {window}")
    _check_existence_law(p_birth, p_death, p_d1, p_fa, p_here)
    codes = torch.arange(2 ** w)
    d = ((codes.unsqueeze(-1) >> torch.arange(w)) & 1).to(torch.bool)  # (2^w, w), every sequence once
    one = torch.ones((), dtype=torch.float64)
    prob = torch.where(d, one * p_d1, one - p_d1).prod(-1)  # (2^w,)
    law = dict(p_birth=p_birth, p_death=p_death, p_d1=p_d1, p_fa=p_fa, p_here=p_here)
    lo = prob @ localised_existence(d, **law, p_alive=0.0)  # (w,): exact from an inactive start
    hi = prob @ localised_existence(d, **law, p_alive=1.0)
    lo_w, hi_w = float(lo[-1]), float(hi[-1])
    mean = torch.full((t_max,), 0.5 * (lo_w + hi_w), dtype=torch.float64)
    err = torch.full((t_max,), 0.5 * (hi_w - lo_w), dtype=torch.float64)
    n = min(t_max, w)
    mean[:n], err[:n] = lo[:n], 0.0
    return ExistenceLimit(mean, err, 0.5 * (lo_w + hi_w), 0.5 * (hi_w - lo_w))


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


class VirtualLeaderMotion(nn.Module):
    """The virtual-leader group model of eqs. 1-16 with the repulsion of eqs. 8-11.

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
        d = diff.square().sum(-1).clamp(min=torch.finfo(pos.dtype).tiny).sqrt()  # coincident: 0 force
        pair = _same_group(labels) & active.unsqueeze(-1) & active.unsqueeze(-2)
        pair = pair & ~torch.eye(pos.shape[-2], dtype=torch.bool, device=pos.device)
        coef = torch.where(pair, self.r1 / ((d + self.r2) * d), torch.zeros_like(d))
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
        log_p0 = torch.where(tr.free_birth, existence.log_p0_position(x_next[..., 0::2]),
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


# ----------------------------------------------------------------------------------------
# pairwise Kalman marginalisation (eqs. 42-58)
# ----------------------------------------------------------------------------------------
class KalmanStats(NamedTuple):
    """``p(w_{t-1} | x_{p,0:t-1}, ...) = N(mean, cov)`` per axis, ``w = [velocities (K),
    leader positions (K), leader velocities (K)]``.

    Attributes
    ----------
    mean : (*S, 2, 3K) one row per axis.
    cov : (*S, 3K, 3K) shared by both axes.

    Example
    -------
    >>> from torchmcmcpf.models.group import GroupExistence, pairwise_kalman_init
    >>> existence = GroupExistence(0.2, 0.05, ((0.0, 1000.0), (0.0, 1000.0)))
    >>> stats = pairwise_kalman_init((5,), 2, existence=existence)   # 5 samples, K = 2: all inactive
    >>> stats.mean.shape, stats.cov.shape                   # w = [velocities, leader pos, leader vel]
    (torch.Size([5, 2, 6]), torch.Size([5, 6, 6]))
    >>> float(stats.cov.abs().max())                        # nothing uncertain yet
    0.0
    """

    mean: Tensor
    cov: Tensor


class GroupPrediction(NamedTuple):
    """Joint Gaussian of ``(x_{p,t}, w_t)`` given the past positions (eqs. 47, 51-52).

    Attributes
    ----------
    mean : (*S, 2, 4K) per axis ``[positions, w]``, without the independent newborns'
        positions' contribution to the new leaders.
    cov : (*S, 4K, 4K).
    transition : the AffineTransition it came from (``observed``, ``free_birth``,
        ``born_gain``).

    Example
    -------
    One step of the pairwise Kalman filter (eqs. 47-58):

    >>> import torch
    >>> from torchmcmcpf.models.group import GroupExistence, VirtualLeaderMotion
    >>> motion = VirtualLeaderMotion(alpha=0.0006, beta=0.05, gamma1=0.001, gamma2=0.001, sigma_x=0.2,
    ...                              sigma_g=0.5, dt=5.0)          # paper 004 Table 1
    >>> existence = GroupExistence(0.2, 0.05, ((0.0, 1000.0), (0.0, 1000.0)))
    >>> x = torch.tensor([[[100.0, 1.0, 100.0, 0.0], [120.0, 1.0, 100.0, 0.0]]], dtype=torch.float64)
    >>> v = torch.tensor([[[110.0, 1.0, 100.0, 0.0], [0.0, 0.0, 0.0, 0.0]]], dtype=torch.float64)
    >>> labels, alive = torch.tensor([[0, 0]]), torch.tensor([[True, True]])   # (S, K): one group of two
    >>> from torchmcmcpf.models.group import pairwise_kalman_init, pairwise_kalman_predict, pairwise_kalman_update
    >>> tr = motion.transition(x[..., 0::2], labels, labels, alive, alive, existence=existence)
    >>> pred = pairwise_kalman_predict(pairwise_kalman_init((1,), 2, existence=existence), x[..., 0::2], tr)
    >>> pred.position_mean.shape, pred.position_cov.shape   # (S, K, 2), (S, K, K) per axis
    (torch.Size([1, 2, 2]), torch.Size([1, 2, 2]))
    >>> log_pred, stats = pairwise_kalman_update(pred, x[..., 0::2])   # condition on positions at t
    >>> log_pred.shape, stats.mean.shape
    (torch.Size([1]), torch.Size([1, 2, 6]))
    """

    mean: Tensor
    cov: Tensor
    transition: AffineTransition

    @property
    def position_mean(self) -> Tensor:
        """(*S, K, 2) predictive mean of the positions (``x~_t`` of eq. 51 on ``Upsilon~``)."""
        k = self.mean.shape[-1] // 4
        return self.mean[..., :k].transpose(-1, -2)

    @property
    def position_cov(self) -> Tensor:
        """(*S, K, K) predictive covariance of the positions, per axis (``L_t`` of eq. 52)."""
        k = self.mean.shape[-1] // 4
        return self.cov[..., :k, :k]


def pairwise_kalman_init(batch_shape: Sequence[int], num_slots: int, *, existence: GroupExistence,
                         dtype: torch.dtype = torch.float64,
                         device: torch.device | str | None = None) -> KalmanStats:
    """Statistics of an all-inactive configuration: velocities at ``x_death``'s, leaders at
    ``v_death``, zero covariance: ``-> mean (*batch, 2, 3K), cov (*batch, 3K, 3K)``.
    """
    k = check_positive_int(num_slots, "num_slots")
    xd, vd = existence.x_death.to(dtype=dtype, device=device), existence.v_death.to(dtype=dtype, device=device)
    row = torch.stack([torch.cat([xd[1 + a].expand(k), vd[a].expand(k), vd[1 + a].expand(k)])
                       for a in (0, 2)])  # (2, 3K)
    mean = row.expand(tuple(batch_shape) + (2, 3 * k)).clone()
    return KalmanStats(mean, torch.zeros(tuple(batch_shape) + (3 * k, 3 * k), dtype=dtype, device=device))


def pairwise_kalman_predict(stats: KalmanStats, pos_prev: Tensor, tr: AffineTransition) -> GroupPrediction:
    """Predict ``(x_{p,t}, w_t)`` jointly from ``N(w_{t-1}; mean, cov)`` and the known
    ``x_{p,t-1}`` through ``s_t = Psi s_{t-1} + r + b`` (eq. 47):
    ``mean = Psi [x_{p,t-1}; w_mean] + r``, ``cov = Psi_{.w} cov Psi_{.w}^T + Q``. Its
    position block is ``(x~_t, L_t)`` of eqs. 51-52.

    Parameters
    ----------
    stats : KalmanStats at ``t - 1``; pos_prev : (*S, K, 2);
    tr : :meth:`VirtualLeaderMotion.transition` (built with ``pos_born=None``).

    Returns
    -------
    GroupPrediction.
    """
    k = pos_prev.shape[-2]
    s_prev = torch.cat([pos_prev.transpose(-1, -2), stats.mean], -1)  # (*S, 2, 4K)
    mean = s_prev @ tr.Psi.transpose(-1, -2) + tr.r
    Pw = tr.Psi[..., :, k:]  # (*S, 4K, 3K)
    cov = Pw @ stats.cov @ Pw.transpose(-1, -2) + tr.Q  # symmetric up to rounding; the update re-symmetrises
    return GroupPrediction(mean, cov, tr)


def pairwise_kalman_update(pred: GroupPrediction, pos: Tensor) -> tuple[Tensor, KalmanStats]:
    """Condition the prediction on the positions ``x_{p,t}`` (eqs. 53-58).

    ``log N(x_{p,t}; x~_t, L_t)`` over the observed positions (survivors and group births,
    eq. 58; both axes), and ``w_t | x_{p,0:t}`` by Gaussian conditioning,
    ``mean_w + S_wp S_pp^{-1} (x_p - x~)``, ``S_ww - S_wp S_pp^{-1} S_pw``: this is the
    pairwise Kalman filter of eqs. 51-57 written as predict-then-condition (eqs. 54-57
    compose the conditioning of ``w_{t-1}`` on ``x_{p,t}`` with the step to ``w_t``). The
    independent newborns' positions enter the new leaders' means through ``born_gain``;
    their ``p_0`` density is not included (:meth:`GroupExistence.log_p0_position`).

    Parameters
    ----------
    pred : GroupPrediction; pos : (*S, K, 2) positions at ``t`` (dead slots ignored).

    Returns
    -------
    log_pred : (*S,) ``log p(x_{p,t,Upsilon~} | x_{p,0:t-1}, e_{0:t}, g_{0:t})``.
    stats : KalmanStats at ``t``.
    """
    tr = pred.transition
    k = pos.shape[-2]
    obs = tr.observed.to(pos.dtype)  # (*S, K)
    posT = pos.transpose(-1, -2)  # (*S, 2, K)
    mean = pred.mean + (tr.born_gain @ (posT * tr.free_birth.to(pos.dtype).unsqueeze(-2)).transpose(-1, -2)
                        ).transpose(-1, -2)
    innov = (posT - mean[..., :k]) * obs.unsqueeze(-2)  # (*S, 2, K)
    S = pred.cov[..., :k, :k] * obs.unsqueeze(-1) * obs.unsqueeze(-2) + torch.diag_embed(1.0 - obs)
    L = torch.linalg.cholesky(S)
    y = torch.linalg.solve_triangular(L, innov.transpose(-1, -2), upper=False)  # (*S, K, 2)
    logdet = 2 * torch.log(torch.diagonal(L, dim1=-2, dim2=-1)).sum(-1)
    log_pred = -0.5 * y.square().sum((-1, -2)) - logdet - obs.sum(-1) * LOG_2PI
    Swp = pred.cov[..., k:, :k] * obs.unsqueeze(-2)  # (*S, 3K, K)
    G = torch.linalg.solve_triangular(L, Swp.transpose(-1, -2), upper=False)  # L^{-1} S_pw (*S, K, 3K)
    w_mean = mean[..., k:] + y.transpose(-1, -2) @ G  # (*S, 2, 3K)
    w_cov = pred.cov[..., k:, k:] - G.transpose(-1, -2) @ G
    return log_pred, KalmanStats(w_mean, 0.5 * (w_cov + w_cov.transpose(-1, -2)))


def pairwise_kalman_sample(pred: GroupPrediction, *, generator: torch.Generator | None = None,
                           eps: Tensor | None = None) -> Tensor:
    """Draw the observed positions from their predictive ``N(x~_t, L_t)`` (eq. 58, the
    position part of the proposal of eq. 63); the other slots are returned as zeros (fill
    them with ``p_0`` / ``q_0`` births and ``x_death``).

    Parameters
    ----------
    pred : GroupPrediction.
    generator : source of the standard normals; or pass them as
    eps : (*S, K, 2) pre-drawn standard normals (compiled kernels, DESIGN.md).

    Returns
    -------
    (*S, K, 2).
    """
    obs = pred.transition.observed
    k = obs.shape[-1]
    mean = pred.mean[..., :k].transpose(-1, -2)  # (*S, K, 2)
    if eps is None:
        if generator is None:
            raise ValueError("pairwise_kalman_sample needs a generator or eps")
        eps = torch.randn(mean.shape, generator=generator, dtype=mean.dtype, device=mean.device)
    L = _masked_cholesky(pred.cov[..., :k, :k], obs)
    return (mean + L @ eps) * obs.to(mean.dtype).unsqueeze(-1)
