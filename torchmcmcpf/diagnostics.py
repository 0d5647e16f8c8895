"""MCMC convergence diagnostics: Gelman-Rubin R-hat, split R-hat, effective sample sizes.

Every function reduces a *chain* dim and a *sample* dim given as arguments and keeps all
other dims, so one call scores every state component of every Monte Carlo run, e.g. a chain
history ``(S, B, C, K, D)`` with ``sample_dim=0, chain_dim=2`` gives ``(B, K, D)``.

Two R-hat definitions are offered, because the literature uses both:

``method="paper"`` (default of :func:`rhat`)
    Bocquel, Driessen and Bagchi (2012), paper 000 eq. 13: ``R = sqrt(C_bar / W_bar)``
    with ``C_bar`` the unbiased (``ddof = 1``) variance of all ``C * n`` samples pooled and
    ``W_bar`` the mean over chains of the unbiased within-chain variances. Writing ``B``
    for ``n`` times the variance of the chain means (``ddof = 1``),
    ``C_bar = ((n - 1) C W_bar + (C - 1) B) / (C n - 1)``.
``method="gelman-rubin"`` (:func:`psrf`)
    Gelman and Rubin (1992), ref. [23] of paper 000, the potential scale reduction factor
    without the degrees-of-freedom correction: ``R = sqrt(((n - 1)/n W_bar + B/n) / W_bar)``.

Both equal 1 for perfectly mixed chains and exceed 1 when chains disagree; for ``C``
chains of ``n`` samples they differ by ``O(1/n)`` (the paper's version is slightly
smaller, since its pooled variance divides by ``C n - 1``). ``W_bar = 0`` (chains that
never moved) gives ``inf`` if the chains disagree and 1 if every sample is equal.

Effective sample sizes: :func:`ess` (importance weights, re-exported from
:mod:`torchmcmcpf.resampling`) and :func:`chain_ess` (autocorrelation-based, Geyer's
initial monotone sequence estimator over several chains, as in Stan / Vehtari et al.
2021).
"""

from __future__ import annotations

import torch

from ._native.select import where
from .resampling import ess
from .typing import Tensor

__all__ = ["rhat", "psrf", "split_rhat", "chain_ess", "ess", "RHAT_METHODS"]

RHAT_METHODS = ("paper", "gelman-rubin")


def _to_chains_samples(x: Tensor, chain_dim: int, sample_dim: int, name: str = "x") -> Tensor:
    """Move the chain and sample dims last: ``(..., C, n)``; validate."""
    if not isinstance(x, torch.Tensor) or not x.is_floating_point():
        raise ValueError(f"{name} must be a floating point torch.Tensor, got {type(x).__name__}"
                         f"{'' if not isinstance(x, torch.Tensor) else ' of dtype ' + str(x.dtype)}")
    nd = x.dim()
    for dim, label in ((chain_dim, "chain_dim"), (sample_dim, "sample_dim")):
        if not -nd <= dim < nd:
            raise ValueError(f"{label}={dim} is out of range for {name} of shape {tuple(x.shape)}")
    if chain_dim % nd == sample_dim % nd:
        raise ValueError(f"chain_dim and sample_dim must differ, both are {chain_dim % nd}")
    return x.movedim((chain_dim, sample_dim), (-2, -1))


def _check_sizes(x: Tensor, min_samples: int, name: str = "x") -> None:
    c, n = x.shape[-2:]
    if c < 2 or n < min_samples:
        raise ValueError(
            f"{name} has {c} chain(s) of {n} sample(s) (chains and samples moved last: shape "
            f"{tuple(x.shape)}); expected at least 2 chains of at least {min_samples} samples"
        )


def _rhat_last(x: Tensor, method: str) -> Tensor:
    """R-hat of ``x (..., C, n)`` over the last two dims."""
    c, n = x.shape[-2:]
    chain_mean = x.mean(-1)  # (..., C)
    w = x.var(-1, correction=1).mean(-1)  # W_bar (...)
    b = n * chain_mean.var(-1, correction=1)  # between-chain variance B (...)
    if method == "paper":
        total = ((n - 1) * c * w + (c - 1) * b) / (c * n - 1)  # pooled variance, ddof 1
    else:
        total = (n - 1) / n * w + b / n
    ratio = total / w
    r = torch.sqrt(ratio)
    degenerate = where(total > 0, torch.full_like(r, float("inf")), torch.ones_like(r))
    return where(w > 0, r, degenerate)


def rhat(x: Tensor, *, chain_dim: int, sample_dim: int, method: str = "paper") -> Tensor:
    """Gelman-Rubin R-hat over chains and samples, batched over every other dim.

    Parameters
    ----------
    x : any shape with a chain dim (C >= 2) and a sample dim (n >= 2), e.g. a chain history
        ``(S, B, C, K, D)`` with ``sample_dim=0, chain_dim=2``.
    chain_dim, sample_dim : the two dims to reduce.
    method : ``"paper"`` (paper 000 eq. 13, ``sqrt(C_bar / W_bar)``, the default) or
        ``"gelman-rubin"`` (the classic PSRF, see :func:`psrf`). The module docstring
        gives both formulas exactly.

    Returns
    -------
    ``x`` without the two reduced dims, e.g. ``(B, K, D)``; values >= 0, ``inf`` where the
    chains disagree but none of them moved.
    """
    if method not in RHAT_METHODS:
        raise ValueError(f"method must be one of {RHAT_METHODS}, got {method!r}")
    xs = _to_chains_samples(x, chain_dim, sample_dim)
    _check_sizes(xs, 2)
    return _rhat_last(xs, method)


def psrf(x: Tensor, *, chain_dim: int, sample_dim: int) -> Tensor:
    """Classic Gelman-Rubin PSRF ``sqrt(((n - 1)/n W + B/n) / W)``: ``rhat(method="gelman-rubin")``."""
    return rhat(x, chain_dim=chain_dim, sample_dim=sample_dim, method="gelman-rubin")


def split_rhat(x: Tensor, *, chain_dim: int, sample_dim: int, method: str = "gelman-rubin") -> Tensor:
    """Split R-hat: every chain is cut into its first and second half (the middle sample of
    an odd-length chain is dropped), then R-hat is taken over the ``2 C`` half-chains
    (Gelman et al., Bayesian Data Analysis, 3rd ed., sec. 11.4). Detects chains that
    drift within themselves, which plain R-hat misses.

    Parameters
    ----------
    x : as in :func:`rhat`, with n >= 4 samples per chain (C >= 1 chains suffice).
    chain_dim, sample_dim : the two dims to reduce.
    method : ``"gelman-rubin"`` (default, the usual definition) or ``"paper"``.

    Returns
    -------
    ``x`` without the two reduced dims.
    """
    if method not in RHAT_METHODS:
        raise ValueError(f"method must be one of {RHAT_METHODS}, got {method!r}")
    xs = _to_chains_samples(x, chain_dim, sample_dim)
    c, n = xs.shape[-2:]
    if c < 1 or n < 4:
        raise ValueError(f"x has {c} chain(s) of {n} sample(s); split R-hat needs n >= 4")
    half = n // 2
    halves = torch.cat([xs[..., :half], xs[..., n - half:]], dim=-2)  # (..., 2C, half)
    return _rhat_last(halves, method)


def chain_ess(x: Tensor, *, chain_dim: int, sample_dim: int) -> Tensor:
    """Effective sample size of MCMC chains from their autocorrelation.

    Multi-chain estimator of Vehtari, Gelman, Simpson, Carpenter and Buerkner (2021),
    "Rank-normalization, folding, and localization" (the non-rank-normalised version):
    per-chain autocovariances by FFT, combined ``rho_t = 1 - (W - mean_c acov_t) / V`` with
    ``V = (n-1)/n W + B/n``, truncated by Geyer's (1992) initial positive sequence of pair
    sums ``P_m = rho_{2m} + rho_{2m+1}`` (summed while positive) made monotone
    (initial monotone sequence), ``tau = -1 + 2 sum_m P_m``, ``ESS = C n / tau``.
    Branch-free over all batch dims.

    Parameters
    ----------
    x : as in :func:`rhat`: C >= 1 chains of n >= 4 samples.
    chain_dim, sample_dim : the two dims to reduce.

    Returns
    -------
    ``x`` without the two reduced dims; ESS in ``(0, C n log10(C n)]`` (antithetic chains
    can exceed ``C n``, as in Stan). Constant components give ``C n``.
    """
    xs = _to_chains_samples(x, chain_dim, sample_dim)
    c, n = xs.shape[-2:]
    if n < 4:
        raise ValueError(f"x has chains of {n} sample(s); chain_ess needs n >= 4")
    centred = xs - xs.mean(-1, keepdim=True)
    size = 2 * n
    f = torch.fft.rfft(centred, n=size, dim=-1)
    acov = torch.fft.irfft(f * f.conj(), n=size, dim=-1)[..., :n] / n  # biased, (..., C, n)
    chain_var = acov[..., 0] * n / (n - 1)  # unbiased within-chain variance (..., C)
    w = chain_var.mean(-1)
    b_over_n = xs.mean(-1).var(-1, correction=1) if c > 1 else torch.zeros_like(w)
    v = (n - 1) / n * w + b_over_n
    safe_v = where(v > 0, v, torch.ones_like(v))
    rho = 1.0 - (w.unsqueeze(-1) - acov.mean(-2)) / safe_v.unsqueeze(-1)  # (..., n)
    rho = rho.clone()
    rho[..., 0] = 1.0
    m = n // 2
    pairs = rho[..., : 2 * m].reshape(rho.shape[:-1] + (m, 2)).sum(-1)  # P_m (..., m)
    positive = torch.cumprod((pairs > 0).to(pairs.dtype), dim=-1)  # initial positive sequence
    monotone = torch.cummin(where(positive > 0, pairs, torch.zeros_like(pairs)), dim=-1).values
    tau = -1.0 + 2.0 * (monotone * positive).sum(-1)
    # tau >= 1/log10(C n) guard (Stan); with P_0 = 1 + rho_1 > 0 tau is positive anyway
    total = c * n
    tau = tau.clamp(min=1.0 / max(torch.log10(torch.tensor(float(total))).item(), 1.0))
    out = total / tau
    return where(v > 0, out, torch.full_like(out, float(total)))
