"""Every slot of one reference state moved on its own (the weights of the independent-partition
filter): one truncated amplitude grid of the reference per run, then the cells of each
candidate's box (:meth:`~.sensor.SeparableGridSensor.log_likelihood_slot_changes` states
the maths).
"""

from __future__ import annotations

from collections.abc import Sequence

import torch

from ....typing import Tensor
from ...base import check_reference
from . import chunks
from ._protocol import GridSensorLike
from .geometry import GridGeometry
from .inputs import check_inputs
from .spread import contract, neighbour_profiles, outer_sum, profiles

__all__ = ["log_likelihood_slot_changes", "truncated_amplitude"]


def truncated_amplitude(geometry: GridGeometry, bins: Sequence[Tensor], u: Tensor, s: Tensor,
                        firsts: Sequence[Tensor]) -> Tensor:
    """Amplitude over the whole grid with the spreads truncated to the boxes (the windowed
    path's): ``u (..., K, n)``, ``s (..., K)`` (times existence), ``firsts[a] (..., K)`` the
    box starts -> ``(..., *G)``; one contraction (``K * G`` multiply-adds per sample).
    """
    cells = [torch.arange(N, device=u.device) for N in geometry.frame_shape]
    truncated = [p * ((c >= f[..., None]) & (c < f[..., None] + W)).to(p.dtype)  # (..., K, N_a)
                 for p, c, f, W in zip(profiles(geometry, bins, u), cells, firsts, geometry.window_sizes)]
    return contract(s, truncated)


def log_likelihood_slot_changes(sensor: GridSensorLike, ref: Tensor, x: Tensor, z: Tensor) -> Tensor:
    """``ref (B, K, D)``, ``x (B, *S, K, D)``, ``z (B, *G)`` -> ``(B, *S, K)`` on the windowed
    path (blocks of samples sized from the memory budget).
    """
    B, K, D = check_reference(ref, x)
    check_inputs(sensor, x, z, None)
    geometry = sensor.geometry
    xf = x.reshape(B, -1, K, D)
    zc = sensor.prepare_frame(z.to(x.dtype))
    u_ref, s_ref = sensor.measurement_coords(ref), sensor.signal(ref)  # (B, K, n), (B, K)
    f_ref = geometry.box_firsts(u_ref)  # (B, K) each
    A = truncated_amplitude(geometry, sensor.all_bins(), u_ref, s_ref, f_ref)  # (B, *G): the reference's

    def block(b0: int, b1: int, p0: int, p1: int) -> Tensor:
        return _slot_term(sensor, xf[b0:b1, p0:p1], zc[b0:b1], A[b0:b1], u_ref[b0:b1], s_ref[b0:b1],
                          [f[b0:b1] for f in f_ref])

    moved = chunks.in_blocks(xf, block, chunks.window_chunk_size(geometry, sensor.memory_budget, K, x.dtype))
    at_ref = _slot_term(sensor, ref[:, None], zc, A, u_ref, s_ref, f_ref)  # (B, 1, K)
    return (moved - at_ref).reshape(x.shape[:-1])


def _slot_term(sensor: GridSensorLike, y: Tensor, zc: Tensor, A: Tensor, u_ref: Tensor, s_ref: Tensor,
               f_ref: Sequence[Tensor]) -> Tensor:
    """``term_k(y)`` of :meth:`~.sensor.SeparableGridSensor.log_likelihood_slot_changes` for a
    block: ``y (b, p, K, D)``, ``zc, A (b, *G)``, ``u_ref (b, K, n)``, ``s_ref (b, K)``,
    ``f_ref[a] (b, K)`` -> ``(b, p, K)``.
    """
    b, p, K, _ = y.shape
    geometry = sensor.geometry
    u, s = sensor.measurement_coords(y), sensor.signal(y)  # (b, p, K, n), (b, p, K)
    firsts = geometry.box_firsts(u)  # (b, p, K)
    # targets: the K candidate slots, then the K reference slots
    u_all = torch.cat([u, u_ref[:, None].expand(b, p, K, u.shape[-1])], 2)
    f_all = [torch.cat([f, fr[:, None].expand(b, p, K)], 2) for f, fr in zip(firsts, f_ref)]
    k = torch.arange(K, device=y.device)
    index = torch.stack([k, k + K], -1).expand(b, p, K, 2)  # box k: candidate k, reference k
    factors, _ = neighbour_profiles(geometry, firsts, u_all, f_all, index)  # (b, p, K, 2, W) each
    own = outer_sum(s[..., None], [f[..., :1, :] for f in factors])  # (b, p, K, *V)
    ref_k = outer_sum(s_ref[:, None, :, None], [f[..., 1:, :] for f in factors])
    rest = (geometry.gather_cells(A, firsts, sensor.box_offsets) - ref_k).clamp_min(0.0)  # T_k (round-off >= 0)
    zw = geometry.gather_cells(zc, firsts, sensor.box_offsets)
    dims = tuple(range(3, 3 + len(geometry.box_cells)))
    return (sensor.cell_log_ratio(rest + own, zw) - sensor.cell_log_ratio(rest, zw)).sum(dims)
