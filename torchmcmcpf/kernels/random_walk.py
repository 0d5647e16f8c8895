"""The random-walk move on the joint state (paper 002 eqs. 13-14) and the joint log
transition density it needs (:mod:`torchmcmcpf.kernels.moves` describes the target).
"""

from __future__ import annotations

import math
from typing import NamedTuple

import torch

from .._native.select import where
from ..models.base import MotionModel, SensorModel
from ..models.motion import LinearGaussianMotion
from ..models.multitarget import Exclusion, log_exclusion
from ..resampling import cdf, gather_particles, inverse_cdf
from ..typing import Measurement, Tensor
from .chains import ChainState, PreviousCloud, evaluate, normals, uniforms, whiten
from .mh import mh_accept, mh_select

__all__ = ["RandomWalkNoise", "log_transition", "propose_random_walk", "random_walk_move", "prior_covariance",
           "RunningMoments", "adapted_step"]

#: Roberts, Gelman and Gilks (1997) / Haario et al. (2001): ``S = 2.38^2 / d * Cov`` for a
#: random walk in d dimensions on a roughly Gaussian target
RW_OPTIMAL = 2.38**2

#: Elements of one ``(B, C, n, K, D)`` chunk in :func:`log_transition` (bounds its memory).
_CHUNK_ELEMENTS = 1 << 22


class RandomWalkNoise(NamedTuple):
    """Noise of one random-walk move: ``eps (B, C, K, D)`` normals, ``u (B, C)`` uniforms for
    the accept/reject and ``u_ancestor (B, C)`` for the Gibbs redraw of the ancestor.

    Example
    -------
    >>> import math
    >>> import torch
    >>> import torchmcmcpf as tp
    >>> from torchmcmcpf.kernels import JointNoise, RandomWalkNoise, init_chains, previous_cloud, random_walk_move
    >>> from torchmcmcpf.models.existence import TargetDynamics
    >>> motion, sensor = tp.ConstantVelocity(dt=1.0, q=1.0), tp.LinearGaussian.position(noise_std=1.0)
    >>> dynamics, g = TargetDynamics(motion), torch.Generator().manual_seed(0)
    >>> cloud = previous_cloud(torch.zeros(2, 100, 3, 4), torch.full((2, 100), -math.log(100)), motion=motion)
    >>> like, z = torch.zeros(2, 8, 3, 4), torch.zeros(2, 3, 2)   # chains (B, C, K, D); a frame (B, K, 2)
    >>> chain = init_chains(cloud, JointNoise.draw(like, dynamics, generator=g), z, dynamics=dynamics, sensor=sensor)
    >>> from torchmcmcpf.kernels.random_walk import adapted_step, prior_covariance
    >>> noise = RandomWalkNoise.draw(like, motion, generator=g)
    >>> noise.eps.shape, noise.u.shape, noise.u_ancestor.shape
    (torch.Size([2, 8, 3, 4]), torch.Size([2, 8]), torch.Size([2, 8]))
    >>> step = adapted_step(prior_covariance(cloud, motion), torch.float32)   # (B, 1, K, D, D)
    >>> chain, accepted = random_walk_move(chain, noise, cloud=cloud, z=z, motion=motion, sensor=sensor, scale=step)
    >>> accepted.shape
    torch.Size([2, 8])
    """

    eps: Tensor
    u: Tensor
    u_ancestor: Tensor

    @classmethod
    def draw(cls, x: Tensor, motion: MotionModel, *, generator: torch.Generator) -> RandomWalkNoise:
        """Draw for chains shaped like ``x (B, C, K, D)``."""
        b, c = x.shape[:2]
        return cls(normals(x.shape, x, generator), uniforms((b, c), x, generator), uniforms((b, c), x, generator))

    # no existence variant: ``random_walk`` is refused with existence (module docstring)


def log_transition(x: Tensor, prev_x: Tensor, *, motion: MotionModel,
                   white_prev: Tensor | None = None) -> Tensor:
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
    scale : (D,) or scalar tensor, the per-component step ``s`` (``S = diag(s^2)``); or a
        ``(B, 1, K, D, D)`` lower-triangular factor ``L`` of a per-run, per-target proposal
        covariance ``S_k = L_k L_k^T`` (block diagonal over targets; :func:`adapted_step`).
    cloud : previous particles ``(B, N, K, D)`` with log-weights ``(B, N)``.

    Returns
    -------
    x_prop : (B, C, K, D) ``x + s * eps``.
    log_ratio : (B, C) ``log sum_i w^i p(x' | x^i) - log sum_i w^i p(x | x^i)`` (the
        proposal is symmetric).
    log_joint_prop, log_joint_cur : (B, C, N) ``log w^i + log p(. | x^i)`` at ``x'`` and ``x``
        (the ancestors' full conditionals, reused by :func:`random_walk_move`).
    """
    x_prop = x + (scale * eps if scale.dim() <= 1 else (scale @ eps.unsqueeze(-1)).squeeze(-1))
    lt = log_transition(torch.cat([x, x_prop], dim=1), cloud.x, motion=motion, white_prev=cloud.white_mean)
    lt = lt + cloud.log_w.unsqueeze(1).to(lt.dtype)
    log_joint_cur, log_joint_prop = lt.chunk(2, dim=1)
    log_ratio = torch.logsumexp(log_joint_prop, -1) - torch.logsumexp(log_joint_cur, -1)
    return x_prop, log_ratio, log_joint_prop, log_joint_cur


def random_walk_move(chain: ChainState, noise: RandomWalkNoise, *, cloud: PreviousCloud,
                     z: Measurement, motion: MotionModel, sensor: SensorModel, scale: Tensor,
                     exclusion: Exclusion | None = None) -> tuple[ChainState, Tensor]:
    """One random-walk MH step on ``x`` (paper 002 eqs. 13-14), then a Gibbs redraw of the
    ancestor from ``p(a | x) ∝ w^a p(x | x^a)``.

    Parameters
    ----------
    chain : ChainState ``(B, C, K, D)``; noise : :class:`RandomWalkNoise`.
    cloud : the previous particles; z : the frame ``(B, *G)``; motion, sensor : the models.
    scale : ``(D,)`` or scalar random-walk step, or a ``(B, 1, K, D, D)`` Cholesky factor
        (:func:`propose_random_walk`).
    exclusion : the exclusion term (:mod:`torchmcmcpf.models.multitarget`), optional: its
        ratio ``Phi(x') / Phi(x)`` joins ``alpha`` (the ancestor's conditional does not
        depend on it).

    Returns
    -------
    chain : the new ChainState.
    accepted : (B, C) bool.
    """
    x_prop, log_ratio, lj_prop, lj_cur = propose_random_walk(chain.x, noise.eps, scale, cloud=cloud,
                                                             motion=motion)
    log_lik, terms = evaluate(x_prop, z, sensor)
    log_ratio = log_ratio + log_exclusion(exclusion, sensor, x_prop) - log_exclusion(exclusion, sensor, chain.x)
    accepted = mh_accept(log_lik - chain.log_lik + log_ratio, noise.u)
    new = mh_select(accepted, ChainState(x_prop, chain.x_prev, log_lik, terms),
                    chain._replace(log_phi=None, cache=None))  # no cache kept
    # Gibbs step on the ancestor: inversion of the conditional's CDF with one uniform per chain.
    lj = where(accepted.unsqueeze(-1), lj_prop, lj_cur)
    idx = inverse_cdf(cdf(lj), noise.u_ancestor.unsqueeze(-1))
    return new._replace(x_prev=gather_particles(cloud.x, idx.squeeze(-1))), accepted


# ----------------------------------------------------------------------------- adaptive step
def prior_covariance(cloud: PreviousCloud, motion: MotionModel) -> Tensor:
    """Per-target covariance of the prior mixture ``sum_i w^i N(x_k; F x^i_k, Q)`` (the
    chains' starting law), ``Cov_w(F x^i_k) + Q``: ``(B, K, D, D)`` (float64).

    Needs a :class:`~torchmcmcpf.models.LinearGaussianMotion` (``mean``, ``Q``).
    """
    if not isinstance(motion, LinearGaussianMotion):
        raise ValueError(f"an adaptive random walk needs a LinearGaussianMotion (F, Q), got {type(motion).__name__}")
    m = motion.mean(cloud.x).to(torch.float64)  # (B, N, K, D)
    w = cloud.log_w.to(torch.float64).exp()  # (B, N)
    mean = torch.einsum("bn,bnkd->bkd", w, m)
    dev = m - mean.unsqueeze(1)
    return torch.einsum("bn,bnkd,bnke->bkde", w, dev, dev) + motion.Q.to(torch.float64)


class RunningMoments(NamedTuple):
    """Sums of the chains' states over MCMC iterations, per run and target (pooled over
    chains): ``num_samples ()``, ``s1 (B, K, D)``, ``s2 (B, K, D, D)`` (float64). Haario, Saksman
    and Tamminen (2001), adaptive Metropolis: the proposal covariance follows the history.
    """

    num_samples: Tensor
    s1: Tensor
    s2: Tensor

    @classmethod
    def zeros(cls, x: Tensor) -> RunningMoments:
        """Empty moments for chains ``x (B, C, K, D)``: num_samples 0, sums ``(B, K, D)`` and ``(B, K, D, D)``."""
        b, _, k, d = x.shape
        f64, dev = torch.float64, x.device
        return cls(torch.zeros((), dtype=f64, device=dev), torch.zeros((b, k, d), dtype=f64, device=dev),
                   torch.zeros((b, k, d, d), dtype=f64, device=dev))

    def update(self, x: Tensor) -> RunningMoments:
        """Add the chain states ``x (B, C, K, D)``."""
        x = x.to(torch.float64)
        return RunningMoments(self.num_samples + x.shape[1], self.s1 + x.sum(1),
                              self.s2 + torch.einsum("bckd,bcke->bkde", x, x))

    def covariance(self, prior: Tensor, prior_weight: float) -> Tensor:
        """The history's covariance shrunk towards ``prior (B, K, D, D)`` with the weight of
        ``prior_weight`` samples (a few samples of a D-dimensional chain do not give a
        full-rank covariance): ``(n Cov + n0 prior) / (n + n0)``.
        """
        n = self.num_samples.clamp(min=1.0)
        mean = self.s1 / n
        cov = self.s2 / n - mean.unsqueeze(-1) * mean.unsqueeze(-2)
        return (self.num_samples * cov + prior_weight * prior) / (self.num_samples + prior_weight)


def adapted_step(cov: Tensor, dtype: torch.dtype) -> Tensor:
    """Cholesky factor of the random-walk covariance ``S_k = 2.38^2 / (K D) * cov_k`` of a
    joint move in ``K * D`` dimensions (Roberts, Gelman and Gilks 1997; Haario et al. 2001),
    with a jitter of ``1e-9`` times the mean variance (a component the motion keeps fixed has
    zero variance).

    Parameters
    ----------
    cov : (B, K, D, D) per-target covariance (float64).

    Returns
    -------
    (B, 1, K, D, D) lower-triangular factors in ``dtype`` (the ``scale`` of
    :func:`random_walk_move`).
    """
    k, d = cov.shape[-3], cov.shape[-1]
    cov = 0.5 * (cov + cov.mT)
    jitter = 1e-9 * torch.diagonal(cov, dim1=-2, dim2=-1).mean(-1).clamp(min=1e-12)
    eye = torch.eye(d, dtype=cov.dtype, device=cov.device)
    chol = torch.linalg.cholesky(RW_OPTIMAL / (k * d) * cov + jitter[..., None, None] * eye)
    return chol.to(dtype).unsqueeze(1)
