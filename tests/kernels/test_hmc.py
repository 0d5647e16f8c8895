"""HMC kernel: invariance of a known Gaussian, leapfrog reversibility and order, API."""

import math

import pytest
import torch

from torchmcmcpf.kernels.hmc import hmc, leapfrog, value_and_grad

MU = torch.tensor([1.0, -2.0], dtype=torch.float64)
COV = torch.tensor([[1.0, 0.6], [0.6, 2.0]], dtype=torch.float64)
PREC = torch.linalg.inv(COV)


def gauss_log_target(q):
    r = q - MU
    return -0.5 * torch.einsum("...i,ij,...j->...", r, PREC, r)


def gauss_grad(q):
    return -(q - MU) @ PREC


def exact_draws(shape, gen):
    L = torch.linalg.cholesky(COV)
    return MU + torch.randn(shape + (2,), generator=gen, dtype=torch.float64) @ L.mT


def moment_errors(q):
    """Standardised errors (estimate - truth) / SE of the mean, variances and covariance.

    The chains start from exact independent draws; if the kernel leaves the target
    invariant the final states are again independent exact draws (chains never interact),
    so with n draws: SE(mean_i) = sqrt(S_ii / n); for a Gaussian SE(var_i) =
    S_ii sqrt(2 / (n - 1)) and SE(cov_01) = sqrt((S_00 S_11 + S_01^2) / n)."""
    x = q.reshape(-1, 2)
    n = x.shape[0]
    mean = x.mean(0)
    c = torch.cov(x.T)
    z_mean = (mean - MU) / torch.sqrt(torch.diagonal(COV) / n)
    z_var = (torch.diagonal(c) - torch.diagonal(COV)) / (torch.diagonal(COV) * math.sqrt(2 / (n - 1)))
    z_cov = (c[0, 1] - COV[0, 1]) / math.sqrt((COV[0, 0] * COV[1, 1] + COV[0, 1] ** 2) / n)
    return torch.cat([z_mean, z_var, z_cov.reshape(1)])


def test_hmc_leaves_gaussian_invariant(gen):
    # 4 runs x 5000 chains = 20000 independent draws; 5 moments at 4.5 SE: a false
    # failure has probability < 5 * 7e-6 under the null.
    q0 = exact_draws((4, 5000), gen)
    q, info = hmc(q0, gauss_log_target, step_size=1.2, num_leapfrog=3, num_steps=5, generator=gen)
    assert q.shape == q0.shape and info.acceptance.shape == (4, 5000)
    acc = info.acceptance.mean().item()
    assert 0.3 < acc < 0.95  # the MH correction is doing real work at this step size
    assert moment_errors(q).abs().max() < 4.5
    # the chains really moved
    assert (q - q0).abs().mean() > 0.3
    torch.testing.assert_close(info.log_target, gauss_log_target(q))


def test_the_invariance_check_has_power(gen):
    # Same trajectories with every proposal accepted (no MH correction): leapfrog with a
    # step of 1.2 does not preserve the target; the moment check must notice.
    q = exact_draws((4, 5000), gen)
    v, g = value_and_grad(gauss_log_target, q)
    for _ in range(5):
        p = torch.randn(q.shape, generator=gen, dtype=q.dtype)
        q, _, v, g = leapfrog(q, p, g, gauss_log_target, step_size=1.2, num_steps=3)
    assert moment_errors(q).abs().max() > 4.5


def test_closed_form_gradient_gives_same_chain(gen):
    q0 = exact_draws((2, 50), gen)
    a, ia = hmc(q0, gauss_log_target, step_size=0.5, num_leapfrog=2, num_steps=3,
                generator=torch.Generator().manual_seed(7))
    b, ib = hmc(q0, gauss_log_target, step_size=0.5, num_leapfrog=2, num_steps=3,
                generator=torch.Generator().manual_seed(7), grad_fn=gauss_grad)
    torch.testing.assert_close(a, b)
    torch.testing.assert_close(ia.acceptance, ib.acceptance)


def test_same_seed_same_result(gen):
    q0 = exact_draws((2, 30), gen)
    runs = [hmc(q0, gauss_log_target, step_size=0.5, num_leapfrog=2, num_steps=4,
                generator=torch.Generator().manual_seed(3)) for _ in range(2)]
    assert torch.equal(runs[0][0], runs[1][0])


def test_per_slot_chains_and_event_dims(gen):
    # chains (B, N, K) with 2-D events: log_target returns (B, N, K)
    q0 = exact_draws((2, 3, 4), gen)
    q, info = hmc(q0, gauss_log_target, step_size=0.5, num_leapfrog=1, num_steps=2, generator=gen)
    assert q.shape == (2, 3, 4, 2) and info.acceptance.shape == (2, 3, 4)
    # chains with scalar states: log_target returns q's own shape
    q, info = hmc(torch.zeros(5, 7, dtype=torch.float64), lambda x: -0.5 * x**2, step_size=0.5,
                  num_leapfrog=1, num_steps=2, generator=gen)
    assert info.acceptance.shape == (5, 7)


def test_divergent_trajectory_is_rejected(gen):
    # log_target is NaN away from |q| < 10: a huge step always leaves it, so nothing moves
    def lt(q):
        v = -0.5 * q.square().sum(-1)
        return torch.where(q.abs().max(-1).values < 10, v, torch.full_like(v, float("nan")))

    q0 = torch.zeros(3, 4, 2, dtype=torch.float64)
    q, info = hmc(q0, lt, step_size=100.0, num_leapfrog=1, num_steps=3, generator=gen)
    assert torch.equal(q, q0) and bool((info.acceptance == 0).all())


def quartic(q):
    return -(q**4).sum(-1) / 4 - 0.5 * (q**2).sum(-1)


def test_leapfrog_is_reversible(gen):
    q0 = torch.randn(100, 3, generator=gen, dtype=torch.float64)
    p0 = torch.randn(100, 3, generator=gen, dtype=torch.float64)
    _, g0 = value_and_grad(quartic, q0)
    q1, p1, _, g1 = leapfrog(q0, p0, g0, quartic, step_size=0.05, num_steps=20)
    q2, p2, _, _ = leapfrog(q1, -p1, g1, quartic, step_size=0.05, num_steps=20)
    torch.testing.assert_close(q2, q0, rtol=0, atol=1e-11)
    torch.testing.assert_close(p2, -p0, rtol=0, atol=1e-11)


def test_leapfrog_energy_error_is_second_order(gen):
    # Over a fixed integration time tau = 1 the leapfrog energy error is
    # h^2 c(q0, p0) + O(h^4); halving h divides the RMS error by 4 (1 + O(h^2)). With
    # h = 0.05 and this quartic the relative O(h^2) term is ~1e-2: ratio in [3.8, 4.2].
    q0 = torch.randn(200, 2, generator=gen, dtype=torch.float64)
    p0 = torch.randn(200, 2, generator=gen, dtype=torch.float64)
    v0, g0 = value_and_grad(quartic, q0)
    h0 = -v0 + 0.5 * p0.square().sum(-1)
    errs = []
    for h in (0.05, 0.025):
        q, p, v, _ = leapfrog(q0, p0, g0, quartic, step_size=h, num_steps=round(1 / h))
        errs.append(((-v + 0.5 * p.square().sum(-1)) - h0).square().mean().sqrt())
    ratio = (errs[0] / errs[1]).item()
    assert 3.8 < ratio < 4.2, ratio


@pytest.mark.parametrize(
    "kwargs, match",
    [
        (dict(step_size=0.0), "step_size"),
        (dict(step_size=torch.tensor([0.1, -0.1])), "step_size"),
        (dict(num_leapfrog=0), "num_leapfrog"),
        (dict(num_steps=0), "num_steps"),
        (dict(generator=None), "generator"),
    ],
)
def test_bad_settings_raise(kwargs, match, gen):
    base = dict(step_size=0.1, num_leapfrog=1, num_steps=1, generator=gen)
    base.update(kwargs)
    with pytest.raises(ValueError, match=match):
        hmc(torch.zeros(2, 2, dtype=torch.float64), gauss_log_target, **base)


def test_bad_inputs_raise(gen):
    with pytest.raises(ValueError, match="floating point"):
        hmc(torch.zeros(2, 2, dtype=torch.long), gauss_log_target, step_size=0.1, num_leapfrog=1,
            num_steps=1, generator=gen)
    with pytest.raises(ValueError, match="log_target returned shape"):
        hmc(torch.zeros(2, 2, dtype=torch.float64), lambda q: q.sum(-1).repeat(2), step_size=0.1, num_leapfrog=1,
            num_steps=1, generator=gen)
