"""The point sensor's Gaussian sums as C loops: its fast path on the CPU.

Every term of :class:`~torchmcmcpf.models.sensors.points.PoissonClutterPoints` is a Gaussian
``exp(c - |p - w_m|^2 / 2)`` of a whitened, centred position ``p = W (h - centre)`` and point
``w_m = W (z_m - centre)`` (``R^-1 = W^T W``; the tensor path's :func:`~.points.gauss_exponents`
expands the square into one matrix product over ``(..., K, M)`` tensors, then ``exp``, a sum
and a ``log``, each a pass over memory). ``torchmcmcpf/_native/points.c`` takes one sample at
a time instead, the square written out, its own vectorised ``exp`` (flushed to exactly 0 below
``e^FLUSH``, as :func:`~.points._exp_`), inactive slots skipped, and no ``(..., K, M)``
tensor stored:

- :func:`intensity`: ``lambda_m = L_C / V + sum_k e_k L_x N(z_m; H x_k, R)`` (paper 001's
  association-free likelihood, DESIGN.md), the chains' cache;
- :func:`delta`: a move of ``V`` slots read from that cache, the change of every point's
  intensity and ``sum_m log(lambda'_m / lambda_m)``, a ``log`` only where a point's intensity
  changes (a one-slot move leaves most of them exactly as they were: far terms flush);
- :func:`log_sum`: ``sum_m log lambda_m`` over a run's valid points (the log-likelihood from
  the intensities), with the loops' vectorised ``log``;
- :func:`near`: ``logsumexp_m (c - |q - w_m|^2 / 2)`` over a run's valid points, the birth and
  relocation proposals' data density (:func:`~.points.log_near_points`).

Float64 throughout, whatever the state's dtype (as the tensor path); the same values to
round-off (tested against the tensor path in float64). The loops serve CPU tensors with no
gradient to record and no ``torch.func`` transform, when the library's C loops are built
(:mod:`torchmcmcpf._native`); otherwise the tensor path runs. The calls are
``torch.library`` custom ops, so compiled filters keep one graph.
"""

from __future__ import annotations

from typing import Any

import torch

from ... import runtime
from ..._native import applies, library
from ...typing import Tensor

__all__ = ["applies", "whiten", "whitened_axes", "centred_axes", "centred", "intensity", "delta", "near", "log_sum",
           "elementwise"]


def whiten(v: Tensor, W: Tensor, diagonal: bool) -> Tensor:
    """``v @ W.mT`` for ``v (..., 2)``; with ``diagonal`` (``W`` diagonal) as one product per axis:
    each entry of the matrix product is ``v_j W_jj`` plus an exact zero, so the same values for
    finite ``v`` (no BLAS call on a product of inner size 2, 4x the time on a million rows).
    """
    if diagonal:
        return v * torch.diagonal(W)
    return v @ W.mT


def whitened_axes(a: Tensor, b: Tensor, W: Tensor, diagonal: bool) -> tuple[Tensor, Tensor]:
    """The two whitened coordinates of the points ``(a, b)`` (each ``(...)``): the values of
    ``whiten(stack([a, b], -1), W, diagonal)`` split by axis.
    """
    if diagonal:
        d = torch.diagonal(W)
        return a * d[0], b * d[1]
    w = whiten(torch.stack([a, b], -1), W, diagonal)
    return w[..., 0], w[..., 1]


def centred_axes(a: Tensor, b: Tensor, W: Tensor, diagonal: bool, centre: Tensor) -> tuple[Tensor, Tensor]:
    """The two axes of ``W ((a, b) - centre)`` in float64, ``a, b (...)`` -> ``(...)`` each: the
    whitened, centred coordinates of positions or points, the loops' inputs and the tensor
    path's (:func:`~.points.gauss_exponents`).
    """
    f64 = torch.float64
    c = centre.to(device=a.device, dtype=f64)
    return whitened_axes(a.to(f64) - c[0], b.to(f64) - c[1], W.to(device=a.device, dtype=f64), diagonal)


def centred(a: Tensor, b: Tensor, W: Tensor, diagonal: bool, centre: Tensor) -> Tensor:
    """:func:`centred_axes` stacked: ``(..., 2)`` float64."""
    return torch.stack(centred_axes(a, b, W, diagonal, centre), -1)


def _n(x: Tensor) -> int:
    return x.data_ptr()


@runtime.custom_op("torchmcmcpf::points_intensity")
def intensity(p: Tensor, c: Tensor, w: Tensor, clutter: float) -> Tensor:
    """``clutter + sum_k exp(c_k - |p_k - w_m|^2 / 2)`` at every point: ``p (B, P, K, 2)``,
    ``c (B, P, K)`` (``-inf``: an inactive slot), ``w (B, 2, M)`` the runs' whitened, centred
    points by axis, all float64 -> ``(B, P, M)`` float64.
    """
    B, P, K = c.shape
    M = w.shape[-1]
    p, c, w = (t.contiguous() for t in (p, c, w))
    lam = torch.empty((B, P, M), dtype=torch.float64)
    lib: Any = library()
    lib.points_intensity(B * P, torch.get_num_threads(), P, K, M, _n(p), _n(c), _n(w), clutter, _n(lam))
    return lam


@intensity.register_fake
def _(p: Tensor, c: Tensor, w: Tensor, clutter: float) -> Tensor:
    return c.new_empty(tuple(c.shape[:2]) + (w.shape[-1],))


@runtime.custom_op("torchmcmcpf::points_delta")
def delta(p: Tensor, c: Tensor, w: Tensor, mask: Tensor, cache: Tensor) -> tuple[Tensor, Tensor]:
    """A move of ``V`` slots read from the intensities ``cache (B, P, M)``: ``p (B, P, 2V, 2)``,
    ``c (B, P, 2V)`` the moved slots' old then new terms (``-inf``: inactive), ``w (B, 2, M)``,
    ``mask (B, M)`` uint8 -> ``(sum over the valid points of log(lambda'_m / lambda_m) (B, P),
    lambda' - lambda (B, P, M))``, float64.
    """
    B, P, V2 = c.shape
    M = w.shape[-1]
    p, c, w, mask, cache = (t.contiguous() for t in (p, c, w, mask, cache))
    out = torch.empty((B, P), dtype=torch.float64)
    change = torch.empty((B, P, M), dtype=torch.float64)
    lib: Any = library()
    lib.points_delta(B * P, torch.get_num_threads(), P, V2 // 2, M, _n(p), _n(c), _n(w), _n(mask), _n(cache),
                     _n(out), _n(change))
    return out, change


@delta.register_fake
def _(p: Tensor, c: Tensor, w: Tensor, mask: Tensor, cache: Tensor) -> tuple[Tensor, Tensor]:
    return c.new_empty(tuple(c.shape[:2])), torch.empty_like(cache)


@runtime.custom_op("torchmcmcpf::points_near")
def near(q: Tensor, w: Tensor, mask: Tensor, c: float) -> Tensor:
    """``log sum_m exp(c - |q - w_m|^2 / 2)`` over each run's valid points: ``q (B, P, 2)``,
    ``w (B, 2, M)`` float64, ``mask (B, M)`` uint8 -> ``(B, P)`` float64 (``-inf`` for a run
    without valid points).
    """
    B, P = q.shape[:2]
    M = w.shape[-1]
    q, w, mask = (t.contiguous() for t in (q, w, mask))
    out = torch.empty((B, P), dtype=torch.float64)
    lib: Any = library()
    lib.points_near(B * P, torch.get_num_threads(), P, M, _n(q), _n(w), _n(mask), c, _n(out))
    return out


@near.register_fake
def _(q: Tensor, w: Tensor, mask: Tensor, c: float) -> Tensor:
    return q.new_empty(tuple(q.shape[:2]))


@runtime.custom_op("torchmcmcpf::points_log_sum")
def log_sum(lam: Tensor, mask: Tensor) -> Tensor:
    """``sum_m log lam_m`` over each run's valid points: ``lam (B, P, M)`` float64, ``mask (B,
    M)`` uint8 -> ``(B, P)`` float64 (the loops' vectorised ``log``).
    """
    B, P, M = lam.shape
    lam, mask = lam.contiguous(), mask.contiguous()
    out = torch.empty((B, P), dtype=torch.float64)
    lib: Any = library()
    lib.points_log_sum(B * P, torch.get_num_threads(), P, M, _n(lam), _n(mask), _n(out))
    return out


@log_sum.register_fake
def _(lam: Tensor, mask: Tensor) -> Tensor:
    return lam.new_empty(tuple(lam.shape[:2]))


def elementwise(name: str, t: Tensor) -> Tensor:
    """The loops' ``exp`` (``name = "exp"``, flushed) or ``log`` on a float64 CPU tensor (for
    their tests against ``torch.exp`` and ``torch.log``).
    """
    t = t.contiguous()
    out = torch.empty_like(t)
    getattr(library(), f"points_{name}")(t.numel(), _n(t), _n(out))
    return out
