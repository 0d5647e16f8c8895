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
3. After ``burn_in`` iterations every chain contributes its next ``S = N / C`` states (with
   ``thinning = m``: its states after every m-th of the next ``m S`` iterations); the
   ``C * S = N`` samples are the new equally weighted particles.
4. *Convergence check* (Alg. 1, step 3): R-hat of eq. 13 (``diagnostics.rhat``,
   ``method="paper"`` by default) of every state component over the chains' states in the
   **second half of the iterations run so far**; where its largest value is
   ``>= rhat_threshold`` the chains of that run go on for another ``thinning * S``
   iterations, the last kept states replace the kept ones and R-hat is taken again over the
   second half of the longer chains, at most ``max_extensions`` times.

Convergence check: what R-hat is computed on, and why
-----------------------------------------------------
Eq. 13 compares the within-chain variances with the variance of all chains pooled. Taken
over the ``S`` kept states alone (the paper's reading, ``S = 10`` for ``N = 500``, ``C =
50``) it cannot work with this kernel: an iteration proposes one of the K slots, so in 10
consecutive iterations a slot is proposed about ``10 / K`` times and accepted less often,
most slots of most chains never move inside the window, the within-chain variance of
their components is 0 and R-hat is ``inf`` or far above 1.1 whether the chains have mixed
or not (10 targets, ``N = 500``: median 24, an extension at every step, while the tracks
are good). The window is therefore Gelman and Rubin's (1992, ref. [23] of paper 000): the
second half of each chain's iterations, burn-in included (``(burn_in + thinning S) / 2``
states per chain, all of them, since R-hat needs no independent samples, only enough
moves inside the window: about ``W / K`` proposals per slot for a window of W
iterations). Each extension lengthens the chains and so the window. This keeps the rule
what the paper says it is, a test that the chains forgot their different starting points
(``R = 1``: "the MCMC chains have converged within the burn-in period"), at no extra
iteration. R-hat is taken per state component (positions, velocities, amplitude of every
slot) on *relabelled* chains: the K slots of a state are exchangeable labels, and two
chains holding the same targets under different labels (they started from particles of a
label-switched cloud, or a two-slot or re-capture move exchanged two targets) have
converged to the same thing, as has a chain whose labels change within the window; each
state's slots are therefore permuted to the labels of a reference common to the run
(:func:`~torchmcmcpf.filters._convergence.chains_relabelled`, Stephens 2000), and R-hat
compares targets. Chains that agree are left as they are. The largest value decides; ``extras["rhat_slot"]`` and
``extras["rhat_dim"]`` say which target and which component drive it (its label after
relabelling). ``thinning`` (default 1, the paper) only changes which states become
particles: with ``thinning = K`` each particle follows one sweep over the slots on
average, at ``K`` times the cost of the kept phase.

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

Exclusion and re-capture (the defaults)
---------------------------------------
With :class:`~torchmcmcpf.models.multitarget.Exclusion` the target gains the pairwise factor
``Phi(y)`` (a one-slot move pays its ``K - 1`` factors); with
:class:`~torchmcmcpf.models.multitarget.Recapture` each slot's prior gains the relocation
component and the exchange move draws a slot from the data with probability ``epsilon``
(the chains cache ``log r_j`` per slot, as for births), and every ``pair_every``-th iteration
moves two slots whose predictions are close, both slots from one previous particle with
probability ``p_same_source`` (the chains then keep each slot's source ``i_j``, and the
move's ratio carries the pair's source term: :mod:`torchmcmcpf.kernels.exchange`, "The
two-slot move's sources"). ``exclusion=None, recapture=None`` is the paper's target and move.

The pair-path move (optional)
-----------------------------
With ``pair_path=PairPath(...)`` (:mod:`torchmcmcpf.kernels.pair_path`; off by default) the
state keeps (``extras["pair_path"]``, a :class:`~torchmcmcpf.kernels.pair_path.PairPathWindow`)
each particle's last ``L + 1`` states per slot (each new slot continues the path
of its source particle's slot, ``ExchangeChains.source``) and the last ``L`` frames; where
two slots' predicted estimates came within ``distance`` resolution cells in the last ``L``
frames, every ``every`` steps, a conditional SMC with ancestor sampling re-draws the pair's
paths over the window for ``num_paths`` of the new particles, invariant for the model's path
posterior's conditional of the pair (that module's eq. 2). ``extras["pair_path_fired"]``,
``extras["pair_path_moved"]`` report it.

Joint pairs (optional)
----------------------
With ``joint_pairs=d`` two slots whose predicted estimates are each other's nearest within
``d`` resolution cells (fixed for the step) keep their *joint* prediction, one source particle
for both, instead of the product of their marginals: the target above with each such pair's
``m_a(y_a) m_b(y_b)`` replaced by ``sum_i w^i p(y_a | x^i_a) p(y_b | x^i_b)`` (the MCMC-PF's
prior over the pair). A paired slot's one-slot move then proposes from its pair's current
source, and the two-slot move (``recapture.pair_every``) runs over these pairs, drawing one
source for both (:mod:`torchmcmcpf.kernels.exchange`, "Joint pairs"; invariance tested on a
quadrature target). After an unresolved crossing the factorised prior also holds the
arrangements that no particle held (docs/tracks.md); the pair's joint prediction does not.

HMC refinement (optional)
-------------------------
With ``hmc=HMCRefine(...)`` (:mod:`torchmcmcpf.kernels.hmc_refine`) every chain also takes
one Hamiltonian Monte Carlo transition of all its slots at once after every
``hmc.every``-th exchange iteration, with autograd gradients of the sensor likelihood
(differentiable through the radar's windowed path), targeting the same

    ``pi(y) ∝ p(z_k | y) prod_j m_j(y_j)``,  ``m_j(y_j) = sum_i w^i N(y_j; F x^i_{k-1,j}, Q)``

(the log-sum-exp over the N previous particles per slot gives ``log m_j`` and its
gradient), so the composition leaves ``pi`` invariant. The exchange move is an
independence sampler: it can only jump to a fresh prediction of one slot; the HMC move
follows the likelihood's gradient and moves every slot of every chain a little at each
transition. ``extras["acceptance_hmc"]`` reports its acceptance rate. The HMC transition
runs eagerly, also with ``compile_step=True`` (which compiles the exchange iteration), and
needs a linear-Gaussian motion and no existence model.

Batching and extensions
-----------------------
Runs differ in whether they need an extension. The extension loop runs while *any* run
needs one (one ``bool(tensor)`` host sync per extension, in eager code); every run
iterates, but only the runs that need it replace their kept samples and chain states and
count the extension (``torch.where``), so each run's result is what it would be alone,
up to the random numbers consumed. The cost: an extension round costs every run
``thinning * S`` iterations (about ``thinning * S / (burn_in + thinning * S)`` of a step,
9 % with the paper's settings) as soon as one of the B runs needs it; ``extras["extensions"]``
counts only the runs that needed it. Running the extension on the runs that need it alone
would change the batch shape from round to round (a recompile per shape under
``compile_step``), which costs more than it saves at the batch sizes used here.

Speed
-----
All random numbers of a segment (the ``burn_in + S`` iterations, then ``S`` per extension)
are drawn in a few eager calls and, the move being an independence proposal, the slots
they propose are made from them in one batched call
(:func:`~torchmcmcpf.kernels.exchange.propose_slots`: parents, motion, births, relocation,
for every iteration at once); both are fed to :func:`exchange_iteration`, a pure tensor
function that traces under ``torch.compile(fullgraph=True)``; ``IPMCMCFilter(compile_step=True)``
compiles it once per filter. Each iteration evaluates the sensor on the ``(B, C)``
proposals only: for grid sensors the change of the log-likelihood caused by the one slot
that moves (``sensor.log_likelihood_delta``, the cells of its old and new box), otherwise
``sensor.log_likelihood`` of the proposal; with the chains' amplitude cache (grid sensors,
:class:`~torchmcmcpf.kernels.exchange.ExchangeChains`), a one-slot move reads the
amplitudes at its two boxes instead of summing the other targets' spreads there, the same
on every device. With the exclusion term the chains also keep their slots' resolution
coordinates (``ExchangeChains.coords``; the proposed slots' are made with the segment's
proposals), and the frame's detections, which every draw from the data reads, are found once
per step (:meth:`~torchmcmcpf.models.base.SensorModel.frame_detections`): the defaults' terms
add no per-iteration mapping of the slots and no repeated CLEAN. On a GPU, the compiled
iteration runs each segment (without HMC refinement) as one CUDA graph
(:meth:`~torchmcmcpf.runtime.Program.capture`), the cache's advance included: the step then
costs the kernels' own time instead of a launch and its Python per iteration (H200, Np =
5000, without the cache: 73 to 16 ms per step; benchmarks/README.md).
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any, NamedTuple

import torch
from torch.utils._pytree import tree_map

from .._native.select import where
from .._validation import check_positive_int
from ..diagnostics import RHAT_METHODS
from ..kernels.exchange import (
    ExchangeChains,
    ExchangeNoise,
    close_pairs,
    draw_exchange_noise,
    exchange_iteration,
    mutual_nearest_pairs,
    one_call_serves,
    propose_slots,
    with_accepted_amplitudes,
)
from ..kernels.exchange_segment import exchange_run, run_serves
from ..kernels.hmc_refine import (
    HMCRefine,
    HMCRefineNoise,
    check_hmc_motion,
    hmc_refine,
    mixture_log_prior,
    with_exclusion,
)
from ..kernels.pair_path import PairPath, PairPathWindow, pair_path_update
from ..models.base import MotionModel, SensorModel
from ..models.existence import BirthDeath, TargetDynamics
from ..models.multitarget import Exclusion, Recapture, check_exclusion, check_recapture, exclusion_on
from ..resampling import gather_particles, normalize, systematic
from ..runtime import Program, take_along
from ..state import ParticleState, StepInfo, existence_estimate, weighted_mean
from ..typing import Measurement, Tensor
from ._bound import Bound, Compile, bind, check_existence_proposal
from ._carry import ESTIMATE, carry
from ._convergence import RhatReport, rhat_report, window_start
from .base import Filter

__all__ = ["IPMCMCFilter", "IPMCMCSettings", "ipmcmc_step", "bind_ipmcmc", "ipmcmc_bound_step", "ipmcmc_program"]

#: the key of ``ParticleState.extras`` under which the pair-path move keeps its window
PAIR_PATH = "pair_path"
carry(PAIR_PATH)(PairPathWindow)  # a typed carry (filters/_carry.py): checked on resume, loads weights_only


class SegmentNoise(NamedTuple):
    """The randomness of one segment of ``L`` iterations: ``single`` (leading ``L``, one slot
    per iteration) and, for the two-slot iterations, ``pair`` (leading ``len(at_pairs)``) with
    ``at_pairs`` the (static) positions of the two-slot iterations in the segment.
    """

    single: ExchangeNoise
    pair: ExchangeNoise | None = None
    at_pairs: tuple[int, ...] = ()

    def iterations(self) -> list[ExchangeNoise]:
        """The noise of every iteration in order (each with leading ``(B, C)``): every field
        unbound once, not indexed per iteration (a select per field and iteration cost 7 % of
        an eager radar step, 10 targets, Np = 5000), from a contiguous copy, so that an
        iteration's noise has the same strides whatever the segment's length (a field drawn
        run-major and moved had strides that grew with it, and a compiled iteration then
        compiled again for the R-hat rule's extensions: 4 programs in the first step instead
        of 2, 36 s cold for Np = 500, 10 targets).
        """
        out = _rows(self.single, self.single.u.shape[0])
        if self.pair is not None:
            for t, noise in zip(self.at_pairs, _rows(self.pair, self.pair.u.shape[0])):
                out[t] = noise
        return out


def _rows(x: Any, length: int) -> list:
    """The rows of a tree of NamedTuples of tensors (leading ``length``) and None, built field
    by field (torch's generic ``tree_unflatten`` cost 30 us an iteration, 6 % of an eager radar
    step), each tensor unbound from a contiguous copy.
    """
    if x is None:
        return [None] * length
    if isinstance(x, torch.Tensor):
        return list(x.contiguous().unbind(0))
    return [type(x)(*row) for row in zip(*(_rows(field, length) for field in x))]


def _run_chains(chains: ExchangeChains, noise: SegmentNoise, iteration: Callable, sensor: SensorModel,
                refine: Callable | None = None, every: int = 1, record_from: int = 0
                ) -> tuple[ExchangeChains, list[ExchangeChains], Tensor, Tensor]:
    """Run ``L`` iterations ``iteration(chains, noise_t) -> (chains, accepted, update)``
    (:func:`exchange_iteration` with its models bound), each followed by the advance of the
    chains' amplitude cache (:func:`with_accepted_amplitudes`) and, after every ``every``-th,
    by ``refine(chains, i) -> (chains, accepted)`` (the ``i``-th HMC refinement) when given;
    return the final chains, the list of the chains after iterations ``record_from .. L - 1``
    (references, no copies, without their caches and sources), the number of exchange acceptances per
    chain ``(B, C)`` and that of refinements.
    """
    trace = []
    log_lik = chains.log_lik
    accepted_count = torch.zeros(log_lik.shape, device=log_lik.device, dtype=log_lik.dtype)
    refined_count = torch.zeros_like(accepted_count)
    for t, noise_t in enumerate(noise.iterations()):
        new, acc, update = iteration(chains, noise_t)
        chains = with_accepted_amplitudes(new, chains.amplitude, update, acc, sensor)
        accepted_count = accepted_count + acc.to(accepted_count.dtype)
        if refine is not None and (t + 1) % every == 0:
            chains, acc = refine(chains, (t + 1) // every - 1)
            refined_count = refined_count + acc.to(refined_count.dtype)
        if t >= record_from:
            # the sources stay: the pair-path window's genealogy
            trace.append(chains._replace(log_w_source=None, amplitude=None, coords=None, terms=None))
    return chains, trace, accepted_count, refined_count


def _segment(iteration: Callable, chains: ExchangeChains, noise: SegmentNoise, x_prev: Tensor,
             exists: Tensor | None, z: Measurement, record_from: int, sensor: SensorModel
             ) -> tuple[ExchangeChains, ExchangeChains, Tensor]:
    """``L`` exchange iterations of every chain (no refinement): ``(chains, trace, accepted)``
    as :func:`_run_chains` gives them, the trace stacked (each entry with leading ``L -
    record_from``; :func:`_unstack` undoes it). The loop that
    :meth:`~torchmcmcpf.runtime.Program.capture` runs as one CUDA graph on a GPU, the
    amplitude cache's advance included (a scatter-add: no host sync).
    """
    def step(ch, nz):
        return iteration(ch, x_prev, exists, z, nz)

    chains, trace, accepted, _ = _run_chains(chains, noise, step, sensor, record_from=record_from)
    return chains, tree_map(lambda *a: None if a[0] is None else torch.stack(a), *trace), accepted


def _unstack(stacked: ExchangeChains) -> list[ExchangeChains]:
    """A stacked trace (:func:`_segment`) -> the list of chains (views)."""
    length = next(t for t in stacked if t is not None).shape[0]
    return [ExchangeChains(*row) for row in zip(*(t.unbind(0) if t is not None else (None,) * length
                                                  for t in stacked))]


def _kept(trace: list, keep: int, thinning: int) -> tuple:
    """The chain tuples after every ``thinning``-th of the last ``keep * thinning`` iterations
    of ``trace``, stacked (leading ``keep``).
    """
    kept = trace[len(trace) - keep * thinning + thinning - 1::thinning]
    return tree_map(lambda *a: None if a[0] is None else torch.stack(a), *kept)


@dataclass(frozen=True)
class IPMCMCSettings:
    """Settings of the IP-MCMC-PF (paper 000), validated on construction.

    Attributes
    ----------
    num_chains : C >= 2 parallel chains (paper: 50); must divide N with ``N / C >= 2``.
    burn_in : iterations discarded per chain (paper: 100).
    rhat_threshold : extend the chains of a run while its largest R-hat is ``>=`` this (1.1);
        ``math.inf`` switches the rule off (as ``max_extensions=0`` does; R-hat is still
        reported).
    max_extensions : at most this many extensions of ``thinning * N / C`` iterations (0
        disables).
    rhat_method : ``"paper"`` (eq. 13), ``"gelman-rubin"`` (see :mod:`..diagnostics`) or
        ``None``: no convergence check, a fixed ``burn_in`` (no extensions, and no R-hat is
        computed: the report's extras are NaN). The check relabels the second half of every
        chain's states: 11 % of a births/deaths step, where it never converges (the
        births/deaths study runs without it, :mod:`~torchmcmcpf.experiments.septier_birth_death`).
    thinning : keep every ``thinning``-th state after the burn-in (1: the paper's
        consecutive states); ``thinning = K`` makes every kept sample follow one sweep over
        the K slots on average.
    hmc : :class:`~torchmcmcpf.kernels.hmc_refine.HMCRefine`, optional: an HMC refinement
        of every chain's states after every ``hmc.every``-th exchange iteration, on the same
        factorised-prior posterior (module docstring); ``None`` (default): exchange only.
    exclusion : :class:`~torchmcmcpf.models.multitarget.Exclusion` (default) or None: the
        exclusion factor between slots in the target (module docstring, "Exclusion and
        re-capture"); None is the paper's factorised prior.
    recapture : :class:`~torchmcmcpf.models.multitarget.Recapture` (default) or None: the
        heavy-tailed slot prior, the data-driven proposal of the exchange move and the
        two-slot move; None is the paper's exchange move. Set to None with ``hmc`` (whose
        target uses the prior without the relocation component).

    existence_proposal : ``(q_birth, q_death)`` or None, as
        :class:`~torchmcmcpf.filters.mcmc.MCMCSettings` (default ``(0.5, 0.1)``).
    pair_path : :class:`~torchmcmcpf.kernels.pair_path.PairPath` or None (default): the
        triggered conditional-SMC move on two close slots' paths over the last ``lag`` frames
        after the chains (module docstring, "The pair-path move"); a known number of
        targets and a tensor frame only.
    joint_pairs : a distance in resolution cells, or None (default): two slots whose
        predicted estimates are each other's nearest within it keep their joint prediction
        (one source for both) instead of the product of their marginals, and the two-slot
        move runs over these pairs (module docstring, "Joint pairs"). Needs ``recapture``
        with ``pair_every > 0`` (the move that changes a pair's source), a known number of
        targets, and no ``hmc``.

    Both are turned off for a sensor that cannot support them
    (:func:`~torchmcmcpf.filters.base.active_prior`).

    Example
    -------
    >>> from torchmcmcpf.filters.ipmcmc import IPMCMCSettings
    >>> settings = IPMCMCSettings(num_chains=50, burn_in=100)          # paper 000's Table II
    >>> settings.rhat_threshold, settings.max_extensions               # extend while R-hat >= 1.1
    (1.1, 2)
    >>> settings.check(500)                                            # 10 kept samples per chain
    >>> settings.check(75)
    Traceback (most recent call last):
    ...
    ValueError: num_chains=50 must divide num_particles=75
    """

    num_chains: int = 50
    burn_in: int = 100
    rhat_threshold: float = 1.1
    max_extensions: int = 2
    rhat_method: str | None = "paper"
    thinning: int = 1
    hmc: HMCRefine | None = None
    exclusion: Exclusion | None = Exclusion()
    recapture: Recapture | None = Recapture()
    existence_proposal: tuple[float, float] | None = (0.5, 0.1)
    pair_path: PairPath | None = None
    joint_pairs: float | None = None

    def __post_init__(self):
        object.__setattr__(self, "num_chains", check_positive_int(self.num_chains, "num_chains", minimum=2))
        object.__setattr__(self, "burn_in", check_positive_int(self.burn_in, "burn_in", minimum=0))
        if not (isinstance(self.rhat_threshold, (int, float)) and float(self.rhat_threshold) > 0):
            raise ValueError(f"rhat_threshold must be > 0 (math.inf: never extend), got {self.rhat_threshold!r}")
        object.__setattr__(self, "rhat_threshold", float(self.rhat_threshold))
        object.__setattr__(self, "max_extensions", check_positive_int(self.max_extensions, "max_extensions", minimum=0))
        if self.rhat_method is not None and self.rhat_method not in RHAT_METHODS:
            raise ValueError(f"rhat_method must be one of {RHAT_METHODS} or None, got {self.rhat_method!r}")
        object.__setattr__(self, "thinning", check_positive_int(self.thinning, "thinning"))
        if self.hmc is not None and not isinstance(self.hmc, HMCRefine):
            raise ValueError(f"hmc must be an HMCRefine or None, got {type(self.hmc).__name__}")
        check_exclusion(self.exclusion)
        check_recapture(self.recapture)
        if self.hmc is not None:
            object.__setattr__(self, "recapture", None)  # HMC's target: the prior without relocation
        object.__setattr__(self, "existence_proposal", check_existence_proposal(self.existence_proposal))
        if self.pair_path is not None and not isinstance(self.pair_path, PairPath):
            raise ValueError(f"pair_path must be a PairPath or None, got {type(self.pair_path).__name__}")
        if self.joint_pairs is not None:
            if isinstance(self.joint_pairs, bool) or not isinstance(self.joint_pairs, (int, float)) \
                    or not float(self.joint_pairs) > 0:
                raise ValueError(f"joint_pairs must be a distance > 0 in resolution cells or None, got "
                                 f"{self.joint_pairs!r}")
            if self.recapture is None or self.recapture.pair_every == 0 or self.hmc is not None:
                raise ValueError("joint_pairs needs recapture with pair_every > 0 (the move that changes a pair's "
                                 f"source) and hmc=None, got recapture={self.recapture!r}, hmc={self.hmc!r}")
            object.__setattr__(self, "joint_pairs", float(self.joint_pairs))

    def check(self, num_particles: int) -> None:
        """``C | N`` with at least 2 kept samples per chain."""
        if num_particles % self.num_chains:
            raise ValueError(f"num_chains={self.num_chains} must divide num_particles={num_particles}")
        if num_particles // self.num_chains < 2:
            raise ValueError(
                f"num_particles / num_chains = {num_particles // self.num_chains}, expected >= 2 kept "
                "samples per chain"
            )


def bind_ipmcmc(motion: MotionModel, sensor: SensorModel, settings: IPMCMCSettings | None = None,
                existence: BirthDeath | None = None, *, num_particles: int | None = None, compile: Compile = None
                ) -> Bound:
    """The IP-MCMC-PF's :class:`~torchmcmcpf.filters._bound.Bound`: the models, ``settings``
    (default :class:`IPMCMCSettings`) checked against them (:meth:`IPMCMCSettings.check` with
    ``num_particles`` when given; ``hmc`` needs a linear-Gaussian motion and no existence),
    the existence model with the settings' ``existence_proposal``, and the program, one
    exchange iteration (:func:`ipmcmc_program`, compiled with ``compile``).
    """
    def check(bound: Bound) -> None:
        if num_particles is not None:
            bound.settings.check(num_particles)
        if bound.settings.hmc is not None:
            check_hmc_motion(motion, bound.existence)
        if bound.settings.joint_pairs is not None and bound.existence is not None:
            raise ValueError("settings.joint_pairs needs a known number of targets (existence=None)")

    return bind(motion, sensor, IPMCMCSettings() if settings is None else settings, existence, check=check,
                program=lambda b, c: ipmcmc_program(b.dynamics, b.sensor, b.settings.exclusion, c), compile=compile)


def ipmcmc_step(
    state: ParticleState,
    z: Measurement,
    *,
    motion: MotionModel,
    sensor: SensorModel,
    settings: IPMCMCSettings = IPMCMCSettings(),
    generator: torch.Generator,
    existence: BirthDeath | None = None,
) -> tuple[ParticleState, StepInfo]:
    """One IP-MCMC-PF step: :func:`ipmcmc_bound_step` after an eager :func:`bind_ipmcmc` (a
    filter binds once). Parameters and returns: :func:`ipmcmc_bound_step`, with the models
    ``motion``, ``sensor``, ``existence`` and ``settings`` (:class:`IPMCMCSettings`) in place
    of ``bound``: ``state`` with ``x (B, N, K, D)``, ``log_w (B, N)`` (``exists (B, N, K)`` with
    births and deaths) and ``z`` one frame per run ``(B, *G)`` give a state of the same shapes.
    """
    bound = bind_ipmcmc(motion, sensor, settings, existence, num_particles=state.x.shape[1])
    return ipmcmc_bound_step(state, z, bound, generator=generator)


def ipmcmc_bound_step(state: ParticleState, z: Measurement, bound: Bound, *, generator: torch.Generator
                      ) -> tuple[ParticleState, StepInfo]:
    """One IP-MCMC-PF step (paper 000 Alg. 1-2); see the module docstring.

    Parameters
    ----------
    state : ParticleState with ``x (B, N, K, D)`` and ``log_w (B, N)`` (uniform after an
        MCMC step; any normalised weights are honoured by the start and source draws).
        ``exists (B, N, K)``: with ``existence`` only (None: every slot starts inactive).
    z : one frame per run ``(B, *G)``.
    bound : :class:`~torchmcmcpf.filters._bound.Bound` of :func:`bind_ipmcmc`: the models,
        :class:`IPMCMCSettings`, the existence model (births and deaths, module docstring:
        the starting points are predicted by :meth:`BirthDeath.propose`, births near the
        points of ``z`` when it draws them so) and the program, one exchange iteration
        (:func:`ipmcmc_program`, ``program(chains, x_prev, exists_prev, z, noise)``; compiled
        by ``IPMCMCFilter(compile_step=True)``, a :class:`~torchmcmcpf.runtime.Program` whose
        ``capture`` runs each segment as one CUDA graph on a GPU).
    generator : the only source of randomness.

    Returns
    -------
    state : ``x (B, N, K, D)``, the kept samples chain by chain (chain ``c`` owns particles
        ``c S .. (c+1) S - 1``), ``log_w = -log N``; with existence ``exists (B, N, K)``.
    info : ``acceptance (B,)``, the exchange acceptance rate over every iteration the run
        used; ``ess``, ``log_evidence`` NaN; extras (floats): ``"rhat" (B,)`` the largest
        R-hat (eq. 13) over the state components of the second half of the run's iterations
        (module docstring, "Convergence check"), ``"rhat_slot"``, ``"rhat_dim"`` (B,) the
        target slot ``k`` and state dimension ``d`` of the component that drives it and
        ``"extensions" (B,)`` how many extensions ran and, with ``settings.hmc``,
        ``"acceptance_hmc" (B,)`` the HMC refinement's acceptance rate.
    """
    motion, sensor, settings, existence = bound.motion, bound.sensor, bound.settings, bound.existence
    # (x, exists) jointly: one model of the slots with or without births and re-capture, for
    # the starting points, the noise and the moves
    dynamics, iteration = bound.dynamics, bound.program
    x_prev, log_w, exists = state.x, state.log_w, state.exists
    num_chains, burn_in = settings.num_chains, settings.burn_in
    rhat_threshold, max_extensions, rhat_method = settings.rhat_threshold, settings.max_extensions, settings.rhat_method
    if existence is None and exists is not None:
        raise ValueError("state.exists must be None without an existence model: pass existence= for an "
                         "unknown number of targets")
    b, n, k, _ = x_prev.shape
    if existence is not None and exists is None:
        exists = torch.zeros((b, n, k), dtype=torch.bool, device=x_prev.device)
    keep = n // num_chains
    recapture = settings.recapture

    # 1. starting points: C previous particles (systematic: one per stratum), predicted
    start = systematic(log_w, torch.rand((b, 1), dtype=torch.float64, generator=generator,
                                           device=x_prev.device), num_chains)
    x0 = gather_particles(x_prev, start)
    e0 = None if exists is None else gather_particles(exists, start)
    # the frame's detections (a grid sensor's CLEAN) once per step, for every draw from the data
    found = None if dynamics.recapture is None else sensor.frame_detections(z)
    y, e, log_r, kind = dynamics.propagate_labelled(x0, e0, *dynamics.draw_noise(x0, z, generator=generator,
                                                                                 found=found), start=True)
    # the chains' amplitudes per cell (grid sensors; ExchangeChains.amplitude): a move then
    # reads its two boxes instead of summing the other targets' spreads there
    # two-slot moves: every pair_every-th iteration, over the pairs of slots whose predicted
    # estimates are close (fixed for the step: a fixed mixture of invariant kernels)
    pair_every = 0 if recapture is None or k < 2 else recapture.pair_every
    joint = settings.joint_pairs is not None and pair_every > 0
    source = log_w_source = None
    if (pair_every and recapture is not None and recapture.p_same_source > 0) or settings.pair_path is not None \
            or joint:
        # every slot's source particle (the pair-path move's genealogy too)
        source = start.unsqueeze(-1).repeat(1, 1, k)  # contiguous, as every later state (one compiled graph)
        log_w_source = take_along(normalize(log_w)[0], start, 1
                                            ).unsqueeze(-1).repeat(1, 1, k)
    # with the exclusion term the chains keep their slots' resolution coordinates, and each
    # segment's proposals come with theirs (one batched call): a move maps no slot again
    excluding = exclusion_on(settings.exclusion, sensor)
    amplitude = sensor.amplitude_cache(y, e, z)
    # what a cached move reads of each slot, kept with the chains (the moved slots' made with
    # each segment's proposals): a move gathers rows instead of mapping states
    terms = None if amplitude is None else sensor.move_terms(y, e)
    chains = ExchangeChains(y, sensor.log_likelihood(y, z, e), e,
                            None if existence is None and recapture is None else log_r, kind, source, log_w_source,
                            amplitude, sensor.resolution_coords(y) if excluding else None, terms)
    pairs = partner = None
    if pair_every and recapture is not None:
        if exists is None:
            centre, alive = weighted_mean(x_prev, log_w), None
        else:
            est = existence_estimate(ParticleState(x_prev, log_w, exists))
            centre, alive = est.mean, est.present
        centre = motion.propagate(centre, torch.zeros(centre.shape[:-1] + (motion.noise_dim,), dtype=centre.dtype,
                                                      device=centre.device))
        if joint and settings.joint_pairs is not None:  # the pairs that keep their joint prediction
            partner = mutual_nearest_pairs(sensor.resolution_coords(centre), settings.joint_pairs, alive)
            own = torch.arange(k, device=partner.device)
            pairs = (partner.unsqueeze(-1) == own) & (own.unsqueeze(-1) < own)  # (B, K, K): i < partner[i]
        else:
            pairs = close_pairs(sensor.resolution_coords(centre), recapture.pair_distance, alive)

    # 2. burn-in + thinning * S iterations; every thinning-th of the last thinning * S is kept
    def draw(steps: int, offset: int) -> SegmentNoise:
        def one(count: int, close: Tensor | None) -> ExchangeNoise:
            noise = draw_exchange_noise(log_w, count, num_chains, k, dynamics=dynamics, generator=generator,
                                        dtype=x_prev.dtype, z=z, pairs=close, exists=exists, found=found,
                                        partner=partner)
            if partner is not None and close is None:  # a paired slot's proposal reads its chain's source
                return noise
            # the segment's proposals in one batched call (an independence proposal); the
            # iterations read them, not the birth and relocation draws they were made from
            return noise._replace(proposal=propose_slots(noise, x_prev, exists, dynamics=dynamics,
                                                         sensor=sensor if excluding else None,
                                                         terms_of=None if terms is None else sensor),
                                  birth=None, relocation=None)
        at_pairs = tuple(t for t in range(steps) if pair_every and (offset + t + 1) % pair_every == 0)
        return SegmentNoise(one(steps, None), one(len(at_pairs), pairs) if at_pairs else None, at_pairs)

    segment = settings.thinning * keep
    hmc = settings.hmc
    refine, every = None, 1
    if hmc is not None:
        hmc_motion = check_hmc_motion(motion, existence)
        every = hmc.every
        log_prior = with_exclusion(mixture_log_prior(x_prev, log_w, hmc_motion), settings.exclusion, sensor)

        def refine(ch, i):
            y_new, ll_new, acc = hmc_refine(ch.y, ch.log_lik, HMCRefineNoise(*(a[i] for a in hmc_noise)), z,
                                            log_prior=log_prior, sensor=sensor, motion=hmc_motion, settings=hmc)
            # every slot may have moved: the amplitudes afresh
            amplitude = None if ch.amplitude is None else sensor.amplitude_cache(y_new, ch.exists, z)
            coords = None if ch.coords is None else sensor.resolution_coords(y_new)
            terms_new = None if ch.terms is None else sensor.move_terms(y_new, ch.exists)
            return ch._replace(y=y_new, log_lik=ll_new, amplitude=amplitude, coords=coords, terms=terms_new), acc

    done = 0  # iterations run so far (the two-slot schedule counts across segments)

    def run(steps, record_from=0):
        nonlocal hmc_noise, done
        noise = draw(steps, done)
        done += steps
        if hmc is not None:  # HMC refinements (eager, autograd) between the iterations
            hmc_noise = HMCRefineNoise.draw(y, generator=generator, leading=(steps // every,))
            return _run_chains(chains, noise, lambda ch, nz: iteration(ch, x_prev, exists, z, nz), sensor, refine,
                               every, record_from)
        # a compiled iteration runs the segment through its capture: one CUDA graph on a GPU
        capture = getattr(iteration, "capture", None)
        args = (chains, noise, x_prev, exists, z, record_from, sensor)
        served = dict(dynamics=dynamics, sensor=sensor, exclusion=settings.exclusion, pairs=noise.pair)
        if run_serves(chains, z, noise.single, **served):
            # the iterations in C calls (eager CPU: faster than the compiled graph)
            ch, acc, trace = exchange_run(chains, z, noise.single, at_pairs=noise.at_pairs, record_from=record_from,
                                          **served)
        else:
            ch, trace, acc = capture(_segment, *args) if capture is not None else _segment(iteration, *args)
        return ch, _unstack(trace), acc, torch.zeros_like(acc)

    hmc_noise = None
    # states before the first window (and before the kept ones) are not recorded; without a
    # check, only the kept ones
    record_from = burn_in if rhat_method is None else min(window_start(burn_in + segment), burn_in)
    chains, trace, accepted, refined = run(burn_in + segment, record_from)
    history = _kept(trace, keep, settings.thinning)
    ys = [c[0] for c in trace]  # (B, C, K, D) after iterations record_from, ...: the R-hat window's source
    iterations = torch.full((b,), float(burn_in + segment), device=x_prev.device, dtype=x_prev.dtype)

    # 3. R-hat on the second half of the iterations, and extensions (all runs iterate, only
    # those that need it update; a run that stops needing never needs again)
    if rhat_method is None:  # no check: nothing to report
        nan = torch.full((b,), math.nan, device=x_prev.device, dtype=x_prev.dtype)
        report = RhatReport(nan, nan, nan)
    else:
        report = rhat_report(ys, record_from, rhat_method, sensor.resolved)
    extensions = torch.zeros(b, dtype=torch.int64, device=x_prev.device)
    for _ in range(max_extensions if rhat_threshold < math.inf and rhat_method is not None else 0):
        need = report.max >= rhat_threshold  # (B,)
        if not bool(need.any()):
            break
        # every run iterates and goes on from where it is (the cache follows the chains); the
        # runs that did not need the extension keep their earlier kept states below
        chains, trace_e, acc_e, ref_e = run(segment)
        hist_e = _kept(trace_e, keep, settings.thinning)
        history = tuple(None if h is None else where(need.reshape((1, b) + (1,) * (h.dim() - 2)), he, h)
                        for he, h in zip(hist_e, history))
        ys = ys + [c[0] for c in trace_e]
        accepted = accepted + where(need.unsqueeze(-1), acc_e, torch.zeros_like(acc_e))
        refined = refined + where(need.unsqueeze(-1), ref_e, torch.zeros_like(ref_e))
        assert rhat_method is not None  # no check: no extensions (the loop's range)
        iterations = iterations + need.to(iterations.dtype) * segment
        extensions = extensions + need.to(extensions.dtype)
        report = RhatReport(*(where(need.reshape((b,) + (1,) * (new.dim() - 1)), new, old)
                              for new, old in zip(rhat_report(ys, record_from, rhat_method, sensor.resolved), report)))

    x_new = history[0].permute(1, 2, 0, 3, 4).reshape(x_prev.shape)  # (B, C*S, K, D)
    exists_new = None if existence is None else history[2].permute(1, 2, 0, 3).reshape(b, n, k)
    log_w_new = torch.full((b, n), -math.log(n), device=x_prev.device, dtype=log_w.dtype)
    extras_new: dict | None = None
    reported: dict[str, Tensor] = {}
    if settings.pair_path is not None:  # the pair-path move on the new particles (module docstring)
        if existence is not None:
            raise ValueError("settings.pair_path needs a known number of targets (existence=None)")
        carried = (state.extras or {}).get(ESTIMATE)
        centre = weighted_mean(x_prev, log_w) if carried is None else carried.mean
        centre = motion.propagate(centre, torch.zeros(centre.shape[:-1] + (motion.noise_dim,), dtype=centre.dtype,
                                                      device=centre.device))
        source_new = history[5].permute(1, 2, 0, 3).reshape(b, n, k)
        x_new, window, reported = pair_path_update((state.extras or {}).get(PAIR_PATH), x_prev, centre, x_new,
                                                   source_new, z, motion=motion, sensor=sensor,
                                                   exclusion=settings.exclusion, settings=settings.pair_path,
                                                   generator=generator)
        extras_new = {PAIR_PATH: window}
    acceptance = accepted.mean(-1) / iterations
    dt = acceptance.dtype
    info = StepInfo.make(acceptance, acceptance=acceptance, extras={
        "rhat": report.max.to(dt), "rhat_slot": report.slot.to(dt), "rhat_dim": report.dim.to(dt),
        "extensions": extensions.to(dt)})
    if hmc is not None:  # refinements per run: (burn_in + segment) // every + extensions * (segment // every)
        count = (burn_in + segment) // every + extensions.to(dt) * (segment // every)
        info.extras["acceptance_hmc"] = refined.mean(-1) / count.clamp(min=1)
    info.extras.update({key: value.to(dt) for key, value in reported.items()})
    return ParticleState(x_new, log_w_new, exists_new, extras_new), info


def ipmcmc_program(dynamics: TargetDynamics, sensor: SensorModel, exclusion: Exclusion | None,
                   compile: Compile = None) -> Callable:
    """The IP-MCMC-PF's program: :func:`exchange_iteration` with the models and the exclusion
    term bound, ``program(chains, x_prev, exists_prev, z, noise)``, compiled with ``compile``
    (``compile_step=True``), else eager.
    """
    def iteration(*args: Any) -> tuple[ExchangeChains, Tensor, tuple[Tensor | None, Tensor] | None]:
        return exchange_iteration(*args, dynamics=dynamics, sensor=sensor, exclusion=exclusion)
    if compile is None:
        return iteration
    program = compile(iteration)
    if isinstance(program, Program):  # a move in its two C calls beats the compiled graph
        program.eager_when = one_call_serves
    return program


class IPMCMCFilter(Filter):
    """Interacting population-based MCMC-PF (paper 000 Alg. 1-2).

    Parameters
    ----------
    motion : MotionModel applied to every target slot.
    sensor : SensorModel (radar TBD, LinearGaussian, ...).
    num_particles : N; ``num_chains`` must divide it.
    settings : :class:`IPMCMCSettings`, optional; its fields (``num_chains``, ``burn_in``,
        ``rhat_threshold``, ``max_extensions``, ``rhat_method``, ``thinning``, ``hmc``,
        ``exclusion``, ``recapture``, ``existence_proposal``) are also keywords of the
        constructor, with the dataclass's defaults (``exclusion`` and ``recapture`` are on;
        ``None`` gives the paper's factorised target and exchange move).
    existence : BirthDeath, optional: births and deaths (module docstring); the estimate
        of a slot is then its mean given existence.
    compile_step : compile one exchange iteration with ``torch.compile(fullgraph=True)``
        (the first step pays the compile time).

    Notes
    -----
    ``StepInfo``: ``acceptance``; ``ess``, ``log_evidence`` NaN; extras ``"rhat"``,
    ``"rhat_slot"``, ``"rhat_dim"``, ``"extensions"`` (:func:`ipmcmc_step`).

    Example
    -------
    Two targets of the ground-radar scene, 4 chains of 10 samples per run:

    >>> import torch
    >>> import torchmcmcpf as tp
    >>> g = torch.Generator().manual_seed(0)
    >>> scene = tp.scenarios.ground_radar(num_targets=2, num_steps=3, batch_size=2, generator=g)
    >>> filt = tp.IPMCMCFilter(scene.motion, scene.sensor, 40, num_chains=4, burn_in=5)
    >>> result = filt(scene.measurements, init=scene.initial_particles(40, generator=g), generator=g)
    >>> sorted(result.info.extras)                    # each (T, B): the largest R-hat, per slot and dim
    ['extensions', 'rhat', 'rhat_dim', 'rhat_slot']
    >>> bool((result.info.extras["extensions"] <= filt.settings.max_extensions).all())   # longer while R-hat >= 1.1
    True
    """

    compile_seconds = 14.0  # benchmarks/bench_compile.py, 5-target ground radar, 2 CPU cores
    settings_class = IPMCMCSettings
    bind = staticmethod(bind_ipmcmc)
    bound_step = staticmethod(ipmcmc_bound_step)

    def __init__(self, *args: Any, **kwargs: Any) -> None:
        super().__init__(*args, **kwargs)
        # the pair-path window is carried only with settings.pair_path (filters/_carry.py, step 3)
        self.state_extras = (  # type: ignore[misc]  # per instance: a carry only some settings use
            frozenset({PAIR_PATH}) if self.settings.pair_path is not None else frozenset())

    def carry_sizes(self) -> dict[str, dict[str, Any]]:
        """The pair-path window's ``lag`` (with ``settings.pair_path``; :meth:`Filter.carry_sizes`)."""
        pair_path = self.settings.pair_path
        return {} if pair_path is None else {PAIR_PATH: {"lag": pair_path.lag}}
