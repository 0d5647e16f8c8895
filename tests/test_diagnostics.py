"""Diagnostics: R-hat (paper eq. 13 and classic PSRF), split R-hat, chain ESS."""

import math

import pytest
import torch

from torchmcmcpf import diagnostics as dg
from torchmcmcpf.resampling import ess as resampling_ess


def test_rhat_equals_hand_computation():
    # chains [1, 2, 3] and [4, 5, 6]: n = 3, C = 2, chain means 2 and 5, within-chain
    # variances 1 and 1 -> W = 1; B = n * var(2, 5) = 3 * 4.5 = 13.5.
    # paper eq. 13: pooled variance of 1..6 (ddof 1) = 3.5 -> sqrt(3.5 / 1)
    # classic PSRF: ((n-1)/n W + B/n) / W = 2/3 + 4.5 -> sqrt(31/6)
    x = torch.tensor([[1.0, 2.0, 3.0], [4.0, 5.0, 6.0]], dtype=torch.float64)
    assert dg.rhat(x, chain_dim=0, sample_dim=1).item() == pytest.approx(math.sqrt(3.5), rel=1e-12)
    assert dg.psrf(x, chain_dim=0, sample_dim=1).item() == pytest.approx(math.sqrt(31 / 6), rel=1e-12)
    assert dg.rhat(x.T, chain_dim=1, sample_dim=0).item() == pytest.approx(math.sqrt(3.5), rel=1e-12)
    # second hand case with unequal within-chain variances:
    # chains [0, 2, 4, 6] (mean 3, var 20/3) and [1, 1, 1, 5] (mean 2, var 4): W = 16/3,
    # B = 4 * var(3, 2) = 2; pooled variance of all 8 values: mean 2.5, sum of squared deviations
    # 6.25 + 0.25 + 2.25 + 12.25 + 3 * 2.25 + 6.25 = 34 -> 34 / 7
    y = torch.tensor([[0.0, 2.0, 4.0, 6.0], [1.0, 1.0, 1.0, 5.0]], dtype=torch.float64)
    assert dg.rhat(y, chain_dim=0, sample_dim=1).item() == pytest.approx(math.sqrt((34 / 7) / (16 / 3)), rel=1e-12)
    psrf = (3 / 4 * 16 / 3 + 2 / 4) / (16 / 3)
    assert dg.psrf(y, chain_dim=0, sample_dim=1).item() == pytest.approx(math.sqrt(psrf), rel=1e-12)


def test_rhat_batched_matches_loop(gen):
    x = torch.randn(30, 3, 4, 2, generator=gen, dtype=torch.float64)  # (S, B, C, D)
    r = dg.rhat(x, chain_dim=2, sample_dim=0)
    assert r.shape == (3, 2)
    for b in range(3):
        for d in range(2):
            ref = dg.rhat(x[:, b, :, d], chain_dim=1, sample_dim=0)
            assert r[b, d].item() == pytest.approx(ref.item(), rel=1e-12)


def test_rhat_mixed_near_one_far_apart_above_threshold(gen):
    # 8 iid N(0, 1) chains of 500: R-hat - 1 = O(1/n) and its sd is O(1/sqrt(C n)) ~ 0.016,
    # so 1.05 is > 3 sd away from the expected value.
    iid = torch.randn(8, 500, generator=gen, dtype=torch.float64)
    assert dg.rhat(iid, chain_dim=0, sample_dim=1).item() < 1.05
    assert dg.split_rhat(iid, chain_dim=0, sample_dim=1).item() < 1.05
    # chains started far apart (offsets 0, 10, 20, ...) and never mixing: B / W ~ n * 100s
    far = iid + 10.0 * torch.arange(8, dtype=torch.float64).unsqueeze(-1)
    assert dg.rhat(far, chain_dim=0, sample_dim=1).item() > 1.1
    assert dg.psrf(far, chain_dim=0, sample_dim=1).item() > 1.1
    # a drifting single chain: plain R-hat cannot see it with one chain, split R-hat does
    drift = iid[:1] + torch.linspace(0, 10, 500, dtype=torch.float64)
    assert dg.split_rhat(drift, chain_dim=0, sample_dim=1).item() > 1.1


def test_rhat_degenerate_and_errors():
    const = torch.ones(3, 5)
    assert dg.rhat(const, chain_dim=0, sample_dim=1).item() == 1.0
    stuck = torch.arange(3.0).unsqueeze(-1).expand(3, 5)
    assert math.isinf(dg.rhat(stuck, chain_dim=0, sample_dim=1).item())
    with pytest.raises(ValueError, match="chain"):
        dg.rhat(torch.ones(1, 5), chain_dim=0, sample_dim=1)
    with pytest.raises(ValueError, match="differ"):
        dg.rhat(torch.ones(3, 5), chain_dim=1, sample_dim=1)
    with pytest.raises(ValueError, match="method"):
        dg.rhat(torch.ones(3, 5), chain_dim=0, sample_dim=1, method="x")
    with pytest.raises(ValueError, match="out of range"):
        dg.rhat(torch.ones(3, 5), chain_dim=2, sample_dim=1)


def test_chain_ess_ar1(gen):
    # AR(1) chains x_t = phi x_{t-1} + sqrt(1 - phi^2) e_t started in stationarity:
    # tau = (1 + phi) / (1 - phi) = 3 for phi = 0.5, ESS = C n / 3.
    # For 64 chains of n = 2000 (C n = 128000) the ESS estimator's relative sd is a few
    # percent (the sum of autocorrelations estimated from Cn samples, window ~ 10 lags:
    # sd(tau_hat)/tau ~ sqrt(2 * 10 / (C n / tau)) ~ 2.2%), so a 10% band is > 4 sd.
    phi, c, n = 0.5, 64, 2000
    e = torch.randn(c, n, generator=gen, dtype=torch.float64)
    x = torch.empty_like(e)
    x[:, 0] = e[:, 0]
    for t in range(1, n):
        x[:, t] = phi * x[:, t - 1] + math.sqrt(1 - phi**2) * e[:, t]
    ess = dg.chain_ess(x.T.unsqueeze(-1), chain_dim=1, sample_dim=0)  # (1,)
    assert ess.shape == (1,)
    assert ess.item() == pytest.approx(c * n / 3, rel=0.10)
    # iid samples: ESS ~ C n
    iid = dg.chain_ess(e, chain_dim=0, sample_dim=1).item()
    assert iid == pytest.approx(c * n, rel=0.10)


def test_importance_ess_reexport():
    assert dg.ess is resampling_ess
    assert dg.ess(torch.zeros(2, 10)).tolist() == pytest.approx([10.0, 10.0])
