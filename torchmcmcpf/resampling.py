"""Resampling of ``(B, N)`` log-weights and the effective sample size.

Every scheme is split in two: the uniforms are drawn from the explicit generator, and a
pure, compile-friendly function maps (log-weights, uniforms) to ancestor indices. The
cumulative sum runs in float64. Arbitrary points are inverted by ``searchsorted``
(:func:`inverse_cdf`, faster than ``torch.multinomial`` and traceable by ``torch.compile``,
DESIGN.md); the sorted stratified and systematic points ``(j + u_j) / M`` are inverted in one
pass by counting (:func:`stratified`), which is 5-8x faster than a batched ``searchsorted``
at B = 100, N = 5000 on the CPU (benchmarks/bench_resampling.py).

References: Douc, Cappe and Moulines (2005), "Comparison of resampling schemes for
particle filtering"; Doucet and Johansen (2009), sec. 3.4.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from typing import NamedTuple

import torch

from . import runtime
from ._native.select import where
from ._validation import check_generator, check_positive_int, check_shape
from .typing import Tensor

__all__ = [
    "normalize",
    "normalize_ess",
    "ess",
    "systematic",
    "stratified",
    "multinomial",
    "resample",
    "gather_particles",
    "RESAMPLERS",
    "cdf",
    "inverse_cdf",
    "Guide",
    "guide_table",
    "uniform_pick",
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
    top, dead, shifted = _shift(log_w)
    lse = torch.logsumexp(shifted, dim=-1, keepdim=True)
    return _finish(log_w, top, dead, shifted, lse)


def normalize_ess(log_w: Tensor) -> tuple[Tensor, Tensor, Tensor]:
    """:func:`normalize` and the effective sample size of the normalised weights, in one pass
    over the weights fewer than both separately (5 passes over ``(B, N)`` instead of about
    15: the linear weights are computed once and give both their sum and the ESS).

    Parameters
    ----------
    log_w : (B, N) unnormalised log-weights; ``-inf`` allowed.

    Returns
    -------
    log_w_norm, log_mean_w : as :func:`normalize` (the same bits: ``logsumexp`` of the
    shifted weights is the log of the sum of their exponentials, summed alike);
    ess : (B,) ``(sum w)^2 / sum w^2`` in ``[1, N]``, ``N`` for an all ``-inf`` row (uniform).
    """
    top = log_w.amax(dim=-1, keepdim=True)
    # a dead row (all -inf) subtracts a finite number and stays -inf; a live row its maximum
    shifted = log_w - top.clamp(min=torch.finfo(log_w.dtype).min)
    w = torch.exp(shifted)  # <= 1: the row maximum is 0
    total = w.sum(-1, keepdim=True)  # >= 1, or 0 for a dead row
    dead = total == 0
    ess_ = (total.squeeze(-1) / torch.linalg.vector_norm(w, dim=-1)).square()
    ess_ = where(dead.squeeze(-1), float(log_w.shape[-1]), ess_)
    return *_finish(log_w, top, dead, shifted, torch.log(total)), ess_


def _shift(log_w: Tensor) -> tuple[Tensor, Tensor, Tensor]:
    """Row maximum ``(B, 1)``, whether it is ``-inf`` and the weights minus it (0 for a dead row)."""
    # Subtract the row maximum first: at log-weights of order -1e4 a float32 subtraction of
    # logsumexp would lose ~1e-3 in the log; differences to the max are exact.
    top = log_w.amax(dim=-1, keepdim=True)
    dead = torch.isneginf(top)
    return top, dead, log_w - where(dead, torch.zeros_like(top), top)


def _finish(log_w: Tensor, top: Tensor, dead: Tensor, shifted: Tensor, lse: Tensor) -> tuple[Tensor, Tensor]:
    """``(shifted - lse`` with dead rows uniform, ``top + lse - log N)``."""
    log_n = math.log(log_w.shape[-1])
    log_w_norm = (shifted - lse).masked_fill_(dead, -log_n)
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
    c = torch.cumsum(torch.softmax(log_w.to(torch.float64), dim=-1), dim=-1)
    # Guard the last bin against round-off: every u < 1 must land inside (in place: the
    # cumulative sum is a fresh tensor, and its backward does not need its output).
    c[..., -1] = 1.0
    return c


def inverse_cdf(cdf_: Tensor, u: Tensor, guide: Guide | None = None) -> Tensor:
    """Categorical draws by inversion: the one index helper of the library (resampling,
    ancestor draws of the MCMC moves, source draws of IP-MCMC).

    Parameters
    ----------
    cdf_ : (..., N) float64 from :func:`cdf`.
    u : (..., M) points in [0, 1) (cast to float64).
    guide : :func:`guide_table` of ``cdf_``, optional: made once for a CDF that many draws
        invert (the previous cloud of an MCMC step's joint draws).

    Returns
    -------
    (..., M) int64 indices ``i`` with ``cdf[i-1] <= u < cdf[i]``.

    Eager on a CPU, with a ``guide`` or with many points per index (``M >= 4 N``: an MCMC
    segment's source draws), by a guide table (:func:`_guided`, the same indices); else
    ``searchsorted``.
    """
    u64 = u.to(torch.float64).contiguous()
    if (guide is not None and runtime.host_reads(u64)) or runtime.guided_search(cdf_, u64):
        found = _guided(cdf_, u64, guide)
        if found is not None:
            return found
    idx = torch.searchsorted(cdf_, u64, right=True)
    return idx.clamp_(max=cdf_.shape[-1] - 1)


def uniform_pick(mask: Tensor, u: Tensor) -> Tensor:
    """Indices drawn uniformly among the valid entries of each row: the data-driven proposals'
    pick of a frame's point or detection.

    Entry ``floor(u n)`` of the row's valid indices in order (``n`` of them; a row with none:
    among all ``M``): the law of ``inverse_cdf(cdf(log_w), u)`` with ``log_w`` 0 where valid,
    ``-inf`` elsewhere, and the same index except where ``u`` lies within a few ulps of a
    boundary ``j / n`` (the CDF's cumulative sum rounds there; near 1 it could name a padded
    entry, this never does). No search: for such weights :func:`inverse_cdf` does a binary
    search of every point, since the padded entries fill its guide table's last bin.

    Parameters
    ----------
    mask : (B, M) bool, the valid entries, ``M >= 1``; u : (B, P) uniforms in [0, 1).

    Returns
    -------
    (B, P) int64 indices into ``M``.
    """
    if mask.dim() != 2 or mask.shape[-1] < 1:
        raise ValueError(f"mask must be (B, M) with M >= 1, got shape {tuple(mask.shape)}")
    n = mask.sum(-1, keepdim=True)  # (B, 1)
    none = n == 0
    # the valid indices first, in order; a row with none: all, in order
    order = runtime.flagged_first(mask | none)
    n = where(none, mask.shape[-1], n)
    j = (u.to(torch.float64) * n).to(torch.int64)  # u >= 0: truncation is the floor
    return torch.gather(order, -1, torch.minimum(j, n - 1))  # u n rounded up to n: the last


#: the guide table's longest scan (entries of the CDF in one of its bins) before
#: :func:`_guided` leaves the points to ``searchsorted`` (weights piled on a few indices)
GUIDE_SCAN = 6
#: the fewest points for which a guide table made beforehand pays (:func:`inverse_cdf` with
#: ``guide``): its lookup is about 30 us of calls (eight passes and two host reads) and 10 ns
#: a point, ``searchsorted`` 60-70 ns a point into 2,000-5,000 indices (one CPU thread)
GUIDED_POINTS = 512


class Guide(NamedTuple):
    """A guide table over a CDF ``(..., N)`` (:func:`guide_table`; Chen and Asau 1974):
    ``lo (..., N + 1)`` int64, the index that the left edge of each bin ``[j / N, (j + 1) /
    N)`` gets (and of 1); ``padded (..., N + 1)`` float64, the CDF with an entry 2 after its
    last (a scan past the end counts nothing); ``scan`` () int64, the most indices a bin spans.

    Example
    -------
    >>> import torch
    >>> from torchmcmcpf.resampling import cdf, guide_table, inverse_cdf
    >>> c = cdf(torch.log(torch.tensor([[0.5, 0.25, 0.25]])))
    >>> guide = guide_table(c)
    >>> guide.lo, guide.scan            # the edges 0, 1/3, 2/3 fall at indices 0, 0, 1; the edge 1 past the end
    (tensor([[0, 0, 1, 3]]), tensor(2))
    >>> inverse_cdf(c, torch.tensor([[0.1, 0.6, 0.9]]), guide)
    tensor([[0, 1, 2]])
    """

    lo: Tensor
    padded: Tensor
    scan: Tensor


def guide_table(cdf_: Tensor) -> Guide:
    """The :class:`Guide` of ``cdf_ (..., N)`` float64 (:func:`cdf`): one ``searchsorted`` of
    the ``N + 1`` bin edges, what one inversion of ``N`` points costs; every inversion of the
    CDF then reads it (:func:`inverse_cdf`).
    """
    n = cdf_.shape[-1]
    edges = torch.arange(n + 1, device=cdf_.device, dtype=torch.float64) / n  # (N + 1,), edges[n] = 1
    lead = cdf_.shape[:-1]
    lo = torch.searchsorted(cdf_, edges.expand(lead + (n + 1,)).contiguous(), right=True)  # (..., N + 1)
    padded = torch.cat([cdf_, torch.full(lead + (1,), 2.0, dtype=cdf_.dtype, device=cdf_.device)], -1)
    return Guide(lo, padded, (lo[..., 1:] - lo[..., :-1]).max())


def _guided(cdf_: Tensor, u: Tensor, guide: Guide | None = None) -> Tensor | None:
    """:func:`inverse_cdf` by a guide table (Chen and Asau 1974; Devroye 1986, sec. III.2.4):
    the ``N`` bins ``[j / N, (j + 1) / N)``, each with the index ``lo[j]`` that the bin's
    left edge gets; a point in bin ``j`` has its index in ``lo[j] .. lo[j + 1]``, found by
    counting the CDF's entries ``<= u`` there, a scan of at most :data:`GUIDE_SCAN` gathers
    (about 1 for near-uniform weights) instead of ``log2 N`` dependent steps of a binary
    search: 2.5x faster for 140,000 points into ``N = 2,000`` (one CPU thread); with the
    table made beforehand (``guide``, :func:`guide_table`), 10,000 points into ``N = 2,000``
    in 0.1 against 0.7 ms. The same indices as ``searchsorted(cdf, u, right=True)`` clamped
    to ``N - 1`` (each point's bin is checked against its edge, and the result against the
    CDF); None where the scan would be longer (two host reads decide it).
    """
    n = cdf_.shape[-1]
    lo, padded, scan_ = guide_table(cdf_) if guide is None else guide
    scan = int(scan_)  # one host read
    if scan > GUIDE_SCAN:
        return None
    j = (u * n).to(torch.int64).clamp_(max=n - 1)  # the point's bin (u >= 0: truncation is the floor)
    j.sub_((u < j.to(torch.float64) / n).to(torch.int64)).clamp_(min=0)  # a product rounded up to the next edge
    idx = torch.gather(lo, -1, j)  # <= the index: every entry before it is <= the bin's edge <= u
    for _ in range(scan):  # count the entries <= u after it (the CDF is sorted: a prefix of the scan)
        idx.add_((torch.gather(padded, -1, idx) <= u).to(torch.int64))
    idx.clamp_(max=n - 1)
    # the index is right where its entry lies beyond u (or it is the last)
    if not bool(((torch.gather(padded, -1, idx) > u) | (idx == n - 1)).all()):  # one host read
        return None
    return idx


def systematic(log_w: Tensor, u: Tensor, num_samples: int | None = None) -> Tensor:
    """Systematic resampling: one uniform per run, points ``(j + u) / M`` (Douc et al. 2005,
    sec. 2.4): the stratified points with the same uniform in every stratum.

    Parameters
    ----------
    log_w : (B, N) log-weights (normalised or not).
    u : (B, 1) uniforms in [0, 1) (or (B, M): stratified).
    num_samples : M, defaults to N.

    Returns
    -------
    (B, M) int64 ancestor indices in ``[0, N)``, non-decreasing; particle ``i`` has
    ``floor(M w_i)`` or ``ceil(M w_i)`` offspring.
    """
    m = log_w.shape[-1] if num_samples is None else num_samples
    return _invert_strata(log_w, u, m)


def stratified(log_w: Tensor, u: Tensor) -> Tensor:
    """Stratified resampling: one uniform per stratum, points ``p_j = (j + u_j) / M`` (Douc
    et al. 2005, sec. 2.3), inverted in one pass without ``searchsorted``.

    The ancestor of point ``j`` is ``#{i : cdf_i <= p_j}`` (as :func:`inverse_cdf`). Since the
    points are sorted, that is ``#{i : n_i <= j}`` with ``n_i = #{j : p_j < cdf_i}``, and
    ``n_i`` has a closed form: with ``k = floor(M cdf_i)``, the points of the strata below
    ``k`` lie under ``cdf_i`` and the one of stratum ``k`` does when ``u_k < M cdf_i - k``.
    A histogram of the ``n_i`` and its cumulative sum give every index: O(N + M) work.

    Parameters
    ----------
    log_w : (B, N); u : (B, M) uniforms in [0, 1).

    Returns
    -------
    (B, M) int64 ancestor indices, non-decreasing.
    """
    return _invert_strata(log_w, u, u.shape[-1])


def _invert_strata(log_w: Tensor, u: Tensor, m: int) -> Tensor:
    """:func:`stratified` for ``u`` (B, M), or (B, 1): the same uniform in every stratum
    (systematic), where ``n_i`` is the number of integers ``j >= 0`` with ``j < M cdf_i - u``,
    ``ceil(M cdf_i - u)``: four passes over the weights (the difference is rounded: a point
    within about 1e-13 of a cdf value may count on the other side).
    """
    b = log_w.shape[0]
    u = u.to(torch.float64)
    if u.shape[-1] == 1:
        below = cdf(log_w).mul_(m).sub_(u).ceil_().to(torch.int64)  # (B, N) n_i, in [0, M]
        # cdf_N = 1 holds every point; M - u can round up to M - 1 when u is within an ulp of 1
        below[:, -1] = m
    else:
        scaled = cdf(log_w) * m                                    # (B, N) float64, last entry M
        k = scaled.floor()
        inside = k < m
        k = k.to(torch.int64).clamp_(max=m - 1)                    # the stratum holding cdf_i
        frac = scaled - k                                          # in [0, 1] where inside
        u_k = torch.gather(u, 1, k)                                # (B, N)
        below = where(inside, k + (u_k < frac), m)           # (B, N) n_i = #{j : p_j < cdf_i}
    hist = torch.zeros(b, m + 1, dtype=torch.int64, device=log_w.device)
    hist.scatter_add_(1, below, torch.ones((), dtype=torch.int64, device=log_w.device).expand_as(below))
    return hist[:, :m].cumsum_(-1)


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


def _u_systematic(b: int, m: int, *, generator: torch.Generator, device: torch.device | str | None,
                  dtype: torch.dtype = torch.float64) -> Tensor:
    return torch.rand(b, 1, generator=generator, device=device, dtype=dtype)


def _u_per_sample(b: int, m: int, *, generator: torch.Generator, device: torch.device | str | None,
                  dtype: torch.dtype = torch.float64) -> Tensor:
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
    num_samples: int | None = None,
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

    One ``index_select`` of whole rows of the flattened ``(B N, *E)`` tensor: 3x faster on
    the CPU than ``take_along_dim`` with an index expanded over ``*E`` (B = 100, N = 5000).
    """
    b, n = x.shape[:2]
    # (B, M) rows of (B N, *E); one run's rows are its indices (four operations fewer at B = 1)
    flat = idx if b == 1 else idx + torch.arange(b, device=idx.device).unsqueeze(-1) * n
    return x.flatten(0, 1).index_select(0, flat.flatten()).view(idx.shape + x.shape[2:])
