"""MCMC moves of the sequential MCMC-based particle filter, batched over runs and chains.

Target
------
At time k the chains sample the joint posterior of the multitarget state and its ancestor
in the previous particle cloud (paper 001, "Target distribution"; paper 004 eq. 59-60):

    ``pi(x_k, a) ∝ p(z_k | x_k) w_{k-1}^a p(x_k | x_{k-1}^a)``,    ``a in {1..N}``,

whose ``x_k``-marginal is the approximate filtering density ``p(z_k | x_k) sum_a
w^a p(x_k | x_{k-1}^a)`` (paper 002 eq. 11; the weights ``w^a`` are ``1/N`` after an MCMC
step). A chain's state is :class:`ChainState`: the multitarget state ``x (B, C, K, D)``, its
ancestor ``x_prev = x_{k-1}^a (B, C, K, D)`` and the cached log-likelihood.

Moves (each leaves ``pi`` invariant)
------------------------------------
* ``joint``: draw ``a' ~ w`` and ``x' ~ p(. | x_{k-1}^{a'})`` for every target (paper 001
  q1; paper 004 Alg. 1 without its auxiliary part, eq. 61 with ``P_a = 0``). The proposal is
  the prior part of ``pi``, which cancels: ``alpha = p(z | x') / p(z | x)``.
* ``refine``: MH-within-Gibbs over the targets (paper 001 Alg. 1; paper 004 Alg. 2): for slot
  n, ``x'_n ~ p(. | x_{prev,n})`` given the chain's ancestor, other slots fixed; the transition
  cancels again and ``alpha = p(z | x_{-n}, x'_n) / p(z | x)``. The ancestor does not move, so
  ``refine`` alone is not irreducible: mix it with ``joint`` (paper 004 uses ``xi = 0.75``).
* ``random_walk``: ``x' = x + s * eps`` on the joint state (paper 002 eq. 13, ``S =
  diag(s^2)``), symmetric, so ``alpha`` is the ratio of ``p(z | x) sum_a w^a p(x | x^a)`` at
  ``x'`` and ``x`` (eq. 14), the mixture prior summed over all N previous particles by
  ``logsumexp``. The move acts on the ``x``-marginal; afterwards the ancestor is redrawn
  from its full conditional ``p(a | x) ∝ w^a p(x | x^a)`` (a Gibbs step on ``a``), which keeps
  the chain state a draw of ``pi`` so the move mixes freely with the two others.

Each move has a pure ``propose_*`` function returning the proposal and its log ratio
(everything of ``log alpha`` except the likelihood ratio: target prior times reverse over
forward proposal density) and a ``*_move`` function that proposes, scores and accepts. All
randomness comes in as pre-drawn noise (the ``*Noise.draw`` constructors take the explicit
generator, in eager code), so a whole MCMC iteration can run under ``torch.compile``.

Sensor hooks for the per-target refinement (declared on ``SensorModel``)
-----------------------------------------------------------------------
``refine`` recomputes only the likelihood terms that change where the sensor says how,
through two methods every :class:`~torchmcmcpf.models.base.SensorModel` has (found by
method, decided statically, so the choice traces under ``torch.compile``):

``log_likelihood_per_target(x, z) -> (B, *S, K)`` (``sensor.separable``)
    For sensors whose log-likelihood is a sum of per-target terms, term n depending on
    ``x[..., n, :]`` only (targets do not interact, e.g. ``LinearGaussian`` with known
    association); ``log_likelihood(x, z) == log_likelihood_per_target(x, z).sum(-1)``. The
    chains cache the K terms (``ChainState.log_lik_terms``) and one call scores the
    proposals of all K slots. The conditional of slot n then does not depend on the other
    slots, so the K single-target updates of a Gibbs sweep are independent and run at once
    (vectorised over K; given the same noise the result equals the sequential sweep's,
    which is tested). The default raises; ``separable`` is False.

``log_likelihood_delta(x, x_n, n, z, exists=None, exists_n=None) -> (B, *S)``
    For sensors whose targets interact (radar TBD, where the amplitudes of nearby targets
    add in a cell): ``log p(z | x with slot n set to x_n) - log p(z | x)`` with ``x (B, *S, K,
    D)`` the current states, ``x_n (B, *S, D)`` the proposed state of slot n and ``n`` a
    Python ``int`` or a ``(B, *S)`` tensor; with existence flags, ``exists (B, *S, K)`` and
    slot n's new flag ``exists_n (B, *S)``. A grid sensor evaluates only the cells near the
    old and the new position of slot n. The default evaluates ``log_likelihood`` twice;
    :meth:`~torchmcmcpf.models.base.SensorModel.log_likelihood_slot` uses an override as
    ``log_lik + delta`` and otherwise one full evaluation of the new state. The sweep is
    sequential over the K slots (:func:`refine_slot`): slot n sees the accepted updates of
    slots ``< n`` (a Python loop over K, the only loop over targets in this module, needed
    because each update's acceptance depends on the previous ones).

Existence: births and deaths (paper 001, "MCMC-based particle algorithm adapted")
---------------------------------------------------------------------------------
With a :class:`~torchmcmcpf.models.existence.BirthDeath` model ``existence`` the K slots
carry flags ``e (B, C, K)`` and the target is

    ``pi(x, e, a) ∝ p(z | x, e) w^a prod_n p(x_n, e_n | x^a_n, e^a_n)``

(paper 001, "Target distribution"; ``p(x_n, e_n | .)`` is :meth:`BirthDeath.log_prob`:
``p(e_n | e^a_n)`` of paper 004 eq. 25 times the motion density for a survivor, the birth
density ``p_0`` for a newborn, the point mass at ``x_death`` for an inactive slot). Both
moves propose slot n from ``q_n(x_n, e_n | x^a_n, e^a_n) = p(e_n | e^a_n) g(x_n)`` with
``g`` the motion density (survivor), the birth proposal ``q_0`` (newborn: ``p_0``, or
near the points of ``z``, :class:`~torchmcmcpf.models.existence.BirthDeath`) or the point
mass at ``x_death``, so that ``p(x_n, e_n | .) / q_n(x_n, e_n | .) = r_n`` with ``r_n =
p_0(x_n) / q_0(x_n)`` for a newborn slot and ``r_n = 1`` otherwise. Then:

* ``joint`` proposes ``(x', e', a')`` from ``q(x, e, a) = w^a prod_n q_n``, independent of
  the current state, and ``pi / q = p(z | x, e) prod_n r_n``, so

      ``log alpha = log p(z | x', e') - log p(z | x, e) + sum_n (log r'_n - log r_n)``;

* ``refine`` proposes slot n's ``(x'_n, e'_n) ~ q_n(. | x^a_n, e^a_n)`` (paper 001 Alg. 1,
  steps 2-9: ``e'_n ~ p(e_n | e^a_n)``, then the motion, a birth or ``x_death``) and the
  conditional target of slot n is ``p(z | x, e) p(x_n, e_n | x^a_n, e^a_n)``, so

      ``log alpha_n = log p(z | x', e') - log p(z | x, e) + log r'_n - log r_n``.

With births from the prior ``r_n = 1`` and both ratios are likelihood ratios. Chains cache
``log r_n`` per slot (``ChainState.log_birth``); the birth candidates and the existence
uniforms are pre-drawn noise (:class:`BirthNoise`) like everything else. The likelihood is
``sensor.log_likelihood(x, z, exists)``; the sweep is sequential, through the same declared
hook with the flags (``log_likelihood_slot(..., exists=, exists_n=)``). ``random_walk`` is not defined on the
discrete flags and is refused with existence.
"""

from __future__ import annotations

from collections.abc import Callable

import torch

from .._native.select import where
from ..models.base import MotionModel, SensorModel
from ..models.existence import TargetDynamics
from ..models.multitarget import Exclusion, exclusion_change, exclusion_on, log_exclusion
from ..resampling import gather_particles
from ..runtime import take_along
from ..typing import Measurement, Tensor
from .chains import ChainState, JointNoise, PreviousCloud, RefineNoise, draw_ancestors, evaluate_cached
from .mh import mh_accept, mh_select

__all__ = ["MOVES", "init_chains", "propose_joint", "joint_move", "refine_move", "refine_slot"]

#: Names of the primitive moves (joint draw and refinement here, the random walk in :mod:`.random_walk`).
MOVES = ("joint", "refine", "random_walk")


# -- joint draw ------------------------------------------------------------------------------
def propose_joint(cloud: PreviousCloud, noise: JointNoise, *, motion: MotionModel
                  ) -> tuple[Tensor, Tensor, Tensor]:
    """Joint draw (paper 001 q1; paper 004 Alg. 1 steps 1 and 4): an ancestor ``a' ~ w``
    per chain, then every target moved by the transition.

    Parameters
    ----------
    cloud : the previous particles ``(B, N, K, D)``.
    noise : :class:`JointNoise` for ``(B, C)`` chains.
    motion : MotionModel.

    Returns
    -------
    x : (B, C, K, D) proposed states ``x' ~ p(. | x_{k-1}^{a'})``.
    x_prev : (B, C, K, D) their ancestors ``x_{k-1}^{a'}``.
    log_ratio : (B, C) zeros: ``q(x', a') = w^{a'} p(x' | x^{a'})`` equals the prior part of
        ``pi``, so prior and proposal cancel (paper 004 eq. 60 with ``P_a = 0``).
    """
    x_prev = gather_particles(cloud.x, draw_ancestors(cloud, noise.u_ancestor))
    x = motion.propagate(x_prev, noise.eps)
    return x, x_prev, torch.zeros_like(noise.u)


def _carries_ratio(dynamics: TargetDynamics) -> bool:
    """Whether the chains carry ``log r_n`` per slot (births and deaths or re-capture)."""
    return dynamics.existence is not None or dynamics.recapture is not None


def _joint_candidate(cloud: PreviousCloud, noise: JointNoise, z: Measurement, dynamics: TargetDynamics,
                     sensor: SensorModel, start: bool = False) -> ChainState:
    """The joint-draw proposal as a scored :class:`ChainState`: an ancestor by weight, then
    ``(x, exists)`` propagated by ``dynamics`` (one path with or without births and
    re-capture).
    """
    a = draw_ancestors(cloud, noise.u_ancestor) if noise.ancestor is None else noise.ancestor
    x_prev = gather_particles(cloud.x, a)
    exists_prev = None if cloud.exists is None else gather_particles(cloud.exists, a)
    x, exists, log_ratio, _ = dynamics.propagate_labelled(x_prev, exists_prev, noise.eps, noise.birth,
                                                          noise.relocation, start=start)
    log_lik, terms, cache = evaluate_cached(x, z, sensor, exists)
    return ChainState(x, x_prev, log_lik, terms, exists, exists_prev, log_ratio if _carries_ratio(dynamics) else None,
                      cache=cache)


def init_chains(cloud: PreviousCloud, noise: JointNoise, z: Measurement, *, dynamics: TargetDynamics,
                sensor: SensorModel) -> ChainState:
    """Start each chain from a previous particle drawn by weight and moved by the prior
    (paper 002, "MCMC-based PF-TBD steps" 1): one joint-draw proposal, always kept.

    Parameters
    ----------
    cloud : previous particles ``(B, N, K, D)``; noise : :class:`JointNoise` for ``(B, C)``
    chains (its ``u`` is unused); z : frame ``(B, *G)``.
    dynamics : :class:`~torchmcmcpf.models.existence.TargetDynamics`, the motion with, optionally,
    births and deaths (``cloud.exists`` and ``noise.birth`` needed; module docstring) and
    re-capture (``noise.relocation`` needed). sensor : the SensorModel.

    The existence flags come from the chain itself (not the existence model's proposal), so
    the chains start where births are as rare as the model says; their ratios are still taken
    against the proposal the moves use.

    Returns
    -------
    ChainState with ``x (B, C, K, D)`` (and, with existence, ``exists (B, C, K)``).
    """
    return _joint_candidate(cloud, noise, z, dynamics, sensor, start=True)


def _log_ratio_sum(chain: ChainState) -> Tensor:
    """``sum_n log r_n`` of a chain ``(B, C)`` (0 without births and re-capture)."""
    if chain.log_ratio is None:
        return torch.zeros_like(chain.log_lik)
    return chain.log_ratio.sum(-1)


def joint_move(chain: ChainState, noise: JointNoise, *, cloud: PreviousCloud, z: Measurement,
               dynamics: TargetDynamics, sensor: SensorModel, exclusion: Exclusion | None = None
               ) -> tuple[ChainState, Tensor]:
    """One joint-draw Metropolis-Hastings step (paper 004 Alg. 1, eq. 60; with existence
    paper 001 step (a), ``log alpha`` of the module docstring).

    Parameters
    ----------
    chain : ChainState ``(B, C, K, D)``.
    noise : :class:`JointNoise`.
    cloud : the previous particles; z : frame ``(B, *G)``.
    dynamics : the slots' joint model (motion, optionally births and deaths and re-capture).
    sensor : the SensorModel.
    exclusion : the exclusion term (:mod:`torchmcmcpf.models.multitarget`), optional.

    Returns
    -------
    chain : the new ChainState.
    accepted : (B, C) bool.
    """
    cand = _joint_candidate(cloud, noise, z, dynamics, sensor)
    if _carries_ratio(dynamics) and chain.log_ratio is None:
        raise ValueError("chain.log_ratio is None but the dynamics have births or re-capture: start the chains "
                         "with init_chains(..., dynamics=dynamics)")
    log_alpha = cand.log_lik - chain.log_lik  # the prior parts cancel (eq. 60, P_a = 0)
    log_alpha = log_alpha + _log_ratio_sum(cand) - _log_ratio_sum(chain)
    phi_cand = log_exclusion(exclusion, sensor, cand.x, cand.exists)
    phi = _log_phi(chain, exclusion, sensor)
    accepted = mh_accept(log_alpha + phi_cand - phi, noise.u)
    new = mh_select(accepted, cand, chain._replace(log_phi=None))  # the cache: a chain without one keeps none
    if exclusion_on(exclusion, sensor) and not torch.compiler.is_compiling():  # eager: keep log Phi of the new state
        new = new._replace(log_phi=(new.x, new.exists, where(accepted, phi_cand, phi)))
    return new, accepted


def _log_phi(chain: ChainState, exclusion: Exclusion | None, sensor: SensorModel) -> Tensor:
    """``log Phi`` of the chains' states ``(B, C)``: the joint draw's cached value while the
    chain holds the tensors it was taken for (the same function of the same values: the same
    bits), else computed.
    """
    cached = chain.log_phi
    if cached is not None and cached[0] is chain.x and cached[1] is chain.exists:
        return cached[2]
    return log_exclusion(exclusion, sensor, chain.x, chain.exists)


# -- per-target refinement -------------------------------------------------------------------
def refine_move(chain: ChainState, noise: RefineNoise, *, z: Measurement, dynamics: TargetDynamics,
                sensor: SensorModel, exclusion: Exclusion | None = None, slot_program: Callable | None = None
                ) -> tuple[ChainState, Tensor]:
    """One MH-within-Gibbs sweep over the K targets (paper 004 Alg. 2; paper 001 Alg. 1).

    Every slot proposes ``(x'_n, e'_n)`` from its ancestor by ``dynamics`` (the motion alone
    without births and re-capture). Vectorised over K for a separable sensor without flags
    and without exclusion; otherwise sequential over K through the declared hook
    ``log_likelihood_slot`` (module docstring).

    Parameters
    ----------
    chain : ChainState ``(B, C, K, D)``.
    noise : :class:`RefineNoise`; z : frame ``(B, *G)``.
    dynamics : the slots' joint model; sensor : the SensorModel.
    exclusion : the exclusion term, optional.
    slot_program : :func:`refine_slot` compiled (:func:`~torchmcmcpf.runtime.compile_program`,
        called with a tensor slot), optional.

    Returns
    -------
    chain : the new ChainState (ancestor unchanged).
    accepted : (B, C, K) bool, one flag per target update.
    """
    # every slot's proposal (x'_n, e'_n) from its ancestor, by TargetDynamics; log_ratio is
    # slot n's log r'_n - log r_n (zeros without births and re-capture: the transition cancels, eq. 66)
    x_prop, e_prop, ratio_prop = dynamics.propagate(chain.x_prev, chain.exists_prev, noise.eps, noise.birth,
                                                    noise.relocation)
    log_ratio = ratio_prop if chain.log_ratio is None else ratio_prop - chain.log_ratio
    coupled = exclusion_on(exclusion, sensor)
    if chain.log_lik_terms is not None and not coupled:  # separable sensor, no flags: all K slots at once
        terms_prop = sensor.log_likelihood_per_target(x_prop, z)
        accepted = mh_accept(terms_prop - chain.log_lik_terms + log_ratio, noise.u)
        x = mh_select(accepted, x_prop, chain.x)
        terms = where(accepted, terms_prop, chain.log_lik_terms)
        new_ratio = None if chain.log_ratio is None else where(accepted, ratio_prop, chain.log_ratio)
        return ChainState(x, chain.x_prev, terms.sum(-1), terms, log_ratio=new_ratio), accepted
    return _sequential_sweep(chain, x_prop, log_ratio, noise.u, z, sensor, e_prop, ratio_prop, exclusion,
                             slot_program)


def refine_slot(x: Tensor, log_lik: Tensor, e: Tensor | None, log_r: Tensor | None, x_prop: Tensor,
                e_prop: Tensor | None, r_prop: Tensor | None, log_ratio: Tensor, u: Tensor,
                n: int | Tensor, z: Measurement, cache: Tensor | None = None, *, sensor: SensorModel,
                exclusion: Exclusion | None = None
                ) -> tuple[Tensor, Tensor, Tensor | None, Tensor | None, Tensor, tuple[Tensor | None, Tensor] | None]:
    """The MH update of one slot ``n`` of the sequential sweep (pure; the program the
    ``compile_step`` of the MCMC filter compiles, once for every slot).

    Parameters
    ----------
    x, log_lik, e, log_r : the chains, ``(B, C, K, D)``, ``(B, C)``, ``(B, C, K)`` or None
        (``log_r`` the cached ``log r_n``, :attr:`ChainState.log_ratio`).
    x_prop, e_prop, r_prop, log_ratio, u : the proposals of every slot, ``(B, C, K, D)``,
        then ``(B, C, K)`` (``e_prop``, ``r_prop`` or None; ``r_prop`` their ``log r'_n``,
        ``log_ratio`` the difference ``log r'_n - log r_n`` taken against the sweep's start).
    n : Python int (eager: slot n's entries read as views and only they rewritten), or (B, C)
        int64 (the same slot everywhere, as a tensor so that one compiled graph serves every
        slot); the same values either way.
    z : the frame; cache : the chains' amplitude cache
        (:meth:`~torchmcmcpf.models.base.SensorModel.amplitude_cache`), optional: the
        proposal's ratio is then read from it (the moved slot's terms only).
    sensor : the SensorModel.
    exclusion : the exclusion term, optional (its ``K - 1`` factors of slot ``n``).

    Returns
    -------
    x, log_lik, e, log_r : the chains after the update; accepted : (B, C) bool; update : the
    cache's ``(cells, change)`` for the accepted moves
    (:meth:`~torchmcmcpf.models.base.SensorModel.update_amplitude_cache`, applied by the
    caller), ``None`` without a cache.
    """
    if e is not None and (e_prop is None or r_prop is None or log_r is None):
        raise ValueError("with existence flags e, e_prop, r_prop and log_r must be given too")
    n_t = n if isinstance(n, torch.Tensor) else torch.full(log_lik.shape, n, dtype=torch.int64, device=x.device)
    if isinstance(n, int):  # the eager sweep: slot n's entries are views, and only they are rewritten
        x_n, u_n, ratio_n = x_prop[..., n, :], u[..., n], log_ratio[..., n]
        e_n = None if e is None or e_prop is None else e_prop[..., n]
    else:  # one compiled graph for every slot: n a tensor
        here = torch.arange(x.shape[-2], device=x.device) == n_t.unsqueeze(-1)  # (B, C, K)

        def pick(t: Tensor) -> Tensor:
            idx = n_t.reshape(n_t.shape + (1,) * (t.dim() - n_t.dim()))
            return take_along(t, idx, dim=n_t.dim()).squeeze(n_t.dim())

        x_n, u_n, ratio_n = pick(x_prop), pick(u), pick(log_ratio)
        e_n = None if e is None or e_prop is None else pick(e_prop)
    update = None
    if cache is not None:  # the moved slot's terms read against the chains' cache
        delta, cells, change = sensor.log_likelihood_delta_cached(cache, x, x_n, n_t, z, exists=e, exists_n=e_n)
        log_lik_cand, update = log_lik + delta, (cells, change)
    else:  # the declared hook: the cells near slot n only for grid sensors, else a full evaluation
        log_lik_cand = sensor.log_likelihood_slot(x, x_n, n, z, log_lik, exists=e, exists_n=e_n)
    log_alpha = log_lik_cand - log_lik + ratio_n + exclusion_change(exclusion, sensor, x, x_n, n_t, e, e_n)
    acc = mh_accept(log_alpha, u_n)
    log_lik = where(acc, log_lik_cand, log_lik)
    if isinstance(n, int):  # slot n set to the accepted value, the other slots' entries copied
        x = _with_slot(x, acc.dim(), n, where(acc.unsqueeze(-1), x_n, x[..., n, :]))
        if e is not None and e_n is not None:
            e = _with_slot(e, acc.dim(), n, where(acc, e_n, e[..., n]))
        if log_r is not None and r_prop is not None:
            log_r = _with_slot(log_r, acc.dim(), n, where(acc, r_prop[..., n], log_r[..., n]))
        return x, log_lik, e, log_r, acc, update
    x = mh_select(acc, where(here.unsqueeze(-1), x_prop, x), x)
    if e is not None and e_prop is not None:
        e = mh_select(acc, where(here, e_prop, e), e)
    if log_r is not None and r_prop is not None:
        log_r = where(acc.unsqueeze(-1) & here, r_prop, log_r)
    return x, log_lik, e, log_r, acc, update


def _with_slot(t: Tensor, axis: int, n: int, value: Tensor) -> Tensor:
    """A copy of ``t`` with entry ``n`` of its slot axis ``axis`` set to ``value`` (``t``'s
    shape without that axis): the values of ``where(slot == n, value, t)``, one copy and
    one slot's write instead of a select over every slot with a broadcast condition, which
    ATen's CPU loop does not vectorise (0.39 against 0.06 ms for ``(10, 1000, 5, 4)``).
    """
    out = t.clone()
    out.select(axis, n).copy_(value)
    return out


def _sequential_sweep(chain: ChainState, x_prop: Tensor, log_ratio: Tensor, u: Tensor, z: Measurement,
                      sensor: SensorModel, e_prop: Tensor | None = None, r_prop: Tensor | None = None,
                      exclusion: Exclusion | None = None, slot_program: Callable | None = None
                      ) -> tuple[ChainState, Tensor]:
    """Sequential Gibbs sweep over the K slots with proposals ``x_prop (B, C, K, D)`` (and
    ``e_prop``, ``r_prop (B, C, K)`` with existence or re-capture), ``log_ratio (B, C, K)`` and
    uniforms ``u (B, C, K)``: slot n sees the accepted updates of slots ``< n``
    (:func:`refine_slot`; ``slot_program`` a compiled one, called with a tensor slot).
    """
    x, log_lik, e, log_r = chain.x, chain.log_lik, chain.exists, chain.log_ratio
    if log_r is None:
        r_prop = None
    # the chains' cache of their point intensities (a sensor whose cache pays for a sweep,
    # SensorModel.sweep_cache): kept from the joint draw that made the state (ChainState.cache)
    # or made here; each slot's update then pays for that slot's terms only, and the accepted
    # changes are added to it in place (as the IP-MCMC-PF's moves do; a copy of the kept one:
    # the caller's chain stays as it was)
    cache = chain.cache.clone() if chain.cache is not None else \
        sensor.amplitude_cache(x, e, z) if sensor.sweep_cache else None
    flags = []
    for n in range(x.shape[-2]):  # sequential Gibbs sweep: slot n sees slots < n (coupled likelihood)
        args = (x, log_lik, e, log_r, x_prop, e_prop, r_prop, log_ratio, u)
        if slot_program is None:
            x, log_lik, e, log_r, acc, update = refine_slot(*args, n, z, cache, sensor=sensor, exclusion=exclusion)
        else:
            x, log_lik, e, log_r, acc, update = slot_program(*args, torch.full(log_lik.shape, n, device=x.device), z,
                                                             cache)
        if cache is not None and update is not None:
            cache = sensor.update_amplitude_cache(cache, *update, acc)
        flags.append(acc)
    return chain._replace(x=x, log_lik=log_lik, log_lik_terms=None, exists=e, log_ratio=log_r, cache=cache), \
        torch.stack(flags, dim=-1)
