"""HMC refinement move (issue 13 item 5): exact invariance of MCMCFilter's conditional
target on a linear-Gaussian case, the filter with the move against the Kalman filter, bad
input. (IP-MCMC's factorised target: tests/filters/test_ipmcmc.py.)"""

import math

import pytest
import torch
from _kalman import kalman_filter

from torchmcmcpf.filters.mcmc import MCMCFilter
from torchmcmcpf.kernels.hmc_refine import HMCRefine, HMCRefineNoise, ancestor_log_prior, hmc_refine
from torchmcmcpf.models.motion import ConstantVelocity, LinearGaussianMotion, WhiteAccelerationMotion
from torchmcmcpf.models.sensors.linear import LinearGaussian

DT = torch.float64


def test_hmc_refine_leaves_ancestor_conditional_invariant(gen):
    """MCMCFilter's target given the chain's ancestor a is pi(x | a) ∝ N(z; x, r) N(x; x_a, q)
    per slot (scalar random walk), exactly N((r x_a + q z)/(q + r), q r/(q + r)). Chains
    started there stay there after 5 transitions: the standardised states have mean 0 and
    variance 1 within 4.5 Monte Carlo standard errors (M = B C K independent chains), and
    the chains move."""
    q, r = 1.0, 0.5
    motion = LinearGaussianMotion(torch.eye(1, dtype=DT), q * torch.eye(1, dtype=DT))
    sensor = LinearGaussian(torch.eye(1, dtype=DT), r * torch.eye(1, dtype=DT))
    b, c, k = 2, 1500, 2
    x_anc = 3.0 * torch.randn(b, c, k, 1, generator=gen, dtype=DT)
    z = torch.tensor([[1.0, -2.0], [0.5, 4.0]], dtype=DT).unsqueeze(-1)  # (B, K, 1)
    mean = (r * x_anc + q * z.unsqueeze(1)) / (q + r)
    sd = math.sqrt(q * r / (q + r))
    x = mean + sd * torch.randn(b, c, k, 1, generator=gen, dtype=DT)
    ll = sensor.log_likelihood(x, z)
    acc = 0.0
    for _ in range(5):
        x, ll, a = hmc_refine(x, ll, HMCRefineNoise.draw(x, generator=gen), z,
                              log_prior=ancestor_log_prior(x_anc, motion), sensor=sensor, motion=motion,
                              settings=HMCRefine(step_size=0.6, num_leapfrog=3))
        acc += a.double().mean().item() / 5
    assert 0.3 < acc < 0.995
    torch.testing.assert_close(ll, sensor.log_likelihood(x, z))
    e = ((x - mean) / sd).flatten()
    m = e.numel()
    assert e.mean().abs() <= 4.5 / math.sqrt(m)
    assert (e.var() - 1).abs() <= 4.5 * math.sqrt(2 / m)


def test_mcmc_filter_with_hmc_matches_kalman(gen):
    """One target, linear-Gaussian: the MCMC filter with the HMC refinement mixed in still
    approximates the exact (Kalman) posterior (unbiased standardised errors, a spread that
    matches the Kalman variance, as tests/filters/test_mcmc.py checks without it)."""
    b, n, c, steps = 20, 200, 20, 4
    motion = ConstantVelocity(1.0, q=1.0).to(DT)
    sensor = LinearGaussian.position(4.0).to(DT)
    m0 = torch.tensor([0.0, 5.0, 0.0, -3.0], dtype=DT).expand(b, 4)
    P0 = torch.diag(torch.tensor([25.0, 1.0, 25.0, 1.0], dtype=DT))
    x = m0 + torch.randn(b, 4, generator=gen, dtype=DT) @ torch.linalg.cholesky(P0).mT
    zs = []
    for _ in range(steps):
        x = motion.sample(x.unsqueeze(1), generator=gen).squeeze(1)
        zs.append(sensor.simulate(x.unsqueeze(1), generator=gen))
    zs = torch.stack(zs)
    x0 = m0[:, None, None] + torch.randn(b, n, 1, 4, generator=gen, dtype=DT) @ torch.linalg.cholesky(P0).mT
    filt = MCMCFilter(motion, sensor, n, num_chains=c, burn_in=10, moves="joint",
                      hmc=HMCRefine(step_size=0.5, num_leapfrog=3, every=2))
    res = filt(zs, init=x0, generator=gen)
    means, covs = kalman_filter(motion.F, motion.Q, sensor.H, sensor.R, m0, P0, zs[:, :, 0])
    sd = torch.diagonal(covs, dim1=-2, dim2=-1).sqrt()
    zerr = (res.mean[:, :, 0] - means) / sd
    per_run = zerr.mean((0, 2))
    assert per_run.mean().abs() <= 4 * per_run.std() / math.sqrt(b)
    ratio = (res.state.x[:, :, 0].var(1) / torch.diagonal(covs[-1], dim1=-2, dim2=-1)).mean(-1)
    assert (ratio.mean() - 1).abs() <= 4 * ratio.std() / math.sqrt(b) + 0.05
    assert zerr.square().mean() <= 0.25
    acc = res.info.extras["acceptance_hmc"]
    assert acc.shape == (steps, b) and ((acc > 0.3) & (acc <= 1)).all()


def test_hmc_refine_bad_input():
    with pytest.raises(ValueError, match="hmc.step_size"):
        HMCRefine(step_size=0.0)
    with pytest.raises(ValueError, match="hmc.every"):
        HMCRefine(every=0)
    with pytest.raises(ValueError, match="LinearGaussianMotion"):
        MCMCFilter(WhiteAccelerationMotion(), LinearGaussian.position(1.0), 10, hmc=HMCRefine())
    with pytest.raises(ValueError, match="hmc must be"):
        MCMCFilter(ConstantVelocity(1.0, 1.0), LinearGaussian.position(1.0), 10, hmc=0.5)


def test_log_priors_match_motion_log_prob(gen):
    """The whitened log-densities equal the motion's own log_prob (and the mixture its
    log-sum-exp over the previous particles)."""
    from torchmcmcpf.kernels.hmc_refine import mixture_log_prior

    motion = ConstantVelocity(1.0, 1.0, amplitude_q=0.01).to(DT)
    x_prev = torch.randn(2, 6, 3, 5, generator=gen, dtype=DT)
    x = torch.randn(2, 4, 3, 5, generator=gen, dtype=DT)
    torch.testing.assert_close(ancestor_log_prior(x_prev[:, :4], motion)(x), motion.log_prob(x, x_prev[:, :4]).sum(-1))
    log_w = torch.log_softmax(torch.randn(2, 6, generator=gen, dtype=DT), -1)
    expected = torch.logsumexp(motion.log_prob(x.unsqueeze(2), x_prev.unsqueeze(1)) + log_w[:, None, :, None], 2)
    torch.testing.assert_close(mixture_log_prior(x_prev, log_w, motion)(x), expected.sum(-1))
