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
a birth or ``x_death``; :func:`torchmcmcpf.kernels.moves.propose_existence`, from pre-drawn
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
function that traces under ``torch.compile(fullgraph=True)``; ``IPMCMCFilter(compile=True)``
compiles it once per filter. Each iteration evaluates the sensor on the ``(B, C)``
proposals only: for grid sensors the change of the log-likelihood caused by the one slot
that moves (``sensor.log_likelihood_delta``, the cells of its old and new box), otherwise
``sensor.log_likelihood`` of the proposal.
"""

from __future__ import annotations

import math
from typing import Callable, NamedTuple, Optional

import torch
from torch.utils._pytree import tree_map

from .._validation import check_generator, check_positive, check_positive_int
from ..diagnostics import RHAT_METHODS, rhat
from ..kernels.mh import mh_accept, mh_select
from ..kernels.moves import BirthNoise, existence_delta, propose_existence
from ..models.base import MotionModel, SensorModel
from ..models.existence import BirthDeath
from ..resampling import gather_particles, systematic
from ..state import ParticleState, StepInfo
from ..typing import Measurement, Tensor
from .base import Filter, check_existence

__all__ = ["IPMCMCFilter", "ipmcmc_step", "exchange_iteration", "exchange_existence_iteration", "ExchangeNoise",
           "draw_exchange_noise"]


class ExchangeNoise(NamedTuple):
    """Pre-drawn randomness of ``L`` exchange iterations (leading dim ``L``).

    Attributes
    ----------
    source : (L, B, C) int64, index of the previous particle each proposal starts from.
    slot : (L, B, C) int64, the target slot ``j`` each chain updates.
    eps : (L, B, C, noise_dim), standard normal process noise of the proposal.
    u : (L, B, C), uniforms of the accept/reject test.
    birth : :class:`~torchmcmcpf.kernels.moves.BirthNoise` with leading ``(L, B, C)``, the
        existence part of the proposals (only with an existence model).
    """

    source: Tensor
    slot: Tensor
    eps: Tensor
    u: Tensor
    birth: Optional[BirthNoise] = None


def draw_exchange_noise(
    log_w: Tensor, num_iterations: int, num_chains: int, num_targets: int, noise_dim: int,
    *, generator: torch.Generator, dtype: torch.dtype, existence: Optional[BirthDeath] = None,
    z: Optional[Measurement] = None,
) -> ExchangeNoise:
    """Draw the randomness of ``L = num_iterations`` exchange iterations in four calls
    (and, with ``existence``, the birth noise: births near the points of the frame ``z``
    when ``existence`` draws them so).

    ``source`` indices are categorical draws from the previous weights ``log_w (B, N)`` by
    inversion of uniforms (float64 CDF + ``searchsorted``, no ``torch.multinomial``).
    """
    b, n = log_w.shape
    shape = (num_iterations, b, num_chains)
    dev = log_w.device
    cdf = torch.cumsum(torch.softmax(log_w.to(torch.float64), -1), -1)
    cdf = torch.cat([cdf[..., :-1], torch.ones_like(cdf[..., -1:])], -1)
    u_src = torch.rand((b, num_iterations * num_chains), generator=generator, device=dev, dtype=torch.float64)
    source = torch.searchsorted(cdf, u_src, right=True).clamp_(max=n - 1)
    source = source.reshape(b, num_iterations, num_chains).permute(1, 0, 2)
    slot = torch.randint(num_targets, shape, generator=generator, device=dev)
    eps = torch.randn(shape + (noise_dim,), generator=generator, device=dev, dtype=dtype)
    u = torch.rand(shape, generator=generator, device=dev, dtype=dtype)
    if existence is None:
        return ExchangeNoise(source, slot, eps, u)
    template = torch.empty((b, num_iterations, num_chains, existence.dim), device=dev, dtype=dtype)
    birth = BirthNoise.draw(template, existence, z, generator=generator)  # leading (B, L, C)
    birth = BirthNoise(birth.u.transpose(0, 1), birth.x.transpose(0, 1), birth.log_ratio.transpose(0, 1))
    return ExchangeNoise(source, slot, eps, u, birth)


def exchange_iteration(
    y: Tensor, log_lik: Tensor, x_prev: Tensor, z: Measurement,
    source: Tensor, slot: Tensor, eps: Tensor, u: Tensor,
    *, motion: MotionModel, sensor: SensorModel,
) -> tuple[Tensor, Tensor, Tensor]:
    """One exchange/mutation MH iteration of every chain (paper 000 Alg. 2, eq. 12).

    Chain ``c`` of run ``b`` replaces slot ``j = slot[b, c]`` by
    ``motion.propagate(x_prev[b, source[b, c], j], eps[b, c])`` and accepts with
    ``log u < log p(z | y') - log p(z | y)``. Exact MH for the factorised-prior posterior
    described in the module docstring. Pure and branch-free (``torch.compile`` friendly).

    A sensor with ``log_likelihood_delta(x, x_n, n, z)`` that accepts a per-chain slot tensor
    ``n (B, C)`` (e.g. :class:`~torchmcmcpf.models.sensors.grid.SeparableGridSensor`) gives
    the ratio from the cells near the old and new position of the slot only, and
    ``log_lik`` is carried as ``log_lik + delta`` (the cache of the current chains); any
    other sensor scores the whole proposal with ``log_likelihood``.

    Parameters
    ----------
    y : (B, C, K, D) chain states; log_lik : (B, C) their ``log p(z | y)``.
    x_prev : (B, N, K, D) previous particles.
    z : the frame ``(B, *G)`` (or a measurement tuple the sensor understands).
    source : (B, C) int64 in [0, N); slot : (B, C) int64 in [0, K).
    eps : (B, C, noise_dim) standard normals; u : (B, C) uniforms in [0, 1).
    motion, sensor : the models.

    Returns
    -------
    y : (B, C, K, D), log_lik : (B, C), accepted : (B, C) bool.
    """
    b, n, k, d = x_prev.shape
    flat = x_prev.reshape(b, n * k, d)
    parent = torch.take_along_dim(flat, (source * k + slot).unsqueeze(-1), dim=1)  # (B, C, D)
    moved = motion.propagate(parent.unsqueeze(-2), eps.unsqueeze(-2))  # (B, C, 1, D)
    here = (torch.arange(k, device=y.device) == slot.unsqueeze(-1)).unsqueeze(-1)  # (B, C, K, 1)
    proposal = torch.where(here, moved, y)
    delta_fn = getattr(sensor, "log_likelihood_delta", None)
    if callable(delta_fn):  # only the cells near the old and new position of the slot
        log_ratio = delta_fn(y, moved.squeeze(-2), slot, z)
        log_lik_prop = log_lik + log_ratio
    else:
        log_lik_prop = sensor.log_likelihood(proposal, z)
        log_ratio = log_lik_prop - log_lik
    accepted = mh_accept(log_ratio, u)
    y, log_lik = mh_select(accepted, (proposal, log_lik_prop), (y, log_lik))
    return y, log_lik, accepted


def exchange_existence_iteration(
    chain: tuple[Tensor, Tensor, Tensor, Tensor], x_prev: Tensor, exists_prev: Tensor, z: Measurement,
    source: Tensor, slot: Tensor, eps: Tensor, u: Tensor, birth: BirthNoise,
    *, motion: MotionModel, sensor: SensorModel, existence: BirthDeath,
) -> tuple[tuple[Tensor, Tensor, Tensor, Tensor], Tensor]:
    """One exchange/mutation MH iteration with births and deaths (module docstring, "Births
    and deaths"): chain ``c`` of run ``b`` replaces slot ``j = slot[b, c]`` by slot ``j`` of
    previous particle ``source[b, c]`` propagated through the existence chain, the motion or
    a birth. Pure and branch-free (``torch.compile`` friendly).

    Parameters
    ----------
    chain : ``(y (B, C, K, D), log_lik (B, C), exists (B, C, K) bool, log_birth (B, C, K))``
        with ``log_lik = log p(z | y, exists)`` and ``log_birth`` the cached ``log r_j``.
    x_prev : (B, N, K, D), exists_prev : (B, N, K) the previous particles.
    z : the frame; source, slot : (B, C) int64; eps : (B, C, noise_dim); u : (B, C).
    birth : :class:`~torchmcmcpf.kernels.moves.BirthNoise` with leading ``(B, C)``.
    motion, sensor, existence : the models.

    Returns
    -------
    chain : the new ``(y, log_lik, exists, log_birth)``; accepted : (B, C) bool.
    """
    y, log_lik, exists, log_birth = chain
    b, n, k, d = x_prev.shape
    at = source * k + slot  # (B, C)
    parent = torch.take_along_dim(x_prev.reshape(b, n * k, d), at.unsqueeze(-1), dim=1)  # (B, C, D)
    parent_e = torch.take_along_dim(exists_prev.reshape(b, n * k), at, dim=1)  # (B, C)
    one = BirthNoise(birth.u.unsqueeze(-1), birth.x.unsqueeze(-2), birth.log_ratio.unsqueeze(-1))
    moved, e_new, lb_new = propose_existence(parent.unsqueeze(-2), parent_e.unsqueeze(-1), eps.unsqueeze(-2), one,
                                             motion=motion, existence=existence)  # (B, C, 1, D), (B, C, 1) x2
    here = torch.arange(k, device=y.device) == slot.unsqueeze(-1)  # (B, C, K)
    proposal = torch.where(here.unsqueeze(-1), moved, y)
    e_prop = torch.where(here, e_new, exists)
    lb_prop = torch.where(here, lb_new, log_birth)
    delta_fn = existence_delta(sensor)
    if delta_fn is not None:  # only the cells near the old and new position of the slot
        log_lik_prop = log_lik + delta_fn(y, moved.squeeze(-2), slot, z, exists=exists, exists_n=e_new.squeeze(-1))
    else:
        log_lik_prop = sensor.log_likelihood(proposal, z, e_prop)
    log_alpha = log_lik_prop - log_lik + (lb_new.squeeze(-1) - torch.where(here, log_birth, 0.0).sum(-1))
    accepted = mh_accept(log_alpha, u)
    new = mh_select(accepted, (proposal, log_lik_prop, e_prop, lb_prop), chain)
    return new, accepted


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
    return chain, tree_map(lambda *a: torch.stack(a), *kept), accepted_count


def _max_rhat(history: Tensor, method: str) -> Tensor:
    """Largest R-hat over the (K, D) components of a ``(S, B, C, K, D)`` history -> (B,)."""
    return rhat(history, chain_dim=2, sample_dim=0, method=method).flatten(1).amax(-1)


def ipmcmc_step(
    state: ParticleState,
    z: Measurement,
    *,
    motion: MotionModel,
    sensor: SensorModel,
    num_chains: int,
    burn_in: int,
    generator: torch.Generator,
    rhat_threshold: float = 1.1,
    max_extensions: int = 2,
    rhat_method: str = "paper",
    iterate: Optional[Callable] = None,
    existence: Optional[BirthDeath] = None,
) -> tuple[ParticleState, StepInfo]:
    """One IP-MCMC-PF step (paper 000 Alg. 1-2); see the module docstring.

    Parameters
    ----------
    state : ParticleState with ``x (B, N, K, D)`` and ``log_w (B, N)`` (uniform after an
        MCMC step; any normalised weights are honoured by the start and source draws).
        ``exists (B, N, K)``: with ``existence`` only (None: every slot starts inactive).
    z : one frame per run ``(B, *G)``.
    motion, sensor : the models.
    num_chains : C, must divide N; every chain keeps ``S = N / C`` samples.
    burn_in : iterations discarded per chain (paper: 100).
    generator : the only source of randomness.
    rhat_threshold : extend the chains of a run while its largest R-hat is ``>=`` this (1.1).
    max_extensions : at most this many extensions of ``S`` iterations each (0 disables).
    rhat_method : ``"paper"`` (eq. 13) or ``"gelman-rubin"`` (see :mod:`..diagnostics`).
    iterate : the iteration kernel, :func:`exchange_iteration` with the models bound (with
        ``existence``: :func:`exchange_existence_iteration`), ``IPMCMCFilter`` passes a
        compiled one; default eager.
    existence : BirthDeath, optional: births and deaths (module docstring); the starting
        points are predicted by :meth:`BirthDeath.propose` (births near the points of ``z``
        when it draws them so).

    Returns
    -------
    state : ``x (B, N, K, D)``, the kept samples chain by chain (chain ``c`` owns particles
        ``c S .. (c+1) S - 1``), ``log_w = -log N``; with existence ``exists (B, N, K)``.
    info : ``rhat (B,)`` largest R-hat of the kept samples, ``extensions (B,)`` int64, and
        ``acceptance["exchange"] (B,)`` acceptance rate over every iteration the run used.
    """
    x_prev, log_w, exists = state
    check_existence(existence)
    if existence is None and exists is not None:
        raise ValueError("state.exists must be None without an existence model: pass existence= for an "
                         "unknown number of targets")
    b, n, k, _ = x_prev.shape
    if existence is not None and exists is None:
        exists = torch.zeros((b, n, k), dtype=torch.bool, device=x_prev.device)
    if n % num_chains:
        raise ValueError(f"num_chains={num_chains} must divide the number of particles N={n}")
    if rhat_method not in RHAT_METHODS:
        raise ValueError(f"rhat_method must be one of {RHAT_METHODS}, got {rhat_method!r}")
    keep = n // num_chains
    if iterate is None:
        iterate = _bind(motion, sensor, existence)

    kw = dict(generator=generator, device=x_prev.device)
    # 1. starting points: C previous particles (systematic: one per stratum), predicted
    start = systematic(log_w, torch.rand((b, 1), dtype=torch.float64, **kw), num_chains)
    if existence is None:
        y = motion.sample(gather_particles(x_prev, start), generator=generator)  # (B, C, K, D)
        chain = (y, sensor.log_likelihood(y, z))

        def step(ch, nz):
            y, ll, acc = iterate(*ch, x_prev, z, nz.source, nz.slot, nz.eps, nz.u)
            return (y, ll), acc
    else:
        y, e, log_birth = existence.propose(gather_particles(x_prev, start), gather_particles(exists, start),
                                            motion=motion, generator=generator, z=z)
        chain = (y, sensor.log_likelihood(y, z, e), e, log_birth)

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
        history = tuple(torch.where(need.reshape((1, b) + (1,) * (h.dim() - 2)), he, h)
                        for he, h in zip(hist_e, history))
        accepted = accepted + torch.where(need.unsqueeze(-1), acc_e, torch.zeros_like(acc_e))
        iterations = iterations + need.to(iterations.dtype) * keep
        extensions = extensions + need.to(extensions.dtype)
        r = torch.where(need, _max_rhat(history[0], rhat_method), r)

    x_new = history[0].permute(1, 2, 0, 3, 4).reshape(x_prev.shape)  # (B, C*S, K, D)
    exists_new = None if existence is None else history[2].permute(1, 2, 0, 3).reshape(b, n, k)
    log_w_new = torch.full((b, n), -math.log(n), device=x_prev.device, dtype=log_w.dtype)
    info = StepInfo(
        rhat=r,
        extensions=extensions,
        acceptance={"exchange": accepted.mean(-1) / iterations},
    )
    return ParticleState(x_new, log_w_new, exists_new), info


def _bind(motion: MotionModel, sensor: SensorModel, existence: Optional[BirthDeath]) -> Callable:
    """The iteration kernel with the models bound (eager)."""
    if existence is None:
        def iterate(*args):
            return exchange_iteration(*args, motion=motion, sensor=sensor)
    else:
        def iterate(*args):
            return exchange_existence_iteration(*args, motion=motion, sensor=sensor, existence=existence)
    return iterate


class IPMCMCFilter(Filter):
    """Interacting population-based MCMC-PF (paper 000 Alg. 1-2) for K known targets.

    Parameters
    ----------
    motion : MotionModel applied to every target slot.
    sensor : SensorModel (radar TBD, LinearGaussian, ...).
    num_particles : N; ``num_chains`` must divide it.
    num_chains : C parallel chains (paper: 50).
    burn_in : iterations discarded per chain (paper: 100).
    rhat_threshold : R-hat level that triggers an extension (paper: 1.1).
    max_extensions : at most this many extensions of N/C iterations per step (default 2).
    rhat_method : ``"paper"`` (eq. 13, default) or ``"gelman-rubin"``.
    compile : compile the MH iteration with ``torch.compile(fullgraph=True)`` (the first
        step pays the compile time).
    existence : BirthDeath, optional: births and deaths (module docstring); the estimate
        of a slot is then its mean given existence
        (:func:`torchmcmcpf.models.existence.existence_estimate`).

    Example
    -------
    >>> filt = IPMCMCFilter(scn.motion, scn.sensor, 5000, num_chains=50, burn_in=100)  # doctest: +SKIP
    >>> result = filt(scn.measurements, init=x0, generator=g)                          # doctest: +SKIP
    >>> result.info.rhat.shape, result.info.extensions.shape                           # (T, B) each
    """

    def __init__(
        self,
        motion: MotionModel,
        sensor: SensorModel,
        num_particles: int,
        num_chains: int = 50,
        burn_in: int = 100,
        rhat_threshold: float = 1.1,
        max_extensions: int = 2,
        *,
        rhat_method: str = "paper",
        compile: bool = False,
        existence: Optional[BirthDeath] = None,
    ):
        super().__init__(motion, sensor)
        self.existence = check_existence(existence)
        self.num_particles = check_positive_int(num_particles, "num_particles")
        self.num_chains = check_positive_int(num_chains, "num_chains", minimum=2)
        if num_particles % num_chains:
            raise ValueError(f"num_chains={num_chains} must divide num_particles={num_particles}")
        if num_particles // num_chains < 2:
            raise ValueError(
                f"num_particles / num_chains = {num_particles // num_chains}, expected >= 2 kept "
                "samples per chain (R-hat needs them)"
            )
        self.burn_in = check_positive_int(burn_in, "burn_in", minimum=0)
        self.rhat_threshold = check_positive(rhat_threshold, "rhat_threshold")
        self.max_extensions = check_positive_int(max_extensions, "max_extensions", minimum=0)
        if rhat_method not in RHAT_METHODS:
            raise ValueError(f"rhat_method must be one of {RHAT_METHODS}, got {rhat_method!r}")
        self.rhat_method = rhat_method
        self.compile = bool(compile)
        self._iterate: Optional[Callable] = None

    def _iteration(self) -> Callable:
        if self._iterate is None:
            iterate = _bind(self.motion, self.sensor, self.existence)
            self._iterate = torch.compile(iterate, fullgraph=True, dynamic=False) if self.compile else iterate
        return self._iterate

    def step(self, state: ParticleState, z: Measurement, *, generator: torch.Generator
             ) -> tuple[ParticleState, StepInfo]:
        """One IP-MCMC-PF step (see :func:`ipmcmc_step`); ``state.x`` is ``(B, N, K, D)``."""
        check_generator(generator)
        return ipmcmc_step(
            state, z, motion=self.motion, sensor=self.sensor, num_chains=self.num_chains,
            burn_in=self.burn_in, generator=generator, rhat_threshold=self.rhat_threshold,
            max_extensions=self.max_extensions, rhat_method=self.rhat_method,
            iterate=self._iteration(), existence=self.existence,
        )

    def extra_repr(self) -> str:
        return (f"num_particles={self.num_particles}, num_chains={self.num_chains}, burn_in={self.burn_in}, "
                f"rhat_threshold={self.rhat_threshold}, max_extensions={self.max_extensions}, "
                f"compile={self.compile}")
