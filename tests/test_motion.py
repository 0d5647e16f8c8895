import pytest
import torch

from torchmcmcpf.models import ConstantVelocity, LinearGaussianMotion


def test_constant_velocity_matrices_match_paper_000():
    # Bocquel et al. (2012) eqs. 16-17 with T = 2, a_x = a_y = 0.5, a_rho = 0.1.
    m = ConstantVelocity(dt=2.0, q=0.5, amplitude_q=0.1)
    F1 = torch.tensor([[1.0, 2.0], [0.0, 1.0]])
    G1 = torch.tensor([[8 / 3, 2.0], [2.0, 2.0]])
    assert torch.allclose(m.F, torch.block_diag(F1, F1, torch.ones(1, 1)))
    assert torch.allclose(m.Q, torch.block_diag(0.5 * G1, 0.5 * G1, torch.full((1, 1), 0.2)))
    assert m.dim == 5 and ConstantVelocity(1.0, 1.0).dim == 4


def test_sample_moments_match_F_and_Q(gen):
    # R draws from one starting point: the sample mean has standard error sqrt(diag Q / R)
    # and each sample covariance entry Q_ij has standard error sqrt((Q_ii Q_jj + Q_ij^2) / R).
    m = ConstantVelocity(dt=1.0, q=2.0, amplitude_q=0.5).double()
    R = 200_000
    x0 = torch.tensor([100.0, 3.0, -50.0, -1.0, 4.0], dtype=torch.float64)
    xs = m.sample(x0.expand(R, 1, 5), generator=gen)[:, 0]
    mean, cov = xs.mean(0), torch.cov(xs.T)
    Q = m.Q
    assert torch.all((mean - m.F @ x0).abs() <= 5 * torch.sqrt(torch.diagonal(Q) / R))
    se_cov = torch.sqrt((torch.outer(torch.diagonal(Q), torch.diagonal(Q)) + Q**2) / R)
    assert torch.all((cov - Q).abs() <= 5 * se_cov)


def test_log_prob_matches_torch_distributions(gen):
    m = ConstantVelocity(dt=0.5, q=1.5).double()
    x = torch.randn(3, 7, 2, 4, generator=gen, dtype=torch.float64)
    xn = m.sample(x, generator=gen)
    ref = torch.distributions.MultivariateNormal(x @ m.F.T, covariance_matrix=m.Q).log_prob(xn)
    lp = m.log_prob(xn, x)
    assert lp.shape == (3, 7, 2)
    assert torch.allclose(lp, ref)


def test_propagate_is_sample_with_given_noise():
    m = ConstantVelocity(1.0, 1.0)
    x = torch.randn(4, 3, 4, generator=torch.Generator().manual_seed(0))
    a = m.sample(x, generator=torch.Generator().manual_seed(3))
    eps = torch.randn(4, 3, 4, generator=torch.Generator().manual_seed(3))
    assert torch.equal(a, m.propagate(x, eps))


@pytest.mark.parametrize("kwargs, name", [({"dt": 0.0, "q": 1.0}, "dt"), ({"dt": 1.0, "q": -1.0}, "q"),
                                          ({"dt": 1.0, "q": 1.0, "amplitude_q": float("nan")}, "amplitude_q")])
def test_bad_parameters(kwargs, name):
    with pytest.raises(ValueError, match=name):
        ConstantVelocity(**kwargs)


def test_linear_gaussian_motion_rejects_bad_covariance():
    with pytest.raises(ValueError, match="Q"):
        LinearGaussianMotion(torch.eye(2), -torch.eye(2))
    with pytest.raises(ValueError, match="square"):
        LinearGaussianMotion(torch.eye(2), torch.eye(3))
