"""Chain states, the previous cloud and the pre-drawn noise of the sequential MCMC moves
(:mod:`torchmcmcpf.kernels.moves` describes the target and the moves).
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import NamedTuple

import torch

from .._native.select import packed_places, unpacked
from ..models.base import MotionModel, SensorModel
from ..models.existence import BirthNoise, TargetDynamics
from ..models.motion import LinearGaussianMotion
from ..models.multitarget import RelocationNoise
from ..resampling import GUIDED_POINTS, Guide, cdf, gather_particles, guide_table, inverse_cdf
from ..runtime import host_reads
from ..typing import Measurement, Tensor

__all__ = ["ChainState", "PreviousCloud", "previous_cloud", "draw_ancestors", "uniforms", "normals", "JointNoise",
           "RefineNoise", "evaluate", "evaluate_cached", "whiten"]


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
    log_ratio : (B, C, K), optional
        With existence or re-capture: ``log r_n``, the slot's target over proposal density
        ratio (``log p_0(x_n) - log q_0(x_n)`` for a slot born between the ancestor and
        ``x``; the relocation ratios of :mod:`torchmcmcpf.models.multitarget` for a
        surviving slot; 0 for an inactive one); ``None`` without either (module docstring
        of :mod:`torchmcmcpf.kernels.moves`).
    log_phi : ``(x, exists, log Phi (B, C))``, optional: the exclusion factor of the state,
        kept by an eager joint draw beside the very tensors ``x`` and ``exists`` it belongs to
        and read only while the chain holds those (a move that replaces ``x`` leaves it
        stale and it is recomputed; :func:`~torchmcmcpf.kernels.moves.joint_move`).
    cache : (B, C, *E), optional: the sensor's amplitude cache of ``x``
        (:meth:`~torchmcmcpf.models.base.SensorModel.amplitude_cache`) for a sensor whose cache
        pays for a sweep (:attr:`~torchmcmcpf.models.base.SensorModel.sweep_cache`: the point
        sensor's intensities ``(B, C, M)``): made with the likelihood of a joint draw's states
        (:func:`evaluate_cached`), advanced by the refinement sweep's accepted moves (to round-off the
        cache of ``x``); ``None`` where a move did not keep it (the sweep then makes its own).

    Example
    -------
    >>> import math
    >>> import torch
    >>> import torchmcmcpf as tp
    >>> from torchmcmcpf.kernels import JointNoise, init_chains, previous_cloud
    >>> from torchmcmcpf.models.existence import TargetDynamics
    >>> motion, sensor = tp.ConstantVelocity(dt=1.0, q=1.0), tp.LinearGaussian.position(noise_std=1.0)
    >>> dynamics, g = TargetDynamics(motion), torch.Generator().manual_seed(0)
    >>> cloud = previous_cloud(torch.zeros(2, 100, 3, 4), torch.full((2, 100), -math.log(100)), motion=motion)
    >>> like, z = torch.zeros(2, 8, 3, 4), torch.zeros(2, 3, 2)   # chains (B, C, K, D); a frame (B, K, 2)
    >>> chain = init_chains(cloud, JointNoise.draw(like, dynamics, generator=g), z, dynamics=dynamics, sensor=sensor)
    >>> chain.x.shape, chain.x_prev.shape, chain.log_lik.shape
    (torch.Size([2, 8, 3, 4]), torch.Size([2, 8, 3, 4]), torch.Size([2, 8]))
    >>> chain.log_lik_terms.shape, chain.exists              # a separable sensor; no existence model
    (torch.Size([2, 8, 3]), None)
    >>> torch.allclose(chain.log_lik, sensor.log_likelihood(chain.x, z))   # kept beside the state
    True
    """

    x: Tensor
    x_prev: Tensor
    log_lik: Tensor
    log_lik_terms: Tensor | None = None
    exists: Tensor | None = None
    exists_prev: Tensor | None = None
    log_ratio: Tensor | None = None
    log_phi: tuple[Tensor, Tensor | None, Tensor] | None = None
    cache: Tensor | None = None


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
    guide : :class:`~torchmcmcpf.resampling.Guide` of ``cdf``, optional (eager on a CPU): the
        guide table every ancestor draw of the frame reads (:func:`draw_ancestors`).

    Example
    -------
    >>> import math
    >>> import torch
    >>> import torchmcmcpf as tp
    >>> from torchmcmcpf.kernels import previous_cloud
    >>> from torchmcmcpf.kernels.chains import draw_ancestors
    >>> log_w = torch.log(torch.tensor([[0.5, 0.25, 0.25]]))             # (B, N)
    >>> cloud = previous_cloud(torch.zeros(1, 3, 2, 4), log_w, motion=tp.ConstantVelocity())
    >>> cloud.cdf, cloud.white_mean.shape                                # (B, N), (B, N, K * D)
    (tensor([[0.5000, 0.7500, 1.0000]], dtype=torch.float64), torch.Size([1, 3, 8]))
    >>> draw_ancestors(cloud, torch.tensor([[0.1, 0.6, 0.9]]))          # inversion of the weights
    tensor([[0, 1, 2]])
    """

    x: Tensor
    log_w: Tensor
    cdf: Tensor
    exists: Tensor | None = None
    white_mean: Tensor | None = None
    guide: Guide | None = None


def previous_cloud(x: Tensor, log_w: Tensor, exists: Tensor | None = None, *,
                   motion: MotionModel | None = None, draws: int = 0) -> PreviousCloud:
    """Build a :class:`PreviousCloud` from particles ``x (B, N, K, D)``, ``log_w (B, N)`` and
    optionally their existence flags ``exists (B, N, K)``. With a linear-Gaussian ``motion``
    the whitened predicted means are cached, so the random walk does not recompute them at
    every iteration of the frame. ``draws``: the ancestors one draw picks (``B C``); from
    :data:`~torchmcmcpf.resampling.GUIDED_POINTS` of them, eager on a CPU
    (:func:`~torchmcmcpf.runtime.host_reads`), the guide table of the draws is made too
    (:func:`~torchmcmcpf.resampling.guide_table`: the births/deaths MCMC-PF's 10,000 ancestors
    among 2,000 particles in 0.1 against 0.7 ms a draw by ``searchsorted``; the same indices).
    """
    white = whiten(motion.mean(x), motion) if isinstance(motion, LinearGaussianMotion) else None
    c = cdf(log_w)
    guided = draws >= GUIDED_POINTS and host_reads(x)
    return PreviousCloud(x, log_w, c, exists, white, guide_table(c) if guided else None)


def draw_ancestors(cloud: PreviousCloud, u: Tensor) -> Tensor:
    """Ancestor indices ``(B, C)`` with ``P(a) = w^a``, by inversion of uniforms ``u (B, C)``."""
    return inverse_cdf(cloud.cdf, u, cloud.guide)


def uniforms(shape: Sequence[int], x: Tensor, generator: torch.Generator) -> Tensor:
    """``U(0, 1)`` draws of ``shape`` with the dtype and device of ``x``."""
    return torch.rand(shape, generator=generator, device=x.device, dtype=x.dtype)


def normals(shape: Sequence[int], x: Tensor, generator: torch.Generator, where: Tensor | None = None) -> Tensor:
    """Standard normal draws of ``shape`` with the dtype and device of ``x``.

    With ``where`` (``shape[:-1]`` bool; eager on a CPU, :func:`~torchmcmcpf.runtime.host_reads`),
    the rows of the last dim are drawn where it is True only, in order, and 0 elsewhere: the
    motion noise of the slots whose ancestor is active, the only ones a move reads (an inactive
    ancestor's slot is born from its own candidate or stays at ``x_death``). Half the
    births/deaths scene's slots are inactive, and float64 ``randn`` is the step's costliest
    draw (PyTorch's CPU kernel draws one number at a time: 18-24 ns a number against 4 for
    ``rand``, AMD EPYC, one thread). Elsewhere every row is drawn (the same law). The rows are
    packed over all runs at once (one block, :func:`~torchmcmcpf._native.select.packed_places`),
    not per run as the newborns are (whose ratios read their run's points): nothing here is per
    run, and a per-run block is as wide as the fullest run, close to every slot with 10 runs
    batched; read back by :func:`~torchmcmcpf._native.select.unpacked` (one pass: 0.10 against
    0.38 ms besides the draws for ``(10, 1000, 5, 4)``, one thread).
    """
    if where is not None and tuple(where.shape) != tuple(shape[:-1]):
        raise ValueError(f"where has shape {tuple(where.shape)}, expected {tuple(shape[:-1])}")
    if where is None or not host_reads(x):
        return torch.randn(shape, generator=generator, device=x.device, dtype=x.dtype)
    flags = where.reshape(1, -1)
    count, place = packed_places(flags)  # all rows one block: the flagged rows' places in order
    drawn = torch.randn((count, shape[-1]), generator=generator, device=x.device, dtype=x.dtype)
    if count == 0:
        return torch.zeros(shape, device=x.device, dtype=x.dtype)
    return unpacked(drawn.unsqueeze(0), place, flags, 0.0).reshape(shape)


class JointNoise(NamedTuple):
    """Noise of one joint draw: ``u_ancestor (B, C)`` and ``u (B, C)`` uniforms, ``eps (B, C,
    K, noise_dim)`` standard normals (the transition noise of every target; drawn with the
    cloud's flags, eager on a CPU, 0 where the ancestor's slot is inactive: :func:`normals`), with existence
    ``birth`` (:class:`BirthNoise`) and with re-capture ``relocation``
    (:class:`~torchmcmcpf.models.multitarget.RelocationNoise`), leading ``(B, C, K)``; and
    ``ancestor (B, C)`` int64, the ancestors ``u_ancestor`` picks in the cloud when the draw
    read them (the newborn candidates' places), so the move does not search the cloud again.

    Example
    -------
    >>> import math
    >>> import torch
    >>> import torchmcmcpf as tp
    >>> from torchmcmcpf.kernels import JointNoise, init_chains, joint_move, previous_cloud
    >>> from torchmcmcpf.models.existence import TargetDynamics
    >>> motion, sensor = tp.ConstantVelocity(dt=1.0, q=1.0), tp.LinearGaussian.position(noise_std=1.0)
    >>> dynamics, g = TargetDynamics(motion), torch.Generator().manual_seed(0)
    >>> cloud = previous_cloud(torch.zeros(2, 100, 3, 4), torch.full((2, 100), -math.log(100)), motion=motion)
    >>> like, z = torch.zeros(2, 8, 3, 4), torch.zeros(2, 3, 2)   # chains (B, C, K, D); a frame (B, K, 2)
    >>> chain = init_chains(cloud, JointNoise.draw(like, dynamics, generator=g), z, dynamics=dynamics, sensor=sensor)
    >>> noise = JointNoise.draw(like, dynamics, generator=g)
    >>> noise.u_ancestor.shape, noise.eps.shape, noise.birth    # no existence model: no birth noise
    (torch.Size([2, 8]), torch.Size([2, 8, 3, 4]), None)
    >>> chain, accepted = joint_move(chain, noise, cloud=cloud, z=z, dynamics=dynamics, sensor=sensor)
    >>> accepted.shape, accepted.dtype                      # one accept/reject per chain
    (torch.Size([2, 8]), torch.bool)
    """

    u_ancestor: Tensor
    eps: Tensor
    u: Tensor
    birth: BirthNoise | None = None
    relocation: RelocationNoise | None = None
    ancestor: Tensor | None = None

    @classmethod
    def draw(cls, x: Tensor, dynamics: TargetDynamics, *, generator: torch.Generator,
             z: Measurement | None = None, relocation: RelocationNoise | None = None,
             cloud: PreviousCloud | None = None) -> JointNoise:
        """Draw for chains shaped like ``x (B, C, K, D)`` (dtype and device of ``x``) moved by
        ``dynamics``: the birth noise only with its existence model, the relocation noise only
        with its re-capture (both from the frame ``z``; ``relocation``, leading ``(B, C, K)``,
        when it was drawn beforehand). With the previous ``cloud`` (its flags ``exists``), the
        motion noise only where the drawn ancestor's slot is active and the newborn candidates
        only where it is inactive
        (:meth:`~torchmcmcpf.models.existence.BirthNoise.draw`).
        """
        b, c, k, _ = x.shape
        u_ancestor = uniforms((b, c), x, generator)
        a = exists = None
        if cloud is not None and cloud.exists is not None and dynamics.existence is not None:
            a = draw_ancestors(cloud, u_ancestor)
            exists = gather_particles(cloud.exists, a)
        eps, u = normals((b, c, k, dynamics.motion.noise_dim), x, generator, exists), uniforms((b, c), x, generator)
        return cls(u_ancestor, eps, u, *_slot_changes(x, dynamics, z, generator, relocation, exists), ancestor=a)


class RefineNoise(NamedTuple):
    """Noise of one refinement sweep: ``eps (B, C, K, noise_dim)`` normals (one proposal per
    slot; with the ancestors' flags and births, eager on a CPU, 0 where a slot's is inactive:
    :func:`normals`),
    ``u (B, C, K)`` uniforms (one accept/reject per slot) and, as in :class:`JointNoise`,
    ``birth`` and ``relocation``.

    Example
    -------
    >>> import math
    >>> import torch
    >>> import torchmcmcpf as tp
    >>> from torchmcmcpf.kernels import JointNoise, RefineNoise, init_chains, previous_cloud, refine_move
    >>> from torchmcmcpf.models.existence import TargetDynamics
    >>> motion, sensor = tp.ConstantVelocity(dt=1.0, q=1.0), tp.LinearGaussian.position(noise_std=1.0)
    >>> dynamics, g = TargetDynamics(motion), torch.Generator().manual_seed(0)
    >>> cloud = previous_cloud(torch.zeros(2, 100, 3, 4), torch.full((2, 100), -math.log(100)), motion=motion)
    >>> like, z = torch.zeros(2, 8, 3, 4), torch.zeros(2, 3, 2)   # chains (B, C, K, D); a frame (B, K, 2)
    >>> chain = init_chains(cloud, JointNoise.draw(like, dynamics, generator=g), z, dynamics=dynamics, sensor=sensor)
    >>> noise = RefineNoise.draw(like, dynamics, generator=g)
    >>> noise.eps.shape, noise.u.shape                      # one proposal and one uniform per slot
    (torch.Size([2, 8, 3, 4]), torch.Size([2, 8, 3]))
    >>> chain, accepted = refine_move(chain, noise, z=z, dynamics=dynamics, sensor=sensor)
    >>> accepted.shape                                      # (B, C, K)
    torch.Size([2, 8, 3])
    """

    eps: Tensor
    u: Tensor
    birth: BirthNoise | None = None
    relocation: RelocationNoise | None = None

    @classmethod
    def draw(cls, x: Tensor, dynamics: TargetDynamics, *, generator: torch.Generator,
             z: Measurement | None = None, relocation: RelocationNoise | None = None,
             exists: Tensor | None = None) -> RefineNoise:
        """Draw for chains shaped like ``x (B, C, K, D)`` (``dynamics``, ``z``, ``relocation``:
        as :meth:`JointNoise.draw`; ``exists (B, C, K)``, the flags of the chains' ancestors
        :attr:`ChainState.exists_prev`: the newborn candidates only where a slot's is inactive,
        the motion noise only where it is active).
        """
        slots = x.shape[:-1]  # (B, C, K)
        if exists is not None and dynamics.existence is None:
            exists = None  # without births every slot moves by the motion
        return cls(normals((*slots, dynamics.motion.noise_dim), x, generator, exists), uniforms(slots, x, generator),
                   *_slot_changes(x, dynamics, z, generator, relocation, exists))


def _slot_changes(x: Tensor, dynamics: TargetDynamics, z: Measurement | None, generator: torch.Generator,
                  relocation: RelocationNoise | None = None, exists: Tensor | None = None
                  ) -> tuple[BirthNoise | None, RelocationNoise | None]:
    """The noise every move draws after its own, for chains ``x (B, C, K, D)``: the births
    (with an existence model; candidates where a slot may be born, narrowed by the ancestors'
    flags ``exists`` when known), then the relocations (with re-capture; ``relocation`` when
    drawn beforehand).
    """
    births = dynamics.draw_births(x, z, generator=generator, exists=exists)
    if relocation is None:
        relocation = dynamics.draw_relocations(tuple(x.shape[:-1]), z, generator=generator, dtype=x.dtype,
                                               device=x.device)
    return births, relocation


# -- likelihood ------------------------------------------------------------------------------
def evaluate(x: Tensor, z: Measurement, sensor: SensorModel, exists: Tensor | None = None
             ) -> tuple[Tensor, Tensor | None]:
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


def evaluate_cached(x: Tensor, z: Measurement, sensor: SensorModel, exists: Tensor | None = None
                    ) -> tuple[Tensor, Tensor | None, Tensor | None]:
    """:func:`evaluate` with, for a sensor whose cache pays for a sweep
    (:attr:`~torchmcmcpf.models.base.SensorModel.sweep_cache`), the states' amplitude cache
    (:attr:`ChainState.cache`) and the likelihood read from it (the same bits): ``(log_lik (B,
    C), log_lik_terms (B, C, K) or None, cache (B, C, *E) or None)``.
    """
    cache = sensor.amplitude_cache(x, exists, z) if sensor.sweep_cache else None
    if cache is not None:
        return sensor.log_likelihood_of_cache(cache, x, z, exists), None, cache
    return (*evaluate(x, z, sensor, exists), None)


def whiten(v: Tensor, motion: LinearGaussianMotion) -> Tensor:
    """``L^-1 v`` per target, flattened: ``(B, M, K, D) -> (B, M, K * D)`` (``Q = L L^T``)."""
    L = motion.L.to(v.dtype)
    L_inv = torch.linalg.solve_triangular(L, torch.eye(L.shape[0], dtype=v.dtype, device=v.device), upper=False)
    return (v @ L_inv.mT).flatten(2)
