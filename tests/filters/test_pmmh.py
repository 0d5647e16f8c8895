"""PMMH (Andrieu, Doucet, Holenstein 2010) driven by the SIR evidence: recovers the process
noise level of a linear-Gaussian model, checked against the exact (Kalman) posterior."""

import math

import pytest
import torch

from torchmcmcpf.diagnostics import chain_ess
from torchmcmcpf.filters.pmmh import ProcessNoiseScale, pmmh, sir_log_evidence
from torchmcmcpf.models.motion import ConstantVelocity
from torchmcmcpf.models.sensors.linear import LinearGaussian

DT = torch.float64


def _kalman_log_evidence(F, Qs, H, R, m0, P0, zs):
    """Exact log p(z_1:T | Q) by the prediction error decomposition, batched over Qs (G, D, D)."""
    g = Qs.shape[0]
    m, P = m0.expand(g, -1), P0.expand(g, -1, -1)
    total = torch.zeros(g, dtype=DT)
    for z in zs:
        m = m @ F.mT
        P = F @ P @ F.mT + Qs
        S = H @ P @ H.mT + R
        innov = z - m @ H.mT
        total += torch.distributions.MultivariateNormal(torch.zeros_like(innov), S).log_prob(innov)
        G = torch.linalg.solve(S, H @ P).mT
        m = m + (innov.unsqueeze(-2) @ G.mT).squeeze(-2)
        P = P - G @ S @ G.mT
    return total


def test_process_noise_scale_matches_cv(gen):
    # Both models' F, Q and chol(Q) are computed in float32 (the default dtype) and then cast,
    # so sqrt(3) chol(Q_1) and chol(Q_3) agree to float32 rounding only: compare at that
    # resolution (eps_32 = 1.2e-7 on terms of size ~5), not float64's.
    base = ConstantVelocity(1.0, q=1.0).to(DT)
    cv3 = ConstantVelocity(1.0, q=3.0).to(DT)
    scaled = ProcessNoiseScale(base, torch.tensor([3.0, 3.0], dtype=DT))
    x = torch.randn(2, 5, 1, 4, dtype=DT, generator=gen)
    xn = torch.randn(2, 5, 1, 4, dtype=DT, generator=gen)
    f32 = {"rtol": 1e-5, "atol": 1e-5}
    torch.testing.assert_close(scaled.log_prob(xn, x), cv3.log_prob(xn, x), **f32)
    eps = torch.randn(2, 5, 1, 4, dtype=DT, generator=gen)
    torch.testing.assert_close(scaled.propagate(x, eps), cv3.propagate(x, eps), **f32)


def test_pmmh_recovers_process_noise(gen):
    true_q, sigma, t_len = 4.0, 3.0, 15
    base = ConstantVelocity(1.0, q=1.0).to(DT)
    truth_motion = ConstantVelocity(1.0, q=true_q).to(DT)
    sensor = LinearGaussian.position(sigma).to(DT)
    m0 = torch.tensor([0.0, 1.0, 0.0, -1.0], dtype=DT)
    P0 = torch.eye(4, dtype=DT)
    x = (m0 + torch.randn(4, generator=gen, dtype=DT)).reshape(1, 1, 4)
    zs = []
    for _ in range(t_len):
        x = truth_motion.sample(x, generator=gen)
        zs.append(sensor.simulate(x, generator=gen))
    zs = torch.stack(zs)  # (T, 1, 1, 2)

    # exact posterior of theta = log q under the N(log 4 - 0.5, 1) prior, on a fine grid
    prior = torch.distributions.Normal(math.log(true_q) - 0.5, 1.0)
    grid = torch.linspace(-1.5, 4.0, 1101, dtype=DT)
    log_post = _kalman_log_evidence(base.F, grid.exp()[:, None, None] * base.Q, sensor.H, sensor.R,
                                    m0, P0, zs[:, 0, 0]) + prior.log_prob(grid)
    w = torch.softmax(log_post, 0)
    exact_mean = (w * grid).sum()
    exact_sd = ((w * grid**2).sum() - exact_mean**2).sqrt()

    def build(theta):
        return ProcessNoiseScale(base, theta[:, 0].exp()), sensor

    def init(m, *, generator):
        return m0 + torch.randn(m, 100, 1, 4, generator=generator, dtype=DT)

    evaluate = sir_log_evidence(build, zs, init, 100)
    c, iters, burn = 6, 60, 15
    theta0 = torch.full((1, c, 1), float(prior.mean), dtype=DT)
    res = pmmh(evaluate, theta0, log_prior=lambda th: prior.log_prob(th[..., 0]),
               proposal_std=0.4, num_iterations=iters, generator=gen)
    kept = res.theta[burn:, 0, :, 0]  # (S, C)
    est = kept.mean()
    # Monte Carlo error of the PMMH mean: posterior sd / sqrt(ESS), ESS from the chains'
    # autocorrelation (Geyer); 4 standard errors.
    ess = chain_ess(kept, chain_dim=1, sample_dim=0)
    mc_se = kept.std() / ess.sqrt()
    assert (est - exact_mean).abs() <= 4 * mc_se, (est, exact_mean, mc_se, ess)
    # the PMMH posterior spread matches the exact one (sd of a sd estimate ~ sd / sqrt(2 ESS))
    assert (kept.std() - exact_sd).abs() <= 4 * exact_sd / (2 * ess).sqrt()
    # and the true parameter lies within 3 posterior sds of the estimate
    assert (est - math.log(true_q)).abs() <= 3 * exact_sd
    assert 0.05 < res.acceptance.mean() < 0.95  # the chains move (a stuck chain lowers the ESS above)


def test_pmmh_rejects_outside_prior_and_is_deterministic():
    calls = []

    def evaluate(theta, *, generator):
        calls.append(theta.clone())
        return -(theta[..., 0] ** 2), None

    def log_prior(th):
        return torch.where(th[..., 0] > 0, torch.zeros_like(th[..., 0]), torch.full_like(th[..., 0], -math.inf))

    run = lambda: pmmh(evaluate, torch.ones(2, 3, 1), log_prior=log_prior, proposal_std=1.0,  # noqa: E731
                       num_iterations=30, generator=torch.Generator().manual_seed(3))
    r1, r2 = run(), run()
    assert torch.equal(r1.theta, r2.theta)
    assert (r1.theta > 0).all()  # never leaves the support
    assert all((c > 0).all() for c in calls)  # the evaluator never sees an invalid theta
    with pytest.raises(ValueError, match="theta0"):
        pmmh(evaluate, -torch.ones(1, 1, 1), log_prior=log_prior, proposal_std=1.0, num_iterations=2,
             generator=torch.Generator())


def test_sequential_pmmh_filter_matches_the_exact_posterior_over_theta():
    """PMMHFilter (particle independent MH over prior draws of theta = log q, module
    docstring of filters/pmmh.py) on a linear-Gaussian model: its estimate of E[x_T | z_1:T]
    and of E[theta | z_1:T], with theta integrated over its posterior, against the exact
    values (Kalman evidence and means on a fine theta grid). B runs filter the SAME data with
    independent randomness, so the run-to-run errors are iid: their mean must be within 5
    standard errors of zero. The finite chain (L candidates, started at a prior draw) has an
    O(1/L) bias: measured 0.14 at L = 16 and 0.03 at L = 64 in theta (posterior sd 0.4), below
    5 standard errors at L = 64 with B = 100."""
    from _kalman import kalman_filter

    from torchmcmcpf.filters import PMMHFilter

    gen = torch.Generator().manual_seed(5)
    true_q, sigma, t_len, b, lc, nc = 4.0, 3.0, 15, 100, 64, 32
    base = ConstantVelocity(1.0, q=1.0).to(DT)
    truth = ConstantVelocity(1.0, q=true_q).to(DT)
    sensor = LinearGaussian.position(sigma).to(DT)
    m0, P0 = torch.tensor([0.0, 1.0, 0.0, -1.0], dtype=DT), torch.eye(4, dtype=DT)
    x = (m0 + torch.randn(4, generator=gen, dtype=DT)).reshape(1, 1, 4)
    zs = []
    for _ in range(t_len):
        x = truth.sample(x, generator=gen)
        zs.append(sensor.simulate(x, generator=gen))
    zs = torch.stack(zs)  # (T, 1, 1, 2)
    mu = math.log(true_q) - 0.5
    grid = torch.linspace(mu - 6, mu + 6, 801, dtype=DT)
    qs = grid.exp()[:, None, None] * base.Q
    log_post = _kalman_log_evidence(base.F, qs, sensor.H, sensor.R, m0, P0, zs[:, 0, 0]) \
        + torch.distributions.Normal(mu, 1.0).log_prob(grid)
    w = torch.softmax(log_post, 0)
    km, _ = kalman_filter(base.F, qs, sensor.H, sensor.R, m0.expand(len(grid), 4), P0, zs[:, 0, 0])
    exact_x, exact_theta = (w[:, None] * km[-1]).sum(0), (w * grid).sum()

    filt = PMMHFilter(base, sensor, lc * nc, num_candidates=lc, prior_mean=mu, prior_std=1.0)
    init = m0 + torch.randn(b, lc * nc, 1, 4, generator=gen, dtype=DT)
    res = filt(zs.expand(t_len, b, 1, 2), init=init, generator=gen)
    err = res.mean[-1, :, 0] - exact_x  # (B, D)
    assert torch.all(err.mean(0).abs() <= 5 * err.std(0) / b**0.5), (err.mean(0), err.std(0))
    theta = res.info.extras["theta_mean"][-1]  # (B,)
    assert (theta.mean() - exact_theta).abs() <= 5 * theta.std() / b**0.5, (theta.mean(), exact_theta)
    assert 0.2 < float(res.info.acceptance.mean()) < 0.9  # the PIMH chain moves
    # the state carries the candidates: theta drawn once, evidence accumulated
    assert res.state.extras["pmmh"].theta.shape == (b, lc)
    torch.testing.assert_close(res.state.extras["pmmh"].log_evidence.logsumexp(-1) - math.log(lc),
                               res.log_evidence)


def test_pmmh_filter_settings_are_validated():
    from torchmcmcpf.filters import PMMHFilter

    motion, sensor = ConstantVelocity(1.0, 1.0), LinearGaussian.position(1.0)
    with pytest.raises(ValueError, match="num_particles must be a multiple of num_candidates"):
        PMMHFilter(motion, sensor, 10, num_candidates=4)
    with pytest.raises(ValueError, match="num_candidates"):
        PMMHFilter(motion, sensor, 10, num_candidates=1)
    with pytest.raises(ValueError, match="burn_in"):
        PMMHFilter(motion, sensor, 12, num_candidates=4, burn_in=4)
    with pytest.raises(ValueError, match="prior_std"):
        PMMHFilter(motion, sensor, 12, num_candidates=4, prior_std=0.0)
