"""The data-driven proposal of the grid sensors (the hooks of
:class:`~torchmcmcpf.models.multitarget.Recapture`): the frame's peaks as points, the density
``g(u | z)`` around them and draws from it.
"""

from __future__ import annotations

import math

import torch

from ...._native.select import where
from ....resampling import uniform_pick
from ....runtime import take_along
from ....typing import Tensor
from ...base import neighbourhood
from ._protocol import GridSensorLike

__all__ = ["peaks", "detections", "log_data_density", "sample_from_data"]

def peaks(sensor: GridSensorLike, z: Tensor) -> Tensor:
    """The cells at which :func:`detections` finds its peaks: ``(B, *G)`` bool."""
    B, G = z.shape[0], sensor.geometry.num_cells
    _, mask, at = _clean(sensor, sensor.detection_statistic(z))
    out = torch.zeros((B, G + 1), dtype=torch.bool, device=z.device)
    out.scatter_(1, where(mask, at, G), True)  # a padded peak writes the spare column
    return out[:, :G].reshape(z.shape)


def detections(sensor: GridSensorLike, z: Tensor) -> tuple[Tensor, Tensor]:
    """The frame's peaks as points, found by CLEAN (Hogbom 1974): ``centres (B, P, n)``
    (``P = min(max_peaks, G)``, strongest first, padded) and ``mask (B, P)``.

    Repeatedly: the cell of largest residual statistic, if above the threshold, is a peak;
    its centre is the centroid of the residual above the noise mean over the cell's ``3^n``
    neighbourhood (cells beyond the grid weigh 0); its point spread, fitted at that centre
    (the sensor's widths, cut at ``window`` cells per axis like the likelihood's), is taken
    off the residual in the domain where targets add
    (:meth:`~.sensor.SeparableGridSensor.detection_signal`). A weak target next to a strong
    one is a shoulder of the strong one's spread, not a local maximum: this finds it once
    the strong one is taken off. An isolated peak's centre is the centroid of the frame
    itself (tested against a loop).
    """
    centres, mask, _ = _clean(sensor, sensor.detection_statistic(z))
    geometry = sensor.geometry
    origin = torch.tensor(geometry.origins, dtype=centres.dtype, device=z.device)
    cell = torch.tensor(geometry.cell_sizes, dtype=centres.dtype, device=z.device)
    return origin + cell * centres, mask


def _spread(cells: Tensor, centre: Tensor, width: Tensor) -> Tensor:
    """The separable Gaussian spread of a target at ``centre (B, n)`` at ``cells (B, C, n)``
    (all in cell units; ``width (n,)`` its standard deviations): ``(B, C)``, 1 at the centre.
    """
    return torch.exp(-0.5 * ((cells - centre.unsqueeze(1)) / width).square().sum(-1))


def _clean(sensor: GridSensorLike, stat: Tensor) -> tuple[Tensor, Tensor, Tensor]:
    """CLEAN over the statistic ``stat (B, *G)`` (:func:`detections`): centres in cell
    units ``(B, P, n)``, ``mask (B, P)`` and the peaks' flat cells ``(B, P)``.

    Only the cells within one cell of a cell above the threshold can hold a peak or weigh in
    a centroid, so the loop runs over those (``C`` per run, the most in any run; one host
    synchronisation) and stops once no run has a residual above the threshold (one per peak).
    """
    geometry = sensor.geometry
    n, shape = geometry.n_axes, geometry.frame_shape
    B, G = stat.shape[0], geometry.num_cells
    P = min(sensor.max_peaks, G)
    dev, dtype = stat.device, stat.dtype
    live = neighbourhood(stat, "max", n) > sensor.detection_threshold  # (B, *G)
    C = max(int(live.reshape(B, G).sum(-1).max()), 1)
    value, at = torch.topk(where(live, stat, float("-inf")).reshape(B, G), C, dim=-1)  # (B, C)
    cand = torch.isfinite(value)
    index: list[Tensor] = []
    rest = at
    for a in reversed(range(n)):  # the flat index unravelled, last axis first
        index.insert(0, rest % shape[a])
        rest = rest // shape[a]
    pos = torch.stack(index, -1).to(dtype)  # (B, C, n) cell coordinates
    width = torch.tensor([w / c for w, c in zip(geometry.widths, geometry.cell_sizes)], dtype=dtype, device=dev)
    reach = float(geometry.window)
    signal = where(cand, sensor.detection_signal(value.clamp(min=0.0)), 0.0)  # the residual (B, C)
    threshold = float(sensor.detection_signal(torch.tensor(sensor.detection_threshold, dtype=dtype)))
    centres = torch.zeros((B, P, n), dtype=dtype, device=dev)
    cells = torch.zeros((B, P), dtype=torch.int64, device=dev)
    mask = torch.zeros((B, P), dtype=torch.bool, device=dev)
    for p in range(P):
        top, i = signal.max(-1)  # (B,)
        found = top > threshold
        if not bool(found.any()):  # the residual only shrinks: no later peak either
            break
        here = take_along(pos, i.reshape(B, 1, 1), 1)  # (B, 1, n)
        offset = pos - here
        near = (offset.abs() <= 1).all(-1) & cand  # the peak's 3^n neighbourhood
        weight = where(near, (sensor.detection_stat(signal) - 1.0).clamp(min=0.0), 0.0)
        centre = (weight.unsqueeze(-1) * pos).sum(1) / weight.sum(-1, keepdim=True).clamp(min=1e-30)  # (B, n)
        # the spread fitted at the centre through the peak cell's residual, cut like the likelihood's
        scale = top / _spread(here, centre, width).squeeze(1)
        box = (offset.abs() <= reach).all(-1)
        taken = where(box & found.unsqueeze(-1), scale.unsqueeze(-1) * _spread(pos, centre, width), 0.0)
        signal = (signal - taken).clamp(min=0.0)
        centres[:, p] = centre
        cells[:, p] = take_along(at, i.unsqueeze(-1), -1).squeeze(-1)
        mask[:, p] = found
    return centres, mask, cells


def log_data_density(sensor: GridSensorLike, coords: Tensor, centres: Tensor, mask: Tensor) -> Tensor:
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
    log_n = where(mask.unsqueeze(1), log_n, float("-inf"))
    count = mask.sum(-1, keepdim=True).to(coords.dtype)  # (B, 1)
    log_near = torch.logsumexp(log_n, -1) - torch.log(count.clamp(min=1.0))  # (B, Q)
    p_u = sensor.uniform_weight
    log_q = torch.logaddexp(torch.full_like(log_near, math.log(p_u) - log_volume), math.log1p(-p_u) + log_near)
    log_q = where(count > 0, log_q, torch.full_like(log_q, -log_volume))
    return log_q.reshape(coords.shape[:-1])


def sample_from_data(sensor: GridSensorLike, z: Tensor, shape: tuple[int, ...], *, generator: torch.Generator,
                     dtype: torch.dtype = torch.float32, scored: Tensor | None = None,
                     found: tuple[Tensor, Tensor] | None = None) -> tuple[Tensor, Tensor]:
    """Draws ``coords (*shape, n)`` from ``g(u | z)`` and ``log p_0 - log g`` there ``(*shape)``
    (with ``scored (*shape)`` bool: only there, 0 elsewhere; the draws are the same), from the
    frame's :func:`detections` ``found = (centres, mask)`` when given (made once per step),
    else found here.
    """
    geometry = sensor.geometry
    B = z.shape[0]
    if not shape or shape[0] != B:
        raise ValueError(f"shape {tuple(shape)} must start with the batch size of z, {B}")
    n, Q = geometry.n_axes, math.prod(shape[1:])
    centres, mask = detections(sensor, z) if found is None else found
    lo, hi, log_volume = geometry.extent()
    u = torch.rand((B, Q, 2), generator=generator, device=z.device, dtype=torch.float64)
    pick = uniform_pick(mask, u[..., 0])
    eps = torch.randn((B, Q, n), generator=generator, device=z.device, dtype=dtype)
    box = torch.rand((B, Q, n), generator=generator, device=z.device, dtype=dtype)
    low = torch.tensor(lo, dtype=dtype, device=z.device)
    span = torch.tensor(hi, dtype=dtype, device=z.device) - low
    scale = torch.tensor([sensor.peak_spread * c for c in geometry.cell_sizes], dtype=dtype, device=z.device)
    near = take_along(centres.to(dtype), pick.unsqueeze(-1), 1) + scale * eps
    use = (u[..., 1] >= sensor.uniform_weight) & mask.any(-1, keepdim=True)
    coords = where(use.unsqueeze(-1), near, low + span * box)  # (B, Q, n)
    inside = ((coords >= low) & (coords <= low + span)).all(-1)
    if scored is None:
        log_ratio = where(inside, -log_volume - log_data_density(sensor, coords, centres, mask), float("-inf"))
    else:  # only the draws a move can read (eager: the noise is drawn outside compiled code)
        rows, cols = scored.reshape(B, Q).nonzero(as_tuple=True)
        log_ratio = torch.zeros((B, Q), dtype=dtype, device=z.device)
        if rows.numel():
            log_g = log_data_density(sensor, coords[rows, cols].unsqueeze(1), centres[rows], mask[rows]).squeeze(1)
            log_ratio.index_put_((rows, cols), where(inside[rows, cols], -log_volume - log_g, float("-inf")))
    return coords.reshape(tuple(shape) + (n,)), log_ratio.reshape(tuple(shape))
