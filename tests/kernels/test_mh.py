import math
from typing import NamedTuple

import torch

from torchmcmcpf.kernels.mh import mh_accept, mh_select


def test_accept_edge_cases():
    inf, nan = math.inf, math.nan
    log_alpha = torch.tensor([[nan, nan, -inf, -inf, inf, 0.0, 2.0, -1.0]])
    u = torch.tensor([[0.0, 0.5, 0.0, 0.5, 0.999, 0.999, 0.5, 0.999]])
    # NaN rejects (even with u = 0), -inf rejects, +inf and log_alpha >= 0 accept
    expected = torch.tensor([[False, False, False, False, True, True, True, False]])
    assert torch.equal(mh_accept(log_alpha, u), expected)


def test_accept_probability_is_min_one_alpha(gen):
    """P(accept) = min(1, alpha). With M uniforms per value the frequency has binomial
    standard error sqrt(p (1 - p) / M); 5 se bounds a chance failure at 6e-7 per value."""
    M = 20000
    alpha = torch.tensor([0.01, 0.3, 0.7, 1.0, 3.0], dtype=torch.float64)
    u = torch.rand(M, 5, generator=gen, dtype=torch.float64)
    freq = mh_accept(alpha.log().expand(M, 5), u).to(torch.float64).mean(0)
    p = alpha.clamp(max=1.0)
    se = torch.sqrt(p * (1 - p) / M)
    assert ((freq - p).abs() <= 5 * se + 1e-12).all(), (freq, p)
    assert freq[3] == 1.0 and freq[4] == 1.0


def test_select_over_trailing_dims():
    accepted = torch.tensor([[True, False, True]])  # (B=1, C=3)
    prop, cur = torch.ones(1, 3, 2, 4), torch.zeros(1, 3, 2, 4)
    out = mh_select(accepted, prop, cur)
    assert out.shape == (1, 3, 2, 4)
    assert torch.equal(out[0, :, 0, 0], torch.tensor([1.0, 0.0, 1.0]))
    assert torch.equal(mh_select(accepted, torch.ones(1, 3), torch.zeros(1, 3)), torch.tensor([[1.0, 0.0, 1.0]]))
    # per-target flags (B, C, K) over states (B, C, K, D)
    per_target = torch.tensor([[[True, False]] * 3])
    out = mh_select(per_target, prop, cur)
    assert torch.equal(out[..., 0, :], prop[..., 0, :]) and torch.equal(out[..., 1, :], cur[..., 1, :])


class _Chain(NamedTuple):
    x: torch.Tensor
    log_lik: torch.Tensor
    terms: torch.Tensor | None = None


def test_select_over_a_pytree_with_none():
    accepted = torch.tensor([[False, True]])
    prop = _Chain(torch.ones(1, 2, 3, 4), torch.ones(1, 2))
    cur = _Chain(torch.zeros(1, 2, 3, 4), torch.zeros(1, 2))
    out = mh_select(accepted, prop, cur)
    assert isinstance(out, _Chain) and out.terms is None
    assert torch.equal(out.log_lik, torch.tensor([[0.0, 1.0]]))
    assert torch.equal(out.x[0, :, 1, 2], torch.tensor([0.0, 1.0]))
