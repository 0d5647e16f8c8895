"""Independent-partition particle filter: one SIR partition per target, resampled per target.

The classic stronger baseline cited by paper 000 (refs. [3], [6]): Orton and Fitzgerald
(2002), "A Bayesian approach to tracking multiple targets using sensor arrays and particle
filters", and Kreucher, Kastella and Hero (2005), "Multitarget tracking using the joint
multitarget probability density" (the *independent partitions* proposal). A joint SIR
filter (Boers and Driessen) weights each particle by the likelihood of the whole frame, so
with K targets a particle is only as good as its worst target and the ESS collapses
exponentially in K. Here every particle still holds all K targets, but each target slot
``k`` (a *partition*) is weighted and resampled on its own:

1. propose every partition from the motion prior, ``x_k^i ~ p(x_k | x_{k,t-1}^i)``;
2. weight partition ``k`` of particle ``i`` by the likelihood with the other targets fixed at
   a reference, ``w_k^i ∝ p(z_t | x_k^i, x_{-k} = hat x_{-k})``, where ``hat x`` is the noise-
   free prediction of the previous posterior mean; only the ratio to ``p(z_t | hat x)``
   matters, computed by
   :meth:`~torchmcmcpf.models.base.SensorModel.log_likelihood_slot_changes` (grid sensors:
   one amplitude grid of the reference per run, then the cells of slot k's new box only).
   For a sensor whose targets do not interact (``sensor.separable``) the weight is target
   k's own term, exactly;
3. resample each partition with its own weights, independently of the other partitions.

Re-capture (``settings.recapture``, on by default for a data-driven sensor). A partition
whose target has left its prediction (two slots on one target, or a target lost) cannot come
back by its motion proposal alone. Each step, the one partition that explains least of the
frame, ``argmin_k [log p(z | hat x) - log p(z | hat x without slot k)]`` (a function of the
reference and the frame only), draws its particles from a mixture: the prediction with
probability ``1 - epsilon``, the frame's data-driven density ``g`` with probability
``epsilon`` (``Recapture.p_propose``); its weights gain the heavy-tailed slot prior over
that proposal, ``r = (1 - delta) / (1 - epsilon)`` or ``delta p_0 / (epsilon g)``
(:func:`~torchmcmcpf.models.multitarget.relocate`: importance sampling on the particle and its
component label). Only one partition a step: every partition is weighed against the others'
*previous* references, so a power that no slot explains would draw every partition that can
gain by it, each abandoning its own target (measured: nine of ten partitions at once,
docs/tracks.md). The other partitions keep the motion proposal (their weights gain the
constant ``1 - delta``).

Approximation. The filter represents the posterior as the product of per-target marginals,
``p(x_1..x_K | z_{1:t}) ~ prod_k p(x_k | z_{1:t})``, and each marginal's weight conditions on
the other targets at their predicted estimates instead of integrating over them. Both are
exact when the targets' point spreads do not overlap (the TBD log-likelihood ratio is a sum
over cells, and a cell then depends on at most one target) and for separable sensors; with
crossing targets the reference is only as good as the prediction. The filter does not
estimate the joint evidence (``log_evidence`` is NaN). Known number of targets only.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

import torch

from ..models.base import MotionModel, SensorModel
from ..models.existence import BirthDeath
from ..models.multitarget import (
    Exclusion,
    Recapture,
    RelocationNoise,
    check_exclusion,
    check_recapture,
    draw_relocation,
    exclusion_against,
    relocate,
)
from ..resampling import RESAMPLERS, ess, normalize
from ..state import ParticleState, StepInfo, weighted_mean
from ..typing import Measurement, Tensor
from ._bound import Bound, Compile, bind
from .base import Filter

__all__ = ["PartitionedSIRFilter", "PartitionedSIRSettings", "partitioned_sir_step", "bind_partitioned_sir",
           "partitioned_sir_bound_step", "partitioned_sir_body", "partitioned_sir_program", "clairvoyant_partitions"]


@dataclass(frozen=True)
class PartitionedSIRSettings:
    """Settings of :class:`PartitionedSIRFilter`.

    Attributes
    ----------
    resample_method : ``"systematic"`` (default), ``"stratified"`` or ``"multinomial"``,
        applied to each partition (every step: the partitions carry no joint weights).
    exclusion : :class:`~torchmcmcpf.models.multitarget.Exclusion` (default) or None: the
        weight of partition ``k`` includes ``prod_{l != k} phi(x_k, hat x_l)``, the exclusion
        factors against the other targets at the reference (Khan et al. 2005).
    recapture : :class:`~torchmcmcpf.models.multitarget.Recapture` (default) or None: the
        partition that explains least of the frame draws a share ``p_propose`` of its
        particles from the frame's data (module docstring; ``p_jump`` and ``p_propose`` are
        used, the IP-MCMC two-slot fields are not). Turned off for a sensor without a
        data-driven proposal (:func:`~torchmcmcpf.filters.base.active_prior`).

    Example
    -------
    >>> import torchmcmcpf as tp
    >>> from torchmcmcpf.filters.partitioned import PartitionedSIRSettings
    >>> PartitionedSIRSettings(resample_method="stratified", recapture=None)
    PartitionedSIRSettings(resample_method='stratified', exclusion=Exclusion(scale=1.0), recapture=None)
    >>> filt = tp.PartitionedSIRFilter(tp.ConstantVelocity(), tp.LinearGaussian.position(noise_std=1.0), 100)
    >>> filt.settings      # a sensor without resolution or data-driven proposal: both prior terms off
    PartitionedSIRSettings(resample_method='systematic', exclusion=None, recapture=None)
    """

    resample_method: str = "systematic"
    exclusion: Exclusion | None = Exclusion()
    recapture: Recapture | None = Recapture()

    def __post_init__(self):
        if self.resample_method not in RESAMPLERS:
            raise ValueError(f"resample_method must be one of {sorted(RESAMPLERS)}, got {self.resample_method!r}")
        check_exclusion(self.exclusion)
        check_recapture(self.recapture)


def least_explained(sensor: SensorModel, ref: Tensor, z: Measurement) -> Tensor:
    """The partition that explains least of the frame: ``(B, K)`` bool, one True per run, at
    ``argmin_k [log p(z | ref) - log p(z | ref without slot k)]`` (K one-slot removals of
    the reference ``ref (B, K, D)``; a slot on no target, or sharing one, explains least).
    """
    b, k, d = ref.shape
    refs = ref.unsqueeze(1).expand(b, k, k, d)  # (B, K, K, D): the reference once per removed slot
    slots = torch.arange(k, device=ref.device).expand(b, k)
    present = torch.ones(b, k, k, dtype=torch.bool, device=ref.device)
    removed = torch.zeros(b, k, dtype=torch.bool, device=ref.device)
    loss = sensor.log_likelihood_delta(refs, ref, slots, z, exists=present, exists_n=removed)  # (B, K) <= 0 mostly
    return torch.nn.functional.one_hot(loss.argmax(-1), k).bool()


def partitioned_sir_body(x: Tensor, log_w: Tensor, z: Measurement, u: Tensor, eps: Tensor,
                         reference: Tensor | None = None, relocation: RelocationNoise | None = None, *,
                         motion: MotionModel, sensor: SensorModel,
                         settings: PartitionedSIRSettings) -> tuple[Tensor, Tensor]:
    """The body of one independent-partition step, all of it but its random draws (pure; the
    program ``compile_step=True`` compiles): propose, weight each partition, resample each
    partition.

    Parameters
    ----------
    x : (B, N, K, D) previous particles; log_w : (B, N) their normalised log-weights.
    z : the frame ``(B, *G)``; u : the resampling uniforms of the B * K partitions
    (``(B * K, 1)`` systematic, ``(B * K, N)`` otherwise); eps : (B, N, K, noise_dim) motion noise.
    reference : (B, K, D) the state the other targets are fixed at; default (None) the
    noise-free prediction of the previous posterior mean. Given the true states, the filter
    is the studies' clairvoyant reference (:func:`clairvoyant_partitions`).
    relocation : :class:`~torchmcmcpf.models.multitarget.RelocationNoise` with leading
    ``(B, N, K)``, the re-capture's draws (needed when ``settings.recapture`` is set).

    Returns
    -------
    x : (B, N, K, D) the resampled partitions; log_lik : (B, K, N) each partition's
    unnormalised log-weights before resampling (their ESS is taken in eager code, so that
    compiled and eager steps agree bit for bit).
    """
    b, n, k, _ = x.shape
    ref = reference  # (B, K, D)
    if ref is None:  # the noise-free prediction of the previous posterior mean
        ref = motion.propagate(weighted_mean(x, log_w), torch.zeros_like(eps[:, 0]))
    x_prop = motion.propagate(x, eps)  # every partition from the motion prior
    log_r: Tensor | float = 0.0  # (B, N, K) with re-capture: the slot prior over the proposal
    if settings.recapture is not None:  # one partition's particles partly drawn from the data
        if relocation is None:
            raise ValueError("relocation must be given when settings.recapture is set")
        free = least_explained(sensor, ref, z).unsqueeze(1).expand(b, n, k)  # (B, N, K)
        x_prop, log_r, _ = relocate(x_prop, free, relocation, settings.recapture, sensor)
    # p(z | x_k, x_-k = ref) / p(z | ref) (B, N, K); target k's own term for a separable sensor
    log_lik = sensor.log_likelihood_slot_changes(ref, x_prop, z) + log_r  # (B, N, K)
    log_lik = (log_lik + exclusion_against(settings.exclusion, sensor, x_prop, ref)).transpose(1, 2)  # (B, K, N)
    log_w_part, _ = normalize(log_lik.reshape(b * k, n))  # (B * K, N)
    idx = RESAMPLERS[settings.resample_method][1](log_w_part, u, n).reshape(b, k, n)
    x_new = torch.gather(x_prop.transpose(1, 2), 2, idx.unsqueeze(-1).expand(b, k, n, x.shape[-1]))
    return x_new.transpose(1, 2), log_lik


def partitioned_sir_program(motion: MotionModel, sensor: SensorModel, settings: PartitionedSIRSettings,
                            compile: Compile = None) -> Callable:
    """The independent-partition filter's program: :func:`partitioned_sir_body` with the
    models bound, ``program(x, log_w, z, u, eps, reference, relocation)``, compiled with
    ``compile`` (``compile_step=True``), else eager.
    """
    def body(*args: Any) -> tuple[Tensor, Tensor]:
        return partitioned_sir_body(*args, motion=motion, sensor=sensor, settings=settings)
    return body if compile is None else compile(body)


def bind_partitioned_sir(motion: MotionModel, sensor: SensorModel, settings: PartitionedSIRSettings | None = None,
                         existence: BirthDeath | None = None, *, num_particles: int | None = None,
                         compile: Compile = None) -> Bound:
    """The independent-partition filter's :class:`~torchmcmcpf.filters._bound.Bound`: the
    models (``existence`` must be None: a known number of targets), ``settings`` (default
    :class:`PartitionedSIRSettings`) as the filter runs them, and the program
    (:func:`partitioned_sir_program`, compiled with ``compile``). ``num_particles`` is
    accepted for the common bind signature (no setting depends on it).
    """
    if existence is not None:
        raise ValueError("existence must be None: the independent-partition filter tracks a known number of targets")
    return bind(motion, sensor, PartitionedSIRSettings() if settings is None else settings, None,
                program=lambda b, c: partitioned_sir_program(b.motion, b.sensor, b.settings, c), compile=compile)


def partitioned_sir_bound_step(state: ParticleState, z: Measurement, bound: Bound, *, generator: torch.Generator,
                               reference: Tensor | None = None) -> tuple[ParticleState, StepInfo]:
    """One independent-partition step (module docstring: weighting and approximation) with
    everything but the state, the frame and the generator resolved in ``bound``.

    Parameters
    ----------
    state : ParticleState with ``x (B, N, K, D)`` and normalised ``log_w (B, N)``.
    z : one measurement per run, ``(B, *G)``.
    bound : :class:`~torchmcmcpf.filters._bound.Bound` of :func:`bind_partitioned_sir`: the
        models, :class:`PartitionedSIRSettings` and the program (:func:`partitioned_sir_body`
        with the models bound, compiled by ``PartitionedSIRFilter(compile_step=True)``).
    generator : source of randomness (motion noise, resampling uniforms, the re-capture's
        draws; drawn here, eagerly).
    reference : (B, K, D), optional: the states the other targets are fixed at (default: the
        noise-free prediction of the previous posterior mean; :func:`partitioned_sir_body`).

    Returns
    -------
    state : the resampled particles, equal weights ``-log N``.
    info : ``ess (B,)`` the mean over targets of the partitions' ESS before resampling;
        ``log_evidence`` and ``acceptance`` NaN; extras ``ess_min (B,)``, the smallest
        partition ESS.
    """
    motion, sensor, settings = bound.motion, bound.sensor, bound.settings
    x, log_w = state.x, state.log_w
    b, n, k, _ = x.shape
    draw, _ = RESAMPLERS[settings.resample_method]
    u = draw(b * k, n, generator=generator, device=x.device)
    eps = torch.randn(x.shape[:-1] + (motion.noise_dim,), generator=generator, device=x.device, dtype=x.dtype)
    relocation = draw_relocation(settings.recapture, sensor, (b, n, k), z, generator=generator, dtype=x.dtype,
                                 device=x.device)
    if reference is not None and reference.shape != (b, k, x.shape[-1]):
        raise ValueError(f"reference has shape {tuple(reference.shape)}, expected (B, K, D) = {(b, k, x.shape[-1])}")
    x_new, log_lik = bound.program(x, log_w, z, u, eps, reference, relocation)
    ess_k = ess(normalize(log_lik)[0])  # (B, K); a partition with all weights -inf: uniform, not NaN
    log_w_new = torch.full((b, n), -math.log(n), device=x.device, dtype=x.dtype)
    return ParticleState(x_new, log_w_new), StepInfo.make(ess_k[:, 0], ess=ess_k.mean(-1),
                                                          extras={"ess_min": ess_k.amin(-1)})


def partitioned_sir_step(
    state: ParticleState,
    z: Measurement,
    *,
    motion: MotionModel,
    sensor: SensorModel,
    settings: PartitionedSIRSettings = PartitionedSIRSettings(),
    generator: torch.Generator,
    existence: BirthDeath | None = None,
    reference: Tensor | None = None,
) -> tuple[ParticleState, StepInfo]:
    """One independent-partition step: :func:`partitioned_sir_bound_step` after an eager
    :func:`bind_partitioned_sir` (a filter binds once). Parameters and returns:
    :func:`partitioned_sir_bound_step`, with the models ``motion``, ``sensor`` and
    ``settings`` (:class:`PartitionedSIRSettings`) in place of ``bound``; ``existence``
    must be None (a known number of targets): ``state`` with ``x (B, N, K, D)``, ``log_w (B,
    N)`` and ``z`` one frame per run ``(B, *G)`` give a state of the same shapes.
    """
    bound = bind_partitioned_sir(motion, sensor, settings, existence)
    return partitioned_sir_bound_step(state, z, bound, generator=generator, reference=reference)


def clairvoyant_partitions(frames: Tensor, truth: Tensor, x: Tensor, *, motion: MotionModel, sensor: SensorModel,
                           generator: torch.Generator) -> tuple[Tensor, Tensor]:
    """The clairvoyant reference of the crossing and soak studies: each target's partition
    weighted with every other target at its true state (:func:`partitioned_sir_step` with
    ``reference`` the truth, no exclusion), so each target is filtered alone, exactly as N
    grows, with the others' contribution to the frame known. What the data allow a tracker
    that never confuses the targets: a loss here is the model's (this SNR and ``q``), a loss
    only in a filter is the association's. An evaluation tool (it reads the truth), not a
    tracker.

    Parameters
    ----------
    frames : (T, B, *G) one frame per step and run; truth : (T, B, K, D) the true states.
    x : (B, N, K, D) the particles before the first frame (equal weights).
    motion, sensor : the models; generator : source of randomness.

    Returns
    -------
    x : (B, N, K, D) after the last frame; mean : (T, B, K, D) the estimate at each step.
    """
    if truth.shape[:2] != (len(frames), x.shape[0]) or truth.shape[2:] != x.shape[2:]:
        raise ValueError(f"truth has shape {tuple(truth.shape)}, expected (T, B, K, D) = "
                         f"{(len(frames), x.shape[0]) + tuple(x.shape[2:])}")
    log_w = torch.full(x.shape[:2], -math.log(x.shape[1]), dtype=x.dtype, device=x.device)
    state, means = ParticleState(x, log_w), []
    # the others are where they are: no exclusion, no re-capture; bound once for every frame
    bound = bind_partitioned_sir(motion, sensor, PartitionedSIRSettings(exclusion=None, recapture=None))
    for t, ref in enumerate(truth):  # a loop over time only
        state, _ = partitioned_sir_bound_step(state, frames[t], bound, generator=generator, reference=ref)
        means.append(state.x.mean(1))
    return state.x, torch.stack(means)


class PartitionedSIRFilter(Filter):
    """Independent-partition SIR filter (Orton and Fitzgerald 2002; Kreucher et al. 2005):
    each target slot proposed from the motion prior, weighted with the other targets at
    their predicted estimates, and resampled on its own (module docstring).

    Parameters
    ----------
    motion : MotionModel applied to every target slot.
    sensor : SensorModel (grid sensors use their one-slot likelihood change; separable
        sensors their per-target terms).
    num_particles : N >= 1 per partition.
    settings : :class:`PartitionedSIRSettings`, optional; its fields ``resample_method``,
        ``exclusion``, ``recapture`` are also keywords of the constructor.
    existence : must be None (known number of targets).
    compile_step : compile :func:`partitioned_sir_body` (the whole step but its draws;
        :func:`partitioned_sir_program`).

    Notes
    -----
    ``StepInfo``: ``ess`` (mean partition ESS); ``log_evidence``, ``acceptance`` NaN;
    extras ``ess_min``.

    Example
    -------
    Two targets 50 m apart, each partition weighted and resampled on its own:

    >>> import torch
    >>> import torchmcmcpf as tp
    >>> g = torch.Generator().manual_seed(0)
    >>> start = torch.tensor([[0.0, 1.0, 0.0, 0.0], [50.0, -1.0, 0.0, 0.0]])   # (K, D): [x, vx, y, vy]
    >>> z = torch.tensor([[1.0, 0.0], [49.0, 0.0]]).expand(1, 1, 2, 2)       # (T, B, K, 2): one frame
    >>> motion, sensor = tp.ConstantVelocity(dt=1.0, q=1.0), tp.LinearGaussian.position(noise_std=1.0)
    >>> result = tp.PartitionedSIRFilter(motion, sensor, 100)(z, init=start + torch.randn(1, 100, 2, 4, generator=g),
    ...                                                       generator=g)
    >>> bool((result.info.extras["ess_min"] <= result.info.ess).all())   # the worst partition against the mean
    True
    """

    compile_seconds = 16.0  # benchmarks/bench_compile.py, 5-target ground radar, 2 CPU cores
    settings_class = PartitionedSIRSettings
    bind = staticmethod(bind_partitioned_sir)
    bound_step = staticmethod(partitioned_sir_bound_step)
