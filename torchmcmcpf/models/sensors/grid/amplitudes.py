"""The chain cache of the grid sensors: each chain's amplitude per cell (truncated spreads, as
the windowed path), so that a move of one slot (or of M slots) reads the amplitudes at its two
(2M) boxes instead of summing the neighbours' spreads there, and the change a move makes to them.
On a grid with no more cells than the move's boxes (:func:`whole_grid`: the crossing's 640
cells against two boxes of 343), the move reads and changes the whole grid instead: the same
sum, without the boxes' gathers and the repeats' masks.

The cache is a field of the chains' state (:class:`~torchmcmcpf.kernels.exchange.ExchangeChains`,
``amplitude``): made once at the start of a step (:func:`amplitude_cache`), read by a move
(:func:`log_likelihood_delta_cached`, which also returns the move's change) and advanced for
the accepted moves by :meth:`~torchmcmcpf.models.base.SensorModel.update_amplitude_cache`, the one
place where it changes.
"""

from __future__ import annotations

import math

import torch

from ....runtime import take_along
from ....typing import Tensor
from . import native
from ._protocol import GridSensorLike
from .inputs import check_inputs, check_move, check_state, flat_inputs
from .slots import truncated_amplitude
from .spread import box_in_box, neighbour_profiles, outer_sum

__all__ = ["amplitude_cache", "log_likelihood_delta_cached", "log_likelihood_delta_on_grid", "whole_grid"]


def amplitude_cache(sensor: GridSensorLike, x: Tensor, exists: Tensor | None = None) -> Tensor:
    """Each sample's amplitude per cell, ``(B, *S, G)`` flat over the grid."""
    check_state(sensor, x, exists)
    u, s, _ = flat_inputs(sensor, x, exists)  # (B, P, K, n), (B, P, K)
    geometry = sensor.geometry
    firsts = geometry.box_firsts(u)
    return truncated_amplitude(geometry, sensor.all_bins(), u, s, firsts).reshape(x.shape[:-2] + (geometry.num_cells,))


def whole_grid(sensor: GridSensorLike, boxes: int) -> bool:
    """Whether a move whose spreads span ``boxes`` boxes (``2M`` for ``M`` slots) is evaluated
    on the whole grid: when the grid has at most ``boxes * prod(W_a)`` cells. Its terms then
    cost no more than the boxes' (``G`` cell log-ratios a sample against ``2M prod(W_a)``),
    and it needs no gathers of the cache and frame at the boxes nor masks of their repeated
    cells: on the crossing's grid (640 cells, boxes of 343) a one-slot move of 5 runs x 50
    chains takes 2.8 against 5.2 ms eager (one thread, AMD EPYC).
    """
    return sensor.geometry.num_cells <= boxes * math.prod(sensor.geometry.window_sizes)


def log_likelihood_delta_cached(sensor: GridSensorLike, cache: Tensor, x: Tensor, x_n: Tensor, n: Tensor,
                                z: Tensor, exists: Tensor | None = None, exists_n: Tensor | None = None
                                ) -> tuple[Tensor, Tensor | None, Tensor]:
    """The change of a move of one slot or of ``M`` slots read from the cache: ``(delta (B,
    *S), cells, change)`` (:meth:`~.sensor.SeparableGridSensor.log_likelihood_delta_cached`),
    over the ``2M`` boxes or, where :func:`whole_grid` says so, over the whole grid.
    """
    B = x.shape[0]
    check_inputs(sensor, x, z, exists)
    S = tuple(x.shape[1:-2])
    G = sensor.geometry.num_cells
    if tuple(cache.shape) != (B,) + S + (G,):
        raise ValueError(f"cache has shape {tuple(cache.shape)}, expected {(B,) + S + (G,)}")
    terms = _moved_terms(sensor, x, x_n, n, exists, exists_n)
    if native.applies(sensor, x) and cache.dtype == torch.float32:  # the radar on the CPU: one C loop a chain,
        return _native_delta(sensor, cache, terms, z)  # boxes on any grid
    u, s = _signed(terms)
    firsts = sensor.geometry.box_firsts(u)  # the loop finds its boxes itself
    if whole_grid(sensor, s.shape[-1]):  # every entry of the cache changes, in order: no cells
        delta, change = _grid_delta(sensor, cache.reshape(B, -1, G), u, s, firsts, z)
        return delta.reshape((B,) + S), None, change.reshape(cache.shape)
    cells, change = _box_change(sensor, u, s, firsts)
    A = cache.reshape(-1).gather(0, cells.reshape(-1)).reshape(change.shape)  # (B, P, 2M, *V)
    # the frame's cells gathered, then prepared (per cell): 2M boxes a move, not the whole grid
    zw = sensor.prepare_frame(sensor.geometry.gather_cells(z.to(x.dtype), firsts, sensor.box_offsets))
    delta = _cell_changes(sensor, A, change, zw).flatten(2).sum(-1)  # each cell once: 0 change on repeats
    return delta.reshape((B,) + S), cells.reshape((B,) + S + cells.shape[2:]), \
        change.reshape((B,) + S + change.shape[2:])


def move_terms(sensor: GridSensorLike, x: Tensor, exists: Tensor | None = None) -> Tensor:
    """Each slot's measured coordinates and amplitude times its flag, ``x (B, *S, K, D) ->
    (B, *S, K, n + 1)``: a move's spreads, unsigned (:func:`_moved_terms`), for
    :func:`log_likelihood_delta_terms`.
    """
    e = torch.ones_like(x[..., 0]) if exists is None else exists.to(x.dtype)
    return torch.cat([sensor.measurement_coords(x), (sensor.signal(x) * e).unsqueeze(-1)], -1)


def log_likelihood_delta_terms(sensor: GridSensorLike, cache: Tensor, terms: Tensor, z: Tensor
                               ) -> tuple[Tensor, Tensor, Tensor]:
    """:func:`log_likelihood_delta_cached` by the C loop from the moved slots' :func:`move_terms`
    ``terms (B, *S, 2M, n + 1)`` (slot 0 before, after, slot 1 before, ...). The caller made
    ``terms`` where :func:`~.native.applies`.
    """
    _check_cache(sensor, cache, tuple(terms.shape[:-2]))
    return _native_delta(sensor, cache, terms, z)


def log_likelihood_delta_rows(sensor: GridSensorLike, cache: Tensor, terms: Tensor, slot: Tensor, terms_new: Tensor,
                              z: Tensor) -> tuple[Tensor, Tensor, Tensor]:
    """:func:`log_likelihood_delta_terms` of moves of ``M`` distinct slots from the rows ``terms
    (B, *S, K, 4)`` at ``slot (B, *S, M)`` to ``terms_new (B, *S, M, 4)``, the old rows read in
    the C loop (:func:`.native.delta_rows`): the same values as the rows gathered and
    interleaved.
    """
    _check_cache(sensor, cache, tuple(terms.shape[:-2]))
    return native.delta_rows(sensor, cache, terms, slot.to(torch.int64), terms_new, z)


def _check_cache(sensor: GridSensorLike, cache: Tensor, lead: tuple[int, ...]) -> None:
    """A ValueError unless ``cache`` is ``(*lead, G)``, the samples' cells."""
    if tuple(cache.shape) != lead + (sensor.geometry.num_cells,):
        raise ValueError(f"cache has shape {tuple(cache.shape)}, expected {lead + (sensor.geometry.num_cells,)}")


def _native_delta(sensor: GridSensorLike, cache: Tensor, terms: Tensor, z: Tensor) -> tuple[Tensor, Tensor, Tensor]:
    """The C loop's move from ``terms (B, *S, 2M, n + 1)`` and ``cache (B, *S, G)``, shaped
    as :func:`log_likelihood_delta_cached` returns it.
    """
    B, S, R = terms.shape[0], tuple(terms.shape[1:-2]), terms.shape[-2]
    u, s = _signed(terms.reshape(B, -1, R, terms.shape[-1]))
    delta, cells, change = native.delta_cached(sensor, cache.reshape(B, -1, cache.shape[-1]), u, s, z)
    return delta.reshape((B,) + S), cells.reshape((B,) + S + cells.shape[2:]), \
        change.reshape((B,) + S + change.shape[2:])


def log_likelihood_delta_on_grid(sensor: GridSensorLike, x: Tensor, x_n: Tensor, n: Tensor, z: Tensor,
                                 exists: Tensor | None = None, exists_n: Tensor | None = None) -> Tensor:
    """:func:`log_likelihood_delta_cached`'s whole-grid sum without a cache (the amplitudes of
    ``x`` made afresh) nor the cells and change it returns for one: ``(B, *S)``. Inputs
    checked by the caller (:func:`~.delta.log_likelihood_delta`).
    """
    u, s = _moved(sensor, x, x_n, n, exists, exists_n)
    firsts = sensor.geometry.box_firsts(u)
    A = amplitude_cache(sensor, x, exists).reshape(s.shape[0], s.shape[1], -1)
    return _grid_delta(sensor, A, u, s, firsts, z)[0].reshape(x.shape[:-2])


def _cell_changes(sensor: GridSensorLike, A: Tensor, change: Tensor, zw: Tensor) -> Tensor:
    """Each cell's log-ratio after the move minus before, amplitudes ``A`` and ``A + change``
    (round-off of the kept sums may leave -1e-7 where a spread left: amplitudes are >= 0).
    """
    return sensor.cell_log_ratio((A + change).clamp_min(0.0), zw) - sensor.cell_log_ratio(A.clamp_min(0.0), zw)


def _grid_delta(sensor: GridSensorLike, A: Tensor, u: Tensor, s: Tensor, firsts: list[Tensor], z: Tensor
                ) -> tuple[Tensor, Tensor]:
    """The move of :func:`_moved` summed over the whole grid from the amplitudes ``A (B, P,
    G)``: ``(delta (B, P), change (B, P, G))``.
    """
    B, P, G = A.shape
    change = truncated_amplitude(sensor.geometry, sensor.all_bins(), u, s, firsts).reshape(B, P, G)
    zc = sensor.prepare_frame(z.to(A.dtype)).reshape(B, 1, G)
    return _cell_changes(sensor, A, change, zc).sum(-1), change


def _moved(sensor: GridSensorLike, x: Tensor, x_n: Tensor, n: Tensor, exists: Tensor | None,
           exists_n: Tensor | None) -> tuple[Tensor, Tensor]:
    """The move's ``2M`` spreads, flat over the samples: their measured coordinates ``u (B, P,
    2M, n)`` and signed amplitudes ``s (B, P, 2M)`` (:func:`_signed` of :func:`_moved_terms`;
    their boxes: ``sensor.geometry.box_firsts(u)``).
    """
    return _signed(_moved_terms(sensor, x, x_n, n, exists, exists_n))


def _moved_terms(sensor: GridSensorLike, x: Tensor, x_n: Tensor, n: Tensor, exists: Tensor | None,
                 exists_n: Tensor | None) -> Tensor:
    """The :func:`move_terms` of a move's ``2M`` spreads, flat over the samples, ``(B, P, 2M,
    n + 1)``, in the order slot 0 before, after, slot 1 before, after, ...
    """
    B, K, D = x.shape[0], x.shape[-2], x.shape[-1]
    S = tuple(x.shape[1:-2])
    P = math.prod(S)
    many = check_move(x, x_n, exists_n)  # (B, *S, M, D): M slots, else one (B, *S, D)
    M = x_n.shape[-2] if many else 1
    slot = n.to(device=x.device, dtype=torch.int64).expand((B,) + S + ((M,) if many else ())).reshape(B, P, M)
    xf = x.reshape(B, P, K, D)
    e = torch.ones_like(xf[..., 0]) if exists is None else exists.reshape(B, P, K).to(x.dtype)
    e_old = take_along(e, slot, 2)  # (B, P, M)
    e_new = e_old if exists_n is None else exists_n.reshape(B, P, M).to(x.dtype)
    moved = torch.stack([take_along(xf, slot[..., None], 2), x_n.reshape(B, P, M, D)], 3)
    return move_terms(sensor, moved.reshape(B, P, 2 * M, D), torch.stack([e_old, e_new], -1).reshape(B, P, 2 * M))


def _signed(terms: Tensor) -> tuple[Tensor, Tensor]:
    """A move's spreads from their :func:`move_terms` ``(..., 2M, n + 1)`` (each slot before,
    then after): the coordinates ``(..., 2M, n)`` and the amplitudes signed, minus before and
    plus after, ``(..., 2M)`` (a negation: exact).
    """
    sign = torch.tensor([-1.0, 1.0] * (terms.shape[-2] // 2), dtype=terms.dtype, device=terms.device)
    return terms[..., :-1], terms[..., -1] * sign


def _box_change(sensor: GridSensorLike, u: Tensor, s: Tensor, firsts: list[Tensor]) -> tuple[Tensor, Tensor]:
    """Where and by how much the move of :func:`_moved` changes the cache on its boxes: ``cells,
    change (B, P, 2M, *V)`` over the boxes old, new of the first moved slot, then of the next
    (``change`` 0 at the cells an earlier box holds, so that each cell changes once).
    """
    B, P, M = s.shape[0], s.shape[1], s.shape[2] // 2
    geometry = sensor.geometry
    factors, indicators = neighbour_profiles(geometry, firsts, u, firsts, None)  # (B, P, 2M box, 2M spread, W)
    change = outer_sum(s[:, :, None], factors)  # (B, P, 2M, *V)
    # cell t of box q repeats a cell of an earlier box j < q where it lies in box j: every
    # pair (q, j < q) in one product of the per-axis indicators (0/1: exact), summed per box q
    once = [torch.ones_like(change[:, :, 0])]
    if M == 1:
        once.append((box_in_box(indicators, 1, 0, s[..., :1]) == 0).to(change.dtype))
    else:
        qs = [q for q in range(1, 2 * M) for _ in range(q)]  # the pairs (1, 0), (2, 0), (2, 1), ...
        js = [j for q in range(1, 2 * M) for j in range(q)]
        ones = torch.ones(s.shape[:2] + (len(qs), 1), dtype=s.dtype, device=s.device)
        inside = outer_sum(ones, [f[:, :, qs, js][..., None, :] for f in indicators])  # (B, P, pairs, *V)
        first = 0
        for q in range(1, 2 * M):  # 2M boxes, static
            once.append((inside[:, :, first:first + q].sum(2) == 0).to(change.dtype))
            first += q
    rows = torch.arange(B * P, device=s.device).reshape((B, P) + (1,) * (1 + len(geometry.box_cells))) \
        * geometry.num_cells
    return geometry.flat_cells(firsts, sensor.box_offsets) + rows, change * torch.stack(once, 2)
