"""Separable point spreads summed over targets: per-axis profiles, their contraction over the
whole grid, their truncated values at the cells of boxes, and the neighbour slots of a box.

The amplitude in a cell is ``A = sum_k s_k prod_a h_{k,a}(c_a)`` (Bocquel et al. 2012,
eq. 20); every evaluation path forms it from per-axis factors, either over the whole grid
(:func:`profiles`, :func:`contract`) or at the cells of a box for the few targets whose boxes
overlap it (:func:`neighbour_profiles`, :func:`outer_sum`, sized by :func:`with_neighbours`).
"""

from __future__ import annotations

import math
from collections.abc import Callable, Sequence

import torch

from .... import runtime
from ....runtime import take_along
from ....typing import Tensor
from .geometry import GridGeometry, merge_last

__all__ = ["profiles", "contract", "outer_sum", "neighbour_profiles", "neighbour_index", "with_neighbours",
           "box_in_box", "TERMWISE_MAX"]


def profiles(geometry: GridGeometry, bins: Sequence[Tensor], u: Tensor) -> list[Tensor]:
    """Per-axis point-spread profiles over every cell: ``u (..., K, n) -> [(..., K, N_a)]``
    (``bins[a] (N_a,)`` the cell centres).
    """
    out = []
    for a, w in enumerate(geometry.widths):
        c = bins[a].to(device=u.device, dtype=u.dtype)
        out.append(torch.exp(-((c - u[..., a, None]) ** 2) / (2.0 * w * w)))
    return out


def contract(s: Tensor, factors: Sequence[Tensor]) -> Tensor:
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
        out = torch.bmm(outer.reshape(-1, K, outer.shape[-1]).mT, last.reshape(-1, K, last.shape[-1]))
    return out.reshape(*lead, *(f.shape[-1] for f in factors))


#: Neighbour slots up to which :func:`outer_sum` adds the terms one by one (fused into one
#: loop by ``torch.compile``); above it, outer products and one bmm (faster for many slots,
#: eager or compiled: measured on the crowded ground-radar scene).
TERMWISE_MAX = 4


def outer_sum(s: Tensor, factors: Sequence[Tensor]) -> Tensor:
    """``sum_m s_m f_1[m, i_1] ... f_n[m, i_n]``.

    ``s (*L, M)``, ``factors[a] (*L, M, W_a)`` -> ``(*L, W_1, ..., W_n)``. On the CPU, up to
    :data:`TERMWISE_MAX` neighbour slots the sum is written out term by term, so that
    ``torch.compile`` fuses the whole per-cell computation into one loop (a reduction over
    ``M`` would be materialised); above it, outer products of the first ``n - 1`` factors
    then one bmm with the last. On a GPU (:func:`~torchmcmcpf.runtime.broadcast_sums`), the
    broadcast product summed over ``M``.
    """
    n, M = len(factors), s.shape[-1]

    def product(w: Tensor, fs: Sequence[Tensor]) -> Tensor:  # w (*J) f_1 ... f_n -> (*J, W_1, ..., W_n)
        t = w.reshape(w.shape + (1,) * n)
        for a, f in enumerate(fs):
            t = t * f.reshape(f.shape[:-1] + (1,) * a + f.shape[-1:] + (1,) * (n - 1 - a))
        return t

    if runtime.broadcast_sums(s):
        return product(s, factors).sum(-n - 1)
    if M > TERMWISE_MAX:
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
    for m in range(1, M):  # neighbour slots, not targets: at most TERMWISE_MAX
        out = out + term(m)
    return out


def neighbour_profiles(geometry: GridGeometry, box_firsts: Sequence[Tensor], u: Tensor, firsts: Sequence[Tensor],
                       index: Tensor | None) -> tuple[list[Tensor], list[Tensor]]:
    """Truncated per-axis profiles of selected targets at the cells of boxes ``q``.

    ``box_firsts[a] (..., Q)`` first cells of the boxes evaluated; ``u (..., T, n)`` and
    ``firsts[a] (..., T)`` the targets' coordinates and box starts; ``index (..., Q, M)``
    int64 the targets evaluated in each box, or ``None`` for every target in every box
    (``M = T``, no gather). Returns, per axis, ``profile (..., Q, M, W)``:
    the Gaussian of target ``index[q, m]`` at cell ``t`` of box ``q`` times the indicator
    that the cell lies in the target's box, and that indicator ``(..., Q, M, W)`` (0/1,
    dtype of ``u``); both lists in the :attr:`GridGeometry.box_cells` layout (the last two
    axes as one factor ``(..., Q, M, W_{n-1} W_n)``).
    """
    Q = box_firsts[0].shape[-1]

    def pick(v: Tensor) -> Tensor:  # (..., T) -> (..., Q, M): the selected targets' values per box
        every = v[..., None, :].expand(*v.shape[:-1], Q, v.shape[-1])
        return every if index is None else take_along(every, index, -1)

    per_axis, indicators = [], []
    for a, (bq, fk, W) in enumerate(zip(box_firsts, firsts, geometry.window_sizes)):
        ua, first = pick(u[..., a]), pick(fk)  # (..., Q, M)
        c0, delta = geometry.origins[a], geometry.cell_sizes[a]
        scale = 1.0 / (math.sqrt(2.0) * geometry.widths[a])
        offsets = torch.arange(W, device=u.device, dtype=u.dtype)
        centre = (c0 + delta * (bq[..., None] + offsets)) * scale  # (..., Q, W)
        dist = centre[..., None, :] - (ua * scale)[..., None]  # (..., Q, M, W)
        # cell t of box q lies in the box of target k iff 0 <= first_q - first_k + t < W
        lag = (bq[..., None] - first)[..., None] + offsets  # (..., Q, M, W)
        inside = ((lag >= 0) & (lag < W)).to(u.dtype)
        per_axis.append(torch.exp(-dist.square()) * inside)
        indicators.append(inside)
    return merge_last(per_axis), merge_last(indicators)


def neighbour_index(overlap: Tensor, count: int) -> tuple[Tensor, Tensor]:
    """The first ``count`` targets that overlap each box: ``overlap (..., Q, T)`` bool ->
    ``index (..., Q, count)`` int64 and ``weight (..., Q, count)`` 0/1 (dtype float32;
    0 marks a filler when a box has fewer overlapping targets).
    """
    if count >= overlap.shape[-1]:  # every target (the dense form): no selection
        index = torch.arange(overlap.shape[-1], device=overlap.device).expand(overlap.shape)
        return index, overlap.to(torch.float32)
    w, index = torch.topk(overlap.to(torch.float32), count, dim=-1, sorted=False)
    return index, w


def with_neighbours(cap: int, dense: int, fn: Callable[..., Tensor], prepare: Callable[..., tuple[Tensor, ...]],
                    inputs: tuple[Tensor, ...]) -> Tensor:
    """``fn(count, *parts)`` with ``parts = prepare(*inputs)`` (whose last entry is the
    overlap mask ``(..., Q, T)`` bool of the boxes evaluated and the targets) and ``count``
    at least the most targets overlapping one box: ``dense`` (every other target) when
    ``cap >= dense``, else as :func:`~torchmcmcpf.runtime.neighbour_count` says:
    ``"dense"``; ``"count"``, the maximum read from the device; ``"cond"``, ``cap`` when no
    box overlaps more targets than that, else ``dense``, chosen by ``torch.cond`` so that
    the graph stays whole and shapes static (both branches are compiled). Exact either way.

    The branches take the raw ``inputs`` and run ``prepare`` again: passed intermediates
    instead, torch 2.13's inductor gave some a transposed layout that the compiled
    branch did not expect (an ``assert_size_stride`` failure at run time).
    """
    parts = prepare(*inputs)
    cap = min(int(cap), dense)
    how = "dense" if cap >= dense else runtime.neighbour_count(parts[-1])
    if how == "dense":
        return fn(dense, *parts)
    most = parts[-1].sum(-1).max()
    if how == "count":
        return fn(int(most), *parts)
    return torch.cond(
        most <= cap, lambda *ins: fn(cap, *prepare(*ins)), lambda *ins: fn(dense, *prepare(*ins)), inputs
    )


def box_in_box(indicators: Sequence[Tensor], box: int, spread: int, like: Tensor) -> Tensor:
    """Which cells of box ``box`` lie in the box of spread ``spread``, ``(B, P, *box_cells)``
    0/1, from the per-axis indicators ``(B, P, Q boxes, M spreads, W)`` of
    :func:`~.spread.neighbour_profiles` (a cell lies in a box iff it does on every axis);
    ``like (B, P, 1)`` gives dtype and device. A move's new box against its old one, or, for
    a move of several slots, each box against the earlier ones, so that a cell counts once.
    """
    return outer_sum(torch.ones_like(like), [f[:, :, box, spread][..., None, :] for f in indicators])
