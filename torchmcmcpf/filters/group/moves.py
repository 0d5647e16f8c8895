"""The group filter's moves as pure functions (paper 004 Algorithm 1, eq. 60; Algorithm 2, eq. 66;
the past and window birth moves of issue 23): noise in, no generator, compile-friendly; and the
containers they work on (the chain state, the previous cloud, the bound models).

The maths, the moves' targets and acceptance ratios: the docstring of :mod:`torchmcmcpf.filters.group`.
"""

from __future__ import annotations

import math
from typing import NamedTuple

import torch
import torch.nn.functional as F

from ..._native.select import where
from ...kernels.mh import mh_accept, mh_select
from ...models.group import (
    GroupExistence,
    GroupStructurePrior,
    KalmanStats,
    VirtualLeaderMotion,
    pairwise_kalman_predict,
    pairwise_kalman_update,
)
from ...models.sensors.pixels import ThresholdedPixels
from ...resampling import cdf, inverse_cdf
from ...typing import Tensor
from .noise import GroupJointNoise, GroupPastNoise, GroupRefineNoise, GroupWindowBirthNoise

__all__ = ["GroupView", "Cloud", "Prev", "Chain", "Models", "make_chain", "joint_proposal", "joint_move",
           "refine_move", "past_move", "window_birth_move"]

LOG_2PI = math.log(2 * math.pi)


# ----------------------------------------------------------------------------------------
# the containers of one step
# ----------------------------------------------------------------------------------------
class GroupView(NamedTuple):
    """A state's fields unpacked from its ``ParticleState`` (:func:`unpack`), ``(B, N, ...)``:
    the particles at ``t - 1`` (``pos``, ``g``, ``labels``, ``exists``, ``w_mean``, ``w_cov``,
    ``log_w``), ``frames (B, F, H, W)`` (the last ``F`` frames, the window's last), and the
    path: the anchor (``anchor_*``) and the window ``win_* (B, N, W, ...)`` of ``W`` past
    steps with their terms ``win_log (B, N, W)`` (``W = 0`` and the anchor the particles
    themselves without a lag).
    """

    pos: Tensor
    g: Tensor
    labels: Tensor
    exists: Tensor
    w_mean: Tensor
    w_cov: Tensor
    log_w: Tensor
    frames: Tensor
    anchor_pos: Tensor
    anchor_g: Tensor
    anchor_labels: Tensor
    anchor_exists: Tensor
    anchor_w_mean: Tensor
    anchor_w_cov: Tensor
    win_pos: Tensor
    win_g: Tensor
    win_labels: Tensor
    win_exists: Tensor
    win_log: Tensor


class Cloud(NamedTuple):
    """The previous particles and the per-step quantities of the proposals (eager, once per
    step): ``view`` (:class:`GroupView`); ``log_pg (B, N, G)`` eq. 19 for every structure;
    ``log_win (B, N)`` the window's terms; ``cdf_alpha``, ``cdf_w (B, N)`` float64 cumulative
    weights of ``alpha`` and ``w``; ``log_wq (B, N)`` ``log w_j - log q(j)`` (eq. 61);
    ``beta (B, HW)`` bool, the pixels of the birth proposal, ``cdf_beta (B, HW)``,
    ``n_obs (B,)``; ``table (G, K)`` the structures; the window birth's pixels, per window
    step ``s``, of ``Z_s`` with a detection of ``Z_{s+1}`` within two pixels, ``pair (B, W,
    HW)`` bool, ``cdf_pair (B, W, HW)``, ``n_pair (B, W)``.
    """

    view: GroupView
    log_pg: Tensor
    log_win: Tensor
    cdf_alpha: Tensor
    cdf_w: Tensor
    log_wq: Tensor
    beta: Tensor
    cdf_beta: Tensor
    n_obs: Tensor
    table: Tensor
    pair: Tensor
    cdf_pair: Tensor
    n_pair: Tensor


class Prev(NamedTuple):
    """A chain's past ``(B, C, ...)``: the positions, structure (``g`` row, ``labels``),
    existence and Kalman statistics at ``t - 1``; ``log_pg (B, C, G)``, ``p(g_t | .)`` of
    every structure; the window positions ``win_pos (B, C, W, K, 2)`` at ``t - W .. t - 1``
    and their terms ``log_win (B, C)``; the window's existence ``win_exists (B, C, W, K)``.
    """

    pos: Tensor
    g: Tensor
    labels: Tensor
    exists: Tensor
    w_mean: Tensor
    w_cov: Tensor
    log_pg: Tensor
    win_pos: Tensor
    log_win: Tensor
    win_exists: Tensor


class Chain(NamedTuple):
    """Chain states ``(B, C, ...)``: ancestor ``j``, structure ``g`` (row) and ``labels``,
    ``exists``, ``pos (B, C, K, 2)``; cached ``log_lik`` (eq. 40), ``log_px``
    (``log p(x | past, g, e)``), ``log_wq`` (``log w_j - log q(j)``), ``log_birth``
    (``sum_free log p_0 - log q_0``); the configuration's predictive ``pm (B, C, K, 2)``,
    ``S (B, C, K, K)``, ``observed``, ``free``; and its :class:`Prev`.
    """

    j: Tensor
    g: Tensor
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
    prev: Prev


class Models(NamedTuple):
    """The models and the proposal constants a move needs (bound, not traced)."""

    motion: VirtualLeaderMotion
    sensor: ThresholdedPixels
    existence: GroupExistence
    structure_prior: GroupStructurePrior
    p_i: float
    p_a: float
    past_step: tuple[float, float] = (10.0, 5.0)


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


def _death_pos(existence: GroupExistence, like: Tensor) -> Tensor:
    """The position ``(2,)`` of ``x_death`` in ``like``'s dtype and device."""
    return existence.x_death[0::2].to(like)


def _predict(prev: Prev, labels: Tensor, exists: Tensor, models: Models) -> tuple[Tensor, Tensor, Tensor, Tensor]:
    """Kalman predictive of the positions of configuration ``(g, e)`` after ``prev``:
    ``pm (B, C, K, 2)``, ``S (B, C, K, K)``, ``observed``, ``free (B, C, K)`` (eqs. 47, 51-52).
    """
    tr = models.motion.transition(prev.pos, prev.labels, labels, prev.exists, exists, existence=models.existence)
    pred = pairwise_kalman_predict(KalmanStats(prev.w_mean, prev.w_cov), prev.pos, tr)
    # contiguous: a chain's fields keep one layout, eager or compiled (no recompilation)
    return pred.position_mean.contiguous(), pred.position_cov.contiguous(), tr.observed, tr.free_birth


def _log_px(pos: Tensor, pm: Tensor, S: Tensor, obs: Tensor, free: Tensor, existence: GroupExistence) -> Tensor:
    """``log p(x | past, g, e)`` (eq. 44): Gaussian over the observed slots (both axes) plus
    ``log p_0`` of the free births: ``-> (B, C)``.
    """
    o = obs.to(pos.dtype)
    Sm = S * o.unsqueeze(-1) * o.unsqueeze(-2) + torch.diag_embed(1.0 - o)
    L = torch.linalg.cholesky(Sm)
    y = torch.linalg.solve_triangular(L, (pos - pm) * o.unsqueeze(-1), upper=False)
    logdet = torch.log(torch.diagonal(L, dim1=-2, dim2=-1)).sum(-1)
    log_g = -0.5 * y.square().sum((-1, -2)) - 2 * logdet - o.sum(-1) * LOG_2PI
    log_p0 = where(free, existence.log_p0_position(pos), torch.zeros_like(pos[..., 0])).sum(-1)
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
    q = where(n > 0, p_i * log_p0.exp() + (1 - p_i) * phi, log_p0.exp())
    return where(torch.isfinite(log_p0), q.log(), log_p0)


def _draw_q0(noise: GroupJointNoise | GroupRefineNoise, cloud: Cloud, sensor: ThresholdedPixels,
             existence: GroupExistence, p_i: float) -> Tensor:
    """Positions from ``q_0`` (eqs. 64-65): ``(B, C, K, 2)`` from the birth noise (pixels by
    the shared inverse CDF).
    """
    uniform = existence.uniform_position(noise.b_xy)
    b = noise.b_pix.shape[0]
    idx = inverse_cdf(cloud.cdf_beta, noise.b_pix.reshape(b, -1)).reshape(noise.b_pix.shape)
    w = sensor.shape[1]
    pix = torch.stack([(idx % w).to(noise.b_xy.dtype), (idx // w).to(noise.b_xy.dtype)], -1)
    in_pixel = (pix + noise.b_xy) * sensor.pixel_size
    n = cloud.n_obs.reshape((-1,) + (1,) * (noise.b_sel.dim() - 1))
    use_uniform = (noise.b_sel < p_i) | (n == 0)
    return where(use_uniform.unsqueeze(-1), uniform, in_pixel)


def _birth_ratio(pos: Tensor, free: Tensor, cloud: Cloud, models: Models) -> Tensor:
    """``sum_free log p_0(x_i) - log q_0(x_i)``: ``-> (B, C)``."""
    r = models.existence.log_p0_position(pos) - _log_q0(pos, cloud, models.sensor, models.existence, models.p_i)
    return where(free, r, torch.zeros_like(r)).sum(-1)


def _draw_structure(log_pg: Tensor, u: Tensor) -> Tensor:
    """Row index from ``log_pg (B, C, G)`` by ``u (B, C)`` (eq. 19)."""
    return inverse_cdf(cdf(log_pg), u.unsqueeze(-1)).squeeze(-1)


def _path_step(stats: KalmanStats, pos_p: Tensor, g_p: Tensor, lab_p: Tensor, ex_p: Tensor, pos: Tensor, g: Tensor,
               lab: Tensor, ex: Tensor, z: Tensor, models: Models) -> tuple[Tensor, KalmanStats]:
    """One step of a particle's path: its term of the target, ``log p(x_s | x_{0:s-1}, g, e)
    + log p(g_s | x_{s-1}, g_{s-1}, e_{s-1}) + log p(Z_s | x_s, e_s)`` (eqs. 19, 44, 40; the
    existence prior, which the past move does not change, left out), and the Kalman
    statistics at ``s``. Leading dims ``(B, *S)``.
    """
    tr = models.motion.transition(pos_p, lab_p, lab, ex_p, ex, existence=models.existence)
    log_pred, stats = pairwise_kalman_update(pairwise_kalman_predict(stats, pos_p, tr), pos)
    log_p0 = where(tr.free_birth, models.existence.log_p0_position(pos), torch.zeros_like(pos[..., 0])).sum(-1)
    log_pg = models.structure_prior.log_probs(g_p, pos_p, ex_p)
    log_g = torch.gather(log_pg, -1, g.unsqueeze(-1)).squeeze(-1)
    return log_pred + log_p0 + log_g + _log_lik(pos, ex, z, models.sensor), stats


def _past(j: Tensor, win_pos: Tensor, cloud: Cloud, models: Models, win_exists: Tensor | None = None) -> Prev:
    """The past of chains with ancestors ``j (B, C)``, window positions ``win_pos (B, C, W,
    K, 2)`` and existence ``win_exists (B, C, W, K)`` (default the ancestor's): the Kalman
    filter re-run from the anchor through the window (:class:`Prev`).
    """
    v = cloud.view
    stats = KalmanStats(_gather(v.anchor_w_mean, j), _gather(v.anchor_w_cov, j))
    pos, g, lab, ex = (_gather(t, j) for t in (v.anchor_pos, v.anchor_g, v.anchor_labels, v.anchor_exists))
    win_g, win_lab = (_gather(t, j) for t in (v.win_g, v.win_labels))
    win_ex = _gather(v.win_exists, j) if win_exists is None else win_exists
    log_win = torch.zeros_like(pos[..., 0, 0])
    off = v.frames.shape[1] - win_pos.shape[2]  # the window's frames are the last W
    for s in range(win_pos.shape[2]):  # the window's steps (time, not particles)
        term, stats = _path_step(stats, pos, g, lab, ex, win_pos[:, :, s], win_g[:, :, s], win_lab[:, :, s],
                                 win_ex[:, :, s], v.frames[:, off + s], models)
        log_win = log_win + term
        pos, g, lab, ex = win_pos[:, :, s], win_g[:, :, s], win_lab[:, :, s], win_ex[:, :, s]
    log_pg = models.structure_prior.log_probs(g, pos, ex)
    return Prev(pos, g, lab, ex, stats.mean, stats.cov, log_pg, win_pos, log_win, win_ex)


def _prev_of(cloud: Cloud, j: Tensor) -> Prev:
    """The past of chains whose ancestors are ``j (B, C)``, as the cloud holds it."""
    v = cloud.view
    return Prev(*(_gather(t, j) for t in (v.pos, v.g, v.labels, v.exists, v.w_mean, v.w_cov, cloud.log_pg,
                                          v.win_pos, cloud.log_win, v.win_exists)))


# ----------------------------------------------------------------------------------------
# the moves (pure: noise in, no generator; compile-friendly)
# ----------------------------------------------------------------------------------------
def make_chain(j: Tensor, g: Tensor, exists: Tensor, pos: Tensor, cloud: Cloud, z: Tensor, models: Models,
               win_pos: Tensor | None = None, win_exists: Tensor | None = None) -> Chain:
    """A chain state ``(B, C, ...)`` with its caches from ``(j, g, e, x_p)`` and, optionally,
    its window ``win_pos (B, C, W, K, 2)`` and ``win_exists (B, C, W, K)`` (default the
    ancestor's); dead slots' positions are set to ``x_death``.
    """
    if win_pos is None and win_exists is not None:
        win_pos = _gather(cloud.view.win_pos, j)
    prev = _prev_of(cloud, j) if win_pos is None else _past(j, win_pos, cloud, models, win_exists)
    labels = cloud.table[g]
    pm, S, obs, free = _predict(prev, labels, exists, models)
    pos = where(exists.unsqueeze(-1), pos, _death_pos(models.existence, pos))
    return Chain(j, g, labels, exists, pos, _log_lik(pos, exists, z, models.sensor),
                 _log_px(pos, pm, S, obs, free, models.existence), _gather(cloud.log_wq, j),
                 _birth_ratio(pos, free, cloud, models), pm, S, obs, free, prev)


def joint_proposal(noise: GroupJointNoise, cloud: Cloud, z: Tensor, models: Models) -> Chain:
    """Algorithm 1 steps 1-4 (eqs. 61-65) for every chain: the proposed state with its caches."""
    existence = models.existence
    use_alpha = noise.mix < models.p_a
    j = where(use_alpha, inverse_cdf(cloud.cdf_alpha, noise.j), inverse_cdf(cloud.cdf_w, noise.j))
    prev = _prev_of(cloud, j)
    g = _draw_structure(prev.log_pg, noise.g)
    labels = cloud.table[g]
    exists = existence.draw_exists(prev.exists, noise.e)
    pm, S, obs, free = _predict(prev, labels, exists, models)
    o = obs.to(pm.dtype)
    L = torch.linalg.cholesky(S * o.unsqueeze(-1) * o.unsqueeze(-2) + torch.diag_embed(1.0 - o))
    x_obs = pm + L @ noise.eps
    x_born = _draw_q0(noise, cloud, models.sensor, existence, models.p_i)
    pos = where(obs.unsqueeze(-1), x_obs, where(free.unsqueeze(-1), x_born, _death_pos(existence, pm)))
    return Chain(j, g, labels, exists, pos, _log_lik(pos, exists, z, models.sensor),
                 _log_px(pos, pm, S, obs, free, existence), _gather(cloud.log_wq, j),
                 _birth_ratio(pos, free, cloud, models), pm, S, obs, free, prev)


def joint_move(chain: Chain, noise: GroupJointNoise, cloud: Cloud, z: Tensor, models: Models) -> tuple[Chain, Tensor]:
    """Algorithm 1 with the acceptance ratio ``rho_1`` of eq. 60 (package docstring).
    Returns the new chain and ``accepted (B, C)`` bool.
    """
    prop = joint_proposal(noise, cloud, z, models)
    log_rho = (prop.log_lik + prop.log_wq + prop.log_birth) - (chain.log_lik + chain.log_wq + chain.log_birth)
    acc = mh_accept(log_rho, noise.u)
    return mh_select(acc, prop, chain), acc


def refine_move(chain: Chain, noise: GroupRefineNoise, cloud: Cloud, z: Tensor, models: Models
                ) -> tuple[Chain, Tensor, Tensor]:
    """Algorithm 2: the structure by ``rho_2``, then each slot's ``(x_i, e_i)`` by ``rho_3``
    (eq. 66; package docstring). Returns the chain, ``accepted_structure (B, C)`` bool and
    ``accepted_targets (B, C, K)`` bool.
    """
    existence, sensor = models.existence, models.sensor
    k = chain.pos.shape[-2]
    prev = chain.prev
    # -- structure (rho_2)
    g = _draw_structure(prev.log_pg, noise.g)
    labels = cloud.table[g]
    pm, S, obs, free = _predict(prev, labels, chain.exists, models)
    log_px = _log_px(chain.pos, pm, S, obs, free, existence)
    acc_g = mh_accept(log_px - chain.log_px, noise.u_g)
    prop = chain._replace(g=g, labels=labels, log_px=log_px, log_birth=_birth_ratio(chain.pos, free, cloud, models),
                          pm=pm, S=S, observed=obs, free=free)
    chain = mh_select(acc_g, prop, chain)
    # -- each target (rho_3)
    x_born = _draw_q0(noise, cloud, sensor, existence, models.p_i)  # (B, C, K, 2)
    dead = _death_pos(existence, chain.pos)
    accs = []
    for i in range(k):
        onehot = torch.arange(k, device=chain.pos.device) == i
        e_i = existence.draw_exists(prev.exists[..., i], noise.e[..., i])
        exists = where(onehot, e_i.unsqueeze(-1), chain.exists)
        pm, S, obs, free = _predict(prev, chain.labels, exists, models)
        cm, cv = _conditional(chain.pos, pm, S, obs, i)
        x_i = where(obs[..., i, None], cm + cv.sqrt().unsqueeze(-1) * noise.eps[..., i, :],
                          where(free[..., i, None], x_born[..., i, :], dead))
        pos = where(onehot.unsqueeze(-1), x_i.unsqueeze(-2), chain.pos)
        log_q_fwd = _log_q_slot(x_i, cm, cv, obs[..., i], free[..., i], cloud, models)
        cm0, cv0 = _conditional(chain.pos, chain.pm, chain.S, chain.observed, i)
        log_q_rev = _log_q_slot(chain.pos[..., i, :], cm0, cv0, chain.observed[..., i], chain.free[..., i],
                                cloud, models)
        log_lik = _log_lik(pos, exists, z, sensor)
        log_px = _log_px(pos, pm, S, obs, free, existence)
        log_rho = (log_lik + log_px - log_q_fwd) - (chain.log_lik + chain.log_px - log_q_rev)
        acc = mh_accept(log_rho, noise.u_x[..., i])
        prop = chain._replace(exists=exists, pos=pos, log_lik=log_lik, log_px=log_px,
                              log_birth=_birth_ratio(pos, free, cloud, models), pm=pm, S=S, observed=obs, free=free)
        chain = mh_select(acc, prop, chain)
        accs.append(acc)
    return chain, acc_g, torch.stack(accs, -1)


def past_move(chain: Chain, noise: GroupPastNoise, cloud: Cloud, z: Tensor, models: Models) -> tuple[Chain, Tensor]:
    """One slot's live positions at ``t - W .. t`` translated by ``a + b (s - t)`` and
    accepted by ``rho_4`` (package docstring, "A target's recent past"). Returns the new
    chain and ``accepted (B, C)`` bool.
    """
    k = chain.pos.shape[-2]
    prev = chain.prev
    w = prev.win_pos.shape[2]
    onehot = F.one_hot((noise.slot * k).long().clamp(max=k - 1), k).to(torch.bool)  # (B, C, K)
    a = noise.step[..., 0, :] * models.past_step[0]  # (B, C, 2)
    b = noise.step[..., 1, :] * models.past_step[1]
    tau = torch.arange(-w, 0, device=a.device, dtype=a.dtype)  # (W,) time relative to t
    win_live = prev.win_exists & onehot.unsqueeze(-2)  # (B, C, W, K)
    shift = a[:, :, None, None, :] + b[:, :, None, None, :] * tau[:, None, None]  # (B, C, W, 1, 2)
    win_pos = prev.win_pos + shift * win_live.unsqueeze(-1).to(a.dtype)
    pos = chain.pos + a.unsqueeze(-2) * (chain.exists & onehot).unsqueeze(-1).to(a.dtype)
    new_prev = _past(chain.j, win_pos, cloud, models, prev.win_exists)
    pm, S, obs, free = _predict(new_prev, chain.labels, chain.exists, models)
    prop = chain._replace(pos=pos, log_lik=_log_lik(pos, chain.exists, z, models.sensor),
                          log_px=_log_px(pos, pm, S, obs, free, models.existence),
                          log_birth=_birth_ratio(pos, free, cloud, models), pm=pm, S=S, observed=obs, free=free,
                          prev=new_prev)
    acc = mh_accept(_past_log_target(prop) - _past_log_target(chain), noise.u)
    return mh_select(acc, prop, chain), acc


def _past_log_target(chain: Chain) -> Tensor:
    """``log pi(j, x_w, g, e, x)`` of the past move's target up to the terms it does not change
    (``w_j``, ``c_j``, the existence prior): the window's terms, ``log p(g | x_{t-1}, .)``,
    ``log p(x | past, g, e)`` and ``log p(Z_t | x, e)``, ``(B, C)``.
    """
    log_g = torch.gather(chain.prev.log_pg, -1, chain.g.unsqueeze(-1)).squeeze(-1)
    return chain.prev.log_win + log_g + chain.log_px + chain.log_lik


def _pixel_log_q(pos: Tensor, masks: Tensor, step: Tensor, n: Tensor, sensor: ThresholdedPixels) -> Tensor:
    """``log`` of the density uniform over the pixels of mask ``masks[b, step[b, c]]`` (``masks
    (B, W, HW)`` bool, ``step (B, C)``; ``n (B, C)`` pixels) at positions ``pos (B, C, 2)``:
    ``-log(n s^2)`` in a pixel of the mask, ``-inf`` elsewhere (and where ``n = 0``): ``-> (B, C)``.
    """
    h, w = sensor.shape
    s = sensor.pixel_size
    col, row = torch.floor(pos[..., 0] / s), torch.floor(pos[..., 1] / s)
    inside = (col >= 0) & (col < w) & (row >= 0) & (row < h)
    flat = (row.clamp(0, h - 1) * w + col.clamp(0, w - 1)).long() + step * (h * w)  # (B, C) into (B, W HW)
    hit = torch.gather(masks.flatten(1), -1, flat) & inside & (n > 0)
    log_q = -torch.log(n.to(pos.dtype).clamp(min=1) * s * s)
    return where(hit, log_q, torch.full_like(log_q, -math.inf))


def _alive_path(chain: Chain, cloud: Cloud, models: Models, onehot: Tensor, s: Tensor, sample: Tensor, y: Tensor,
                eps: Tensor, win_exists: Tensor, exists: Tensor) -> tuple[Tensor, Tensor, Tensor]:
    """The positions of slot ``i`` (``onehot (B, C, K)``) alive from window step ``s (B, C)``
    through ``t``, and their proposal density: at ``s`` the position ``y (B, C, 2)``, at each
    later step the conditional of the Kalman predictive (re-run from the anchor with
    ``win_exists (B, C, W, K)``, ``exists (B, C, K)``) given the other observed slots, drawn
    from ``eps (B, C, L, 2)`` where ``sample`` else the chain's own. Returns the window
    positions ``(B, C, W, K, 2)``, the positions at ``t`` ``(B, C, K, 2)`` and ``log q
    (B, C)`` of the steps after ``s`` (the pixel density of ``y`` is the caller's).
    """
    v = cloud.view
    j, prev = chain.j, chain.prev
    stats = KalmanStats(_gather(v.anchor_w_mean, j), _gather(v.anchor_w_cov, j))
    pos_p, lab_p, ex_p = (_gather(t, j) for t in (v.anchor_pos, v.anchor_labels, v.anchor_exists))
    win_lab = _gather(v.win_labels, j)
    w = prev.win_pos.shape[2]
    sel = onehot.unsqueeze(-1)
    log_q = torch.zeros_like(y[..., 0])
    out = []
    for r in range(w + 1):  # the window's steps and t (time, not particles)
        pos_r, lab_r, ex_r = ((prev.win_pos[:, :, r], win_lab[:, :, r], win_exists[:, :, r]) if r < w
                              else (chain.pos, chain.labels, exists))
        tr = models.motion.transition(pos_p, lab_p, lab_r, ex_p, ex_r, existence=models.existence)
        pred = pairwise_kalman_predict(stats, pos_p, tr)
        cm, cv = _conditional_slot(pos_r, pred.position_mean.contiguous(), pred.position_cov.contiguous(),
                                   tr.observed, onehot)
        own = (pos_r * sel.to(y.dtype)).sum(-2)
        x = where(sample.unsqueeze(-1), cm + cv.clamp(min=0).sqrt().unsqueeze(-1) * eps[:, :, max(r - 1, 0)],
                        own)
        after = s < r
        log_q = log_q + where(after, _log_normal2(x, cm, cv), torch.zeros_like(cv))
        x = where(after.unsqueeze(-1), x, where((s == r).unsqueeze(-1), y, own))
        pos_r = where(sel & (s <= r)[..., None, None], x.unsqueeze(-2), pos_r)
        _, stats = pairwise_kalman_update(pred, pos_r)
        out.append(pos_r)
        pos_p, lab_p, ex_p = pos_r, lab_r, ex_r
    return torch.stack(out[:w], 2), out[w], log_q


def window_birth_move(chain: Chain, noise: GroupWindowBirthNoise, cloud: Cloud, z: Tensor, models: Models
                      ) -> tuple[Chain, Tensor]:
    """One slot ``i`` born at a window step ``s`` and alive through ``t``, or the reverse
    (package docstring, "A target born in the window"); accepted by ``rho_5``. Returns the new
    chain and ``accepted (B, C)`` bool (False where the slot's existence pattern allows
    neither direction).
    """
    existence, sensor = models.existence, models.sensor
    k = chain.pos.shape[-2]
    prev = chain.prev
    w = prev.win_pos.shape[2]
    if w == 0:  # no window (a state without a path): nothing to do
        return chain, torch.zeros_like(noise.u, dtype=torch.bool)
    anchor_ex = _gather(cloud.view.anchor_exists, chain.j)
    # (slot, s) uniform over the eligible pairs of the chain's state (a birth or a death is possible)
    births, deaths = _eligible(anchor_ex, prev.win_exists, chain.exists, cloud.n_pair)  # (B, C, K, W)
    elig = (births | deaths).flatten(-2)
    n_elig = elig.sum(-1)  # (B, C)
    rank = (noise.slot * n_elig).long().clamp(max=(n_elig - 1).clamp(min=0)).unsqueeze(-1)
    pick = (elig.cumsum(-1) > rank).to(torch.int64).argmax(-1)  # (B, C): the first with rank + 1 eligible
    onehot = F.one_hot(pick // w, k).to(torch.bool)  # (B, C, K)
    s = pick % w  # (B, C) the birth step in the window
    steps = torch.arange(w, device=s.device)
    birth = torch.gather(births.flatten(-2), -1, pick.unsqueeze(-1)).squeeze(-1) & (n_elig > 0)
    death = torch.gather(deaths.flatten(-2), -1, pick.unsqueeze(-1)).squeeze(-1) & (n_elig > 0)
    n_s = torch.gather(cloud.n_pair, 1, s)  # (B, C)
    # y ~ uniform over the paired detections of Z_s (a pixel by the shared inverse CDF, then a
    # place in it): every chain's draw searched in each window step's CDF (W searches of a
    # row, not a copy of a (HW) row per chain), the chain's step s kept
    b, c = s.shape
    idx = torch.gather(inverse_cdf(cloud.cdf_pair, noise.y_pix.unsqueeze(1).expand(b, w, c)), 1,
                       s.unsqueeze(1)).squeeze(1)  # (B, C)
    width = sensor.shape[1]
    pix = torch.stack([(idx % width).to(noise.y_xy.dtype), (idx // width).to(noise.y_xy.dtype)], -1)
    y_new = (pix + noise.y_xy) * sensor.pixel_size  # (B, C, 2)
    sel = onehot.unsqueeze(-1)
    y_own = (torch.gather(prev.win_pos, 2, s[:, :, None, None, None].expand(b, c, 1, k, 2)).squeeze(2)
             * sel.to(y_new.dtype)).sum(-2)
    y = where(birth.unsqueeze(-1), y_new, y_own)
    # the configuration with slot i alive from s on: proposed (a birth) or the chain's own (a death)
    in_window = (steps.reshape(1, 1, w) >= s.unsqueeze(-1)).unsqueeze(-1) & onehot.unsqueeze(2)  # (B, C, W, K)
    alive_win_ex = prev.win_exists | in_window
    alive_ex = chain.exists | onehot
    win_alive, pos_alive, log_qx = _alive_path(chain, cloud, models, onehot, s, birth, y, noise.x_eps,
                                               alive_win_ex, alive_ex)
    log_q = _pixel_log_q(y, cloud.pair, s, n_s, sensor) + log_qx
    # the proposed state: alive from s (a birth) or dead from s (a death; positions to x_death)
    dead = _death_pos(existence, y_new)
    win_exists = where(birth[..., None, None], alive_win_ex, prev.win_exists & ~in_window)
    exists = where(birth.unsqueeze(-1), alive_ex, chain.exists & ~onehot)
    win_pos = where(birth[..., None, None, None], win_alive,
                          where(in_window.unsqueeze(-1), dead, prev.win_pos))
    pos = where(birth[..., None, None], pos_alive, where(sel, dead, chain.pos))
    new_prev = _past(chain.j, win_pos, cloud, models, win_exists)
    pm, S, obs, free = _predict(new_prev, chain.labels, exists, models)
    prop = chain._replace(exists=exists, pos=pos, log_lik=_log_lik(pos, exists, z, sensor),
                          log_px=_log_px(pos, pm, S, obs, free, existence),
                          log_birth=_birth_ratio(pos, free, cloud, models), pm=pm, S=S, observed=obs, free=free,
                          prev=new_prev)

    def log_e(win_ex: Tensor, ex: Tensor) -> Tensor:  # eq. 25 over the window and t
        full = torch.cat([anchor_ex.unsqueeze(2), win_ex, ex.unsqueeze(2)], 2)
        return existence.log_prob_exists(full[:, :, 1:], full[:, :, :-1]).sum((-1, -2))

    log_rho = (_past_log_target(prop) - _past_log_target(chain)
               + (log_e(win_exists, exists) - log_e(prev.win_exists, chain.exists)).to(y.dtype))
    log_rho = log_rho + where(birth, -log_q, log_q)
    n_new = torch.stack(_eligible(anchor_ex, win_exists, exists, cloud.n_pair)).any(0).flatten(-2).sum(-1)
    log_rho = log_rho + torch.log(n_elig.to(y.dtype)) - torch.log(n_new.to(y.dtype))  # the pick's 1 / n ratio
    acc = (birth | death) & mh_accept(log_rho, noise.u)
    return mh_select(acc, prop, chain), acc


def _eligible(anchor_ex: Tensor, win_ex: Tensor, ex: Tensor, n_pair: Tensor) -> tuple[Tensor, Tensor]:
    """The window birth's possible ``(slot, s)`` pairs: ``births (B, C, K, W)``, the slot dead
    from ``s - 1`` through ``t`` (and a paired detection at ``s``), and ``deaths``, dead at
    ``s - 1`` and alive from ``s`` through ``t``; from the existence at the anchor ``(B, C,
    K)``, in the window ``(B, C, W, K)`` and at ``t`` ``(B, C, K)``; ``n_pair (B, W)``.
    """
    w = win_ex.shape[2]
    f = torch.cat([anchor_ex.unsqueeze(2), win_ex, ex.unsqueeze(2)], 2).transpose(-1, -2)  # (B, C, K, W + 2)
    dead_on = torch.flip(torch.cumprod(torch.flip(~f, [-1]).to(torch.int64), -1), [-1]).to(torch.bool)  # dead from
    alive_on = torch.flip(torch.cumprod(torch.flip(f, [-1]).to(torch.int64), -1), [-1]).to(torch.bool)
    before = ~f[..., :w]
    births = before & dead_on[..., 1:w + 1] & (n_pair > 0)[:, None, None, :]
    return births, before & alive_on[..., 1:w + 1]


def _log_normal2(x: Tensor, mean: Tensor, var: Tensor) -> Tensor:
    """``log N(x; mean, var I_2)``: ``(B, C, 2), (B, C, 2), (B, C) -> (B, C)``."""
    return -0.5 * (x - mean).square().sum(-1) / var - torch.log(var) - LOG_2PI


def _conditional_slot(pos: Tensor, pm: Tensor, S: Tensor, obs: Tensor, onehot: Tensor) -> tuple[Tensor, Tensor]:
    """:func:`_conditional` for a slot chosen per chain by ``onehot (B, C, K)`` (it must be
    observed): mean ``(B, C, 2)``, variance ``(B, C)``; independent of the slot's own position.
    """
    o = obs.to(pos.dtype)
    P = _observed_precision(S, o)
    sel = onehot.to(pos.dtype)
    p_i = (P * sel.unsqueeze(-1)).sum(-2)  # (B, C, K): row i
    pii = (p_i * sel).sum(-1)
    d = (pos - pm) * (o * (1.0 - sel)).unsqueeze(-1)  # the other observed slots
    return (pm * sel.unsqueeze(-1)).sum(-2) - (p_i.unsqueeze(-2) @ d).squeeze(-2) / pii.unsqueeze(-1), 1.0 / pii


def _observed_precision(S: Tensor, o: Tensor) -> Tensor:
    """The precision of the observed block of ``S (B, C, K, K)`` (``o (B, C, K)`` 1 where
    observed; the unobserved rows and columns replaced by the identity): ``(B, C, K, K)``.
    """
    Sm = S * o.unsqueeze(-1) * o.unsqueeze(-2) + torch.diag_embed(1.0 - o)
    return torch.cholesky_inverse(torch.linalg.cholesky(Sm))


def _conditional(pos: Tensor, pm: Tensor, S: Tensor, obs: Tensor, i: int) -> tuple[Tensor, Tensor]:
    """Conditional of slot ``i``'s position given the other observed slots under the
    predictive ``N(pm, S)`` (per axis): mean ``(B, C, 2)``, variance ``(B, C)``. Through the
    precision ``P`` of the observed block: ``var = 1 / P_ii``,
    ``mean = x_i - (P d)_i / P_ii`` with ``d = (x - pm)`` on the observed slots.
    """
    o = obs.to(pos.dtype)
    P = _observed_precision(S, o)
    d = (pos - pm) * o.unsqueeze(-1)
    Pd = P[..., i, :].unsqueeze(-2) @ d  # (B, C, 1, 2)
    pii = P[..., i, i]
    return pos[..., i, :] - Pd.squeeze(-2) / pii.unsqueeze(-1), 1.0 / pii


def _log_q_slot(x_i: Tensor, cm: Tensor, cv: Tensor, obs_i: Tensor, free_i: Tensor, cloud: Cloud,
                models: Models) -> Tensor:
    """``log q_i(x_i)``: conditional Gaussian if observed, ``q_0`` if a free birth, 0 (point
    mass) if dead: ``-> (B, C)``.
    """
    log_n = _log_normal2(x_i, cm, cv)
    log_q0 = _log_q0(x_i.unsqueeze(-2), cloud, models.sensor, models.existence, models.p_i).squeeze(-1)
    return where(obs_i, log_n, where(free_i, log_q0, torch.zeros_like(log_n)))
