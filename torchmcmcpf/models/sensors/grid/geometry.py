"""Box geometry and ownership of the grid sensors: where each target's box lies, which cells
of the frame it covers, which boxes overlap, and which box counts each cell of their union.

A grid has ``n`` axes of ``N_a`` cells, uniform centres ``origin_a + i * cell_a``. Each target
gets a box of ``W_a = min(2 * window + 1, N_a)`` cells per axis around its nearest cell,
shifted to lie inside the grid (:meth:`GridGeometry.box_first`). The windowed paths hold the
cells of a box in the layout ``(W_1, ..., W_{n-2}, W_{n-1} * W_n)``
(:attr:`GridGeometry.box_cells`): the last two axes merged, so that the innermost loop is
long enough to vectorise.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass
from functools import cached_property

import torch

from .... import runtime
from ...._native.select import where
from ...._validation import check_positive
from ....typing import Tensor

__all__ = ["GridGeometry", "lattice", "uniform_bins", "polar", "materialise", "merge_last"]


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


def uniform_bins(bins: Tensor | Sequence[float], name: str) -> tuple[Tensor, float, float]:
    """Check 1-D, finite, strictly increasing, uniformly spaced cell centres (``name`` for
    the error messages).

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
    sx = where(far, px, one)  # double-where: the unused branch gets no gradient
    sy = where(far, py, torch.zeros_like(py))
    r = torch.sqrt(sx * sx + sy * sy)
    return where(far, r, torch.zeros_like(r)), torch.atan2(sy, sx), sx / r, sy / r


def materialise(t: Tensor) -> Tensor:
    """``t`` unchanged, but computed into its own buffer when compiled for the CPU.

    Inductor inlines a cheap pointwise tensor into each consumer; when the consumer is a
    vectorised per-cell loop whose index into ``t`` needs a division or modulo, the loop
    falls back to scalar code (:func:`~torchmcmcpf.runtime.compiled_for_cpu`). A product
    with a ``1 x 1`` one runs as an extern gemm there, whose input and output are buffers of
    their own (exact: integers are converted to float32 and back, and must stay below
    ``2**24`` in magnitude). Eager or on other devices: ``t``.
    """
    if not runtime.compiled_for_cpu(t):
        return t
    value = t if t.is_floating_point() else t.to(torch.float32)
    one = torch.ones(1, 1, dtype=value.dtype, device=t.device)
    return torch.matmul(value.reshape(-1, 1), one).reshape(t.shape).to(t.dtype)


def merge_last(factors: list[Tensor]) -> list[Tensor]:
    """Per-axis factors ``(..., W_a)`` -> the :attr:`GridGeometry.box_cells` layout (the last
    two replaced by their flattened outer product ``(..., W_{n-1} * W_n)``).
    """
    if len(factors) < 2:
        return factors
    a, b = factors[-2][..., :, None], factors[-1][..., None, :]
    # compiled on the CPU, a matmul with inner size 1 fuses better than the broadcast
    # product (measured, benchmarks/bench_likelihood.py); eager it would be a bmm of tiny
    # matrices, and on a GPU a batched gemm of them (slow there, runtime.broadcast_sums)
    q = torch.matmul(a, b) if runtime.compiled_for_cpu(a) else a * b
    return factors[:-2] + [q.flatten(-2)]


@dataclass(frozen=True)
class GridGeometry:
    """The cells of a separable grid and the boxes of the windowed paths.

    Attributes
    ----------
    frame_shape : ``(N_1, ..., N_n)`` cells per axis.
    origins, cell_sizes : the first centre and the spacing of each axis.
    widths : the point-spread standard deviation ``w_a`` of each axis.
    window : the half-width of a box in cells.

    Example
    -------
    >>> import torch
    >>> from torchmcmcpf.models.sensors.grid import GridGeometry
    >>> grid = GridGeometry((20, 30), origins=(0.0, 0.0), cell_sizes=(5.0, 1.0), widths=(5.0, 1.0), window=3)
    >>> grid.num_cells, grid.window_sizes, grid.box_cells   # 7 x 7 cells per box, the last two merged
    (600, (7, 7), (49,))
    >>> grid.box_firsts(torch.tensor([[50.0, 1.0]]))        # a target at cell (10, 1): box from (7, 0)
    [tensor([7.]), tensor([0.])]
    """

    frame_shape: tuple[int, ...]
    origins: tuple[float, ...]
    cell_sizes: tuple[float, ...]
    widths: tuple[float, ...]
    window: int

    #: targets per word of the ownership masks of :meth:`owned_cells` (int32 words built by
    #: a float32 matmul, exact up to 2**24)
    MASK_BITS = 24

    @property
    def n_axes(self) -> int:
        """Number of grid axes ``n``."""
        return len(self.frame_shape)

    @property
    def num_cells(self) -> int:
        """Number of cells of one frame, ``N_1 * ... * N_n``."""
        return math.prod(self.frame_shape)

    @cached_property
    def window_sizes(self) -> tuple[int, ...]:
        """Cells per axis of one target's box: ``min(2 * window + 1, N_a)``."""
        return tuple(min(2 * self.window + 1, n) for n in self.frame_shape)

    @cached_property
    def box_cells(self) -> tuple[int, ...]:
        """Layout of the cells of one box on the windowed paths: ``(W_1, ..., W_{n-2},
        W_{n-1} * W_n)``, the last two axes merged so that the innermost loop is long enough
        to vectorise (``W_a`` is 7 or 9, the vector width 8 or 16).
        """
        W = self.window_sizes
        return W if len(W) < 2 else W[:-2] + (W[-2] * W[-1],)

    def box_first(self, ua: Tensor, axis: int) -> Tensor:
        """First cell (float index) of the box on ``axis`` of targets at coordinates ``ua``:
        the nearest cell minus ``window``, shifted to lie inside the grid. Same shape as ``ua``.
        """
        N, W = self.frame_shape[axis], self.window_sizes[axis]
        nearest = torch.round((ua.detach() - self.origins[axis]) / self.cell_sizes[axis])
        return (nearest - self.window).clamp(0, N - W)

    def box_firsts(self, u: Tensor) -> list[Tensor]:
        """:meth:`box_first` of every axis: ``u (..., n) -> [(...)] * n``."""
        return [self.box_first(u[..., a], a) for a in range(self.n_axes)]

    def overlaps(self, box_firsts: Sequence[Tensor], firsts: Sequence[Tensor]) -> Tensor:
        """Whether box ``q`` (first cells ``box_firsts[a] (..., Q)``) and the box of target ``k``
        (``firsts[a] (..., T)``) share a cell: ``(..., Q, T)`` bool.
        """
        near = [(bq[..., :, None] - fk[..., None, :]).abs() < W
                for bq, fk, W in zip(box_firsts, firsts, self.window_sizes)]
        out = near[0]
        for other in near[1:]:
            out = out & other
        return out

    def box_offsets(self) -> Tensor:
        """Offset of each cell of a box from the box's first cell in the flattened frame,
        ``(*box_cells)`` int64 (the sensor keeps it as a buffer, ``box_offsets``: compiled,
        the gather of :meth:`gather_cells` then loads its cell offsets instead of recomputing
        them from the merged index with an integer division per cell).
        """
        G, W = self.frame_shape, self.window_sizes
        off = torch.zeros((), dtype=torch.int64)
        for a, w in enumerate(W):
            t = torch.arange(w, dtype=torch.int64) * math.prod(G[a + 1:])
            off = off[..., None] + t
        return off.reshape(self.box_cells)

    def flat_cells(self, firsts: Sequence[Tensor], offsets: Tensor) -> Tensor:
        """Flat index in one frame of every cell of boxes with first cells ``firsts[a] (...)``:
        ``(..., *box_cells)`` int64 (the box's first cell plus ``offsets``, :meth:`box_offsets`).
        """
        base = firsts[0].long() * math.prod(self.frame_shape[1:])
        for a in range(1, self.n_axes):
            base = base + firsts[a].long() * math.prod(self.frame_shape[a + 1:])
        return base.reshape(base.shape + (1,) * offsets.dim()) + offsets

    def gather_cells(self, zc: Tensor, firsts: Sequence[Tensor], offsets: Tensor) -> Tensor:
        """``zc (B, *G)`` at the cells of boxes with first cells ``firsts[a] (B, P, Q)`` ->
        ``(B, P, Q, *box_cells)``: the flat index of each box's first cell plus ``offsets``,
        one gather along the flat frame (``B`` a run's frame, or one frame for every run). The
        same values as indexing ``zc.flatten(1)[run, index]``, 5x faster eager on the CPU (0.21
        against 1.12 ms for 343,000 cells of 10 frames).
        """
        index = self.flat_cells(firsts, offsets)  # (B, P, Q, *V)
        b = max(zc.shape[0], index.shape[0])
        flat = zc.flatten(1).expand(b, -1)
        return flat.gather(1, index.expand((b,) + index.shape[1:]).reshape(b, -1)).reshape((b,) + index.shape[1:])

    def owned_cells(self, firsts: Sequence[Tensor], live: Tensor) -> Tensor:
        """Which cells each box counts on the windowed path, so that every cell of the union
        of the live boxes is counted exactly once: cell ``t`` of box ``j`` when ``j`` is live
        and no live box ``i < j`` contains the cell (the union's cells belong to the first box
        that holds them).

        ``firsts[a] (b, p, K)`` the box starts, ``live (b, p, K)`` bool -> ``(b, p, K,
        *box_cells)`` bool. Per axis ``a``, ``cover_a[c]`` is the bit set of the live boxes
        whose span on that axis holds grid cell ``c`` (int32 words of :attr:`MASK_BITS`
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
        V = self.box_cells
        if K == 1:  # no earlier box: a live box owns all its cells (skips the covers' O(N_a) work)
            return live.reshape(live.shape + (1,) * len(V)).expand(live.shape + V)
        words = -(-K // self.MASK_BITS)
        i = torch.arange(K, device=live.device)
        # (I, words): target i's bit in its word, as a float
        bits = where((i // self.MASK_BITS)[:, None] == torch.arange(words, device=live.device),
                           torch.exp2((i % self.MASK_BITS).float())[:, None], 0.0)
        add = (live[..., None] * bits).to(torch.float32).mT  # (b, p, words, I): live boxes' bits
        earlier = ((i[None, :] < i[:, None]).float() @ bits).int()  # (J, words): boxes i < j
        masks = []
        for first, W, N in zip(firsts, self.window_sizes, self.frame_shape):
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

    def extent(self) -> tuple[list[float], list[float], float]:
        """Lower and upper edges of the grid per axis and ``log`` of its volume (the field of view)."""
        lo = [o - 0.5 * c for o, c in zip(self.origins, self.cell_sizes)]
        hi = [o + (N - 0.5) * c for o, c, N in zip(self.origins, self.cell_sizes, self.frame_shape)]
        return lo, hi, sum(math.log(h - lw) for lw, h in zip(lo, hi))
