"""Multitarget SIR track-before-detect particle filter (the baseline).

Boers and Driessen (2004), "Multitarget particle filter track-before-detect application"
(ref. [4] of Bocquel et al. 2012, paper 000, sec. III-B): every particle carries the joint
state of all K targets; the proposal is the motion prior, the weight the likelihood of the
whole frame, and the estimate the weighted mean (paper 000 eq. 6).
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

import torch

from .._native.select import where
from ..models.base import MotionModel, SensorModel
from ..models.existence import BirthDeath, BirthNoise, TargetDynamics
from ..models.multitarget import Exclusion, exclusion_on, log_exclusion
from ..resampling import RESAMPLERS, ess, gather_particles, normalize_ess
from ..state import ParticleState, StepInfo
from ..typing import Measurement, Tensor
from ._bound import Bound, Compile, bind
from .base import Filter

__all__ = ["SIRFilter", "SIRSettings", "sir_step", "sir_body", "sir_program", "bind_sir", "sir_bound_step"]


@dataclass(frozen=True)
class SIRSettings:
    """Settings of the SIR filter.

    Attributes
    ----------
    resample_method : ``"systematic"`` (default), ``"stratified"`` or ``"multinomial"``.
    ess_threshold : resample when ``ESS < ess_threshold * N``; 1.0 resamples at every step
        (Boers and Driessen), 0.0 never.
    exclusion : :class:`~torchmcmcpf.models.multitarget.Exclusion` (default) or None: the
        weights include the exclusion factor ``Phi(x)`` between slots (Khan et al. 2005); None
        is the paper's factorised prior. Ignored for a sensor without ``resolution_coords``.

    Example
    -------
    >>> import torchmcmcpf as tp
    >>> from torchmcmcpf.filters.sir import SIRSettings
    >>> settings = SIRSettings(ess_threshold=0.5)          # resample when ESS < N / 2
    >>> filt = tp.SIRFilter(tp.ConstantVelocity(), tp.LinearGaussian.position(noise_std=1.0), 100, settings=settings)
    >>> filt.settings              # what the filter does: this sensor declares no resolution, so no exclusion
    SIRSettings(resample_method='systematic', ess_threshold=0.5, exclusion=None)
    >>> SIRSettings(resample_method="residual")
    Traceback (most recent call last):
    ...
    ValueError: resample_method must be one of ['multinomial', 'stratified', 'systematic'], got 'residual'
    """

    resample_method: str = "systematic"
    ess_threshold: float = 1.0
    exclusion: Exclusion | None = Exclusion()

    def __post_init__(self):
        if self.resample_method not in RESAMPLERS:
            raise ValueError(f"resample_method must be one of {sorted(RESAMPLERS)}, got {self.resample_method!r}")
        if not 0.0 <= float(self.ess_threshold) <= 1.0:
            raise ValueError(f"ess_threshold must be in [0, 1], got {self.ess_threshold!r}")
        object.__setattr__(self, "ess_threshold", float(self.ess_threshold))


def sir_body(x: Tensor, log_w: Tensor, exists: Tensor | None, z: Measurement, need: Tensor, u: Tensor,
             eps: Tensor, birth: BirthNoise | None, *, dynamics: TargetDynamics, sensor: SensorModel,
             settings: SIRSettings) -> tuple[Tensor, Tensor | None, Tensor]:
    """The body of one SIR step: all of it but its random draws (pure; the filter's program,
    :func:`sir_program`, which ``compile_step=True`` compiles).

    Parameters
    ----------
    x : (B, N, K, D); log_w : (B, N) normalised; exists : (B, N, K) bool or None.
    z : the frame ``(B, *G)``; need : (B,) bool, the runs to resample; u : the resampling
    uniforms (``(B, 1)`` systematic, ``(B, N)`` otherwise); eps : (B, N, K, noise_dim)
    motion noise; birth : :class:`BirthNoise` for ``(B, N)`` (with an existence model) or None.
    dynamics : the slots' joint model (:class:`~torchmcmcpf.models.existence.TargetDynamics`:
    the motion, with births and deaths or not); sensor : the SensorModel; settings :
    :class:`SIRSettings`.

    Returns
    -------
    x : (B, N, K, D) propagated; exists : (B, N, K) or None;
    log_w : (B, N) unnormalised new log-weights ``log w_{k-1} + log p(z | x)`` (normalised
    in eager code, so that compiled and eager steps agree bit for bit).
    """
    n = x.shape[1]
    # Resample the previous cloud where its ESS is low; where not, keep it and its weights.
    # The two fixed thresholds are decided here, statically: resampling every step (Boers and
    # Driessen; the default) or never costs no per-run selection.
    every_step = settings.ess_threshold >= 1.0  # then the weights are -log N after resampling: a constant
    if settings.ess_threshold > 0.0:
        idx = RESAMPLERS[settings.resample_method][1](log_w, u, n)
        if not every_step:
            keep = torch.arange(n, device=x.device).expand_as(idx)
            idx = where(need.unsqueeze(-1), idx, keep)
            log_w = where(need.unsqueeze(-1), torch.full_like(log_w, -math.log(n)), log_w)
        x = gather_particles(x, idx)
        if exists is not None:
            exists = gather_particles(exists, idx)
    # (x, exists) propagated jointly: one code path whatever the number of targets
    x, exists, log_ratio = dynamics.propagate(x, exists, eps, birth)
    log_lik = sensor.log_likelihood(x, z, exists)  # (B, N)
    if exclusion_on(settings.exclusion, sensor):  # else log Phi = 0: no zeros added
        log_lik = log_lik + log_exclusion(settings.exclusion, sensor, x, exists)
    if dynamics.existence is not None:
        log_lik = log_lik + log_ratio.sum(-1)  # the birth correction p_0 / q_0
    return x, exists, (log_lik - math.log(n)) if every_step else log_w + log_lik


def sir_program(dynamics: TargetDynamics, sensor: SensorModel, settings: SIRSettings, compile: Compile = None
                ) -> Callable:
    """:func:`sir_body` with the models bound, ``program(x, log_w, exists, z, need, u, eps,
    birth)``: compiled with ``compile`` (``compile_step=True``), else eager.
    """
    def body(*args: Any) -> tuple[Tensor, Tensor | None, Tensor]:
        return sir_body(*args, dynamics=dynamics, sensor=sensor, settings=settings)
    return body if compile is None else compile(body)


def bind_sir(motion: MotionModel, sensor: SensorModel, settings: SIRSettings | None = None,
             existence: BirthDeath | None = None, *, num_particles: int | None = None, compile: Compile = None
             ) -> Bound:
    """The SIR filter's :class:`~torchmcmcpf.filters._bound.Bound`: the models, ``settings``
    (default :class:`SIRSettings`) as the filter runs them, and the program :func:`sir_program`
    (compiled with ``compile``). ``num_particles`` is accepted for the common bind signature
    (no setting depends on it).
    """
    return bind(motion, sensor, SIRSettings() if settings is None else settings, existence,
                program=lambda b, c: sir_program(b.dynamics, b.sensor, b.settings, c), compile=compile)


def sir_bound_step(state: ParticleState, z: Measurement, bound: Bound, *, generator: torch.Generator
                   ) -> tuple[ParticleState, StepInfo]:
    """One SIR step (:func:`sir_step`) with everything but the state, the frame and the
    generator resolved beforehand in ``bound`` (:func:`bind_sir`): resample (when ESS <
    ``ess_threshold * N``), propagate, weight.

    Parameters
    ----------
    state : ParticleState with ``x (B, N, K, D)``, normalised ``log_w (B, N)`` and, with an
        existence model, ``exists (B, N, K)`` (None: every slot starts inactive).
    z : one measurement per run, ``(B, *G)``.
    bound : :class:`~torchmcmcpf.filters._bound.Bound` of :func:`bind_sir` (its ``program``
        is :func:`sir_body` with the models bound, compiled or eager).
    generator : source of randomness (every draw is made here, in eager code).

    Returns
    -------
    ``(state, info)`` as :func:`sir_step`.
    """
    settings, dynamics = bound.settings, bound.dynamics
    x, log_w, exists = state.x, state.log_w, state.exists
    b, n, k, _ = x.shape
    draw, _ = RESAMPLERS[settings.resample_method]
    u = draw(b, n, generator=generator, device=x.device)
    eps, birth, _ = dynamics.draw_noise(x, z, generator=generator)
    # ESS in eager code (1.0 and 0.0 decided statically, never by round-off at ESS = N)
    if settings.ess_threshold >= 1.0 or settings.ess_threshold <= 0.0:
        need = torch.full((b,), settings.ess_threshold >= 1.0, device=x.device)
    else:
        need = ess(log_w) < settings.ess_threshold * n  # (B,)
    x, exists, log_w = bound.program(x, log_w, exists, z, need, u, eps, birth)
    log_w_new, log_mean, ess_new = normalize_ess(log_w)
    # log p(z_k | z_1:k-1) ~= log sum_i w_{k-1}^i p(z_k | x_k^i), w_{k-1} normalised
    log_evidence = log_mean + math.log(n)
    return ParticleState(x, log_w_new, exists), StepInfo.make(log_evidence, ess=ess_new, log_evidence=log_evidence)


def sir_step(
    state: ParticleState,
    z: Measurement,
    *,
    motion: MotionModel,
    sensor: SensorModel,
    settings: SIRSettings = SIRSettings(),
    generator: torch.Generator,
    existence: BirthDeath | None = None,
) -> tuple[ParticleState, StepInfo]:
    """One SIR step: resample (when ESS < ``ess_threshold * N``), propagate, weight
    (:func:`sir_bound_step` after an eager :func:`bind_sir`; a filter binds once).

    Parameters
    ----------
    state : ParticleState with ``x (B, N, K, D)`` and normalised ``log_w (B, N)``.
    z : one measurement per run, ``(B, *G)``.
    motion, sensor : the models; settings : :class:`SIRSettings`.
    generator : source of randomness (every draw is made here, in eager code).
    existence : BirthDeath, optional: an unknown number of targets. ``(x, exists)`` are
        propagated jointly (:class:`~torchmcmcpf.models.existence.TargetDynamics`, births near
        the points of ``z`` when it draws them so, with the weight correction ``p_0 / q_0``);
        ``state.exists`` None means every slot starts inactive (paper 004 sec. 5).

    Returns
    -------
    state : the weighted particles at time k (``log_w`` normalised).
    info : ``ess (B,)`` of the new weights, ``log_evidence (B,)``, the estimate of
        ``log p(z_k | z_{1:k-1})`` (relative to the sensor's "no target" hypothesis for
        likelihood-ratio sensors; with ``settings.exclusion`` the weights, hence this
        estimate, include the exclusion factor ``Phi``); ``acceptance`` NaN (no MH step); no
        extras.

    An all-underflowing set of weights does not produce NaN: weights stay in log space and
    a run whose likelihoods are all ``-inf`` keeps uniform weights (``log_evidence = -inf``).
    """
    return sir_bound_step(state, z, bind_sir(motion, sensor, settings, existence), generator=generator)


class SIRFilter(Filter):
    """Multitarget SIR TBD particle filter for a known number of targets, or for an unknown
    one with ``existence`` (K = N_max slots with existence flags).

    Parameters
    ----------
    motion : MotionModel applied to every target slot.
    sensor : SensorModel (radar TBD, Swerling-I, pixels, LinearGaussian, ...).
    num_particles : N >= 1.
    settings : :class:`SIRSettings`, optional; its fields ``resample_method``,
        ``ess_threshold``, ``exclusion`` are also keywords of the constructor.
    existence : BirthDeath, optional: births and deaths (see :func:`sir_step`); the
        estimate of a slot is then its mean given existence.
    compile_step : compile :func:`sir_body` (the whole step but its random draws;
        :func:`sir_program`).

    Notes
    -----
    ``StepInfo``: ``ess``, ``log_evidence``; ``acceptance`` NaN; ``extras`` empty.

    Example
    -------
    One target moving at ``(1, 0.5)`` m/s, resampled when the ESS falls below N / 2:

    >>> import torch
    >>> import torchmcmcpf as tp
    >>> g = torch.Generator().manual_seed(0)
    >>> z = torch.tensor([[1.0, 0.5], [2.0, 1.0], [3.0, 1.5]])[:, None, None]   # (T, B, K, 2) positions
    >>> init = torch.tensor([0.0, 1.0, 0.0, 0.5]) + 0.3 * torch.randn(1, 500, 1, 4, generator=g)  # (B, N, K, D)
    >>> filt = tp.SIRFilter(tp.ConstantVelocity(dt=1.0, q=0.1), tp.LinearGaussian.position(noise_std=0.5), 500,
    ...                     ess_threshold=0.5)
    >>> result = filt(z, init=init, generator=g)
    >>> bool((result.mean[-1, 0, 0, ::2] - torch.tensor([3.0, 1.5])).abs().max() < 0.5)   # [x, vx, y, vy]
    True
    >>> result.log_evidence.shape                     # (B,): log p(z_1:T), the SIR filter's estimate
    torch.Size([1])
    """

    compile_seconds = 20.0  # benchmarks/bench_compile.py, 5-target ground radar, 2 CPU cores
    settings_class = SIRSettings
    bind = staticmethod(bind_sir)
    bound_step = staticmethod(sir_bound_step)
