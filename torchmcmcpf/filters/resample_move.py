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
import torch

from .._validation import check_positive, check_positive_int
from ..kernels.hmc import hmc
from ..models.base import MotionModel, SensorModel
from ..models.sensors.association import (
    AssociationSensor,
    _split,
    metropolis_association,
    padded_pair_log_likelihood,
)
from ..resampling import RESAMPLERS, ess, gather_particles, normalize, resample
from ..state import ParticleState, StepInfo
from ..typing import Measurement, Tensor
from .base import Filter

__all__ = ["ResampleMoveFilter", "resample_move_step", "ASSOCIATIONS"]

ASSOCIATIONS = ("exact", "metropolis")


def resample_move_step(
    state: ParticleState,
    z: Measurement,
    *,
    motion: MotionModel,
    sensor: SensorModel,
    generator: torch.Generator,
    step_size: float = 0.1,
    num_leapfrog: int = 1,
    num_hmc_steps: int = 100,
    association: str = "exact",
    association_iters: int = 30,
    resample_method: str = "systematic",
) -> tuple[ParticleState, StepInfo]:
    """One step of the particle filter with an HMC move (module docstring, paper 003).

    Parameters
    ----------
    state : ParticleState, ``x (B, N, K, D)``, normalised ``log_w (B, N)``, optional
        ``exists (B, N, K)``.
    z : one measurement per run (e.g. ``PointFrame(z (B, M, d), mask (B, M))``).
    motion : any MotionModel (the move acts on its ``propagate`` noise).
    sensor : any SensorModel differentiable in ``x``.
    generator : the only source of randomness.
    step_size, num_leapfrog, num_hmc_steps : HMC settings (paper: 0.1, 1, 100);
        ``num_hmc_steps=0`` gives the generic particle filter.
    association : ``"exact"`` or ``"metropolis"`` (module docstring).
    association_iters : Metropolis proposals per particle (``"metropolis"`` only).
    resample_method : ``"systematic"``, ``"stratified"`` or ``"multinomial"``.

    Returns
    -------
    state : equally weighted particles at time k.
    info : ``ess (B,)`` of the weights of step 2, ``log_evidence (B,)``
        (``log sum_i w_{k-1}^i g(x_k^i, z_k)``), and ``acceptance = {"hmc": (B,)}``, the mean
        HMC acceptance over particles (and existing slots); ``None`` without a move.
    """
    x_prev, log_w_prev, exists = state
    eps = torch.randn(x_prev.shape[:-1] + (motion.noise_dim,), generator=generator,
                      device=x_prev.device, dtype=x_prev.dtype)
    x = motion.propagate(x_prev, eps)

    assignment = None
    if association == "metropolis":
        zz, mask = _split(z)
        square, _ = padded_pair_log_likelihood(sensor.pair_log_likelihood(x, zz), exists, mask)
        assignment, _, _ = metropolis_association(square, num_iters=association_iters, generator=generator)
        log_lik = sensor.assigned_log_likelihood(x, z, assignment, exists).sum(-1)
    else:
        log_lik = sensor.log_likelihood(x, z, exists)

    # Weights may all underflow in linear space; in log space they stay finite, and a run
    # whose likelihoods are all -inf keeps uniform weights (normalize), never NaN.
    log_w, _ = normalize(log_w_prev + log_lik)
    info_ess = ess(log_w)
    log_evidence = torch.logsumexp(log_w_prev + log_lik, dim=-1)

    # Resample the pairs (x_{k-1}, u) (paper 003 sec. 1.3, modified step 4).
    idx = resample(log_w, resample_method, generator=generator)
    x_prev, eps = gather_particles(x_prev, idx), gather_particles(eps, idx)
    if exists is not None:
        exists = gather_particles(exists, idx)
    n = x_prev.shape[1]
    uniform = torch.full_like(log_w, -math.log(n))
    if num_hmc_steps == 0:
        return (ParticleState(motion.propagate(x_prev, eps), uniform, exists),
                StepInfo(ess=info_ess, log_evidence=log_evidence))

    if assignment is not None:
        assignment = gather_particles(assignment, idx)

        def log_target(u: Tensor) -> Tensor:  # (B, N, K): one chain per slot, eq. 9
            lik = sensor.assigned_log_likelihood(motion.propagate(x_prev, u), z, assignment, exists)
            return lik - 0.5 * u.square().sum(-1)
    else:
        def log_target(u: Tensor) -> Tensor:  # (B, N): one chain per particle, eq. 10
            return sensor.log_likelihood(motion.propagate(x_prev, u), z, exists) - 0.5 * u.square().sum((-2, -1))

    eps, hinfo = hmc(eps, log_target, step_size=step_size, num_leapfrog=num_leapfrog,
                     num_steps=num_hmc_steps, generator=generator)
    acc = hinfo.acceptance
    if acc.dim() == 3:  # per slot: average over existing slots
        w = torch.ones_like(acc) if exists is None else exists.to(acc.dtype)
        acc = (acc * w).sum((-2, -1)) / w.sum((-2, -1)).clamp(min=1)
    else:
        acc = acc.mean(-1)
    x = motion.propagate(x_prev, eps)
    return (ParticleState(x, uniform, exists),
            StepInfo(ess=info_ess, log_evidence=log_evidence, acceptance={"hmc": acc}))


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
    step_size : leapfrog step (paper: 0.1).
    num_leapfrog : leapfrog steps per trajectory (paper: 1).
    num_hmc_steps : accept/reject rounds per time step (paper: 100); 0 gives the generic
        particle filter of paper 003 sec. 1.2 with the same models.
    association : ``"exact"`` (default) or ``"metropolis"``.
    association_iters : Metropolis proposals per particle and step.
    resample_method : ``"systematic"`` (default), ``"stratified"``, ``"multinomial"``.

    Example
    -------
    >>> filt = ResampleMoveFilter(WhiteAccelerationMotion(), AssociationPosition(), 100)
    >>> state, info = filt.step(state, frame, generator=g)             # doctest: +SKIP
    """

    def __init__(
        self,
        motion: MotionModel,
        sensor: SensorModel,
        num_particles: int,
        *,
        step_size: float = 0.1,
        num_leapfrog: int = 1,
        num_hmc_steps: int = 100,
        association: str = "exact",
        association_iters: int = 30,
        resample_method: str = "systematic",
    ):
        super().__init__(motion, sensor)
        self.num_particles = check_positive_int(num_particles, "num_particles")
        self.step_size = check_positive(step_size, "step_size")
        self.num_leapfrog = check_positive_int(num_leapfrog, "num_leapfrog")
        self.num_hmc_steps = check_positive_int(num_hmc_steps, "num_hmc_steps", minimum=0)
        if association not in ASSOCIATIONS:
            raise ValueError(f"association must be one of {ASSOCIATIONS}, got {association!r}")
        if association == "metropolis" and not isinstance(sensor, AssociationSensor):
            raise ValueError(
                f"association='metropolis' needs an AssociationSensor, got {type(sensor).__name__}"
            )
        self.association = association
        self.association_iters = check_positive_int(association_iters, "association_iters")
        if resample_method not in RESAMPLERS:
            raise ValueError(f"resample_method must be one of {sorted(RESAMPLERS)}, got {resample_method!r}")
        self.resample_method = resample_method

    def step(self, state: ParticleState, z: Measurement, *, generator: torch.Generator
             ) -> tuple[ParticleState, StepInfo]:
        """One step (see :func:`resample_move_step`); ``state.x`` is ``(B, N, K, D)``."""
        return resample_move_step(
            state, z, motion=self.motion, sensor=self.sensor, generator=generator,
            step_size=self.step_size, num_leapfrog=self.num_leapfrog,
            num_hmc_steps=self.num_hmc_steps, association=self.association,
            association_iters=self.association_iters, resample_method=self.resample_method,
        )

    def extra_repr(self) -> str:
        return (f"num_particles={self.num_particles}, step_size={self.step_size}, "
                f"num_leapfrog={self.num_leapfrog}, num_hmc_steps={self.num_hmc_steps}, "
                f"association={self.association!r}")
