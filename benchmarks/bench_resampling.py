"""Systematic resampling of ``(B, N)`` log-weights: the one-pass counting inversion of the
sorted points (:func:`torchmcmcpf.resampling.systematic`) against the generic ``searchsorted``
inversion of the same points (:func:`torchmcmcpf.resampling.inverse_cdf`), in one run.

    .venv/bin/pytest benchmarks/bench_resampling.py --benchmark-only --benchmark-group-by=group

Groups ``resample-B<B>-N<N>``; both variants return the same indices (tests/test_resampling.py).
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
