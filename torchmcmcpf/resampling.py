"""Resampling of ``(B, N)`` log-weights and the effective sample size.

Every scheme is split in two: the uniforms are drawn from the explicit generator, and a
pure, compile-friendly function maps (log-weights, uniforms) to ancestor indices. The
cumulative sum runs in float64 and indices come from ``searchsorted`` (faster than
``torch.multinomial`` and traceable by ``torch.compile``, DESIGN.md).

References: Douc, Cappe and Moulines (2005), "Comparison of resampling schemes for
particle filtering"; Doucet and Johansen (2009), sec. 3.4.
"""

from __future__ import annotations

import math
from typing import Callable, Optional

import torch

from ._validation import check_generator, check_positive_int, check_shape
from .typing import Tensor

__all__ = [
    "normalize",
    "ess",
    "systematic",
    "stratified",
    "multinomial",
    "resample",
    "gather_particles",
    "RESAMPLERS",
    "cdf",
    "inverse_cdf",
]


def normalize(log_w: Tensor) -> tuple[Tensor, Tensor]:
    """Normalise log-weights over the last dim.

    Parameters
    ----------
    log_w : (B, N) unnormalised log-weights; ``-inf`` allowed, not everywhere.

    Returns
    -------
    log_w_norm : (B, N) with ``logsumexp == 0`` per row.
    log_mean_w : (B,) ``log(mean(w))``, the evidence increment of an SIR step.

    A row whose weights are all ``-inf`` (or all underflow in linear space) stays finite:
    ``logsumexp`` works in log space, and an all ``-inf`` row becomes uniform with
    ``log_mean_w = -inf`` rather than NaN.
    """
    # Subtract the row maximum first: at log-weights of order -1e4 a float32 subtraction of
    # logsumexp would lose ~1e-3 in the log; differences to the max are exact.
    top = log_w.amax(dim=-1, keepdim=True)
    dead = torch.isneginf(top)
    shifted = log_w - torch.where(dead, torch.zeros_like(top), top)
    lse = torch.logsumexp(shifted, dim=-1, keepdim=True)
    log_n = math.log(log_w.shape[-1])
    log_w_norm = torch.where(dead, torch.full_like(log_w, -log_n), shifted - lse)
    return log_w_norm, (top + lse).squeeze(-1) - log_n


def ess(log_w: Tensor) -> Tensor:
    """Effective sample size ``1 / sum w_i^2`` of (possibly unnormalised) log-weights.

    Parameters
    ----------
    log_w : (..., N)

    Returns
    -------
    (...,) in ``[1, N]``.
    """
    log_w = log_w - torch.logsumexp(log_w, dim=-1, keepdim=True)
    return torch.exp(-torch.logsumexp(2.0 * log_w, dim=-1))


def cdf(log_w: Tensor) -> Tensor:
    """Cumulative normalised weights in float64, last entry exactly 1.

    Parameters
    ----------
    log_w : (..., N) log-weights (normalised or not).

    Returns
    -------
    (..., N) float64.
    """
    w = torch.softmax(log_w.to(torch.float64), dim=-1)
    c = torch.cumsum(w, dim=-1)
    # Guard the last bin against round-off: every u < 1 must land inside.
    return torch.cat([c[..., :-1], torch.ones_like(c[..., -1:])], dim=-1)


def inverse_cdf(cdf_: Tensor, u: Tensor) -> Tensor:
    """Categorical draws by inversion: the one index helper of the library (resampling,
    ancestor draws of the MCMC moves, source draws of IP-MCMC).

    Parameters
    ----------
    cdf_ : (..., N) float64 from :func:`cdf`.
    u : (..., M) points in [0, 1) (cast to float64).

    Returns
    -------
    (..., M) int64 indices ``i`` with ``cdf[i-1] <= u < cdf[i]``.
    """
    idx = torch.searchsorted(cdf_, u.to(torch.float64).contiguous(), right=True)
    return idx.clamp_(max=cdf_.shape[-1] - 1)




def systematic(log_w: Tensor, u: Tensor, num_samples: Optional[int] = None) -> Tensor:
    """Systematic resampling: one uniform per run, points ``(i + u) / M``.

    Parameters
    ----------
    log_w : (B, N) log-weights (normalised or not).
    u : (B, 1) uniforms in [0, 1) (or (B, M): stratified).
    num_samples : M, defaults to N.

    Returns
    -------
    (B, M) int64 ancestor indices in ``[0, N)``.
    """
    m = log_w.shape[-1] if num_samples is None else num_samples
    grid = torch.arange(m, device=log_w.device, dtype=torch.float64)
    return inverse_cdf(cdf(log_w), (grid + u.to(torch.float64)) / m)


def stratified(log_w: Tensor, u: Tensor) -> Tensor:
    """Stratified resampling: one uniform per stratum, points ``(i + u_i) / M`` (the
    systematic points with a uniform per stratum).

    Parameters
    ----------
    log_w : (B, N); u : (B, M) uniforms in [0, 1).

    Returns
    -------
    (B, M) int64 ancestor indices.
    """
    return systematic(log_w, u, u.shape[-1])


def multinomial(log_w: Tensor, u: Tensor) -> Tensor:
    """Multinomial resampling by inversion of sorted uniforms (no ``torch.multinomial``).

    Parameters
    ----------
    log_w : (B, N); u : (B, M) uniforms in [0, 1).

    Returns
    -------
    (B, M) int64 ancestor indices, in increasing order (the particles are exchangeable).
    """
    return inverse_cdf(cdf(log_w), torch.sort(u, dim=-1).values)


def _u_systematic(b: int, m: int, *, generator, device, dtype=torch.float64) -> Tensor:
    return torch.rand(b, 1, generator=generator, device=device, dtype=dtype)


def _u_per_sample(b: int, m: int, *, generator, device, dtype=torch.float64) -> Tensor:
    return torch.rand(b, m, generator=generator, device=device, dtype=dtype)


#: name -> (uniform sampler, index kernel)
RESAMPLERS: dict[str, tuple[Callable, Callable]] = {
    "systematic": (_u_systematic, lambda lw, u, m: systematic(lw, u, m)),
    "stratified": (_u_per_sample, lambda lw, u, m: stratified(lw, u)),
    "multinomial": (_u_per_sample, lambda lw, u, m: multinomial(lw, u)),
}


def resample(
    log_w: Tensor,
    method: str = "systematic",
    *,
    generator: torch.Generator,
    num_samples: Optional[int] = None,
) -> Tensor:
    """Draw ancestor indices from ``(B, N)`` log-weights.

    Parameters
    ----------
    log_w : (B, N) log-weights.
    method : ``"systematic"`` (default), ``"stratified"`` or ``"multinomial"``.
    generator : the source of randomness.
    num_samples : M, number of indices per run (defaults to N).

    Returns
    -------
    (B, M) int64 ancestor indices.
    """
    if method not in RESAMPLERS:
        raise ValueError(f"method must be one of {sorted(RESAMPLERS)}, got {method!r}")
    check_generator(generator)
    check_shape(log_w, "log_w", (None, None))
    b, n = log_w.shape
    if b == 0 or n == 0:
        raise ValueError(f"log_w has shape {tuple(log_w.shape)}, expected (B, N) with B >= 1 and N >= 1")
    m = n if num_samples is None else check_positive_int(num_samples, "num_samples")
    draw, kernel = RESAMPLERS[method]
    u = draw(b, m, generator=generator, device=log_w.device)
    return kernel(log_w, u, m)


def gather_particles(x: Tensor, idx: Tensor) -> Tensor:
    """Select particles by ancestor index along dim 1.

    Parameters
    ----------
    x : (B, N, *E) any per-particle tensor; idx : (B, M) int64.

    Returns
    -------
    (B, M, *E).
    """
    view = idx.reshape(idx.shape + (1,) * (x.dim() - 2))
    return torch.take_along_dim(x, view, dim=1)
