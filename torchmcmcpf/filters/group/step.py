"""One time step of the group filter (:func:`group_mcmc_step`): the state's group fields
(:func:`unpack`), the per-step quantities of the proposals (:func:`make_cloud`, eqs. 19, 61-62, 65),
the chains' mixture of moves and the kept states' Kalman statistics.

The maths, the moves' targets and acceptance ratios: the docstring of :mod:`torchmcmcpf.filters.group`.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from typing import Any

import torch
import torch.nn.functional as F
from torch.utils._pytree import tree_map

from ..._native.select import where
from ...models.base import neighbourhood
from ...models.group import (
    GroupExistence,
    GroupStructurePrior,
    KalmanStats,
    VirtualLeaderMotion,
    group_structures,
    pairwise_kalman_predict,
    pairwise_kalman_update,
    structure_index,
)
from ...models.sensors.pixels import ThresholdedPixels
from ...resampling import cdf
from ...runtime import repeating
from ...state import ParticleState, StepInfo
from ...typing import Tensor
from .._bound import Bound, Compile
from ..mcmc import pick_moves
from .moves import (
    Chain,
    Cloud,
    GroupView,
    Models,
    _death_pos,
    _gather,
    _log_lik,
    _path_step,
    _prev_of,
    joint_move,
    joint_proposal,
    past_move,
    refine_move,
    window_birth_move,
)
from .noise import (
    NOISES,
    GroupJointNoise,
    GroupPastNoise,
    GroupRefineNoise,
    GroupWindowBirthNoise,
    _draw_fields,
    draw_noise,
)
from .settings import GroupMCMCSettings
from .state import KEY, GroupPath, GroupState

__all__ = ["group_mcmc_step", "bind_group", "group_mcmc_bound_step", "group_program", "make_cloud", "unpack"]


# ----------------------------------------------------------------------------------------
# the state: a ParticleState whose extras["group"] is the GroupState
# ----------------------------------------------------------------------------------------
def unpack(state: ParticleState, lag: int) -> GroupView:
    """The group fields of a state (its :class:`~torchmcmcpf.filters.group.GroupState`,
    package docstring "State and outputs") as a :class:`GroupView`; a state without a path
    (or with a longer one than ``lag``) starts one at its current step.
    """
    group: GroupState = state.extras[KEY]  # type: ignore[index]
    pos = state.x[..., 0::2]
    exists = state.exists if state.exists is not None else torch.zeros(pos.shape[:-1], dtype=torch.bool,
                                                                       device=pos.device)
    labels, w_mean, w_cov, frames = group.labels, group.w_mean, group.w_cov, group.frames
    g = structure_index(labels)
    b, n, k = labels.shape
    path = group.path
    if lag > 0 and path is not None and path.length <= lag + 1:
        pp, pl, pe, plog = path.pos, path.labels, path.exists, path.log
        pg = structure_index(pl)
        return GroupView(pos, g, labels, exists, w_mean, w_cov, state.log_w, frames,
                         pp[:, :, 0], pg[:, :, 0], pl[:, :, 0], pe[:, :, 0], path.anchor_w_mean, path.anchor_w_cov,
                         pp[:, :, 1:], pg[:, :, 1:], pl[:, :, 1:], pe[:, :, 1:], plog[:, :, 1:])
    none = pos.new_zeros((b, n, 0))
    return GroupView(pos, g, labels, exists, w_mean, w_cov, state.log_w, frames,
                     pos, g, labels, exists, w_mean, w_cov, pos.new_zeros((b, n, 0, k, 2)), g.new_zeros((b, n, 0)),
                     labels.new_zeros((b, n, 0, k)), exists.new_zeros((b, n, 0, k)), none)


# ----------------------------------------------------------------------------------------
# the step
# ----------------------------------------------------------------------------------------
def _predictive_log_lik(pm: Tensor, var: Tensor, exists: Tensor, z: Tensor, sensor: ThresholdedPixels,
                        p_death: float, radius: int = 2) -> Tensor:
    """``sum_i log[(1 - P_D) E_{N(pm_i, var_i I)} p(Z | x_i) + P_D]`` over the live slots
    (alpha ``"predictive"``, package docstring): ``pm (B, n, K, 2)``, ``var (B, n, K)`` ->
    ``(B, n)``. The Gaussian's mass on each pixel of a ``(2 radius + 1)^2`` window around its
    mean times the pixel's one-target ratio (eq. 40); mass outside the window or the grid
    counts with ratio 1 (the mean ratio of a pixel without a target is ``1``).
    """
    s = sensor.pixel_size
    h, w = sensor.shape
    sd = var.clamp(min=1e-12).sqrt().unsqueeze(-1)
    offs = torch.arange(-radius, radius + 1, device=pm.device, dtype=pm.dtype)
    cols = torch.floor(pm[..., 0] / s).unsqueeze(-1) + offs  # (B, n, K, R)
    rows = torch.floor(pm[..., 1] / s).unsqueeze(-1) + offs

    def mass(c: Tensor, mu: Tensor) -> Tensor:
        mu = mu.unsqueeze(-1)
        return torch.special.ndtr(((c + 1) * s - mu) / sd) - torch.special.ndtr((c * s - mu) / sd)

    m2 = mass(rows, pm[..., 1]).unsqueeze(-1) * mass(cols, pm[..., 0]).unsqueeze(-2)  # (B, n, K, R, R)
    inside = (((rows >= 0) & (rows < h)).unsqueeze(-1) & ((cols >= 0) & (cols < w)).unsqueeze(-2))
    flat = (rows.clamp(0, h - 1).long().unsqueeze(-1) * w + cols.clamp(0, w - 1).long().unsqueeze(-2))
    b = flat.shape[0]
    hit = torch.gather(z.reshape(b, -1).to(torch.bool), 1, flat.reshape(b, -1)).reshape(flat.shape)
    lr1 = sensor.p_d1 / sensor.p_fa
    lr0 = (1.0 - sensor.p_d1) / (1.0 - sensor.p_fa)
    lr = where(inside, hit.to(pm.dtype) * (lr1 - lr0) + lr0, torch.ones_like(m2))
    e_lr = (m2 * lr).sum((-1, -2)) + (1.0 - m2.sum((-1, -2))).clamp(min=0.0)
    term = torch.log((1.0 - p_death) * e_lr + p_death)
    return where(exists, term, torch.zeros_like(term)).sum(-1)


def _log_alpha_lik(v: GroupView, z: Tensor, models: Models, alpha: str, chunk: int = 512) -> Tensor:
    """``log p(Z_t | j)`` of eq. 62 (``"mean"``) or the predictive likelihood
    (``"predictive"``) of every particle, ``(B, N)`` (chunks of particles bound the memory).
    """
    out = []
    for s in range(0, v.pos.shape[1], chunk):
        sl = slice(s, s + chunk)
        pos, lab, ex = v.pos[:, sl], v.labels[:, sl], v.exists[:, sl]
        tr = models.motion.transition(pos, lab, lab, ex, ex, existence=models.existence)
        pred = pairwise_kalman_predict(KalmanStats(v.w_mean[:, sl], v.w_cov[:, sl]), pos, tr)
        if alpha == "mean":
            pm = where(ex.unsqueeze(-1), pred.position_mean, _death_pos(models.existence, pos))
            out.append(_log_lik(pm, ex, z, models.sensor))
        else:
            var = torch.diagonal(pred.position_cov, dim1=-2, dim2=-1)
            out.append(_predictive_log_lik(pred.position_mean, var, ex, z, models.sensor, models.existence.p_death))
    return torch.cat(out, 1)


def make_cloud(state: ParticleState, z: Tensor, *, models: Models, settings: GroupMCMCSettings) -> Cloud:
    """Per-step quantities of the proposals (eqs. 19, 61-62, 65), eager."""
    v = unpack(state, settings.lag)
    b, _, k = v.exists.shape
    table = group_structures(k, device=v.pos.device)
    log_pg = models.structure_prior.log_probs(v.g, v.pos, v.exists)
    log_w = torch.log_softmax(state.log_w.to(torch.float64), -1)
    log_alpha = torch.log_softmax(log_w + _log_alpha_lik(v, z, models, settings.alpha).to(torch.float64), -1)
    log_q = torch.log(settings.p_a * log_alpha.exp() + (1.0 - settings.p_a) * log_w.exp())  # eq. 61
    zb = z.to(torch.bool)
    if settings.birth == "eq65":  # without a previous frame (or an empty one: the start), the current one
        prev = zb if v.frames.shape[1] == 0 else v.frames[:, -1].to(torch.bool)
        prev = where(prev.flatten(1).any(-1)[:, None, None], prev, zb)
        beta = (zb & _near(prev, 1)).reshape(b, -1)
    else:
        beta = zb.reshape(b, -1)
    # the window birth: per window step s, the detections of Z_s with a detection of Z_{s+1} within two
    # pixels (a step of <= 100 m; Z_{W} = Z_t)
    w = v.win_pos.shape[2]
    seq = torch.cat([v.frames[:, v.frames.shape[1] - w:].to(torch.bool), zb.unsqueeze(1)], 1)  # (B, W + 1, H, W)
    pair = (seq[:, :-1] & _near(seq[:, 1:], 2)).flatten(2)  # (B, W, HW)
    return Cloud(v, log_pg, v.win_log.sum(-1), cdf(log_alpha), cdf(log_w), (log_w - log_q).to(v.pos.dtype),
                 beta, _uniform_cdf(beta), beta.sum(-1), table, pair, _uniform_cdf(pair), pair.sum(-1))


def _near(frames: Tensor, radius: int) -> Tensor:
    """Pixels within ``radius`` pixels (a square) of a detection of the binary ``frames (*S, H,
    W)``: ``-> (*S, H, W)`` bool.
    """
    return neighbourhood(frames.to(torch.float32), "max", 2, radius) > 0


def _uniform_cdf(mask: Tensor) -> Tensor:
    """The CDF (:func:`~torchmcmcpf.resampling.cdf`) of the distribution uniform over the True
    entries of each row of ``mask (*S, M)``; uniform over all ``M`` where a row has none (the
    draw is then unused but finite).
    """
    return cdf(where(mask | ~mask.any(-1, keepdim=True), 0.0, -math.inf).to(torch.float64))


def _keep(cloud: Cloud, j: Tensor, g: Tensor, exists: Tensor, pos: Tensor, win_pos: Tensor, win_exists: Tensor,
          z: Tensor, models: Models, settings: GroupMCMCSettings, generator: torch.Generator, chunk: int = 512
          ) -> GroupState:
    """The group fields of the kept states ``(B, N, ...)`` at ``t``: the Kalman statistics
    (eqs. 53-57; from the anchor through the window with a lag, sampled with zero covariance
    when not marginalising), the frames and, with a lag, the new path.
    """
    v = cloud.view
    lag, w = settings.lag, win_pos.shape[2]
    labels = cloud.table[g]
    trim = lag > 0 and w == lag  # the path is full: its first entry leaves, the next is the anchor
    parts: list[tuple[Tensor, Tensor, GroupPath | None]] = []  # (w_mean, w_cov, path) per chunk
    for s in range(0, j.shape[1], chunk):
        sl = slice(s, s + chunk)
        jj = j[:, sl]
        if lag == 0:
            prev = _prev_of(cloud, jj)
            tr = models.motion.transition(prev.pos, prev.labels, labels[:, sl], prev.exists, exists[:, sl],
                                          existence=models.existence)
            _, st = pairwise_kalman_update(pairwise_kalman_predict(KalmanStats(prev.w_mean, prev.w_cov), prev.pos, tr),
                                           pos[:, sl])
            mean, cov = st.mean, st.cov
            if not settings.marginalise:
                d = cov.shape[-1]
                jitter = 1e-9 * (1.0 + torch.diagonal(cov, dim1=-2, dim2=-1).amax(-1))[..., None, None]
                L = torch.linalg.cholesky(cov + jitter * torch.eye(d, dtype=cov.dtype, device=cov.device))
                eps = torch.randn(mean.shape, generator=generator, dtype=mean.dtype, device=mean.device)
                mean = mean + eps @ L.transpose(-1, -2)
                cov = torch.zeros_like(cov)
            parts.append((mean, cov, None))
            continue
        stats = KalmanStats(_gather(v.anchor_w_mean, jj), _gather(v.anchor_w_cov, jj))
        a_pos, a_g, a_lab, a_ex = (_gather(t, jj) for t in (v.anchor_pos, v.anchor_g, v.anchor_labels,
                                                             v.anchor_exists))
        wg, wl = (_gather(t, jj) for t in (v.win_g, v.win_labels))
        we = win_exists[:, sl]
        off = v.frames.shape[1] - w  # the window's frames are the last W
        steps = [(win_pos[:, sl, i], wg[:, :, i], wl[:, :, i], we[:, :, i], v.frames[:, off + i]) for i in range(w)]
        steps.append((pos[:, sl], g[:, sl], labels[:, sl], exists[:, sl], z))
        path = [(a_pos, a_lab, a_ex)]
        terms, first = [], stats
        p_pos, p_g, p_lab, p_ex = a_pos, a_g, a_lab, a_ex
        for i, (q_pos, q_g, q_lab, q_ex, q_z) in enumerate(steps):
            term, stats = _path_step(stats, p_pos, p_g, p_lab, p_ex, q_pos, q_g, q_lab, q_ex, q_z, models)
            terms.append(term)
            path.append((q_pos, q_lab, q_ex))
            if i == 0:
                first = stats
            p_pos, p_g, p_lab, p_ex = q_pos, q_g, q_lab, q_ex
        anchor = first if trim else KalmanStats(_gather(v.anchor_w_mean, jj), _gather(v.anchor_w_cov, jj))
        if trim:
            path, terms = path[1:], terms[1:]
        parts.append((stats.mean, stats.cov, GroupPath(
            torch.stack([p[0] for p in path], 2), torch.stack([p[1] for p in path], 2),
            torch.stack([p[2] for p in path], 2), torch.stack([torch.zeros_like(terms[0])] + terms, 2),
            anchor.mean, anchor.cov)))
    # the chunks joined along the particles, field by field (the path None without a lag)
    w_mean, w_cov, new_path = tree_map(lambda *ts: None if ts[0] is None else torch.cat(ts, 1), *parts)
    frames = torch.cat([v.frames, z.to(torch.bool).unsqueeze(1)], 1)
    frames = frames[:, frames.shape[1] - (new_path.length - 1 if new_path is not None else 1):].contiguous()
    return GroupState(labels, w_mean, w_cov, frames, new_path)


def bind_group(motion: VirtualLeaderMotion, sensor: ThresholdedPixels, settings: GroupMCMCSettings | None = None,
               existence: GroupExistence | None = None, *, structure_prior: GroupStructurePrior,
               num_particles: int | None = None, compile: Compile = None) -> Bound:
    """The group filter's :class:`~torchmcmcpf.filters._bound.Bound`: the models, ``settings``
    (default :class:`GroupMCMCSettings`; ``num_particles``, when given, a multiple of
    ``num_chains``), as ``dynamics`` the :class:`~torchmcmcpf.filters.group.moves.Models`
    the moves read (the models, the structure prior of eq. 19 and the proposal constants),
    and the program, the move runner ``program(move, chain, noise, cloud, z)``
    (:func:`group_program`, each move compiled with ``compile``).
    """
    settings = GroupMCMCSettings() if settings is None else settings
    if num_particles is not None:
        settings.check(num_particles)
    if not isinstance(motion, VirtualLeaderMotion):
        raise ValueError(f"motion must be a VirtualLeaderMotion, got {type(motion).__name__}")
    if not isinstance(existence, GroupExistence):
        raise ValueError(f"existence must be a GroupExistence, got {type(existence).__name__}")
    if not isinstance(structure_prior, GroupStructurePrior):
        raise ValueError(f"structure_prior must be a GroupStructurePrior, got {type(structure_prior).__name__}")
    models = Models(motion, sensor, existence, structure_prior, float(settings.p_i), float(settings.p_a),
                    settings.past_step)
    # a whole-configuration Motion, not a per-slot MotionModel: the shared bind would refuse it
    return Bound(motion, sensor, settings, existence, models, group_program(models, compile))  # type: ignore[arg-type]


def group_mcmc_step(state: ParticleState, z: Tensor, *, motion: VirtualLeaderMotion, sensor: ThresholdedPixels,
                    settings: GroupMCMCSettings = GroupMCMCSettings(), generator: torch.Generator,
                    existence: GroupExistence, structure_prior: GroupStructurePrior) -> tuple[ParticleState, StepInfo]:
    """One time step of the group filter: :func:`group_mcmc_bound_step` after an eager
    :func:`bind_group` (a filter binds once). Parameters and returns:
    :func:`group_mcmc_bound_step`, with the models ``motion``, ``sensor``, ``existence``,
    ``structure_prior`` and ``settings`` (:class:`GroupMCMCSettings`) in place of ``bound``:
    ``state`` with ``x (B, N, K, 4)`` and the group extras and ``z`` a binary frame ``(B, H, W)``
    give a state of the same shapes.
    """
    bound = bind_group(motion, sensor, settings, existence, structure_prior=structure_prior,
                       num_particles=state.x.shape[1])
    return group_mcmc_bound_step(state, z, bound, generator=generator)


def group_mcmc_bound_step(state: ParticleState, z: Tensor, bound: Bound, *, generator: torch.Generator
                          ) -> tuple[ParticleState, StepInfo]:
    """One time step of the marginalised MCMC-based particle filter (package docstring).

    Parameters
    ----------
    state : ParticleState at ``t - 1`` with the group extras (``x (B, N, K, 4)``;
        :meth:`GroupMCMCFilter.init`).
    z : (B, H, W) binary frame at ``t``.
    bound : :class:`~torchmcmcpf.filters._bound.Bound` of :func:`bind_group`: the models
        (eqs. 13, 41, 25/33, 19; ``bound.dynamics`` the :class:`Models` the moves read),
        :class:`GroupMCMCSettings` and the program ``program(move, chain, noise, cloud, z)``
        running the move ``"joint"``, ``"refine"``, ``"past"`` or ``"birth"`` (compiled ones
        with ``GroupMCMCFilter(compile_step=True)``).
    generator : the only source of randomness (eager draws).

    Returns
    -------
    state : ParticleState at ``t`` (chain-major particles, equal weights).
    info : ``acceptance (B,)`` over all MH decisions; ``extras``: ``acceptance_joint``,
        ``acceptance_structure``, ``acceptance_target`` and, with a lag, ``acceptance_past``
        and, with ``p_window_birth``, ``acceptance_birth`` (B,) (NaN where the move never
        ran; the window birth counts its no-op proposals as rejections), ``structure_prob (B, Bell(K))``,
        ``exists_prob (B, K)``, ``expected_count (B,)``, ``all_exist_prob (B,)`` (every slot
        alive) and ``structure_prob_all_exist (B, Bell(K))``, the structure given that every
        slot is alive (NaN where no particle has them all).
    """
    settings, models, moves = bound.settings, bound.dynamics, bound.program
    b, n, k, _ = state.x.shape
    c = settings.num_chains
    dtype, dev = state.x.dtype, state.x.device
    cloud = make_cloud(state, z, models=models, settings=settings)
    first = draw_noise(GroupJointNoise, (b, c, k), generator=generator, dtype=dtype, device=dev)
    chain = joint_proposal(first, cloud, z, models)
    per_chain = n // c
    names = (["joint", "structure", "target"] + (["past"] if settings.lag else [])
             + (["birth"] if settings.p_window_birth else []))
    acc = {name: state.x.new_zeros(b) for name in names}
    cnt = {name: state.x.new_zeros(b) for name in names}
    kept = []
    count = settings.burn_in + settings.thinning * per_chain
    with repeating():  # compiled moves: repeats skip Dynamo's guards (runtime.repeating)
        for m, move in enumerate(pick_moves(settings.moves(), count, generator=generator), start=1):
            noise = _draw_fields(NOISES[move], (b, c, k), generator, dtype, dev, window=max(settings.lag, 1))
            out = moves(move, chain, noise, cloud, z)
            chain = out[0]
            if move == "refine":
                acc["structure"] += out[1].to(dtype).sum(1)
                cnt["structure"] += c
                acc["target"] += out[2].to(dtype).sum((1, 2))
                cnt["target"] += c * k
            else:
                acc[move] += out[1].to(dtype).sum(1)
                cnt[move] += c
            if m > settings.burn_in and (m - settings.burn_in) % settings.thinning == 0:
                kept.append((chain.j, chain.g, chain.exists, chain.pos, chain.prev.win_pos, chain.prev.win_exists))
    j, g, exists, pos, win_pos, win_ex = (torch.stack(t, 2).flatten(1, 2) for t in zip(*kept))  # (B, C * N/C, ...)
    group = _keep(cloud, j, g, exists, pos, win_pos, win_ex, z, models, settings, generator)
    vel = group.w_mean[..., :k].transpose(-1, -2)  # (B, N, K, 2)
    x = torch.stack([pos[..., 0], vel[..., 0], pos[..., 1], vel[..., 1]], -1)
    new = ParticleState(x, x.new_full((b, n), -math.log(n)), exists, {KEY: group})
    one_hot = F.one_hot(g, cloud.table.shape[0]).to(x.dtype)  # (B, N, G)
    all_exist = exists.all(-1).to(x.dtype)  # (B, N)
    exists_prob = exists.to(x.dtype).mean(1)
    info = {f"acceptance_{name}": acc[name] / cnt[name] for name in names}
    info.update(structure_prob=one_hot.mean(1), exists_prob=exists_prob, expected_count=exists_prob.sum(-1),
                all_exist_prob=all_exist.mean(1),
                structure_prob_all_exist=(one_hot * all_exist.unsqueeze(-1)).sum(1) / all_exist.sum(1, keepdim=True))
    acceptance = sum(acc.values(), x.new_zeros(b)) / sum(cnt.values(), x.new_zeros(b))
    return new, StepInfo.make(acceptance, acceptance=acceptance, extras=info)


def group_program(models: Models, compile: Compile = None) -> Callable[..., Any]:
    """The group filter's program, ``program(move, chain, noise, cloud, z)``: the moves with
    the models bound (each compiled on its own with ``compile``: one function per move, so
    that each has its own compile cache), eager without ``compile``.
    """
    def joint(chain: Chain, noise: GroupJointNoise, cloud: Cloud, z: Tensor) -> Any:
        return joint_move(chain, noise, cloud, z, models)

    def refine(chain: Chain, noise: GroupRefineNoise, cloud: Cloud, z: Tensor) -> Any:
        return refine_move(chain, noise, cloud, z, models)

    def past(chain: Chain, noise: GroupPastNoise, cloud: Cloud, z: Tensor) -> Any:
        return past_move(chain, noise, cloud, z, models)

    def birth(chain: Chain, noise: GroupWindowBirthNoise, cloud: Cloud, z: Tensor) -> Any:
        return window_birth_move(chain, noise, cloud, z, models)

    programs: dict[str, Callable[..., Any]] = {"joint": joint, "refine": refine, "past": past, "birth": birth}
    if compile is not None:
        programs = {name: compile(fn) for name, fn in programs.items()}

    def run(move: str, chain: Chain, noise: Any, cloud: Cloud, z: Tensor) -> Any:
        return programs[move](chain, noise, cloud, z)

    return run
