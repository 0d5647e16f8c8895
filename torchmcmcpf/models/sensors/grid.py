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
  with ``window`` at least the grid size the two paths agree to round-off.
- :meth:`~SeparableGridSensor.log_likelihood_delta`: the change of the windowed
  log-likelihood when one target slot moves, from the cells of its old and new box only
  (the per-target refinement of the MCMC filter, the exchange move of IP-MCMC-PF).

Subclasses implement :meth:`measurement_coords`, :meth:`signal`, :meth:`cell_log_ratio`
(optionally :meth:`prepare_frame`) and :meth:`simulate`.
"""

from __future__ import annotations

import math
from typing import Optional, Sequence, Union

import torch
from torch.utils.checkpoint import checkpoint

from ..._validation import check_nonnegative, check_positive, check_positive_int, check_shape
from ...typing import Tensor
from ..base import SensorModel

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
    #: intermediates, those of the float32 log I0 polynomial included), on top of the
    #: ``K * prod(N_1..N_{n-1})`` outer-product buffer.
    #: Checked against a measured peak in tests/models/test_radar.py.
    _GRID_TEMPS = 9

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

    def _box_first(self, ua: Tensor, axis: int) -> Tensor:
        """First cell (float index) of the box on ``axis`` of targets at coordinates ``ua``:
        the nearest cell minus ``window``, shifted to lie inside the grid. Same shape as ``ua``."""
        N, W = self.frame_shape[axis], self.window_sizes()[axis]
        nearest = torch.round((ua.detach() - self.origins[axis]) / self.cell_sizes[axis])
        return (nearest - self.window).clamp(0, N - W)

    def _box_profiles(self, first_q: Tensor, ua: Tensor, first_k: Tensor, axis: int) -> tuple[Tensor, Tensor]:
        """Truncated profiles of targets ``k`` at the cells of boxes ``q`` on one axis.

        ``first_q (..., Q)`` first cells of the boxes evaluated; ``ua, first_k (..., K)`` the
        targets' coordinates and box starts. Returns ``profile (..., Q, K, W)``, the Gaussian of
        target ``k`` at cell ``t`` of box ``q`` times the indicator that the cell lies in box
        ``k``, and that indicator ``(..., Q, K, W)`` (0/1, dtype of ``ua``).
        """
        W = self.window_sizes()[axis]
        c0, delta = self.origins[axis], self.cell_sizes[axis]
        scale = 1.0 / (math.sqrt(2.0) * self.widths[axis])
        offsets = torch.arange(W, device=ua.device, dtype=ua.dtype)
        centre = (c0 + delta * (first_q[..., None] + offsets)) * scale  # (..., Q, W)
        dist = centre[..., :, None, :] - (ua * scale)[..., None, :, None]  # (..., Q, K, W)
        # cell t of box q lies in box k iff 0 <= first_q - first_k + t < W
        lag = (first_q[..., :, None] - first_k[..., None, :])[..., None] + offsets  # (..., Q, K, W)
        inside = ((lag >= 0) & (lag < W)).to(ua.dtype)
        return torch.exp(-dist.square()) * inside, inside

    def _gather_cells(self, zc: Tensor, firsts: Sequence[Tensor]) -> Tensor:
        """``zc (B, *G)`` at the cells of boxes with first cells ``firsts[a] (B, P, Q)`` ->
        ``(B, P, Q, *W)`` by broadcast advanced indexing (no index blow-up)."""
        B, P, Q = firsts[0].shape
        n = self.n_axes
        index = [torch.arange(B, device=zc.device).reshape((B,) + (1,) * (2 + n))]
        for a, (first, W) in enumerate(zip(firsts, self.window_sizes())):
            cells = first.long()[..., None] + torch.arange(W, device=zc.device)  # (B, P, Q, W)
            index.append(cells.reshape((B, P, Q) + tuple(-1 if b == a else 1 for b in range(n))))
        return zc[tuple(index)]

    def log_likelihood_window(self, x: Tensor, z: Tensor, exists: Optional[Tensor] = None) -> Tensor:
        """Fast path: the exact log-likelihood of the sensor with *truncated* point spreads.

        Each target ``k`` gets a box of ``W_a = min(2 * window + 1, N_a)`` cells per axis,
        centred on its nearest cell and shifted to lie inside the grid, and its point spread
        is cut to that box: ``h~_k(c) = prod_a h_{k,a}(c_a) 1[c_a in box_{k,a}]``. Then
        ``A = sum_k e_k s_k h~_k`` vanishes outside the union of the boxes and the
        log-likelihood is the sum of :meth:`cell_log_ratio` over that union, computed box by
        box: at the cells of box ``j``, ``A`` is the contraction of the truncated per-axis
        profiles of every target (``(K, K, W_a)`` per axis, one bmm), and a cell inside
        ``n_c`` boxes is weighted ``1 / n_c`` (``n_c`` the same contraction with the 0/1
        indicators). The cut drops ``h`` below ``exp(-(window + 1/2)^2 / 2)`` of the peak
        (2e-3 at ``window = 3`` and widths equal to the cell size): the difference to
        :meth:`log_likelihood_grid` is stated in the subclass (tests/models/test_radar.py).

        Because the spread is truncated the likelihood is local: moving one target changes
        only the cells of its old and new box, which :meth:`log_likelihood_delta` exploits.

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
        firsts = [self._box_first(u[..., a], a) for a in range(self.n_axes)]  # (B, P, K) each
        profiles, indicators = [], []
        for a, first in enumerate(firsts):
            profile, inside = self._box_profiles(first, u[..., a], first, a)  # (B, P, J, K, W)
            profiles.append(profile)
            indicators.append(inside)
        lead = (B, P, K)  # J = K: one box per target slot
        A = self._contract(s[..., None, :].expand(*lead, K), profiles)  # (B, P, J, *W)
        n_boxes = self._contract(e[..., None, :].expand(*lead, K), indicators)
        zw = self._gather_cells(self.prepare_frame(z.to(x.dtype)), firsts)  # (B, P, J, *W)
        n = self.n_axes
        # weight 1 / n_c; an absent box j has n_c >= 0, so add (1 - e_j) before dividing and
        # zero its sum afterwards
        n_boxes = n_boxes + (1.0 - e).reshape(lead + (1,) * n)
        per_box = (self.cell_log_ratio(A, zw) / n_boxes).flatten(3).sum(-1)  # (B, P, J)
        return (per_box * e).sum(-1).reshape(x.shape[:-2])

    def log_likelihood_delta(
        self,
        x: Tensor,
        x_n: Tensor,
        n: Union[int, Tensor],
        z: Tensor,
        exists: Optional[Tensor] = None,
        exists_n: Optional[Tensor] = None,
    ) -> Tensor:
        """Change of :meth:`log_likelihood_window` when slot ``n`` of ``x`` is set to ``x_n``.

        With truncated point spreads (see :meth:`log_likelihood_window`) only the cells of
        slot ``n``'s old box and of its new box change, so the difference is
        ``sum over box_old ∪ box_new of cell_log_ratio(A') - cell_log_ratio(A)`` (a cell in
        both boxes counted once), with ``A`` and ``A'`` the current and the new amplitude
        there (every other target's truncated spread included). Cost per sample:
        ``4 * (K + 2) * prod(W_a)`` multiply-adds and ``4 * prod(W_a)`` cell log-ratios,
        against ``4 * K^2 * prod(W_a)`` and ``2 * K * prod(W_a)`` for two full windowed
        evaluations (``K / 2`` times fewer log-ratios). This is the
        ``log_likelihood_delta`` hook of :mod:`torchmcmcpf.kernels.moves` (per-target
        refinement) and of :func:`torchmcmcpf.filters.ipmcmc.exchange_iteration`; it equals
        ``log_likelihood_window(x') - log_likelihood_window(x)`` to round-off (tested).
        Pure and branch-free (``torch.compile`` friendly). With ``method="grid"`` it is the
        difference of two :meth:`log_likelihood_grid` calls instead (consistent with
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
        B, K, D = x.shape[0], x.shape[-2], x.shape[-1]
        S = tuple(x.shape[1:-2])
        if tuple(x_n.shape) != (B,) + S + (D,):
            raise ValueError(f"x_n has shape {tuple(x_n.shape)}, expected {(B,) + S + (D,)} to match x {tuple(x.shape)}")
        if exists_n is not None and tuple(exists_n.shape) != (B,) + S:
            raise ValueError(f"exists_n has shape {tuple(exists_n.shape)}, expected {(B,) + S}")
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
        u, s, e = self._flat_inputs(x, exists)  # (B, P, K, n), (B, P, K), (B, P, K)
        P = u.shape[1]
        at = slot[..., None]  # (B, P, 1)
        x_new = x_n.reshape(B, P, 1, D)
        e_new = torch.take_along_dim(e, at, 2) if exists_n is None else exists_n.reshape(B, P, 1).to(x.dtype)
        s_old = torch.take_along_dim(s, at, 2)  # (B, P, 1)
        s_new = self.signal(x_new) * e_new
        s_rest = torch.where(torch.arange(K, device=x.device) == at, torch.zeros_like(s), s)
        # targets: the K slots (slot n silenced), slot n before and after the move: K + 2
        u_all = torch.cat([u, torch.take_along_dim(u, at[..., None], 2), self.measurement_coords(x_new)], 2)
        zero = torch.zeros_like(s_old)
        s_cur = torch.cat([s_rest, s_old, zero], -1)  # (B, P, K + 2)
        s_prop = torch.cat([s_rest, zero, s_new], -1)
        firsts, profiles, in_old = [], [], []
        for a in range(self.n_axes):
            first = self._box_first(u_all[..., a], a)  # (B, P, K + 2)
            boxes = first[..., K:]  # (B, P, 2): old and new box of slot n
            profile, inside = self._box_profiles(boxes, u_all[..., a], first, a)  # (B, P, 2, K + 2, W)
            firsts.append(boxes)
            profiles.append(profile)
            in_old.append(inside[:, :, 1, K])  # (B, P, W): cells of the new box inside the old one
        signals = torch.stack([s_cur, s_prop], 2)[:, :, :, None].expand(B, P, 2, 2, K + 2)  # (B, P, 2v, 2q, K+2)
        factors = [f[:, :, None].expand(B, P, 2, *f.shape[2:]) for f in profiles]
        A = self._contract(signals, factors)  # (B, P, 2 (cur, prop), 2 (old box, new box), *W)
        zw = self._gather_cells(self.prepare_frame(z.to(x.dtype)), firsts)[:, :, None]  # (B, P, 1, 2, *W)
        ratio = self.cell_log_ratio(A, zw)
        diff = ratio[:, :, 1] - ratio[:, :, 0]  # (B, P, 2, *W)
        both = self._contract(torch.ones_like(s_old), [f[..., None, :] for f in in_old])  # (B, P, *W)
        out = diff[:, :, 0].flatten(2).sum(-1) + (diff[:, :, 1] * (1.0 - both)).flatten(2).sum(-1)
        return out.reshape((B,) + S)

    # ---------------------------------------------------------------- checks
    def validate_state(self, x: Tensor, name: str = "x") -> Tensor:
        """Refuse a negative signal (amplitude or power) in a state ``(..., K, D)``."""
        check_nonnegative(self.signal(x), f"{name} (signal component)")
        return x

    def validate(self, z: Tensor, batch_size: Optional[int] = None, name: str = "z") -> Tensor:
        """Check one frame ``z (B, *G)``: shape, batch size, finite, non-negative. Returns ``z``."""
        check_shape(z, name, (None,) + tuple(self.frame_shape))
        if z.shape[0] == 0:
            raise ValueError(f"{name} has shape {tuple(z.shape)}: empty batch, expected B >= 1")
        super().validate(z, batch_size, name)
        return check_nonnegative(z, name)
