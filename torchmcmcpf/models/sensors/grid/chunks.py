"""Memory chunking of the grid sensors: how many samples one block of an evaluation holds so
that its temporaries stay within the sensor's ``memory_budget``, and the loop over blocks
(each checkpointed when autograd records, so the memory held for the backward pass is
bounded by the same budget).
"""

from __future__ import annotations

import math
from collections.abc import Callable

import torch
from torch.utils.checkpoint import checkpoint

from ....typing import Tensor
from .geometry import GridGeometry

__all__ = ["GRID_TEMPS", "WINDOW_TEMPS", "grid_chunk_size", "window_chunk_size", "in_blocks"]

#: temporaries of one sample held at once by the whole-grid path, in units of the grid size
#: G (the amplitude, the gathered frame term and the cell log-ratio with its intermediates,
#: those of the float32 log I0 polynomial included), on top of the ``K * prod(N_1..N_{n-1})``
#: outer-product buffer. Checked against a measured peak in tests/models/test_radar.py.
GRID_TEMPS = 9

#: per-cell temporaries of one box cell held at once by the eager windowed path: the
#: amplitude sum with its running terms, the ownership masks, the frame cells, the log
#: ratio with the intermediates of the float32 log I0 polynomial (as :data:`GRID_TEMPS`)
WINDOW_TEMPS = 12


def _itemsize(dtype: torch.dtype) -> int:
    return torch.empty((), dtype=dtype).element_size()


def grid_chunk_size(geometry: GridGeometry, budget: int, num_targets: int, dtype: torch.dtype) -> int:
    """Samples (rows of the flattened ``B * prod(S)``) per block of the whole-grid path: one
    sample holds ``K * prod(N_1..N_{n-1})`` elements of outer products plus about
    ``GRID_TEMPS * G`` elements of per-cell temporaries; the largest count whose total stays
    within ``budget`` bytes (at least 1).
    """
    per_sample = _itemsize(dtype) * (
        num_targets * math.prod(geometry.frame_shape[:-1]) + GRID_TEMPS * geometry.num_cells
    )
    return max(1, budget // per_sample)


def window_chunk_size(geometry: GridGeometry, budget: int, num_targets: int, dtype: torch.dtype) -> int:
    """Samples per block of the windowed paths: one sample holds about ``WINDOW_TEMPS * K *
    prod(W_a)`` elements of per-cell temporaries, whatever the number of neighbour slots
    (they are summed term by term); the largest count whose total stays within ``budget``
    bytes (at least 1).
    """
    per_sample = _itemsize(dtype) * num_targets * math.prod(geometry.window_sizes) * WINDOW_TEMPS
    return max(1, budget // per_sample)


def in_blocks(x: Tensor, fn: Callable[[int, int, int, int], Tensor], chunk: int) -> Tensor:
    """Apply ``fn(b0, b1, p0, p1) -> (b, p, ...)`` to blocks of at most ``chunk`` rows of the
    flattened ``(B, P)`` samples of ``x (B, P, ...)`` (a block is ``runs x samples``), each
    block checkpointed when autograd records, and reassemble ``(B, P, ...)``. Chunks of
    rows, not a loop per particle or per run.
    """
    B, P = x.shape[:2]
    runs = min(B, chunk)
    samples = max(1, chunk // runs)
    if runs >= B and samples >= P:
        return fn(0, B, 0, P)
    grad = torch.is_grad_enabled() and x.requires_grad
    out = []
    for b in range(0, B, runs):
        row = []
        for p in range(0, P, samples):
            args = (b, min(b + runs, B), p, min(p + samples, P))
            row.append(checkpoint(fn, *args, use_reentrant=False) if grad else fn(*args))
        out.append(torch.cat(row, 1))
    return torch.cat(out)
