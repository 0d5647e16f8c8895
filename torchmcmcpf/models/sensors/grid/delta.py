"""The one-slot change of the windowed log-likelihood: when slot ``n`` moves, only the cells of
its old and new box change, so the difference is summed over those two boxes, with the
spreads of slot ``n`` before and after the move and those of the live targets whose boxes
overlap them (:meth:`~.sensor.SeparableGridSensor.log_likelihood_delta` states the maths).
"""

from __future__ import annotations

import torch

from ...._native.select import where
from ....runtime import take_along
from ....typing import Tensor
from . import native, whole
from ._protocol import GridSensorLike
from .amplitudes import log_likelihood_delta_on_grid, whole_grid
from .inputs import check_inputs, check_move, flat_inputs, slots
from .spread import box_in_box, neighbour_index, neighbour_profiles, outer_sum, with_neighbours

__all__ = ["log_likelihood_delta"]


def log_likelihood_delta(sensor: GridSensorLike, x: Tensor, x_n: Tensor, n: int | Tensor, z: Tensor,
                         exists: Tensor | None = None, exists_n: Tensor | None = None) -> Tensor:
    """``log p(z | x with slot n = x_n) - log p(z | x)`` ``(B, *S)`` on the windowed path,
    or the difference of two whole-grid evaluations with ``method="grid"``.
    """
    check_inputs(sensor, x, z, exists)
    if check_move(x, x_n, exists_n):
        raise ValueError(f"x_n has shape {tuple(x_n.shape)}, expected {tuple(x.shape[:-2]) + (x.shape[-1],)}: one "
                         "slot (log_likelihood_delta_cached moves several)")
    B, K = x.shape[0], x.shape[-2]
    S = tuple(x.shape[1:-2])
    if not torch.is_tensor(n) and (isinstance(n, bool) or not isinstance(n, int) or not 0 <= n < K):
        raise ValueError(f"n must be an int in [0, {K}) or an int64 tensor, got {n!r}")
    if sensor.method == "grid":  # consistent with log_likelihood: two reference evaluations
        here = torch.arange(K, device=x.device) == slots(n, x).reshape((B,) + S + (1,))
        e_old = torch.ones(x.shape[:-1], dtype=torch.bool, device=x.device) if exists is None else exists
        e_new = e_old if exists_n is None else where(here, exists_n[..., None], e_old)
        x_new = where(here[..., None], x_n[..., None, :], x)
        return whole.log_likelihood(sensor, x_new, z, e_new) - whole.log_likelihood(sensor, x, z, e_old)
    if native.applies(sensor, x):  # the radar on the CPU: one C loop a sample, the two boxes on any grid
        return native.delta(sensor, x, x_n, slots(n, x), z, exists, exists_n).reshape((B,) + S)
    if whole_grid(sensor, 2):  # no more cells than the two boxes: the sum on the whole grid
        slot = n if torch.is_tensor(n) else torch.tensor(n, device=x.device)
        return log_likelihood_delta_on_grid(sensor, x, x_n, slot, z, exists, exists_n)
    names = [k for k, v in (("n", n if torch.is_tensor(n) else None), ("exists", exists), ("exists_n", exists_n))
             if v is not None]

    def prepare(x: Tensor, x_n: Tensor, z: Tensor, *optional: Tensor) -> tuple[Tensor, ...]:
        kw = dict(zip(names, optional))
        return _parts(sensor, x, x_n, kw.get("n", n), z, kw.get("exists"), kw.get("exists_n"))

    inputs = (x, x_n, z) + tuple(v for v in (n, exists, exists_n) if torch.is_tensor(v))
    return with_neighbours(sensor.max_neighbours, K - 1, lambda c, *a: _box_sums(sensor, c, *a), prepare,
                           inputs).reshape((B,) + S)


def _parts(sensor: GridSensorLike, x: Tensor, x_n: Tensor, n: int | Tensor, z: Tensor,
           exists: Tensor | None, exists_n: Tensor | None) -> tuple[Tensor, ...]:
    """The arguments of :func:`log_likelihood_delta` (checked) -> ``(u_all, s, s_old, s_new,
    z, *firsts, others)``: ``u_all (B, P, K + 2, n)`` the coordinates of the K slots, then
    of slot ``n`` before and after the move; ``s (B, P, K)``, ``s_old, s_new (B, P, 1)`` the
    signals (times existence); ``z`` the frame in the dtype of ``x``, not yet prepared;
    ``firsts[a] (B, P, K + 2)`` the box starts; ``others (B, P, 2, K)`` whether the old / new
    box of slot ``n`` overlaps the box of another live slot.
    """
    B, K, D = x.shape[0], x.shape[-2], x.shape[-1]
    slot = slots(n, x)
    u, s, e = flat_inputs(sensor, x, exists)  # (B, P, K, n), (B, P, K), (B, P, K)
    P = u.shape[1]
    at = slot[..., None]  # (B, P, 1)
    x_new = x_n.reshape(B, P, 1, D)
    e_new = take_along(e, at, 2) if exists_n is None else exists_n.reshape(B, P, 1).to(x.dtype)
    s_old = take_along(s, at, 2)  # (B, P, 1)
    s_new = sensor.signal(x_new) * e_new
    # targets: the K slots, then slot n before (index K) and after (index K + 1) the move
    u_all = torch.cat([u, take_along(u, at[..., None], 2), sensor.measurement_coords(x_new)], 2)
    geometry = sensor.geometry
    firsts = geometry.box_firsts(u_all)  # (B, P, K + 2)
    boxes = [f[..., K:] for f in firsts]  # (B, P, 2): old and new box of slot n
    rest = (torch.arange(K, device=x.device) != at) & (e > 0)  # (B, P, K): the other live slots
    others = geometry.overlaps(boxes, [f[..., :K] for f in firsts]) & rest[..., None, :]  # (B, P, 2, K)
    return (u_all, s, s_old, s_new, z.to(x.dtype), *firsts, others)


def _box_sums(sensor: GridSensorLike, count: int, u_all: Tensor, s: Tensor, s_old: Tensor, s_new: Tensor,
              z: Tensor, *rest: Tensor) -> Tensor:
    """:func:`log_likelihood_delta` ``(B, P)`` from :func:`_parts`, with ``count`` neighbour
    slots per box.
    """
    *firsts, others = rest
    B, P, K = s.shape
    boxes = [f[..., K:] for f in firsts]
    moved = torch.tensor([K, K + 1], device=s.device).expand(B, P, 2, 2)  # (B, P, 2q, 2)
    zero = torch.zeros_like(s_old)
    cur = torch.cat([s_old, zero], -1)[:, :, None].expand(B, P, 2, 2)
    prop = torch.cat([zero, s_new], -1)[:, :, None].expand(B, P, 2, 2)
    if count > 0:
        nb, w = neighbour_index(others, count)  # (B, P, 2q, count)
        s_nb = take_along(s[:, :, None].expand(B, P, 2, K), nb, -1) * w.to(s.dtype)
        index = torch.cat([nb, moved], -1)  # (B, P, 2q, count + 2)
        cur, prop = torch.cat([s_nb, cur], -1), torch.cat([s_nb, prop], -1)
    else:
        index = moved
    geometry = sensor.geometry
    factors, indicators = neighbour_profiles(geometry, boxes, u_all, firsts, index)  # (B, P, 2q, M, W)
    signals = torch.stack([cur, prop], 2)  # (B, P, 2 (cur, prop), 2 (old box, new box), M)
    A = outer_sum(signals, [f[:, :, None] for f in factors])  # (B, P, 2, 2, *W)
    # the two boxes' cells of the frame, then prepared (per cell; not the whole grid per move)
    zw = sensor.prepare_frame(geometry.gather_cells(z, boxes, sensor.box_offsets))[:, :, None]  # (B, P, 1, 2, *W)
    ratio = sensor.cell_log_ratio(A, zw)
    diff = ratio[:, :, 1] - ratio[:, :, 0]  # (B, P, 2, *W)
    both = box_in_box(indicators, 1, count, s_old)  # (B, P, *W): cells of the new box in the old one
    return diff[:, :, 0].flatten(2).sum(-1) + (diff[:, :, 1] * (1.0 - both)).flatten(2).sum(-1)
