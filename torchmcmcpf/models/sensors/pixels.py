"""Thresholded pixel sensor (Septier, Pang, Godsill and Carmi 2009, eqs. 39-41).

A frame is a binary image ``z (B, H, W)`` over the area ``[0, W s] x [0, H s]`` (pixel size
``s``): pixel ``(i, j)`` covers ``x in [j s, (j + 1) s)``, ``y in [i s, (i + 1) s)``.
Pixels are conditionally independent given the targets (eq. 39); a pixel holding ``n``
active targets fires with

    P_d,n = P_fa ** (1 / (1 + n SNR))                                        (eq. 41)

(``P_d,0 = P_fa``, the false alarm probability). The likelihood ratio against "no target"
keeps the pixels that hold targets only (eq. 40):

    log p(Z | x, e) - log p(Z | none) = sum_{occupied pixels} z log(P_d,n / P_fa)
                                         + (1 - z) log((1 - P_d,n) / (1 - P_fa)).

A target outside the grid, or inactive, occupies no pixel.

SNR
---
The paper's numbers are ``P_d,1 = 0.7``, ``P_fa = 0.002`` "(i.e. SNR = 17 dB)", but eq. 41
gives ``SNR = log P_fa / log P_d,1 - 1 = 16.4`` for them, i.e. 12.2 dB (17 dB, 50.1, would
give ``P_d,1 = 0.885``). We take ``P_d,1`` as given and derive the SNR from it.
"""

from __future__ import annotations

import math
from collections.abc import Sequence

import torch

from ..._native.select import where
from ..._validation import check_finite, check_positive, check_shape
from ...typing import Tensor, X, Y
from ..base import SensorModel

__all__ = ["ThresholdedPixels"]


class ThresholdedPixels(SensorModel[Tensor]):
    """Binary pixel frames with ``P_d,n = P_fa ** (1 / (1 + n SNR))`` (module docstring).

    Parameters
    ----------
    shape : ``(H, W)`` pixels (rows along y, columns along x).
    pixel_size : side of a pixel [m] (paper: 50).
    p_fa : false alarm probability per pixel (paper: 0.002).
    p_d1 : detection probability of one target in a pixel (paper: 0.7); or give
    snr : the linear SNR of eq. 41 instead (exactly one of ``p_d1`` and ``snr``).
    position_index : where x and y sit in a target's state (default ``(X, Y) = (0, 2)`` of the
        ``[x, vx, y, vy]`` layout; ``(0, 1)`` for position-only states ``(*S, K, 2)``).

    Example
    -------
    >>> from torchmcmcpf.models import ThresholdedPixels
    >>> sensor = ThresholdedPixels((100, 100), 50.0, p_fa=0.002, p_d1=0.7)
    >>> round(sensor.snr_db, 1)
    12.2
    """

    def __init__(self, shape: Sequence[int], pixel_size: float, p_fa: float, p_d1: float | None = None,
                 snr: float | None = None, *, position_index: Sequence[int] = (X, Y)) -> None:
        super().__init__()
        if len(shape) != 2 or any(int(s) != s or s < 1 for s in shape):
            raise ValueError(f"shape must be (H, W) positive integers, got {shape!r}")
        self.shape = (int(shape[0]), int(shape[1]))
        self.frame_shape = self.shape
        self.pixel_size = check_positive(pixel_size, "pixel_size")
        self.p_fa = float(p_fa)
        if not 0.0 < self.p_fa < 1.0:
            raise ValueError(f"p_fa must be in (0, 1), got {p_fa!r}")
        if (p_d1 is None) == (snr is None):
            raise ValueError("give exactly one of p_d1 and snr")
        if p_d1 is not None:
            if not self.p_fa < float(p_d1) < 1.0:
                raise ValueError(f"p_d1 must be in (p_fa, 1) = ({self.p_fa}, 1), got {p_d1!r}")
            self.snr = math.log(self.p_fa) / math.log(float(p_d1)) - 1.0
        else:
            self.snr = check_positive(snr, "snr")
        self.p_d1 = self.p_fa ** (1.0 / (1.0 + self.snr))
        self.position_index = tuple(int(i) for i in position_index)
        if len(self.position_index) != 2:
            raise ValueError(f"position_index must name two state components, got {position_index!r}")

    @property
    def snr_db(self) -> float:
        """The SNR of eq. 41 in dB, ``10 log10(SNR)``."""
        return 10 * math.log10(self.snr)

    @property
    def area(self) -> tuple[tuple[float, float], tuple[float, float]]:
        """``((0, W s), (0, H s))`` [m]."""
        return ((0.0, self.shape[1] * self.pixel_size), (0.0, self.shape[0] * self.pixel_size))

    def resolution_coords(self, x: Tensor) -> Tensor:
        """Position in pixels: ``(*S, K, D) -> (*S, K, 2)`` (two targets in one pixel are
        unresolved).
        """
        ix, iy = self.position_index
        return torch.stack([x[..., ix], x[..., iy]], -1) / self.pixel_size

    def log_p_detect(self, n: Tensor, dtype: torch.dtype = torch.float64) -> Tensor:
        """``log P_d,n`` of eq. 41 for target counts ``n`` (any shape): ``log P_fa / (1 + n SNR)``."""
        return math.log(self.p_fa) / (1.0 + n.to(dtype) * self.snr)

    def pixel_index(self, x: Tensor, exists: Tensor | None = None) -> Tensor:
        """Flat pixel index ``i W + j`` of each target, ``-1`` if inactive or off the grid:
        ``(*S, K, D) -> (*S, K)`` int64.
        """
        ix, iy = self.position_index
        col = torch.floor(x[..., ix] / self.pixel_size)
        row = torch.floor(x[..., iy] / self.pixel_size)
        h, w = self.shape
        inside = (col >= 0) & (col < w) & (row >= 0) & (row < h) & torch.isfinite(col) & torch.isfinite(row)
        if exists is not None:
            inside = inside & exists
        flat = (row.clamp(0, h - 1) * w + col.clamp(0, w - 1)).long()
        return where(inside, flat, torch.full_like(flat, -1))

    def log_likelihood(self, x: Tensor, z: Tensor, exists: Tensor | None = None) -> Tensor:
        """Log ratio against "no target" over the occupied pixels (eq. 40).

        Parameters
        ----------
        x : (B, *S, K, D) states; z : (B, H, W) binary frame (bool or 0/1);
        exists : (B, *S, K) bool, optional.

        Returns
        -------
        (B, *S), in ``x``'s dtype. Piecewise constant in ``x`` (no useful gradient).
        """
        idx = self.pixel_index(x, exists)  # (B, *S, K)
        b = idx.shape[0]
        k = idx.shape[-1]
        occ = idx >= 0
        same = (idx.unsqueeze(-1) == idx.unsqueeze(-2)) & occ.unsqueeze(-1) & occ.unsqueeze(-2)
        n = same.sum(-1)  # targets sharing each target's pixel
        earlier = torch.tril(torch.ones(k, k, dtype=torch.bool, device=idx.device), -1)
        first = occ & ~(same & earlier).any(-1)  # count each pixel once, at its first target
        zf = z.reshape(b, -1)
        zk = torch.gather(zf, 1, idx.clamp(min=0).reshape(b, -1)).reshape(idx.shape).to(torch.bool)
        dtype = x.dtype if x.is_floating_point() else torch.float64
        log_pd = self.log_p_detect(n, dtype)
        term = where(zk, log_pd - math.log(self.p_fa),
                           torch.log(-torch.expm1(log_pd)) - math.log1p(-self.p_fa))
        return where(first, term, torch.zeros_like(term)).sum(-1)

    def simulate(self, x: Tensor, *, generator: torch.Generator, exists: Tensor | None = None) -> Tensor:
        """Draw one binary frame per run: ``x (B, K, D) -> (B, H, W)`` bool."""
        idx = self.pixel_index(x, exists)  # (B, K)
        b = idx.shape[0]
        h, w = self.shape
        counts = torch.zeros(b, h * w + 1, dtype=torch.int64, device=x.device)
        counts.scatter_add_(1, where(idx >= 0, idx, h * w), torch.ones_like(idx))
        p = self.log_p_detect(counts[:, :-1]).exp()
        u = torch.rand(b, h * w, generator=generator, dtype=torch.float64, device=x.device)
        return (u < p).reshape(b, h, w)

    def validate(self, z: Tensor, batch_size: int | None = None, name: str = "z") -> Tensor:
        """Check a frame ``(B, H, W)``: shape, batch size and binary values."""
        check_shape(z, name, (None,) + self.shape)
        if batch_size is not None and z.shape[0] != batch_size:
            raise ValueError(f"{name} has batch size {z.shape[0]}, expected {batch_size}")
        if z.is_floating_point():
            check_finite(z, name)
        if z.dtype != torch.bool and not bool(((z == 0) | (z == 1)).all()):
            raise ValueError(f"{name} must be binary (0/1 or bool), got values outside {{0, 1}}")
        return z

    def extra_repr(self) -> str:
        """The constructor arguments, shown inside ``repr(module)``."""
        return (f"shape={self.shape}, pixel_size={self.pixel_size}, p_fa={self.p_fa}, "
                f"p_d1={self.p_d1:.4g}, snr={self.snr:.4g} ({self.snr_db:.1f} dB)")
