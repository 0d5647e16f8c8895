"""What the multitarget prior adds to the per-target motion: exclusion between slots and a
slot prior with a heavy tail (re-capture).

Why a factorised prior lets tracks coalesce
-------------------------------------------
With K fixed slots and a prior that factorises over slots (the IP-MCMC-PF's target, paper
000 sec. IV-B, and the joint SIR / MCMC-PF prior ``prod_n p(x_n | x^a_n)``), nothing in the
model says that two slots cannot be one target. Where two targets pass unresolved, both
slots can follow the stronger one: radar returns add coherently, so two slots that split
one target's amplitude explain the data as well as one slot does, and the weaker target is
then explained by no slot. A proposal that draws a slot only from its own prediction can
never bring it back once its prediction has moved away from the target (tens of metres,
hundreds of nats of prior). Two additions repair this, each a term of the filtering target
with its own invariance test:

Exclusion (Khan, Balch and Dellaert 2005)
-----------------------------------------
A pairwise Markov-random-field factor on the current multitarget state,

    ``Phi(x) = prod_{i < j, both alive} phi(d_ij)``,   ``phi(d) = 1 - exp(-d^2 / (2 s^2))``,

with ``d_ij`` the distance between slots ``i`` and ``j`` in **resolution cells** of the
sensor (:meth:`~torchmcmcpf.models.base.SensorModel.resolution_coords`: range, doppler and
bearing over their point-spread widths for the radar, the whitened position for point
sensors) and ``s`` the :class:`Exclusion` scale (1: one resolution cell). Two slots one
resolution cell apart keep 39 % of their prior weight, two cells 86 %, three 99 %; two slots
on top of each other have none. Following Khan et al. (their eq. 5, the MRF-augmented
filtering target), the factor multiplies the predictive density at the current time,

    ``pi_k(x) ∝ p(z_k | x) Phi(x) sum_a w^a p(x | x^a_{k-1})``,

not the transition (whose normaliser would then depend on ``x_{k-1}``). Every filter with
fixed slots targets this ``pi_k``: SIR and resample-move weigh by ``Phi``, the MCMC moves put
the ratio ``Phi(x') / Phi(x)`` in their acceptance (a one-slot move pays only the ``K - 1``
factors of the moved slot, :meth:`Exclusion.log_change`), the HMC moves add ``log Phi`` to
their potential. ``log phi`` is floored at :data:`LOG_PHI_FLOOR` so that two coincident slots
(a start state, say) give a finite, very low density rather than ``-inf - (-inf)``.

Re-capture: a heavy-tailed slot prior and a data-driven proposal
----------------------------------------------------------------
The slot prior gets a small *relocation* component (:class:`Recapture`): with probability
``delta = p_jump`` per slot and step the slot's target may be anywhere in the sensor's field
of view,

    ``f~(x_n | x^a_n) = (1 - delta) f(x_n | x^a_n) + delta p_0(x_n; x^a_n)``,

where a relocated slot keeps the coordinates the sensor does not measure from its own
prediction (the radar's tangential velocity and amplitude; the velocity of a point target)
and its measured coordinates ``u`` (range, doppler, bearing; or the position) are uniform
over the field of view: ``p_0`` is the push-forward of ``u ~ U(fov)`` and ``x_p ~ f(. |
x^a_n)`` through :meth:`~torchmcmcpf.models.base.SensorModel.place`. Proposals draw that
component with probability ``epsilon = p_propose`` and take ``u`` from the data-driven
density ``g(u | z_k)`` of :meth:`~torchmcmcpf.models.base.SensorModel.sample_from_data`
(peaks of the frame above a threshold for a grid sensor, the neighbourhood of a point for a
point sensor, mixed with a little of the uniform so that ``g > 0`` on the whole field of
view). Sampled with the component label ``c_n`` (motion or relocation) and the ancestor,
the target of slot ``n`` over its proposal is

    ``r_n = (1 - delta) / (1 - epsilon)``                       (motion),
    ``r_n = delta p_0(u_n) / (epsilon g(u_n | z_k))``           (relocation),

since everything else (the ancestor's weight, the prediction of the unmeasured coordinates,
the Jacobian of ``place``) is shared by target and proposal and cancels. This is the same
bookkeeping as births drawn near the data (:class:`~torchmcmcpf.models.existence.BirthDeath`,
``r_n = p_0 / q_0``), and the filters cache it the same way: one ``log r_n`` per slot, and
``log alpha`` gains ``sum (log r'_n - log r_n)`` over the slots a move changes. The heavy
tail makes the ratio finite for a slot whose prediction is far from its target; ``delta``
is small enough (1e-3 by default) that a tracked slot is relocated with negligible
posterior probability (its motion prior density at the target exceeds ``delta p_0`` by many
orders of magnitude), so the filters' accuracy on tracked targets is unchanged.

With births and deaths the relocation component applies to surviving slots only (a newborn
comes from the birth proposal, an inactive slot is ``x_death``).
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import TYPE_CHECKING, NamedTuple, TypeGuard

import torch

from .._native import applies
from .._native.select import packed_places, unpacked, where
from .._validation import check_positive, check_positive_int
from ..runtime import broadcast_shapes, pairwise_squared_distances, squared_norm
from ..typing import Tensor
from . import _exclusion_native

if TYPE_CHECKING:  # the sensor protocol is imported by the callers
    from .base import SensorModel

__all__ = ["Exclusion", "check_exclusion", "check_recapture", "Recapture", "RelocationNoise", "LOG_PHI_FLOOR",
           "relocate", "exclusion_on", "log_exclusion", "exclusion_change", "exclusion_against", "draw_relocation",
           "log_q_component", "log_q_ratio", "FIXED", "MOTION", "RELOCATED"]

#: Lower bound of ``log phi(d)`` (``phi = e^-50``): two coincident slots get a finite, very low
#: exclusion factor, so moves away from them have finite acceptance ratios (never NaN).
LOG_PHI_FLOOR = -50.0


def _probability(value: float, name: str, *, open_low: bool = False) -> float:
    v = float(value)
    if not (0.0 < v < 1.0 if open_low else 0.0 <= v < 1.0):
        interval = "(0, 1)" if open_low else "[0, 1)"
        raise ValueError(f"{name} must be a probability in {interval}, got {value!r}")
    return v


@dataclass(frozen=True)
class Exclusion:
    """Pairwise exclusion factor between target slots (Khan, Balch and Dellaert 2005; module
    docstring): ``phi(d) = 1 - exp(-d^2 / (2 scale^2))`` with ``d`` in resolution cells.

    Attributes
    ----------
    scale : > 0, the distance (in resolution cells) at which ``phi = 1 - e^{-1/2} = 0.39``.
    """

    scale: float = 1.0

    def __post_init__(self):
        object.__setattr__(self, "scale", check_positive(self.scale, "scale"))

    def log_phi(self, d2: Tensor) -> Tensor:
        """``log phi`` from squared distances ``d2`` (any shape), floored at
        :data:`LOG_PHI_FLOOR`.
        """
        # log phi ~ log(d^2 / 2 s^2) near 0: flooring the argument floors log phi, with a finite
        # (zero) gradient where it applies
        x = (d2 / (2.0 * self.scale**2)).clamp(min=math.exp(LOG_PHI_FLOOR))
        return torch.log(-torch.expm1(-x))

    def log_factor(self, u: Tensor, alive: Tensor | None = None) -> Tensor:
        """``log Phi`` of multitarget states given their resolution coordinates.

        Parameters
        ----------
        u : (*S, K, r) ``sensor.resolution_coords(x)``.
        alive : (*S, K) bool, optional: only pairs of live slots interact.

        Returns
        -------
        (*S,), dtype of ``u``; differentiable in ``u``.
        """
        k = u.shape[-2]
        if u.shape[-1] < 1:
            raise ValueError(f"u has shape {tuple(u.shape)}: expected at least one coordinate")
        if applies(u):  # the C loop: no (*S, P) tensors
            lead, r = tuple(u.shape[:-2]), u.shape[-1]
            rows = math.prod(lead)
            flags = None if alive is None else alive.expand(lead + (k,)).reshape(rows, k).to(torch.uint8)
            out = _exclusion_native.factor(u.reshape(rows, k, r).double(), flags, 1.0 / (2.0 * self.scale**2),
                                           math.exp(LOG_PHI_FLOOR))
            return out.reshape(lead).to(u.dtype)
        i, j = torch.triu_indices(k, k, 1, device=u.device)  # the K (K - 1) / 2 pairs i < j
        # the pairs' squared distances only, (*S, P): the two slots of each pair as rows, their
        # difference's squares added coordinate by coordinate (the values of
        # pairwise_squared_distances at [..., i, j], in 0.55 of the time)
        d2 = squared_norm(u.index_select(-2, i) - u.index_select(-2, j))
        # log_phi is floored (finite, zero slope at d = 0): the pairs of inactive slots are
        # dropped after it, as in log_change
        terms = self.log_phi(d2)
        if alive is not None:
            terms = where(alive.index_select(-1, i) & alive.index_select(-1, j), terms, 0.0)
        return terms.sum(-1)

    def log_change(self, u: Tensor, u_n: Tensor, n: Tensor, alive: Tensor | None = None,
                   alive_n: Tensor | None = None) -> Tensor:
        """``log Phi(x with slot n moved) - log Phi(x)``: the ``K - 1`` factors of slot ``n``.

        Parameters
        ----------
        u : (*S, K, r) resolution coordinates of the current states.
        u_n : (*S, r) the new coordinates of slot ``n``.
        n : (*S) int64, the slot that moves.
        alive : (*S, K) bool, optional, the current flags; alive_n : (*S) bool, slot n's new
            flag (defaults to its current one).

        Returns
        -------
        (*S,).
        """
        k = u.shape[-2]
        if applies(u):  # the C loop: no (*S, 2, K) tensor
            lead = broadcast_shapes(u.shape[:-2], n.shape)
            rows, r = math.prod(lead), u.shape[-1]

            def flat(t: Tensor, inner: tuple[int, ...], dtype: torch.dtype) -> Tensor:
                # (rows, *inner) in dtype: no expand where t has the shape already (a call each)
                t = t if tuple(t.shape) == lead + inner else t.expand(lead + inner)
                return t.reshape((rows,) + inner).to(dtype)

            out = _exclusion_native.change(flat(u, (k, r), torch.float64), flat(u_n, (r,), torch.float64),
                                           flat(n, (), torch.int64),
                                           None if alive is None else flat(alive, (k,), torch.uint8),
                                           None if alive_n is None else flat(alive_n, (), torch.uint8),
                                           1.0 / (2.0 * self.scale**2), math.exp(LOG_PHI_FLOOR))
            return out.reshape(lead).to(u.dtype)
        others = torch.arange(k, device=u.device) != n.unsqueeze(-1)  # (*S, K)
        u_old = torch.gather(u, -2, n.reshape(n.shape + (1, 1)).expand(n.shape + (1, u.shape[-1])))  # (*S, 1, r)
        # slot n before (row 0) and after (row 1) the move against every slot: one log_phi
        d2 = pairwise_squared_distances(torch.stack([u_old.squeeze(-2), u_n], -2), u)  # (*S, 2, K)
        if alive is None:
            on = others.unsqueeze(-2)
        else:
            a_old = torch.gather(alive, -1, n.unsqueeze(-1))  # (*S, 1)
            a_new = a_old if alive_n is None else alive_n.unsqueeze(-1)
            on = (others & alive).unsqueeze(-2) & torch.stack([a_old, a_new], -2)  # (*S, 2, K)
        # log_phi is floored (finite, zero slope below the floor at d = 0): the pairs off are
        # dropped after it, no mask before it (a move pays one select, not two)
        terms = where(on, self.log_phi(d2), 0.0)
        return (terms[..., 1, :] - terms[..., 0, :]).sum(-1)


def check_exclusion(exclusion: object) -> Exclusion | None:
    """``exclusion`` if it is an :class:`Exclusion` or None, else a ValueError naming it."""
    if exclusion is not None and not isinstance(exclusion, Exclusion):
        raise ValueError(f"exclusion must be an Exclusion or None, got {type(exclusion).__name__}")
    return exclusion


def check_recapture(recapture: object) -> Recapture | None:
    """``recapture`` if it is a :class:`Recapture` or None, else a ValueError naming it."""
    if recapture is not None and not isinstance(recapture, Recapture):
        raise ValueError(f"recapture must be a Recapture or None, got {type(recapture).__name__}")
    return recapture


def exclusion_on(exclusion: Exclusion | None, sensor: SensorModel) -> TypeGuard[Exclusion]:
    """Whether the exclusion term applies: it is set and the sensor declares a resolution
    (:attr:`~torchmcmcpf.models.base.SensorModel.resolved`); else every ``log Phi`` is 0.
    """
    return exclusion is not None and sensor.resolved


def log_exclusion(exclusion: Exclusion | None, sensor: SensorModel, x: Tensor, exists: Tensor | None = None
                  ) -> Tensor:
    """``log Phi(x)`` of states ``x (*S, K, D)`` (flags ``exists (*S, K)``) with the sensor's
    resolution: ``(*S,)``; zeros when ``exclusion`` is None or the sensor declares no
    resolution (:attr:`~torchmcmcpf.models.base.SensorModel.resolved`).
    """
    if exclusion_on(exclusion, sensor):
        return exclusion.log_factor(sensor.resolution_coords(x), exists)
    return torch.zeros(x.shape[:-2], dtype=x.dtype, device=x.device)


def exclusion_change(exclusion: Exclusion | None, sensor: SensorModel, x: Tensor, x_n: Tensor, n: Tensor,
                     exists: Tensor | None = None, exists_n: Tensor | None = None) -> Tensor:
    """``log Phi(x with slot n set to x_n) - log Phi(x)``: ``x (*S, K, D)``, ``x_n (*S, D)``,
    ``n (*S)`` int64, flags ``exists (*S, K)``, ``exists_n (*S)`` -> ``(*S,)`` (zeros when
    off, as :func:`log_exclusion`).
    """
    if exclusion_on(exclusion, sensor):
        u = sensor.resolution_coords(x)
        u_n = sensor.resolution_coords(x_n.unsqueeze(-2)).squeeze(-2)
        return exclusion.log_change(u, u_n, n, exists, exists_n)
    return torch.zeros(x.shape[:-2], dtype=x.dtype, device=x.device)


def exclusion_against(exclusion: Exclusion | None, sensor: SensorModel, x: Tensor, ref: Tensor) -> Tensor:
    """Each slot of ``x (B, *S, K, D)`` against the *other* slots of one reference state per
    run ``ref (B, K, D)``: ``sum_{l != k} log phi(d(x_k, ref_l))``, ``(B, *S, K)`` (the
    independent-partition filter's weights, whose other targets sit at the reference).
    Zeros when off (as :func:`log_exclusion`).
    """
    if not exclusion_on(exclusion, sensor):
        return torch.zeros(x.shape[:-1], dtype=x.dtype, device=x.device)
    u = sensor.resolution_coords(x)  # (B, *S, K, r)
    u_ref = sensor.resolution_coords(ref)  # (B, K, r)
    u_ref = u_ref.reshape(u_ref.shape[:1] + (1,) * (x.dim() - 3) + u_ref.shape[1:])
    d2 = pairwise_squared_distances(u, u_ref)  # (B, *S, K, K): slot k vs reference l
    k = x.shape[-2]
    others = ~torch.eye(k, dtype=torch.bool, device=x.device)
    terms = exclusion.log_phi(where(others, d2, torch.ones_like(d2)))
    return where(others, terms, torch.zeros_like(terms)).sum(-1)


@dataclass(frozen=True)
class Recapture:
    """The heavy-tailed slot prior and its data-driven proposal (module docstring).

    Attributes
    ----------
    p_jump : ``delta`` in (0, 1), the prior probability per slot and step that a slot's
        target is anywhere in the field of view (the relocation component); pass
        ``recapture=None`` to a filter for the paper's prior without it.
    p_propose : ``epsilon`` in (0, 1), the probability that a proposal draws a slot from the
        data instead of its prediction.
    pair_every : every ``pair_every``-th IP-MCMC iteration is a joint move of two slots whose
        predictions lie within ``pair_distance`` resolution cells of each other: both slots
        re-drawn together from their proposals (Kreucher, Kastella and Hero's coupled
        partitions), so two slots that block each other's one-slot moves can change places
        or separate in one step; 0 disables. A fixed schedule (not a random pick) keeps the
        sequence of kernels a constant of the step, so a captured CUDA graph is reused.
    pair_distance : > 0, resolution cells.
    p_propose_pair : ``epsilon`` of the two-slot move (both slots from the data with
        probability ``epsilon^2``: after two tracks have swapped their amplitudes in a
        crossing, only a joint move of both onto the two peaks repairs it). Each kernel
        scores the chains with its own ``epsilon`` (:func:`log_q_component`), so the mixture
        of one- and two-slot moves stays exact.
    p_same_source : ``rho`` in [0, 1), the probability that the two-slot move draws both
        slots from one previous particle (the pair's joint prediction) instead of two
        independent ones (:mod:`torchmcmcpf.kernels.exchange`, "The two-slot move's
        sources"): a pair of slots that only a few previous particles hold together (a
        repaired crossing) is then re-proposed together with probability ``rho w`` instead
        of ``w^2``. 0 gives independent sources.
    """

    p_jump: float = 1e-3
    p_propose: float = 0.1
    pair_every: int = 10
    pair_distance: float = 3.0
    p_propose_pair: float = 0.5
    p_same_source: float = 0.5

    def __post_init__(self):
        object.__setattr__(self, "p_jump", _probability(self.p_jump, "p_jump", open_low=True))
        object.__setattr__(self, "p_propose", _probability(self.p_propose, "p_propose", open_low=True))
        object.__setattr__(self, "pair_every", check_positive_int(self.pair_every, "pair_every", minimum=0))
        object.__setattr__(self, "pair_distance", check_positive(self.pair_distance, "pair_distance"))
        object.__setattr__(self, "p_propose_pair", _probability(self.p_propose_pair, "p_propose_pair",
                                                                open_low=True))
        object.__setattr__(self, "p_same_source", _probability(self.p_same_source, "p_same_source"))


class RelocationNoise(NamedTuple):
    """Pre-drawn randomness of the relocation component for slots ``(*S, K)``.

    Attributes
    ----------
    u : (*S, K) uniforms: a slot is proposed from the data where ``u < p_propose``.
    coords : (*S, K, r) measured coordinates drawn from ``g(. | z)``
        (:meth:`~torchmcmcpf.models.base.SensorModel.sample_from_data`).
    log_ratio : (*S, K) ``log p_0(coords) - log g(coords | z)`` where ``u`` is below the
        ``p_propose`` the noise was drawn for (:meth:`draw`), 0 elsewhere: :func:`relocate`
        reads it only where ``u < epsilon``, so a proposal with that ``epsilon`` or a smaller
        one may use the noise.
    """

    u: Tensor
    coords: Tensor
    log_ratio: Tensor

    @classmethod
    def draw(cls, shape: tuple[int, ...], sensor: SensorModel, z: object, *, generator: torch.Generator,
             dtype: torch.dtype, device: torch.device | str | None, p_propose: float = 1.0,
             found: object = None, packed: bool = False) -> RelocationNoise:
        """Draw for slots of ``shape = (B, *S, K)`` from the frame ``z`` (one per run), for
        proposals with ``epsilon <= p_propose``: ``g`` (a sum over the frame's points or
        peaks) is evaluated for those draws only (``u < p_propose``; 10 % at the default
        ``epsilon``), the same draws either way. ``found``: the frame's
        :meth:`~torchmcmcpf.models.base.SensorModel.frame_detections`, made once per step
        (None: the sensor finds them).

        ``packed``: the coordinates themselves are drawn for those slots only, each run's packed
        in order into one ``(B, W)`` block (:func:`~torchmcmcpf._native.select.packed_places`), and are
        0 elsewhere (never read: :func:`relocate`). The MCMC-PF draws a relocation for every
        slot of every move, a tenth of them read, and packs them; the IP-MCMC-PF's draws (one
        slot a chain and iteration) keep the dense stream its recorded studies ran on.
        """
        u = torch.rand(shape, generator=generator, device=device, dtype=dtype)
        # handed on only when there is something (a sensor that prepares nothing need not take it)
        extra = {} if found is None else {"found": found}
        if packed and p_propose < 1.0:
            b = shape[0]
            flags = (u < p_propose).reshape(b, -1)
            width, place = packed_places(flags)
            # at least one column, so that an empty draw still has the coordinates' shape
            block, block_ratio = sensor.sample_from_data(z, (b, max(width, 1)), generator=generator, dtype=dtype,
                                                         scored=None, **extra)
            coords, log_ratio = unpacked(block, place, flags, 0.0), unpacked(block_ratio, place, flags, 0.0)
            return cls(u, coords.reshape(tuple(shape) + coords.shape[-1:]), log_ratio.reshape(tuple(shape)))
        scored = None if p_propose >= 1.0 else u < p_propose
        coords, log_ratio = sensor.sample_from_data(z, shape, generator=generator, dtype=dtype, scored=scored,
                                                    **extra)
        return cls(u, coords, log_ratio)


def draw_relocation(recapture: Recapture | None, sensor: SensorModel | None, shape: tuple[int, ...], z: object, *,
                    generator: torch.Generator, dtype: torch.dtype, device: torch.device | str | None,
                    p_propose: float | None = None, found: object = None, packed: bool = False
                    ) -> RelocationNoise | None:
    """:class:`RelocationNoise` for slots of ``shape = (B, *S, K)`` from the frame ``z``, for
    proposals with ``epsilon <= p_propose`` (default ``recapture.p_propose``, that of
    :func:`relocate`), or None without ``recapture``; ``found``: the frame's detections made
    once per step, ``packed``: the coordinates drawn where read only (:meth:`RelocationNoise.draw`).
    """
    if recapture is None:
        return None
    if sensor is None or z is None:
        raise ValueError("recapture needs the sensor and the frame z to draw from the data")
    return RelocationNoise.draw(shape, sensor, z, generator=generator, dtype=dtype, device=device,
                                p_propose=recapture.p_propose if p_propose is None else p_propose, found=found,
                                packed=packed)


#: The component a slot was proposed from (:func:`relocate`): its prior density over its
#: proposal density does not depend on the proposal's ``epsilon`` (``FIXED``: inactive or
#: newborn), or carries a factor ``1 - epsilon`` (``MOTION``) or ``epsilon`` (``RELOCATED``).
FIXED, MOTION, RELOCATED = 0, 1, 2


def log_q_component(kind: Tensor, p_propose: float) -> Tensor:
    """``log`` of the proposal's component probability per slot: ``log(1 - epsilon)`` for a
    :data:`MOTION` slot, ``log epsilon`` for a :data:`RELOCATED` one, 0 otherwise. A slot's
    ``log r`` under a proposal of probability ``epsilon`` is its epsilon-free part minus this,
    so that kernels with different ``epsilon`` (the one- and two-slot moves) score the same
    chain state exactly. ``kind (*S, K)`` int8 -> ``(*S, K)`` float64.
    """
    return _by_kind(kind, math.log1p(-p_propose), math.log(p_propose))


def log_q_ratio(kind: Tensor, p_from: float, p_to: float) -> Tensor:
    """``log_q_component(kind, p_from) - log_q_component(kind, p_to)``, the same values (each
    kind's difference taken in float64 once, not per slot): what converts a slot's cached
    ``log r`` between two moves' ``epsilon``. ``kind (*S, K)`` int8 -> ``(*S, K)`` float64.
    """
    return _by_kind(kind, math.log1p(-p_from) - math.log1p(-p_to), math.log(p_from) - math.log(p_to))


def _by_kind(kind: Tensor, motion: float, jump: float) -> Tensor:
    """``motion`` where ``kind`` is :data:`MOTION`, ``jump`` where :data:`RELOCATED`, 0
    elsewhere, float64.
    """
    zero = torch.zeros(kind.shape, dtype=torch.float64, device=kind.device)
    return where(kind == MOTION, motion, where(kind == RELOCATED, jump, zero))


def relocate(x: Tensor, survive: Tensor | None, noise: RelocationNoise, recapture: Recapture,
             sensor: SensorModel, p_propose: float | None = None) -> tuple[Tensor, Tensor, Tensor]:
    """Apply the relocation component to propagated slots (pure, ``torch.compile`` friendly).

    Parameters
    ----------
    x : (*S, K, D) the slots predicted by the motion model (or born, or inactive).
    survive : (*S, K) bool, the slots alive before and after the step (``None``: all of them,
        a known number of targets); only they may be relocated.
    noise : :class:`RelocationNoise` with leading ``(*S, K)``.
    recapture : :class:`Recapture`; sensor : the sensor whose
        :meth:`~torchmcmcpf.models.base.SensorModel.place` sets the measured coordinates.
    p_propose : ``epsilon`` of this proposal (default ``recapture.p_propose``).

    Returns
    -------
    x : (*S, K, D) with the relocated slots placed at ``noise.coords``;
    log_ratio : (*S, K) ``log r_n`` of the module docstring (with this ``epsilon``) for every
    surviving slot, 0 for the others; kind : (*S, K) int8, :data:`MOTION`,
    :data:`RELOCATED` or :data:`FIXED` (not surviving).
    """
    eps = recapture.p_propose if p_propose is None else p_propose
    jump = noise.u < eps
    alive = torch.ones_like(jump) if survive is None else survive
    jump = jump & alive
    x = where(jump.unsqueeze(-1), sensor.place(x, noise.coords), x)
    kind = where(jump, RELOCATED, where(alive, MOTION, FIXED)).to(torch.int8)
    log_free = where(jump, math.log(recapture.p_jump) + noise.log_ratio,
                           torch.full_like(noise.log_ratio, math.log1p(-recapture.p_jump)))
    log_r = log_free - log_q_component(kind, eps).to(log_free.dtype)
    return x, where(alive, log_r, 0.0), kind
