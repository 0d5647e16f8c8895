"""The data-driven proposal of the grid sensors (the hooks of
:class:`~torchmcmcpf.models.multitarget.Recapture`): the frame's peaks as points, the density
``g(u | z)`` around them and draws from it.
"""

from __future__ import annotations

import math
from typing import TYPE_CHECKING

import torch

from ....resampling import cdf, inverse_cdf
from ....typing import Tensor
from ...base import neighbourhood

if TYPE_CHECKING:
    from .sensor import SeparableGridSensor

__all__ = ["peaks", "detections", "log_data_density", "sample_from_data"]

def peaks(sensor: SeparableGridSensor, z: Tensor) -> Tensor:
    """Local maxima of the detection statistic over their ``3^n`` neighbourhood above the
    threshold: ``(B, *G)`` bool.
    """
    return _peaks_of(sensor, sensor.detection_statistic(z))


def _peaks_of(sensor: SeparableGridSensor, stat: Tensor) -> Tensor:
    """:func:`peaks` from the detection statistic ``stat (B, *G)``."""
    return (stat >= neighbourhood(stat, "max", sensor.n_axes)) & (stat > sensor.detection_threshold)


def detections(sensor: SeparableGridSensor, z: Tensor) -> tuple[Tensor, Tensor]:
    """The frame's peaks as points: ``centres (B, P, n)`` (the strongest
    ``P = min(max_peaks, G)``, padded) and ``mask (B, P)``; a centre is the centroid of the
    statistic above the noise mean over the peak's ``3^n`` neighbourhood (cells beyond the
    grid weigh 0), read at the P peaks only (the frame is pooled once, for the peaks).
    """
    geometry = sensor.geometry
    n, shape = geometry.n_axes, geometry.frame_shape
    stat = sensor.detection_statistic(z)
    peak = _peaks_of(sensor, stat)
    B, G = stat.shape[0], geometry.num_cells
    P = min(sensor.max_peaks, G)
    top, at = torch.topk(torch.where(peak, stat, float("-inf")).reshape(B, G), P, dim=-1)
    mask = torch.isfinite(top)
    weight = (stat - 1.0).clamp(min=0.0).reshape(B, G)  # above the noise mean (1)
    # each peak's 3^n neighbours: per axis the cell index - 1, + 0, + 1, broadcast over the others
    step = torch.arange(-1, 2, device=z.device)
    index = torch.zeros((), dtype=torch.int64, device=z.device)
    inside = torch.ones((), dtype=torch.bool, device=z.device)
    coords: list[Tensor] = []
    rest = at
    for a in reversed(range(n)):  # the flat index unravelled, last axis first
        near = (rest % shape[a]).unsqueeze(-1) + step  # (B, P, 3)
        rest = rest // shape[a]
        view = (B, P) + (1,) * a + (3,) + (1,) * (n - 1 - a)
        inside = inside & ((near >= 0) & (near < shape[a])).reshape(view)
        index = index + (near.clamp(0, shape[a] - 1) * math.prod(shape[a + 1:])).reshape(view)
        coords.insert(0, (geometry.origins[a] + geometry.cell_sizes[a] * near.to(stat.dtype)).reshape(view))
    w = torch.where(inside, torch.take_along_dim(weight, index.reshape(B, P * 3**n), -1).reshape(index.shape), 0.0)
    norm = w.flatten(2).sum(-1).clamp(min=1e-30)  # (B, P); > 0 at a real peak (its own cell is above 10)
    centres = [(w * c).flatten(2).sum(-1) / norm for c in coords]
    return torch.stack(centres, -1), mask


def log_data_density(sensor: SeparableGridSensor, coords: Tensor, centres: Tensor, mask: Tensor) -> Tensor:
    """``log g(u | z)`` at ``coords (B, *S, n)`` given the frame's detections: ``(B, *S)``."""
    geometry = sensor.geometry
    B, n = coords.shape[0], geometry.n_axes
    used = int(mask.sum(-1).max()) if mask.numel() else 0  # the padding holds no peak: drop it (eager)
    centres, mask = centres[:, :max(used, 1)], mask[:, :max(used, 1)]
    lo, hi, log_volume = geometry.extent()
    scale = torch.tensor([sensor.peak_spread * c for c in geometry.cell_sizes], dtype=coords.dtype,
                         device=coords.device)
    flat = coords.reshape(B, -1, 1, n)  # (B, Q, 1, n)
    white = (flat - centres.to(coords.dtype).unsqueeze(1)) / scale  # (B, Q, P, n)
    log_n = -0.5 * white.square().sum(-1) - torch.log(scale).sum() - 0.5 * n * math.log(2 * math.pi)
    log_n = torch.where(mask.unsqueeze(1), log_n, float("-inf"))
    count = mask.sum(-1, keepdim=True).to(coords.dtype)  # (B, 1)
    log_near = torch.logsumexp(log_n, -1) - torch.log(count.clamp(min=1.0))  # (B, Q)
    p_u = sensor.uniform_weight
    log_q = torch.logaddexp(torch.full_like(log_near, math.log(p_u) - log_volume), math.log1p(-p_u) + log_near)
    log_q = torch.where(count > 0, log_q, torch.full_like(log_q, -log_volume))
    return log_q.reshape(coords.shape[:-1])


def sample_from_data(sensor: SeparableGridSensor, z: Tensor, shape: tuple[int, ...], *, generator: torch.Generator,
                     dtype: torch.dtype = torch.float32) -> tuple[Tensor, Tensor]:
    """Draws ``coords (*shape, n)`` from ``g(u | z)`` and ``log p_0 - log g`` there ``(*shape)``."""
    geometry = sensor.geometry
    B = z.shape[0]
    if not shape or shape[0] != B:
        raise ValueError(f"shape {tuple(shape)} must start with the batch size of z, {B}")
    n, Q = geometry.n_axes, math.prod(shape[1:])
    centres, mask = detections(sensor, z)
    lo, hi, log_volume = geometry.extent()
    u = torch.rand((B, Q, 2), generator=generator, device=z.device, dtype=torch.float64)
    pick = inverse_cdf(cdf(torch.where(mask | ~mask.any(-1, keepdim=True), 0.0, float("-inf"))), u[..., 0])
    eps = torch.randn((B, Q, n), generator=generator, device=z.device, dtype=dtype)
    box = torch.rand((B, Q, n), generator=generator, device=z.device, dtype=dtype)
    low = torch.tensor(lo, dtype=dtype, device=z.device)
    span = torch.tensor(hi, dtype=dtype, device=z.device) - low
    scale = torch.tensor([sensor.peak_spread * c for c in geometry.cell_sizes], dtype=dtype, device=z.device)
    near = torch.take_along_dim(centres.to(dtype), pick.unsqueeze(-1), 1) + scale * eps
    use = (u[..., 1] >= sensor.uniform_weight) & mask.any(-1, keepdim=True)
    coords = torch.where(use.unsqueeze(-1), near, low + span * box)  # (B, Q, n)
    inside = ((coords >= low) & (coords <= low + span)).all(-1)
    log_ratio = torch.where(inside, -log_volume - log_data_density(sensor, coords, centres, mask), float("-inf"))
    return coords.reshape(tuple(shape) + (n,)), log_ratio.reshape(tuple(shape))
