"""HMC refinement of the target states inside the MCMC filters (issue 13, item 5).

One Hamiltonian Monte Carlo transition (:func:`~torchmcmcpf.kernels.hmc.hmc_transition`:
Gaussian momenta, leapfrog, Metropolis accept/reject) on the states ``x (B, C, K, D)`` of
C chains per run, every slot and every state dimension at once (positions, velocities and,
for the radar, the amplitude), with gradients of the sensor log-likelihood from autograd
(``torch.autograd.grad``, eager; the radar TBD likelihood is differentiable through its
windowed path, its gradients agree with finite differences). The target density is the
filter's own MCMC target, so the move can be mixed with the filter's other moves without
changing what the chains sample:

- :class:`~torchmcmcpf.filters.mcmc.MCMCFilter` samples ``(x_k, a)`` from
  ``pi(x_k, a) ∝ p(z_k | x_k) w^a p(x_k | x_{k-1}^a)`` (paper 002 eq. 11 with the ancestor
  index ``a``). The HMC move updates ``x_k`` given the chain's ancestor, i.e. targets the
  conditional ``pi(x_k | a) ∝ p(z_k | x_k) prod_j p(x_{k,j} | x_{k-1,j}^a)``
  (:func:`ancestor_log_prior`); a conditional update leaves the joint invariant.
- :class:`~torchmcmcpf.filters.ipmcmc.IPMCMCFilter` samples the factorised-prior posterior
  ``pi(y) ∝ p(z_k | y) prod_j m_j(y_j)``, ``m_j(y_j) = sum_i w^i p(y_j | x_{k-1,j}^i)``
  (see :mod:`torchmcmcpf.filters.ipmcmc`); the HMC move targets exactly that
  (:func:`mixture_log_prior`, a log-sum-exp over the N previous particles per slot).

Scales: the state dimensions have very different posterior scales (metres, m/s, the
amplitude), so the leapfrog step is ``step_size * sqrt(diag Q)`` per dimension (Q the
motion's process noise covariance): a diagonal preconditioning, equivalent to unit-mass
HMC in coordinates ``x_d / sqrt(Q_dd)``, which keeps the move exact (volume-preserving and
reversible). Needs a :class:`~torchmcmcpf.models.motion.LinearGaussianMotion` (``Q``,
``log_prob``) and a known number of targets (no existence flags).
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass
from typing import NamedTuple

import torch

from .._native.select import where
from .._validation import check_positive, check_positive_int
from ..models.base import MotionModel, SensorModel
from ..models.existence import BirthDeath
from ..models.motion import LinearGaussianMotion
from ..models.multitarget import Exclusion, exclusion_on, log_exclusion
from ..typing import Measurement, Tensor
from .hmc import hmc_transition, value_and_grad

__all__ = ["HMCRefine", "HMCRefineNoise", "hmc_refine", "ancestor_log_prior", "mixture_log_prior",
           "check_hmc_motion", "with_exclusion"]


@dataclass(frozen=True)
class HMCRefine:
    """Settings of the HMC refinement move.

    Attributes
    ----------
    step_size : leapfrog step in units of the process noise standard deviations
        ``sqrt(diag Q)`` per state dimension (> 0).
    num_leapfrog : leapfrog steps per transition (>= 1).
    every : one HMC transition of every chain after every ``every``-th iteration of the
        filter's own kernel (IP-MCMC: the exchange move; MCMCFilter: its move mixture).

    The defaults suit a unit-scale linear-Gaussian problem. On the radar scene the doppler
    likelihood is far sharper than ``sqrt(Q)`` in velocity: ``step_size=0.05`` gives an
    acceptance of 0.98, ``0.5`` accepts nothing (README, "Reproducing the papers").

    Example
    -------
    >>> import torch
    >>> import torchmcmcpf as tp
    >>> from torchmcmcpf.kernels import HMCRefine
    >>> settings = HMCRefine(step_size=0.5, num_leapfrog=3, every=2)
    >>> filt = tp.MCMCFilter(tp.ConstantVelocity(), tp.LinearGaussian.position(noise_std=1.0), 64, num_chains=4,
    ...                      burn_in=2, hmc=settings)         # an HMC transition every 2nd iteration
    >>> filt(torch.zeros(2, 1, 1, 2), init=torch.zeros(1, 64, 1, 4), generator=torch.Generator()).mean.shape
    torch.Size([2, 1, 1, 4])
    >>> HMCRefine(every=0)
    Traceback (most recent call last):
    ...
    ValueError: hmc.every must be an integer >= 1, got 0
    """

    step_size: float = 0.5
    num_leapfrog: int = 3
    every: int = 10

    def __post_init__(self):
        object.__setattr__(self, "step_size", check_positive(self.step_size, "hmc.step_size"))
        object.__setattr__(self, "num_leapfrog", check_positive_int(self.num_leapfrog, "hmc.num_leapfrog"))
        object.__setattr__(self, "every", check_positive_int(self.every, "hmc.every"))


def check_hmc_motion(motion: MotionModel, existence: BirthDeath | None) -> LinearGaussianMotion:
    """The move needs a linear-Gaussian motion (``Q``, ``log_prob``) and no existence model.

    Returns ``motion``, narrowed to :class:`~torchmcmcpf.models.LinearGaussianMotion`.
    """
    if not isinstance(motion, LinearGaussianMotion):
        raise ValueError(f"hmc= needs a LinearGaussianMotion (Q and log_prob) as motion, got {type(motion).__name__}")
    if existence is not None:
        raise ValueError("hmc= is not available with an existence model (births and deaths)")
    return motion


class HMCRefineNoise(NamedTuple):
    """Pre-drawn randomness of one HMC transition: momenta ``p (B, C, K, D)`` and accept
    uniforms ``u (B, C)``.

    Example
    -------
    >>> import torch
    >>> import torchmcmcpf as tp
    >>> from torchmcmcpf.kernels import HMCRefine, HMCRefineNoise, hmc_refine
    >>> from torchmcmcpf.kernels.hmc_refine import ancestor_log_prior
    >>> motion, sensor = tp.ConstantVelocity(), tp.LinearGaussian.position(noise_std=1.0)
    >>> x, z = torch.zeros(2, 8, 3, 4), torch.zeros(2, 3, 2)     # chains (B, C, K, D), a frame
    >>> noise = HMCRefineNoise.draw(x, generator=torch.Generator().manual_seed(0))
    >>> noise.p.shape, noise.u.shape
    (torch.Size([2, 8, 3, 4]), torch.Size([2, 8]))
    >>> x_new, log_lik, accepted = hmc_refine(x, sensor.log_likelihood(x, z), noise, z, sensor=sensor, motion=motion,
    ...                                       log_prior=ancestor_log_prior(x, motion), settings=HMCRefine())
    >>> x_new.shape, accepted.shape
    (torch.Size([2, 8, 3, 4]), torch.Size([2, 8]))
    """

    p: Tensor
    u: Tensor

    @classmethod
    def draw(cls, x: Tensor, *, generator: torch.Generator, leading: tuple = ()) -> HMCRefineNoise:
        """For chains shaped like ``x (B, C, K, D)``, with optional extra leading dims."""
        p = torch.randn(leading + tuple(x.shape), generator=generator, device=x.device, dtype=x.dtype)
        u = torch.rand(leading + tuple(x.shape[:2]), generator=generator, device=x.device, dtype=x.dtype)
        return cls(p, u)


def _whitening(motion: LinearGaussianMotion, like: Tensor) -> tuple[Tensor, Tensor]:
    """``L^-1`` (``Q = L L^T``) and ``log N``'s constant ``-D/2 log 2 pi - sum log L_dd``:
    the Gaussian log-density by a matrix product, not a batched triangular solve (whose
    backward under ``torch.func.grad`` costs seconds for thousands of chains).
    """
    L = motion.L.to(like.dtype)
    d = L.shape[0]
    L_inv = torch.linalg.solve_triangular(L, torch.eye(d, dtype=like.dtype, device=like.device), upper=False)
    return L_inv, -0.5 * d * math.log(2 * math.pi) - torch.log(torch.diagonal(L)).sum()


def ancestor_log_prior(x_prev: Tensor, motion: LinearGaussianMotion) -> Callable[[Tensor], Tensor]:
    """``x (B, C, K, D) -> sum_j log N(x_j; F x_prev_j, Q)`` ``(B, C)``, with the chains'
    ancestors ``x_prev (B, C, K, D)`` (MCMCFilter's conditional target; equals
    ``motion.log_prob(x, x_prev).sum(-1)``).
    """
    L_inv, log_norm = _whitening(motion, x_prev)
    white_prev = motion.mean(x_prev) @ L_inv.mT

    def log_prior(x: Tensor) -> Tensor:
        return (log_norm - 0.5 * (x @ L_inv.mT - white_prev).square().sum(-1)).sum(-1)
    return log_prior


def mixture_log_prior(x_prev: Tensor, log_w: Tensor, motion: LinearGaussianMotion) -> Callable[[Tensor], Tensor]:
    """``y (B, C, K, D) -> sum_j log m_j(y_j)`` ``(B, C)``, ``m_j(y_j) = sum_i w^i N(y_j; F
    x_prev^i_j, Q)`` over the previous cloud ``x_prev (B, N, K, D)``, ``log_w (B, N)``
    normalised (IP-MCMC's factorised prior). Whitened once (``Q = L L^T``): memory
    ``B C N K D`` per evaluation.
    """
    L_inv, log_norm = _whitening(motion, x_prev)
    white_prev = motion.mean(x_prev) @ L_inv.mT  # (B, N, K, D)

    def log_prior(y: Tensor) -> Tensor:
        r = (y @ L_inv.mT).unsqueeze(2) - white_prev.unsqueeze(1)  # (B, C, N, K, D)
        lp = log_norm - 0.5 * r.square().sum(-1)  # (B, C, N, K)
        return torch.logsumexp(lp + log_w[:, None, :, None], dim=2).sum(-1)
    return log_prior


def with_exclusion(log_prior: Callable[[Tensor], Tensor], exclusion: Exclusion | None, sensor: SensorModel
                   ) -> Callable[[Tensor], Tensor]:
    """``log_prior`` plus the exclusion term ``log Phi(x)`` (:mod:`torchmcmcpf.models.multitarget`),
    differentiable, so the HMC move targets the filter's target with exclusion; ``log_prior``
    itself when the term is off.
    """
    if not exclusion_on(exclusion, sensor):
        return log_prior

    def log_prior_excl(x: Tensor) -> Tensor:
        return log_prior(x) + log_exclusion(exclusion, sensor, x)
    return log_prior_excl


def hmc_refine(x: Tensor, log_lik: Tensor, noise: HMCRefineNoise, z: Measurement, *, log_prior: Callable,
               sensor: SensorModel, motion: LinearGaussianMotion, settings: HMCRefine
               ) -> tuple[Tensor, Tensor, Tensor]:
    """One HMC transition of every chain on ``log p(z | x) + log_prior(x)``.

    Parameters
    ----------
    x : (B, C, K, D) chain states; log_lik : (B, C) ``sensor.log_likelihood(x, z)``.
    noise : :class:`HMCRefineNoise`; z : the frame.
    log_prior : ``(B, C, K, D) -> (B, C)``, :func:`ancestor_log_prior` or
        :func:`mixture_log_prior`.
    sensor, motion : the models; settings : :class:`HMCRefine`.

    Returns
    -------
    x : (B, C, K, D) new states; log_lik : (B, C) their log-likelihoods (re-evaluated, so
    a chain's cached value stays exactly ``sensor.log_likelihood``); accepted : (B, C) bool.
    """
    def log_target(q):
        return sensor.log_likelihood(q, z) + log_prior(q)

    # eager autograd (torch.autograd.grad): torch.func.grad falls back to a slow per-sample
    # path for batched triangular solves (seconds instead of milliseconds for 3000 chains)
    scale = torch.diagonal(motion.Q.to(x.dtype)).sqrt() * settings.step_size  # (D,)
    value, grad = value_and_grad(log_target, x)
    x_new, _, _, accepted = hmc_transition(x, value, grad, noise.p, noise.u, log_target=log_target,
                                           step_size=scale, num_leapfrog=settings.num_leapfrog)
    log_lik_new = where(accepted, sensor.log_likelihood(x_new, z), log_lik)
    return x_new, log_lik_new, accepted
