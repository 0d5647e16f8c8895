"""The exchange / mutation move of the IP-MCMC-PF (Bocquel et al. 2012, paper 000, Alg. 2,
eq. 12), with births and deaths, exclusion and re-capture, and its two-slot variant; see
:mod:`torchmcmcpf.filters.ipmcmc` for the target it leaves invariant. One iteration of the
chains is one exchange move (:func:`exchange_iteration`). Pure and branch-free: the noise is
pre-drawn (:func:`draw_exchange_noise`), so one iteration compiles with ``fullgraph=True``.
The chains' state, the amplitude cache included, is data: :class:`ExchangeChains`, taken and
returned.

One iteration moves ``M`` slots of every chain at once (``M`` is the trailing size of the
noise, static): ``M = 1`` is the paper's exchange move, ``M = 2`` the joint move of two slots
whose predictions are close (:class:`~torchmcmcpf.models.multitarget.Recapture`'s
``pair_every``; its two slots from one particle with probability ``p_same_source``, below).
Each moved slot ``j`` is drawn independently of the chain's state, from
previous particle ``i ~ w`` propagated by
:class:`~torchmcmcpf.models.existence.TargetDynamics` (motion, existence chain, birth or
``x_death``, relocation from the data), so the move is an independence proposal on those
slots and

    ``log alpha = log p(z | y') - log p(z | y) + log Phi(y') - log Phi(y)
                  + sum_{moved j} (log r'_j - log r_j)``

with ``Phi`` the exclusion factor and ``r_j`` the slot's cached target-over-proposal ratio
(plus, for a two-slot move with ``p_same_source > 0``, the pair's source term below).

The two-slot move's sources
---------------------------
The chains sample the target extended by each slot's source ``i_j`` (the previous particle
its proposal came from; :mod:`torchmcmcpf.filters.ipmcmc`, "Births and deaths"),

    ``pi(y, i) ∝ p(z | y) Phi(y) prod_j w^{i_j} f~(y_j | x^{i_j}_j)``,

whose ``i``-marginal is the factorised target. Drawn independently, the two slots of the
two-slot move come from one particle with probability ``sum_i (w^i)^2`` only, so a pair of
slots that only a few previous particles hold together (a crossing that a few chains
repaired: the two slots are right together and wrong apart) is almost never proposed as a
pair. With probability ``rho`` (:attr:`~torchmcmcpf.models.multitarget.Recapture.p_same_source`)
both slots are drawn from one particle ``i ~ w`` (their joint prediction), else from two
independent ones, so the pair's sources have the proposal probability
``Q(i_j, i_l) = (1 - rho) w^{i_j} w^{i_l} + rho w^{i_j} 1[i_j = i_l]`` against their target
factor ``w^{i_j} w^{i_l}``, and the move's ``log alpha`` gains

    ``s(i'_j, i'_l) - s(i_j, i_l)``,   ``s(i_j, i_l) = -log(1 + rho / ((1 - rho) w^{i_l}))`` if
    ``i_j = i_l``, else 0

(the constant ``-log(1 - rho)`` cancels): 6.2 nats to make a pair one-sourced at ``rho =
0.5``, ``N = 500``: a repair is taken where the frame favours it by more than that
(docs/tracks.md has cases either side). The chains keep every
slot's source and its log-weight (:class:`ExchangeChains`), taken from the move's noise.

Joint pairs
-----------
The factorised prior drops the correlation of two slots that the previous cloud holds
together: after an unresolved crossing the product of their marginals also holds the
arrangements no particle held (both slots on one target, or each on the other's path with
its own amplitude), and one frame scores some of them within a few nats of the truth. With
``partner`` (:func:`mutual_nearest_pairs`: two slots whose predictions are each other's
nearest within a distance, fixed for the step) the target keeps each such pair's *joint*
prediction, ``sum_i w^i f~(y_a | x^i_a) f~(y_b | x^i_b)``, and the other slots' marginals:
the extended target forces one source on the pair,

    ``pi(y, i) ∝ p(z | y) Phi(y) prod_{unpaired j} w^{i_j} f~(y_j | x^{i_j}_j)
                 prod_{pairs (a, b)} w^{i_a} 1[i_a = i_b] f~(y_a | x^{i_a}_a) f~(y_b | x^{i_a}_b)``,

whose ``i``-marginal is that prior (paper 002 eq. 11's joint prediction over the pair, the
MCMC-PF's target restricted to it). Its moves: an unpaired slot's as above; a paired slot's
one-slot move keeps the pair's source (``y'_a ~ q(. | x^{i_b}_a)``, a Metropolis-within-Gibbs
update of ``y_a`` given ``i``: ``log alpha`` as above, the source unchanged); the two-slot
move of a pair draws one source ``i ~ w`` for both (``rho = 1``: the pair's proposal
``w^i q q`` against its factor ``w^i f~ f~``, so no source term). Every state the chains start
from (both slots of a starting point from one particle) satisfies the constraint.
"""

from __future__ import annotations

import math
from typing import NamedTuple

import torch

from .._native.select import MIN_ELEMENTS, where
from ..models.base import SensorModel
from ..models.existence import BirthNoise, TargetDynamics
from ..models.multitarget import LOG_PHI_FLOOR, Exclusion, RelocationNoise, exclusion_on, log_q_ratio
from ..resampling import cdf, inverse_cdf, normalize
from ..runtime import pairwise_squared_distances, take_along
from ..typing import Measurement, Tensor
from . import _exchange_native
from .mh import mh_accept

__all__ = ["ExchangeChains", "ExchangeNoise", "ExchangeProposal", "draw_exchange_noise", "propose_slots",
           "exchange_iteration", "one_call_serves", "close_pairs", "mutual_nearest_pairs", "with_accepted_amplitudes",
           "pair_source_log_ratio"]


class ExchangeChains(NamedTuple):
    """The state of C chains in each of B runs under the exchange move.

    Attributes
    ----------
    y : (B, C, K, D) the chains' multitarget states.
    log_lik : (B, C) ``log p(z | y, exists)``.
    exists : (B, C, K) bool with an existence model, else ``None``.
    log_r : (B, C, K) the cached ``log r_j`` (at ``recapture.p_propose``) with an existence
        model or re-capture, else ``None``.
    kind : (B, C, K) int8, the slots' proposal components with re-capture
        (:func:`~torchmcmcpf.models.multitarget.relocate`), else ``None``.
    source : (B, C, K) int64, each slot's source particle ``i_j``, with one-sourced two-slot
        moves (``p_same_source > 0``) or joint pairs (module docstring), else ``None``.
    log_w_source : (B, C, K), the normalised log-weight ``log w^{i_j}`` of that source, with
        ``source``, else ``None``.
    amplitude : (B, C, G), optional: the chains' amplitude per cell
        (:meth:`~torchmcmcpf.models.base.SensorModel.amplitude_cache`), so that a one-slot
        move reads its two boxes instead of summing the other targets' spreads there
        (:meth:`~torchmcmcpf.models.base.SensorModel.log_likelihood_delta_cached`). A speed
        choice, not another algorithm: with it or without, the chains are the same to
        round-off (tested in float64). Made once per step for the chains, advanced for the
        accepted moves by :func:`with_accepted_amplitudes` only, never recorded in a trace.
    coords : (B, C, K, r), optional: the slots' resolution coordinates
        (:meth:`~torchmcmcpf.models.base.SensorModel.resolution_coords` of ``y``) with the
        exclusion term, so that a move reads them instead of mapping every slot of every
        chain again (the moved slots' come with the segment's proposals,
        :attr:`ExchangeProposal.coords`); selected with the state, equal to the recomputed
        coordinates (tested), never recorded in a trace.
    terms : (B, C, K, T), optional, with ``amplitude``: what the sensor's cached move reads
        of each slot (:meth:`~torchmcmcpf.models.base.SensorModel.move_terms`: the radar's
        measured coordinates and amplitude), so that a move gathers its slots' rows instead
        of mapping their states again (the moved slots' come with the segment's proposals,
        :attr:`ExchangeProposal.terms`); selected with the state, the values of the states
        mapped afresh (tested; a bearing can differ by an ulp where the batch's layout takes
        ATen's other ``atan2`` loop), never recorded in a trace.

    Example
    -------
    One exchange iteration of 8 chains in each of 2 runs, 3 slots, a linear sensor:

    >>> import math
    >>> import torch
    >>> import torchmcmcpf as tp
    >>> from torchmcmcpf.kernels.exchange import ExchangeChains, ExchangeNoise, draw_exchange_noise, exchange_iteration
    >>> from torchmcmcpf.models.existence import TargetDynamics
    >>> motion, sensor = tp.ConstantVelocity(dt=1.0, q=1.0), tp.LinearGaussian.position(noise_std=1.0)
    >>> dynamics, g = TargetDynamics(motion), torch.Generator().manual_seed(0)
    >>> x_prev, log_w = torch.zeros(2, 100, 3, 4), torch.full((2, 100), -math.log(100))   # (B, N, K, D)
    >>> z, y = torch.zeros(2, 3, 2), torch.zeros(2, 8, 3, 4)          # a frame; the chains (B, C, K, D)
    >>> chains = ExchangeChains(y, sensor.log_likelihood(y, z))
    >>> noise = draw_exchange_noise(log_w, 1, 8, 3, dynamics=dynamics, generator=g, dtype=torch.float32)
    >>> first = ExchangeNoise(*(t if t is None else t[0] for t in noise))   # iteration 0: leading (B, C)
    >>> chains, accepted, update = exchange_iteration(chains, x_prev, None, z, first, dynamics=dynamics,
    ...                                               sensor=sensor)
    >>> chains.y.shape, accepted.shape, update        # a linear sensor keeps no amplitude cache
    (torch.Size([2, 8, 3, 4]), torch.Size([2, 8]), None)
    >>> torch.allclose(chains.log_lik, sensor.log_likelihood(chains.y, z))
    True
    """

    y: Tensor
    log_lik: Tensor
    exists: Tensor | None = None
    log_r: Tensor | None = None
    kind: Tensor | None = None
    source: Tensor | None = None
    log_w_source: Tensor | None = None
    amplitude: Tensor | None = None
    coords: Tensor | None = None
    terms: Tensor | None = None


def with_accepted_amplitudes(chains: ExchangeChains, amplitude: Tensor | None,
                             update: tuple[Tensor | None, Tensor] | None, accepted: Tensor,
                             sensor: SensorModel) -> ExchangeChains:
    """``chains`` (the output of :func:`exchange_iteration`) with the amplitude cache of the
    chains before the iteration, ``amplitude``, advanced by the iteration's ``update`` for its
    ``accepted (B, C)`` moves.

    The one place a chain state changes in place: the cache is the chains' own buffer, so
    :meth:`~torchmcmcpf.models.base.SensorModel.update_amplitude_cache` adds the accepted
    changes into it instead of copying the grid at every iteration (one scatter-add, no host
    sync); the chains before the iteration hand it over and do not use it again.
    """
    if amplitude is None or update is None:
        return chains
    return chains._replace(amplitude=sensor.update_amplitude_cache(amplitude, *update, accepted))


class ExchangeProposal(NamedTuple):
    """The slots that ``L`` iterations (or one) propose, from their :class:`ExchangeNoise`
    (:func:`propose_slots`). The exchange move is an independence proposal: what it
    proposes does not depend on the chains' state, so a segment's proposals are made in one
    batched call before its iterations run instead of one small call per iteration.

    Attributes
    ----------
    moved : (*L, B, C, M, D) the proposed states of the moved slots.
    exists : (*L, B, C, M) bool, their proposed flags with an existence model, else ``None``.
    log_r : (*L, B, C, M) their ``log r`` at this move's ``epsilon`` (zeros without an
        existence model or re-capture).
    kind : (*L, B, C, M) int8, their proposal components with re-capture, else ``None``.
    coords : (*L, B, C, M, r), their resolution coordinates
        (:meth:`~torchmcmcpf.models.base.SensorModel.resolution_coords`) when
        :func:`propose_slots` is given the sensor (the exclusion term), else ``None``: one
        batched call per segment instead of one per iteration.
    terms : (*L, B, C, M, T), the moved slots'
        :meth:`~torchmcmcpf.models.base.SensorModel.move_terms` (with their proposed flags)
        when :func:`propose_slots` is given ``terms_of``, else ``None``.

    Example
    -------
    >>> import math
    >>> import torch
    >>> import torchmcmcpf as tp
    >>> from torchmcmcpf.kernels.exchange import draw_exchange_noise, propose_slots
    >>> from torchmcmcpf.models.existence import TargetDynamics
    >>> dynamics = TargetDynamics(tp.ConstantVelocity(dt=1.0, q=1.0))
    >>> x_prev, log_w = torch.zeros(2, 100, 3, 4), torch.full((2, 100), -math.log(100))
    >>> noise = draw_exchange_noise(log_w, 5, 8, 3, dynamics=dynamics, generator=torch.Generator(),
    ...                             dtype=torch.float32)
    >>> proposal = propose_slots(noise, x_prev, None, dynamics=dynamics)   # 5 iterations at once
    >>> proposal.moved.shape, proposal.exists, proposal.kind          # (L, B, C, M, D); no births, no re-capture
    (torch.Size([5, 2, 8, 1, 4]), None, None)
    """

    moved: Tensor
    exists: Tensor | None
    log_r: Tensor
    kind: Tensor | None
    coords: Tensor | None = None
    terms: Tensor | None = None


class ExchangeNoise(NamedTuple):
    """Pre-drawn randomness of ``L`` iterations moving ``M`` slots each (leading dim ``L``).

    Attributes
    ----------
    source : (L, B, C, M) int64, the previous particle each moved slot starts from (with
        ``M = 2`` both slots' the same with probability ``p_same_source``).
    log_w_source : (L, B, C, M), its normalised log-weight.
    slot : (L, B, C, M) int64, the target slots each chain updates (distinct).
    eps : (L, B, C, M, noise_dim), standard normal process noise of the proposals.
    u : (L, B, C), uniforms of the accept/reject test.
    birth : :class:`~torchmcmcpf.models.existence.BirthNoise` with leading ``(L, B, C, M)``
        (only with an existence model).
    relocation : :class:`~torchmcmcpf.models.multitarget.RelocationNoise` with leading
        ``(L, B, C, M)`` (only with re-capture).
    valid : (L, B, C) bool, optional: False where a run has no pair of close slots (the
        two-slot move is then rejected).
    proposal : :class:`ExchangeProposal` with leading ``(L, B, C)``, optional: the slots
        this noise proposes, made in advance (:func:`propose_slots`); without it each
        iteration makes its own (the same values).
    partner : (L, B, C, M) int64, optional: with joint pairs (module docstring) each moved
        slot's partner, the slot itself where it has none. A one-slot move of a paired slot
        then takes its partner's current source, not ``source`` (so its proposal is made in
        the iteration), and a two-slot move has one source and no source term.

    Example
    -------
    >>> import math
    >>> import torch
    >>> import torchmcmcpf as tp
    >>> from torchmcmcpf.kernels.exchange import draw_exchange_noise
    >>> from torchmcmcpf.models.existence import TargetDynamics
    >>> dynamics = TargetDynamics(tp.ConstantVelocity(dt=1.0, q=1.0))
    >>> log_w = torch.full((2, 100), -math.log(100))                   # the previous weights (B, N)
    >>> noise = draw_exchange_noise(log_w, 5, 8, 3, dynamics=dynamics, generator=torch.Generator(),
    ...                             dtype=torch.float32)
    >>> noise.source.shape, noise.eps.shape, noise.u.shape            # (L, B, C, M), ..., (L, B, C)
    (torch.Size([5, 2, 8, 1]), torch.Size([5, 2, 8, 1, 4]), torch.Size([5, 2, 8]))
    >>> bool((noise.slot < 3).all()), noise.birth, noise.relocation
    (True, None, None)
    """

    source: Tensor
    log_w_source: Tensor
    slot: Tensor
    eps: Tensor
    u: Tensor
    birth: BirthNoise | None = None
    relocation: RelocationNoise | None = None
    valid: Tensor | None = None
    proposal: ExchangeProposal | None = None
    partner: Tensor | None = None


def close_pairs(centres: Tensor, distance: float, exists: Tensor | None = None) -> Tensor:
    """Pairs of slots whose predictions lie within ``distance`` resolution cells.

    Parameters
    ----------
    centres : (B, K, r) resolution coordinates of each slot's predicted estimate.
    distance : > 0.
    exists : (B, K) bool, optional: only slots that exist somewhere pair.

    Returns
    -------
    (B, K, K) bool, True for ``i < j`` within ``distance``.
    """
    k = centres.shape[-2]
    _, near = _within(centres, distance, exists)
    return near & torch.ones((k, k), dtype=torch.bool, device=centres.device).triu(1)


def _within(centres: Tensor, distance: float, exists: Tensor | None) -> tuple[Tensor, Tensor]:
    """The squared distances ``(B, K, K)`` between the slots' predictions and which pairs lie
    within ``distance`` (both existing, where ``exists`` is given), as :func:`close_pairs`
    takes them.
    """
    d2 = pairwise_squared_distances(centres, centres)
    near = d2 < distance**2
    if exists is not None:
        near = near & exists.unsqueeze(-1) & exists.unsqueeze(-2)
    return d2, near


def mutual_nearest_pairs(centres: Tensor, distance: float, exists: Tensor | None = None) -> Tensor:
    """Each slot's partner under joint pairs (module docstring): the slot whose prediction is
    its nearest, where that lies within ``distance`` resolution cells and the two are each
    other's nearest (a matching: every slot has at most one partner); else the slot itself.
    ``centres (B, K, r)``, ``distance`` and ``exists (B, K)`` as :func:`close_pairs` takes them;
    returns ``(B, K)`` int64 with ``partner[partner[j]] = j`` for every slot.

    Example
    -------
    >>> import torch
    >>> from torchmcmcpf.kernels.exchange import mutual_nearest_pairs
    >>> centres = torch.tensor([[[0.0], [1.0], [1.5], [9.0]]])     # (B, K, r): 1 and 2 closest
    >>> mutual_nearest_pairs(centres, 2.0).tolist()
    [[0, 2, 1, 3]]
    """
    if not distance > 0:
        raise ValueError(f"distance must be > 0 resolution cells, got {distance!r}")
    k = centres.shape[-2]
    d2, near = _within(centres, distance, exists)
    far = ~near | torch.eye(k, dtype=torch.bool, device=centres.device)
    d2 = where(far, torch.full_like(d2, float("inf")), d2)
    nearest = d2.argmin(-1)  # (B, K); any slot where all are far (its row inf), checked below
    own = torch.arange(k, device=centres.device).expand_as(nearest)
    mutual = (take_along(nearest, nearest, -1) == own) & torch.isfinite(take_along(d2, nearest.unsqueeze(-1), -1)
                                                                          ).squeeze(-1)
    return where(mutual, nearest, own)


def draw_exchange_noise(
    log_w: Tensor, num_iterations: int, num_chains: int, num_targets: int, *, dynamics: TargetDynamics,
    generator: torch.Generator, dtype: torch.dtype, z: Measurement | None = None, pairs: Tensor | None = None,
    exists: Tensor | None = None, found: object = None, partner: Tensor | None = None,
) -> ExchangeNoise:
    """Draw the randomness of ``L = num_iterations`` iterations: one slot per iteration
    (uniform over the K slots) or, with ``pairs``, two slots (uniform over the close pairs of
    the run); the motion noise of ``dynamics``, with its existence model the birth noise
    (births near the points of the frame ``z`` when the model draws them so), with its
    re-capture the relocation noise (from ``z``).

    ``source`` indices are categorical draws from the previous weights ``log_w (B, N)`` by
    inversion of uniforms (float64 CDF + ``searchsorted``, no ``torch.multinomial``); with
    ``pairs`` and ``dynamics.recapture.p_same_source = rho > 0`` the second slot takes the
    first's source with probability ``rho`` (module docstring).

    Parameters
    ----------
    pairs : (B, K, K) bool, optional (:func:`close_pairs`): draw two-slot moves.
    exists : (B, N, K) bool, optional: the previous particles' flags. A newborn's ratio (a
        sum over the frame's points) is then taken only where the moved slot's source slot is
        inactive (with ``p_same_source``, where either possible source's is), the only place
        a move reads it (:meth:`~torchmcmcpf.models.existence.BirthDeath.can_be_born`); the
        draws are the same.
    found : optional, the frame's detections for the relocation draws
        (:meth:`~torchmcmcpf.models.base.SensorModel.frame_detections`, made once per step).
    partner : (B, K) int64, optional: joint pairs (:func:`mutual_nearest_pairs`; module
        docstring): the noise carries each moved slot's partner, and a two-slot draw (over
        ``pairs``, the pairs of ``partner``) takes one source for both slots. No existence
        model.
    """
    b, n = log_w.shape
    m = 1 if pairs is None else 2
    shape = (num_iterations, b, num_chains)
    dev = log_w.device
    u_src = torch.rand((b, num_iterations * num_chains * m), generator=generator, device=dev, dtype=torch.float64)
    source = inverse_cdf(cdf(log_w), u_src).reshape(b, num_iterations, num_chains, m).transpose(0, 1)
    valid = None
    if pairs is None:
        slot = torch.randint(num_targets, shape + (1,), generator=generator, device=dev)
    else:
        flat = pairs.reshape(b, num_targets * num_targets)
        valid_run = flat.any(-1)  # (B,)
        # a run without a close pair draws pair (0, 1) and is rejected (valid False)
        fallback = torch.zeros_like(flat).index_fill_(-1, torch.tensor([1], device=dev), True)
        weights = where(valid_run.unsqueeze(-1), flat, fallback)
        log_p = where(weights, 0.0, float("-inf")).to(torch.float64)
        u_pair = torch.rand((b, num_iterations * num_chains), generator=generator, device=dev, dtype=torch.float64)
        at = inverse_cdf(cdf(log_p), u_pair).reshape(b, num_iterations, num_chains).transpose(0, 1)
        slot = torch.stack([at // num_targets, at % num_targets], -1)
        valid = valid_run.reshape(1, b, 1).expand(shape)
    eps = torch.randn(shape + (m, dynamics.motion.noise_dim), generator=generator, device=dev, dtype=dtype)
    u = torch.rand(shape, generator=generator, device=dev, dtype=dtype)
    birth = None
    if dynamics.existence is not None:
        template = torch.empty((b, num_iterations, num_chains, m, dynamics.existence.dim), device=dev, dtype=dtype)
        parent_e = None
        if exists is not None:  # the source slots' flags, leading (B, L, C, M)
            flags = exists.reshape(b, n * exists.shape[-1])
            src = source.transpose(0, 1)

            def flag(particle: Tensor) -> Tensor:
                at = (particle * exists.shape[-1] + slot.transpose(0, 1)).reshape(b, -1)
                return take_along(flags, at, 1).reshape(at.shape[:1] + src.shape[1:])

            parent_e = flag(src)
            if pairs is not None and dynamics.recapture is not None and dynamics.recapture.p_same_source > 0:
                # the second slot may take the first's source (drawn below): live only where both are
                parent_e = parent_e & flag(src[..., :1].expand(src.shape))
        drawn = dynamics.draw_births(template, z, generator=generator, exists=parent_e)  # leading (B, L, C, M)
        birth = None if drawn is None else BirthNoise(*(t.transpose(0, 1) for t in drawn))
    relocation = dynamics.draw_relocations((b, num_iterations, num_chains, m), z, generator=generator, dtype=dtype,
                                           device=dev, p_propose=None if dynamics.recapture is None or m == 1
                                           else dynamics.recapture.p_propose_pair, found=found)
    if relocation is not None:
        relocation = RelocationNoise(*(t.transpose(0, 1) for t in relocation))
    rho = 0.0 if pairs is None or dynamics.recapture is None else dynamics.recapture.p_same_source
    carried = None
    if partner is not None:  # joint pairs: every moved slot's partner; a pair's two slots one source
        if dynamics.existence is not None:
            raise ValueError("joint pairs (partner) need a known number of targets (no existence model)")
        carried = take_along(partner.unsqueeze(0).expand(shape[:2] + (num_targets,)), slot.flatten(2), -1
                             ).reshape(slot.shape)
        if pairs is not None:
            source = source[..., :1].expand(source.shape).contiguous()
            rho = 0.0
    if rho > 0:  # both slots from one particle (drawn last: the other draws are those of rho = 0)
        same = torch.rand(shape, generator=generator, device=dev, dtype=torch.float64) < rho
        source = torch.stack([source[..., 0], where(same, source[..., 0], source[..., 1])], -1)
    log_w_source = take_along(normalize(log_w)[0], source.movedim(0, 1).reshape(b, -1), 1).reshape(
        (b, num_iterations, num_chains, m)).movedim(1, 0)
    return ExchangeNoise(source, log_w_source, slot, eps, u, birth, relocation, valid, None, carried)


def pair_source_log_ratio(source: Tensor, log_w_source: Tensor, rho: float) -> Tensor:
    """``s(i_j, i_l)`` of the module docstring for the two slots of a move: ``-log(1 + rho /
    ((1 - rho) w^{i_l}))`` where both have one source, 0 otherwise.

    Parameters
    ----------
    source : (*S, 2) int64; log_w_source : (*S, 2) their normalised log-weights; rho : in
        (0, 1).

    Returns
    -------
    (*S,), in the dtype of ``log_w_source``.
    """
    log_odds = math.log(rho) - math.log1p(-rho)
    same = source[..., 0] == source[..., 1]
    return where(same, -torch.nn.functional.softplus(log_odds - log_w_source[..., 1]),
                       torch.zeros_like(log_w_source[..., 1]))


def propose_slots(noise: ExchangeNoise, x_prev: Tensor, exists_prev: Tensor | None, *,
                  dynamics: TargetDynamics, sensor: SensorModel | None = None,
                  terms_of: SensorModel | None = None) -> ExchangeProposal:
    """The slots that ``noise`` proposes (module docstring): slot ``noise.slot`` of previous
    particle ``noise.source``, propagated by ``dynamics`` with the noise's motion, birth and
    relocation draws, scored at the move's ``epsilon`` (``recapture.p_propose`` for one slot,
    ``p_propose_pair`` for two).

    Parameters
    ----------
    noise : :class:`ExchangeNoise` with leading ``(*L, B, C)`` (one iteration or several).
    x_prev : (B, N, K, D), exists_prev : (B, N, K) or None: the previous particles.
    sensor : optional: the proposed slots' resolution coordinates too
        (:attr:`ExchangeProposal.coords`, for the exclusion term), in the same call.
    terms_of : optional: the sensor whose :meth:`~torchmcmcpf.models.base.SensorModel.move_terms`
        of the proposed slots the chains read (:attr:`ExchangeProposal.terms`).

    Returns
    -------
    :class:`ExchangeProposal` with leading ``(*L, B, C)``.
    """
    b, n, k, d = x_prev.shape
    m = noise.slot.shape[-1]
    # runs first, so that one gather per run reads every iteration's and chain's parent
    at = (noise.source * k + noise.slot).movedim(-3, 0)  # (B, *L, C, M)
    flat = at.reshape(b, -1)
    parent = take_along(x_prev.reshape(b, n * k, d), flat.unsqueeze(-1), dim=1).reshape(at.shape + (d,))
    parent = parent.movedim(0, -4)
    parent_e = None if exists_prev is None else \
        take_along(exists_prev.reshape(b, n * k), flat, dim=1).reshape(at.shape).movedim(0, -3)
    recapture = dynamics.recapture
    eps_k = None if recapture is None else (recapture.p_propose if m == 1 else recapture.p_propose_pair)
    moved, e_new, log_r, kind = dynamics.propagate_labelled(parent, parent_e, noise.eps, noise.birth,
                                                            noise.relocation, eps_k)
    return ExchangeProposal(moved, e_new, log_r, kind, None if sensor is None else sensor.resolution_coords(moved),
                            None if terms_of is None else terms_of.move_terms(moved, e_new))


def _write_row(t: Tensor, slot: Tensor, row: Tensor, accepted: Tensor, take: Tensor) -> Tensor:
    """``t (B, C, K, D)`` with row ``slot (B, C)`` set to ``row (B, C, D)`` where ``accepted
    (B, C)`` (``take (B, C, K)``: the slot's place where accepted): a new tensor, the values of
    ``where(take[..., None], row[..., None, :], t)``. That select, its mask and row
    broadcast over the inner dim, costs 3x a copy on the CPU: a large ``t`` (the births/deaths
    chains) is written by a gather, a select of the row and a scatter instead; a small one
    (under :data:`~torchmcmcpf._native.select.MIN_ELEMENTS`) by the one select (five calls
    fewer).
    """
    if t.numel() < MIN_ELEMENTS:
        return where(take.unsqueeze(-1), row.unsqueeze(-2), t)
    at = slot.reshape(slot.shape + (1, 1)).expand(slot.shape + (1, t.shape[-1]))  # (B, C, 1, D)
    keep = where(accepted.reshape(accepted.shape + (1, 1)), row.unsqueeze(-2), torch.gather(t, -2, at))
    return t.scatter(-2, at, keep)


def one_call_serves(chains: ExchangeChains, x_prev: Tensor, exists_prev: Tensor | None, z: Measurement,
                    noise: ExchangeNoise) -> bool:
    """Whether :func:`exchange_iteration` on these arguments (its positional ones) runs the
    rest of its move in one C call (its docstring): chains that keep their move terms and an
    amplitude cache, without existence flags, eager on float32 CPU tensors. A compiled
    IP-MCMC-PF runs such iterations eagerly (:attr:`~torchmcmcpf.runtime.Program.eager_when`):
    a one-slot iteration 0.26 ms against 0.58 for the compiled graph on bench's radar scene
    (Np = 5000, 50 chains, 2 threads; benchmarks/README.md).
    """
    return _in_c(chains)


def _in_c(chains: ExchangeChains) -> bool:
    """Chains whose moves the C calls serve: move terms and an amplitude cache kept, no
    existence flags, eager on float32 CPU tensors.
    """
    return chains.terms is not None and chains.amplitude is not None and chains.exists is None \
        and _exchange_native.applies(chains.log_lik)


def _move_fields(chains: ExchangeChains, proposal: ExchangeProposal, source: Tensor | None,
                 log_w_source: Tensor | None, with_coords: bool, base: float | None, eps_k: float | None
                 ) -> dict[str, tuple[Tensor, Tensor]]:
    """The chain fields a move writes, each with the moved slots' new rows (the proposal's,
    leading ``(*L, B, C, M)``), in a fixed order: ``y``; ``log_r`` (written at the chains'
    ``epsilon`` ``base``, the move's is ``eps_k``); ``kind``; ``source`` and ``log_w_source``
    (the moved slots' ``source``, ``log_w_source``); ``coords`` (where ``with_coords``);
    ``terms``; each where the chains and the proposal have it.
    """
    y, _, _, log_r, kind, src, lw, _, coords, terms = chains
    moved, _, r_new, kind_new, coords_new, terms_new = proposal
    fields: dict[str, tuple[Tensor, Tensor]] = {"y": (y, moved)}
    if log_r is not None and r_new is not None:
        fields["log_r"] = (log_r, _convert(r_new, kind_new, eps_k, base))
    if kind is not None and kind_new is not None:
        fields["kind"] = (kind, kind_new)
    if src is not None and lw is not None and source is not None and log_w_source is not None:
        fields.update(source=(src, source), log_w_source=(lw, log_w_source.to(lw.dtype)))
    if with_coords and coords is not None and coords_new is not None:
        fields["coords"] = (coords, coords_new)
    if terms is not None and terms_new is not None:
        fields["terms"] = (terms, terms_new)
    return fields


def _convert(r: Tensor, kind: Tensor | None, src: float | None, dst: float | None) -> Tensor:
    """A cached ``log r`` at ``epsilon = src`` converted to ``dst`` by the slots' ``kind``
    (:func:`~torchmcmcpf.models.multitarget.log_q_ratio`, added in ``r``'s dtype).
    """
    if kind is None or src is None or dst is None or src == dst:
        return r
    return r + log_q_ratio(kind, src, dst).to(r.dtype)


def _source_term(noise: ExchangeNoise, source: Tensor | None, log_w_source: Tensor | None, rho: float
                 ) -> Tensor | None:
    """The pair's source term of a two-slot move (module docstring), new minus old: the
    moved slots' from ``noise`` (one iteration, leading ``(B, C)``), the chains' ``source``
    and ``log_w_source`` at the moved slots; None without one (``rho = 0``).
    """
    if rho > 0 and source is not None and log_w_source is not None:
        return (pair_source_log_ratio(noise.source, noise.log_w_source, rho)
                - pair_source_log_ratio(take_along(source, noise.slot, -1), take_along(log_w_source, noise.slot, -1),
                                        rho))
    return None


def _one_call(chains: ExchangeChains, noise: ExchangeNoise, proposal: ExchangeProposal, delta: Tensor, cells: Tensor,
              change: Tensor, exclusion: Exclusion | None, source: Tensor | None, log_w_source: Tensor | None,
              src_term: Tensor | None, base: float | None, eps_k: float | None
              ) -> tuple[ExchangeChains, Tensor, None]:
    """:func:`exchange_iteration`'s move of ``M`` slots after the likelihood's change ``delta``
    (``cells``, ``change`` its cache update) in one C call (:mod:`._exchange_native`): the
    same chains, decisions and cache as the tensor path; the cache advanced in place, so the
    returned chains carry it and the update is ``None``. ``exclusion`` only where the chains
    keep their coordinates; ``source``, ``log_w_source`` the moved slots' (B, C, M);
    ``src_term`` the pair's source term; ``base`` the ``epsilon`` at which the chains cache
    ``log r``, ``eps_k`` this move's (:func:`_convert`).
    """
    log_lik, log_r, kind, src, lw, cache = (chains.log_lik, chains.log_r, chains.kind, chains.source,
                                            chains.log_w_source, chains.amplitude)
    r_new = proposal.log_r
    assert cache is not None
    m = noise.slot.shape[-1]
    fields = _move_fields(chains, proposal, source, log_w_source, exclusion is not None, base, eps_k)
    r_old = None
    if log_r is not None and "log_r" in fields and m > 1:  # the moved slots' at this move's epsilon (M = 1: in C)
        r_old = _convert(torch.gather(log_r, -1, noise.slot), None if kind is None else torch.gather(
            kind, -1, noise.slot), base, eps_k)
    u, u_new = fields["coords"] if "coords" in fields else (None, None)
    ll, accepted, out = _exchange_native.commit(
        log_lik, delta, noise.u, noise.valid, noise.slot, src_term, u, u_new,
        1.0 if exclusion is None else exclusion.scale, LOG_PHI_FLOOR, log_r if "log_r" in fields else None,
        r_new if "log_r" in fields else None, r_old, list(fields.values()), cache, cells, change)
    new = dict(zip(fields, out))
    return ExchangeChains(new["y"], ll, None, new.get("log_r", log_r), new.get("kind", kind), new.get("source", src),
                          new.get("log_w_source", lw), cache, new.get("coords"), new.get("terms")), accepted, None


def exchange_iteration(
    chains: ExchangeChains, x_prev: Tensor, exists_prev: Tensor | None, z: Measurement, noise: ExchangeNoise,
    *, dynamics: TargetDynamics, sensor: SensorModel, exclusion: Exclusion | None = None,
) -> tuple[ExchangeChains, Tensor, tuple[Tensor | None, Tensor] | None]:
    """One exchange/mutation MH iteration of every chain (paper 000 Alg. 2, eq. 12) moving
    ``M`` slots (module docstring), with or without births and deaths, exclusion and
    re-capture (one code path: the slots are propagated by ``dynamics``).

    With the chains' ``amplitude`` cache the proposal's ratio is
    :meth:`SensorModel.log_likelihood_delta_cached` of all ``M`` moved slots at once (the
    amplitudes at their old and new boxes read, not summed from the neighbours' spreads; a
    cell the boxes share counted once), and the cache's change is returned: the iteration is
    pure, and :func:`with_accepted_amplitudes` advances the cache for the accepted moves. With
    the chains' ``terms`` and the proposal's, the sensor reads the moved slots' rows
    (:meth:`SensorModel.log_likelihood_delta_terms`) instead of their states.
    Without a cache it is scored by the declared hook :meth:`SensorModel.log_likelihood_slot`,
    slot after slot: a sensor that overrides ``log_likelihood_delta`` gives each ratio from the
    cells near the old and new position of the slot only, carried as ``log_lik + delta``; any
    other sensor scores the whole proposal with ``log_likelihood``.

    A move read from the chains' terms on float32 CPU tensors without existence flags,
    eager, runs its rest in one C call after the likelihood's change
    (:mod:`._exchange_native`: the decision, the fields and the cache; the same bits).

    Parameters
    ----------
    chains : :class:`ExchangeChains` ``(B, C, ...)``.
    x_prev : (B, N, K, D), exists_prev : (B, N, K) or None: the previous particles.
    z : the frame; noise : :class:`ExchangeNoise` of one iteration (leading ``(B, C)``).
    dynamics : :class:`~torchmcmcpf.models.existence.TargetDynamics`, the slots' joint model
        (motion, optionally births and deaths and re-capture); sensor : the SensorModel;
        exclusion : the exclusion term, optional.

    Returns
    -------
    chains : the new :class:`ExchangeChains`, without their ``amplitude`` (None), but after
        the one C call, which advanced the cache in place: then the chains carry it.
    accepted : (B, C) bool.
    update : ``(cells, change)`` with an ``amplitude`` cache (None after the one C call),
        else ``None``.
    """
    y, log_lik, exists, log_r, kind, source, log_w_source, cache, coords, terms = chains
    existence, recapture = dynamics.existence, dynamics.recapture
    k, m = x_prev.shape[-2], noise.slot.shape[-1]
    if (existence is not None or recapture is not None) and log_r is None:
        raise ValueError("with an existence model or re-capture the chains need log_r (got None)")
    if existence is not None and exists is None:
        raise ValueError("with an existence model the chains need exists (got None)")
    joint = noise.partner is not None  # joint pairs (module docstring): no source term
    rho = 0.0 if recapture is None or m == 1 or joint else recapture.p_same_source
    if (rho > 0 or joint) and (source is None or log_w_source is None):
        raise ValueError("a two-slot move with p_same_source > 0 and joint pairs need the chains' source and "
                         "log_w_source (got None)")
    # this move's epsilon; the chains cache log r at recapture.p_propose, converted by the
    # slots' kinds (models/multitarget.py, log_q_ratio) where the two differ
    base = None if recapture is None else recapture.p_propose
    eps_k = None if recapture is None else (base if m == 1 else recapture.p_propose_pair)
    on = exclusion_on(exclusion, sensor)
    src_moved, lw_moved = noise.source, noise.log_w_source
    if joint and m == 1 and source is not None and log_w_source is not None and noise.partner is not None:
        # a paired slot keeps its pair's source: the proposal depends on the chain, made here
        paired = noise.partner != noise.slot  # (B, C, 1)
        src_moved = where(paired, take_along(source, noise.partner, -1), noise.source)
        lw_moved = where(paired, take_along(log_w_source, noise.partner, -1).to(noise.log_w_source.dtype),
                               noise.log_w_source)
        proposal = propose_slots(noise._replace(source=src_moved), x_prev, exists_prev, dynamics=dynamics,
                                 sensor=sensor if on else None, terms_of=None if terms is None else sensor)
    else:
        proposal = noise.proposal if noise.proposal is not None else \
            propose_slots(noise, x_prev, exists_prev, dynamics=dynamics)
    moved, e_new, r_new, kind_new, coords_new, terms_new = proposal
    by_terms = cache is not None and terms is not None and terms_new is not None  # rows read, states not mapped
    kept = on and coords is not None and coords_new is not None  # the chains keep their coordinates

    update = None
    if by_terms and cache is not None and terms is not None and terms_new is not None:  # the moved slots' rows
        delta, cells, change = sensor.log_likelihood_delta_rows(cache, terms, noise.slot, terms_new, z)
        # the rest of the iteration in one C call
        if (one_call_serves(chains, x_prev, exists_prev, z, noise) and cells is not None and e_new is None
                and (kept or not on) and cache.is_contiguous()
                and _exchange_native.applies(delta, noise.u, cache, log_r, r_new, coords, coords_new)):
            pair = _source_term(noise, source, log_w_source, rho)
            return _one_call(chains, noise, proposal, delta, cells, change, exclusion if kept else None,
                             src_moved, lw_moved, None if pair is None else pair.to(log_lik.dtype),
                             base, eps_k)
        update = (cells, change)

    # the proposal's terms first (the slots that move are distinct: each reads its own current
    # terms), then the accepted moves written into the state, one select per field
    cur_y, cur_e, cur_ll = y, exists, log_lik
    log_prior = torch.zeros_like(log_lik)
    pair = _source_term(noise, source, log_w_source, rho)
    if pair is not None:
        log_prior = log_prior + pair.to(log_prior.dtype)
    cur_u = u_moved = None
    if on:
        if kept:  # read: the chains' from their state, the moved slots' from the segment's proposals
            cur_u, u_moved = coords, coords_new
        else:  # the chains' and the moved slots' coordinates, one call
            u_all = sensor.resolution_coords(torch.cat([y, moved], -2))
            cur_u, u_moved = u_all[..., :k, :], u_all[..., k:, :]
    if update is not None:  # by_terms, above
        cur_ll = log_lik + delta
    elif cache is not None:  # every moved slot at once, each cell of their boxes counted once
        delta, cells, change = sensor.log_likelihood_delta_cached(cache, y, moved, noise.slot, z, exists=exists,
                                                                  exists_n=e_new)
        cur_ll, update = log_lik + delta, (cells, change)
    heres = []
    for j in range(m):  # M = 1 or 2, static: the moved slots one after the other
        slot = noise.slot[..., j]  # (B, C)
        here = torch.arange(k, device=y.device) == slot.unsqueeze(-1)  # (B, C, K)
        heres.append(here)
        x_n, e_n = moved[:, :, j], None if e_new is None else e_new[:, :, j]
        if cache is None:
            cur_ll = sensor.log_likelihood_slot(cur_y, x_n, slot, z, cur_ll, exists=cur_e, exists_n=e_n)
        if exclusion is not None and cur_u is not None and u_moved is not None:  # the K - 1 factors of the slot
            log_prior = log_prior + exclusion.log_change(cur_u, u_moved[:, :, j], slot, cur_e, e_n)
            if j + 1 < m:  # the next slot's factors see this one moved
                cur_u = where(here.unsqueeze(-1), u_moved[:, :, j].unsqueeze(-2), cur_u)
        if log_r is not None:  # the slot's own cached ratio (distinct slots: none moved yet)
            at = slot.unsqueeze(-1)
            r_old = torch.gather(log_r, -1, at).squeeze(-1)
            if kind is not None and base != eps_k:
                r_old = _convert(r_old, torch.gather(kind, -1, at).squeeze(-1), base, eps_k)
            log_prior = log_prior + r_new[:, :, j] - r_old
        if j + 1 < m:  # the next slot's likelihood and factors see this one moved
            if cache is None:
                cur_y = where(here.unsqueeze(-1), x_n.unsqueeze(-2), cur_y)
            if cur_e is not None and e_n is not None:
                cur_e = where(here, e_n.unsqueeze(-1), cur_e)
    accepted = mh_accept(cur_ll - log_lik + log_prior, noise.u)
    if noise.valid is not None:
        accepted = accepted & noise.valid
    y_out, e_out, r_out, kind_out, src_out, lw_out = y, exists, log_r, kind, source, log_w_source
    u_out = coords if kept else None
    t_out = terms if by_terms else None
    for j, here in enumerate(heres):  # each moved slot written where its move is accepted
        take = here & accepted.unsqueeze(-1)  # (B, C, K)
        # the vector fields by their moved slot's row (its new or its old value): _write_row
        y_out = _write_row(y_out, noise.slot[..., j], moved[:, :, j], accepted, take)
        if e_out is not None and e_new is not None:
            e_out = where(take, e_new[:, :, j].unsqueeze(-1), e_out)
        if r_out is not None:
            k_j = None if kind_new is None else kind_new[:, :, j]
            r_out = where(take, _convert(r_new[:, :, j], k_j, eps_k, base).unsqueeze(-1), r_out)
            if kind_out is not None and k_j is not None:
                kind_out = where(take, k_j.unsqueeze(-1), kind_out)
        if src_out is not None and lw_out is not None:
            src_out = where(take, src_moved[..., j].unsqueeze(-1), src_out)
            lw_out = where(take, lw_moved[..., j].unsqueeze(-1).to(lw_out.dtype), lw_out)
        if u_out is not None and u_moved is not None:
            u_out = _write_row(u_out, noise.slot[..., j], u_moved[:, :, j], accepted, take)
        if t_out is not None and terms_new is not None:
            t_out = _write_row(t_out, noise.slot[..., j], terms_new[:, :, j], accepted, take)
    new = ExchangeChains(y_out, where(accepted, cur_ll, log_lik), e_out, r_out, kind_out, src_out, lw_out,
                         None, u_out, t_out)
    return new, accepted, update
