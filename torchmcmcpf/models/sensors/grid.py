"""Track-before-detect sensors on a separable cell grid: the shared machinery.

A TBD sensor of this family sees one value per cell of a regular grid ``*G = (N_1, ..., N_n)``
(range x doppler x bearing, azimuth x range, pixels). Target ``j`` maps to measurement
coordinates ``u_j`` (one per axis) and a signal ``s_j`` (amplitude or power), and spreads it
over the cells with a separable Gaussian point spread

    ``h(cell) = prod_a exp(-(c_a - u_{j,a})^2 / (2 w_a^2))``      (Bocquel et al. 2012, eq. 20)

so the signal in a cell is ``A(cell) = sum_j e_j s_j h_j(cell)`` (``e_j`` the existence flag).
Cells are independent given ``A``; a subclass gives the per-cell log-likelihood ratio
``cell_log_ratio(A, z)`` against "no target" (zero where ``A = 0``), and the sensor's
log-likelihood is its sum over cells.

:class:`SeparableGridSensor` evaluates that sum two ways:

- :meth:`~SeparableGridSensor.log_likelihood_grid`, the reference: every cell of the grid,
  ``A`` by a contraction of per-axis profiles, in chunks of the sample dims sized from
  ``memory_budget`` (autograd-checkpointed per chunk, so gradients stay within it too);
- :meth:`~SeparableGridSensor.log_likelihood_window`, the fast path: each target's point
  spread is truncated to a box of ``2 * window + 1`` cells per axis around its nearest cell,
  and the result is the exact log-likelihood of that truncated-spread sensor (a sum over the
  union of the boxes, a cell inside several boxes counted once). The truncation is the only
  approximation (spread values below ``exp(-(window + 1/2)^2 / 2)`` of the peak are dropped);
  with ``window`` at least the grid size the two paths agree to round-off. A box sums only
  the targets whose boxes overlap it (neighbour slots, see
  :attr:`~SeparableGridSensor.max_neighbours`), so the cost is ``O(N K W^n)``, not
  ``O(N K^2 W^n)``; blocks of samples sized from ``memory_budget``.
- :meth:`~SeparableGridSensor.log_likelihood_delta`: the change of the windowed
  log-likelihood when one target slot moves, from the cells of its old and new box only
  (the per-target refinement of the MCMC filter, the exchange move of IP-MCMC-PF), summing
  in each box slot ``n`` before and after the move and its overlapping neighbours.

Subclasses declare their axes and noise parameter (one base constructor serves all) and
implement :meth:`measurement_coords`, :meth:`signal`, :meth:`cell_log_ratio`
(optionally :meth:`prepare_frame`) and :meth:`simulate`.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Sequence
from typing import Any

import torch
from torch.utils.checkpoint import checkpoint
from typing_extensions import Self  # typing.Self needs Python 3.11; requires-python is 3.10

from ..._validation import check_nonnegative, check_positive, check_positive_int, check_shape
from ...resampling import cdf, inverse_cdf
from ...typing import Tensor
from ..base import SensorModel, _check_reference

__all__ = ["SeparableGridSensor", "polar", "lattice"]


def lattice(limits: tuple[float, float], cell: float, name: str) -> Tensor:
    """Uniform cell centres ``first + i * cell``, ``i = 0 .. floor((last - first) / cell)``.

    Parameters
    ----------
    limits : ``(first, last)``: the first centre and an upper limit (``last`` is included
        when it lies on the lattice).
    cell : cell size > 0.
    name : axis name for error messages (``f"{name}_limits"``, ``f"{name}_cell"``).

    Returns
    -------
    (N,) float64 centres.
    """
    check_positive(cell, f"{name}_cell")
    lo, hi = (float(v) for v in limits)
    if not (math.isfinite(lo) and math.isfinite(hi) and hi >= lo):
        raise ValueError(f"{name}_limits must be finite (first, last) with last >= first, got {limits!r}")
    n = int(math.floor((hi - lo) / cell + 1e-9)) + 1
    return lo + cell * torch.arange(n, dtype=torch.float64)


def polar(px: Tensor, py: Tensor) -> tuple[Tensor, Tensor, Tensor, Tensor]:
    """Range and bearing of positions seen from a sensor at the origin, safe at the origin.

    Parameters
    ----------
    px, py : (...) Cartesian position [m].

    Returns
    -------
    r, b : (...) range ``sqrt(x^2 + y^2)`` and bearing ``atan2(y, x)`` [rad];
    ux, uy : (...) the unit line-of-sight vector ``(x, y) / r``.

    A position within 1e-6 m of the sensor (e.g. an inactive slot parked at ``x_death = 0``)
    is mapped to range 0, bearing 0 and line of sight ``(1, 0)`` with zero gradient, so
    neither the values nor autograd produce NaN (``sqrt``, ``atan2`` and ``/ r`` all divide
    by zero there). Elsewhere the map is exact.
    """
    r2 = px * px + py * py
    far = r2 > 1e-12
    one = torch.ones_like(px)
    sx = torch.where(far, px, one)  # double-where: the unused branch gets no gradient
    sy = torch.where(far, py, torch.zeros_like(py))
    r = torch.sqrt(sx * sx + sy * sy)
    return torch.where(far, r, torch.zeros_like(r)), torch.atan2(sy, sx), sx / r, sy / r

_METHODS = ("window", "grid")


def materialise(t: Tensor) -> Tensor:
    """``t`` unchanged, but computed into its own buffer when compiled for the CPU.

    Inductor inlines a cheap pointwise tensor into each consumer; when the consumer is a
    vectorised per-cell loop whose index into ``t`` needs a division or modulo, the loop
    falls back to scalar code. A product with a ``1 x 1`` one runs as an extern gemm there,
    whose input and output are buffers of their own (exact: integers are converted to float32
    and back, and must stay below ``2**24`` in magnitude). Eager or on other devices: ``t``.
    """
    if not torch.compiler.is_compiling() or t.device.type != "cpu":
        return t
    value = t if t.is_floating_point() else t.to(torch.float32)
    one = torch.ones(1, 1, dtype=value.dtype, device=t.device)
    return torch.matmul(value.reshape(-1, 1), one).reshape(t.shape).to(t.dtype)


def _uniform_bins(bins: Tensor | Sequence[float], name: str) -> tuple[Tensor, float, float]:
    """Check 1-D, finite, strictly increasing, uniformly spaced cell centres.

    Returns the centres as a float64 tensor, the first centre and the spacing (1.0 for a
    single cell).
    """
    if not torch.is_tensor(bins):
        bins = torch.as_tensor(bins, dtype=torch.float64)
    if bins.dim() != 1 or bins.numel() == 0:
        raise ValueError(f"{name} has shape {tuple(bins.shape)}, expected (N,) with N >= 1 cell centres")
    bins = bins.detach().to(torch.float64)
    if not bool(torch.isfinite(bins).all()):
        raise ValueError(f"{name} contains NaN/inf; expected finite cell centres")
    if bins.numel() == 1:
        return bins, float(bins[0]), 1.0
    steps = torch.diff(bins)
    delta = float(steps.mean())
    if delta <= 0 or float((steps - delta).abs().max()) > 1e-6 * delta + 1e-9 * float(bins.abs().max()):
        raise ValueError(
            f"{name} must be strictly increasing with uniform spacing; got spacings between "
            f"{float(steps.min()):.6g} and {float(steps.max()):.6g}"
        )
    return bins, float(bins[0]), delta


class SeparableGridSensor(SensorModel[Tensor]):
    """Base of the TBD sensors whose point spread is a separable Gaussian over a regular grid.

    One constructor serves every subclass; a subclass declares its axes
    (:attr:`axis_names`), its noise parameter (:attr:`noise_name`), its default window and
    the default cell sizes of :meth:`uniform`, and documents the resulting keywords.

    Parameters
    ----------
    *bins : n 1-D tensors ``(N_a,)``, one per axis of :attr:`axis_names`
        Cell centres of each axis, increasing and uniformly spaced. Stored as buffers named
        ``f"{axis}_bins"`` (float64; computations follow the dtype of ``x``).
    window : int, optional
        Half-width, in cells, of the box evaluated around each target by the windowed path
        (default :attr:`default_window`).
    method : {"window", "grid"}
        What :meth:`log_likelihood` dispatches to.
    memory_budget : int
        Bytes of temporaries either path may hold at once (see :meth:`grid_chunk_size`,
        :meth:`window_chunk_size`).
    **settings
        ``f"{axis}_width"`` (float or ``None``): the point-spread standard deviation ``w_a``
        of each axis, in the axis' unit; ``None`` (default) means the cell spacing of that
        axis. ``noise_name`` (float > 0, default 1.0): the noise parameter of the subclass,
        stored as an attribute of that name. Any other keyword is a ``ValueError``.
    """

    #: grid axes in frame order; buffer and keyword names derive from them
    #: (``f"{axis}_bins"``, ``f"{axis}_width"``, ``f"{axis}_cell"``). Subclasses set it.
    axis_names: tuple[str, ...]
    #: keyword (and attribute) name of the subclass's noise parameter
    noise_name: str
    #: default ``window``
    default_window: int
    #: default cell size per axis of :meth:`uniform`
    default_cells: tuple[float, ...]

    #: per-target state size D; subclasses set it
    dim: int
    #: ``(N_1, ..., N_n)``, the cells per axis: a grid sensor knows every size
    frame_shape: tuple[int, ...]

    #: temporaries of one sample held at once by the whole-grid path, in units of the grid
    #: size G (the amplitude, the gathered frame term and the cell log-ratio with its
    #: intermediates, those of the float32 log I0 polynomial included), on top of the
    #: ``K * prod(N_1..N_{n-1})`` outer-product buffer.
    #: Checked against a measured peak in tests/models/test_radar.py.
    _GRID_TEMPS = 9

    def __init__(
        self,
        *bins: Tensor,
        window: int | None = None,
        method: str = "window",
        memory_budget: int = 2**30,
        **settings: float | None,
    ):
        super().__init__()
        names = self.axis_names
        if len(bins) != len(names):
            raise ValueError(
                f"{type(self).__name__} takes {len(names)} bin tensors ({', '.join(f'{a}_bins' for a in names)}), "
                f"got {len(bins)}"
            )
        widths = [settings.pop(f"{a}_width", None) for a in names]
        noise = settings.pop(self.noise_name, 1.0)
        if settings:
            raise ValueError(
                f"unexpected keyword(s) {sorted(settings)} for {type(self).__name__}; expected "
                f"{', '.join(f'{a}_width' for a in names)}, {self.noise_name}, window, method, memory_budget"
            )
        setattr(self, self.noise_name, check_positive(noise, self.noise_name))
        self.window = check_positive_int(self.default_window if window is None else window, "window", minimum=0)
        if method not in _METHODS:
            raise ValueError(f"method must be one of {_METHODS}, got {method!r}")
        self.method = method
        self.memory_budget = check_positive_int(memory_budget, "memory_budget")
        origins, deltas, ws = [], [], []
        for b, w, name in zip(bins, widths, names):
            b, c0, delta = _uniform_bins(b, f"{name}_bins")
            self.register_buffer(f"{name}_bins", b)
            if w is None:
                if b.numel() == 1:
                    raise ValueError(f"{name}_width must be given when {name}_bins has a single cell")
                w = delta
            ws.append(check_positive(w, f"{name}_width"))
            origins.append(c0)
            deltas.append(delta)
        self.origins = tuple(origins)
        self.cell_sizes = tuple(deltas)
        self.widths = tuple(ws)
        self.frame_shape = tuple(int(getattr(self, f"{n}_bins").numel()) for n in names)
        self.register_buffer("box_offsets", self._flat_box_offsets(), persistent=False)

    @classmethod
    def uniform(cls, *limits: tuple[float, float], **kw: Any) -> Self:
        """Uniform grid: one ``(first, last)`` per axis gives the first cell centre and an
        upper limit; centres are ``first + i * cell`` for ``i = 0 .. floor((last - first) /
        cell)`` (``last`` included when it lies on the lattice). Cell sizes by the keywords
        ``f"{axis}_cell"``, default :attr:`default_cells`; other keywords go to the
        constructor.
        """
        if len(limits) != len(cls.axis_names):
            raise ValueError(
                f"{cls.__name__}.uniform takes {len(cls.axis_names)} limits "
                f"({', '.join(f'{a}_limits' for a in cls.axis_names)}), got {len(limits)}"
            )
        cells = [kw.pop(f"{a}_cell", c) for a, c in zip(cls.axis_names, cls.default_cells)]
        return cls(*(lattice(lim, c, a) for lim, c, a in zip(limits, cells, cls.axis_names)), **kw)

    # ---------------------------------------------------------------- subclass hooks
    def measurement_coords(self, x: Tensor) -> Tensor:
        """Per-target measurement coordinates, one per grid axis: ``(..., K, D) -> (..., K, n)``."""
        raise NotImplementedError

    def signal(self, x: Tensor) -> Tensor:
        """Per-target signal spread by the point spread (amplitude or power): ``(..., K, D) -> (..., K)``."""
        raise NotImplementedError

    def prepare_frame(self, z: Tensor) -> Tensor:
        """Per-cell transform of the frame done once per call, before cells are gathered
        (e.g. ``sqrt(z)``); :meth:`cell_log_ratio` receives its output. Identity by default.
        ``(B, *G) -> (B, *G)``.
        """
        return z

    def cell_log_ratio(self, A: Tensor, zc: Tensor) -> Tensor:
        """``log p(z_c | A) - log p(z_c | 0)`` per cell; ``A`` and ``zc = prepare_frame(z)`` at
        the same cells broadcast together. Must be 0 where ``A = 0``.
        """
        raise NotImplementedError

    # ---------------------------------------------------------------- shared pieces
    @property
    def n_axes(self) -> int:
        """Number of grid axes ``n`` (``len(frame_shape)``)."""
        return len(self.frame_shape)

    @property
    def num_cells(self) -> int:
        """Number of cells of one frame, ``N_1 * ... * N_n``."""
        return math.prod(self.frame_shape)

    def bins(self, axis: int) -> Tensor:
        """Cell centres of ``axis``, ``(N_a,)``."""
        return getattr(self, f"{self.axis_names[axis]}_bins")

    def _check_inputs(self, x: Tensor, z: Tensor, exists: Tensor | None) -> None:
        # Shape checks only (no device sync): the hot path stays compile-friendly. Values
        # are checked once per frame by validate().
        self._check_state(x, exists)
        if z.dim() != 1 + self.n_axes or tuple(z.shape[1:]) != self.frame_shape or z.shape[0] != x.shape[0]:
            raise ValueError(
                f"z has shape {tuple(z.shape)}, expected ({x.shape[0]}, "
                f"{', '.join(map(str, self.frame_shape))}) to match x {tuple(x.shape)}"
            )

    def _check_state(self, x: Tensor, exists: Tensor | None) -> None:
        """Shapes of a state ``x (B, *S, K, D)`` and its flags ``exists (B, *S, K)``."""
        if x.dim() < 3 or x.shape[-1] != self.dim:
            raise ValueError(f"x has shape {tuple(x.shape)}, expected (B, *S, K, {self.dim})")
        if exists is not None and tuple(exists.shape) != tuple(x.shape[:-1]):
            raise ValueError(f"exists has shape {tuple(exists.shape)}, expected {tuple(x.shape[:-1])}")

    @staticmethod
    def _check_move(x: Tensor, x_n: Tensor, exists_n: Tensor | None) -> None:
        """Shapes of a one-slot move: ``x_n (B, *S, D)`` and ``exists_n (B, *S)`` against
        ``x (B, *S, K, D)``.
        """
        lead = tuple(x.shape[:-2])
        if tuple(x_n.shape) != lead + (x.shape[-1],):
            raise ValueError(f"x_n has shape {tuple(x_n.shape)}, expected {lead + (x.shape[-1],)} to match x "
                             f"{tuple(x.shape)}")
        if exists_n is not None and tuple(exists_n.shape) != lead:
            raise ValueError(f"exists_n has shape {tuple(exists_n.shape)}, expected {lead}")

    def _flat_inputs(self, x: Tensor, exists: Tensor | None) -> tuple[Tensor, Tensor, Tensor]:
        """``x (B, *S, K, D) -> u (B, P, K, n), s (B, P, K), e (B, P, K)`` with ``P = prod(S)``;
        ``s`` already multiplied by the existence flags ``e`` (float, dtype of ``x``).
        """
        B, K = x.shape[0], x.shape[-2]
        x = x.reshape(B, -1, K, x.shape[-1])
        u = self.measurement_coords(x)
        e = torch.ones_like(x[..., 0]) if exists is None else exists.reshape(B, -1, K).to(x.dtype)
        return u, self.signal(x) * e, e

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

    # ---------------------------------------------------------------- whole grid
    def _profiles(self, u: Tensor) -> list[Tensor]:
        """Per-axis point-spread profiles over every cell: ``u (..., K, n) -> [(..., K, N_a)]``."""
        out = []
        for a, w in enumerate(self.widths):
            c = self.bins(a).to(device=u.device, dtype=u.dtype)
            out.append(torch.exp(-((c - u[..., a, None]) ** 2) / (2.0 * w * w)))
        return out

    @staticmethod
    def _contract(s: Tensor, factors: Sequence[Tensor]) -> Tensor:
        """``sum_k s_k f_1[k, i_1] ... f_n[k, i_n]`` by outer products then one bmm.

        ``s (*L, K)``, ``factors[a] (*L, K, W_a)`` -> ``(*L, W_1, ..., W_n)``.
        """
        lead, K = s.shape[:-1], s.shape[-1]
        outer = s[..., None] * factors[0]
        for f in factors[1:-1]:
            outer = (outer[..., :, None] * f[..., None, :]).flatten(-2)
        if len(factors) == 1:
            out = outer.sum(-2)
        else:
            last = factors[-1]
            out = torch.bmm(
                outer.reshape(-1, K, outer.shape[-1]).mT, last.reshape(-1, K, last.shape[-1])
            )
        return out.reshape(*lead, *(f.shape[-1] for f in factors))

    def signal_grid(self, x: Tensor, exists: Tensor | None = None) -> Tensor:
        """Noise-free signal ``A`` in every cell (eq. 19 without noise and phase).

        Parameters
        ----------
        x : (B, *S, K, D); exists : (B, *S, K) bool, optional.

        Returns
        -------
        (B, *S, *G). Not chunked: meant for one frame per run (simulation, plots).
        """
        u, s, _ = self._flat_inputs(x, exists)
        A = self._contract(s, self._profiles(u))
        return A.reshape(x.shape[:-2] + self.frame_shape)

    def grid_chunk_size(self, num_targets: int, dtype: torch.dtype = torch.float32) -> int:
        """Samples (rows of the flattened ``B * prod(S)``) per chunk of the whole-grid path.

        One sample holds ``K * prod(N_1..N_{n-1})`` elements of outer products plus about
        ``_GRID_TEMPS * G`` elements of per-cell temporaries; the chunk is the largest count
        whose total stays within ``memory_budget`` bytes (at least 1).
        """
        itemsize = torch.empty((), dtype=dtype).element_size()
        per_sample = itemsize * (
            num_targets * math.prod(self.frame_shape[:-1]) + self._GRID_TEMPS * self.num_cells
        )
        return max(1, self.memory_budget // per_sample)

    def _grid_chunk(self, u: Tensor, s: Tensor, zc: Tensor) -> Tensor:
        """``u (b, p, K, n), s (b, p, K), zc (b, 1, *G)`` -> summed log ratio ``(b, p)``."""
        A = self._contract(s, self._profiles(u))
        return self.cell_log_ratio(A, zc).flatten(2).sum(-1)

    def log_likelihood_grid(self, x: Tensor, z: Tensor, exists: Tensor | None = None) -> Tensor:
        """Reference: :meth:`cell_log_ratio` summed over every cell of the grid.

        ``A`` over the grid is ``sum_k s_k a_k(i_1) ... a_k(i_n)`` (per-axis profiles, one bmm).
        Blocks of at most :meth:`grid_chunk_size` rows of ``(B, prod(S))`` are processed at a time,
        so the forward temporaries stay within ``memory_budget`` whatever ``B``, ``S`` and the
        grid size; when ``x`` requires grad each chunk is checkpointed (recomputed in the
        backward pass), so the memory held for autograd is bounded by the same budget.

        Parameters
        ----------
        x : (B, *S, K, D); z : (B, *G); exists : (B, *S, K) bool, optional.

        Returns
        -------
        (B, *S).
        """
        self._check_inputs(x, z, exists)
        B, K = x.shape[0], x.shape[-2]
        u, s, _ = self._flat_inputs(x, exists)  # (B, P, K, n), (B, P, K)
        P = u.shape[1]
        zc = self.prepare_frame(z.to(x.dtype))[:, None]  # (B, 1, *G), broadcast, never copied
        chunk = self.grid_chunk_size(K, x.dtype)
        runs = min(B, chunk)
        samples = max(1, chunk // runs)  # a chunk is runs x samples <= chunk rows
        grad = torch.is_grad_enabled() and x.requires_grad
        out = []
        for b in range(0, B, runs):  # chunks of rows, not a loop per particle or per run
            row = []
            for p in range(0, P, samples):
                args = (u[b : b + runs, p : p + samples], s[b : b + runs, p : p + samples], zc[b : b + runs])
                if grad:
                    row.append(checkpoint(self._grid_chunk, *args, use_reentrant=False))
                else:
                    row.append(self._grid_chunk(*args))
            out.append(torch.cat(row, 1))
        return torch.cat(out).reshape(x.shape[:-2])

    # ---------------------------------------------------------------- windowed fast path
    #: On the windowed paths a box sums the truncated spreads of its own target and of the
    #: other targets whose boxes overlap it, in a fixed number of neighbour slots per box:
    #: eager, the most any box of the call has; under ``torch.compile`` (static shapes) this
    #: many, or every target (the dense form, ``K - 1`` neighbours) for a call in which some
    #: box has more. Exact either way (see :meth:`_select`). Setting it to ``K - 1`` or more
    #: forces the dense form, the cost of the whole-grid-free path before neighbour slots
    #: (benchmarks/bench_likelihood.py compares both).
    max_neighbours: int = 3

    def window_sizes(self) -> tuple[int, ...]:
        """Cells per axis of one target's box: ``min(2 * window + 1, N_a)``."""
        return tuple(min(2 * self.window + 1, n) for n in self.frame_shape)

    def _box_first(self, ua: Tensor, axis: int) -> Tensor:
        """First cell (float index) of the box on ``axis`` of targets at coordinates ``ua``:
        the nearest cell minus ``window``, shifted to lie inside the grid. Same shape as ``ua``.
        """
        N, W = self.frame_shape[axis], self.window_sizes()[axis]
        nearest = torch.round((ua.detach() - self.origins[axis]) / self.cell_sizes[axis])
        return (nearest - self.window).clamp(0, N - W)

    def _overlaps(self, box_firsts: Sequence[Tensor], firsts: Sequence[Tensor]) -> Tensor:
        """Whether box ``q`` (first cells ``box_firsts[a] (..., Q)``) and the box of target ``k``
        (``firsts[a] (..., T)``) share a cell: ``(..., Q, T)`` bool.
        """
        near = [(bq[..., :, None] - fk[..., None, :]).abs() < W
                for bq, fk, W in zip(box_firsts, firsts, self.window_sizes())]
        out = near[0]
        for other in near[1:]:
            out = out & other
        return out

    def _neighbour_profiles(
        self, box_firsts: Sequence[Tensor], u: Tensor, firsts: Sequence[Tensor], index: Tensor
    ) -> tuple[list[Tensor], list[Tensor]]:
        """Truncated per-axis profiles of selected targets at the cells of boxes ``q``.

        ``box_firsts[a] (..., Q)`` first cells of the boxes evaluated; ``u (..., T, n)`` and
        ``firsts[a] (..., T)`` the targets' coordinates and box starts; ``index (..., Q, M)``
        int64 the targets evaluated in each box. Returns, per axis, ``profile (..., Q, M, W)``:
        the Gaussian of target ``index[q, m]`` at cell ``t`` of box ``q`` times the indicator
        that the cell lies in the target's box, and that indicator ``(..., Q, M, W)`` (0/1,
        dtype of ``u``); both lists in the :meth:`box_cells` layout (the last two axes as one
        factor ``(..., Q, M, W_{n-1} W_n)``).
        """
        Q = index.shape[-2]

        def pick(v: Tensor) -> Tensor:  # (..., T) -> (..., Q, M): the selected targets' values per box
            return torch.take_along_dim(v[..., None, :].expand(*v.shape[:-1], Q, v.shape[-1]), index, -1)

        profiles, indicators = [], []
        for a, (bq, fk, W) in enumerate(zip(box_firsts, firsts, self.window_sizes())):
            ua, first = pick(u[..., a]), pick(fk)  # (..., Q, M)
            c0, delta = self.origins[a], self.cell_sizes[a]
            scale = 1.0 / (math.sqrt(2.0) * self.widths[a])
            offsets = torch.arange(W, device=u.device, dtype=u.dtype)
            centre = (c0 + delta * (bq[..., None] + offsets)) * scale  # (..., Q, W)
            dist = centre[..., None, :] - (ua * scale)[..., None]  # (..., Q, M, W)
            # cell t of box q lies in the box of target k iff 0 <= first_q - first_k + t < W
            lag = (bq[..., None] - first)[..., None] + offsets  # (..., Q, M, W)
            inside = ((lag >= 0) & (lag < W)).to(u.dtype)
            profiles.append(torch.exp(-dist.square()) * inside)
            indicators.append(inside)
        return self._merge_last(profiles), self._merge_last(indicators)

    #: Neighbour slots up to which :meth:`_outer_sum` adds the terms one by one (fused into
    #: one loop by ``torch.compile``); above it, outer products and one bmm (faster for many
    #: slots, eager or compiled: measured on the crowded ground-radar scene).
    _TERMWISE_MAX = 4

    @classmethod
    def _outer_sum(cls, s: Tensor, factors: Sequence[Tensor]) -> Tensor:
        """``sum_m s_m f_1[m, i_1] ... f_n[m, i_n]``.

        ``s (*L, M)``, ``factors[a] (*L, M, W_a)`` -> ``(*L, W_1, ..., W_n)``. On the CPU, up
        to ``_TERMWISE_MAX`` neighbour slots the sum is written out term by term, so that
        ``torch.compile`` fuses the whole per-cell computation into one loop (a reduction
        over ``M`` would be materialised); above it, outer products of the first ``n - 1``
        factors then one bmm with the last. On a GPU, the broadcast product summed over ``M``.
        """
        n, M = len(factors), s.shape[-1]

        def product(w: Tensor, fs: Sequence[Tensor]) -> Tensor:  # w (*J) f_1 ... f_n -> (*J, W_1, ..., W_n)
            t = w.reshape(w.shape + (1,) * n)
            for a, f in enumerate(fs):
                t = t * f.reshape(f.shape[:-1] + (1,) * a + f.shape[-1:] + (1,) * (n - 1 - a))
            return t

        if s.device.type == "cuda":
            # on a GPU, one broadcast product summed over M (fused by torch.compile): the bmm
            # below would be tens of thousands of tiny matrices, which cuBLAS runs at a few
            # percent of the card (its gemms were 70 % of the IP-MCMC-PF's GPU time on an
            # H200, benchmarks/README.md)
            return product(s, factors).sum(-n - 1)
        if M > cls._TERMWISE_MAX:
            outer = s[..., None] * factors[0]
            for f in factors[1:-1]:
                outer = (outer[..., :, None] * f[..., None, :]).flatten(-2)
            lead = outer.shape[:-2]  # broadcast of the leading dims of s and the factors
            if n == 1:
                out = outer.sum(-2)
            else:
                last = factors[-1].expand(lead + factors[-1].shape[-2:])
                out = torch.bmm(outer.reshape(-1, M, outer.shape[-1]).mT, last.reshape(-1, M, last.shape[-1]))
            return out.reshape(*lead, *(f.shape[-1] for f in factors))

        def term(m: int) -> Tensor:  # s_m f_1[m, i_1] ... f_n[m, i_n], (*L, W_1, ..., W_n)
            return product(s[..., m], [f[..., m, :] for f in factors])

        out = term(0)
        for m in range(1, M):  # neighbour slots, not targets: at most _TERMWISE_MAX
            out = out + term(m)
        return out

    def _neighbour_index(self, overlap: Tensor, count: int) -> tuple[Tensor, Tensor]:
        """The first ``count`` targets that overlap each box: ``overlap (..., Q, T)`` bool ->
        ``index (..., Q, count)`` int64 and ``weight (..., Q, count)`` 0/1 (dtype float32;
        0 marks a filler when a box has fewer overlapping targets).
        """
        if count >= overlap.shape[-1]:  # every target (the dense form): no selection
            index = torch.arange(overlap.shape[-1], device=overlap.device).expand(overlap.shape)
            return index, overlap.to(torch.float32)
        w, index = torch.topk(overlap.to(torch.float32), count, dim=-1, sorted=False)
        return index, w

    def _select(
        self,
        dense: int,
        fn: Callable[..., Tensor],
        prepare: Callable[..., tuple[Tensor, ...]],
        inputs: tuple[Tensor, ...],
    ) -> Tensor:
        """``fn(count, *parts)`` with ``parts = prepare(*inputs)`` (whose last entry is the
        overlap mask ``(..., Q, T)`` bool of the boxes evaluated and the targets) and
        ``count`` at least the most targets overlapping one box. On a CUDA device it is
        always ``dense``. Otherwise, eager, ``count`` is that maximum (one read from the
        device). Under ``torch.compile`` it is
        :attr:`max_neighbours` when no box overlaps more targets than that, else ``dense``
        (at least the most a box can have), chosen by ``torch.cond`` so that the graph stays
        whole and shapes static (both branches are compiled); inside a ``torch.func``
        transform (the compiled HMC kernel) always ``dense``. Exact either way.

        The branches take the raw ``inputs`` and run ``prepare`` again: passed intermediates
        instead, torch 2.13's inductor gave some a transposed layout that the compiled
        branch did not expect (an ``assert_size_stride`` failure at run time).
        """
        parts = prepare(*inputs)
        cap = min(int(self.max_neighbours), dense)
        if cap >= dense or parts[-1].device.type == "cuda":
            # on a GPU, the dense form: no device sync for the count, no branch, so that a
            # compiled kernel can be captured whole in a CUDA graph (filters.base.compile_kernel)
            return fn(dense, *parts)
        most = parts[-1].sum(-1).max()
        if not torch.compiler.is_compiling():
            return fn(int(most), *parts)
        if torch._C._are_functorch_transforms_active():
            # torch.cond cannot be traced inside torch.func.grad (the compiled HMC kernel of
            # the resample-move filter): take the dense form, exact as well
            return fn(dense, *parts)
        return torch.cond(
            most <= cap, lambda *ins: fn(cap, *prepare(*ins)), lambda *ins: fn(dense, *prepare(*ins)), inputs
        )

    def box_cells(self) -> tuple[int, ...]:
        """Layout of the cells of one box on the windowed paths: ``(W_1, ..., W_{n-2},
        W_{n-1} * W_n)``, the last two axes merged so that the innermost loop is long enough
        to vectorise (``W_a`` is 7 or 9, the vector width 8 or 16).
        """
        W = self.window_sizes()
        return W if len(W) < 2 else W[:-2] + (W[-2] * W[-1],)

    @staticmethod
    def _merge_last(factors: list[Tensor]) -> list[Tensor]:
        """Per-axis factors ``(..., W_a)`` -> the :meth:`box_cells` layout (the last two
        replaced by their flattened outer product ``(..., W_{n-1} * W_n)``).
        """
        if len(factors) < 2:
            return factors
        a, b = factors[-2][..., :, None], factors[-1][..., None, :]
        # compiled on the CPU, a matmul with inner size 1 fuses better than the broadcast
        # product (measured, benchmarks/bench_likelihood.py); eager it would be a bmm of tiny
        # matrices, and on a GPU a batched gemm of them (slow there, see _outer_sum)
        q = torch.matmul(a, b) if torch.compiler.is_compiling() and a.device.type != "cuda" else a * b
        return factors[:-2] + [q.flatten(-2)]

    def _flat_box_offsets(self) -> Tensor:
        """Offset of each cell of a box from the box's first cell in the flattened frame,
        ``(*box_cells())`` int64 (a buffer, ``box_offsets``: compiled, the gather of
        :meth:`_gather_cells` then loads its cell offsets instead of recomputing them from the
        merged index with an integer division per cell).
        """
        G, W = self.frame_shape, self.window_sizes()
        off = torch.zeros((), dtype=torch.int64)
        for a, w in enumerate(W):
            t = torch.arange(w, dtype=torch.int64) * math.prod(G[a + 1:])
            off = off[..., None] + t
        return off.reshape(self.box_cells())

    def _gather_cells(self, zc: Tensor, firsts: Sequence[Tensor]) -> Tensor:
        """``zc (B, *G)`` at the cells of boxes with first cells ``firsts[a] (B, P, Q)`` ->
        ``(B, P, Q, *box_cells())``: the flat index of each box's first cell plus
        :attr:`box_offsets`, one gather.
        """
        B = zc.shape[0]
        index = self._flat_cells(firsts)  # (B, P, Q, *V)
        run = torch.arange(B, device=zc.device).reshape((B,) + (1,) * (index.dim() - 1))
        return zc.flatten(1)[run, index]

    def _flat_cells(self, firsts: Sequence[Tensor]) -> Tensor:
        """Flat index in one frame of every cell of boxes with first cells ``firsts[a] (...)``:
        ``(..., *box_cells())`` int64 (the box's first cell plus :attr:`box_offsets`).
        """
        base = firsts[0].long() * math.prod(self.frame_shape[1:])
        for a in range(1, self.n_axes):
            base = base + firsts[a].long() * math.prod(self.frame_shape[a + 1:])
        offsets: Tensor = self.box_offsets  # type: ignore[assignment]  # a buffer (nn.Module types it loosely)
        return base.reshape(base.shape + (1,) * offsets.dim()) + offsets

    def window_chunk_size(self, num_targets: int, dtype: torch.dtype = torch.float32) -> int:
        """Samples (rows of the flattened ``B * prod(S)``) per chunk of the windowed path.

        One sample holds about ``_WINDOW_TEMPS * K * prod(W_a)`` elements of per-cell
        temporaries, whatever the number of neighbour slots (they are summed term by term,
        see :meth:`_outer_sum`); the chunk is the largest count whose total stays within
        ``memory_budget`` bytes (at least 1).
        """
        itemsize = torch.empty((), dtype=dtype).element_size()
        per_sample = itemsize * num_targets * math.prod(self.window_sizes()) * self._WINDOW_TEMPS
        return max(1, self.memory_budget // per_sample)

    #: per-cell temporaries of one box cell held at once by the eager windowed path: the
    #: amplitude sum with its running terms, the ownership masks, the frame cells, the log
    #: ratio with the intermediates of the float32 log I0 polynomial (as ``_GRID_TEMPS``)
    _WINDOW_TEMPS = 12

    def _window_rows(self, x: Tensor, fn: Callable[[int, int, int, int], Tensor], chunk: int) -> Tensor:
        """Apply ``fn(rows) -> (b, p)`` to blocks of at most ``chunk`` rows of the flattened
        ``(B, P)`` samples of ``x (B, P, ...)`` (a row block is ``runs x samples``), each block
        checkpointed when autograd records, and reassemble ``(B, P)``.
        """
        B, P = x.shape[:2]
        runs = min(B, chunk)
        samples = max(1, chunk // runs)
        if runs >= B and samples >= P:
            return fn(0, B, 0, P)
        grad = torch.is_grad_enabled() and x.requires_grad
        out = []
        for b in range(0, B, runs):  # chunks of rows, not a loop per particle or per run
            row = []
            for p in range(0, P, samples):
                args = (b, min(b + runs, B), p, min(p + samples, P))
                row.append(checkpoint(fn, *args, use_reentrant=False) if grad else fn(*args))
            out.append(torch.cat(row, 1))
        return torch.cat(out)

    def _window_parts(self, x: Tensor, z: Tensor, exists: Tensor | None = None) -> tuple[Tensor, ...]:
        """``x (b, p, K, D)``, ``z (b, *G)``, ``exists (b, p, K)`` -> ``(u, s, e, zc, *firsts,
        others)``: see :meth:`_flat_inputs`; ``firsts[a] (b, p, K)`` the box starts and
        ``others (b, p, J, K)`` whether the boxes of live targets ``j != k`` overlap.
        """
        K = x.shape[-2]
        u, s, e = self._flat_inputs(x, exists)
        firsts = [self._box_first(u[..., a], a) for a in range(self.n_axes)]  # (b, p, K) each
        live = e > 0
        others = self._overlaps(firsts, firsts) & live[..., :, None] & live[..., None, :]
        others = others & ~torch.eye(K, dtype=torch.bool, device=x.device)  # (b, p, J, K)
        return (u, s, e, self.prepare_frame(z.to(x.dtype)), *firsts, others)

    def _window_sum(self, count: int, u: Tensor, s: Tensor, e: Tensor, zc: Tensor, *parts: Tensor) -> Tensor:
        """Windowed log-likelihood ``(b, p)`` of a block of samples from
        :meth:`_window_parts`, with ``count`` neighbour slots per box (at least the most
        other boxes overlapping one box).
        """
        *firsts, others = parts
        b, p, K = s.shape
        index = torch.arange(K, device=u.device).expand(b, p, K)[..., None]  # (b, p, J, 1): the box's own target
        weight = torch.ones(index.shape, dtype=s.dtype, device=u.device)
        if count > 0:
            nb, w = self._neighbour_index(others, count)  # (b, p, J, count)
            index, weight = torch.cat([index, nb], -1), torch.cat([weight, w.to(s.dtype)], -1)
        profiles, _ = self._neighbour_profiles(firsts, u, firsts, index)  # (b, p, J, M, W) each
        s_nb = torch.take_along_dim(s[..., None, :].expand(b, p, K, K), index, -1) * weight  # (b, p, J, M)
        A = self._outer_sum(s_nb, profiles)  # (b, p, J, *W)
        zw = self._gather_cells(zc, firsts)  # (b, p, J, *W)
        owned = self._owned_cells(firsts, e > 0)  # (b, p, J, *W): each cell of the union counted once
        V = self.box_cells()
        # one reduction over boxes and cells (fused with the cell terms under torch.compile)
        return torch.where(owned, self.cell_log_ratio(A, zw), 0.0).sum(tuple(range(2, 3 + len(V))))

    #: targets per word of the ownership masks of :meth:`_owned_cells` (int32 words built by
    #: a float32 matmul, exact up to 2**24)
    _MASK_BITS = 24

    def _owned_cells(self, firsts: Sequence[Tensor], live: Tensor) -> Tensor:
        """Which cells each box counts on the windowed path, so that every cell of the union
        of the live boxes is counted exactly once: cell ``t`` of box ``j`` when ``j`` is live
        and no live box ``i < j`` contains the cell (the union's cells belong to the first box
        that holds them).

        ``firsts[a] (b, p, K)`` the box starts, ``live (b, p, K)`` bool -> ``(b, p, K,
        *box_cells())`` bool. Per axis ``a``, ``cover_a[c]`` is the bit set of the live boxes
        whose span on that axis holds grid cell ``c`` (int32 words of :attr:`_MASK_BITS`
        targets): a difference array (``+bit_i`` at the span's first cell, ``-bit_i`` past
        its last) summed by one ``cumsum``, exact in float32 since every partial sum is a sum
        of distinct powers of two below ``2**24``; O(K + N_a) per sample. Box ``j`` reads
        ``cover_a`` at its cells and keeps the boxes ``i < j``. A cell lies in box ``i`` iff it
        does on every axis, so it is owned iff the AND of its axes' masks is empty: three
        integer operations per cell. The last two axes' merged mask is materialised
        (:func:`materialise`), so that the compiled per-cell loop loads it contiguously and
        stays vectorised (inlined, its per-cell division and modulo by ``W`` kept the loop
        scalar: 99 -> 81 ms for the compiled radar SIR step at N = 5000, K = 10, A/B in one
        process, benchmarks/README.md).
        """
        K = live.shape[-1]
        V = self.box_cells()
        if K == 1:  # no earlier box: a live box owns all its cells (skips the covers' O(N_a) work)
            return live.reshape(live.shape + (1,) * len(V)).expand(live.shape + V)
        words = -(-K // self._MASK_BITS)
        i = torch.arange(K, device=live.device)
        # (I, words): target i's bit in its word, as a float
        bits = torch.where((i // self._MASK_BITS)[:, None] == torch.arange(words, device=live.device),
                           torch.exp2((i % self._MASK_BITS).float())[:, None], 0.0)
        add = (live[..., None] * bits).to(torch.float32).mT  # (b, p, words, I): live boxes' bits
        earlier = ((i[None, :] < i[:, None]).float() @ bits).int()  # (J, words): boxes i < j
        masks = []
        for first, W, N in zip(firsts, self.window_sizes(), self.frame_shape):
            first = first.long()
            start = first[..., None, :].expand(add.shape)  # (b, p, words, I)
            diff = torch.zeros(add.shape[:-1] + (N + 1,), dtype=add.dtype, device=add.device)
            cover = diff.scatter_add(-1, start, add).scatter_add(-1, start + W, -add).cumsum(-1)
            cells = (first[..., :, None] + torch.arange(W, device=live.device)).flatten(-2)  # (b, p, J W)
            m = torch.gather(cover, -1, cells[..., None, :].expand(add.shape[:-1] + cells.shape[-1:]))
            masks.append(m.int().mT.unflatten(-2, (K, W)))  # (b, p, J, W, words)
        masks[0] = masks[0] & earlier[:, None, :]
        n = len(masks)
        if n >= 2:  # the box_cells layout: the last two axes merged
            last = masks[-2][..., :, None, :] & masks[-1][..., None, :, :]
            masks = masks[:-2] + [materialise(last.flatten(-3, -2))]
        both = masks[0]
        for a, m in enumerate(masks[1:], start=1):  # (b, p, J, V_1, ..., V_a, words)
            both = both.unsqueeze(-2) & m.reshape(m.shape[:3] + (1,) * a + m.shape[-2:])
        # one word (K <= 24): no reduction over words, which compiled code would not fuse
        free = (both == 0).all(-1) if words > 1 else both[..., 0] == 0
        return free & live.reshape(live.shape + (1,) * len(V))

    def log_likelihood_window(self, x: Tensor, z: Tensor, exists: Tensor | None = None) -> Tensor:
        """Fast path: the exact log-likelihood of the sensor with *truncated* point spreads.

        Each target ``k`` gets a box of ``W_a = min(2 * window + 1, N_a)`` cells per axis,
        centred on its nearest cell and shifted to lie inside the grid, and its point spread
        is cut to that box: ``h~_k(c) = prod_a h_{k,a}(c_a) 1[c_a in box_{k,a}]``. Then
        ``A = sum_k e_k s_k h~_k`` vanishes outside the union of the boxes and the
        log-likelihood is the sum of :meth:`cell_log_ratio` over that union, computed box by
        box: at the cells of box ``j``, ``A`` sums the truncated spreads of target ``j`` and
        of the targets whose boxes overlap box ``j`` (the only ones nonzero there; at most
        :attr:`max_neighbours` of them on the fast form, all ``K`` otherwise, see
        :meth:`_select`), and a cell inside several boxes is counted once, by the first live box
        that holds it (:meth:`_owned_cells`: per-axis bit masks, three integer operations per
        cell). The cut drops ``h`` below ``exp(-(window +
        1/2)^2 / 2)`` of the peak (2e-3 at ``window = 3`` and widths equal to the cell size):
        the difference to :meth:`log_likelihood_grid` is stated in the subclass
        (tests/models/test_radar.py).

        Because the spread is truncated the likelihood is local: moving one target changes
        only the cells of its old and new box, which :meth:`log_likelihood_delta` exploits.

        Cost per sample: ``K * (1 + M) * prod(W_a)`` multiply-adds (``M`` the neighbour
        slots, ``max_neighbours`` unless some box of the call overlaps more boxes) and
        ``K * prod(W_a)`` cell log-ratios, independent of the grid size. Blocks of at most
        :meth:`window_chunk_size` samples are processed at a time (checkpointed under
        autograd), so temporaries stay within ``memory_budget``.

        Parameters
        ----------
        x : (B, *S, K, D); z : (B, *G); exists : (B, *S, K) bool, optional.

        Returns
        -------
        (B, *S).
        """
        self._check_inputs(x, z, exists)
        B, K = x.shape[0], x.shape[-2]
        xf = x.reshape(B, -1, K, x.shape[-1])  # (B, P, K, D)
        ef = None if exists is None else exists.reshape(B, -1, K)

        def rows(b0: int, b1: int, p0: int, p1: int) -> Tensor:
            inputs = (xf[b0:b1, p0:p1], z[b0:b1]) + (() if ef is None else (ef[b0:b1, p0:p1],))
            return self._select(K - 1, self._window_sum, self._window_parts, inputs)

        out = self._window_rows(xf, rows, self.window_chunk_size(K, x.dtype))
        return out.reshape(x.shape[:-2])

    def log_likelihood_delta(
        self,
        x: Tensor,
        x_n: Tensor,
        n: int | Tensor,
        z: Tensor,
        exists: Tensor | None = None,
        exists_n: Tensor | None = None,
    ) -> Tensor:
        """Change of :meth:`log_likelihood_window` when slot ``n`` of ``x`` is set to ``x_n``.

        With truncated point spreads (see :meth:`log_likelihood_window`) only the cells of
        slot ``n``'s old box and of its new box change, so the difference is
        ``sum over box_old ∪ box_new of cell_log_ratio(A') - cell_log_ratio(A)`` (a cell in
        both boxes counted once), with ``A`` and ``A'`` the current and the new amplitude
        there: the spreads of slot ``n`` before and after the move and those of the other
        targets whose boxes overlap the box (at most :attr:`max_neighbours` on the fast
        form, see :meth:`_select`). Cost per sample: ``4 * (M + 2) * prod(W_a)``
        multiply-adds and ``4 * prod(W_a)`` cell log-ratios, independent of ``K`` on the
        fast form. This is the ``log_likelihood_delta`` hook of
        :mod:`torchmcmcpf.kernels.moves` (per-target refinement) and of
        :func:`torchmcmcpf.filters.ipmcmc.exchange_iteration`; it equals
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
        self._check_inputs(x, z, exists)
        self._check_move(x, x_n, exists_n)
        B, K = x.shape[0], x.shape[-2]
        S = tuple(x.shape[1:-2])
        if torch.is_tensor(n):
            slot = n.to(device=x.device, dtype=torch.int64).expand((B,) + S).reshape(B, -1)
        else:
            if isinstance(n, bool) or not isinstance(n, int) or not 0 <= n < K:
                raise ValueError(f"n must be an int in [0, {K}) or an int64 tensor, got {n!r}")
            slot = torch.full((B, math.prod(S)), n, device=x.device, dtype=torch.int64)
        if self.method == "grid":  # consistent with log_likelihood: two reference evaluations
            here = torch.arange(K, device=x.device) == slot.reshape((B,) + S + (1,))
            e_old = torch.ones(x.shape[:-1], dtype=torch.bool, device=x.device) if exists is None else exists
            e_new = e_old if exists_n is None else torch.where(here, exists_n[..., None], e_old)
            x_new = torch.where(here[..., None], x_n[..., None, :], x)
            return self.log_likelihood_grid(x_new, z, e_new) - self.log_likelihood_grid(x, z, e_old)
        names = [k for k, v in (("n", n if torch.is_tensor(n) else None), ("exists", exists), ("exists_n", exists_n))
                 if v is not None]

        def prepare(x: Tensor, x_n: Tensor, z: Tensor, *optional: Tensor) -> tuple[Tensor, ...]:
            kw = dict(zip(names, optional))
            return self._delta_parts(x, x_n, kw.get("n", n), z, kw.get("exists"), kw.get("exists_n"))

        inputs = (x, x_n, z) + tuple(v for v in (n, exists, exists_n) if torch.is_tensor(v))
        return self._select(K - 1, self._delta_sum, prepare, inputs).reshape((B,) + S)

    def _delta_parts(
        self, x: Tensor, x_n: Tensor, n: int | Tensor, z: Tensor, exists: Tensor | None,
        exists_n: Tensor | None,
    ) -> tuple[Tensor, ...]:
        """The arguments of :meth:`log_likelihood_delta` (checked) -> ``(u_all, s, s_old,
        s_new, zc, *firsts, others)``: ``u_all (B, P, K + 2, n)`` the coordinates of the K
        slots, then of slot ``n`` before and after the move; ``s (B, P, K)``, ``s_old, s_new
        (B, P, 1)`` the signals (times existence); ``firsts[a] (B, P, K + 2)`` the box starts;
        ``others (B, P, 2, K)`` whether the old / new box of slot ``n`` overlaps the box of
        another live slot.
        """
        B, K, D = x.shape[0], x.shape[-2], x.shape[-1]
        if torch.is_tensor(n):
            slot = n.to(device=x.device, dtype=torch.int64).expand(x.shape[:-2]).reshape(B, -1)
        else:
            slot = torch.full((B, math.prod(x.shape[1:-2])), n, device=x.device, dtype=torch.int64)
        u, s, e = self._flat_inputs(x, exists)  # (B, P, K, n), (B, P, K), (B, P, K)
        P = u.shape[1]
        at = slot[..., None]  # (B, P, 1)
        x_new = x_n.reshape(B, P, 1, D)
        e_new = torch.take_along_dim(e, at, 2) if exists_n is None else exists_n.reshape(B, P, 1).to(x.dtype)
        s_old = torch.take_along_dim(s, at, 2)  # (B, P, 1)
        s_new = self.signal(x_new) * e_new
        # targets: the K slots, then slot n before (index K) and after (index K + 1) the move
        u_all = torch.cat([u, torch.take_along_dim(u, at[..., None], 2), self.measurement_coords(x_new)], 2)
        firsts = [self._box_first(u_all[..., a], a) for a in range(self.n_axes)]  # (B, P, K + 2)
        boxes = [f[..., K:] for f in firsts]  # (B, P, 2): old and new box of slot n
        rest = (torch.arange(K, device=x.device) != at) & (e > 0)  # (B, P, K): the other live slots
        others = self._overlaps(boxes, [f[..., :K] for f in firsts]) & rest[..., None, :]  # (B, P, 2, K)
        return (u_all, s, s_old, s_new, self.prepare_frame(z.to(x.dtype)), *firsts, others)

    def _delta_sum(
        self, count: int, u_all: Tensor, s: Tensor, s_old: Tensor, s_new: Tensor, zc: Tensor, *parts: Tensor
    ) -> Tensor:
        """:meth:`log_likelihood_delta` ``(B, P)`` from :meth:`_delta_parts`, with ``count``
        neighbour slots per box.
        """
        *firsts, others = parts
        B, P, K = s.shape
        boxes = [f[..., K:] for f in firsts]
        moved = torch.tensor([K, K + 1], device=s.device).expand(B, P, 2, 2)  # (B, P, 2q, 2)
        zero = torch.zeros_like(s_old)
        cur = torch.cat([s_old, zero], -1)[:, :, None].expand(B, P, 2, 2)
        prop = torch.cat([zero, s_new], -1)[:, :, None].expand(B, P, 2, 2)
        if count > 0:
            nb, w = self._neighbour_index(others, count)  # (B, P, 2q, count)
            s_nb = torch.take_along_dim(s[:, :, None].expand(B, P, 2, K), nb, -1) * w.to(s.dtype)
            index = torch.cat([nb, moved], -1)  # (B, P, 2q, count + 2)
            cur, prop = torch.cat([s_nb, cur], -1), torch.cat([s_nb, prop], -1)
        else:
            index = moved
        profiles, indicators = self._neighbour_profiles(boxes, u_all, firsts, index)  # (B, P, 2q, M, W)
        signals = torch.stack([cur, prop], 2)  # (B, P, 2 (cur, prop), 2 (old box, new box), M)
        A = self._outer_sum(signals, [f[:, :, None] for f in profiles])  # (B, P, 2, 2, *W)
        zw = self._gather_cells(zc, boxes)[:, :, None]  # (B, P, 1, 2, *W)
        ratio = self.cell_log_ratio(A, zw)
        diff = ratio[:, :, 1] - ratio[:, :, 0]  # (B, P, 2, *W)
        both = self._new_box_in_old(indicators, count, s_old)  # (B, P, *W)
        return diff[:, :, 0].flatten(2).sum(-1) + (diff[:, :, 1] * (1.0 - both)).flatten(2).sum(-1)

    def _new_box_in_old(self, indicators: Sequence[Tensor], old: int, like: Tensor) -> Tensor:
        """Which cells of a move's new box the old box holds, ``(B, P, *box_cells())`` 0/1:
        from the per-axis indicators ``(B, P, 2 boxes, M, W)`` of
        :meth:`_neighbour_profiles`, entry ``old`` being the moved slot's old spread;
        ``like (B, P, 1)`` gives dtype and device.
        """
        return self._outer_sum(torch.ones_like(like), [f[:, :, 1, old][..., None, :] for f in indicators])

    # ---------------------------------------------------------------- every slot of one reference
    def log_likelihood_slot_changes(self, ref: Tensor, x: Tensor, z: Tensor) -> Tensor:
        """Every slot of one reference state moved on its own (see
        :meth:`SensorModel.log_likelihood_slot_changes`): ``ref (B, K, D)``, ``x (B, *S, K,
        D)``, ``z (B, *G)`` -> ``(B, *S, K)``, equal to :meth:`log_likelihood_delta` of the
        windowed path with ``ref`` as the current state (tested).

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
        B, K, D = _check_reference(ref, x)
        self._check_inputs(x, z, None)
        xf = x.reshape(B, -1, K, D)
        zc = self.prepare_frame(z.to(x.dtype))
        u_ref, s_ref = self.measurement_coords(ref), self.signal(ref)  # (B, K, n), (B, K)
        f_ref = [self._box_first(u_ref[..., a], a) for a in range(self.n_axes)]  # (B, K) each
        A = self._truncated_amplitude(u_ref, s_ref, f_ref)  # (B, *G): the reference's amplitude

        def rows(b0: int, b1: int, p0: int, p1: int) -> Tensor:
            return self._slot_term(xf[b0:b1, p0:p1], zc[b0:b1], A[b0:b1], u_ref[b0:b1], s_ref[b0:b1],
                                   [f[b0:b1] for f in f_ref])

        moved = self._window_rows(xf, rows, self.window_chunk_size(K, x.dtype))  # (B, P, K)
        at_ref = self._slot_term(ref[:, None], zc, A, u_ref, s_ref, f_ref)  # (B, 1, K)
        return (moved - at_ref).reshape(x.shape[:-1])

    def _truncated_amplitude(self, u: Tensor, s: Tensor, firsts: Sequence[Tensor]) -> Tensor:
        """Amplitude over the whole grid with truncated spreads (:meth:`log_likelihood_window`):
        ``u (..., K, n)``, ``s (..., K)`` (times existence), ``firsts[a] (..., K)`` the box
        starts -> ``(..., *G)``; one contraction (``K * G`` multiply-adds per sample).
        """
        cells = [torch.arange(N, device=u.device) for N in self.frame_shape]
        truncated = [p * ((c >= f[..., None]) & (c < f[..., None] + W)).to(p.dtype)  # (..., K, N_a)
                     for p, c, f, W in zip(self._profiles(u), cells, firsts, self.window_sizes())]
        return self._contract(s, truncated)

    # ---------------------------------------------------------------- per-sample amplitude cache
    def amplitude_cache(self, x: Tensor, exists: Tensor | None = None) -> Tensor | None:
        """Each sample's amplitude per cell, ``(B, *S, G)`` flat over the grid (truncated
        spreads, as :meth:`log_likelihood_window`), for :meth:`log_likelihood_delta_cached`;
        ``None`` with ``method="grid"`` (the whole-grid reference has no truncated spreads).
        ``G * 4`` bytes per sample in float32 (244 kB on the ground radar's 87 x 22 x 32
        cells).
        """
        if self.method == "grid":
            return None
        self._check_state(x, exists)
        u, s, _ = self._flat_inputs(x, exists)  # (B, P, K, n), (B, P, K)
        firsts = [self._box_first(u[..., a], a) for a in range(self.n_axes)]
        return self._truncated_amplitude(u, s, firsts).reshape(x.shape[:-2] + (self.num_cells,))

    def log_likelihood_delta_cached(
        self, cache: Tensor, x: Tensor, x_n: Tensor, n: Tensor, z: Tensor,
        exists: Tensor | None = None, exists_n: Tensor | None = None,
    ) -> tuple[Tensor, Tensor, Tensor]:
        """:meth:`log_likelihood_delta` read from the samples' amplitudes
        (:meth:`amplitude_cache`) instead of summing the neighbours' spreads: the cells of
        slot ``n``'s old and new box hold ``A`` (gathered) and ``A'`` = ``A`` minus the old
        spread plus the new one, so a move costs ``2 * prod(W_a)`` cells with two cell
        log-ratios each, whatever the number of targets nearby. Equal to
        :meth:`log_likelihood_delta` to round-off (tested).

        Parameters
        ----------
        cache : (B, *S, G) the amplitudes of ``x`` (kept current by
            :meth:`update_amplitude_cache`).
        x, x_n, n, z, exists, exists_n : as :meth:`log_likelihood_delta`; ``n`` an int64
            tensor broadcastable to ``(B, *S)``.

        Returns
        -------
        delta : (B, *S); cells, change : as :meth:`amplitude_change`.
        """
        B = x.shape[0]
        self._check_inputs(x, z, exists)
        S = tuple(x.shape[1:-2])
        if tuple(cache.shape) != (B,) + S + (self.num_cells,):
            raise ValueError(f"cache has shape {tuple(cache.shape)}, expected {(B,) + S + (self.num_cells,)}")
        cells, change, firsts = self._amplitude_change(x, x_n, n, exists, exists_n)
        A = cache.reshape(-1).gather(0, cells.reshape(-1)).reshape(change.shape)  # (B, P, 2, *V)
        zw = self._gather_cells(self.prepare_frame(z.to(x.dtype)), firsts)
        # round-off of the kept sums may leave -1e-7 where a spread left: amplitudes are >= 0
        diff = self.cell_log_ratio((A + change).clamp_min(0.0), zw) - self.cell_log_ratio(A.clamp_min(0.0), zw)
        delta = diff.flatten(2).sum(-1)  # each cell counted once: ``change`` is 0 on the repeats
        return delta.reshape((B,) + S), cells.reshape((B,) + S + cells.shape[2:]), \
            change.reshape((B,) + S + change.shape[2:])

    def amplitude_change(self, x: Tensor, x_n: Tensor, n: Tensor, exists: Tensor | None = None,
                         exists_n: Tensor | None = None) -> tuple[Tensor, Tensor]:
        """Where and by how much slot ``n``'s move changes the samples' amplitudes
        (:meth:`amplitude_cache`), for :meth:`update_amplitude_cache`.

        Parameters
        ----------
        x, x_n, n, exists, exists_n : as :meth:`log_likelihood_delta_cached`.

        Returns
        -------
        cells : (B, *S, 2, *box_cells()) int64, flat indices into a ``(B, *S, G)`` cache of
        the cells of the old and the new box; change : the same shape, ``A' - A`` there (0 at
        the cells of the new box that the old box holds, so that each cell changes once).
        """
        self._check_state(x, exists)
        cells, change, _ = self._amplitude_change(x, x_n, n, exists, exists_n)
        lead = tuple(x.shape[:-2])
        return cells.reshape(lead + cells.shape[2:]), change.reshape(lead + change.shape[2:])

    def _amplitude_change(self, x: Tensor, x_n: Tensor, n: Tensor, exists: Tensor | None,
                          exists_n: Tensor | None) -> tuple[Tensor, Tensor, list[Tensor]]:
        """:meth:`amplitude_change` flat over the samples ``(B, P, 2, *V)``, and the boxes'
        first cells ``firsts[a] (B, P, 2)``.
        """
        B, K, D = x.shape[0], x.shape[-2], x.shape[-1]
        self._check_move(x, x_n, exists_n)
        S = tuple(x.shape[1:-2])
        P = math.prod(S)
        slot = n.to(device=x.device, dtype=torch.int64).expand((B,) + S).reshape(B, P, 1)
        xf = x.reshape(B, P, K, D)
        e = torch.ones_like(xf[..., 0]) if exists is None else exists.reshape(B, P, K).to(x.dtype)
        e_old = torch.take_along_dim(e, slot, 2)  # (B, P, 1)
        e_new = e_old if exists_n is None else exists_n.reshape(B, P, 1).to(x.dtype)
        moved = torch.cat([torch.take_along_dim(xf, slot[..., None], 2), x_n.reshape(B, P, 1, D)], 2)  # (B, P, 2, D)
        u = self.measurement_coords(moved)  # (B, P, 2, n): slot n before and after
        s = self.signal(moved) * torch.cat([e_old, e_new], -1)  # (B, P, 2)
        firsts = [self._box_first(u[..., a], a) for a in range(self.n_axes)]  # (B, P, 2): old, new box
        index = torch.arange(2, device=x.device).expand(B, P, 2, 2)
        profiles, indicators = self._neighbour_profiles(firsts, u, firsts, index)  # (B, P, 2 box, 2 spread, W)
        change = self._outer_sum(torch.stack([-s[..., 0], s[..., 1]], -1)[:, :, None], profiles)  # (B, P, 2, *V)
        V = self.box_cells()
        both = self._new_box_in_old(indicators, 0, s[..., :1])  # (B, P, *V)
        once = torch.stack([torch.ones_like(both), 1.0 - both], 2)  # (B, P, 2, *V)
        rows = torch.arange(B * P, device=x.device).reshape((B, P) + (1,) * (1 + len(V))) * self.num_cells
        return self._flat_cells(firsts) + rows, change * once, firsts

    @staticmethod
    def update_amplitude_cache(cache: Tensor, cells: Tensor, change: Tensor, accepted: Tensor) -> Tensor:
        """Add the ``change`` of :meth:`log_likelihood_delta_cached` to ``cache`` in place for
        the ``accepted (B, *S)`` samples (eager: the rows of the accepted moves only, one
        ``index_add_``). Returns ``cache``.
        """
        rows = accepted.reshape(-1).nonzero().squeeze(1)
        per_row = cells.reshape(accepted.numel(), -1)
        cache.view(-1).index_add_(0, per_row[rows].reshape(-1), change.reshape(accepted.numel(), -1)[rows].reshape(-1))
        return cache

    def _slot_term(self, y: Tensor, zc: Tensor, A: Tensor, u_ref: Tensor, s_ref: Tensor,
                   f_ref: Sequence[Tensor]) -> Tensor:
        """``term_k(y)`` of :meth:`log_likelihood_slot_changes` for a block: ``y (b, p, K, D)``,
        ``zc, A (b, *G)``, ``u_ref (b, K, n)``, ``s_ref (b, K)``, ``f_ref[a] (b, K)`` ->
        ``(b, p, K)``.
        """
        b, p, K, _ = y.shape
        u, s = self.measurement_coords(y), self.signal(y)  # (b, p, K, n), (b, p, K)
        firsts = [self._box_first(u[..., a], a) for a in range(self.n_axes)]  # (b, p, K)
        # targets: the K candidate slots, then the K reference slots
        u_all = torch.cat([u, u_ref[:, None].expand(b, p, K, u.shape[-1])], 2)
        f_all = [torch.cat([f, fr[:, None].expand(b, p, K)], 2) for f, fr in zip(firsts, f_ref)]
        k = torch.arange(K, device=y.device)
        index = torch.stack([k, k + K], -1).expand(b, p, K, 2)  # box k: candidate k, reference k
        profiles, _ = self._neighbour_profiles(firsts, u_all, f_all, index)  # (b, p, K, 2, W) each
        own = self._outer_sum(s[..., None], [f[..., :1, :] for f in profiles])  # (b, p, K, *V)
        ref_k = self._outer_sum(s_ref[:, None, :, None], [f[..., 1:, :] for f in profiles])
        rest = (self._gather_cells(A, firsts) - ref_k).clamp_min(0.0)  # T_k at the box (round-off >= 0)
        zw = self._gather_cells(zc, firsts)
        dims = tuple(range(3, 3 + len(self.box_cells())))
        return (self.cell_log_ratio(rest + own, zw) - self.cell_log_ratio(rest, zw)).sum(dims)


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

    @property
    def data_driven(self) -> bool:
        """Whether the subclass gives :meth:`detection_statistic` and :meth:`place`."""
        cls = type(self)
        return (cls.detection_statistic is not SeparableGridSensor.detection_statistic
                and cls.place is not SensorModel.place)

    def _pool(self, t: Tensor, kind: str) -> Tensor:
        """``3^n`` max or average pooling of ``t (B, *G)`` with stride 1 (same shape)."""
        fn = getattr(torch.nn.functional, f"{kind}_pool{self.n_axes}d")
        return fn(t.unsqueeze(1), 3, stride=1, padding=1).squeeze(1)

    def peaks(self, z: Tensor) -> Tensor:
        """Cells that are local maxima of :meth:`detection_statistic` over their ``3^n``
        neighbourhood and exceed :attr:`detection_threshold`: ``(B, *G)`` bool. A target
        gives about one peak, whatever its SNR (a strong target lights many cells above the
        threshold, but one local maximum).
        """
        stat = self.detection_statistic(z)
        return (stat >= self._pool(stat, "max")) & (stat > self.detection_threshold)

    def detections(self, z: Tensor) -> tuple[Tensor, Tensor]:
        """The frame's :meth:`peaks` as points: the centroid of the statistic over each peak's
        ``3^n`` neighbourhood, in the units of :meth:`measurement_coords`.

        Parameters
        ----------
        z : (B, *G).

        Returns
        -------
        centres : (B, P, n), the strongest ``P = min(max_peaks, G)`` peaks (padded);
        mask : (B, P) bool, True for a real peak.
        """
        stat = self.detection_statistic(z)
        peak = (stat >= self._pool(stat, "max")) & (stat > self.detection_threshold)
        B, G = stat.shape[0], self.num_cells
        weight = (stat - 1.0).clamp(min=0.0)  # above the noise mean (1)
        norm = self._pool(weight, "avg").reshape(B, G)
        P = min(self.max_peaks, G)
        top, at = torch.topk(torch.where(peak, stat, float("-inf")).reshape(B, G), P, dim=-1)
        mask = torch.isfinite(top)
        centres = []
        for a in range(self.n_axes):
            shape = [1] * (self.n_axes + 1)
            shape[1 + a] = self.frame_shape[a]
            coord = (self.origins[a] + self.cell_sizes[a] * torch.arange(
                self.frame_shape[a], device=z.device, dtype=stat.dtype)).reshape(shape)
            moment = self._pool(weight * coord, "avg").reshape(B, G)
            centres.append(torch.take_along_dim(moment / norm.clamp(min=1e-30), at, -1))
        return torch.stack(centres, -1), mask

    def _extent(self) -> tuple[list[float], list[float], float]:
        """Lower and upper edges of the grid per axis and ``log`` of its volume (the field of view)."""
        lo = [o - 0.5 * c for o, c in zip(self.origins, self.cell_sizes)]
        hi = [o + (N - 0.5) * c for o, c, N in zip(self.origins, self.cell_sizes, self.frame_shape)]
        return lo, hi, sum(math.log(h - lw) for lw, h in zip(lo, hi))

    def log_data_density(self, coords: Tensor, centres: Tensor, mask: Tensor) -> Tensor:
        """``log g(u | z)`` of :meth:`sample_from_data` at ``coords (B, *S, n)``, given the
        frame's :meth:`detections` ``centres (B, P, n)``, ``mask (B, P)``: ``(B, *S)``.
        """
        B, n = coords.shape[0], self.n_axes
        used = int(mask.sum(-1).max()) if mask.numel() else 0  # the padding holds no peak: drop it (eager)
        centres, mask = centres[:, :max(used, 1)], mask[:, :max(used, 1)]
        lo, hi, log_volume = self._extent()
        scale = torch.tensor([self.peak_spread * c for c in self.cell_sizes], dtype=coords.dtype,
                             device=coords.device)
        flat = coords.reshape(B, -1, 1, n)  # (B, Q, 1, n)
        white = (flat - centres.to(coords.dtype).unsqueeze(1)) / scale  # (B, Q, P, n)
        log_n = -0.5 * white.square().sum(-1) - torch.log(scale).sum() - 0.5 * n * math.log(2 * math.pi)
        log_n = torch.where(mask.unsqueeze(1), log_n, float("-inf"))
        count = mask.sum(-1, keepdim=True).to(coords.dtype)  # (B, 1)
        log_near = torch.logsumexp(log_n, -1) - torch.log(count.clamp(min=1.0))  # (B, Q)
        p_u = self.uniform_weight
        log_q = torch.logaddexp(torch.full_like(log_near, math.log(p_u) - log_volume), math.log1p(-p_u) + log_near)
        log_q = torch.where(count > 0, log_q, torch.full_like(log_q, -log_volume))
        return log_q.reshape(coords.shape[:-1])

    def sample_from_data(self, z: Tensor, shape: tuple[int, ...], *, generator: torch.Generator,
                         dtype: torch.dtype = torch.float32) -> tuple[Tensor, Tensor]:
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

        Returns
        -------
        coords : (B, *S, n) in the units of :meth:`measurement_coords`;
        log_ratio : (B, *S).
        """
        B = z.shape[0]
        if not shape or shape[0] != B:
            raise ValueError(f"shape {tuple(shape)} must start with the batch size of z, {B}")
        n, Q = self.n_axes, math.prod(shape[1:])
        centres, mask = self.detections(z)
        lo, hi, log_volume = self._extent()
        u = torch.rand((B, Q, 2), generator=generator, device=z.device, dtype=torch.float64)
        pick = inverse_cdf(cdf(torch.where(mask | ~mask.any(-1, keepdim=True), 0.0, float("-inf"))), u[..., 0])
        eps = torch.randn((B, Q, n), generator=generator, device=z.device, dtype=dtype)
        box = torch.rand((B, Q, n), generator=generator, device=z.device, dtype=dtype)
        low = torch.tensor(lo, dtype=dtype, device=z.device)
        span = torch.tensor(hi, dtype=dtype, device=z.device) - low
        scale = torch.tensor([self.peak_spread * c for c in self.cell_sizes], dtype=dtype, device=z.device)
        near = torch.take_along_dim(centres.to(dtype), pick.unsqueeze(-1), 1) + scale * eps
        use = (u[..., 1] >= self.uniform_weight) & mask.any(-1, keepdim=True)
        coords = torch.where(use.unsqueeze(-1), near, low + span * box)  # (B, Q, n)
        inside = ((coords >= low) & (coords <= low + span)).all(-1)
        log_ratio = torch.where(inside, -log_volume - self.log_data_density(coords, centres, mask), float("-inf"))
        return coords.reshape(tuple(shape) + (n,)), log_ratio.reshape(tuple(shape))

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
