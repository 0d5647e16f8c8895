"""The public face of the grid sensors: :class:`SeparableGridSensor`.

It holds the grid (its axes' cell centres as buffers, the point-spread widths, the window)
and the subclass's model pieces, and dispatches each evaluation to the module of its
concern (see :mod:`torchmcmcpf.models.sensors.grid`).
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence

import torch

from .... import runtime
from ...._native import RowsLoop
from ...._validation import check_nonnegative, check_positive, check_positive_int, check_shape
from ....typing import Tensor
from ...base import SensorModel
from . import amplitudes, chunks, data, delta, native, slots, whole, window
from .geometry import GridGeometry, uniform_bins

__all__ = ["SeparableGridSensor"]

_METHODS = ("window", "grid")

#: the cell centres and the point-spread standard deviation of one axis (``None``: the cell
#: spacing), keyed by the name of the axis' buffer (e.g. ``"range_bins"``)
AxisSpec = tuple[Tensor | Sequence[float], float | None]


class SeparableGridSensor(SensorModel[Tensor]):
    """Base of the TBD sensors whose point spread is a separable Gaussian over a regular grid.

    A subclass declares its constructor with its own keywords (its axes' bins and widths, its
    noise parameter) and passes the axes here; it implements :meth:`measurement_coords`,
    :meth:`signal`, :meth:`cell_log_ratio` (optionally :meth:`prepare_frame`) and
    :meth:`simulate`.

    Parameters
    ----------
    axes : ``{buffer name: (bins, width)}`` in frame order (the radar's: ``"range_bins"``,
        ``"doppler_bins"``, ``"bearing_bins"``). ``bins (N_a,)``: the cell centres of the
        axis, increasing and uniformly spaced, stored as a float64 buffer of that name
        (computations follow the dtype of ``x``). ``width``: the point-spread standard
        deviation ``w_a`` in the axis' unit; ``None`` means the cell spacing (error messages
        call it ``<axis>_width``).
    window : int >= 0
        Half-width, in cells, of the box evaluated around each target by the windowed path.
    method : {"window", "grid"}
        What :meth:`log_likelihood` dispatches to.
    memory_budget : int, optional
        Bytes of temporaries either path may hold at once (:meth:`grid_chunk_size`,
        :meth:`window_chunk_size`); ``None`` (default): the process-wide
        :func:`~torchmcmcpf.runtime.memory_budget` (1 GiB unless set,
        ``--memory-budget`` on the command line).

    Example
    -------
    A range-only power sensor with exponential noise (Swerling I) in a few lines:

    >>> import torch
    >>> from torchmcmcpf.models.sensors.grid import SeparableGridSensor
    >>> class RangePower(SeparableGridSensor):
    ...     dim = 5                                           # [x, vx, y, vy, P]
    ...     def __init__(self, range_bins, noise_power=1.0):
    ...         super().__init__({"range_bins": (range_bins, None)}, window=2)
    ...         self.noise_power = noise_power
    ...     def measurement_coords(self, x):                  # (..., K, D) -> (..., K, 1)
    ...         return x[..., [0, 2]].norm(dim=-1, keepdim=True)
    ...     def signal(self, x):                              # (..., K, D) -> (..., K)
    ...         return x[..., 4]
    ...     def cell_log_ratio(self, A, zc):                  # exponential power of mean 1 + A
    ...         m = self.noise_power + A
    ...         return zc / self.noise_power - zc / m - torch.log(m / self.noise_power)
    ...     def simulate(self, x, *, generator, exists=None):
    ...         mean = self.noise_power + self.signal_grid(x, exists)   # (B, Nr)
    ...         return -mean * torch.rand(mean.shape, generator=generator).log()
    >>> sensor = RangePower(torch.arange(0.0, 100.0, 5.0))   # 20 cells of 5 m
    >>> truth = torch.tensor([[[30.0, 0.0, 40.0, 0.0, 20.0]]])   # (B, K, D): 50 m away, power 20
    >>> z = sensor.simulate(truth, generator=torch.Generator().manual_seed(0))
    >>> z.shape, z.argmax(-1)                               # the brightest cell: 50 m
    (torch.Size([1, 20]), tensor([10]))
    >>> x = truth.expand(1, 3, 1, 5).clone()                # (B, N, K, D): three particles
    >>> x[0, :, 0, 0] = torch.tensor([0.0, 30.0, 60.0])     # at 40, 50 and 72 m
    >>> sensor.log_likelihood(x, z).argmax(-1)              # the windowed path (the default)
    tensor([1])
    """

    #: per-target state size D; subclasses set it
    dim: int
    #: ``(N_1, ..., N_n)``, the cells per axis: a grid sensor knows every size
    frame_shape: tuple[int, ...]
    #: offsets of the cells of a box in the flattened frame (:meth:`GridGeometry.box_offsets`)
    box_offsets: Tensor
    #: temporaries per sample of the two paths, in grid or box cells (:mod:`.chunks`)
    _GRID_TEMPS = chunks.GRID_TEMPS
    _WINDOW_TEMPS = chunks.WINDOW_TEMPS

    def __init__(self, axes: Mapping[str, AxisSpec], *, window: int, method: str = "window",
                 memory_budget: int | None = None):
        super().__init__()
        origins, deltas, widths, names = [], [], [], []
        for name, (bins, width) in axes.items():
            centres, c0, spacing = uniform_bins(bins, name)
            self.register_buffer(name, centres)
            axis = name.removesuffix("_bins")
            if width is None:
                if centres.numel() == 1:
                    raise ValueError(f"{axis}_width must be given when {name} has a single cell")
                width = spacing
            widths.append(check_positive(width, f"{axis}_width"))
            origins.append(c0)
            deltas.append(spacing)
            names.append(name)
        self._bin_buffers = tuple(names)
        window = check_positive_int(window, "window", minimum=0)
        if method not in _METHODS:
            raise ValueError(f"method must be one of {_METHODS}, got {method!r}")
        self.method = method
        self.memory_budget = memory_budget  # type: ignore[assignment]  # the setter takes None
        self.frame_shape = tuple(int(self.get_buffer(n).numel()) for n in names)
        self.geometry = GridGeometry(self.frame_shape, tuple(origins), tuple(deltas), tuple(widths), window)
        self.register_buffer("box_offsets", self.geometry.box_offsets(), persistent=False)

    # ---------------------------------------------------------------- subclass hooks
    def measurement_coords(self, x: Tensor) -> Tensor:
        """Per-target measurement coordinates, one per grid axis: ``(..., K, D) -> (..., K, n)``."""
        raise NotImplementedError

    def signal(self, x: Tensor) -> Tensor:
        """Per-target signal spread by the point spread (amplitude or power): ``(..., K, D) -> (..., K)``."""
        raise NotImplementedError

    def prepare_frame(self, z: Tensor) -> Tensor:
        """Per-cell (elementwise) transform of the frame (e.g. ``sqrt(z)``);
        :meth:`cell_log_ratio` receives its output. Identity by default. ``(B, *G) -> (B, *G)``,
        or any shape: the moves' likelihood changes apply it to the cells they gather (two
        boxes a move) rather than to the whole frame, so it must act on each cell alone.
        """
        return z

    def native_ratio(self) -> tuple[str, float] | None:
        """The cell ratio as the C loop of :mod:`.native` knows it, or ``None`` (the default:
        every path uses :meth:`cell_log_ratio`). ``("rician", 1 / (2 sigma^2))`` declares
        ``cell_log_ratio(A, zc) = log I0(A zc) - A^2 / (2 sigma^2)``.
        """
        return None

    def cell_log_ratio(self, A: Tensor, zc: Tensor) -> Tensor:
        """``log p(z_c | A) - log p(z_c | 0)`` per cell; ``A`` and ``zc = prepare_frame(z)`` at
        the same cells broadcast together. Must be 0 where ``A = 0``.
        """
        raise NotImplementedError

    # ---------------------------------------------------------------- the grid
    @property
    def window(self) -> int:
        """Half-width, in cells, of the box of each target on the windowed paths."""
        return self.geometry.window

    @property
    def origins(self) -> tuple[float, ...]:
        """The first cell centre of each axis."""
        return self.geometry.origins

    @property
    def cell_sizes(self) -> tuple[float, ...]:
        """The cell spacing of each axis."""
        return self.geometry.cell_sizes

    @property
    def widths(self) -> tuple[float, ...]:
        """The point-spread standard deviation ``w_a`` of each axis."""
        return self.geometry.widths

    @property
    def n_axes(self) -> int:
        """Number of grid axes ``n`` (``len(frame_shape)``)."""
        return self.geometry.n_axes

    @property
    def num_cells(self) -> int:
        """Number of cells of one frame, ``N_1 * ... * N_n``."""
        return self.geometry.num_cells

    def bins(self, axis: int) -> Tensor:
        """Cell centres of ``axis``, ``(N_a,)``."""
        return self.get_buffer(self._bin_buffers[axis])

    def all_bins(self) -> tuple[Tensor, ...]:
        """Cell centres of every axis, in frame order."""
        return tuple(self.get_buffer(n) for n in self._bin_buffers)

    def window_sizes(self) -> tuple[int, ...]:
        """Cells per axis of one target's box: ``min(2 * window + 1, N_a)``."""
        return self.geometry.window_sizes

    def box_cells(self) -> tuple[int, ...]:
        """Layout of the cells of one box on the windowed paths (:attr:`GridGeometry.box_cells`)."""
        return self.geometry.box_cells

    @property
    def memory_budget(self) -> int:
        """Bytes of temporaries either path may hold at once: the sensor's own, or the
        process-wide :func:`~torchmcmcpf.runtime.memory_budget`.
        """
        return runtime.memory_budget() if self._memory_budget is None else self._memory_budget

    @memory_budget.setter
    def memory_budget(self, value: int | None) -> None:
        self._memory_budget = None if value is None else check_positive_int(value, "memory_budget")

    def grid_chunk_size(self, num_targets: int, dtype: torch.dtype = torch.float32) -> int:
        """Samples (rows of the flattened ``B * prod(S)``) per block of the whole-grid path
        (:func:`~.chunks.grid_chunk_size`).
        """
        return chunks.grid_chunk_size(self.geometry, self.memory_budget, num_targets, dtype)

    def window_chunk_size(self, num_targets: int, dtype: torch.dtype = torch.float32) -> int:
        """Samples per block of the windowed paths (:func:`~.chunks.window_chunk_size`)."""
        return chunks.window_chunk_size(self.geometry, self.memory_budget, num_targets, dtype)

    # ---------------------------------------------------------------- evaluation paths
    def log_likelihood(self, x: Tensor, z: Tensor, exists: Tensor | None = None) -> Tensor:
        """Sum over cells of :meth:`cell_log_ratio`, by ``self.method``.

        Parameters
        ----------
        x : (B, *S, K, D) multitarget states (any number of sample dims ``*S``).
        z : (B, *G) one frame per run (validate it once with :meth:`validate`).
        exists : (B, *S, K) bool, optional; an absent slot is the same as no slot (its
            state must still be finite).

        Returns
        -------
        (B, *S), dtype of ``x``; differentiable in ``x``.
        """
        if self.method == "grid":
            return self.log_likelihood_grid(x, z, exists)
        return self.log_likelihood_window(x, z, exists)

    def signal_grid(self, x: Tensor, exists: Tensor | None = None) -> Tensor:
        """Noise-free signal ``A`` in every cell (eq. 19 without noise and phase).

        Parameters
        ----------
        x : (B, *S, K, D); exists : (B, *S, K) bool, optional.

        Returns
        -------
        (B, *S, *G). Not chunked: meant for one frame per run (simulation, plots).
        """
        return whole.signal_grid(self, x, exists)

    def log_likelihood_grid(self, x: Tensor, z: Tensor, exists: Tensor | None = None) -> Tensor:
        """Reference: :meth:`cell_log_ratio` summed over every cell of the grid
        (:mod:`.whole`).

        ``A`` over the grid is ``sum_k s_k a_k(i_1) ... a_k(i_n)`` (per-axis profiles, one bmm).
        Blocks of at most :meth:`grid_chunk_size` rows of ``(B, prod(S))`` are processed at a time,
        so the forward temporaries stay within ``memory_budget`` whatever ``B``, ``S`` and the
        grid size; when ``x`` requires grad each block is checkpointed (recomputed in the
        backward pass), so the memory held for autograd is bounded by the same budget.

        Parameters
        ----------
        x : (B, *S, K, D); z : (B, *G); exists : (B, *S, K) bool, optional.

        Returns
        -------
        (B, *S).
        """
        return whole.log_likelihood(self, x, z, exists)

    #: On the windowed paths a box sums the truncated spreads of its own target and of the
    #: other targets whose boxes overlap it, in a fixed number of neighbour slots per box:
    #: eager, the most any box of the call has; under ``torch.compile`` (static shapes) this
    #: many, or every target (the dense form, ``K - 1`` neighbours) for a call in which some
    #: box has more. Exact either way (:func:`~.spread.with_neighbours`). Setting it to
    #: ``K - 1`` or more forces the dense form, the cost of the whole-grid-free path before
    #: neighbour slots (benchmarks/bench_likelihood.py compares both).
    max_neighbours: int = 3

    def log_likelihood_window(self, x: Tensor, z: Tensor, exists: Tensor | None = None) -> Tensor:
        """Fast path: the exact log-likelihood of the sensor with *truncated* point spreads
        (:mod:`.window`).

        Each target ``k`` gets a box of ``W_a = min(2 * window + 1, N_a)`` cells per axis,
        centred on its nearest cell and shifted to lie inside the grid, and its point spread
        is cut to that box: ``h~_k(c) = prod_a h_{k,a}(c_a) 1[c_a in box_{k,a}]``. Then
        ``A = sum_k e_k s_k h~_k`` vanishes outside the union of the boxes and the
        log-likelihood is the sum of :meth:`cell_log_ratio` over that union, computed box by
        box: at the cells of box ``j``, ``A`` sums the truncated spreads of target ``j`` and
        of the targets whose boxes overlap box ``j`` (the only ones nonzero there; at most
        :attr:`max_neighbours` of them on the fast form, all ``K`` otherwise), and a cell
        inside several boxes is counted once, by the first live box that holds it
        (:meth:`GridGeometry.owned_cells`: per-axis bit masks, three integer operations per
        cell). The cut drops ``h`` below ``exp(-(window + 1/2)^2 / 2)`` of the peak (2e-3 at
        ``window = 3`` and widths equal to the cell size): the difference to
        :meth:`log_likelihood_grid` is stated in the subclass (tests/models/test_radar.py).

        Because the spread is truncated the likelihood is local: moving one target changes
        only the cells of its old and new box, which :meth:`log_likelihood_delta` exploits.

        Cost per sample: ``K * (1 + M) * prod(W_a)`` multiply-adds (``M`` the neighbour
        slots, ``max_neighbours`` unless some box of the call overlaps more boxes) and
        ``K * prod(W_a)`` cell log-ratios, independent of the grid size. Blocks of at most
        :meth:`window_chunk_size` samples are processed at a time (checkpointed under
        autograd), so temporaries stay within ``memory_budget``. Arguments and result as
        :meth:`log_likelihood_grid`. On the CPU in float32 with no gradient to record, a sensor
        that declares its ratio (:meth:`native_ratio`: the radar) runs the same sum as one C
        loop per particle (:mod:`.native`: each overlapping target over the boxes'
        intersection only, to float32 round-off of the tensor form; no temporaries).
        """
        return window.log_likelihood(self, x, z, exists)

    def log_likelihood_delta(self, x: Tensor, x_n: Tensor, n: int | Tensor, z: Tensor,
                             exists: Tensor | None = None, exists_n: Tensor | None = None) -> Tensor:
        """Change of :meth:`log_likelihood_window` when slot ``n`` of ``x`` is set to ``x_n``
        (:mod:`.delta`).

        With truncated point spreads (see :meth:`log_likelihood_window`) only the cells of
        slot ``n``'s old box and of its new box change, so the difference is
        ``sum over box_old ∪ box_new of cell_log_ratio(A') - cell_log_ratio(A)`` (a cell in
        both boxes counted once), with ``A`` and ``A'`` the current and the new amplitude
        there: the spreads of slot ``n`` before and after the move and those of the other
        targets whose boxes overlap the box (at most :attr:`max_neighbours` on the fast
        form). Cost per sample: ``4 * (M + 2) * prod(W_a)`` multiply-adds and
        ``4 * prod(W_a)`` cell log-ratios, independent of ``K`` on the fast form. This is the
        ``log_likelihood_delta`` hook of :mod:`torchmcmcpf.kernels.moves` (per-target
        refinement) and of :func:`torchmcmcpf.kernels.exchange.exchange_iteration`; it equals
        ``log_likelihood_window(x') - log_likelihood_window(x)`` to round-off (tested).
        Branch-free under ``torch.compile`` (``torch.cond``). With ``method="grid"`` it is
        the difference of two :meth:`log_likelihood_grid` calls instead (consistent with
        :meth:`log_likelihood`, no speed-up).

        Parameters
        ----------
        x : (B, *S, K, D) current states.
        x_n : (B, *S, D) the new state of slot ``n``.
        n : int in ``[0, K)``, or an int64 tensor broadcastable to ``(B, *S)``: the slot moved
            in each sample (values not checked: no device sync).
        z : (B, *G) the frame.
        exists : (B, *S, K) bool, optional: existence of the current slots.
        exists_n : (B, *S) bool, optional: existence of slot ``n`` after the move (default: as
            before it).

        Returns
        -------
        (B, *S): ``log p(z | x with slot n = x_n) - log p(z | x)``.
        """
        return delta.log_likelihood_delta(self, x, x_n, n, z, exists, exists_n)

    def log_likelihood_slot_changes(self, ref: Tensor, x: Tensor, z: Tensor) -> Tensor:
        """Every slot of one reference state moved on its own (see
        :meth:`SensorModel.log_likelihood_slot_changes`): ``ref (B, K, D)``, ``x (B, *S, K,
        D)``, ``z (B, *G)`` -> ``(B, *S, K)``, equal to :meth:`log_likelihood_delta` of the
        windowed path with ``ref`` as the current state (tested; :mod:`.slots`).

        With truncated spreads (:meth:`log_likelihood_window`), let ``A`` be the reference's
        amplitude over the grid and ``T_k = A - s_k h~_{ref_k}`` the same without slot ``k``.
        Moving slot ``k`` to ``y`` changes ``sum_c l(A_c)`` by
        ``sum_c [l(T_k + s_y h~_y) - l(T_k)] - sum_c [l(A) - l(T_k)]`` (``l`` the
        :meth:`cell_log_ratio`), and both sums have the form
        ``term_k(y) = sum over box(y) of l(T_k + s_y h~_y) - l(T_k)`` (the summand vanishes
        outside ``box(y)``), so the change is ``term_k(x) - term_k(ref_k)``.

        ``A`` is one contraction over the grid per run (``K * G`` multiply-adds); a term
        gathers ``A`` and the frame at the cells of one box and evaluates two cell log-ratios
        there. Cost per sample and slot: ``2 * prod(W_a)`` cell log-ratios, whatever the
        number of targets near the box (the one-slot change with a current state per sample
        sums the neighbours' spreads box by box instead). With ``method="grid"``, the
        default (two whole-grid evaluations per slot).
        """
        if self.method == "grid":
            return super().log_likelihood_slot_changes(ref, x, z)
        return slots.log_likelihood_slot_changes(self, ref, x, z)

    # ---------------------------------------------------------------- the chain cache
    def amplitude_cache(self, x: Tensor, exists: Tensor | None = None, z: Tensor | None = None) -> Tensor | None:
        """Each sample's amplitude per cell, ``(B, *S, G)`` flat over the grid (truncated
        spreads, as :meth:`log_likelihood_window`; ``z`` is not read), for
        :meth:`log_likelihood_delta_cached`;
        ``None`` with ``method="grid"`` (the whole-grid reference has no truncated spreads).
        ``G * 4`` bytes per sample in float32 (244 kB on the ground radar's 87 x 22 x 32
        cells). :mod:`.amplitudes`.
        """
        if self.method == "grid":
            return None
        return amplitudes.amplitude_cache(self, x, exists)

    def log_likelihood_delta_cached(
        self, cache: Tensor, x: Tensor, x_n: Tensor, n: Tensor, z: Tensor,
        exists: Tensor | None = None, exists_n: Tensor | None = None,
    ) -> tuple[Tensor, Tensor | None, Tensor]:
        """:meth:`log_likelihood_delta` read from the samples' amplitudes
        (:meth:`amplitude_cache`) instead of summing the neighbours' spreads, for a move of
        one slot or of ``M`` distinct slots at once: the cells of each moved slot's old and
        new box hold ``A`` (gathered) and ``A'`` = ``A`` minus the moved slots' old spreads
        plus their new ones, each cell of the union of the ``2M`` boxes counted once. A
        one-slot move costs ``2 * prod(W_a)`` cells with two cell log-ratios each, whatever
        the number of targets nearby. Equal to :meth:`log_likelihood_delta` (one slot) and to
        the difference of two :meth:`log_likelihood_window` calls (``M`` slots) to round-off
        (tested).

        Parameters
        ----------
        cache : (B, *S, G) the amplitudes of ``x`` (kept current by
            :meth:`update_amplitude_cache`).
        x, z, exists : as :meth:`log_likelihood_delta`.
        x_n : (B, *S, D) the new state of slot ``n``, or (B, *S, M, D) those of ``M`` slots.
        n : int64 tensor broadcastable to (B, *S), or to (B, *S, M) with ``M`` slots
            (distinct within a sample; values not checked: no device sync).
        exists_n : (B, *S), or (B, *S, M), optional: the moved slots' new flags.

        Returns
        -------
        delta : (B, *S) ``log p(z | x with the slots moved) - log p(z | x)``.
        cells : (B, *S, 2M, *box_cells()) int64, flat indices into the ``(B, *S, G)`` cache of
            the cells of each moved slot's old and new box; change : the same shape, ``A' - A``
            there (0 at the cells an earlier box holds, so that each cell changes once), for
            :meth:`update_amplitude_cache`. On a grid with no more cells than the ``2M`` boxes
            (:func:`~.amplitudes.whole_grid`) the move is evaluated on the whole grid:
            ``cells`` is ``None`` and ``change`` ``(B, *S, G)``, every cell once, in order.
        """
        return amplitudes.log_likelihood_delta_cached(self, cache, x, x_n, n, z, exists, exists_n)

    def move_terms(self, x: Tensor, exists: Tensor | None = None) -> Tensor | None:
        """Each slot's measured coordinates and amplitude times its flag, ``(B, *S, K, n +
        1)``, where the C loop serves the cached moves (:func:`~.native.applies`; else
        ``None``): what :meth:`log_likelihood_delta_terms` reads. :mod:`.amplitudes`.
        """
        if self.method == "grid" or not native.applies(self, x):
            return None
        return amplitudes.move_terms(self, x, exists)

    def log_likelihood_delta_terms(self, cache: Tensor, terms: Tensor, z: Tensor
                                   ) -> tuple[Tensor, Tensor | None, Tensor]:
        """:meth:`log_likelihood_delta_cached` from the moved slots' :meth:`move_terms`
        ``(B, *S, 2M, n + 1)`` (each slot before, then after), by the C loop: the same values
        as from the states (the same bits where the terms are the states' mapped in the same
        layout).
        """
        return amplitudes.log_likelihood_delta_terms(self, cache, terms, z)

    def log_likelihood_delta_rows(self, cache: Tensor, terms: Tensor, slot: Tensor, terms_new: Tensor, z: Tensor
                                  ) -> tuple[Tensor, Tensor | None, Tensor]:
        """:meth:`log_likelihood_delta_terms` of the rows ``terms`` at ``slot (B, *S, M)``
        moved to ``terms_new (B, *S, M, n + 1)``, the rows read in the C loop (no gathered
        copy; the same values).
        """
        if terms.shape[-1] != 4:
            return super().log_likelihood_delta_rows(cache, terms, slot, terms_new, z)
        return amplitudes.log_likelihood_delta_rows(self, cache, terms, slot, terms_new, z)

    def delta_rows_loop(self, terms: Tensor, z: Tensor) -> RowsLoop | None:
        """:meth:`log_likelihood_delta_rows`' C loop as an entry for another C loop
        (:func:`.native.rows_loop`) where it serves these rows (:meth:`move_terms`' ``(B, *S,
        K, 4)``), else ``None``.
        """
        if terms.shape[-1] != 4 or not native.applies(self, terms):
            return None
        return native.rows_loop(self, z, terms[..., 0, 0].numel() // z.shape[0])

    # ---------------------------------------------------------------- multitarget prior hooks
    #: Threshold of the data-driven proposal on :meth:`detection_statistic`: a noise-only
    #: cell exceeds it with probability ``exp(-10) = 4.5e-5`` (about 3 cells of the ground
    #: radar's 61,248 per frame), the peak cell of a 10 dB target about half the time.
    detection_threshold: float = 10.0
    #: At most this many peaks per frame (the strongest) enter the data-driven density.
    max_peaks: int = 64
    #: Standard deviation of a proposal around a peak's centroid, in cells of each axis.
    peak_spread: float = 0.3
    #: Weight of the uniform part of the data-driven density (so that ``g > 0`` on the whole grid).
    uniform_weight: float = 0.05

    def resolution_coords(self, x: Tensor) -> Tensor:
        """:meth:`measurement_coords` over the point-spread widths: ``(*S, K, D) -> (*S, K, n)``
        (one unit is one standard deviation of the spread, the cell size by default).
        """
        widths = torch.tensor(self.widths, dtype=x.dtype, device=x.device)
        return self.measurement_coords(x) / widths

    def detection_statistic(self, z: Tensor) -> Tensor:
        """Per-cell statistic of the frame scaled so that a noise-only cell is ``Exp(1)``
        (the radar's power over ``2 sigma^2``, Swerling's over ``sigma^2``): ``(B, *G) ->
        (B, *G)``. Subclasses with a data-driven proposal implement it.
        """
        raise NotImplementedError(f"{type(self).__name__} declares no detection statistic")

    def detection_signal(self, stat: Tensor) -> Tensor:
        """The :meth:`detection_statistic` in the domain where the targets of a cell add, for
        the CLEAN of :meth:`detections`: here power, ``stat - 1`` (the noise mean off; a sensor
        whose frame is power over noise, such as Swerling's). Elementwise; inverse
        :meth:`detection_stat`.
        """
        return stat - 1.0

    def detection_stat(self, signal: Tensor) -> Tensor:
        """Inverse of :meth:`detection_signal`: ``signal + 1`` here."""
        return signal + 1.0

    @property
    def data_driven(self) -> bool:
        """Whether the subclass gives :meth:`detection_statistic` and :meth:`place`."""
        return self._overrides(SeparableGridSensor, "detection_statistic", "place")

    def peaks(self, z: Tensor) -> Tensor:
        """The cells at which :meth:`detections` finds its peaks (above
        :attr:`detection_threshold` after the stronger peaks' spreads are taken off):
        ``(B, *G)`` bool. A target gives about one peak, whatever its SNR (a strong target
        lights many cells above the threshold, but its spread is taken off as a whole).
        """
        return data.peaks(self, z)

    def detections(self, z: Tensor) -> tuple[Tensor, Tensor]:
        """The frame's :meth:`peaks` as points, by CLEAN (Hogbom 1974; :func:`.data.detections`):
        the strongest residual cell above the threshold, the centroid of the residual over its
        ``3^n`` neighbourhood, its fitted spread taken off, again; in the units of
        :meth:`measurement_coords`. A weak target beside a strong one (a shoulder of its
        spread, not a local maximum) is found once the strong one is taken off.

        Parameters
        ----------
        z : (B, *G).

        Returns
        -------
        centres : (B, P, n), the strongest ``P = min(max_peaks, G)`` peaks (padded);
        mask : (B, P) bool, True for a real peak.
        """
        return data.detections(self, z)

    def log_data_density(self, coords: Tensor, centres: Tensor, mask: Tensor) -> Tensor:
        """``log g(u | z)`` of :meth:`sample_from_data` at ``coords (B, *S, n)``, given the
        frame's :meth:`detections` ``centres (B, P, n)``, ``mask (B, P)``: ``(B, *S)``.
        """
        return data.log_data_density(self, coords, centres, mask)

    def frame_detections(self, z: Tensor) -> tuple[Tensor, Tensor]:
        """The frame's :meth:`detections` ``(centres (B, P, n), mask (B, P))``, what
        :meth:`sample_from_data` reads of it (``found=``): CLEAN, a loop over the peaks with
        host syncs, run once per step instead of once per draw.
        """
        return data.detections(self, z)

    def sample_from_data(self, z: Tensor, shape: tuple[int, ...], *, generator: torch.Generator,
                         dtype: torch.dtype = torch.float32, scored: Tensor | None = None,
                         found: tuple[Tensor, Tensor] | None = None) -> tuple[Tensor, Tensor]:
        """Measured coordinates from ``g(u | z) = (1 - p_u) (1/P) sum_p N(u; c_p, S) + p_u
        U(grid)``: a peak ``p`` of the frame drawn uniformly (:meth:`detections`: centroids
        ``c_p``; ``S`` diagonal, :attr:`peak_spread` cells per axis), or with probability
        ``p_u`` = :attr:`uniform_weight` (or for a frame without peaks) a point uniform over
        the grid. ``p_0`` is uniform over the grid's extent, so ``log_ratio = -log V -
        log g`` inside it (:meth:`log_data_density`) and ``-inf`` outside.

        Parameters
        ----------
        z : (B, *G) one frame per run; shape : ``(B, *S)``.
        generator : source of randomness; dtype : of the outputs.
        scored : (B, *S) bool, optional: ``g`` is evaluated where True only, ``log_ratio``
            is 0 elsewhere (the base method); the draws are the same.
        found : optional, :meth:`frame_detections` of ``z`` (made once per step); None: found
            here.

        Returns
        -------
        coords : (B, *S, n) in the units of :meth:`measurement_coords`;
        log_ratio : (B, *S).
        """
        return data.sample_from_data(self, z, shape, generator=generator, dtype=dtype, scored=scored, found=found)

    # ---------------------------------------------------------------- checks
    def validate_state(self, x: Tensor, name: str = "x") -> Tensor:
        """Refuse a negative signal (amplitude or power) in a state ``(..., K, D)``."""
        check_nonnegative(self.signal(x), f"{name} (signal component)")
        return x

    def validate(self, z: Tensor, batch_size: int | None = None, name: str = "z") -> Tensor:
        """Check one frame ``z (B, *G)``: shape, batch size, finite, non-negative. Returns ``z``."""
        check_shape(z, name, (None,) + tuple(self.frame_shape))
        if z.shape[0] == 0:
            raise ValueError(f"{name} has shape {tuple(z.shape)}: empty batch, expected B >= 1")
        super().validate(z, batch_size, name)
        return check_nonnegative(z, name)
