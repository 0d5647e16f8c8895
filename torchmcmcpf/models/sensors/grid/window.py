"""The windowed evaluation, the fast path: the exact log-likelihood of the sensor whose point
spreads are truncated to each target's box, summed box by box over the union of the boxes
(:meth:`~.sensor.SeparableGridSensor.log_likelihood_window` states the maths), or, on a grid
with no more cells than the boxes (:func:`~.amplitudes.whole_grid`), the truncated spreads
summed over the whole grid (a cell outside every box has ratio 0).
"""

from __future__ import annotations

import torch

from ...._native.select import where
from ....runtime import take_along
from ....typing import Tensor
from . import chunks, native
from ._protocol import GridSensorLike
from .amplitudes import amplitude_cache, whole_grid
from .geometry import materialise
from .inputs import check_inputs, flat_inputs
from .spread import neighbour_index, neighbour_profiles, outer_sum, with_neighbours

__all__ = ["log_likelihood", "parts"]


def parts(sensor: GridSensorLike, x: Tensor, z: Tensor, exists: Tensor | None = None) -> tuple[Tensor, ...]:
    """``x (b, p, K, D)``, ``z (b, *G)``, ``exists (b, p, K)`` -> ``(u, s, e, zc, *firsts,
    others)``: see :func:`~.inputs.flat_inputs`; ``firsts[a] (b, p, K)`` the box starts and
    ``others (b, p, J, K)`` whether the boxes of live targets ``j != k`` overlap.
    """
    K = x.shape[-2]
    geometry = sensor.geometry
    u, s, e = flat_inputs(sensor, x, exists)
    firsts = geometry.box_firsts(u)  # (b, p, K) each
    live = e > 0
    others = geometry.overlaps(firsts, firsts) & live[..., :, None] & live[..., None, :]
    others = others & ~torch.eye(K, dtype=torch.bool, device=x.device)  # (b, p, J, K)
    # the prepared frame in a buffer of its own when compiled for the CPU: Inductor otherwise
    # recomputes it (a sqrt and a division for the radar) in the per-cell loop that gathers
    # it, once per box cell (the radar SIR's compiled step 183 -> 159 ms, N = 5000, K = 10)
    return (u, s, e, materialise(sensor.prepare_frame(z.to(x.dtype))), *firsts, others)


def _box_sums(sensor: GridSensorLike, count: int, u: Tensor, s: Tensor, e: Tensor, zc: Tensor,
              *rest: Tensor) -> Tensor:
    """Windowed log-likelihood ``(b, p)`` of a block of samples from :func:`parts`, with
    ``count`` neighbour slots per box (at least the most other boxes overlapping one box).
    """
    *firsts, others = rest
    geometry = sensor.geometry
    b, p, K = s.shape
    index = torch.arange(K, device=u.device).expand(b, p, K)[..., None]  # (b, p, J, 1): the box's own target
    weight = torch.ones(index.shape, dtype=s.dtype, device=u.device)
    if count > 0:
        nb, w = neighbour_index(others, count)  # (b, p, J, count)
        index, weight = torch.cat([index, nb], -1), torch.cat([weight, w.to(s.dtype)], -1)
    factors, _ = neighbour_profiles(geometry, firsts, u, firsts, index)  # (b, p, J, M, W) each
    s_nb = take_along(s[..., None, :].expand(b, p, K, K), index, -1) * weight  # (b, p, J, M)
    A = outer_sum(s_nb, factors)  # (b, p, J, *W)
    zw = geometry.gather_cells(zc, firsts, sensor.box_offsets)  # (b, p, J, *W)
    owned = geometry.owned_cells(firsts, e > 0)  # (b, p, J, *W): each cell of the union counted once
    V = geometry.box_cells
    # one reduction over boxes and cells (fused with the cell terms under torch.compile)
    return where(owned, sensor.cell_log_ratio(A, zw), 0.0).sum(tuple(range(2, 3 + len(V))))


def log_likelihood(sensor: GridSensorLike, x: Tensor, z: Tensor, exists: Tensor | None = None) -> Tensor:
    """The windowed log-likelihood ``(B, *S)`` of ``x (B, *S, K, D)``, blocks of at most
    :func:`~.chunks.window_chunk_size` samples (checkpointed under autograd).
    """
    check_inputs(sensor, x, z, exists)
    if native.applies(sensor, x):  # the radar on the CPU: one C loop per particle
        return native.log_likelihood(sensor, x, z, exists)
    B, K = x.shape[0], x.shape[-2]
    xf = x.reshape(B, -1, K, x.shape[-1])  # (B, P, K, D)
    ef = None if exists is None else exists.reshape(B, -1, K)

    grid = whole_grid(sensor, K)

    def block(b0: int, b1: int, p0: int, p1: int) -> Tensor:
        xb, zb = xf[b0:b1, p0:p1], z[b0:b1]
        eb = None if ef is None else ef[b0:b1, p0:p1]
        if grid:  # no more cells than the K boxes: the truncated spreads summed on the whole grid
            A = amplitude_cache(sensor, xb, eb)  # (b, p, G)
            zc = sensor.prepare_frame(zb.to(x.dtype)).reshape(A.shape[0], 1, A.shape[-1])
            return sensor.cell_log_ratio(A, zc).sum(-1)
        inputs = (xb, zb) + (() if eb is None else (eb,))
        return with_neighbours(sensor.max_neighbours, K - 1, lambda c, *a: _box_sums(sensor, c, *a),
                               lambda *a: parts(sensor, *a), inputs)

    chunk = chunks.window_chunk_size(sensor.geometry, sensor.memory_budget, K, x.dtype)
    return chunks.in_blocks(xf, block, chunk).reshape(x.shape[:-2])
