"""Thresholded pixel sensor (Septier et al. 2009, eqs. 39-41)."""

from __future__ import annotations

import itertools
import math

import pytest
import torch

from torchmcmcpf.models.sensors import ThresholdedPixels


def _brute_force(sensor, x, z, exists):
    """log prod over EVERY pixel of p(z_ij | x) / p(z_ij | no target), float64 loops."""
    h, w = sensor.shape
    s = sensor.pixel_size
    out = torch.zeros(x.shape[:-2], dtype=torch.float64)
    for lead in itertools.product(*(range(d) for d in x.shape[:-2])):
        b = lead[0]
        total = 0.0
        for i in range(h):
            for j in range(w):
                n = 0
                for k in range(x.shape[-2]):
                    px, py = float(x[lead + (k, 0)]), float(x[lead + (k, 2)])
                    if exists[lead + (k,)] and j * s <= px < (j + 1) * s and i * s <= py < (i + 1) * s:
                        n += 1
                pd = sensor.p_fa ** (1.0 / (1.0 + n * sensor.snr))
                zij = bool(z[b, i, j])
                num = pd if zij else 1 - pd
                den = sensor.p_fa if zij else 1 - sensor.p_fa
                total += math.log(num / den)
        out[lead] = total
    return out


def test_log_likelihood_equals_brute_force_product(gen):
    sensor = ThresholdedPixels((4, 5), 10.0, p_fa=0.05, p_d1=0.7)
    b, n, k = 2, 6, 4
    x = torch.zeros(b, n, k, 4, dtype=torch.float64)
    x[..., 0] = -5 + 60 * torch.rand(b, n, k, generator=gen, dtype=torch.float64)  # some off-grid
    x[..., 2] = -5 + 50 * torch.rand(b, n, k, generator=gen, dtype=torch.float64)
    x[..., 1::2] = torch.randn(b, n, k, 2, generator=gen, dtype=torch.float64)
    # particle 0: two targets in one pixel, one outside, one inactive
    x[:, 0, 0, [0, 2]] = torch.tensor([12.0, 23.0], dtype=torch.float64)
    x[:, 0, 1, [0, 2]] = torch.tensor([18.5, 21.0], dtype=torch.float64)
    x[:, 0, 2, [0, 2]] = torch.tensor([51.0, 5.0], dtype=torch.float64)
    # particle 1: three targets in one pixel
    x[:, 1, :3, 0], x[:, 1, :3, 2] = 31.0, 11.0
    exists = torch.rand(b, n, k, generator=gen) < 0.8
    exists[:, :2, :3] = True
    exists[:, 0, 3] = False
    z = torch.rand(b, 4, 5, generator=gen) < 0.5
    z[:, 2, 1] = True  # the shared pixel of particle 0 fires in run 0 ...
    z[1, 2, 1] = False  # ... and not in run 1
    got = sensor.log_likelihood(x, z, exists)
    assert got.shape == (b, n) and got.dtype == torch.float64
    ref = _brute_force(sensor, x, z, exists)
    torch.testing.assert_close(got, ref, rtol=1e-12, atol=1e-12)
    # without exists: every slot active
    torch.testing.assert_close(sensor.log_likelihood(x, z), _brute_force(sensor, x, z, torch.ones_like(exists)),
                               rtol=1e-12, atol=1e-12)


def test_position_only_states(gen):
    sensor = ThresholdedPixels((4, 5), 10.0, p_fa=0.05, p_d1=0.7)
    pos_only = ThresholdedPixels((4, 5), 10.0, p_fa=0.05, p_d1=0.7, position_index=(0, 1))
    x = 45 * torch.rand(2, 3, 4, 4, generator=gen, dtype=torch.float64)
    z = torch.rand(2, 4, 5, generator=gen) < 0.5
    torch.testing.assert_close(pos_only.log_likelihood(x[..., 0::2], z), sensor.log_likelihood(x, z))


def test_snr_from_p_d1_and_the_papers_discrepancy():
    sensor = ThresholdedPixels((100, 100), 50.0, p_fa=0.002, p_d1=0.7)
    assert sensor.snr == pytest.approx(math.log(0.002) / math.log(0.7) - 1, rel=1e-15)
    assert sensor.snr == pytest.approx(16.42, abs=0.01) and sensor.snr_db == pytest.approx(12.15, abs=0.01)
    assert sensor.p_d1 == pytest.approx(0.7, rel=1e-14)
    at_17db = ThresholdedPixels((100, 100), 50.0, p_fa=0.002, snr=10 ** 1.7)
    assert at_17db.p_d1 == pytest.approx(0.885, abs=1e-3)
    assert sensor.area == ((0.0, 5000.0), (0.0, 5000.0))


def test_simulate_rates(gen):
    sensor = ThresholdedPixels((20, 20), 1.0, p_fa=0.05, p_d1=0.6)
    b = 4000
    x = torch.zeros(b, 3, 4, dtype=torch.float64)
    x[:, 0, [0, 2]] = torch.tensor([3.5, 2.5], dtype=torch.float64)   # alone in pixel (2, 3)
    x[:, 1, [0, 2]] = torch.tensor([10.2, 10.2], dtype=torch.float64)  # two in pixel (10, 10)
    x[:, 2, [0, 2]] = torch.tensor([10.7, 10.9], dtype=torch.float64)
    z = sensor.simulate(x, generator=gen)
    assert z.shape == (b, 20, 20) and z.dtype == torch.bool
    p2 = 0.05 ** (1 / (1 + 2 * sensor.snr))
    for rate, p in ((z[:, 2, 3].double().mean(), 0.6), (z[:, 10, 10].double().mean(), p2)):
        assert abs(float(rate) - p) < 5 * math.sqrt(p * (1 - p) / b)
    fa = z.double().sum((1, 2)) - z[:, 2, 3].double() - z[:, 10, 10].double()
    p_fa = float(fa.mean()) / 398
    assert abs(p_fa - 0.05) < 5 * math.sqrt(0.05 * 0.95 / (398 * b))
    # inactive targets do not fire their pixel beyond P_fa
    z0 = sensor.simulate(x, generator=gen, exists=torch.zeros(b, 3, dtype=torch.bool))
    assert abs(float(z0[:, 2, 3].double().mean()) - 0.05) < 5 * math.sqrt(0.05 * 0.95 / b)


def test_same_seed_same_frame():
    sensor = ThresholdedPixels((10, 10), 5.0, p_fa=0.01, p_d1=0.7)
    x = torch.rand(3, 4, 4, generator=torch.Generator().manual_seed(0), dtype=torch.float64) * 50
    a = sensor.simulate(x, generator=torch.Generator().manual_seed(7))
    assert torch.equal(a, sensor.simulate(x, generator=torch.Generator().manual_seed(7)))


def test_bad_input():
    with pytest.raises(ValueError, match="exactly one"):
        ThresholdedPixels((4, 4), 1.0, p_fa=0.01)
    with pytest.raises(ValueError, match="p_d1"):
        ThresholdedPixels((4, 4), 1.0, p_fa=0.01, p_d1=0.005)
    with pytest.raises(ValueError, match="p_fa"):
        ThresholdedPixels((4, 4), 1.0, p_fa=1.5, p_d1=0.7)
    with pytest.raises(ValueError, match="shape"):
        ThresholdedPixels((4,), 1.0, p_fa=0.01, p_d1=0.7)
    sensor = ThresholdedPixels((4, 4), 1.0, p_fa=0.01, p_d1=0.7)
    with pytest.raises(ValueError, match="z has shape"):
        sensor.validate(torch.zeros(2, 4, 5))
    with pytest.raises(ValueError, match="binary"):
        sensor.validate(torch.full((2, 4, 4), 0.5))
