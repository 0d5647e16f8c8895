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

Sensor hooks for the per-target refinement (optional, duck-typed)
-----------------------------------------------------------------
``refine`` recomputes only the likelihood terms that change where the sensor says how. A
sensor may define one of:

``log_likelihood_per_target(x, z) -> (B, *S, K)``
    For sensors whose log-likelihood is a sum of per-target terms, term n depending on
    ``x[..., n, :]`` only (targets do not interact, e.g. ``LinearGaussian`` with known
    association); ``log_likelihood(x, z) == log_likelihood_per_target(x, z).sum(-1)``. The
    chains cache the K terms (``ChainState.log_lik_terms``) and one call scores the
    proposals of all K slots. The conditional of slot n then does not depend on the other
    slots, so the K single-target updates of a Gibbs sweep are independent and run at once
    (vectorised over K; given the same noise the result equals the sequential sweep's,
    which is tested).

``log_likelihood_delta(x, x_n, n, z) -> (B, *S)``
    For sensors whose targets interact (radar TBD, where the amplitudes of nearby targets
    add in a cell): ``log p(z | x with slot n set to x_n) - log p(z | x)`` with ``x (B, *S, K,
    D)`` the current states, ``x_n (B, *S, D)`` the proposed state of slot n and ``n`` a
    Python ``int`` (static under ``torch.compile``). It should evaluate only the cells near
    the old and the new position of slot n (with the other slots' contributions in those
    cells), equal the difference of two ``log_likelihood`` calls to within round-off
    (ideally within the same stated tolerance as the sensor's windowed path), be finite
    wherever both are, and be pure (no ``.item()``, no data-dependent Python branching).
    The sweep is then sequential over the K slots: slot n sees the accepted updates of
    slots ``< n`` (a Python loop over K, the only loop over targets in this module, needed
    because each update's acceptance depends on the previous ones).

Without either, the sweep is sequential and scores each slot's proposal by a full
``log_likelihood`` call (exact; K full evaluations per sweep).

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
``sensor.log_likelihood(x, z, exists)``; the sweep is sequential, and uses the delta hook
when it also takes the keywords ``exists`` (current flags ``(B, *S, K)``) and ``exists_n``
(slot n's new flag ``(B, *S)``), as
:meth:`~torchmcmcpf.models.sensors.grid.SeparableGridSensor.log_likelihood_delta` does
(:func:`existence_delta`), otherwise full evaluations. ``random_walk`` is not defined on the
discrete flags and is refused with existence.
"""

from __future__ import annotations

import math
from typing import NamedTuple, Optional

import torch

from ..models.base import MotionModel, SensorModel
from ..models.existence import BirthDeath, BirthNoise
from ..models.motion import LinearGaussianMotion
from ..resampling import cdf, gather_particles, inverse_cdf
from ..typing import Measurement, Tensor
from .mh import mh_accept, mh_select

__all__ = [
    "MOVES",
    "ChainState",
    "PreviousCloud",
    "JointNoise",
    "RefineNoise",
    "RandomWalkNoise",
    "BirthNoise",
    "previous_cloud",
    "evaluate",
    "init_chains",
    "propose_joint",
    "propose_existence",
    "joint_move",
    "propose_refine",
    "refine_move",
    "log_transition",
    "propose_random_walk",
    "random_walk_move",
]

#: Names of the primitive moves.
MOVES = ("joint", "refine", "random_walk")

#: Elements of one ``(B, C, n, K, D)`` chunk in :func:`log_transition` (bounds its memory).
_CHUNK_ELEMENTS = 1 << 22


class ChainState(NamedTuple):
    """The state of C chains in each of B runs.

    Attributes
    ----------
    x : (B, C, K, D)
        Multitarget state at time k.
    x_prev : (B, C, K, D)
        Its ancestor ``x_{k-1}^a`` in the previous particle cloud.
    log_lik : (B, C)
        ``sensor.log_likelihood(x, z)``.
    log_lik_terms : (B, C, K), optional
        Per-target terms of ``log_lik`` for sensors with ``log_likelihood_per_target``;
        ``None`` otherwise.
    exists, exists_prev : (B, C, K) bool, optional
        With existence: the flags of ``x`` and of its ancestor (``None`` for a known number
        of targets; ``log_lik`` is then ``sensor.log_likelihood(x, z, exists)``).
    log_birth : (B, C, K), optional
        With existence: ``log r_n = log p_0(x_n) - log q_0(x_n)`` for a slot born between
        the ancestor and ``x``, 0 for the others (module docstring).
    """

    x: Tensor
    x_prev: Tensor
    log_lik: Tensor
    log_lik_terms: Optional[Tensor] = None
    exists: Optional[Tensor] = None
    exists_prev: Optional[Tensor] = None
    log_birth: Optional[Tensor] = None


class PreviousCloud(NamedTuple):
    """The particle approximation of ``p(x_{k-1} | z_{1:k-1})`` that the target mixes over.

    Attributes
    ----------
    x : (B, N, K, D) particles.
    log_w : (B, N) normalised log-weights (``-log N`` after an MCMC step).
    cdf : (B, N) float64 cumulative weights, last entry exactly 1 (ancestor draws by
        inversion, ``searchsorted``).
    exists : (B, N, K) bool, optional: the particles' existence flags.
    white_mean : (B, N, K * D), optional: the whitened predicted means ``L^-1 F x^i`` of a
        linear-Gaussian motion, computed once per frame for :func:`log_transition`.
    """

    x: Tensor
    log_w: Tensor
    cdf: Tensor
    exists: Optional[Tensor] = None
    white_mean: Optional[Tensor] = None


def previous_cloud(x: Tensor, log_w: Tensor, exists: Optional[Tensor] = None, *,
                   motion: Optional[MotionModel] = None) -> PreviousCloud:
    """Build a :class:`PreviousCloud` from particles ``x (B, N, K, D)``, ``log_w (B, N)`` and
    optionally their existence flags ``exists (B, N, K)``. With a linear-Gaussian ``motion``
    the whitened predicted means are cached, so the random walk does not recompute them at
    every iteration of the frame."""
    white = _whiten(motion.mean(x), motion) if isinstance(motion, LinearGaussianMotion) else None
    return PreviousCloud(x, log_w, cdf(log_w), exists, white)


def _draw_ancestors(cloud: PreviousCloud, u: Tensor) -> Tensor:
    """Ancestor indices ``(B, C)`` with ``P(a) = w^a``, by inversion of uniforms ``u (B, C)``."""
    return inverse_cdf(cloud.cdf, u)


def _uniform(shape, x: Tensor, generator: torch.Generator) -> Tensor:
    return torch.rand(shape, generator=generator, device=x.device, dtype=x.dtype)


def _normal(shape, x: Tensor, generator: torch.Generator) -> Tensor:
    return torch.randn(shape, generator=generator, device=x.device, dtype=x.dtype)


def _births(x: Tensor, existence: Optional[BirthDeath], z: Measurement, generator: torch.Generator
            ) -> Optional[BirthNoise]:
    return None if existence is None else BirthNoise.draw(x, existence, z, generator=generator)


class JointNoise(NamedTuple):
    """Noise of one joint draw: ``u_ancestor (B, C)`` and ``u (B, C)`` uniforms, ``eps (B, C,
    K, noise_dim)`` standard normals (the transition noise of every target) and, with
    existence, ``birth`` (:class:`BirthNoise`)."""

    u_ancestor: Tensor
    eps: Tensor
    u: Tensor
    birth: Optional[BirthNoise] = None

    @classmethod
    def draw(cls, x: Tensor, motion: MotionModel, *, generator: torch.Generator,
             existence: Optional[BirthDeath] = None, z: Optional[Measurement] = None) -> "JointNoise":
        """Draw for chains shaped like ``x (B, C, K, D)`` (dtype and device of ``x``); the
        birth noise only with ``existence`` (which needs the frame ``z``)."""
        b, c, k, _ = x.shape
        return cls(_uniform((b, c), x, generator), _normal((b, c, k, motion.noise_dim), x, generator),
                   _uniform((b, c), x, generator), _births(x, existence, z, generator))


class RefineNoise(NamedTuple):
    """Noise of one refinement sweep: ``eps (B, C, K, noise_dim)`` normals (one proposal per
    slot), ``u (B, C, K)`` uniforms (one accept/reject per slot) and, with existence,
    ``birth`` (:class:`BirthNoise`)."""

    eps: Tensor
    u: Tensor
    birth: Optional[BirthNoise] = None

    @classmethod
    def draw(cls, x: Tensor, motion: MotionModel, *, generator: torch.Generator,
             existence: Optional[BirthDeath] = None, z: Optional[Measurement] = None) -> "RefineNoise":
        """Draw for chains shaped like ``x (B, C, K, D)`` (``existence``, ``z``: as
        :meth:`JointNoise.draw`)."""
        b, c, k, _ = x.shape
        return cls(_normal((b, c, k, motion.noise_dim), x, generator), _uniform((b, c, k), x, generator),
                   _births(x, existence, z, generator))


class RandomWalkNoise(NamedTuple):
    """Noise of one random-walk move: ``eps (B, C, K, D)`` normals, ``u (B, C)`` uniforms for
    the accept/reject and ``u_ancestor (B, C)`` for the Gibbs redraw of the ancestor."""

    eps: Tensor
    u: Tensor
    u_ancestor: Tensor

    @classmethod
    def draw(cls, x: Tensor, motion: MotionModel, *, generator: torch.Generator) -> "RandomWalkNoise":
        """Draw for chains shaped like ``x (B, C, K, D)``."""
        b, c = x.shape[:2]
        return cls(_normal(x.shape, x, generator), _uniform((b, c), x, generator), _uniform((b, c), x, generator))

    # no existence variant: ``random_walk`` is refused with existence (module docstring)


# -- likelihood ------------------------------------------------------------------------------
def evaluate(x: Tensor, z: Measurement, sensor: SensorModel, exists: Optional[Tensor] = None
             ) -> tuple[Tensor, Optional[Tensor]]:
    """Log-likelihood of chain states, with per-target terms when the sensor has them.

    Parameters
    ----------
    x : (B, C, K, D); z : one frame per run (B, *G); sensor : the SensorModel.
    exists : (B, C, K) bool, optional: existence flags (then no per-target terms).

    Returns
    -------
    log_lik : (B, C).
    log_lik_terms : (B, C, K), or ``None`` for a sensor without ``log_likelihood_per_target``
        or with ``exists``.
    """
    if exists is not None:
        return sensor.log_likelihood(x, z, exists), None
    if sensor.separable:
        terms = sensor.log_likelihood_per_target(x, z)
        return terms.sum(-1), terms
    return sensor.log_likelihood(x, z), None


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
    x_prev = gather_particles(cloud.x, _draw_ancestors(cloud, noise.u_ancestor))
    x = motion.propagate(x_prev, noise.eps)
    return x, x_prev, torch.zeros_like(noise.u)


def propose_existence(x_prev: Tensor, exists_prev: Tensor, eps: Tensor, birth: BirthNoise, *,
                      motion: MotionModel, existence: BirthDeath) -> tuple[Tensor, Tensor, Tensor]:
    """Per-slot proposal ``q_n`` of the existence moves (module docstring; paper 001 Alg. 1
    steps 2-9): the birth/death law :meth:`BirthDeath.propagate` from pre-drawn noise.

    Parameters
    ----------
    x_prev : (B, C, K, D) ancestors; exists_prev : (B, C, K) bool their flags.
    eps : (B, C, K, noise_dim) motion noise; birth : :class:`BirthNoise`.

    Returns
    -------
    x : (B, C, K, D); exists : (B, C, K) bool;
    log_birth : (B, C, K) ``log r_n = log p_0(x_n) - log q_0(x_n)`` of newborn slots, else 0.
    """
    return existence.propagate(x_prev, exists_prev, eps, birth, motion=motion)


def _joint_candidate(cloud: PreviousCloud, noise: JointNoise, z: Measurement, motion: MotionModel,
                     sensor: SensorModel, existence: Optional[BirthDeath]) -> ChainState:
    """The joint-draw proposal as a scored :class:`ChainState`."""
    if existence is None:
        x, x_prev, _ = propose_joint(cloud, noise, motion=motion)
        return ChainState(x, x_prev, *evaluate(x, z, sensor))
    a = _draw_ancestors(cloud, noise.u_ancestor)
    x_prev, exists_prev = gather_particles(cloud.x, a), gather_particles(cloud.exists, a)
    x, exists, log_birth = propose_existence(x_prev, exists_prev, noise.eps, noise.birth, motion=motion,
                                             existence=existence)
    return ChainState(x, x_prev, *evaluate(x, z, sensor, exists), exists, exists_prev, log_birth)


def init_chains(cloud: PreviousCloud, noise: JointNoise, z: Measurement, *, motion: MotionModel,
                sensor: SensorModel, existence: Optional[BirthDeath] = None) -> ChainState:
    """Start each chain from a previous particle drawn by weight and moved by the prior
    (paper 002, "MCMC-based PF-TBD steps" 1): one joint-draw proposal, always kept.

    Parameters
    ----------
    cloud : previous particles ``(B, N, K, D)``; noise : :class:`JointNoise` for ``(B, C)``
    chains (its ``u`` is unused); z : frame ``(B, *G)``; motion, sensor : the models.
    existence : BirthDeath, optional: births and deaths (``cloud.exists`` and
    ``noise.birth`` needed; module docstring).

    Returns
    -------
    ChainState with ``x (B, C, K, D)`` (and, with existence, ``exists (B, C, K)``).
    """
    return _joint_candidate(cloud, noise, z, motion, sensor, existence)


def joint_move(chain: ChainState, noise: JointNoise, *, cloud: PreviousCloud, z: Measurement,
               motion: MotionModel, sensor: SensorModel, existence: Optional[BirthDeath] = None
               ) -> tuple[ChainState, Tensor]:
    """One joint-draw Metropolis-Hastings step (paper 004 Alg. 1, eq. 60; with existence
    paper 001 step (a), ``log alpha`` of the module docstring).

    Parameters
    ----------
    chain : ChainState ``(B, C, K, D)``; noise : :class:`JointNoise`; cloud : previous
    particles; z : frame ``(B, *G)``; motion, sensor : the models; existence : BirthDeath,
    optional.

    Returns
    -------
    chain : the new ChainState.
    accepted : (B, C) bool.
    """
    cand = _joint_candidate(cloud, noise, z, motion, sensor, existence)
    log_alpha = cand.log_lik - chain.log_lik  # the prior parts cancel (eq. 60, P_a = 0)
    if existence is not None:
        log_alpha = log_alpha + cand.log_birth.sum(-1) - chain.log_birth.sum(-1)
    accepted = mh_accept(log_alpha, noise.u)
    return mh_select(accepted, cand, chain), accepted


# -- per-target refinement -------------------------------------------------------------------
def propose_refine(x_prev: Tensor, eps: Tensor, *, motion: MotionModel) -> tuple[Tensor, Tensor]:
    """Per-target proposals from the transition given the chain's ancestor (paper 001 Alg. 1
    step 6; paper 004 Alg. 2 step 7): ``x'_n ~ p(. | x_{prev,n})`` for every slot n at once.

    The proposal of slot n depends on ``x_prev`` only, which the sweep does not change, so
    all K proposals can be drawn before the sweep.

    Parameters
    ----------
    x_prev : (B, C, K, D) the chains' ancestors; eps : (B, C, K, noise_dim) normals.

    Returns
    -------
    x : (B, C, K, D), slot n holding the proposal for target n.
    log_ratio : (B, C, K) zeros: the proposal is the transition factor of ``pi``'s conditional
        for slot n, which cancels (paper 004 eq. 66).
    """
    x = motion.propagate(x_prev, eps)
    return x, torch.zeros_like(x[..., 0])


def refine_move(chain: ChainState, noise: RefineNoise, *, z: Measurement, motion: MotionModel,
                sensor: SensorModel, existence: Optional[BirthDeath] = None) -> tuple[ChainState, Tensor]:
    """One MH-within-Gibbs sweep over the K targets (paper 004 Alg. 2; paper 001 Alg. 1).

    Vectorised over K for sensors with ``log_likelihood_per_target``; sequential over K
    (``log_likelihood_delta`` or full re-evaluation) otherwise: see the module docstring.
    With ``existence`` each slot proposes ``(x'_n, e'_n)`` (:func:`propose_existence`) and the
    sweep is sequential with full evaluations of ``log p(z | x, e)``.

    Parameters
    ----------
    chain : ChainState ``(B, C, K, D)``; noise : :class:`RefineNoise`; z : frame ``(B, *G)``;
    motion, sensor : the models; existence : BirthDeath, optional.

    Returns
    -------
    chain : the new ChainState (ancestor unchanged).
    accepted : (B, C, K) bool, one flag per target update.
    """
    if existence is not None:
        x_prop, e_prop, birth_prop = propose_existence(chain.x_prev, chain.exists_prev, noise.eps, noise.birth,
                                                       motion=motion, existence=existence)
        log_ratio = birth_prop - chain.log_birth  # slot n's log r'_n - log r_n
        return _sequential_sweep(chain, x_prop, log_ratio, noise.u, z, sensor, e_prop, birth_prop)
    x_prop, log_ratio = propose_refine(chain.x_prev, noise.eps, motion=motion)
    if chain.log_lik_terms is not None:
        terms_prop = sensor.log_likelihood_per_target(x_prop, z)
        accepted = mh_accept(terms_prop - chain.log_lik_terms + log_ratio, noise.u)
        x = mh_select(accepted, x_prop, chain.x)
        terms = torch.where(accepted, terms_prop, chain.log_lik_terms)
        return ChainState(x, chain.x_prev, terms.sum(-1), terms), accepted
    return _sequential_sweep(chain, x_prop, log_ratio, noise.u, z, sensor)


def _sequential_sweep(chain: ChainState, x_prop: Tensor, log_ratio: Tensor, u: Tensor, z: Measurement,
                      sensor: SensorModel, e_prop: Optional[Tensor] = None, birth_prop: Optional[Tensor] = None
                      ) -> tuple[ChainState, Tensor]:
    """Sequential Gibbs sweep over the K slots with proposals ``x_prop (B, C, K, D)`` (and
    ``e_prop``, ``birth_prop (B, C, K)`` with existence), ``log_ratio (B, C, K)`` and
    uniforms ``u (B, C, K)``: slot n sees the accepted updates of slots ``< n``."""
    existence = e_prop is not None
    x, log_lik, e, log_birth = chain.x, chain.log_lik, chain.exists, chain.log_birth
    slots = torch.arange(x.shape[-2], device=x.device)
    flags = []
    for n in range(x.shape[-2]):  # sequential Gibbs sweep: slot n sees slots < n (coupled likelihood)
        here = slots == n
        x_cand = torch.where(here.unsqueeze(-1), x_prop, x)
        if existence:
            e_cand = torch.where(here, e_prop, e)
        # the declared hook: the cells near slot n only for grid sensors, else a full evaluation
        log_lik_cand = sensor.log_likelihood_slot(x, x_prop[..., n, :], n, z, log_lik, exists=e,
                                                  exists_n=e_prop[..., n] if existence else None)
        delta = log_lik_cand - log_lik
        acc = mh_accept(delta + log_ratio[..., n], u[..., n])
        x = mh_select(acc, x_cand, x)
        log_lik = torch.where(acc, log_lik_cand, log_lik)
        if existence:
            e = mh_select(acc, e_cand, e)
            log_birth = torch.where(acc.unsqueeze(-1) & here, birth_prop, log_birth)
        flags.append(acc)
    return chain._replace(x=x, log_lik=log_lik, log_lik_terms=None, exists=e, log_birth=log_birth), \
        torch.stack(flags, dim=-1)


# -- random walk on the joint state ----------------------------------------------------------
def _whiten(v: Tensor, motion: LinearGaussianMotion) -> Tensor:
    """``L^-1 v`` per target, flattened: ``(B, M, K, D) -> (B, M, K * D)`` (``Q = L L^T``)."""
    L = motion.L.to(v.dtype)
    L_inv = torch.linalg.solve_triangular(L, torch.eye(L.shape[0], dtype=v.dtype, device=v.device), upper=False)
    return (v @ L_inv.mT).flatten(2)


def log_transition(x: Tensor, prev_x: Tensor, *, motion: MotionModel,
                   white_prev: Optional[Tensor] = None) -> Tensor:
    """Joint log transition density from every previous particle to every chain state,
    ``sum_k log p(x_k | x_{k-1,k}^i)``.

    For a :class:`~torchmcmcpf.models.LinearGaussianMotion` the density is a Gaussian in
    whitened coordinates, ``log N(x; F x^i, Q) = c - |L^-1 x - L^-1 F x^i|^2 / 2``: both sides
    are whitened once and ``torch.cdist`` (direct differences, no ``|a|^2 - 2ab + |b|^2``
    cancellation) gives all ``(C, N)`` distances without a ``(B, C, N, K, D)`` intermediate
    (100x faster than the generic path at ``C = 40, N = 200``). Any other motion goes through
    ``motion.log_prob`` in chunks of previous particles, each holding about
    ``_CHUNK_ELEMENTS`` elements of ``(B, C, n, K, D)`` (a memory bound: one chunk for small
    problems).

    Parameters
    ----------
    x : (B, C, K, D) chain states; prev_x : (B, N, K, D) previous particles.
    white_prev : (B, N, K * D), optional: ``PreviousCloud.white_mean`` (linear-Gaussian
        motion), the whitened predicted means of ``prev_x`` when already computed.

    Returns
    -------
    (B, C, N).
    """
    b, c, k, d = x.shape
    n = prev_x.shape[1]
    if isinstance(motion, LinearGaussianMotion):
        log_norm = -0.5 * d * math.log(2 * math.pi) - torch.log(torch.diagonal(motion.L.to(x.dtype))).sum()
        if white_prev is None:
            white_prev = _whiten(motion.mean(prev_x), motion)
        dist = torch.cdist(_whiten(x, motion), white_prev, compute_mode="donot_use_mm_for_euclid_dist")
        return k * log_norm - 0.5 * dist.square()
    step = max(1, _CHUNK_ELEMENTS // max(1, b * c * k * d))
    out = []
    for i in range(0, n, step):
        p = prev_x[:, i:i + step]
        shape = (b, c, p.shape[1], k, d)
        out.append(motion.log_prob(x.unsqueeze(2).expand(shape), p.unsqueeze(1).expand(shape)).sum(-1))
    return torch.cat(out, dim=-1)


def propose_random_walk(x: Tensor, eps: Tensor, scale: Tensor, *, cloud: PreviousCloud,
                        motion: MotionModel) -> tuple[Tensor, Tensor, Tensor, Tensor]:
    """Gaussian random walk on the joint state (paper 002 eq. 13) and its log ratio (eq. 14
    without the likelihood).

    Parameters
    ----------
    x : (B, C, K, D) current states; eps : (B, C, K, D) normals.
    scale : (D,) or scalar tensor, the per-component step ``s`` (``S = diag(s^2)``).
    cloud : previous particles ``(B, N, K, D)`` with log-weights ``(B, N)``.

    Returns
    -------
    x_prop : (B, C, K, D) ``x + s * eps``.
    log_ratio : (B, C) ``log sum_i w^i p(x' | x^i) - log sum_i w^i p(x | x^i)`` (the
        proposal is symmetric).
    log_joint_prop, log_joint_cur : (B, C, N) ``log w^i + log p(. | x^i)`` at ``x'`` and ``x``
        (the ancestors' full conditionals, reused by :func:`random_walk_move`).
    """
    x_prop = x + scale * eps
    lt = log_transition(torch.cat([x, x_prop], dim=1), cloud.x, motion=motion, white_prev=cloud.white_mean)
    lt = lt + cloud.log_w.unsqueeze(1).to(lt.dtype)
    log_joint_cur, log_joint_prop = lt.chunk(2, dim=1)
    log_ratio = torch.logsumexp(log_joint_prop, -1) - torch.logsumexp(log_joint_cur, -1)
    return x_prop, log_ratio, log_joint_prop, log_joint_cur


def random_walk_move(chain: ChainState, noise: RandomWalkNoise, *, cloud: PreviousCloud,
                     z: Measurement, motion: MotionModel, sensor: SensorModel, scale: Tensor
                     ) -> tuple[ChainState, Tensor]:
    """One random-walk MH step on ``x`` (paper 002 eqs. 13-14), then a Gibbs redraw of the
    ancestor from ``p(a | x) ∝ w^a p(x | x^a)``.

    Parameters
    ----------
    chain : ChainState ``(B, C, K, D)``; noise : :class:`RandomWalkNoise`; cloud : previous
    particles; z : frame ``(B, *G)``; motion, sensor : the models; scale : (D,) or scalar
    random-walk step.

    Returns
    -------
    chain : the new ChainState.
    accepted : (B, C) bool.
    """
    x_prop, log_ratio, lj_prop, lj_cur = propose_random_walk(chain.x, noise.eps, scale, cloud=cloud,
                                                             motion=motion)
    log_lik, terms = evaluate(x_prop, z, sensor)
    accepted = mh_accept(log_lik - chain.log_lik + log_ratio, noise.u)
    new = mh_select(accepted, ChainState(x_prop, chain.x_prev, log_lik, terms), chain)
    # Gibbs step on the ancestor: inversion of the conditional's CDF with one uniform per chain.
    lj = torch.where(accepted.unsqueeze(-1), lj_prop, lj_cur)
    idx = inverse_cdf(cdf(lj), noise.u_ancestor.unsqueeze(-1))
    return new._replace(x_prev=gather_particles(cloud.x, idx.squeeze(-1))), accepted
