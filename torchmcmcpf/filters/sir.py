"""Multitarget SIR track-before-detect particle filter (the baseline).

Boers and Driessen (2004), "Multitarget particle filter track-before-detect application"
(ref. [4] of Bocquel et al. 2012, paper 000, sec. III-B): every particle carries the joint
state of all K targets; the proposal is the motion prior, the weight the likelihood of the
whole frame, and the estimate the weighted mean (paper 000 eq. 6).
"""

from __future__ import annotations

import math
from typing import Optional

import torch

from .._validation import check_positive_int
from ..models.base import MotionModel, SensorModel
from ..models.existence import BirthDeath
from ..resampling import RESAMPLERS, ess, gather_particles, normalize, resample
from ..state import ParticleState, StepInfo
from ..typing import Measurement
from .base import Filter, check_existence

__all__ = ["SIRFilter", "sir_step"]


def sir_step(
    state: ParticleState,
    z: Measurement,
    *,
    motion: MotionModel,
    sensor: SensorModel,
    generator: torch.Generator,
    resample_method: str = "systematic",
    ess_threshold: float = 1.0,
    existence: Optional[BirthDeath] = None,
) -> tuple[ParticleState, StepInfo]:
    """One SIR step: resample (when ESS < ``ess_threshold * N``), propagate, weight.

    Parameters
    ----------
    state : ParticleState with ``x (B, N, K, D)`` and normalised ``log_w (B, N)``.
    z : one measurement per run, ``(B, *G)``.
    motion, sensor : the models.
    generator : source of randomness.
    resample_method : ``"systematic"``, ``"stratified"`` or ``"multinomial"``.
    ess_threshold : resample when ``ESS < ess_threshold * N``; 1.0 resamples at every
        step (Boers and Driessen), 0.0 never.
    existence : BirthDeath, optional: an unknown number of targets. ``(x, exists)`` are
        propagated jointly by ``existence.propose`` (births near the points of ``z`` when it
        draws them so, with the weight correction ``p_0 / q_0``); ``state.exists`` None
        means every slot starts inactive (paper 004 sec. 5).

    Returns
    -------
    state : the weighted particles at time k (``log_w`` normalised).
    info : ``ess (B,)`` of the new weights and ``log_evidence (B,)``, the estimate of
        ``log p(z_k | z_{1:k-1})`` (relative to the sensor's "no target" hypothesis for
        likelihood-ratio sensors).

    An all-underflowing set of weights does not produce NaN: weights stay in log space and
    a run whose likelihoods are all ``-inf`` keeps uniform weights (``log_evidence = -inf``).
    """
    x, log_w, exists = state
    n = x.shape[1]
    # Resample the previous cloud where its ESS is low; where not, keep it and its weights.
    need = ess(log_w) < ess_threshold * n  # (B,)
    idx = resample(log_w, resample_method, generator=generator)
    keep = torch.arange(n, device=x.device).expand_as(idx)
    idx = torch.where(need.unsqueeze(-1), idx, keep)
    x = gather_particles(x, idx)
    if exists is not None:
        exists = gather_particles(exists, idx)
    log_w = torch.where(need.unsqueeze(-1), torch.full_like(log_w, -math.log(n)), log_w)

    if existence is None:
        x = motion.sample(x, generator=generator)
        log_lik = sensor.log_likelihood(x, z, exists)  # (B, N)
    else:
        if exists is None:
            exists = torch.zeros(x.shape[:-1], dtype=torch.bool, device=x.device)
        x, exists, log_ratio = existence.propose(x, exists, motion=motion, generator=generator, z=z)
        log_lik = sensor.log_likelihood(x, z, exists) + log_ratio.sum(-1)  # (B, N)
    log_w_new, log_mean = normalize(log_w + log_lik)
    # log p(z_k | z_1:k-1) ~= log sum_i w_{k-1}^i p(z_k | x_k^i), w_{k-1} normalised
    log_evidence = log_mean + math.log(n)
    return ParticleState(x, log_w_new, exists), StepInfo(ess=ess(log_w_new), log_evidence=log_evidence)


class SIRFilter(Filter):
    """Multitarget SIR TBD particle filter for a known number of targets, or for an unknown
    one with ``existence`` (K = N_max slots with existence flags).

    Parameters
    ----------
    motion : MotionModel applied to every target slot.
    sensor : SensorModel (radar TBD, Swerling-I, pixels, LinearGaussian, ...).
    num_particles : N >= 1.
    resample_method : ``"systematic"`` (default), ``"stratified"``, ``"multinomial"``.
    ess_threshold : resample when ESS < ``ess_threshold * N`` (1.0: every step).
    existence : BirthDeath, optional: births and deaths (see :func:`sir_step`); the
        estimate of a slot is then its mean given existence
        (:func:`torchmcmcpf.models.existence.existence_estimate`).

    Example
    -------
    >>> filt = SIRFilter(ConstantVelocity(1.0, 1.0), LinearGaussian.position(1.0), 500)
    >>> result = filt(z, init=x0, generator=torch.Generator().manual_seed(0))  # doctest: +SKIP
    """

    def __init__(
        self,
        motion: MotionModel,
        sensor: SensorModel,
        num_particles: int,
        *,
        resample_method: str = "systematic",
        ess_threshold: float = 1.0,
        existence: Optional[BirthDeath] = None,
    ):
        super().__init__(motion, sensor)
        self.existence = check_existence(existence)
        self.num_particles = check_positive_int(num_particles, "num_particles")
        if resample_method not in RESAMPLERS:
            raise ValueError(f"resample_method must be one of {sorted(RESAMPLERS)}, got {resample_method!r}")
        if not 0.0 <= float(ess_threshold) <= 1.0:
            raise ValueError(f"ess_threshold must be in [0, 1], got {ess_threshold!r}")
        self.resample_method = resample_method
        self.ess_threshold = float(ess_threshold)

    def step(self, state: ParticleState, z: Measurement, *, generator: torch.Generator
             ) -> tuple[ParticleState, StepInfo]:
        """One SIR step (see :func:`sir_step`); ``state.x`` is ``(B, N, K, D)``."""
        return sir_step(
            state, z, motion=self.motion, sensor=self.sensor, generator=generator,
            resample_method=self.resample_method, ess_threshold=self.ess_threshold,
            existence=self.existence,
        )

    def extra_repr(self) -> str:
        return f"num_particles={self.num_particles}, resample_method={self.resample_method!r}"
