"""The whole-grid evaluation, the reference of the grid sensors: the cell log-ratio summed
over every cell, the amplitude ``A`` over the grid as ``sum_k s_k a_k(i_1) ... a_k(i_n)``
(per-axis profiles, one bmm), in blocks of samples sized from the memory budget.
"""

from __future__ import annotations

from ....typing import Tensor
from . import chunks
from ._protocol import GridSensorLike
from .inputs import check_inputs, flat_inputs
from .spread import contract, profiles

__all__ = ["log_likelihood", "signal_grid"]


def signal_grid(sensor: GridSensorLike, x: Tensor, exists: Tensor | None = None) -> Tensor:
    """Noise-free signal ``A`` in every cell: ``x (B, *S, K, D) -> (B, *S, *G)`` (not chunked)."""
    u, s, _ = flat_inputs(sensor, x, exists)
    A = contract(s, profiles(sensor.geometry, sensor.all_bins(), u))
    return A.reshape(x.shape[:-2] + sensor.frame_shape)


def log_likelihood(sensor: GridSensorLike, x: Tensor, z: Tensor, exists: Tensor | None = None) -> Tensor:
    """:meth:`~.sensor.SeparableGridSensor.cell_log_ratio` summed over every cell of the grid:
    ``x (B, *S, K, D)``, ``z (B, *G)``, ``exists (B, *S, K)`` -> ``(B, *S)``. Blocks of at most
    :func:`~.chunks.grid_chunk_size` rows of ``(B, prod(S))`` at a time (checkpointed under
    autograd).
    """
    check_inputs(sensor, x, z, exists)
    K = x.shape[-2]
    u, s, _ = flat_inputs(sensor, x, exists)  # (B, P, K, n), (B, P, K)
    zc = sensor.prepare_frame(z.to(x.dtype))[:, None]  # (B, 1, *G), broadcast, never copied
    bins = sensor.all_bins()

    def block(b0: int, b1: int, p0: int, p1: int) -> Tensor:
        A = contract(s[b0:b1, p0:p1], profiles(sensor.geometry, bins, u[b0:b1, p0:p1]))
        return sensor.cell_log_ratio(A, zc[b0:b1]).flatten(2).sum(-1)

    chunk = chunks.grid_chunk_size(sensor.geometry, sensor.memory_budget, K, x.dtype)
    return chunks.in_blocks(u, block, chunk).reshape(x.shape[:-2])
