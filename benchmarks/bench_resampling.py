"""Systematic resampling of ``(B, N)`` log-weights: the one-pass counting inversion of the
sorted points (:func:`torchmcmcpf.resampling.systematic`) against the generic ``searchsorted``
inversion of the same points (:func:`torchmcmcpf.resampling.inverse_cdf`), in one run.

    .venv/bin/pytest benchmarks/bench_resampling.py --benchmark-only --benchmark-group-by=group

Groups ``resample-B<B>-N<N>``; both variants return the same indices (tests/test_resampling.py).
Groups ``sources-<weights>``: an MCMC segment's many source draws, by the guide table of
:func:`~torchmcmcpf.resampling.inverse_cdf` against plain ``searchsorted``.
"""

from __future__ import annotations

import pytest
import torch

from torchmcmcpf import resampling as rs


def _searchsorted(log_w, u):
    m = log_w.shape[-1]
    return rs.inverse_cdf(rs.cdf(log_w), (torch.arange(m, dtype=torch.float64) + u) / m)


@pytest.mark.parametrize("variant", ["counting", "searchsorted"])
@pytest.mark.parametrize("b", [1, 100])
def test_systematic(benchmark, variant, b, n=5000):
    g = torch.Generator().manual_seed(0)
    log_w = torch.randn(b, n, generator=g) * 3
    u = torch.rand(b, 1, generator=g, dtype=torch.float64)
    fn = rs.systematic if variant == "counting" else _searchsorted
    benchmark.group = f"resample-B{b}-N{n}"
    benchmark.extra_info.update(variant=variant)
    idx = benchmark.pedantic(fn, args=(log_w, u), rounds=30, iterations=1, warmup_rounds=2)
    assert idx.shape == (b, n)


@pytest.mark.parametrize("variant", ["inverse_cdf", "searchsorted"])
@pytest.mark.parametrize("weights", ["uniform", "random"])
def test_source_draws(benchmark, variant, weights, b=10, n=2000, m=14000):
    """An IP-MCMC-PF segment's source draws on the births/deaths scene (B = 10 runs, N = 2000
    particles, 70 iterations x 200 chains = 14,000 points a run): :func:`inverse_cdf`, which
    takes its guide table there (``M >= 4 N``, eager CPU), against the plain
    ``searchsorted`` it replaces; the same indices (tests/test_resampling.py). Groups
    ``sources-<weights>``."""
    g = torch.Generator().manual_seed(0)
    log_w = torch.zeros(b, n, dtype=torch.float64) if weights == "uniform" else \
        torch.randn(b, n, generator=g, dtype=torch.float64)
    c = rs.cdf(log_w)
    u = torch.rand(b, m, generator=g, dtype=torch.float64)

    def plain(c, u):
        return torch.searchsorted(c, u, right=True).clamp_(max=n - 1)

    fn = rs.inverse_cdf if variant == "inverse_cdf" else plain
    benchmark.group = f"sources-{weights}"
    benchmark.extra_info.update(variant=variant, threads=torch.get_num_threads())
    idx = benchmark.pedantic(fn, args=(c, u), rounds=30, iterations=1, warmup_rounds=2)
    assert torch.equal(idx, plain(c, u))
