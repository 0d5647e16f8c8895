"""Particle marginal Metropolis-Hastings (PMMH) for static parameters: offline and sequential.

Andrieu, Doucet and Holenstein (2010), "Particle Markov chain Monte Carlo methods", JRSS B
72(3), sec. 2.4 (refs. [7], [8] of paper 000). The intractable likelihood
``p(z_{1:t} | theta)`` of a static parameter ``theta`` is replaced in a Metropolis-Hastings
chain by the unbiased SIR estimate ``hat p(z_{1:t} | theta) = prod_k hat p(z_k | z_{1:k-1},
theta)``. The pair (theta, the random numbers of the filter) is an exact MH chain on an
extended space whose theta-marginal is ``p(theta | z_{1:t})`` (pseudo-marginal argument,
Andrieu and Roberts 2009), whatever the number of particles.

Two forms live here:

- :func:`pmmh` (offline, the paper's form): a random-walk chain over the whole sequence;
  every iteration reruns an SIR filter over all T frames (:func:`sir_log_evidence`).
- :class:`PMMHFilter` / :func:`pmmh_step` (sequential, on the filter contract): a *particle
  independent Metropolis-Hastings* chain with theta (Andrieu et al. 2010, sec. 2.4.1 with
  the parameter added; sec. 2.4.2 with an independence proposal). The proposal is the prior:
  ``L`` candidates ``theta_l ~ p(theta)`` are drawn once, at the first step, and their SIR
  filters run side by side as blocks of the particle dimension (``N = L * N_c``, candidate
  ``l`` owns particles ``l N_c .. (l+1) N_c - 1``), step by step. Each candidate accumulates
  ``log hat Z_l(t) = log hat p(z_{1:t} | theta_l)`` in the state. At every step the MH chain
  visits the candidates in order, starting at candidate 0, and moves from the current one
  ``c`` to candidate ``l`` with probability ``min(1, hat Z_l(t) / hat Z_c(t))`` (the
  proposal is the prior, so the prior and proposal densities cancel and only the evidence
  ratio remains). The chain is a valid PIMH chain of length L targeting
  ``p(theta, x_{0:t} | z_{1:t})`` at each t (fresh uniforms every step), so its average of
  the candidates' filtering means is a consistent estimate of ``E[x_t | z_{1:t}]`` with theta
  integrated over its posterior, exact as ``L -> infinity`` for any ``N_c``.

What the PMMH row of Table II (paper 000) runs here
---------------------------------------------------
Paper 000 does not say which static parameter its PMMH estimated, nor how it produced
filtering estimates. Our row (``experiments/bocquel_table2.py``) is :class:`PMMHFilter`
with ``theta = log q``, the log of the scale of the filters' process noise (true value 0:
``q = 1 m^2 s^-3``, acceleration standard deviation 1 m/s^2), prior ``N(0, 1)``, ``L``
candidates (chain length L, no burn-in), each an SIR filter with ``Np`` particles
(``N = L * Np`` in all); the track at each step is the chain average of the candidates'
SIR filtering means (the Rao-Blackwellised PIMH estimate). Its seconds per step are those
of the whole filter (L SIR filters). The offline :func:`pmmh` stays for parameter
estimation over a whole sequence (tests/filters/test_pmmh.py checks it against the exact
Kalman posterior).
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any, NamedTuple

import torch
from torch.utils._pytree import tree_map

from .._native.select import where
from .._validation import as_int, check_generator, check_positive_int, check_shape
from ..kernels.mh import mh_accept, mh_select
from ..models.base import MotionModel, SensorModel
from ..models.existence import BirthDeath
from ..models.motion import ProcessNoiseScale
from ..resampling import ess, normalize
from ..state import ParticleState, StepInfo
from ..typing import Measurement, Tensor
from ._bound import Bound, Compile, bind
from ._carry import carry, check_fields, typed_extras
from .base import Filter
from .sir import SIRFilter, SIRSettings, sir_bound_step, sir_program

__all__ = ["pmmh", "PMMHResult", "sir_log_evidence", "ProcessNoiseScale", "PMMHFilter", "PMMHSettings",
           "PMMHState", "pmmh_step", "bind_pmmh", "pmmh_bound_step"]


class PMMHResult(NamedTuple):
    """Output of :func:`pmmh`.

    Attributes
    ----------
    theta : (L, B, C, P) the chain of every run, one row per iteration.
    log_evidence : (L, B, C) the accepted log-evidence estimates.
    aux : pytree of ``(L, B, C, ...)`` tensors: the accepted auxiliary output of the
        evaluator (e.g. filter means), or ``None``.
    acceptance : (B, C) acceptance rate of every chain.

    Example
    -------
    An exact log-evidence ``-(theta - 1)^2 / 2`` in place of a filter's estimate, a flat prior:

    >>> import torch
    >>> from torchmcmcpf.filters.pmmh import pmmh
    >>> def evaluate(theta, *, generator):                  # (B, C, P) -> (B, C), aux
    ...     return -0.5 * (theta - 1.0).square().sum(-1), None
    >>> result = pmmh(evaluate, torch.zeros(2, 4, 1, dtype=torch.float64), log_prior=lambda t: 0.0 * t.sum(-1),
    ...               proposal_std=1.0, num_iterations=2000, generator=torch.Generator().manual_seed(0))
    >>> result.theta.shape, result.log_evidence.shape, result.acceptance.shape   # (L, B, C, P), ...
    (torch.Size([2000, 2, 4, 1]), torch.Size([2000, 2, 4]), torch.Size([2, 4]))
    >>> round(result.theta[500:].mean().item(), 1)          # the posterior N(1, 1)
    1.0
    """

    theta: Tensor
    log_evidence: Tensor
    aux: Any
    acceptance: Tensor


def sir_log_evidence(
    build_models: Callable[[Tensor], tuple[MotionModel, SensorModel]],
    measurements: Tensor,
    init: Callable[..., Tensor],
    num_particles: int,
    *,
    keep_means: bool = False,
) -> Callable[..., tuple[Tensor, Any]]:
    """The SIR estimate of ``log p(z_{1:T} | theta)``, batched over runs and chains.

    Parameters
    ----------
    build_models : ``theta (B*C, P) -> (motion, sensor)``, models whose parameters are
        batched over the ``B * C`` copies (e.g. :class:`ProcessNoiseScale`).
    measurements : (T, B, *G) the data of the B runs.
    init : ``init(M, *, generator) -> (M, N, K, D)`` initial particles of the copies, where
        copy ``m`` belongs to run ``m // C`` (run ``b``'s chains are ``b C .. b C + C - 1``).
    num_particles : N of the SIR filter.
    keep_means : also return the filter means ``(B, C, T, K, D)`` as auxiliary output.

    Returns
    -------
    ``evaluate(theta (B, C, P), *, generator) -> (log_evidence (B, C), aux)``.
    """
    num_particles = check_positive_int(num_particles, "num_particles")

    def evaluate(theta: Tensor, *, generator: torch.Generator) -> tuple[Tensor, Any]:
        b, c, p = theta.shape
        motion, sensor = build_models(theta.reshape(b * c, p))
        filt = SIRFilter(motion, sensor, num_particles)
        z = measurements.repeat_interleave(c, dim=1)  # (T, B*C, *G)
        res = filt(z, init=init(b * c, generator=generator), generator=generator)
        aux = None
        if keep_means:
            t = res.mean.shape[0]
            aux = res.mean.reshape((t, b, c) + res.mean.shape[2:]).movedim(0, 2)
        return res.log_evidence.reshape(b, c), aux

    return evaluate


def pmmh(
    evaluate: Callable[..., tuple[Tensor, Any]],
    theta0: Tensor,
    *,
    log_prior: Callable[[Tensor], Tensor],
    proposal_std: Tensor | float,
    num_iterations: int,
    generator: torch.Generator,
) -> PMMHResult:
    """Particle marginal Metropolis-Hastings with a Gaussian random-walk proposal.

    Each iteration proposes ``theta' = theta + proposal_std * eps`` for every chain of every
    run, estimates ``log hat p(z | theta')`` with a fresh filter run (``evaluate``) and
    accepts with ``log alpha = log hat p(z|theta') + log p(theta') - log hat p(z|theta)
    - log p(theta)`` (Andrieu et al. 2010, eq. 13; the symmetric proposal cancels). The
    current estimate is *kept* on rejection, never recomputed: that is what makes the chain
    exact. A proposal outside the prior's support (``log_prior = -inf``) is rejected without
    evaluating the filter at it (the evaluator sees the current ``theta`` there instead).

    Parameters
    ----------
    evaluate : ``(theta (B, C, P), *, generator) -> (log_evidence (B, C), aux)``, e.g.
        :func:`sir_log_evidence`; ``aux`` a pytree of ``(B, C, ...)`` tensors or ``None``.
    theta0 : (B, C, P) starting points.
    log_prior : ``theta (B, C, P) -> (B, C)`` log prior density (``-inf`` off support).
    proposal_std : scalar or (P,) random-walk standard deviation.
    num_iterations : L >= 1 iterations (the starting point is not counted or stored).
    generator : the only source of randomness.

    Returns
    -------
    PMMHResult with ``theta (L, B, C, P)``, ``log_evidence (L, B, C)``, ``aux`` and the
    acceptance rates ``(B, C)``.
    """
    check_generator(generator)
    check_shape(theta0, "theta0", (None, None, None))
    num_iterations = check_positive_int(num_iterations, "num_iterations")
    std = torch.as_tensor(proposal_std, dtype=theta0.dtype, device=theta0.device)
    if not bool((std > 0).all()):
        raise ValueError(f"proposal_std must be > 0, got {proposal_std!r}")
    theta, lp = theta0, log_prior(theta0)
    if not bool(torch.isfinite(lp).all()):
        raise ValueError("theta0 has zero prior density for some chain (log_prior is not finite)")
    log_ev, aux = evaluate(theta, generator=generator)
    thetas, evs, auxs = [], [], []
    accepted_count = torch.zeros(theta.shape[:2], device=theta.device, dtype=theta.dtype)
    for _ in range(num_iterations):
        eps = torch.randn(theta.shape, generator=generator, device=theta.device, dtype=theta.dtype)
        u = torch.rand(theta.shape[:2], generator=generator, device=theta.device, dtype=theta.dtype)
        prop = theta + std * eps
        lp_prop = log_prior(prop)
        valid = torch.isfinite(lp_prop)
        ev_prop, aux_prop = evaluate(where(valid.unsqueeze(-1), prop, theta), generator=generator)
        log_alpha = where(valid, ev_prop + lp_prop - log_ev - lp, torch.full_like(lp, -math.inf))
        acc = mh_accept(log_alpha, u)
        theta, lp, log_ev, aux = mh_select(acc, (prop, lp_prop, ev_prop, aux_prop), (theta, lp, log_ev, aux))
        accepted_count += acc.to(accepted_count.dtype)
        thetas.append(theta)
        evs.append(log_ev)
        auxs.append(aux)
    stacked_aux = None if aux is None else torch.utils._pytree.tree_map(lambda *a: torch.stack(a), *auxs)
    return PMMHResult(torch.stack(thetas), torch.stack(evs), stacked_aux, accepted_count / num_iterations)


# ----------------------------------------------------------------------------- sequential
@dataclass(frozen=True)
class PMMHSettings:
    """Settings of :class:`PMMHFilter` (see the module docstring).

    Attributes
    ----------
    num_candidates : L >= 2, the candidate parameters (the length of the MH chain at each
        step); ``num_particles`` must be a multiple of L.
    burn_in : chain iterations discarded from the estimate, ``0 <= burn_in < L``.
    prior_mean, prior_std : the ``N(prior_mean, prior_std^2)`` prior of ``theta``, the log
        of the process-noise scale (the proposal of the independence sampler).
    resample_method, ess_threshold : of each candidate's SIR filter (:class:`SIRSettings`).
    sir : the settings of every candidate's SIR filter (set on construction).

    Example
    -------
    >>> import torchmcmcpf as tp
    >>> from torchmcmcpf.filters.pmmh import PMMHSettings
    >>> settings = PMMHSettings(num_candidates=4, prior_std=0.5)
    >>> settings.sir                                        # what each candidate's SIR filter runs
    SIRSettings(resample_method='systematic', ess_threshold=1.0, exclusion=Exclusion(scale=1.0))
    >>> tp.PMMHFilter(tp.ConstantVelocity(), tp.LinearGaussian.position(noise_std=1.0), 100,
    ...               settings=settings).settings.num_candidates    # 4 candidates of 25 particles
    4
    >>> PMMHSettings(num_candidates=4, burn_in=4)
    Traceback (most recent call last):
    ...
    ValueError: burn_in must be an integer in [0, num_candidates = 4), got 4
    """

    num_candidates: int = 10
    burn_in: int = 0
    prior_mean: float = 0.0
    prior_std: float = 1.0
    resample_method: str = "systematic"
    ess_threshold: float = 1.0
    sir: SIRSettings = field(init=False, repr=False, compare=False)

    def __post_init__(self):
        num_candidates = check_positive_int(self.num_candidates, "num_candidates", minimum=2)
        object.__setattr__(self, "num_candidates", num_candidates)
        burn_in = as_int(self.burn_in)
        if burn_in is None or not 0 <= burn_in < self.num_candidates:
            raise ValueError(f"burn_in must be an integer in [0, num_candidates = {self.num_candidates}), "
                             f"got {self.burn_in!r}")
        object.__setattr__(self, "burn_in", burn_in)
        if not math.isfinite(float(self.prior_mean)):
            raise ValueError(f"prior_mean must be finite, got {self.prior_mean!r}")
        if not (math.isfinite(float(self.prior_std)) and float(self.prior_std) > 0):
            raise ValueError(f"prior_std must be finite and > 0, got {self.prior_std!r}")
        object.__setattr__(self, "prior_mean", float(self.prior_mean))
        object.__setattr__(self, "prior_std", float(self.prior_std))
        sir = SIRSettings(resample_method=self.resample_method, ess_threshold=self.ess_threshold)  # validates them
        object.__setattr__(self, "sir", sir)
        object.__setattr__(self, "ess_threshold", sir.ess_threshold)


#: the key of ``ParticleState.extras`` under which the PMMH filter carries its :class:`PMMHState`
KEY = "pmmh"


@carry(KEY, old_keys=("theta", "log_evidence", "log_w_candidate"))
class PMMHState(NamedTuple):
    """The sequential PMMH filter's carry (``ParticleState.extras["pmmh"]``): its L candidates,
    run dim first (module docstring, :func:`pmmh_bound_step`).

    Attributes
    ----------
    theta : (B, L), the candidate parameters (drawn from the prior at the first step).
    log_evidence : (B, L), each candidate's accumulated ``log hat Z_l(t) = log hat p(z_{1:t} |
        theta_l)``.
    log_w_candidate : (B, N), each candidate's normalised SIR log-weights, block ``l`` of
        ``N / L`` particles per candidate.

    Example
    -------
    >>> import torch
    >>> import torchmcmcpf as tp
    >>> from torchmcmcpf.filters.pmmh import PMMHState
    >>> filt = tp.PMMHFilter(tp.ConstantVelocity(dt=1.0, q=1.0), tp.LinearGaussian.position(noise_std=1.0), 100,
    ...                      num_candidates=4)
    >>> result = filt(torch.zeros(3, 2, 1, 2), init=torch.zeros(2, 100, 1, 4), generator=torch.Generator())
    >>> carry = result.state.extras["pmmh"]
    >>> isinstance(carry, PMMHState), tuple(carry.theta.shape), tuple(carry.log_w_candidate.shape)   # (B, L), (B, N)
    (True, (2, 4), (2, 100))
    >>> carry.check(result.state, num_candidates=5)
    Traceback (most recent call last):
    ...
    ValueError: state.extras['pmmh'].theta has shape (2, 4), expected (2, 5)
    """

    theta: Tensor
    log_evidence: Tensor
    log_w_candidate: Tensor

    @staticmethod
    def first(state: ParticleState, settings: PMMHSettings, generator: torch.Generator) -> PMMHState:
        """The carry at the first step: ``theta (B, L)`` drawn from the prior, zero
        log-evidence, ``state.log_w (B, N)`` split into the L blocks, each renormalised.
        """
        x, log_w = state.x, state.log_w
        b, n = log_w.shape
        lc = settings.num_candidates
        theta = settings.prior_mean + settings.prior_std * torch.randn(
            (b, lc), generator=generator, device=x.device, dtype=x.dtype)
        log_w_c = normalize(log_w.reshape(b * lc, n // lc))[0].reshape(b, n)
        return PMMHState(theta, torch.zeros_like(theta), log_w_c)

    def check(self, state: ParticleState, name: str = "state.extras['pmmh']", *,
              num_candidates: int | None = None) -> None:
        """Every field against ``state.x (B, N, K, D)`` (its dtype and device) and
        ``num_candidates`` (L, any when None, the same for both ``(B, L)`` fields); a
        ``ValueError`` naming the field, the shape seen and the shape expected otherwise.
        """
        b, n = state.x.shape[:2]
        lc = num_candidates
        if lc is None and torch.is_tensor(self.theta) and self.theta.dim() == 2:
            lc = self.theta.shape[1]
        real = state.x.dtype
        check_fields(name, [("theta", self.theta, (b, lc), real), ("log_evidence", self.log_evidence, (b, lc), real),
                            ("log_w_candidate", self.log_w_candidate, (b, n), real)], state.x.device)


def bind_pmmh(motion: MotionModel, sensor: SensorModel, settings: PMMHSettings | None = None,
              existence: BirthDeath | None = None, *, num_particles: int | None = None, compile: Compile = None
              ) -> Bound:
    """The sequential PMMH filter's :class:`~torchmcmcpf.filters._bound.Bound`: the models,
    ``settings`` (default :class:`PMMHSettings`; ``num_particles``, when given, a multiple of
    ``num_candidates``) and the program, the candidates' SIR body
    (:func:`~torchmcmcpf.filters.sir.sir_program` with ``settings.sir``, compiled with
    ``compile``).
    """
    def check(bound: Bound) -> None:
        lc = bound.settings.num_candidates
        if num_particles is not None and num_particles % lc:
            raise ValueError(f"num_particles must be a multiple of num_candidates = {lc}, got {num_particles}")

    return bind(motion, sensor, PMMHSettings() if settings is None else settings, existence, check=check,
                program=lambda b, c: sir_program(b.dynamics, b.sensor, b.settings.sir, c), compile=compile)


def pmmh_step(
    state: ParticleState,
    z: Measurement,
    *,
    motion: MotionModel,
    sensor: SensorModel,
    settings: PMMHSettings = PMMHSettings(),
    generator: torch.Generator,
    existence: BirthDeath | None = None,
) -> tuple[ParticleState, StepInfo]:
    """One step of the sequential PMMH filter: :func:`pmmh_bound_step` after an eager
    :func:`bind_pmmh` (a filter binds once). Parameters and returns: :func:`pmmh_bound_step`,
    with the models ``motion``, ``sensor``, ``existence`` and ``settings`` (:class:`PMMHSettings`)
    in place of ``bound``: ``state`` with ``x (B, N, K, D)``, ``log_w (B, N)`` and ``z`` one
    frame per run ``(B, *G)`` give a state of the same shapes with ``extras["pmmh"]`` a
    :class:`PMMHState` (``theta (B, L)``, ``log_evidence (B, L)``, ``log_w_candidate (B, N)``).
    """
    return pmmh_bound_step(state, z, bind_pmmh(motion, sensor, settings, existence), generator=generator)


def pmmh_bound_step(state: ParticleState, z: Measurement, bound: Bound, *, generator: torch.Generator
                    ) -> tuple[ParticleState, StepInfo]:
    """One step of the sequential PMMH filter (particle independent MH with theta, module
    docstring): advance the L candidates' SIR filters, then run the MH chain over them.

    ``theta`` scales the motion's process noise by ``e^theta``: each candidate's SIR step
    propagates with ``e^(theta_l / 2) eps`` (covariance ``e^theta_l Q`` for a linear-Gaussian
    motion, as :class:`ProcessNoiseScale`).

    Parameters
    ----------
    state : ParticleState with ``x (B, N, K, D)``, ``log_w (B, N)`` and ``extras["pmmh"]`` a
        :class:`PMMHState` (absent at the first step: ``theta`` is then drawn from the prior
        and ``log_w`` split into the L blocks of ``N / L`` particles, each renormalised,
        :meth:`PMMHState.first`; the open keys of older states are converted).
    z : one measurement per run ``(B, *G)`` (every candidate reads it).
    bound : :class:`~torchmcmcpf.filters._bound.Bound` of :func:`bind_pmmh`: the models
        (``theta = 0`` is the motion as given; the existence model, optional, is every
        candidate's), :class:`PMMHSettings` and the program, the candidates' SIR body
        (:func:`~torchmcmcpf.filters.sir.sir_body` with the models bound, compiled by
        ``PMMHFilter(compile_step=True)``).
    generator : the only source of randomness (theta at the first step, the SIR draws, the
        L MH uniforms).

    Returns
    -------
    state : ``log_w (B, N)`` the PIMH estimate's weights, ``(occupancy of candidate l) / (L -
        burn_in)`` times the candidate's normalised SIR weights (``state.mean()`` is the
        PMMH estimate); ``extras["pmmh"]`` a :class:`PMMHState`: ``theta (B, L)``,
        ``log_evidence (B, L)`` (``log hat Z_l(t)``), ``log_w_candidate (B, N)``.
    info : ``ess`` (B,) of the combined weights; ``log_evidence`` (B,) the increment of
        ``log (1/L) sum_l hat Z_l(t)`` (the prior-averaged evidence); ``acceptance`` (B,)
        the fraction of the L - 1 MH moves that accepted; extras ``theta_mean`` (B,) the
        chain's posterior mean of theta and ``candidate_ess`` (B,) the ESS of the
        candidates' evidences (how many candidates the data leave alive).
    """
    settings = bound.settings
    x, exists = state.x, state.exists
    b, n, k, d = x.shape
    lc, burn = settings.num_candidates, settings.burn_in
    if n % lc:
        raise ValueError(f"state.x has {n} particles, expected a multiple of num_candidates = {lc}")
    m = n // lc
    carried = typed_extras(state.extras or {}).get(KEY)
    pmmh_state = PMMHState.first(state, settings, generator) if carried is None else carried
    if not isinstance(pmmh_state, PMMHState):
        raise ValueError(f"state.extras['pmmh'] must be a PMMHState, got {type(pmmh_state).__name__}")
    pmmh_state.check(state, num_candidates=lc)
    theta, log_ev = pmmh_state.theta, pmmh_state.log_evidence

    # the L candidates' SIR filters as B * L runs of N / L particles
    sub = ParticleState(x.reshape(b * lc, m, k, d), pmmh_state.log_w_candidate.reshape(b * lc, m),
                        None if exists is None else exists.reshape(b * lc, m, k))
    zc = tree_map(lambda a: a.repeat_interleave(lc, dim=0), z)
    base = bound.program
    scale = (0.5 * theta).exp().reshape(b * lc, 1, 1, 1)

    def scaled(x_, log_w_, exists_, z_, need, u, eps, birth):
        return base(x_, log_w_, exists_, z_, need, u, eps * scale.to(eps.dtype), birth)

    # each candidate's SIR step: the same bound models, the noise scaled by its theta
    candidates = dataclasses.replace(bound, settings=settings.sir, program=scaled)
    sub, sub_info = sir_bound_step(sub, zc, candidates, generator=generator)
    log_ev_new = log_ev + sub_info.log_evidence.reshape(b, lc)  # (B, L)

    # the PIMH chain over the candidates, in order (MCMC iterations: a loop over L)
    u = torch.rand((b, lc), generator=generator, device=x.device, dtype=x.dtype)
    cur = torch.zeros(b, dtype=torch.long, device=x.device)
    cur_ev = log_ev_new[:, 0]
    counts = torch.zeros_like(log_ev_new)
    accepted = torch.zeros_like(cur_ev)
    for it in range(lc):
        if it > 0:
            acc = mh_accept(log_ev_new[:, it] - cur_ev, u[:, it])
            cur = where(acc, torch.full_like(cur, it), cur)
            cur_ev = where(acc, log_ev_new[:, it], cur_ev)
            accepted = accepted + acc.to(accepted.dtype)
        if it >= burn:
            counts = counts + torch.nn.functional.one_hot(cur, lc).to(counts.dtype)
    occupancy = counts / (lc - burn)  # (B, L)
    log_w_c = sub.log_w.reshape(b, n)
    log_w_new = occupancy.log().repeat_interleave(m, dim=1) + log_w_c
    new_state = ParticleState(sub.x.reshape(b, n, k, d), log_w_new,
                              None if sub.exists is None else sub.exists.reshape(b, n, k),
                              {KEY: PMMHState(theta, log_ev_new, log_w_c)})
    log_mean_ev = torch.logsumexp(log_ev_new, -1) - torch.logsumexp(log_ev, -1)
    info = StepInfo.make(log_mean_ev, ess=ess(log_w_new), log_evidence=log_mean_ev,
                         acceptance=accepted / (lc - 1),
                         extras={"theta_mean": (occupancy * theta).sum(-1), "candidate_ess": ess(log_ev_new)})
    return new_state, info


class PMMHFilter(Filter):
    """Sequential PMMH on the filter contract: a particle independent Metropolis-Hastings
    chain over ``L`` prior draws of the process-noise log-scale ``theta``, each with its own
    SIR filter of ``num_particles / L`` particles (module docstring, :func:`pmmh_step`).

    Parameters
    ----------
    motion : MotionModel (``theta`` scales its process noise by ``e^theta``).
    sensor : SensorModel.
    num_particles : N, a multiple of ``num_candidates`` (N / L particles per candidate).
    settings : :class:`PMMHSettings`, optional; its fields ``num_candidates``, ``burn_in``,
        ``prior_mean``, ``prior_std``, ``resample_method``, ``ess_threshold`` are also keywords
        of the constructor.
    existence : BirthDeath, optional, passed to every candidate's SIR filter.
    compile_step : compile the candidates' SIR step body (:func:`~torchmcmcpf.filters.sir.sir_body`).

    Notes
    -----
    ``StepInfo``: ``ess``, ``log_evidence``, ``acceptance`` (the PIMH moves); extras
    ``theta_mean``, ``candidate_ess``. The state carries a :class:`PMMHState` under
    ``extras["pmmh"]`` (the candidates' ``theta``, accumulated log-evidence and
    within-candidate weights), so a checkpoint of the state and the generator resumes bit for
    bit.

    Example
    -------
    >>> import torch
    >>> import torchmcmcpf as tp
    >>> filt = tp.PMMHFilter(tp.ConstantVelocity(dt=1.0, q=1.0), tp.LinearGaussian.position(noise_std=1.0), 100,
    ...                      num_candidates=4, prior_std=0.5)   # 4 candidates of 25 particles, theta ~ N(0, 0.5^2)
    >>> result = filt(torch.zeros(5, 2, 1, 2), init=torch.zeros(2, 100, 1, 4), generator=torch.Generator())
    >>> result.state.extras["pmmh"].theta.shape       # (B, L): each run's candidates, carried in the state
    torch.Size([2, 4])
    >>> result.info.extras["theta_mean"].shape        # (T, B): posterior mean of log q
    torch.Size([5, 2])
    """

    compile_seconds = 13.0  # benchmarks/bench_compile.py, 5-target ground radar, 2 CPU cores
    #: the candidates carried between steps (:class:`PMMHState` under ``extras["pmmh"]``): a
    #: resumed state must hold them
    state_extras = frozenset({KEY})
    settings_class = PMMHSettings
    bind = staticmethod(bind_pmmh)
    bound_step = staticmethod(pmmh_bound_step)

    def carry_sizes(self) -> dict[str, dict[str, Any]]:
        """:meth:`Filter.carry_sizes`: the number of candidates of :class:`PMMHState`."""
        return {KEY: {"num_candidates": self.settings.num_candidates}}
