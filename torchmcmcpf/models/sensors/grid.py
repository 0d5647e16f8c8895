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
- :meth:`~SeparableGridSensor.log_likelihood_window`, the fast path: only the cells of a box of
  ``2 * window + 1`` cells per axis around each target's nearest cell. ``A`` there is exact
  (every target's full Gaussian contributes) and a cell inside several boxes is counted once,
  so the result is the reference restricted to the union of the boxes. Dropping the cells
  outside the union is the only approximation; with ``window`` at least the grid size the two
  paths agree to round-off.

Subclasses implement :meth:`measurement_coords`, :meth:`signal`, :meth:`cell_log_ratio`
(optionally :meth:`prepare_frame`) and :meth:`simulate`.
"""

from __future__ import annotations

import math
from typing import Optional, Sequence

import torch
from torch.utils.checkpoint import checkpoint

from ..._validation import check_nonnegative, check_positive, check_positive_int, check_shape
from ...typing import Tensor
from ..base import SensorModel

__all__ = ["SeparableGridSensor"]

_METHODS = ("window", "grid")


def _uniform_bins(bins, name: str) -> tuple[Tensor, float, float]:
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


class SeparableGridSensor(SensorModel):
    """Base of the TBD sensors whose point spread is a separable Gaussian over a regular grid.

    Parameters
    ----------
    bins : sequence of n 1-D tensors ``(N_a,)``
        Cell centres of each axis, increasing and uniformly spaced. Stored as buffers named
        ``f"{name}_bins"`` (float64; computations follow the dtype of ``x``).
    widths : sequence of n floats or ``None``
        Point-spread standard deviation ``w_a`` of each axis, in the axis' unit; ``None`` means
        the cell spacing of that axis.
    names : sequence of n str
        Axis names, used for buffers and error messages.
    window : int
        Half-width, in cells, of the box evaluated around each target by the windowed path.
    method : {"window", "grid"}
        What :meth:`log_likelihood` dispatches to.
    memory_budget : int
        Bytes of temporaries the whole-grid path may hold at once (see :meth:`grid_chunk_size`).
    """

    #: per-target state size D; subclasses set it
    dim: int

    #: temporaries of one sample held at once by the whole-grid path, in units of the grid
    #: size G (the amplitude, the gathered frame term and the cell log-ratio with its
    #: intermediates), on top of the ``K * prod(N_1..N_{n-1})`` outer-product buffer.
    #: Checked against a measured peak in tests/models/test_radar.py.
    _GRID_TEMPS = 6

    def __init__(
        self,
        bins: Sequence[Tensor],
        widths: Sequence[Optional[float]],
        *,
        names: Sequence[str],
        window: int,
        method: str = "window",
        memory_budget: int = 2**30,
    ):
        super().__init__()
        if not (len(bins) == len(widths) == len(names)) or len(bins) == 0:
            raise ValueError(
                f"bins, widths and names must have the same length >= 1; got {len(bins)}, "
                f"{len(widths)}, {len(names)}"
            )
        self.axis_names = tuple(names)
        self.window = check_positive_int(window, "window", minimum=0)
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
        ``(B, *G) -> (B, *G)``."""
        return z

    def cell_log_ratio(self, A: Tensor, zc: Tensor) -> Tensor:
        """``log p(z_c | A) - log p(z_c | 0)`` per cell; ``A`` and ``zc = prepare_frame(z)`` at
        the same cells broadcast together. Must be 0 where ``A = 0``."""
        raise NotImplementedError

    # ---------------------------------------------------------------- shared pieces
    @property
    def n_axes(self) -> int:
        return len(self.frame_shape)

    @property
    def num_cells(self) -> int:
        return math.prod(self.frame_shape)

    def bins(self, axis: int) -> Tensor:
        """Cell centres of ``axis``, ``(N_a,)``."""
        return getattr(self, f"{self.axis_names[axis]}_bins")

    def _check_inputs(self, x: Tensor, z: Tensor, exists: Optional[Tensor]) -> None:
        # Shape checks only (no device sync): the hot path stays compile-friendly. Values
        # are checked once per frame by validate().
        if x.dim() < 3 or x.shape[-1] != self.dim:
            raise ValueError(f"x has shape {tuple(x.shape)}, expected (B, *S, K, {self.dim})")
        if z.dim() != 1 + self.n_axes or tuple(z.shape[1:]) != self.frame_shape or z.shape[0] != x.shape[0]:
            raise ValueError(
                f"z has shape {tuple(z.shape)}, expected ({x.shape[0]}, "
                f"{', '.join(map(str, self.frame_shape))}) to match x {tuple(x.shape)}"
            )
        if exists is not None and tuple(exists.shape) != tuple(x.shape[:-1]):
            raise ValueError(f"exists has shape {tuple(exists.shape)}, expected {tuple(x.shape[:-1])}")

    def _flat_inputs(self, x: Tensor, exists: Optional[Tensor]) -> tuple[Tensor, Tensor, Tensor]:
        """``x (B, *S, K, D) -> u (B, P, K, n), s (B, P, K), e (B, P, K)`` with ``P = prod(S)``;
        ``s`` already multiplied by the existence flags ``e`` (float, dtype of ``x``)."""
        B, K = x.shape[0], x.shape[-2]
        x = x.reshape(B, -1, K, x.shape[-1])
        u = self.measurement_coords(x)
        e = torch.ones_like(x[..., 0]) if exists is None else exists.reshape(B, -1, K).to(x.dtype)
        return u, self.signal(x) * e, e

    def log_likelihood(self, x: Tensor, z: Tensor, exists: Optional[Tensor] = None) -> Tensor:
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

    def signal_grid(self, x: Tensor, exists: Optional[Tensor] = None) -> Tensor:
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

    def log_likelihood_grid(self, x: Tensor, z: Tensor, exists: Optional[Tensor] = None) -> Tensor:
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
    def window_sizes(self) -> tuple[int, ...]:
        """Cells per axis of one target's box: ``min(2 * window + 1, N_a)``."""
        return tuple(min(2 * self.window + 1, n) for n in self.frame_shape)

    def log_likelihood_window(self, x: Tensor, z: Tensor, exists: Optional[Tensor] = None) -> Tensor:
        """Fast path: :meth:`cell_log_ratio` summed over the union of the targets' boxes.

        Each existing target ``j`` gets a box of ``W_a = min(2 * window + 1, N_a)`` cells per
        axis, centred on its nearest cell and shifted to lie inside the grid. The signal at a
        box cell is exact, ``A = sum_k e_k s_k h_k(cell)`` over all targets: profiles of every
        target ``k`` at the box indices of ``j`` (``(K, K, W_a)`` per axis), contracted by one
        bmm. A cell inside ``n_c`` boxes is weighted ``1 / n_c``; ``n_c`` is the same
        contraction with 0/1 box indicators in place of the profiles. Hence the result equals
        :meth:`log_likelihood_grid` restricted to the union of the boxes.

        Cost per sample: ``2 * K^2 * prod(W_a)`` multiply-adds and ``K * prod(W_a)`` cell
        log-ratios, independent of the grid size.

        Parameters
        ----------
        x : (B, *S, K, D); z : (B, *G); exists : (B, *S, K) bool, optional.

        Returns
        -------
        (B, *S).
        """
        self._check_inputs(x, z, exists)
        B, K = x.shape[0], x.shape[-2]
        u, s, e = self._flat_inputs(x, exists)  # (B, P, K, n), (B, P, K), (B, P, K)
        P = u.shape[1]
        profiles, indicators, cells = [], [], []
        for a, (N, W) in enumerate(zip(self.frame_shape, self.window_sizes())):
            c0, delta = self.origins[a], self.cell_sizes[a]
            scale = 1.0 / (math.sqrt(2.0) * self.widths[a])
            ua = u[..., a]
            nearest = torch.round((ua.detach() - c0) / delta)
            first = (nearest - self.window).clamp(0, N - W)  # (B, P, K) first cell of each box
            offsets = torch.arange(W, device=x.device, dtype=x.dtype)
            # profile of target k at the cells of box j: (B, P, J, K, W)
            centre = (c0 + delta * (first[..., None] + offsets)) * scale  # (B, P, J, W)
            dist = centre[..., :, None, :] - (ua * scale)[..., None, :, None]
            profiles.append(torch.exp(-dist.square()))
            # cell t of box j lies in box k iff 0 <= first_j - first_k + t < W: look the
            # (B, P, J, K) shift up in a (2W + 1, W) table instead of comparing W-vectors
            shift = (first[..., :, None] - first[..., None, :]).clamp(-W, W).long() + W
            lags = torch.arange(-W, W + 1, device=x.device)[:, None] + offsets.long()
            table = ((lags >= 0) & (lags < W)).to(x.dtype)
            indicators.append(table[shift])
            cells.append(first.long()[..., None] + offsets.long())  # (B, P, J, W)
        lead = (B, P, K)  # J = K: one box per target slot
        A = self._contract(s[..., None, :].expand(*lead, K), profiles)  # (B, P, J, *W)
        n_boxes = self._contract(e[..., None, :].expand(*lead, K), indicators)
        # gather prepare_frame(z) at the box cells by broadcast advanced indexing (no index blow-up)
        zc = self.prepare_frame(z.to(x.dtype))
        n = self.n_axes
        index = [torch.arange(B, device=x.device).reshape((B,) + (1,) * (2 + n))]
        for a, idx in enumerate(cells):
            index.append(idx.reshape((B, P, K) + tuple(-1 if b == a else 1 for b in range(n))))
        zw = zc[tuple(index)]  # (B, P, J, *W)
        # weight 1 / n_c; an absent box j has n_c >= 0, so add (1 - e_j) before dividing and
        # zero its sum afterwards
        n_boxes = n_boxes + (1.0 - e).reshape(lead + (1,) * n)
        per_box = (self.cell_log_ratio(A, zw) / n_boxes).flatten(3).sum(-1)  # (B, P, J)
        return (per_box * e).sum(-1).reshape(x.shape[:-2])

    # ---------------------------------------------------------------- checks
    def validate(self, z: Tensor, batch_size: Optional[int] = None, name: str = "z") -> Tensor:
        """Check one frame ``z (B, *G)``: shape, batch size, finite, non-negative. Returns ``z``."""
        check_shape(z, name, (None,) + tuple(self.frame_shape))
        if z.shape[0] == 0:
            raise ValueError(f"{name} has shape {tuple(z.shape)}: empty batch, expected B >= 1")
        super().validate(z, batch_size, name)
        return check_nonnegative(z, name)
