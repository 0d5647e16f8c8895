"""Interacting population-based MCMC particle filter (IP-MCMC-PF).

Bocquel, Driessen and Bagchi (2012), "Multitarget tracking with interacting
population-based MCMC-PF" (paper 000), Algorithms 1 and 2, eqs. 12-13.

One time step, for every Monte Carlo run at once (batch dim B):

1. *Starting points* (Alg. 1, step 1): C of the N previous particles are drawn (systematic
   resampling of their weights with C samples: a random subset, one particle per stratum of
   N/C) and predicted with the motion model; these are the chains' initial states.
2. *Exchange / mutation move* (Alg. 2): at every iteration every chain picks a target slot
   ``j ~ U{1..K}`` and a previous particle ``i ~ w_{k-1}`` (uniform for an MCMC-PF cloud),
   proposes ``y'_j = f(x_{k-1,j}^i) + v`` (fresh process noise) in place of its slot ``j``
   and accepts with the likelihood ratio of eq. 12,
   ``alpha = p(z_k | y') / p(z_k | y)``.
3. After ``burn_in`` iterations every chain contributes its next ``S = N / C`` states; the
   ``C * S = N`` samples are the new equally weighted particles.
4. *Convergence check* (Alg. 1, step 3): R-hat of eq. 13 over the kept samples of every
   state component (``diagnostics.rhat``, ``method="paper"`` by default); where its largest
   value is ``>= rhat_threshold`` the chains of that run go on for another ``S``
   iterations and the **last** ``S`` states replace the kept ones, at most
   ``max_extensions`` times.

Which target density the move leaves invariant
----------------------------------------------
For slot ``j`` the proposal ``q(y' | y) = (1/K) m_j(y'_j) prod_{l != j} delta(y'_l - y_l)``
does not depend on the current ``y_j``: ``m_j(y_j) = sum_i w_{k-1}^i p(y_j | x_{k-1,j}^i)``
is the marginal mixture prior (prediction) of slot ``j``. The Metropolis-Hastings ratio for

    ``pi(y) ∝ p(z_k | y) prod_{j=1..K} m_j(y_j)``

is ``[p(z|y') m_j(y'_j) m_j(y_j)] / [p(z|y) m_j(y_j) m_j(y'_j)] = p(z|y') / p(z|y)``, which
is eq. 12. So each iteration is an exact MH (Metropolis-within-Gibbs, independence proposal
per slot) kernel for ``pi``: the posterior under a predictive prior that *factorises over
targets* (the product of the per-target marginals of the particle prediction), not under the
joint prediction ``sum_i w^i prod_j p(y_j | x^i_j)``. The two coincide for one target
(K = 1), where the filter is a consistent approximation of the exact filter (tested against
a Kalman filter), and whenever the previous cloud factorises; with several targets the
cross-target correlations of the previous cloud are dropped at every step (paper 000,
sec. IV-B: "information exchange between chains").

Births and deaths
-----------------
With a :class:`~torchmcmcpf.models.existence.BirthDeath` model (``existence=``) every slot
also carries an existence flag and the per-slot prediction is that of ``(y_j, e_j)``,
``m_j(y_j, e_j) = sum_i w^i p(y_j, e_j | x^i_j, e^i_j)`` (paper 004 eq. 25 and the birth
density ``p_0``). The exchange move of slot ``j`` draws a previous particle ``i ~ w`` and
propagates its slot ``j`` as :meth:`BirthDeath.propose` does (existence chain, then motion,
a birth or ``x_death``; :meth:`BirthDeath.propagate`, from pre-drawn
noise). With births from ``p_0`` the proposal is ``m_j`` itself and eq. 12 holds unchanged.
With births drawn near the measurements from ``q_0``, the chains sample the target extended
by each slot's source ``i_j`` (whose ``i_j``-marginal is the one above):
``pi(y, e, i) ∝ p(z | y, e) prod_j w^{i_j} p(y_j, e_j | x^{i_j}_j, e^{i_j}_j)``; the proposal
of slot ``j`` differs from its factor only by ``r_j = p_0(y_j) / q_0(y_j)`` for a newborn
(1 otherwise), so

    ``log alpha = log p(z | y', e') - log p(z | y, e) + log r'_j - log r_j``

(the chains cache ``log r_j`` per slot). R-hat is taken over the state components as
before (an inactive slot sits at ``x_death``, so a slot that is alive in some chains and
dead in others shows up).

Batching and extensions
-----------------------
Runs differ in whether they need an extension. The extension loop runs while *any* run
needs one (one ``bool(tensor)`` host sync per extension, in eager code); every run
iterates, but only the runs that need it replace their kept samples and chain states and
count the extension (``torch.where``), so each run's result is what it would be alone,
up to the random numbers consumed.

Speed
-----
All random numbers of a segment (the ``burn_in + S`` iterations, then ``S`` per extension)
are drawn in a few eager calls and fed to :func:`exchange_iteration`, a pure tensor
function that traces under ``torch.compile(fullgraph=True)``; ``IPMCMCFilter(compile_step=True)``
compiles it once per filter. Each iteration evaluates the sensor on the ``(B, C)``
proposals only: for grid sensors the change of the log-likelihood caused by the one slot
that moves (``sensor.log_likelihood_delta``, the cells of its old and new box), otherwise
``sensor.log_likelihood`` of the proposal.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Callable, Optional

import torch
from torch.utils._pytree import tree_map

from .._validation import check_positive, check_positive_int
from ..diagnostics import RHAT_METHODS, rhat
from ..kernels.exchange import (
    ExchangeNoise,
    draw_exchange_noise,
    exchange_iteration,
)
from ..kernels.mh import mh_select
from ..models.base import MotionModel, SensorModel
from ..models.existence import BirthDeath, TargetDynamics
from ..resampling import gather_particles, systematic
from ..state import ParticleState, StepInfo
from ..typing import Measurement, Tensor
from .base import Filter

__all__ = ["IPMCMCFilter", "IPMCMCSettings", "ipmcmc_step", "exchange_iteration", "ExchangeNoise",
           "draw_exchange_noise"]


def _run_chains(chain: tuple, noise: ExchangeNoise, keep: int, step: Callable):
    """Run ``L`` iterations of ``step(chain, noise_t) -> (chain, accepted)`` on a chain tuple
    ``(y, log_lik, ...)``; return the final chains, the last ``keep`` chain tuples stacked
    (leading ``keep``) and the number of acceptances per chain ``(B, C)``."""
    steps = noise.u.shape[0]
    kept = []
    log_lik = chain[1]
    accepted_count = torch.zeros(log_lik.shape, device=log_lik.device, dtype=log_lik.dtype)
    for t in range(steps):
        chain, acc = step(chain, tree_map(lambda a: None if a is None else a[t], noise))
        accepted_count = accepted_count + acc.to(accepted_count.dtype)
        if t >= steps - keep:
            kept.append(chain)
    return chain, tree_map(lambda *a: None if a[0] is None else torch.stack(a), *kept), accepted_count


def _max_rhat(history: Tensor, method: str) -> Tensor:
    """Largest R-hat over the (K, D) components of a ``(S, B, C, K, D)`` history -> (B,)."""
    return rhat(history, chain_dim=2, sample_dim=0, method=method).flatten(1).amax(-1)


@dataclass(frozen=True)
class IPMCMCSettings:
    """Settings of the IP-MCMC-PF (paper 000), validated on construction.

    Attributes
    ----------
    num_chains : C >= 2 parallel chains (paper: 50); must divide N with ``N / C >= 2``.
    burn_in : iterations discarded per chain (paper: 100).
    rhat_threshold : extend the chains of a run while its largest R-hat is ``>=`` this (1.1).
    max_extensions : at most this many extensions of ``N / C`` iterations (0 disables).
    rhat_method : ``"paper"`` (eq. 13) or ``"gelman-rubin"`` (see :mod:`..diagnostics`).
    """

    num_chains: int = 50
    burn_in: int = 100
    rhat_threshold: float = 1.1
    max_extensions: int = 2
    rhat_method: str = "paper"

    def __post_init__(self):
        check_positive_int(self.num_chains, "num_chains", minimum=2)
        check_positive_int(self.burn_in, "burn_in", minimum=0)
        object.__setattr__(self, "rhat_threshold", check_positive(self.rhat_threshold, "rhat_threshold"))
        check_positive_int(self.max_extensions, "max_extensions", minimum=0)
        if self.rhat_method not in RHAT_METHODS:
            raise ValueError(f"rhat_method must be one of {RHAT_METHODS}, got {self.rhat_method!r}")

    def check(self, num_particles: int) -> None:
        """``C | N`` with at least 2 kept samples per chain (R-hat needs them)."""
        if num_particles % self.num_chains:
            raise ValueError(f"num_chains={self.num_chains} must divide num_particles={num_particles}")
        if num_particles // self.num_chains < 2:
            raise ValueError(
                f"num_particles / num_chains = {num_particles // self.num_chains}, expected >= 2 kept "
                "samples per chain (R-hat needs them)"
            )


def ipmcmc_step(
    state: ParticleState,
    z: Measurement,
    *,
    motion: MotionModel,
    sensor: SensorModel,
    settings: IPMCMCSettings = IPMCMCSettings(),
    generator: torch.Generator,
    existence: Optional[BirthDeath] = None,
    kernel: Optional[Callable] = None,
) -> tuple[ParticleState, StepInfo]:
    """One IP-MCMC-PF step (paper 000 Alg. 1-2); see the module docstring.

    Parameters
    ----------
    state : ParticleState with ``x (B, N, K, D)`` and ``log_w (B, N)`` (uniform after an
        MCMC step; any normalised weights are honoured by the start and source draws).
        ``exists (B, N, K)``: with ``existence`` only (None: every slot starts inactive).
    z : one frame per run ``(B, *G)``.
    motion, sensor : the models; settings : :class:`IPMCMCSettings`.
    generator : the only source of randomness.
    existence : BirthDeath, optional: births and deaths (module docstring); the starting
        points are predicted by :meth:`BirthDeath.propose` (births near the points of ``z``
        when it draws them so).
    kernel : the iteration kernel, :func:`exchange_iteration` with the models bound;
        ``IPMCMCFilter(compile_step=True)``
        passes a compiled one; default eager.

    Returns
    -------
    state : ``x (B, N, K, D)``, the kept samples chain by chain (chain ``c`` owns particles
        ``c S .. (c+1) S - 1``), ``log_w = -log N``; with existence ``exists (B, N, K)``.
    info : ``acceptance (B,)``, the exchange acceptance rate over every iteration the run
        used; ``ess``, ``log_evidence`` NaN; ``extras["rhat"] (B,)`` the largest R-hat of the
        kept samples and ``extras["extensions"] (B,)`` how many extensions ran (as a float).
    """
    x_prev, log_w, exists = state.x, state.log_w, state.exists
    num_chains, burn_in = settings.num_chains, settings.burn_in
    rhat_threshold, max_extensions, rhat_method = settings.rhat_threshold, settings.max_extensions, settings.rhat_method
    if existence is None and exists is not None:
        raise ValueError("state.exists must be None without an existence model: pass existence= for an "
                         "unknown number of targets")
    b, n, k, _ = x_prev.shape
    if existence is not None and exists is None:
        exists = torch.zeros((b, n, k), dtype=torch.bool, device=x_prev.device)
    settings.check(n)
    keep = n // num_chains
    iterate = _bind(motion, sensor, existence) if kernel is None else kernel

    kw = dict(generator=generator, device=x_prev.device)
    # 1. starting points: C previous particles (systematic: one per stratum), predicted
    start = systematic(log_w, torch.rand((b, 1), dtype=torch.float64, **kw), num_chains)
    dynamics = TargetDynamics(motion, existence)  # (x, exists) jointly: one path with or without births
    x0 = gather_particles(x_prev, start)
    e0 = None if exists is None else gather_particles(exists, start)
    y, e, log_birth = dynamics.propagate(x0, e0, *dynamics.draw_noise(x0, z, generator=generator))  # (B, C, K, D)
    chain = (y, sensor.log_likelihood(y, z, e), e, None if existence is None else log_birth)

    def step(ch, nz):
        return iterate(ch, x_prev, exists, z, nz.source, nz.slot, nz.eps, nz.u, nz.birth)

    # 2. burn-in + S kept iterations
    births = {} if existence is None else dict(existence=existence, z=z)
    draw = lambda steps: draw_exchange_noise(  # noqa: E731
        log_w, steps, num_chains, k, motion.noise_dim, generator=generator, dtype=x_prev.dtype, **births)
    chain, history, accepted = _run_chains(chain, draw(burn_in + keep), keep, step)
    iterations = torch.full((b,), float(burn_in + keep), device=x_prev.device, dtype=x_prev.dtype)

    # 3. R-hat and extensions (all runs iterate, only those that need it update)
    r = _max_rhat(history[0], rhat_method)
    extensions = torch.zeros(b, dtype=torch.int64, device=x_prev.device)
    for _ in range(max_extensions):
        need = r >= rhat_threshold  # (B,)
        if not bool(need.any()):
            break
        chain_e, hist_e, acc_e = _run_chains(chain, draw(keep), keep, step)
        chain = mh_select(need, chain_e, chain)
        history = tuple(None if h is None else torch.where(need.reshape((1, b) + (1,) * (h.dim() - 2)), he, h)
                        for he, h in zip(hist_e, history))
        accepted = accepted + torch.where(need.unsqueeze(-1), acc_e, torch.zeros_like(acc_e))
        iterations = iterations + need.to(iterations.dtype) * keep
        extensions = extensions + need.to(extensions.dtype)
        r = torch.where(need, _max_rhat(history[0], rhat_method), r)

    x_new = history[0].permute(1, 2, 0, 3, 4).reshape(x_prev.shape)  # (B, C*S, K, D)
    exists_new = None if existence is None else history[2].permute(1, 2, 0, 3).reshape(b, n, k)
    log_w_new = torch.full((b, n), -math.log(n), device=x_prev.device, dtype=log_w.dtype)
    acceptance = accepted.mean(-1) / iterations
    info = StepInfo.make(acceptance, acceptance=acceptance, extras={"rhat": r.to(acceptance.dtype),
                                                                    "extensions": extensions.to(acceptance.dtype)})
    return ParticleState(x_new, log_w_new, exists_new), info


def _bind(motion: MotionModel, sensor: SensorModel, existence: Optional[BirthDeath]) -> Callable:
    """:func:`exchange_iteration` with the models bound."""
    def iterate(*args):
        return exchange_iteration(*args, motion=motion, sensor=sensor, existence=existence)
    return iterate


class IPMCMCFilter(Filter):
    """Interacting population-based MCMC-PF (paper 000 Alg. 1-2).

    Parameters
    ----------
    motion : MotionModel applied to every target slot.
    sensor : SensorModel (radar TBD, LinearGaussian, ...).
    num_particles : N; ``num_chains`` must divide it.
    num_chains, burn_in, rhat_threshold, max_extensions, rhat_method : see :class:`IPMCMCSettings`.
    existence : BirthDeath, optional: births and deaths (module docstring); the estimate
        of a slot is then its mean given existence.
    compile_step : compile one exchange iteration with ``torch.compile(fullgraph=True)``
        (the first step pays the compile time).

    ``StepInfo``: ``acceptance``; ``ess``, ``log_evidence`` NaN; extras ``"rhat"``, ``"extensions"``.

    Example
    -------
    >>> filt = IPMCMCFilter(scn.motion, scn.sensor, 5000, num_chains=50, burn_in=100)  # doctest: +SKIP
    >>> result = filt(scn.measurements, init=x0, generator=g)                          # doctest: +SKIP
    >>> result.info.extras["rhat"].shape                                               # (T, B)
    """

    def __init__(
        self,
        motion: MotionModel,
        sensor: SensorModel,
        num_particles: int,
        *,
        num_chains: int = 50,
        burn_in: int = 100,
        rhat_threshold: float = 1.1,
        max_extensions: int = 2,
        rhat_method: str = "paper",
        existence: Optional[BirthDeath] = None,
        compile_step: bool = False,
    ):
        settings = IPMCMCSettings(num_chains, burn_in, rhat_threshold, max_extensions, rhat_method)
        super().__init__(motion, sensor, num_particles, settings, existence=existence, compile_step=compile_step)
        settings.check(num_particles)

    def _kernel(self, compile: Callable) -> Callable:
        return compile(_bind(self.motion, self.sensor, self.existence))

    def _step(self, state, z, generator):
        return ipmcmc_step(state, z, motion=self.motion, sensor=self.sensor, settings=self.settings,
                           generator=generator, existence=self.existence, kernel=self.kernel())
