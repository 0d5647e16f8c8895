"""The two model roles: motion (transition density) and sensor (likelihood).

Models hold parameters (buffers), never filtering state. Every method accepts any leading
dims ``(*S, K, D)`` and reduces only trailing ones, so one model serves particles
``(B, N, K, D)`` and chains ``(B, C, K, D)`` alike.
"""

from __future__ import annotations

import math
import weakref
from typing import Any, ClassVar, Generic, TypeVar

import torch
from torch import nn

from .. import runtime
from .._native import RowsLoop
from .._native.select import where
from .._validation import check_batch, check_finite, check_shape
from ..typing import Measurement, Tensor

__all__ = ["Motion", "MotionModel", "SensorModel", "linear_map", "check_reference"]


def linear_map(x: Tensor, M: Tensor) -> Tensor:
    """``x @ M.mT``: a small matrix ``M (d, D)`` applied to every row of ``x (B, ..., D)``
    -> ``(B, ..., d)``, the per-target linear maps of the motion and sensor models.

    On the CPU, BLAS is slow on a tall product with ``D`` and ``d`` of 2 to 5 columns: 1.6 ms
    for ``x (5e5, 4) @ (4, 4)`` on 2 cores, a third of the point-measurement SIR step
    (benchmarks/bench_stonesoup.py, groups ``linear-map-*``). There, ``g`` consecutive rows are read
    as one row of ``g * D`` columns and multiplied by the block-diagonal ``I_g (x) M^T``
    (``g * min(D, d)`` about 16): the extra terms are exact zeros, so each output is the same
    sum of ``D`` products (up to summation order), 2-8x faster (measured: 1.6 -> 0.54 ms at
    ``D = d = 4``, 1.3 -> 0.40 ms at ``D = 4, d = 2``). ``g`` divides the rows of one run
    (``prod(x.shape[1:-1])``), so a non-finite row can only affect rows of its own run,
    whose normalisation it already spoils. Under ``torch.compile`` the same block product is
    traced, so a compiled kernel calls the same BLAS product as eager code (the same bits:
    ``compile_step=True`` equals eager) at the grouped product's speed (a plain ``x @ M.mT``
    there cost the compiled point SIR step 4.6 of its 14 ms at B = 100, N = 5000). On other
    devices, or when no such ``g`` exists, it is ``x @ M.mT``.
    """
    M = M.to(x.dtype)
    d, D = M.shape
    g = 2 ** round(math.log2(16 / min(d, D))) if min(d, D) < 16 else 1
    rows = math.prod(x.shape[1:-1]) if x.dim() > 1 else 1
    while g > 1 and rows % g:
        g //= 2
    if g == 1 or not runtime.blocked_linear_map(x) or x.dim() < 2:
        return x @ M.mT
    return (x.reshape(-1, g * D) @ _block(M, g)).reshape(x.shape[:-1] + (d,))


def neighbourhood(t: Tensor, reduce: str, axes: int, radius: int = 1) -> Tensor:
    """Every cell of the last ``axes`` axes of ``t (*L, *G)`` reduced over its neighbourhood
    of ``2 radius + 1`` cells along each (stride 1, same shape): ``"max"`` (cells beyond the
    grid count as ``-inf``) or ``"mean"`` (as 0, divided by ``(2 radius + 1)^axes``: average
    pooling with ``count_include_pad``). One axis at a time (both reductions separate), so
    ``axes`` passes over ``2 radius + 1`` shifted copies replace the ``(2 radius + 1)^axes``
    reads of ATen's pooling (whose CPU ``max_pool3d`` took 4 ms of a 61,248-cell radar frame,
    the separable form 0.5). The grid sensors' peaks and centroids and the group filter's
    pixels near a detection.
    """
    if reduce not in ("max", "mean"):
        raise ValueError(f"reduce must be 'max' or 'mean', got {reduce!r}")
    if not 1 <= axes <= t.dim() or radius < 1:
        raise ValueError(f"expected 1 <= axes <= t.dim() = {t.dim()} and radius >= 1, got axes={axes}, "
                         f"radius={radius}")
    fill = float("-inf") if reduce == "max" else 0.0
    for axis in range(t.dim() - axes, t.dim()):
        size = t.shape[axis]
        edge = torch.full_like(t.narrow(axis, 0, 1), fill).expand(
            t.shape[:axis] + (min(radius, size),) + t.shape[axis + 1:])

        def shifted(by: int, t: Tensor = t, axis: int = axis, size: int = size, edge: Tensor = edge) -> Tensor:
            """``t`` moved by ``by`` cells along ``axis`` (entry i holds cell i + by), filled."""
            if by == 0:
                return t
            keep = max(size - abs(by), 0)
            pad = edge.narrow(axis, 0, min(abs(by), size))
            if by < 0:
                return torch.cat([pad, t.narrow(axis, 0, keep)], axis)
            return torch.cat([t.narrow(axis, size - keep, keep), pad], axis)

        out = shifted(-radius)
        for by in range(-radius + 1, radius + 1):  # the 2 radius + 1 cells of one axis, in order
            out = torch.maximum(out, shifted(by)) if reduce == "max" else out + shifted(by)
        t = out if reduce == "max" else out / float(2 * radius + 1)
    return t


#: id(M) -> (weak reference to M, its version, g, I_g (x) M^T): the block matrices of
#: :func:`linear_map`, built once per model matrix in eager code
_BLOCKS: dict[int, tuple] = {}


def _block(M: Tensor, g: int) -> Tensor:
    """``I_g (x) M^T`` ``(g D, g d)``, cached for a matrix that needs no gradient (a model's
    buffer): building it took three of a point SIR step's 85 operations, 10 % of a step at
    B = 1. Rebuilt when ``M`` changes in place (version counter); traced under ``torch.compile``.
    Made outside ``torch.inference_mode()`` (a normal tensor, which a later call under
    autograd may use).
    """
    if M.requires_grad or runtime.compiling() or M.is_inference():
        return torch.block_diag(*([M.mT] * g))
    hit = _BLOCKS.get(id(M))
    if hit is not None and hit[0]() is M and hit[1] == M._version and hit[2] == g:
        return hit[3]
    if len(_BLOCKS) > 256:  # matrices of dead models
        _BLOCKS.clear()
    with torch.inference_mode(False):
        block = torch.block_diag(*([M.mT] * g))
    _BLOCKS[id(M)] = (weakref.ref(M), M._version, g, block)
    return block


class Motion(nn.Module):
    """What every motion model declares to the filters: the per-target state size ``dim``
    and whether its slots are exchangeable (:attr:`exchangeable_slots`). The one base of
    motion models: :class:`MotionModel` (the same transition applied to every slot, which
    every filter but the group filter takes) and whole-configuration motions such as
    :class:`~torchmcmcpf.models.group.VirtualLeaderMotion` (the slots move jointly, a slot's
    label is its place in the group structure), which only the filter built for them takes
    (its bind function checks the motion's class). The :class:`~torchmcmcpf.filters.base.Filter`
    base reads :attr:`exchangeable_slots` to decide whether its estimate may relabel the
    particles' slots; nothing about a particular motion is a flag of the filter.

    Attributes
    ----------
    dim : int
        Per-target state size D (``x (B, N, K, D)``).
    exchangeable_slots : bool
        True (the default) where the motion treats every slot alike, so that a slot's label
        carries no meaning and the estimate may relabel the particles (Stephens 2000); False
        where a slot's label is part of the model.

    Example
    -------
    >>> import torchmcmcpf as tp
    >>> from torchmcmcpf.models.base import Motion
    >>> from torchmcmcpf.models.group import VirtualLeaderMotion
    >>> cv = tp.ConstantVelocity()
    >>> isinstance(cv, Motion), cv.dim, cv.exchangeable_slots          # a per-slot MotionModel
    (True, 4, True)
    >>> VirtualLeaderMotion.exchangeable_slots                         # labels are group places
    False
    """

    dim: int
    exchangeable_slots: ClassVar[bool] = True


class MotionModel(Motion):
    """Per-target Markov transition ``p(x_k | x_{k-1})``, applied to every slot alike.

    Subclasses implement :meth:`propagate` (deterministic given standard normal noise) and
    :meth:`log_prob`; :meth:`sample` draws the noise from the explicit generator. Splitting
    the draw from the map lets compiled kernels take pre-drawn noise (DESIGN.md) and lets
    HMC move the noise itself (Maroulas and Stinis 2010).

    Attributes
    ----------
    dim : int
        Per-target state size D.
    noise_dim : int
        Size of the standard normal noise one transition consumes per target.

    Example
    -------
    A Gaussian random walk in a few lines:

    >>> import torch
    >>> from torchmcmcpf.models.base import MotionModel
    >>> class RandomWalk(MotionModel):
    ...     def __init__(self, std: float):
    ...         super().__init__()
    ...         self.std, self.dim, self.noise_dim = std, 4, 4
    ...     def propagate(self, x, eps):
    ...         return x + self.std * eps
    ...     def log_prob(self, x_next, x):
    ...         return torch.distributions.Normal(x, self.std).log_prob(x_next).sum(-1)
    >>> motion = RandomWalk(0.5)
    >>> x = torch.zeros(2, 100, 3, 4)                       # (B, N, K, D)
    >>> x_next = motion.sample(x, generator=torch.Generator().manual_seed(0))
    >>> x_next.shape, motion.log_prob(x_next, x).shape      # per target slot
    (torch.Size([2, 100, 3, 4]), torch.Size([2, 100, 3]))
    """

    dim: int
    noise_dim: int

    def propagate(self, x: Tensor, eps: Tensor) -> Tensor:
        """Map ``x (*S, K, D)`` and standard normal ``eps (*S, K, noise_dim)`` to ``x_next``."""
        raise NotImplementedError

    def log_prob(self, x_next: Tensor, x: Tensor) -> Tensor:
        """``log p(x_next | x)`` per target: ``(*S, K, D), (*S, K, D) -> (*S, K)``."""
        raise NotImplementedError

    def sample(self, x: Tensor, *, generator: torch.Generator) -> Tensor:
        """Draw ``x_next ~ p(. | x)``: ``(*S, K, D) -> (*S, K, D)``."""
        eps = torch.randn(
            x.shape[:-1] + (self.noise_dim,), generator=generator, device=x.device, dtype=x.dtype
        )
        return self.propagate(x, eps)


#: The measurement type of a sensor (a :data:`~torchmcmcpf.typing.Measurement`): ``Tensor``
#: for the grid sensors, :data:`~torchmcmcpf.typing.PointMeasurement` for the point sensors.
Z = TypeVar("Z", bound=Measurement)


class SensorModel(nn.Module, Generic[Z]):
    """Measurement likelihood ``p(z_k | x_k)`` of a multitarget state.

    Subclasses implement :meth:`log_likelihood`, :meth:`simulate` and declare
    :attr:`frame_shape` (the trailing shape of one run's measurement, e.g. ``(Nr, Nd, Nb)``
    or ``(K, 2)``). :meth:`validate` then checks shape and values in eager code.

    The class is generic in its measurement type ``Z``: a grid sensor is a
    ``SensorModel[Tensor]``, a point sensor a ``SensorModel[PointMeasurement]``; filters and
    kernels, which pass measurements through, take any ``SensorModel``.

    Example
    -------
    A sensor that measures each slot's range, in a few lines (the fast paths keep their
    exact defaults):

    >>> import torch
    >>> from torchmcmcpf.models.base import SensorModel
    >>> class Range(SensorModel):
    ...     frame_shape = (None,)                           # (K,): one range per slot
    ...     def log_likelihood(self, x, z, exists=None):
    ...         r = x[..., [0, 2]].norm(dim=-1)             # (B, *S, K)
    ...         z = z.reshape(z.shape[:1] + (1,) * (r.dim() - 2) + z.shape[1:])
    ...         return -0.5 * (r - z).square().sum(-1)
    ...     def simulate(self, x, *, generator, exists=None):
    ...         r = x[..., [0, 2]].norm(dim=-1)
    ...         return r + torch.randn(r.shape, generator=generator)
    >>> sensor = Range()
    >>> truth = torch.tensor([[[3.0, 0.0, 4.0, 0.0]]])      # (B, K, D): 5 m away
    >>> z = sensor.simulate(truth, generator=torch.Generator().manual_seed(0))
    >>> z.shape
    torch.Size([1, 1])
    >>> sensor.log_likelihood(torch.zeros(1, 100, 1, 4), z).shape   # (B, N)
    torch.Size([1, 100])
    >>> sensor.log_likelihood(truth, torch.tensor([[6.0]]))         # 1 m from the true range
    tensor([-0.5000])
    >>> sensor.separable, sensor.resolved                   # optional hooks it does not declare
    (False, False)
    """

    #: trailing shape of one run's measurement; ``None`` entries match any size
    frame_shape: tuple[int | None, ...] = ()

    def log_likelihood(self, x: Tensor, z: Z, exists: Tensor | None = None) -> Tensor:
        """``log p(z | x)`` up to terms that do not depend on ``x``.

        Parameters
        ----------
        x : (B, *S, K, D) multitarget states.
        z : (B, *G) one frame per run.
        exists : (B, *S, K) bool, optional; absent slots contribute nothing.

        Returns
        -------
        (B, *S). Differentiable in ``x``.
        """
        raise NotImplementedError

    def simulate(
        self, x: Tensor, *, generator: torch.Generator, exists: Tensor | None = None
    ) -> Z:
        """Draw one frame per run from the true states ``x (B, K, D)``: ``-> (B, *G)``."""
        raise NotImplementedError

    # -- declared fast paths (optional; the defaults are exact and always available) -------
    def log_likelihood_per_target(self, x: Tensor, z: Z, exists: Tensor | None = None) -> Tensor:
        """Per-target terms ``(B, *S, K)`` with ``log_likelihood == per_target.sum(-1)``, term n
        depending on ``x[..., n, :]`` only. Only sensors whose targets do not interact
        override it (then :attr:`separable` is True); the default raises.
        """
        raise NotImplementedError(f"{type(self).__name__} has no per-target log-likelihood terms")

    @property
    def separable(self) -> bool:
        """Whether this sensor overrides :meth:`log_likelihood_per_target` (decided by method,
        static under ``torch.compile``).
        """
        return type(self).log_likelihood_per_target is not SensorModel.log_likelihood_per_target

    def log_likelihood_delta(self, x: Tensor, x_n: Tensor, n: int | Tensor, z: Z,
                             exists: Tensor | None = None, exists_n: Tensor | None = None) -> Tensor:
        """``log p(z | x with slot n set to x_n (, e_n)) - log p(z | x (, e))``: ``(B, *S)``.

        The default evaluates :meth:`log_likelihood` twice (exact); grid sensors override it
        with the cells near the old and new position of the slot only.

        Parameters
        ----------
        x : (B, *S, K, D) current states; x_n : (B, *S, D) the new state of slot ``n``.
        n : Python int, or (B, *S) int64 (one slot per sample).
        z : one frame per run; exists : (B, *S, K) bool, optional, current flags;
        exists_n : (B, *S) bool, optional, slot n's new flag (with ``exists``).
        """
        x_new, e_new = _set_slot(x, x_n, n, exists, exists_n)
        return self.log_likelihood(x_new, z, e_new) - self.log_likelihood(x, z, exists)

    def trim_frame(self, z: Z) -> Z:
        """The frame ``z`` without the padding that no run of the batch uses, for an eager step
        (:meth:`~torchmcmcpf.filters.base.Filter.step`): a frame padded to the widest frame of
        a whole sequence costs every step the padding's arithmetic. The same likelihoods and
        draws (to round-off: a reduction over fewer zeros may add in another order). The
        default: ``z`` itself (a frame of fixed shape has no padding).
        """
        return z

    #: whether a sequential sweep over the slots (the MCMC-PF's refinement) should build the
    #: :meth:`amplitude_cache` for itself: True where the cache is small beside the
    #: likelihood (the point sensor's ``M`` intensities per sample: the births/deaths MCMC-PF
    #: step 1.35-1.4x faster), False where building it costs more than the ``K`` local
    #: one-slot changes it saves (the grid sensors' dense per-cell grid: the compiled radar
    #: MCMC-PF step 0.33 against 0.30 s with it, N = 5000, K = 10). The IP-MCMC-PF builds it
    #: once per step and uses it for every iteration whatever this says.
    sweep_cache: bool = False

    def amplitude_cache(self, x: Tensor, exists: Tensor | None = None, z: Z | None = None) -> Tensor | None:
        """Per-sample state kept beside MCMC chains so that a one-slot move reads it instead
        of recomputing the other targets' contribution: grid sensors keep each sample's
        amplitude per cell, the point sensor each sample's Poisson intensity at every point of
        the frame ``z`` (a sensor whose cache depends on the frame needs ``z``); read by
        :meth:`log_likelihood_delta_cached`. ``None`` (the default): this sensor keeps none.
        """
        return None

    def log_likelihood_of_cache(self, cache: Tensor, x: Tensor, z: Z, exists: Tensor | None = None) -> Tensor:
        """:meth:`log_likelihood` of ``x (B, *S, K, D)`` from its :meth:`amplitude_cache`
        ``cache``, ``(B, *S)``: a sensor whose cache pays for a sweep (:attr:`sweep_cache`) makes
        the cache and the likelihood of a joint draw's states in one evaluation, and the chains
        keep the cache. The default: :meth:`log_likelihood` itself (a sensor whose likelihood
        is a function of its cache overrides it; the point sensor's is the log of it).
        """
        return self.log_likelihood(x, z, exists)

    def log_likelihood_delta_cached(self, cache: Tensor, x: Tensor, x_n: Tensor, n: Tensor, z: Z,
                                    exists: Tensor | None = None, exists_n: Tensor | None = None
                                    ) -> tuple[Tensor, Tensor | None, Tensor]:
        """:meth:`log_likelihood_delta` read from :meth:`amplitude_cache`, with the cache's
        change: ``(delta (B, *S), cells, change)`` for :meth:`update_amplitude_cache`; one
        slot (``x_n (B, *S, D)``, ``n`` broadcastable to ``(B, *S)``) or ``M`` distinct slots
        moved at once (``x_n (B, *S, M, D)``, ``n`` and ``exists_n`` ``(B, *S, M)``); ``cells``
        ``None`` when the change covers every entry of the cache in order (``change`` then of
        the cache's shape). Only sensors whose :meth:`amplitude_cache` is not ``None``
        implement it.
        """
        raise NotImplementedError(f"{type(self).__name__} keeps no amplitude cache")

    def move_terms(self, x: Tensor, exists: Tensor | None = None) -> Tensor | None:
        """What :meth:`log_likelihood_delta_terms` reads of each slot, ``(B, *S, K, T)``, so
        that a chain keeps it beside its states and a move of one slot reads a row instead
        of mapping the slot's old and new state again (a segment's proposals map theirs in
        one batched call); ``None`` (the default) where the sensor reads its moves from the
        states (:meth:`log_likelihood_delta_cached`). Elementwise in the slots: the terms of
        a slot depend on its state and flag only.
        """
        return None

    def log_likelihood_delta_terms(self, cache: Tensor, terms: Tensor, z: Z) -> tuple[Tensor, Tensor | None, Tensor]:
        """:meth:`log_likelihood_delta_cached` of a move of ``M`` distinct slots from their
        :meth:`move_terms`: ``terms (B, *S, 2M, T)`` the first moved slot's before and after,
        then the next's, ...; the same ``(delta, cells, change)``. Only
        sensors whose :meth:`move_terms` is not ``None`` implement it.
        """
        raise NotImplementedError(f"{type(self).__name__} reads its moves from the states")

    def log_likelihood_delta_rows(self, cache: Tensor, terms: Tensor, slot: Tensor, terms_new: Tensor, z: Z
                                  ) -> tuple[Tensor, Tensor | None, Tensor]:
        """:meth:`log_likelihood_delta_terms` of a move of the ``M`` distinct slots ``slot (B,
        *S, M)`` (int64) of states whose :meth:`move_terms` are ``terms (B, *S, K, T)``, to
        the rows ``terms_new (B, *S, M, T)``: the slots' rows gathered before the move,
        interleaved with the new ones. A sensor may read the rows in its own loop (the radar's
        C loop does); the same ``(delta, cells, change)``.
        """
        t, m = terms.shape[-1], slot.shape[-1]
        old = torch.gather(terms, -2, slot.unsqueeze(-1).expand(slot.shape + (t,)))  # (B, *S, M, T)
        return self.log_likelihood_delta_terms(cache, torch.stack([old, terms_new], -2).reshape(
            old.shape[:-2] + (2 * m, t)), z)

    def delta_rows_loop(self, terms: Tensor, z: Z) -> RowsLoop | None:
        """:meth:`log_likelihood_delta_rows` of one sample as a C entry
        (:class:`~torchmcmcpf._native.RowsLoop`), for a kernel whose own C loop calls it sample
        by sample (the IP-MCMC-PF's runs of one-slot moves,
        :func:`~torchmcmcpf.kernels.exchange_segment.exchange_run`), for samples whose
        :meth:`move_terms` are ``terms (B, *S, K, T)`` on frames ``z``; ``None`` (the default)
        where the sensor has no such entry. The same values as
        :meth:`log_likelihood_delta_rows` to the bit.
        """
        return None

    @staticmethod
    def update_amplitude_cache(cache: Tensor, cells: Tensor | None, change: Tensor, accepted: Tensor) -> Tensor:
        """``cache (B, *S, G)`` with the ``change`` of the ``accepted (B, *S)`` moves added at
        their ``cells`` (flat indices into ``cache``, the shape of ``change``, leading ``(B,
        *S)``; :meth:`log_likelihood_delta_cached`), or, with ``cells=None``, entry by entry
        (``change (B, *S, G)``, every entry of ``cache`` in order: the point sensor's
        intensities, a grid small enough to be moved on whole), in place; returns ``cache``.

        The one place the chain cache changes. It belongs to the chains (made for them at the
        start of a step, never shared), so adding in place is the functional update ``cache ->
        cache'`` without a copy per iteration (12 MB per run on the ground radar's 61,248 cells
        and 50 chains: the copy would cost about what the iteration does). Compiled or on a
        GPU, one scatter-add of every move's cells (one add over the whole cache without
        ``cells``), the rejected ones adding exact zeros: no host sync (no ``nonzero``), so it
        runs inside a captured CUDA graph as well; eager on a CPU, the accepted moves' rows
        only (:func:`~torchmcmcpf.runtime.host_reads`: the scatter is bound by its cache
        misses), the same bits. A sensor gives each cell at most one nonzero change per move,
        so the result does not depend on the order of the additions.
        """
        flat = accepted.numel()
        if runtime.host_reads(cache):  # eager CPU: the accepted rows only, in order (the same bits)
            rows = accepted.reshape(-1).nonzero().squeeze(-1)
            added = change.reshape(flat, -1)[rows]
            if cells is None:  # every entry in order: whole rows, no per-entry index
                cache.view(flat, -1).index_add_(0, rows, added)
            else:
                cache.view(-1).index_add_(0, cells.reshape(flat, -1)[rows].reshape(-1), added.reshape(-1))
            return cache
        keep = accepted.reshape(accepted.shape + (1,) * (change.dim() - accepted.dim()))
        added = where(keep, change, 0.0)
        if cells is None:
            return cache.add_(added.reshape(cache.shape))
        cache.view(-1).index_add_(0, cells.reshape(-1), added.reshape(-1))
        return cache

    def log_likelihood_slot_changes(self, ref: Tensor, x: Tensor, z: Z) -> Tensor:
        """Every slot of one reference state moved on its own: entry ``[b, *s, k]`` is
        ``log p(z | ref[b] with slot k set to x[b, *s, k]) - log p(z | ref[b])``.

        The weights of the independent-partition filter
        (:func:`~torchmcmcpf.filters.partitioned.partitioned_sir_body`). The default is
        exact: the difference of per-target terms for a :attr:`separable` sensor, else
        :meth:`log_likelihood_delta` with the reference repeated for every sample and slot
        (``K`` one-slot changes per sample); grid sensors override it with one amplitude grid
        of the reference and one box per slot (cost independent of ``K`` per slot).

        Parameters
        ----------
        ref : (B, K, D) the reference state of each run (every slot present).
        x : (B, *S, K, D) the candidate states, slot by slot.
        z : one frame per run.

        Returns
        -------
        (B, *S, K), dtype of ``x``.
        """
        B, K, D = check_reference(ref, x)
        S = tuple(x.shape[1:-2])
        if self.separable:
            at_ref = self.log_likelihood_per_target(ref[:, None], z)  # (B, 1, K)
            return self.log_likelihood_per_target(x, z) - at_ref.reshape((B,) + (1,) * len(S) + (K,))
        refs = ref.reshape((B,) + (1,) * len(S) + (1, K, D)).expand(x.shape[:-1] + (K, D))  # (B, *S, K, K, D)
        slots = torch.arange(K, device=x.device).expand(x.shape[:-1])  # (B, *S, K)
        return self.log_likelihood_delta(refs, x, slots, z)

    def log_likelihood_slot(self, x: Tensor, x_n: Tensor, n: int | Tensor, z: Z, log_lik: Tensor,
                            exists: Tensor | None = None, exists_n: Tensor | None = None) -> Tensor:
        """``log p(z | x with slot n set to x_n)`` given ``log_lik = log p(z | x)`` ``(B, *S)``
        (arguments as :meth:`log_likelihood_delta`): ``log_lik + delta`` when the sensor
        overrides :meth:`log_likelihood_delta`, else one full evaluation of the new state.
        """
        if type(self).log_likelihood_delta is not SensorModel.log_likelihood_delta:
            return log_lik + self.log_likelihood_delta(x, x_n, n, z, exists=exists, exists_n=exists_n)
        x_new, e_new = _set_slot(x, x_n, n, exists, exists_n)
        return self.log_likelihood(x_new, z, e_new)

    # -- the multitarget prior's hooks (models/multitarget.py) -----------------------------
    def resolution_coords(self, x: Tensor) -> Tensor:
        """The state in the sensor's measurement space in units of its resolution: ``(*S, K,
        D) -> (*S, K, r)``; two targets less than one unit apart are unresolved. The
        :class:`~torchmcmcpf.models.multitarget.Exclusion` factor is a function of these
        distances. The default raises (:attr:`resolved` is then False and the filters run
        without exclusion).
        """
        raise NotImplementedError(f"{type(self).__name__} declares no resolution_coords")

    @property
    def resolved(self) -> bool:
        """Whether this sensor overrides :meth:`resolution_coords` (decided by method)."""
        return type(self).resolution_coords is not SensorModel.resolution_coords

    def frame_detections(self, z: Z) -> Any:
        """What :meth:`sample_from_data` reads of the frame ``z`` beyond the frame itself (a
        grid sensor's peaks, found by CLEAN), made once per step by a filter that draws from
        the data several times and handed to every draw (``found=``); ``None`` (the default):
        nothing to prepare. A function of ``z`` alone: the draws are the same either way.
        """
        return None

    def sample_from_data(self, z: Z, shape: tuple[int, ...], *, generator: torch.Generator,
                         dtype: torch.dtype = torch.float32, scored: Tensor | None = None, found: Any = None
                         ) -> tuple[Tensor, Tensor]:
        """Measured coordinates drawn where the frame says targets may be (the data-driven
        density ``g(u | z)`` of :class:`~torchmcmcpf.models.multitarget.Recapture`).

        Parameters
        ----------
        z : one frame per run ``(B, *G)``; shape : ``(B, *S)``, the leading shape of the draws.
        generator : the only source of randomness; dtype : of the outputs.
        scored : (B, *S) bool, optional: the draws whose ``log_ratio`` is read (a proposal
            reads it only where it takes the data-driven component); ``log_ratio`` is 0
            elsewhere, so a sensor may skip evaluating ``g`` there. The draws do not depend
            on it.
        found : optional, :meth:`frame_detections` of ``z`` (made once per step); None: the
            sensor prepares the frame itself.

        Returns
        -------
        coords : (B, *S, r) measured coordinates (those :meth:`place` sets);
        log_ratio : (B, *S) ``log p_0(coords) - log g(coords | z)``, ``p_0`` uniform over the
        sensor's field of view (0 where ``scored`` is False).

        The default raises (:attr:`data_driven` is then False and the filters run without
        re-capture).
        """
        raise NotImplementedError(f"{type(self).__name__} has no data-driven proposal")

    def place(self, x: Tensor, coords: Tensor) -> Tensor:
        """``x (*S, D)`` with its measured coordinates set to ``coords (*S, r)`` and the
        others kept (the relocation map of :mod:`torchmcmcpf.models.multitarget`). Pure,
        differentiable.
        """
        raise NotImplementedError(f"{type(self).__name__} has no data-driven proposal")

    @property
    def data_driven(self) -> bool:
        """Whether this sensor overrides :meth:`sample_from_data` and :meth:`place`."""
        return self._overrides(SensorModel, "sample_from_data", "place")

    @classmethod
    def _overrides(cls, base: type, *names: str) -> bool:
        """Whether this class replaces each of the methods ``names`` of ``base`` (a data-driven
        sensor is one whose class fills the hooks its base declares).
        """
        return all(getattr(cls, name) is not getattr(base, name) for name in names)

    def validate_state(self, x: Tensor, name: str = "x") -> Tensor:
        """Check a state ``(B, *S, K, D)`` for values this sensor cannot score (eager, at the
        door). The default accepts every finite state; grid sensors refuse a negative
        signal (amplitude or power).
        """
        return x

    def validate(self, z: Z, batch_size: int | None = None, name: str = "z") -> Z:
        """Check one frame ``z (B, *G)``: shape, batch size, finite values. Returns ``z``.

        The default handles tensor measurements; sensors with tuple measurements (points
        and a mask) override it.
        """
        if not isinstance(z, torch.Tensor):
            raise ValueError(f"{name} must be a tensor (B, *G) for {type(self).__name__}, got {type(z).__name__}")
        check_shape(z, name, (None,) + tuple(self.frame_shape))
        if batch_size is not None:
            check_batch(z, name, batch_size)
        check_finite(z, name)
        return z


def check_reference(ref: Tensor, x: Tensor) -> tuple[int, int, int]:
    """Shapes of :meth:`SensorModel.log_likelihood_slot_changes`: ``ref (B, K, D)`` against
    ``x (B, *S, K, D)`` -> ``(B, K, D)``.
    """
    if x.dim() < 3:
        raise ValueError(f"x has shape {tuple(x.shape)}, expected (B, *S, K, D)")
    B, K, D = x.shape[0], x.shape[-2], x.shape[-1]
    if tuple(ref.shape) != (B, K, D):
        raise ValueError(f"ref has shape {tuple(ref.shape)}, expected {(B, K, D)} to match x {tuple(x.shape)}")
    return B, K, D


def _set_slot(x: Tensor, x_n: Tensor, n: int | Tensor, exists: Tensor | None, exists_n: Tensor | None
              ) -> tuple[Tensor, Tensor | None]:
    """``x`` with slot ``n`` (int, or (B, *S) int64) set to ``x_n (B, *S, D)`` (and its flag)."""
    slots = torch.arange(x.shape[-2], device=x.device)
    here = slots == (n.unsqueeze(-1) if isinstance(n, torch.Tensor) else n)  # (B, *S, K) or (K,)
    x_new = where(here.unsqueeze(-1), x_n.unsqueeze(-2), x)
    if exists is None:
        return x_new, None
    e_n = exists[..., 0] if exists_n is None else exists_n
    return x_new, where(here, e_n.unsqueeze(-1), exists)
