"""The random-walk move on the joint state (paper 002 eqs. 13-14) and the joint log
transition density it needs (:mod:`torchmcmcpf.kernels.moves` describes the target)."""

from __future__ import annotations

import math
from typing import NamedTuple, Optional

import torch

from ..models.base import MotionModel, SensorModel
from ..models.motion import LinearGaussianMotion
from ..resampling import cdf, gather_particles, inverse_cdf
from ..typing import Measurement, Tensor
from .chains import ChainState, PreviousCloud, _normal, _uniform, evaluate, whiten
from .mh import mh_accept, mh_select

__all__ = ["RandomWalkNoise", "log_transition", "propose_random_walk", "random_walk_move"]

_CHUNK_ELEMENTS = 1 << 22


class RandomWalkNoise(NamedTuple):
    """Noise of one random-walk move: ``eps (B, C, K, D)`` normals, ``u (B, C)`` uniforms for
    the accept/reject and ``u_ancestor (B, C)`` for the Gibbs redraw of the ancestor."""

    eps: Tensor
    u: Tensor
    u_ancestor: Tensor

    @classmethod
    def draw(cls, x: Tensor, motion: MotionModel, *, generator: torch.Generator) -> "RandomWalkNoise":
        """Draw for chains shaped like ``x (B, C, K, D)``."""
        b, c = x.shape[:2]
        return cls(_normal(x.shape, x, generator), _uniform((b, c), x, generator), _uniform((b, c), x, generator))

    # no existence variant: ``random_walk`` is refused with existence (module docstring)


def log_transition(x: Tensor, prev_x: Tensor, *, motion: MotionModel,
                   white_prev: Optional[Tensor] = None) -> Tensor:
    """Joint log transition density from every previous particle to every chain state,
    ``sum_k log p(x_k | x_{k-1,k}^i)``.

    For a :class:`~torchmcmcpf.models.LinearGaussianMotion` the density is a Gaussian in
    whitened coordinates, ``log N(x; F x^i, Q) = c - |L^-1 x - L^-1 F x^i|^2 / 2``: both sides
    are whitened once and ``torch.cdist`` (direct differences, no ``|a|^2 - 2ab + |b|^2``
    cancellation) gives all ``(C, N)`` distances without a ``(B, C, N, K, D)`` intermediate
    (100x faster than the generic path at ``C = 40, N = 200``). Any other motion goes through
    ``motion.log_prob`` in chunks of previous particles, each holding about
    ``_CHUNK_ELEMENTS`` elements of ``(B, C, n, K, D)`` (a memory bound: one chunk for small
    problems).

    Parameters
    ----------
    x : (B, C, K, D) chain states; prev_x : (B, N, K, D) previous particles.
    white_prev : (B, N, K * D), optional: ``PreviousCloud.white_mean`` (linear-Gaussian
        motion), the whitened predicted means of ``prev_x`` when already computed.

    Returns
    -------
    (B, C, N).
    """
    b, c, k, d = x.shape
    n = prev_x.shape[1]
    if isinstance(motion, LinearGaussianMotion):
        log_norm = -0.5 * d * math.log(2 * math.pi) - torch.log(torch.diagonal(motion.L.to(x.dtype))).sum()
        if white_prev is None:
            white_prev = whiten(motion.mean(prev_x), motion)
        dist = torch.cdist(whiten(x, motion), white_prev, compute_mode="donot_use_mm_for_euclid_dist")
        return k * log_norm - 0.5 * dist.square()
    step = max(1, _CHUNK_ELEMENTS // max(1, b * c * k * d))
    out = []
    for i in range(0, n, step):
        p = prev_x[:, i:i + step]
        shape = (b, c, p.shape[1], k, d)
        out.append(motion.log_prob(x.unsqueeze(2).expand(shape), p.unsqueeze(1).expand(shape)).sum(-1))
    return torch.cat(out, dim=-1)


def propose_random_walk(x: Tensor, eps: Tensor, scale: Tensor, *, cloud: PreviousCloud,
                        motion: MotionModel) -> tuple[Tensor, Tensor, Tensor, Tensor]:
    """Gaussian random walk on the joint state (paper 002 eq. 13) and its log ratio (eq. 14
    without the likelihood).

    Parameters
    ----------
    x : (B, C, K, D) current states; eps : (B, C, K, D) normals.
    scale : (D,) or scalar tensor, the per-component step ``s`` (``S = diag(s^2)``).
    cloud : previous particles ``(B, N, K, D)`` with log-weights ``(B, N)``.

    Returns
    -------
    x_prop : (B, C, K, D) ``x + s * eps``.
    log_ratio : (B, C) ``log sum_i w^i p(x' | x^i) - log sum_i w^i p(x | x^i)`` (the
        proposal is symmetric).
    log_joint_prop, log_joint_cur : (B, C, N) ``log w^i + log p(. | x^i)`` at ``x'`` and ``x``
        (the ancestors' full conditionals, reused by :func:`random_walk_move`).
    """
    x_prop = x + scale * eps
    lt = log_transition(torch.cat([x, x_prop], dim=1), cloud.x, motion=motion, white_prev=cloud.white_mean)
    lt = lt + cloud.log_w.unsqueeze(1).to(lt.dtype)
    log_joint_cur, log_joint_prop = lt.chunk(2, dim=1)
    log_ratio = torch.logsumexp(log_joint_prop, -1) - torch.logsumexp(log_joint_cur, -1)
    return x_prop, log_ratio, log_joint_prop, log_joint_cur


def random_walk_move(chain: ChainState, noise: RandomWalkNoise, *, cloud: PreviousCloud,
                     z: Measurement, motion: MotionModel, sensor: SensorModel, scale: Tensor
                     ) -> tuple[ChainState, Tensor]:
    """One random-walk MH step on ``x`` (paper 002 eqs. 13-14), then a Gibbs redraw of the
    ancestor from ``p(a | x) ∝ w^a p(x | x^a)``.

    Parameters
    ----------
    chain : ChainState ``(B, C, K, D)``; noise : :class:`RandomWalkNoise`; cloud : previous
    particles; z : frame ``(B, *G)``; motion, sensor : the models; scale : (D,) or scalar
    random-walk step.

    Returns
    -------
    chain : the new ChainState.
    accepted : (B, C) bool.
    """
    x_prop, log_ratio, lj_prop, lj_cur = propose_random_walk(chain.x, noise.eps, scale, cloud=cloud,
                                                             motion=motion)
    log_lik, terms = evaluate(x_prop, z, sensor)
    accepted = mh_accept(log_lik - chain.log_lik + log_ratio, noise.u)
    new = mh_select(accepted, ChainState(x_prop, chain.x_prev, log_lik, terms), chain)
    # Gibbs step on the ancestor: inversion of the conditional's CDF with one uniform per chain.
    lj = torch.where(accepted.unsqueeze(-1), lj_prop, lj_cur)
    idx = inverse_cdf(cdf(lj), noise.u_ancestor.unsqueeze(-1))
    return new._replace(x_prev=gather_particles(cloud.x, idx.squeeze(-1))), accepted
