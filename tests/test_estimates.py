"""``state.weighted_cov``: the weighted covariance of each slot against a float64 reference
(NumPy's ``cov`` with ``aweights``), with and without existence flags.
"""

import math

import numpy as np
import torch

from torchmcmcpf.state import weighted_cov, weighted_mean


def _reference(x, w, e):
    """Per run and slot, NumPy's weighted covariance (``bias=True``) over the live particles."""
    b, _, k, d = x.shape
    out = np.zeros((b, k, d, d))
    for i in range(b):  # a reference, over a handful of runs and slots
        for j in range(k):
            live = e[i, :, j]
            if live.sum() > 0:
                out[i, j] = np.cov(x[i, live, j].T, aweights=w[i, live], bias=True)
    return out


def test_weighted_cov_matches_numpy_with_and_without_existence():
    g = torch.Generator().manual_seed(0)
    b, n, k, d = 3, 400, 2, 4
    x = 1000.0 + 3.0 * torch.randn(b, n, k, d, generator=g, dtype=torch.float64)  # far from 0, as positions are
    log_w = torch.randn(b, n, generator=g, dtype=torch.float64)
    w = torch.softmax(log_w, -1)
    mean = weighted_mean(x, log_w)
    ones = np.ones((b, n, k), dtype=bool)
    got = weighted_cov(x, log_w, mean)
    assert got.shape == (b, k, d, d) and torch.equal(got, got.mT)
    np.testing.assert_allclose(got.numpy(), _reference(x.numpy(), w.numpy(), ones), rtol=1e-10, atol=1e-10)

    exists = torch.rand(b, n, k, generator=g) < 0.6
    exists[0, :, 1] = False  # a slot no particle has: zeros, not NaN
    x_dead = x.masked_fill(~exists.unsqueeze(-1), math.inf)  # dead slots hold x_death
    we = w.unsqueeze(-1) * exists
    live_x = x.masked_fill(~exists.unsqueeze(-1), 0.0)
    mean_e = (we.unsqueeze(-1) * live_x).sum(1) / we.sum(1).clamp(min=1e-300)[..., None]
    got = weighted_cov(x_dead, log_w, mean_e, exists)
    assert torch.isfinite(got).all() and (got[0, 1] == 0).all()
    np.testing.assert_allclose(got.numpy(), _reference(x.numpy(), w.numpy(), exists.numpy()), rtol=1e-10, atol=1e-10)


def test_weighted_cov_float32_keeps_the_spread_of_far_particles():
    """Centred before the product: a spread of 1 m at 1e4 m in float32 is not lost."""
    g = torch.Generator().manual_seed(1)
    x = 1e4 + torch.randn(2, 5000, 1, 4, generator=g)
    log_w = torch.zeros(2, 5000)
    got = weighted_cov(x, log_w, weighted_mean(x, log_w))
    ref = _reference(x.double().numpy(), np.full((2, 5000), 1 / 5000), np.ones((2, 5000, 1), dtype=bool))
    np.testing.assert_allclose(got.double().numpy(), ref, rtol=1e-3, atol=1e-3)
