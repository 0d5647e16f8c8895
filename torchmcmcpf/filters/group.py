"""Marginalised MCMC-based particle filter for coordinated groups (Septier, Pang, Godsill and
Carmi 2009, paper 004, sec. 4, Algorithms 1-2, eqs. 59-66).

The state of a particle is ``(x_{p,t}, g_t, e_t)``: the positions ``x_p (K, 2)``, the group
structure ``g`` (canonical labels ``(K,)``) and the existence flags ``e (K,)`` of ``K = N_max``
slots; the velocities and the virtual leaders ``w`` are integrated out by one pairwise
Kalman filter per particle (:mod:`torchmcmcpf.models.group`, eqs. 42-58). Each chain samples
the target of eq. 43 with the previous cloud in place of the previous posterior (eq. 59),

    pi(j, g, e, x) ∝ w_j p(g | j) p(e | e^j) p(x | j, g, e) p(Z_t | x, e),

``j`` the index of the previous particle (its whole past), ``w_j`` its weight (``1 / N`` for
an MCMC cloud), ``p(g | j)`` eq. 19 from ``(x_p^j, g^j, e^j)``, ``p(e | e^j)`` eq. 25,
``p(x | j, g, e) = prod_{free births} p_0(x_i) N(x_obs; x~, L)`` (eq. 44: the uniform
``p_0`` of eq. 33 for the independent newborns ``Upsilon_2^1``, the pairwise Kalman
predictive of eq. 58 for the survivors and group births, a point mass at ``x_death`` for the
dead slots) and ``p(Z | x, e)`` the thresholded-pixel likelihood ratio (eqs. 39-41).

Moves and their acceptance ratios
---------------------------------
**Joint draw** (Algorithm 1, eq. 60). Propose ``j* ~ q(j) = P_a alpha_j + (1 - P_a) w_j``
(eqs. 61-62; ``alpha_j ∝ w_j p(Z_t | x~^j, e^j)`` scores particle ``j``'s positions
predicted by its Kalman filter with its structure and existence unchanged), ``g* ~ p(g | j*)``
(eq. 19), ``e* ~ p(e | e^{j*})`` (eq. 25), the survivors' and group births' positions from
the Kalman predictive ``N(x~, L)`` (eq. 58) and the independent newborns' from the
data-driven ``q_0`` (eqs. 63-65). The prior terms ``p(g | j)``, ``p(e | e^j)`` and the
Gaussian ``N(x_obs; x~, L)`` appear in target and proposal alike and cancel:

    rho_1 = min(1, [p(Z|x*, e*) w_{j*} / q(j*) prod_{free*} p_0(x*_i) / q_0(x*_i)]
                 / [p(Z|x, e)   w_j    / q(j)  prod_{free}  p_0(x_i)  / q_0(x_i) ]).

**Structure** (Algorithm 2, step 1-3). Propose ``g* ~ p(g | j)`` (eq. 19, the current ``j``);
``p(g | j)`` cancels and

    rho_2 = min(1, p(x | j, g*, e) / p(x | j, g, e))

with ``p(x | ...)`` the full density above (Gaussian part and ``p_0`` terms: a newborn may
change from independent to group birth with the structure).

**Each target** (Algorithm 2, steps 4-10, eq. 66), for slot ``i = 0 .. K-1`` in turn:
``e_i* ~ p(e_i | e^j_i)`` (eq. 25, cancels), then ``x_i*`` from ``q_i``: the conditional of
the Kalman predictive given the other observed slots ``N(x_i; x~_i|rest, L_i|rest)`` if ``i``
is a survivor or a group birth under ``(g, e*)``, ``q_0`` (eq. 64) if it is an independent
newborn, ``x_death`` (a point mass, ``q = 1``) if dead:

    rho_3 = min(1, [p(Z|x*, e*) p(x* | j, g, e*) / q_i(x_i* | x_rest, e*)]
                 / [p(Z|x, e)   p(x  | j, g, e)  / q_i(x_i  | x_rest, e) ]).

The mixture kernel makes a joint draw with probability ``xi`` (paper: 0.75), else one
refinement sweep (structure, then each target). One uniform per iteration picks the move
for every chain of every run (the pick does not depend on the state, so each chain's kernel
is still the mixture; only one move is computed per iteration).

Chains
------
``C`` chains per run are a tensor dimension (``(B, C, ...)``); each starts from a joint
proposal (accepted), runs ``burn_in + thinning N / C`` iterations and keeps every
``thinning``-th state after the burn-in (``N / C`` each). The kept states' Kalman statistics
(eqs. 56-57) are computed once, after the chains ran. ``marginalise=False`` gives the
same sampler without Rao-Blackwellisation: each kept particle *samples* its velocities and
leaders from their Kalman posterior and carries a point mass (zero covariance), so the next
step's position prior is conditional on sampled ``w`` (issue 11, item 4a).

Outputs
-------
``GroupState.x (B, N, K, 4)`` holds ``[x, vx, y, vy]``: the sampled positions and each
particle's Kalman posterior-mean velocities, so the MMSE estimate (``existence_estimate``)
gives positions and velocities; ``StepInfo.extras`` has ``structure_prob (B, Bell(K))``
(posterior probability of every row of :func:`~torchmcmcpf.models.group.group_structures`),
``exists_prob (B, K)``, ``expected_count (B,)`` and the acceptance rate of each move.

Contract deviations
-------------------
The filtering state is a :class:`GroupState` (``x, log_w, exists`` as in ``ParticleState``
plus the structure labels, the Kalman statistics and the previous frame for eq. 65), and
the step function also takes the ``structure_prior`` (eq. 19). The per-target refinement
loops over the ``K`` slots (a Gibbs sweep is sequential by definition).
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any, NamedTuple

import torch
import torch.nn.functional as F
from torch import nn

from .._validation import check_generator, check_positive_int, check_shape
from ..models.group import (
    GroupExistence,
    GroupStructurePrior,
    KalmanStats,
    VirtualLeaderMotion,
    group_structures,
    pairwise_kalman_init,
    pairwise_kalman_predict,
    pairwise_kalman_update,
    structure_index,
)
from ..models.sensors.pixels import ThresholdedPixels
from ..resampling import cdf, inverse_cdf
from ..state import FilterResult, StepInfo, existence_estimate, stack_infos, weighted_mean
from ..typing import Tensor
from .base import Filter, compile_kernel

__all__ = ["GroupMCMCFilter", "GroupMCMCSettings", "GroupState", "group_mcmc_step"]

LOG_2PI = math.log(2 * math.pi)

Noise = dict[str, Tensor]
"""The uniforms and normals of one move, by name (:func:`draw_joint_noise`, :func:`draw_refine_noise`)."""


@dataclass(frozen=True)
class GroupMCMCSettings:
    """Settings of :class:`GroupMCMCFilter` (paper 004 sec. 5 values as defaults where given).

    Attributes
    ----------
    num_chains : C >= 1 chains per run (a divisor of N).
    burn_in : iterations discarded per chain and step (paper: 1000).
    thinning : keep every ``thinning``-th state (paper: 6).
    xi : probability of the joint draw in the mixture kernel (paper: 0.75).
    p_a : ``P_a`` of eq. 61, weight of the likelihood-weighted choice of the ancestor (0.5).
    p_i : ``P_I`` of eq. 64, weight of the uniform birth proposal (0.01).
    marginalise : integrate the velocities and leaders out (paper); ``False`` samples them.
    """

    num_chains: int = 1
    burn_in: int = 1000
    thinning: int = 6
    xi: float = 0.75
    p_a: float = 0.5
    p_i: float = 0.01
    marginalise: bool = True

    def __post_init__(self) -> None:
        check_positive_int(self.num_chains, "num_chains")
        check_positive_int(self.burn_in, "burn_in", minimum=0)
        check_positive_int(self.thinning, "thinning")
        for name, lo_open in (("xi", False), ("p_a", False), ("p_i", True)):
            v = float(getattr(self, name))
            if not (0.0 <= v <= 1.0) or (lo_open and v == 0.0):
                raise ValueError(f"{name} must be a probability in {'(0, 1]' if lo_open else '[0, 1]'}, got {v!r}")
        if not isinstance(self.marginalise, bool):
            raise ValueError(f"marginalise must be a bool, got {self.marginalise!r}")

    def check(self, num_particles: int) -> None:
        """Raise ``ValueError`` unless ``num_particles`` is a multiple of ``num_chains``."""
        if num_particles % self.num_chains:
            raise ValueError(f"num_particles ({num_particles}) must be a multiple of num_chains ({self.num_chains})")


class GroupState(NamedTuple):
    """Particle approximation of ``p(x_p, g, e | Z_1:t)`` with each particle's Kalman filter.

    Attributes
    ----------
    x : (B, N, K, 4) ``[x, vx, y, vy]``: sampled positions, Kalman posterior-mean velocities.
    log_w : (B, N) normalised log-weights (equal after an MCMC step).
    exists : (B, N, K) bool.
    labels : (B, N, K) int64 canonical structure labels.
    w_mean : (B, N, 2, 3K) Kalman mean of ``w = [velocities, leader pos, leader vel]`` per axis.
    w_cov : (B, N, 3K, 3K) its covariance (zero with ``marginalise=False``).
    frame_prev : (B, H, W) bool, the previous frame (birth proposal, eq. 65); ``None`` at the
        start (the current frame is used).
    """

    x: Tensor
    log_w: Tensor
    exists: Tensor
    labels: Tensor
    w_mean: Tensor
    w_cov: Tensor
    frame_prev: Tensor | None = None

    @property
    def batch_size(self) -> int:
        """``B``, the number of independent runs."""
        return self.x.shape[0]

    @property
    def num_particles(self) -> int:
        """``N``, the number of particles per run."""
        return self.x.shape[1]

    def mean(self) -> Tensor:
        """Weighted mean of the particles, ``(B, K, 4)`` (ignores existence: see
        :func:`~torchmcmcpf.state.existence_estimate` for the mean given existence).
        """
        return weighted_mean(self.x, self.log_w)


torch.serialization.add_safe_globals([GroupState])


class Cloud(NamedTuple):
    """The previous particles and the per-step quantities of the proposals (eager, once per
    step). ``pos (B, N, K, 2)``, ``labels (B, N, K)``, ``exists (B, N, K)``, ``w_mean``,
    ``w_cov``; ``log_pg (B, N, G)`` eq. 19 for every structure; ``cdf_alpha (B, N)``,
    ``cdf_w (B, N)`` float64 cumulative weights of ``alpha`` and ``w``; ``log_wq (B, N)``
    ``log w_j - log q(j)`` (eq. 61); ``beta (B, HW)`` bool pixels of eq. 65, ``cdf_beta (B, HW)``,
    ``n_obs (B,)``; ``table (G, K)`` the structures.
    """

    pos: Tensor
    labels: Tensor
    exists: Tensor
    w_mean: Tensor
    w_cov: Tensor
    log_pg: Tensor
    cdf_alpha: Tensor
    cdf_w: Tensor
    log_wq: Tensor
    beta: Tensor
    cdf_beta: Tensor
    n_obs: Tensor
    table: Tensor


class Chain(NamedTuple):
    """Chain states ``(B, C, ...)``: ancestor ``j``, ``labels``, ``exists``, ``pos (B, C, K, 2)``;
    cached ``log_lik`` (eq. 40), ``log_px`` (``log p(x | j, g, e)``), ``log_wq``
    (``log w_j - log q(j)``), ``log_birth`` (``sum_free log p_0 - log q_0``); and the
    configuration's predictive: ``pm (B, C, K, 2)``, ``S (B, C, K, K)``, ``observed``, ``free``.
    """

    j: Tensor
    labels: Tensor
    exists: Tensor
    pos: Tensor
    log_lik: Tensor
    log_px: Tensor
    log_wq: Tensor
    log_birth: Tensor
    pm: Tensor
    S: Tensor
    observed: Tensor
    free: Tensor


class Models(NamedTuple):
    """The models and the proposal constants a move needs (bound, not traced)."""

    motion: VirtualLeaderMotion
    sensor: ThresholdedPixels
    existence: GroupExistence
    p_i: float
    p_a: float


# ----------------------------------------------------------------------------------------
# small pieces
# ----------------------------------------------------------------------------------------
def _lift(pos: Tensor, sensor: ThresholdedPixels) -> Tensor:
    """Positions ``(*S, K, 2)`` into the sensor's state layout ``(*S, K, D)``."""
    ix, iy = sensor.position_index
    d = max(ix, iy) + 1
    out = pos.new_zeros(pos.shape[:-1] + (d,))
    out[..., ix] = pos[..., 0]
    out[..., iy] = pos[..., 1]
    return out


def _log_lik(pos: Tensor, exists: Tensor, z: Tensor, sensor: ThresholdedPixels) -> Tensor:
    """``log p(Z | x, e)`` (eq. 40) of positions ``(B, *S, K, 2)``: ``-> (B, *S)``."""
    return sensor.log_likelihood(_lift(pos, sensor), z, exists)


def _gather(t: Tensor, j: Tensor) -> Tensor:
    """Rows ``j (B, C)`` of ``t (B, N, ...)`` -> ``(B, C, ...)``."""
    b = torch.arange(t.shape[0], device=t.device).unsqueeze(-1)
    return t[b, j]


def _predict(cloud: Cloud, j: Tensor, labels: Tensor, exists: Tensor, models: Models
             ) -> tuple[Tensor, Tensor, Tensor, Tensor]:
    """Kalman predictive of the positions of configuration ``(j, g, e)``: ``pm (B, C, K, 2)``,
    ``S (B, C, K, K)``, ``observed``, ``free (B, C, K)`` (eqs. 47, 51-52).
    """
    pos_prev = _gather(cloud.pos, j)
    tr = models.motion.transition(pos_prev, _gather(cloud.labels, j), labels, _gather(cloud.exists, j), exists,
                                  existence=models.existence)
    pred = pairwise_kalman_predict(KalmanStats(_gather(cloud.w_mean, j), _gather(cloud.w_cov, j)), pos_prev, tr)
    return pred.position_mean, pred.position_cov, tr.observed, tr.free_birth


def _log_px(pos: Tensor, pm: Tensor, S: Tensor, obs: Tensor, free: Tensor, existence: GroupExistence) -> Tensor:
    """``log p(x | j, g, e)`` (eq. 44): Gaussian over the observed slots (both axes) plus
    ``log p_0`` of the free births: ``-> (B, C)``.
    """
    o = obs.to(pos.dtype)
    Sm = S * o.unsqueeze(-1) * o.unsqueeze(-2) + torch.diag_embed(1.0 - o)
    L = torch.linalg.cholesky(Sm)
    y = torch.linalg.solve_triangular(L, (pos - pm) * o.unsqueeze(-1), upper=False)
    logdet = torch.log(torch.diagonal(L, dim1=-2, dim2=-1)).sum(-1)
    log_g = -0.5 * y.square().sum((-1, -2)) - 2 * logdet - o.sum(-1) * LOG_2PI
    log_p0 = torch.where(free, existence.log_p0_position(pos), torch.zeros_like(pos[..., 0])).sum(-1)
    return log_g + log_p0


def _log_q0(pos: Tensor, cloud: Cloud, sensor: ThresholdedPixels, existence: GroupExistence, p_i: float) -> Tensor:
    """``log q_0(x)`` of eq. 64 per slot: ``(B, C, K, 2) -> (B, C, K)``."""
    log_p0 = existence.log_p0_position(pos)
    h, w = sensor.shape
    s = sensor.pixel_size
    col = torch.floor(pos[..., 0] / s).clamp(0, w - 1).long()
    row = torch.floor(pos[..., 1] / s).clamp(0, h - 1).long()
    flat = (row * w + col).reshape(pos.shape[0], -1)
    hit = torch.gather(cloud.beta, 1, flat).reshape(pos.shape[:-1]).to(pos.dtype)
    n = cloud.n_obs.to(pos.dtype).reshape((-1,) + (1,) * (pos.dim() - 2))
    phi = hit / (n.clamp(min=1) * s * s)
    q = torch.where(n > 0, p_i * log_p0.exp() + (1 - p_i) * phi, log_p0.exp())
    return torch.where(torch.isfinite(log_p0), q.log(), log_p0)


def _draw_q0(noise: Noise, cloud: Cloud, sensor: ThresholdedPixels, existence: GroupExistence, p_i: float
             ) -> Tensor:
    """Positions from ``q_0`` (eqs. 64-65): ``(B, C, K, 2)`` from the birth noise."""
    u_sel, u_pix, u_xy = noise["b_sel"], noise["b_pix"], noise["b_xy"]
    a = existence.area.to(u_xy.dtype)
    uniform = a[:, 0] + (a[:, 1] - a[:, 0]) * u_xy
    b = u_pix.shape[0]
    total = cloud.cdf_beta[:, -1:]
    idx = torch.searchsorted(cloud.cdf_beta, (u_pix.reshape(b, -1) * total).contiguous(), right=True)
    idx = idx.clamp(max=cloud.cdf_beta.shape[-1] - 1).reshape(u_pix.shape)
    w = sensor.shape[1]
    s = sensor.pixel_size
    pix = torch.stack([(idx % w).to(u_xy.dtype), (idx // w).to(u_xy.dtype)], -1)
    in_pixel = (pix + u_xy) * s
    n = cloud.n_obs.reshape((-1,) + (1,) * (u_sel.dim() - 1))
    use_uniform = (u_sel < p_i) | (n == 0)
    return torch.where(use_uniform.unsqueeze(-1), uniform, in_pixel)


def _birth_ratio(pos: Tensor, free: Tensor, cloud: Cloud, models: Models) -> Tensor:
    """``sum_free log p_0(x_i) - log q_0(x_i)``: ``-> (B, C)``."""
    r = models.existence.log_p0_position(pos) - _log_q0(pos, cloud, models.sensor, models.existence, models.p_i)
    return torch.where(free, r, torch.zeros_like(r)).sum(-1)


def _draw_structure(log_pg: Tensor, u: Tensor) -> Tensor:
    """Row index from ``log_pg (B, C, G)`` by ``u (B, C)`` (eq. 19)."""
    return inverse_cdf(cdf(log_pg), u.unsqueeze(-1)).squeeze(-1)


def _draw_exists(e_prev: Tensor, u: Tensor, existence: GroupExistence) -> Tensor:
    """``e ~ p(e | e_prev)`` (eq. 25) from uniforms ``u`` of ``e_prev``'s shape."""
    p_alive = torch.where(e_prev, torch.full_like(u, 1.0 - existence.p_death), torch.full_like(u, existence.p_birth))
    return u < p_alive


def _select(mask: Tensor, new: Chain, old: Chain) -> Chain:
    """Chain-wise ``torch.where`` over every field; ``mask (B, C)``."""
    def pick(a: Tensor, b: Tensor) -> Tensor:
        m = mask.reshape(mask.shape + (1,) * (a.dim() - mask.dim()))
        return torch.where(m, a, b)
    return type(old)(*(pick(a, b) for a, b in zip(new, old)))


def _death_pos(existence: GroupExistence, like: Tensor) -> Tensor:
    """The position ``(2,)`` of ``x_death`` in ``like``'s dtype and device."""
    return existence.x_death[0::2].to(like)


# ----------------------------------------------------------------------------------------
# the moves (pure: noise in, no generator; compile-friendly)
# ----------------------------------------------------------------------------------------
def make_chain(j: Tensor, labels: Tensor, exists: Tensor, pos: Tensor, cloud: Cloud, z: Tensor, models: Models
               ) -> Chain:
    """A chain state ``(B, C, ...)`` with its caches from ``(j, g, e, x_p)`` (dead slots' positions
    are set to ``x_death``).
    """
    pm, S, obs, free = _predict(cloud, j, labels, exists, models)
    pos = torch.where(exists.unsqueeze(-1), pos, _death_pos(models.existence, pos))
    return Chain(j, labels, exists, pos, _log_lik(pos, exists, z, models.sensor),
                 _log_px(pos, pm, S, obs, free, models.existence), _gather(cloud.log_wq, j),
                 _birth_ratio(pos, free, cloud, models), pm, S, obs, free)


def joint_proposal(noise: Noise, cloud: Cloud, z: Tensor, models: Models) -> Chain:
    """Algorithm 1 steps 1-4 (eqs. 61-65) for every chain: the proposed state with its caches."""
    existence = models.existence
    use_alpha = noise["mix"] < models.p_a
    j = torch.where(use_alpha, inverse_cdf(cloud.cdf_alpha, noise["j"]), inverse_cdf(cloud.cdf_w, noise["j"]))
    g = _draw_structure(_gather(cloud.log_pg, j), noise["g"])
    labels = cloud.table[g]
    exists = _draw_exists(_gather(cloud.exists, j), noise["e"], existence)
    pm, S, obs, free = _predict(cloud, j, labels, exists, models)
    o = obs.to(pm.dtype)
    L = torch.linalg.cholesky(S * o.unsqueeze(-1) * o.unsqueeze(-2) + torch.diag_embed(1.0 - o))
    x_obs = pm + L @ noise["eps"]
    x_born = _draw_q0(noise, cloud, models.sensor, existence, models.p_i)
    pos = torch.where(obs.unsqueeze(-1), x_obs, torch.where(free.unsqueeze(-1), x_born, _death_pos(existence, pm)))
    log_lik = _log_lik(pos, exists, z, models.sensor)
    log_px = _log_px(pos, pm, S, obs, free, existence)
    return Chain(j, labels, exists, pos, log_lik, log_px, _gather(cloud.log_wq, j),
                 _birth_ratio(pos, free, cloud, models), pm, S, obs, free)


def joint_move(chain: Chain, noise: Noise, cloud: Cloud, z: Tensor, models: Models) -> tuple[Chain, Tensor]:
    """Algorithm 1 with the acceptance ratio ``rho_1`` of eq. 60 (module docstring).
    Returns the new chain and ``accepted (B, C)`` bool.
    """
    prop = joint_proposal(noise, cloud, z, models)
    log_rho = (prop.log_lik + prop.log_wq + prop.log_birth) - (chain.log_lik + chain.log_wq + chain.log_birth)
    acc = torch.log(noise["u"]) < log_rho
    return _select(acc, prop, chain), acc


def refine_move(chain: Chain, noise: Noise, cloud: Cloud, z: Tensor, models: Models
                ) -> tuple[Chain, Tensor, Tensor]:
    """Algorithm 2: the structure by ``rho_2``, then each slot's ``(x_i, e_i)`` by ``rho_3``
    (eq. 66; module docstring). Returns the chain, ``accepted_structure (B, C)`` bool and
    ``accepted_targets (B, C, K)`` bool.
    """
    existence, sensor = models.existence, models.sensor
    k = chain.pos.shape[-2]
    # -- structure (rho_2)
    g = _draw_structure(_gather(cloud.log_pg, chain.j), noise["g"])
    labels = cloud.table[g]
    pm, S, obs, free = _predict(cloud, chain.j, labels, chain.exists, models)
    log_px = _log_px(chain.pos, pm, S, obs, free, existence)
    acc_g = torch.log(noise["u_g"]) < log_px - chain.log_px
    prop = chain._replace(labels=labels, log_px=log_px, log_birth=_birth_ratio(chain.pos, free, cloud, models),
                          pm=pm, S=S, observed=obs, free=free)
    chain = _select(acc_g, prop, chain)
    # -- each target (rho_3)
    e_prev = _gather(cloud.exists, chain.j)
    x_born = _draw_q0(noise, cloud, sensor, existence, models.p_i)  # (B, C, K, 2)
    dead = _death_pos(existence, chain.pos)
    accs = []
    for i in range(k):
        onehot = torch.arange(k, device=chain.pos.device) == i
        e_i = _draw_exists(e_prev[..., i], noise["e"][..., i], existence)
        exists = torch.where(onehot, e_i.unsqueeze(-1), chain.exists)
        pm, S, obs, free = _predict(cloud, chain.j, chain.labels, exists, models)
        cm, cv = _conditional(chain.pos, pm, S, obs, i)
        x_i = torch.where(obs[..., i, None], cm + cv.sqrt().unsqueeze(-1) * noise["eps"][..., i, :],
                          torch.where(free[..., i, None], x_born[..., i, :], dead))
        pos = torch.where(onehot.unsqueeze(-1), x_i.unsqueeze(-2), chain.pos)
        log_q_fwd = _log_q_slot(x_i, cm, cv, obs[..., i], free[..., i], cloud, models)
        cm0, cv0 = _conditional(chain.pos, chain.pm, chain.S, chain.observed, i)
        log_q_rev = _log_q_slot(chain.pos[..., i, :], cm0, cv0, chain.observed[..., i], chain.free[..., i],
                                cloud, models)
        log_lik = _log_lik(pos, exists, z, sensor)
        log_px = _log_px(pos, pm, S, obs, free, existence)
        log_rho = (log_lik + log_px - log_q_fwd) - (chain.log_lik + chain.log_px - log_q_rev)
        acc = torch.log(noise["u_x"][..., i]) < log_rho
        prop = chain._replace(exists=exists, pos=pos, log_lik=log_lik, log_px=log_px,
                              log_birth=_birth_ratio(pos, free, cloud, models), pm=pm, S=S, observed=obs, free=free)
        chain = _select(acc, prop, chain)
        accs.append(acc)
    return chain, acc_g, torch.stack(accs, -1)


def _conditional(pos: Tensor, pm: Tensor, S: Tensor, obs: Tensor, i: int) -> tuple[Tensor, Tensor]:
    """Conditional of slot ``i``'s position given the other observed slots under the
    predictive ``N(pm, S)`` (per axis): mean ``(B, C, 2)``, variance ``(B, C)``. Through the
    precision ``P`` of the observed block: ``var = 1 / P_ii``,
    ``mean = x_i - (P d)_i / P_ii`` with ``d = (x - pm)`` on the observed slots.
    """
    o = obs.to(pos.dtype)
    Sm = S * o.unsqueeze(-1) * o.unsqueeze(-2) + torch.diag_embed(1.0 - o)
    P = torch.cholesky_inverse(torch.linalg.cholesky(Sm))
    d = (pos - pm) * o.unsqueeze(-1)
    Pd = P[..., i, :].unsqueeze(-2) @ d  # (B, C, 1, 2)
    pii = P[..., i, i]
    return pos[..., i, :] - Pd.squeeze(-2) / pii.unsqueeze(-1), 1.0 / pii


def _log_q_slot(x_i: Tensor, cm: Tensor, cv: Tensor, obs_i: Tensor, free_i: Tensor, cloud: Cloud,
                models: Models) -> Tensor:
    """``log q_i(x_i)``: conditional Gaussian if observed, ``q_0`` if a free birth, 0 (point
    mass) if dead: ``-> (B, C)``.
    """
    log_n = (-0.5 * (x_i - cm).square().sum(-1) / cv - torch.log(cv) - LOG_2PI)
    log_q0 = _log_q0(x_i.unsqueeze(-2), cloud, models.sensor, models.existence, models.p_i).squeeze(-1)
    return torch.where(obs_i, log_n, torch.where(free_i, log_q0, torch.zeros_like(log_n)))


# ----------------------------------------------------------------------------------------
# noise (eager)
# ----------------------------------------------------------------------------------------
def _birth_noise(shape: tuple[int, int, int], g: torch.Generator, *, dtype: torch.dtype,
                 device: torch.device | str | None) -> Noise:
    """Uniforms of the birth proposal ``q_0`` (eqs. 64-65): ``b_sel``, ``b_pix (B, C, K)``,
    ``b_xy (B, C, K, 2)``.
    """
    return {"b_sel": torch.rand(shape, generator=g, dtype=dtype, device=device),
            "b_pix": torch.rand(shape, generator=g, dtype=dtype, device=device),
            "b_xy": torch.rand(shape + (2,), generator=g, dtype=dtype, device=device)}


def draw_joint_noise(shape: tuple[int, int, int], *, generator: torch.Generator,
                     dtype: torch.dtype = torch.float64, device: torch.device | str | None = None) -> Noise:
    """Uniforms and normals of one joint draw for chains of ``shape = (B, C, K)``: ``mix``,
    ``j``, ``g``, ``u (B, C)``, ``e (B, C, K)``, ``eps (B, C, K, 2)`` and the birth uniforms.
    """
    b, c, k = shape
    g = generator
    noise = {"mix": torch.rand((b, c), generator=g, dtype=dtype, device=device),
             "j": torch.rand((b, c), generator=g, dtype=dtype, device=device),
             "g": torch.rand((b, c), generator=g, dtype=dtype, device=device),
             "e": torch.rand((b, c, k), generator=g, dtype=dtype, device=device),
             "eps": torch.randn((b, c, k, 2), generator=g, dtype=dtype, device=device),
             "u": torch.rand((b, c), generator=g, dtype=dtype, device=device)}
    noise.update(_birth_noise((b, c, k), g, dtype=dtype, device=device))
    return noise


def draw_refine_noise(shape: tuple[int, int, int], *, generator: torch.Generator,
                      dtype: torch.dtype = torch.float64, device: torch.device | str | None = None) -> Noise:
    """Uniforms and normals of one refinement sweep for chains of ``shape = (B, C, K)``:
    ``g``, ``u_g (B, C)``, ``e``, ``u_x (B, C, K)``, ``eps (B, C, K, 2)`` and the birth uniforms.
    """
    b, c, k = shape
    g = generator
    noise = {"g": torch.rand((b, c), generator=g, dtype=dtype, device=device),
             "u_g": torch.rand((b, c), generator=g, dtype=dtype, device=device),
             "e": torch.rand((b, c, k), generator=g, dtype=dtype, device=device),
             "eps": torch.randn((b, c, k, 2), generator=g, dtype=dtype, device=device),
             "u_x": torch.rand((b, c, k), generator=g, dtype=dtype, device=device)}
    noise.update(_birth_noise((b, c, k), g, dtype=dtype, device=device))
    return noise


# ----------------------------------------------------------------------------------------
# the step
# ----------------------------------------------------------------------------------------
def _predicted_positions(state: GroupState, models: Models, chunk: int = 512) -> Tensor:
    """``x~^j`` of eq. 62: each particle's positions predicted with its structure and existence
    unchanged, ``(B, N, K, 2)`` (chunks of particles bound the memory).
    """
    out = []
    pos = state.x[..., 0::2]
    for s in range(0, pos.shape[1], chunk):
        sl = slice(s, s + chunk)
        tr = models.motion.transition(pos[:, sl], state.labels[:, sl], state.labels[:, sl], state.exists[:, sl],
                                      state.exists[:, sl], existence=models.existence)
        pred = pairwise_kalman_predict(KalmanStats(state.w_mean[:, sl], state.w_cov[:, sl]), pos[:, sl], tr)
        out.append(torch.where(state.exists[:, sl].unsqueeze(-1), pred.position_mean,
                               _death_pos(models.existence, pos)))
    return torch.cat(out, 1)


def make_cloud(state: GroupState, z: Tensor, *, structure_prior: GroupStructurePrior, models: Models,
               settings: GroupMCMCSettings) -> Cloud:
    """Per-step quantities of the proposals (eqs. 19, 61-62, 65), eager."""
    sensor = models.sensor
    pos = state.x[..., 0::2]
    b, _, k = state.exists.shape
    table = group_structures(k, device=pos.device)
    log_pg = structure_prior.log_probs(structure_index(state.labels), pos, state.exists)
    log_w = torch.log_softmax(state.log_w.to(torch.float64), -1)
    pred = _predicted_positions(state, models)
    log_alpha = torch.log_softmax(log_w + _log_lik(pred, state.exists, z, sensor).to(torch.float64), -1)
    log_q = torch.log(settings.p_a * log_alpha.exp() + (1.0 - settings.p_a) * log_w.exp())  # eq. 61
    zb = z.to(torch.bool)
    prev = zb if state.frame_prev is None else state.frame_prev.to(torch.bool)
    near = F.max_pool2d(prev.to(torch.float64).unsqueeze(1), 3, stride=1, padding=1).squeeze(1) > 0
    beta = (zb & near).reshape(b, -1)
    return Cloud(pos, state.labels, state.exists, state.w_mean, state.w_cov, log_pg,
                 cdf(log_alpha), cdf(log_w),
                 (log_w - log_q).to(pos.dtype), beta, beta.to(torch.float64).cumsum(-1), beta.sum(-1), table)


def _kalman_at_keep(cloud: Cloud, j: Tensor, labels: Tensor, exists: Tensor, pos: Tensor, models: Models,
                    marginalise: bool, generator: torch.Generator, chunk: int = 512) -> tuple[Tensor, Tensor]:
    """Kalman statistics at ``t`` of kept states ``(B, N, ...)`` (eqs. 53-57); sampled with zero
    covariance when not marginalising.
    """
    means, covs = [], []
    for s in range(0, j.shape[1], chunk):
        sl = slice(s, s + chunk)
        jj = j[:, sl]
        pos_prev = _gather(cloud.pos, jj)
        tr = models.motion.transition(pos_prev, _gather(cloud.labels, jj), labels[:, sl], _gather(cloud.exists, jj),
                                      exists[:, sl], existence=models.existence)
        pred = pairwise_kalman_predict(KalmanStats(_gather(cloud.w_mean, jj), _gather(cloud.w_cov, jj)), pos_prev, tr)
        _, st = pairwise_kalman_update(pred, pos[:, sl])
        mean, cov = st.mean, st.cov
        if not marginalise:
            d = cov.shape[-1]
            jitter = 1e-9 * (1.0 + torch.diagonal(cov, dim1=-2, dim2=-1).amax(-1))[..., None, None]
            L = torch.linalg.cholesky(cov + jitter * torch.eye(d, dtype=cov.dtype, device=cov.device))
            eps = torch.randn(mean.shape, generator=generator, dtype=mean.dtype, device=mean.device)
            mean = mean + eps @ L.transpose(-1, -2)
            cov = torch.zeros_like(cov)
        means.append(mean)
        covs.append(cov)
    return torch.cat(means, 1), torch.cat(covs, 1)


def group_mcmc_step(state: GroupState, z: Tensor, *, motion: VirtualLeaderMotion, sensor: ThresholdedPixels,
                    settings: GroupMCMCSettings = GroupMCMCSettings(), generator: torch.Generator,
                    existence: GroupExistence, structure_prior: GroupStructurePrior,
                    kernels: dict[str, Callable[..., Any]] | None = None) -> tuple[GroupState, StepInfo]:
    """One time step of the marginalised MCMC-based particle filter (module docstring).

    Parameters
    ----------
    state : GroupState at ``t - 1`` (``x (B, N, K, 4)``).
    z : (B, H, W) binary frame at ``t``.
    motion, sensor, existence, structure_prior : the models (eqs. 13, 41, 25/33, 19).
    settings : GroupMCMCSettings; generator : the only source of randomness (eager draws).
    kernels : ``{"joint": f, "refine": f}``, :func:`joint_move` / :func:`refine_move` with the
        models bound, ``f(chain, noise, cloud, z)`` (compiled ones,
        ``GroupMCMCFilter(compile_step=True)``); default eager.

    Returns
    -------
    state : GroupState at ``t`` (chain-major particles, equal weights).
    info : ``acceptance (B,)`` over all MH decisions; ``extras``: ``acceptance_joint``,
        ``acceptance_structure``, ``acceptance_target`` (B,) (NaN where the move never ran),
        ``structure_prob (B, Bell(K))``, ``exists_prob (B, K)``, ``expected_count (B,)``.
    """
    b, n, k, _ = state.x.shape
    settings.check(n)
    c = settings.num_chains
    models = Models(motion, sensor, existence, float(settings.p_i), float(settings.p_a))
    kernels = kernels or _bind(models)
    dtype, dev = state.x.dtype, state.x.device
    cloud = make_cloud(state, z, structure_prior=structure_prior, models=models, settings=settings)
    chain = joint_proposal(draw_joint_noise((b, c, k), generator=generator, dtype=dtype, device=dev), cloud, z, models)
    per_chain = n // c
    acc = {name: state.x.new_zeros(b) for name in ("joint", "structure", "target")}
    cnt = {name: state.x.new_zeros(b) for name in acc}
    kept = []
    for m in range(1, settings.burn_in + settings.thinning * per_chain + 1):
        if float(torch.rand((), generator=generator, dtype=torch.float64)) < settings.xi:
            noise = draw_joint_noise((b, c, k), generator=generator, dtype=dtype, device=dev)
            chain, a = kernels["joint"](chain, noise, cloud, z)
            acc["joint"] += a.to(dtype).sum(1)
            cnt["joint"] += c
        else:
            noise = draw_refine_noise((b, c, k), generator=generator, dtype=dtype, device=dev)
            chain, a_g, a_x = kernels["refine"](chain, noise, cloud, z)
            acc["structure"] += a_g.to(dtype).sum(1)
            cnt["structure"] += c
            acc["target"] += a_x.to(dtype).sum((1, 2))
            cnt["target"] += c * k
        if m > settings.burn_in and (m - settings.burn_in) % settings.thinning == 0:
            kept.append((chain.j, chain.labels, chain.exists, chain.pos))
    j, labels, exists, pos = (torch.stack(t, 2).flatten(1, 2) for t in zip(*kept))  # (B, C * N/C, ...)
    w_mean, w_cov = _kalman_at_keep(cloud, j, labels, exists, pos, models, settings.marginalise, generator)
    vel = w_mean[..., :k].transpose(-1, -2)  # (B, N, K, 2)
    x = torch.stack([pos[..., 0], vel[..., 0], pos[..., 1], vel[..., 1]], -1)
    new = GroupState(x, x.new_full((b, n), -math.log(n)), exists, labels, w_mean, w_cov, z.to(torch.bool))
    g = group_structures(k, device=x.device).shape[0]
    structure_prob = F.one_hot(structure_index(labels), g).to(x.dtype).mean(1)
    exists_prob = exists.to(x.dtype).mean(1)
    extras = {f"acceptance_{name}": acc[name] / cnt[name] for name in acc}
    extras.update(structure_prob=structure_prob, exists_prob=exists_prob, expected_count=exists_prob.sum(-1))
    acceptance = (acc["joint"] + acc["structure"] + acc["target"]) / (cnt["joint"] + cnt["structure"] + cnt["target"])
    return new, StepInfo.make(acceptance, acceptance=acceptance, extras=extras)


def _bind(models: Models) -> dict[str, Callable[..., Any]]:
    """The two moves with the models bound: ``{"joint": f(chain, noise, cloud, z), "refine": ...}``."""
    def joint(chain: Chain, noise: Noise, cloud: Cloud, z: Tensor) -> tuple[Chain, Tensor]:
        return joint_move(chain, noise, cloud, z, models)

    def refine(chain: Chain, noise: Noise, cloud: Cloud, z: Tensor) -> tuple[Chain, Tensor, Tensor]:
        return refine_move(chain, noise, cloud, z, models)

    return {"joint": joint, "refine": refine}


# ----------------------------------------------------------------------------------------
# the filter
# ----------------------------------------------------------------------------------------
class GroupMCMCFilter(Filter):
    """Marginalised MCMC-based particle filter for coordinated groups (paper 004, sec. 4).

    Parameters
    ----------
    motion : VirtualLeaderMotion (eqs. 1-16); sensor : ThresholdedPixels (eqs. 39-41) or
        a pixel sensor with ``shape``, ``pixel_size``, ``position_index``.
    num_particles : N, a multiple of ``num_chains``.
    existence : GroupExistence (eq. 25, births eqs. 29-37); structure_prior :
        GroupStructurePrior (eq. 19).
    num_chains, burn_in, thinning, xi, p_a, p_i, marginalise : :class:`GroupMCMCSettings`.
    compile_step : compile the joint move and the refinement sweep
        (``torch.compile(fullgraph=True)``; noise drawn eagerly, so compiled == eager).

    Example
    -------
    >>> scn = group_merge(2, generator=torch.Generator().manual_seed(0))    # doctest: +SKIP
    >>> filt = GroupMCMCFilter(scn.motion, scn.sensor, 400, existence=scn.existence,
    ...                        structure_prior=scn.structure_prior, num_chains=20, burn_in=50)
    >>> res = filt(scn.frames, init=filt.init_inactive(2), generator=g)     # doctest: +SKIP
    >>> res.info.extras["structure_prob"].shape                               # (T, B, 15)
    """

    # Contract deviation (module docstring): the group models replace Filter's MotionModel and
    # BirthDeath, and the filtering state is a GroupState, not a ParticleState; hence the
    # targeted ``type: ignore[assignment]`` / ``[override]`` / ``[arg-type]`` in this class.
    motion: VirtualLeaderMotion  # type: ignore[assignment]
    sensor: ThresholdedPixels
    existence: GroupExistence  # type: ignore[assignment]

    def __init__(self, motion: VirtualLeaderMotion, sensor: ThresholdedPixels, num_particles: int, *,
                 existence: GroupExistence, structure_prior: GroupStructurePrior, num_chains: int = 1,
                 burn_in: int = 1000, thinning: int = 6, xi: float = 0.75, p_a: float = 0.5, p_i: float = 0.01,
                 marginalise: bool = True, compile_step: bool = False) -> None:
        nn.Module.__init__(self)
        if not isinstance(motion, VirtualLeaderMotion):
            raise ValueError(f"motion must be a VirtualLeaderMotion, got {type(motion).__name__}")
        if not all(hasattr(sensor, a) for a in ("shape", "pixel_size", "position_index", "log_likelihood")):
            raise ValueError(f"sensor must be a pixel sensor (ThresholdedPixels), got {type(sensor).__name__}")
        if not isinstance(existence, GroupExistence):
            raise ValueError(f"existence must be a GroupExistence, got {type(existence).__name__}")
        if not isinstance(structure_prior, GroupStructurePrior):
            raise ValueError(f"structure_prior must be a GroupStructurePrior, got {type(structure_prior).__name__}")
        if not isinstance(compile_step, bool):
            raise ValueError(f"compile_step must be a bool, got {compile_step!r}")
        self.motion, self.sensor, self.existence, self.structure_prior = motion, sensor, existence, structure_prior
        self.num_particles = check_positive_int(num_particles, "num_particles")
        self.settings = GroupMCMCSettings(num_chains, burn_in, thinning, xi, p_a, p_i, marginalise)
        self.settings.check(self.num_particles)
        self.compile_step = compile_step
        self._compiled_moves: dict[str, Callable[..., Any]] | None = None

    def kernels(self) -> dict[str, Callable[..., Any]] | None:
        """The moves passed to :func:`group_mcmc_step`: ``None`` (its eager ones) unless
        ``compile_step``, then ``{"joint": f, "refine": f}`` compiled once
        (:func:`~torchmcmcpf.filters.base.compile_kernel`), ``f(chain, noise, cloud, z)``.
        """
        if not self.compile_step:
            return None
        if self._compiled_moves is None:
            models = Models(self.motion, self.sensor, self.existence, float(self.settings.p_i),
                            float(self.settings.p_a))
            self._compiled_moves = {name: compile_kernel(fn) for name, fn in _bind(models).items()}
        return self._compiled_moves

    def init(self, particles: Tensor, exists: Tensor | None = None,  # type: ignore[override]
             labels: Tensor | None = None) -> GroupState:
        """Wrap initial particles ``(B, N, K, 4)`` (``[x, vx, y, vy]``; ``exists (B, N, K)``,
        default all inactive; ``labels (B, N, K)``, default each slot its own group) into a
        GroupState with exact (zero-covariance) Kalman statistics: velocities from
        ``particles``, leaders at ``v_death``.
        """
        check_shape(particles, "init", (None, self.num_particles, None, 4))
        if not particles.is_floating_point() or not bool(torch.isfinite(particles).all()):
            raise ValueError("init must be a finite floating tensor (B, N, K, 4)")
        b, n, k, _ = particles.shape
        if exists is None:
            exists = torch.zeros((b, n, k), dtype=torch.bool, device=particles.device)
        check_shape(exists, "init.exists", (b, n, k))
        if labels is None:
            labels = torch.arange(k, device=particles.device).expand(b, n, k)
        check_shape(labels, "init.labels", (b, n, k))
        exists = exists.to(torch.bool)
        x = torch.where(exists.unsqueeze(-1), particles, self.existence.x_death.to(particles))
        st = pairwise_kalman_init((b, n), k, existence=self.existence, dtype=particles.dtype, device=particles.device)
        w_mean = st.mean.clone()
        w_mean[..., :k] = x[..., 1::2].transpose(-1, -2)
        log_w = particles.new_full((b, n), -math.log(n))
        return GroupState(x, log_w, exists, labels.to(torch.int64).contiguous(), w_mean, st.cov)

    def init_inactive(self, batch_size: int, num_slots: int = 4, *, dtype: torch.dtype = torch.float64,
                      device: torch.device | str | None = None) -> GroupState:
        """``K = num_slots`` slots, all inactive in every particle of every run (paper 004 sec. 5)."""
        b = check_positive_int(batch_size, "batch_size")
        k = check_positive_int(num_slots, "num_slots")
        return self.init(torch.zeros((b, self.num_particles, k, 4), dtype=dtype, device=device))

    def _check(self, state: GroupState, z: Tensor, name: str = "z") -> None:
        if not isinstance(state, GroupState):
            raise ValueError(f"state must be a GroupState, got {type(state).__name__}")
        check_shape(z, name, (state.batch_size,) + tuple(self.sensor.shape))
        self.sensor.validate(z, state.batch_size, name)

    def step(self, state: GroupState, z: Tensor, *,  # type: ignore[override]
             generator: torch.Generator) -> tuple[GroupState, StepInfo]:
        """Advance by one frame ``z (B, H, W)``."""
        check_generator(generator)
        self._check(state, z)
        return self._step(state, z, generator)

    def _step(self, state: GroupState, z: Tensor,  # type: ignore[override]
              generator: torch.Generator) -> tuple[GroupState, StepInfo]:
        """One call of :func:`group_mcmc_step` with this filter's models and settings."""
        return group_mcmc_step(state, z, motion=self.motion, sensor=self.sensor, settings=self.settings,
                               generator=generator, existence=self.existence, structure_prior=self.structure_prior,
                               kernels=self.kernels())

    def forward(self, measurements: Tensor, *, init: GroupState,  # type: ignore[override]
                generator: torch.Generator, progress: bool | None = None) -> FilterResult:
        """Filter frames ``(T, B, H, W)`` from ``init`` (a GroupState, e.g. :meth:`init_inactive`).

        Returns FilterResult: ``mean (T, B, K, 4)`` (each slot's mean given existence),
        ``exists_prob (T, B, K)``, ``info.extras`` stacked ``(T, B, ...)``.
        """
        check_generator(generator)
        if not torch.is_tensor(measurements) or measurements.dim() != 4 or measurements.shape[0] == 0:
            raise ValueError(f"measurements must be frames (T, B, H, W) with T >= 1, got "
                             f"{getattr(measurements, 'shape', type(measurements).__name__)}")
        if not isinstance(init, GroupState):
            raise ValueError(f"init must be a GroupState (filt.init / filt.init_inactive), got {type(init).__name__}")
        self._check(init, measurements[0], "measurements[0]")
        self.sensor.validate(measurements.flatten(0, 1), None, "measurements")
        state = init
        steps: Any = range(measurements.shape[0])
        if progress:
            from tqdm.auto import tqdm

            steps = tqdm(steps, desc=type(self).__name__, leave=False)
        means, infos, probs = [], [], []
        for t in steps:
            state, info = self._step(state, measurements[t], generator)
            est = existence_estimate(state, x_death=self.existence.x_death)  # type: ignore[arg-type]  # GroupState
            means.append(est.mean)
            probs.append(est.exists_prob)
            infos.append(info)
        info = stack_infos(infos)
        # the result holds the GroupState (resume with init=result.state)
        return FilterResult(torch.stack(means), state, info,  # type: ignore[arg-type]
                            info.log_evidence.sum(0), torch.stack(probs))

    def estimate(self, state: GroupState) -> Tensor:  # type: ignore[override]
        """Each slot's mean given existence, ``(B, K, 4)`` (``x_death`` where no particle has it)."""
        return existence_estimate(state, x_death=self.existence.x_death).mean  # type: ignore[arg-type]
