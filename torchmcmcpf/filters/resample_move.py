"""Particle filter with an HMC move on the process noise (Maroulas and Stinis 2010, paper 003).

One step (paper 003 sec. 1.3, "Particle filter with MCMC step", and sec. 1.4):

1. predict: draw the standard normal process noise ``u ~ N(0, I)`` and set
   ``x_k = f(x_{k-1}, u)`` (``motion.propagate``; for paper 003 eq. 11
   ``x_k = A x_{k-1} + B sigma u``);
2. weight: ``w ∝ w_{k-1} g(x_k, z_k)``; the ESS of these weights is reported (sec. 1.3);
3. resample the *pairs* ``(x_{k-1}, u)`` (equivalently ``(x_{k-1}, x_k)``);
4. move: for each resampled pair run HMC over ``u`` with ``x_{k-1}`` fixed, targeting
   ``g(f(x_{k-1}, u), z_k) N(u; 0, I)``, i.e. the density ``g dP`` of eq. 6 with the
   Wiener measure ``dP`` of the increments; minus its log is the potential of eq. 29
   (linear) and of eq. 30 (bearing-range) (sec. 2.1.2: 100 accept/reject rounds of one
   leapfrog step of 0.1). Gradients come from autograd, so any differentiable sensor and
   any ``MotionModel`` (through ``propagate``) work;
5. ``x_k = f(x_{k-1}, u)`` with equal weights.

Step 4 leaves the target of step 3 invariant, so the particles remain a sample of
``p(x_k | z_{1:k})``, with the approximation of eq. 6 (the integral over ``x_{k-1}`` by the
resampled ancestors). With ``num_hmc_steps=0`` the step is the paper's generic particle
filter (sec. 1.2: predict, weight, resample), its baseline.

Effective sample sizes (paper 003 sec. 1.3-1.4)
-----------------------------------------------
The paper's ``ess(T_k) = N / (1 + C_k^2)``, with ``C_k`` the coefficient of variation of
``g(X^n_{T_k}, Z_{T_k})`` over the N samples, is exactly ``(sum g)^2 / sum g^2``, the usual
ESS of the normalised weights ``g``; the question is which samples. ``info.ess`` is that of
the weights of step 2, over the *predicted* particles, before resampling and the move (the
generic PF's ESS). The paper measures the improved filter on its returned samples
``X^n_{T_k} = Y^{n, L}``, i.e. *after* the move ("we can still measure how well these
samples approximate the posterior ... by comparing the effective sample sizes with and
without the MCMC step"): ``extras["ess_after_move"]`` (one more likelihood evaluation
per step). For several targets the paper's ``ess_Lambda`` uses the
product of the per-target ``g_lambda`` (joint, as both fields here); with
``association="metropolis"`` the per-target ESS (each target's own weights, eq. 8's
marginals) is reported as well, before and after the move.

Association: with ``association="exact"`` the sensor's exact likelihood is used and HMC
moves the noise of all K slots of a particle jointly (eq. 10). With ``"metropolis"`` (an
:class:`~torchmcmcpf.models.sensors.association.AssociationSensor` only) each predicted
particle gets the best association found by the Metropolis search of paper 003, the
likelihood factorises over slots, and HMC runs one chain per slot with its own
accept/reject (eq. 9).

Deviation from the paper, on purpose: eqs. 26-27 move the position by ``T sigma u`` in the
MCMC step while eq. 12 moves it by ``T^2/2 sigma u`` in the prediction. We use the
prediction's map (``motion.propagate``) in both places, so the move targets exactly the
distribution the weights describe.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass

import torch

from .._validation import check_positive, check_positive_int
from ..kernels.hmc import hmc_transition, value_and_grad
from ..models.base import MotionModel, SensorModel
from ..models.existence import BirthDeath, BirthNoise, TargetDynamics
from ..models.multitarget import Exclusion, log_exclusion
from ..models.sensors.association import (
    AssociationSensor,
    metropolis_association,
    padded_pair_log_likelihood,
)
from ..resampling import RESAMPLERS, ess, gather_particles, normalize, resample
from ..state import ParticleState, StepInfo
from ..typing import Measurement, Tensor, split_points
from ._bound import Bound, Compile, bind
from .base import Filter

__all__ = ["ResampleMoveFilter", "ResampleMoveSettings", "resample_move_step", "bind_resample_move",
           "resample_move_bound_step", "resample_move_program", "ASSOCIATIONS"]

ASSOCIATIONS = ("exact", "metropolis")


@dataclass(frozen=True)
class ResampleMoveSettings:
    """Settings of the resample-move filter (paper 003), validated on construction.

    Attributes
    ----------
    step_size, num_leapfrog, num_hmc_steps : HMC settings (paper: 0.1, 1, 100);
        ``num_hmc_steps=0`` gives the generic particle filter (sec. 1.2).
    association : ``"exact"`` or ``"metropolis"`` (module docstring).
    association_iters : Metropolis proposals per particle (``"metropolis"`` only).
    resample_method : ``"systematic"``, ``"stratified"`` or ``"multinomial"``.
    exclusion : :class:`~torchmcmcpf.models.multitarget.Exclusion` (default) or None: the
        weights and the HMC target include the exclusion factor ``Phi(x)`` between slots
        (Khan et al. 2005). Set to None with ``association="metropolis"``, whose per-slot HMC
        chains (eq. 9) need a target that factorises over the slots.

    Example
    -------
    >>> from torchmcmcpf.filters.resample_move import ResampleMoveSettings
    >>> ResampleMoveSettings(num_hmc_steps=0).num_hmc_steps     # the generic particle filter
    0
    >>> ResampleMoveSettings(association="metropolis").exclusion is None   # a factorised target
    True
    >>> ResampleMoveSettings(step_size=-0.1)
    Traceback (most recent call last):
    ...
    ValueError: step_size must be > 0 and finite, got -0.1
    """

    step_size: float = 0.1
    num_leapfrog: int = 1
    num_hmc_steps: int = 100
    association: str = "exact"
    association_iters: int = 30
    resample_method: str = "systematic"
    exclusion: Exclusion | None = Exclusion()

    def __post_init__(self):
        object.__setattr__(self, "step_size", check_positive(self.step_size, "step_size"))
        object.__setattr__(self, "num_leapfrog", check_positive_int(self.num_leapfrog, "num_leapfrog"))
        object.__setattr__(self, "num_hmc_steps", check_positive_int(self.num_hmc_steps, "num_hmc_steps", minimum=0))
        if self.association not in ASSOCIATIONS:
            raise ValueError(f"association must be one of {ASSOCIATIONS}, got {self.association!r}")
        object.__setattr__(self, "association_iters", check_positive_int(self.association_iters, "association_iters"))
        if self.resample_method not in RESAMPLERS:
            raise ValueError(f"resample_method must be one of {sorted(RESAMPLERS)}, got {self.resample_method!r}")
        if self.association == "metropolis":
            object.__setattr__(self, "exclusion", None)  # eq. 9's per-slot chains: a factorised target


def _predict(x_prev: Tensor, exists: Tensor | None, eps: Tensor, birth: BirthNoise | None,
             dynamics: TargetDynamics) -> tuple[Tensor, Tensor | None, Tensor]:
    """``x_k = f(x_{k-1}, u)`` through ``dynamics`` (one path with or without births and
    deaths); returns ``x``, ``exists`` and the per-particle birth weight correction ``(B, N)``.
    """
    x, e, log_ratio = dynamics.propagate(x_prev, exists, eps, birth)
    return x, e, log_ratio.sum(-1)


def bind_resample_move(motion: MotionModel, sensor: SensorModel, settings: ResampleMoveSettings | None = None,
                       existence: BirthDeath | None = None, *, num_particles: int | None = None,
                       compile: Compile = None) -> Bound:
    """The resample-move filter's :class:`~torchmcmcpf.filters._bound.Bound`: the models,
    ``settings`` (default :class:`ResampleMoveSettings`; ``association="metropolis"`` needs an
    :class:`~torchmcmcpf.models.sensors.association.AssociationSensor`) and the program, one
    HMC transition (:func:`resample_move_program`, compiled with ``compile``).
    ``num_particles`` is accepted for the common bind signature (no setting depends on it).
    """
    def check(bound: Bound) -> None:
        if bound.settings.association == "metropolis" and not isinstance(sensor, AssociationSensor):
            raise ValueError(f"association='metropolis' needs an AssociationSensor, got {type(sensor).__name__}")

    return bind(motion, sensor, ResampleMoveSettings() if settings is None else settings, existence, check=check,
                program=lambda b, c: resample_move_program(b.dynamics, b.sensor, b.settings, c), compile=compile)


def resample_move_step(
    state: ParticleState,
    z: Measurement,
    *,
    motion: MotionModel,
    sensor: SensorModel,
    settings: ResampleMoveSettings = ResampleMoveSettings(),
    generator: torch.Generator,
    existence: BirthDeath | None = None,
) -> tuple[ParticleState, StepInfo]:
    """One step of the particle filter with an HMC move: :func:`resample_move_bound_step`
    after an eager :func:`bind_resample_move` (a filter binds once). Parameters and returns:
    :func:`resample_move_bound_step`, with the models ``motion``, ``sensor``, ``existence``
    and ``settings`` (:class:`ResampleMoveSettings`) in place of ``bound``: ``state`` with
    ``x (B, N, K, D)``, ``log_w (B, N)`` (``exists (B, N, K)`` with births and deaths) and ``z``
    one measurement per run give a state of the same shapes.
    """
    bound = bind_resample_move(motion, sensor, settings, existence)
    return resample_move_bound_step(state, z, bound, generator=generator)


def resample_move_bound_step(state: ParticleState, z: Measurement, bound: Bound, *, generator: torch.Generator
                             ) -> tuple[ParticleState, StepInfo]:
    """One step of the particle filter with an HMC move (module docstring, paper 003).

    Parameters
    ----------
    state : ParticleState, ``x (B, N, K, D)``, normalised ``log_w (B, N)``, optional
        ``exists (B, N, K)``.
    z : one measurement per run (e.g. ``PointFrame(z (B, M, d), mask (B, M))``).
    bound : :class:`~torchmcmcpf.filters._bound.Bound` of :func:`bind_resample_move`: any
        MotionModel (the move acts on its ``propagate`` noise), any SensorModel
        differentiable in ``x``, :class:`ResampleMoveSettings`, the existence model (births
        and deaths, propagated with the same law as every other filter,
        :meth:`BirthDeath.propagate`; the HMC move acts on the motion noise with the
        existence draws of the resampled pair fixed; ``state.exists`` None: every slot starts
        inactive) and the program, the HMC move, one transition
        (:func:`resample_move_program`, ``program(eps, value, grad, p, u, x_prev, exists,
        birth, z, assignment)``, compiled by ``ResampleMoveFilter(compile_step=True)``).
    generator : the only source of randomness.

    Returns
    -------
    state : equally weighted particles at time k.
    info : ``ess (B,)`` of the weights of step 2, ``log_evidence (B,)``
        (``log sum_i w_{k-1}^i g(x_k^i, z_k)``), ``acceptance (B,)`` the mean HMC acceptance
        over particles (and existing slots), NaN without a move; extras (module docstring,
        "Effective sample sizes"): ``"ess_after_move" (B,)``, ``N / (1 + C_k^2)`` of paper
        003 sec. 1.3-1.4 over the returned particles ``g(x_k^n, z_k)`` (joint over the
        targets; without a move, the resampled predicted particles); with
        ``association="metropolis"`` also ``"ess_per_target"`` and
        ``"ess_per_target_after_move"`` (B,), the ESS of each target's own weights (before:
        ``w_{k-1} g_lambda`` of the predicted particles; after: ``g_lambda`` of the returned
        ones) averaged over the existing targets.
    """
    sensor, settings, existence = bound.sensor, bound.settings, bound.existence
    dynamics = bound.dynamics  # (x, exists) jointly, with or without births and deaths
    x_prev, log_w_prev, exists = state.x, state.log_w, state.exists
    b, n, k, _ = x_prev.shape
    if existence is not None and exists is None:
        exists = torch.zeros((b, n, k), dtype=torch.bool, device=x_prev.device)
    eps, birth, _ = dynamics.draw_noise(x_prev, z, generator=generator)
    x, exists_new, log_birth = _predict(x_prev, exists, eps, birth, dynamics)

    assignment = None
    extras = {}
    assoc: AssociationSensor | None = None
    if settings.association == "metropolis" and isinstance(sensor, AssociationSensor):  # bind_resample_move checks
        assoc = sensor
        zz, mask = split_points(z)
        square, _ = padded_pair_log_likelihood(sensor.pair_log_likelihood(x, zz), exists_new, mask)
        assignment, _, _ = metropolis_association(square, num_iters=settings.association_iters, generator=generator)
        log_lik_slot = sensor.assigned_log_likelihood(x, z, assignment, exists_new)  # (B, N, K)
        extras["ess_per_target"] = _ess_per_target(log_w_prev.unsqueeze(-1) + log_lik_slot, exists_new)
        log_lik = log_lik_slot.sum(-1)
    else:
        log_lik = sensor.log_likelihood(x, z, exists_new)
    log_g = log_lik  # the sensor likelihood g of the predicted particles (B, N), without births' r
    log_lik = log_lik + log_birth + log_exclusion(settings.exclusion, sensor, x, exists_new)

    # Weights may all underflow in linear space; in log space they stay finite, and a run
    # whose likelihoods are all -inf keeps uniform weights (normalize), never NaN.
    log_w, _ = normalize(log_w_prev + log_lik)
    info_ess = ess(log_w)
    log_evidence = torch.logsumexp(log_w_prev + log_lik, dim=-1)

    # Resample the pairs (x_{k-1}, u) (paper 003 sec. 1.3, modified step 4), with their
    # existence draws.
    idx = resample(log_w, settings.resample_method, generator=generator)
    x_prev, eps = gather_particles(x_prev, idx), gather_particles(eps, idx)
    if exists is not None:
        exists = gather_particles(exists, idx)
    if birth is not None:
        birth = BirthNoise(*(gather_particles(t, idx) for t in birth))
    uniform = torch.full_like(log_w, -math.log(n))
    if settings.num_hmc_steps == 0:
        x, exists_new, _ = _predict(x_prev, exists, eps, birth, dynamics)
        extras["ess_after_move"] = ess(normalize(gather_particles(log_g, idx))[0])
        if "ess_per_target" in extras:
            extras["ess_per_target_after_move"] = _ess_per_target(gather_particles(log_lik_slot, idx), exists_new)
        return ParticleState(x, uniform, exists_new), StepInfo.make(info_ess, ess=info_ess, log_evidence=log_evidence,
                                                                    extras=extras)

    if assignment is not None:
        assignment = gather_particles(assignment, idx)
    move = bound.program
    target = _target(dynamics, sensor, settings.exclusion)
    value, grad = value_and_grad(lambda u: target(u, x_prev, exists, birth, z, assignment), eps)
    accepted = torch.zeros_like(value)
    for _ in range(settings.num_hmc_steps):
        p = torch.randn(eps.shape, generator=generator, device=eps.device, dtype=eps.dtype)
        u = torch.rand(value.shape, generator=generator, device=eps.device, dtype=eps.dtype)
        eps, value, grad, accept = move(eps, value, grad, p, u, x_prev, exists, birth, z, assignment)
        accepted = accepted + accept.to(accepted.dtype)
    acc = accepted / settings.num_hmc_steps
    x, exists_new, _ = _predict(x_prev, exists, eps, birth, dynamics)
    # g at the moved particles, evaluated eagerly (one likelihood evaluation; not read off the
    # HMC log-target, whose compiled value may differ from eager in the last bits)
    if assoc is not None and assignment is not None:  # per slot (B, N, K)
        log_g_slot = assoc.assigned_log_likelihood(x, z, assignment, exists_new)
        extras["ess_per_target_after_move"] = _ess_per_target(log_g_slot, exists_new)
        log_g_moved = log_g_slot.sum(-1)
    else:
        log_g_moved = sensor.log_likelihood(x, z, exists_new)
    extras["ess_after_move"] = ess(normalize(log_g_moved)[0])
    if acc.dim() == 3:  # per slot: average over existing slots
        w = torch.ones_like(acc) if exists_new is None else exists_new.to(acc.dtype)
        acc = (acc * w).sum((-2, -1)) / w.sum((-2, -1)).clamp(min=1)
    else:
        acc = acc.mean(-1)
    return ParticleState(x, uniform, exists_new), StepInfo.make(info_ess, ess=info_ess, log_evidence=log_evidence,
                                                                acceptance=acc, extras=extras)


def _ess_per_target(log_w_slot: Tensor, exists: Tensor | None) -> Tensor:
    """ESS of each slot's own weights ``log_w_slot (B, N, K)`` (unnormalised, normalised
    over N here), averaged over the slots that exist in some particle -> (B,); paper 003
    sec. 1.3's ``N / (1 + C^2)`` per target (eq. 8: the targets' marginal weights).
    """
    per = ess(normalize(log_w_slot.transpose(-1, -2))[0])  # (B, K)
    alive = torch.ones_like(per) if exists is None else exists.any(1).to(per.dtype)
    return (per * alive).sum(-1) / alive.sum(-1).clamp(min=1)


def _target(dynamics: TargetDynamics, sensor: SensorModel, exclusion: Exclusion | None = None) -> Callable:
    """``log_target(u, x_prev, exists, birth, z, assignment)`` of the HMC move: ``(B, N)``
    (one chain per particle, eq. 10, times the exclusion factor) or ``(B, N, K)`` with an
    association (eq. 9).
    """
    def log_target(u, x_prev, exists, birth, z, assignment):
        x, e, _ = _predict(x_prev, exists, u, birth, dynamics)
        if assignment is not None:  # one chain per slot, eq. 9
            return sensor.assigned_log_likelihood(x, z, assignment, e) - 0.5 * u.square().sum(-1)
        return sensor.log_likelihood(x, z, e) - 0.5 * u.square().sum((-2, -1)) + log_exclusion(exclusion, sensor, x, e)
    return log_target


def resample_move_program(dynamics: TargetDynamics, sensor: SensorModel, settings: ResampleMoveSettings,
                          compile: Compile = None) -> Callable:
    """The resample-move filter's program: the HMC move, one transition with the models and
    the settings (as the filter runs them, :func:`bind_resample_move`) bound,
    ``program(eps, value, grad, p, u, x_prev, exists, birth, z, assignment)``; gradients by
    ``torch.func.grad`` (which traces under ``torch.compile(fullgraph=True)``, unlike
    ``torch.autograd.grad``). Compiled with ``compile``, else eager.
    """
    target = _target(dynamics, sensor, settings.exclusion)

    def move(eps, value, grad, p, u, x_prev, exists, birth, z, assignment):
        def log_target(q):
            return target(q, x_prev, exists, birth, z, assignment)

        def grad_fn(q):
            return torch.func.grad(lambda q_: log_target(q_).sum())(q)

        return hmc_transition(eps, value, grad, p, u, log_target=log_target, step_size=settings.step_size,
                              num_leapfrog=settings.num_leapfrog, grad_fn=grad_fn)
    return move if compile is None else compile(move)


class ResampleMoveFilter(Filter):
    """Particle filter with an HMC move on the process noise (paper 003; module docstring).

    Parameters
    ----------
    motion : MotionModel (e.g. the paper-003 model,
        :class:`torchmcmcpf.models.WhiteAccelerationMotion`).
    sensor : SensorModel differentiable in ``x`` (for unknown association,
        :class:`~torchmcmcpf.models.sensors.association.AssociationPosition` or
        :class:`~torchmcmcpf.models.sensors.association.AssociationBearingRange`).
    num_particles : N >= 1.
    settings : :class:`ResampleMoveSettings`, optional; its fields ``step_size``,
        ``num_leapfrog``, ``num_hmc_steps``, ``association``, ``association_iters``,
        ``resample_method``, ``exclusion`` are also keywords of the constructor.
    existence : BirthDeath, optional: births and deaths, as for every other filter.
    compile_step : compile one HMC transition (leapfrog with ``torch.func.grad``).

    Notes
    -----
    ``StepInfo``: ``ess``, ``log_evidence``, ``acceptance`` (NaN without a move); extras
    ``"ess_after_move"`` (and per target with ``association="metropolis"``, see
    :func:`resample_move_step`).

    Example
    -------
    Three HMC moves of every particle's process noise after each resampling:

    >>> import torch
    >>> import torchmcmcpf as tp
    >>> filt = tp.ResampleMoveFilter(tp.ConstantVelocity(dt=1.0, q=1.0), tp.LinearGaussian.position(noise_std=0.5),
    ...                              100, num_hmc_steps=3, step_size=0.3)
    >>> result = filt(torch.ones(4, 1, 1, 2), init=torch.zeros(1, 100, 1, 4), generator=torch.Generator())
    >>> bool(((result.info.acceptance >= 0) & (result.info.acceptance <= 1)).all())   # (T, B) HMC acceptance
    True
    >>> sorted(result.info.extras)                    # the ESS the move leaves
    ['ess_after_move']
    """

    compile_seconds = 29.0  # benchmarks/bench_compile.py, 5-target ground radar, 2 CPU cores
    settings_class = ResampleMoveSettings
    bind = staticmethod(bind_resample_move)
    bound_step = staticmethod(resample_move_bound_step)
