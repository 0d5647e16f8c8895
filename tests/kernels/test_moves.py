"""Every MCMC move leaves the exact posterior of a linear-Gaussian problem invariant.

Target: ``pi(x, a) ∝ N(z; H vec(x), R) w_a prod_k N(x_k; F x_{a,k}, Q)`` over a fixed cloud of
N = 20 weighted previous particles (K = 2 targets, D = 4), whose moments are exact
(``_kalman.mixture_posterior``). C = 1000 independent chains per run, B = 2 runs.

Tolerance (all tests): the final states of the C chains are independent, so the sample
mean of any statistic f has standard error ``se = std(f) / sqrt(C)``; we require ``|mean -
exact| <= 5 se`` for f = each component of x (mean), each product of two components'
deviations from the exact mean (covariance, the 36 pairs i <= j), each component of the
ancestor x_prev and the products ``(x_j - E x_j)(x_prev_j - E x_prev_j)`` (the dependence
between a state and its ancestor), each centred on its exact mean. A two-sided 5-sigma miss has
probability 5.7e-7, so the 2 x 60 comparisons of a test fail by chance with probability < 7e-5.

Burn-in bias. Tests that start away from pi bound it with the Doeblin minorisation of the
joint draw, an independence sampler with proposal ``w_a p(x | x_a)``: ``pi / q = p(z | x) /
p(z) <= max_x p(z | x) / p(z) = 1 / eps``, so one joint draw satisfies ``P(x, .) >= eps
pi(.)`` and a mixture that picks it with probability xi satisfies ``P >= xi eps pi``; if every
component is pi-invariant, ``P^m = (1 - (1 - xi eps)^m) pi + (1 - xi eps)^m R_m``, so the mean
is off by at most ``(1 - xi eps)^m`` times the distance between the start and the target
(a few posterior sds). We run m iterations with ``(1 - xi eps)^m <= 1e-4``: bias <= 0.001 sd,
against 5 se = 5 / sqrt(1000) = 0.16 sd. Each such test also checks that the start is more
than 10 se away from pi, so a move that does not move fails. Tests that start at pi exactly
(moves without a closed-form bound) check instead that the chains moved many times.
"""

import math

import pytest
import torch
from _kalman import mixture_posterior

from torchmcmcpf import ConstantVelocity, LinearGaussian
from torchmcmcpf.filters.mcmc import draw_iteration_noise, mcmc_iteration, pick_moves
from torchmcmcpf.kernels.chains import ChainState, JointNoise, RefineNoise, evaluate, previous_cloud
from torchmcmcpf.kernels.moves import init_chains, propose_joint, refine_move
from torchmcmcpf.kernels.random_walk import log_transition
from torchmcmcpf.models.base import MotionModel, SensorModel
from torchmcmcpf.models.existence import TargetDynamics
from torchmcmcpf.resampling import gather_particles, multinomial

DT = torch.float64
B, N, K, D, C = 2, 20, 2, 4, 1000
Z_TOL = 5.0  # tolerance in standard errors (see the module docstring)
TV_TARGET = 1e-4  # burn-in: (1 - xi eps)^m <= TV_TARGET


# -- models ----------------------------------------------------------------------------------
class CoupledPositions(SensorModel):
    """``z = A vec(p) + N(0, s^2 I)`` with ``p (K, 2)`` the positions: the targets interact
    (through the sum of the positions), so the likelihood is not a sum over targets."""

    def __init__(self, A: torch.Tensor, std: float):
        super().__init__()
        self.register_buffer("A", A)
        self.std = std
        self.frame_shape = (A.shape[0],)

    def log_likelihood(self, x, z, exists=None):
        r = self._residual(x, z)
        return -0.5 * (r / self.std).square().sum(-1) - r.shape[-1] * (math.log(self.std) + 0.5 * math.log(2 * math.pi))

    def _residual(self, x, z):
        pos = x[..., [0, 2]].flatten(-2)
        return z.reshape(z.shape[:1] + (1,) * (x.dim() - 3) + z.shape[1:]) - pos @ self.A.mT

    def observation(self):
        """(H (m, K*D), R (m, m)) on the stacked state."""
        sel = torch.zeros(2 * K, K * D, dtype=DT)
        for k in range(K):
            sel[2 * k, k * D] = sel[2 * k + 1, k * D + 2] = 1.0
        return self.A @ sel, self.std**2 * torch.eye(self.A.shape[0], dtype=DT)


class CoupledWithDelta(CoupledPositions):
    """The same sensor with the ``log_likelihood_delta`` hook: only slot n's columns of A."""

    def log_likelihood_delta(self, x, x_n, n, z, exists=None, exists_n=None):
        r = self._residual(x, z)
        shift = (x_n[..., [0, 2]] - x[..., n, [0, 2]]) @ self.A[:, 2 * n:2 * n + 2].mT
        return -0.5 * ((r - shift).square().sum(-1) - r.square().sum(-1)) / self.std**2


class Opaque(SensorModel):
    """Hides every hook of ``inner``: only ``log_likelihood`` (the generic fallback)."""

    def __init__(self, inner):
        super().__init__()
        self.inner = inner

    def log_likelihood(self, x, z, exists=None):
        return self.inner.log_likelihood(x, z, exists)


class PerTargetAsDelta(Opaque):
    """``log_likelihood_delta`` computed from per-target terms (the sequential hook path)."""

    def log_likelihood_delta(self, x, x_n, n, z, exists=None, exists_n=None):
        new = self.inner.log_likelihood_per_target(x_n.unsqueeze(-2), z[:, n:n + 1]).squeeze(-1)
        return new - self.inner.log_likelihood_per_target(x, z)[..., n]


class GenericMotion(MotionModel):
    """A motion model that is not a LinearGaussianMotion: forces the generic code paths."""

    def __init__(self, inner):
        super().__init__()
        self.inner, self.dim, self.noise_dim = inner, inner.dim, inner.noise_dim

    def propagate(self, x, eps):
        return self.inner.propagate(x, eps)

    def log_prob(self, x_next, x):
        return self.inner.log_prob(x_next, x)


def _coupled(cls=CoupledPositions, std=2.0, sum_only=False):
    """Observe the sum of the positions (and, unless ``sum_only``, the position of target
    1): ``A'A`` is not block diagonal. A has full row rank, so every z is reachable."""
    A = torch.tensor([[1.0, 0, 1, 0], [0, 1, 0, 1], [1, 0, 0, 0], [0, 1, 0, 0]], dtype=DT)
    return cls(A[:2] if sum_only else A, std)


def _problem(sensor, gen, q=0.5):
    """Motion (process noise level q), previous weighted cloud ``(B, N, K, D)``, frame z and
    the exact posterior."""
    motion = ConstantVelocity(1.0, q).to(DT)
    centre = torch.tensor([[0.0, 1.0, 0.0, 1.0], [6.0, -1.0, 3.0, 0.0]], dtype=DT)
    spread = torch.tensor([1.0, 0.5, 1.0, 0.5], dtype=DT)
    prev = centre + spread * torch.randn(B, N, K, D, generator=gen, dtype=DT)
    log_w = torch.log_softmax(0.5 * torch.randn(B, N, generator=gen, dtype=DT), -1)
    truth = motion.sample(centre + spread * torch.randn(B, K, D, generator=gen, dtype=DT), generator=gen)
    # The posterior is exact for any z; a noise-free frame keeps the burn-in bound short.
    if isinstance(sensor, LinearGaussian):
        H, R = torch.block_diag(*[sensor.H] * K), torch.block_diag(*[sensor.R] * K)
        z = truth @ sensor.H.mT  # (B, K, 2)
        post = mixture_posterior(prev, log_w, motion.F, motion.Q, H, R, z.reshape(B, -1))
    else:
        H, R = sensor.observation()
        z = truth.reshape(B, K * D) @ H.mT  # (B, m)
        post = mixture_posterior(prev, log_w, motion.F, motion.Q, H, R, z)
    return motion, previous_cloud(prev, log_w), z, post


def _iterations(bound) -> int:
    """Smallest m with ``bound(m) <= TV_TARGET`` (bound decreasing in m)."""
    m = 1
    while bound(m) > TV_TARGET:
        m += 1
    assert m < 2000, "test problem too hard for the burn-in bound"
    return m


def _joint_eps(post) -> float:
    """Doeblin constant of the joint draw, ``min_b p(z) / max_x p(z | x)``."""
    return float(torch.exp(post.log_evidence - post.log_lik_max).min())


# -- checks ----------------------------------------------------------------------------------
def _discrepancies(chain: ChainState, post, cloud) -> dict:
    """Largest |estimate - exact| / se over the components of each statistic."""
    xs = chain.x.flatten(2)  # (B, C, K*D), C independent chains
    root_c = math.sqrt(xs.shape[1])
    dev = xs - post.mean.unsqueeze(1)
    i, j = torch.triu_indices(dev.shape[-1], dev.shape[-1])
    dev2 = dev[..., i] * dev[..., j]  # E[dev2] = Cov(x)_ij exactly (centred on the exact mean)
    ps = chain.x_prev.flatten(2)
    prev_mean = torch.einsum("bn,bnj->bj", post.ancestor_log_w.exp(), cloud.x.flatten(2))
    # Cov(x_j, x_prev_j) = sum_a p(a | z) (m_{a,j} - E x_j)(x_{a,j} - E x_prev_j): the
    # dependence between a state and its ancestor
    w = post.ancestor_log_w.exp()
    cross = torch.einsum("bn,bnj->bj", w, (post.component_means - post.mean.unsqueeze(1))
                         * (cloud.x.flatten(2) - prev_mean.unsqueeze(1)))
    stats = {
        "mean of x": (xs, post.mean),
        "covariance of x": (dev2, post.cov[:, i, j]),
        "mean of the ancestor": (ps, prev_mean),
        "covariance of x and its ancestor": (
            (xs - post.mean.unsqueeze(1)) * (ps - prev_mean.unsqueeze(1)), cross),
    }
    return {k: float(((f.mean(1) - exact).abs() / (f.std(1) / root_c)).max()) for k, (f, exact) in stats.items()}


def _assert_pi(chain: ChainState, post, cloud):
    worst = _discrepancies(chain, post, cloud)
    assert max(worst.values()) <= Z_TOL, f"standard errors off (tolerance {Z_TOL}): {worst}"
    # x_prev is always one of the previous particles
    ps = chain.x_prev.flatten(2)
    assert (ps.unsqueeze(2) == cloud.x.flatten(2).unsqueeze(1)).all(-1).any(-1).all()


def _assert_far(chain: ChainState, post, cloud):
    """The start is > 10 se from pi in some statistic: a move that does not move would fail."""
    assert max(_discrepancies(chain, post, cloud).values()) > 10


def _run(chain, moves, iters, *, cloud, z, motion, sensor, gen, rw_scale=None):
    accepted = {name: torch.zeros(B, dtype=DT) for name, _ in moves}
    for move in pick_moves(moves, iters, generator=gen):
        noise = draw_iteration_noise(move, chain.x, TargetDynamics(motion), generator=gen)
        chain, acc = mcmc_iteration(chain, noise, move=move, cloud=cloud, z=z, dynamics=TargetDynamics(motion),
                                    sensor=sensor, rw_scale=rw_scale)
        accepted[move] += acc.mean(1)
    return chain, accepted  # accepted: expected number of accepted moves per chain


def _exact_chains(post, cloud, z, sensor, gen):
    """C independent exact draws of pi: a ~ p(a | z), then x | a ~ N(m_a, P)."""
    a = multinomial(post.ancestor_log_w, torch.rand(B, C, generator=gen, dtype=DT))
    noise = torch.randn(B, C, K * D, generator=gen, dtype=DT) @ torch.linalg.cholesky(post.component_cov).mT
    x = (gather_particles(post.component_means, a) + noise).reshape(B, C, K, D)
    return ChainState(x, gather_particles(cloud.x, a), *evaluate(x, z, sensor))


def _prior_chains(cloud, z, motion, sensor, gen):
    template = cloud.x.new_empty(B, C, K, D)
    dynamics = TargetDynamics(motion)
    return init_chains(cloud, JointNoise.draw(template, dynamics, generator=gen), z, dynamics=dynamics, sensor=sensor)


# -- tests -----------------------------------------------------------------------------------
def test_joint_draw_converges_to_the_posterior(gen):
    sensor = LinearGaussian.position(2.0).to(DT)
    motion, cloud, z, post = _problem(sensor, gen)
    eps = _joint_eps(post)
    iters = _iterations(lambda m: (1 - eps) ** m)
    chain = _prior_chains(cloud, z, motion, sensor, gen)
    _assert_far(chain, post, cloud)
    chain, acc = _run(chain, (("joint", 1.0),), iters, cloud=cloud, z=z, motion=motion, sensor=sensor, gen=gen)
    _assert_pi(chain, post, cloud)


def test_refine_keeps_the_posterior(gen):
    """Separable sensor (vectorised sweep). Start at pi exactly, 40 sweeps. Refine never
    moves the ancestor, so it cannot converge from an arbitrary start on its own (the
    mixture test covers convergence); a wrong conditional target would drift away from pi
    within the > 10 accepted updates per target that the chains must make."""
    sensor = LinearGaussian.position(1.0).to(DT)
    motion, cloud, z, post = _problem(sensor, gen, q=3.0)  # given a, only Q spreads x: make it matter
    chain = _exact_chains(post, cloud, z, sensor, gen)
    chain, acc = _run(chain, (("refine", 1.0),), 40, cloud=cloud, z=z, motion=motion, sensor=sensor, gen=gen)
    assert (acc["refine"] > 10).all()
    assert chain.log_lik_terms is not None
    torch.testing.assert_close(chain.log_lik, sensor.log_likelihood(chain.x, z))
    _assert_pi(chain, post, cloud)


@pytest.mark.parametrize("cls", [CoupledPositions, CoupledWithDelta], ids=["full-recompute", "delta-hook"])
def test_refine_sequential_sweep_keeps_the_coupled_posterior(cls, gen):
    """Coupled sensor: the sweep must be sequential. Start at pi exactly, 60 sweeps; a
    parallel (Jacobi) update or a wrong conditional would drift away from pi. The chains must
    have accepted > 10 target updates each on average, so that doing nothing fails."""
    sensor = _coupled(cls, std=0.5, sum_only=True).to(DT)  # x_1 + x_2 pinned: strongly coupled
    motion, cloud, z, post = _problem(sensor, gen, q=3.0)
    chain = _exact_chains(post, cloud, z, sensor, gen)
    chain, acc = _run(chain, (("refine", 1.0),), 60, cloud=cloud, z=z, motion=motion, sensor=sensor, gen=gen)
    assert (acc["refine"] > 10).all()
    torch.testing.assert_close(chain.log_lik, sensor.log_likelihood(chain.x, z))
    _assert_pi(chain, post, cloud)


def test_random_walk_keeps_the_posterior(gen):
    """Start at pi exactly, 60 random-walk moves with the Gibbs redraw of the ancestor."""
    sensor = LinearGaussian.position(1.0).to(DT)
    # wide components (large Q) let the walk move between ancestors: the redraw matters
    motion, cloud, z, post = _problem(sensor, gen, q=3.0)
    chain = _exact_chains(post, cloud, z, sensor, gen)
    scale = torch.tensor([0.3, 0.5, 0.3, 0.5], dtype=DT)
    chain, acc = _run(chain, (("random_walk", 1.0),), 60, cloud=cloud, z=z, motion=motion, sensor=sensor,
                      gen=gen, rw_scale=scale)
    assert (acc["random_walk"] > 10).all()
    _assert_pi(chain, post, cloud)


def test_mixture_of_all_moves_converges_on_a_coupled_sensor(gen):
    """Joint draw (xi = 0.4), sequential refinement and random walk per chain, from the
    prior: the Doeblin bound with xi eps holds only if refine and random walk are
    pi-invariant too, so a wrong one fails the moments."""
    sensor = _coupled().to(DT)
    motion, cloud, z, post = _problem(sensor, gen)
    xi = 0.4
    eps = _joint_eps(post)
    iters = _iterations(lambda m: (1 - xi * eps) ** m)
    chain = _prior_chains(cloud, z, motion, sensor, gen)
    _assert_far(chain, post, cloud)
    moves = (("joint", xi), ("refine", 0.3), ("random_walk", 0.3))
    chain, acc = _run(chain, moves, iters, cloud=cloud, z=z, motion=motion, sensor=sensor, gen=gen,
                      rw_scale=torch.tensor(0.3, dtype=DT))
    _assert_pi(chain, post, cloud)


def test_refine_vectorised_and_sequential_paths_agree(gen):
    """Given the same noise, the vectorised sweep of a separable sensor, the sequential sweep
    with full re-evaluation and the sequential sweep with a delta hook accept the same
    updates (the conditional of slot n does not depend on the other slots)."""
    inner = LinearGaussian.position(1.0).to(DT)
    motion, cloud, z, _ = _problem(inner, gen, q=3.0)
    results = []
    for sensor in (inner, Opaque(inner), PerTargetAsDelta(inner)):
        g = torch.Generator().manual_seed(7)
        chain = _prior_chains(cloud, z, motion, sensor, g)
        chain, accepted = refine_move(chain, RefineNoise.draw(chain.x, TargetDynamics(motion), generator=g), z=z,
                                      dynamics=TargetDynamics(motion), sensor=sensor)
        results.append((chain, accepted))
    (ref, acc_ref), others = results[0], results[1:]
    assert acc_ref.any() and not acc_ref.all()  # a mix of accepts and rejects
    for chain, acc in others:
        assert torch.equal(acc, acc_ref)
        assert torch.equal(chain.x, ref.x) and torch.equal(chain.x_prev, ref.x_prev)
        torch.testing.assert_close(chain.log_lik, ref.log_lik)


class Recording(CoupledPositions):
    """Records every state the sweep scores (full re-evaluation path)."""

    def log_likelihood(self, x, z, exists=None):
        self.calls.append(x.clone())
        return super().log_likelihood(x, z, exists)


def test_sequential_sweep_scores_slot_n_against_the_updated_slots(gen):
    """Gibbs, not Jacobi: the candidate of slot 1 carries the already updated slot 0. (The
    moment tests have little power against a parallel update on Gaussian targets.)"""
    sensor = Recording(_coupled().A, 0.5).to(DT)
    sensor.calls = []
    motion, cloud, z, _ = _problem(sensor, gen, q=3.0)
    chain = _prior_chains(cloud, z, motion, sensor, gen)
    sensor.calls = []
    new, accepted = refine_move(chain, RefineNoise.draw(chain.x, TargetDynamics(motion), generator=gen), z=z,
                                dynamics=TargetDynamics(motion), sensor=sensor)
    assert len(sensor.calls) == K and accepted[..., 0].any() and not accepted[..., 0].all()
    assert torch.equal(sensor.calls[1][..., 0, :], new.x[..., 0, :])
    assert torch.equal(sensor.calls[0][..., 1, :], chain.x[..., 1, :])


def test_log_transition_fast_path_matches_generic(gen):
    motion = ConstantVelocity(1.0, 0.5).to(DT)
    x = torch.randn(B, 3, K, D, generator=gen, dtype=DT)
    prev = torch.randn(B, 5, K, D, generator=gen, dtype=DT)
    fast = log_transition(x, prev, motion=motion)
    generic = log_transition(x, prev, motion=GenericMotion(motion))
    cloud = previous_cloud(prev, torch.zeros(B, 5, dtype=DT), motion=motion)  # caches L^-1 F x^i
    assert torch.equal(log_transition(x, prev, motion=motion, white_prev=cloud.white_mean), fast)
    assert previous_cloud(prev, torch.zeros(B, 5, dtype=DT), motion=GenericMotion(motion)).white_mean is None
    assert fast.shape == (B, 3, 5)
    # the generic path's constant comes from motion._log_norm, computed at float32 before .to()
    torch.testing.assert_close(fast, generic, rtol=0, atol=1e-6)
    direct = motion.log_prob(x[:, 1], prev[:, 4]).sum(-1)
    torch.testing.assert_close(fast[:, 1, 4], direct, rtol=0, atol=1e-6)


def test_joint_proposal_shapes_and_ratio(gen):
    motion, cloud, z, _ = _problem(LinearGaussian.position(2.0).to(DT), gen)
    noise = JointNoise.draw(cloud.x.new_empty(B, 7, K, D), TargetDynamics(motion), generator=gen)
    x, x_prev, log_ratio = propose_joint(cloud, noise, motion=motion)
    assert x.shape == x_prev.shape == (B, 7, K, D)
    assert torch.equal(log_ratio, torch.zeros(B, 7, dtype=DT))
    torch.testing.assert_close(x, motion.propagate(x_prev, noise.eps))



def test_previous_cloud_guide_draws_the_ancestors_searchsorted_draws(gen):
    """A cloud that many ancestor draws read (``draws >= GUIDED_POINTS``) carries a guide
    table, and its draws are the indices ``searchsorted`` gives; a cloud of few draws has none."""
    from torchmcmcpf.kernels.chains import draw_ancestors
    from torchmcmcpf.resampling import GUIDED_POINTS, cdf

    log_w = torch.randn(3, 700, generator=gen, dtype=torch.float64)
    x = torch.zeros(3, 700, 2, 4)
    guided = previous_cloud(x, log_w, draws=GUIDED_POINTS)
    assert guided.guide is not None and previous_cloud(x, log_w, draws=GUIDED_POINTS - 1).guide is None
    u = torch.rand(3, 400, generator=gen)
    want = torch.searchsorted(cdf(log_w), u.double(), right=True).clamp_(max=699)
    assert torch.equal(draw_ancestors(guided, u), want)


def test_normals_drawn_where_flagged_only(gen):
    """``normals(..., where=)`` draws the flagged rows in order, zeros elsewhere: the flagged
    rows are the next draws of the generator (so standard normal), and a wrong-shaped flag
    tensor is refused by name."""
    from torchmcmcpf.kernels.chains import normals

    like = torch.zeros((), dtype=DT)
    flags = torch.rand(4, 300, 5, generator=gen) < 0.4
    g = torch.Generator().manual_seed(11)
    eps = normals((4, 300, 5, 3), like, g, flags)
    assert eps.shape == (4, 300, 5, 3) and eps.dtype == DT
    assert torch.equal(eps[~flags], torch.zeros(int((~flags).sum()), 3, dtype=DT))
    expected = torch.randn(int(flags.sum()), 3, generator=torch.Generator().manual_seed(11), dtype=DT)
    assert torch.equal(eps[flags], expected)
    n = expected.numel()  # about 7,200 numbers: mean within 4 se, variance within 4 se of 1
    assert abs(float(expected.mean())) < 4 / math.sqrt(n) and abs(float(expected.var()) - 1) < 4 * math.sqrt(2 / n)
    with pytest.raises(ValueError, match="where has shape"):
        normals((4, 300, 5, 3), like, g, flags[:, :10])


# -- existence: births and deaths --------------------------------------------------------------
# Exact target (module "Existence" docstring of torchmcmcpf.kernels.moves) on a problem small
# enough to enumerate: K = 2 slots, N0 = 4 distinct previous particles (every existence
# pattern), one point z per run in Poisson clutter. The likelihood of one point,
#   p(z | x, e) = exp(-(L_C + L_x |e|)) (L_C / V + L_x sum_n e_n N(z; H x_n, R)),
# is linear in each N(z; H x_n, R), and given (a, e) the slots are independent under the
# prior, so every expectation below is a closed form:
#   E[N(z; H x_n, R) | a, e_n = 1] = g_n(a) = N(z; H F x^a_n, H Q H' + R)   (survivor)
#                                            = P_box(z) / V                  (newborn, p_0)
#   W(a, e) = w_a p(e | e^a) exp(-(L_C + L_x |e|)) (L_C / V + L_x sum_{n: e_n} g_n(a))
# and E[e_n pos_n | a, e] W(a, e) / (...) uses the prior mean m_n and the posterior mean mu_n
# of pos_n given the point (Kalman for a survivor, truncated normal for a newborn).
EX_AREA = ((0.0, 100.0), (0.0, 100.0))
EX_C = 1000  # independent chains per run
EX_STATS = ("P(e_0)", "P(e_1)", "P(e_0 e_1)", "E[e_0 x_0]", "E[e_0 y_0]", "E[e_1 x_1]", "E[e_1 y_1]",
            "P(e^a_0)")


def _existence_problem(birth_std):
    from torchmcmcpf.models.existence import BirthDeath
    from torchmcmcpf.models.sensors.points import PointFrame, PoissonClutterPoints

    motion = ConstantVelocity(1.0, 3.0).to(DT)
    # dense clutter and a wide point spread keep the Doeblin constant of the joint draw large
    sensor = PoissonClutterPoints(10.0, 2.0, EX_AREA, noise_std=4.0).to(DT)
    existence = BirthDeath(0.3, 0.2, EX_AREA, velocity_std=1.0, birth_std=birth_std, p_uniform=0.5).to(DT)
    flags = torch.tensor([[1, 1], [1, 0], [0, 1], [0, 0]], dtype=torch.bool)
    live = torch.tensor([[40.0, 1.0, 50.0, 0.0], [60.0, 0.0, 52.0, -1.0]], dtype=DT)  # slot 0, slot 1
    x0 = torch.where(flags.unsqueeze(-1), live, existence.x_death)  # (4, K, D)
    x0 = x0.expand(B, 4, K, D)
    log_w0 = torch.log_softmax(torch.tensor([[0.3, -0.2, 0.1, 0.0], [0.0, 0.5, -0.3, 0.2]], dtype=DT), -1)
    # run 0: a point next to slot 0's prediction (41, 50); run 1: a point far from both
    pts = torch.tensor([[[43.0, 50.5]], [[80.0, 20.0]]], dtype=DT)
    z = PointFrame(pts, torch.ones(B, 1, dtype=torch.bool))
    # the cloud: each distinct particle repeated N / 4 times (N = C: one kept state per chain)
    rep = EX_C // 4
    x = x0.repeat_interleave(rep, 1)
    log_w = log_w0.repeat_interleave(rep, 1) - math.log(rep)
    cloud = previous_cloud(x, log_w, flags.expand(B, 4, K).repeat_interleave(rep, 1))
    exact, evidence = _existence_exact(x0, log_w0, flags, pts[:, 0], motion, sensor, existence)
    return motion, sensor, existence, cloud, z, exact, evidence


def _existence_exact(x0, log_w0, flags, z, motion, sensor, existence):
    """Exact expectations of EX_STATS under pi ``(B, len(EX_STATS))`` and the evidence
    ``p(z) = sum_{a, e} W(a, e)`` (B,)."""
    normal = torch.distributions.Normal(torch.tensor(0.0, dtype=DT), torch.tensor(1.0, dtype=DT))
    L_C, L_x, V = sensor.clutter_rate, sensor.detection_rate, sensor.volume
    s2 = float(sensor.R[0, 0])
    idx = [0, 2]  # x, y
    q = torch.diagonal(motion.Q)[idx]  # position variances of the transition (independent x and y)
    m_surv = motion.mean(x0)[..., idx]  # (B, 4, K, 2)
    zb = z[:, None, None, :]  # (B, 1, 1, 2)
    S = q + s2
    g_surv = (torch.exp(-0.5 * (zb - m_surv).square() / S) / torch.sqrt(2 * math.pi * S)).prod(-1)
    mu_surv = m_surv + q / S * (zb - m_surv)
    lo, hi = existence.area[:, 0], existence.area[:, 1]
    s = math.sqrt(s2)
    al, be = (lo - z) / s, (hi - z) / s  # (B, 2)
    mass = normal.cdf(be) - normal.cdf(al)
    g_born = mass.prod(-1) / V  # (B,)
    mu_born = z + s * (normal.log_prob(al).exp() - normal.log_prob(be).exp()) / mass
    alive_a = flags.unsqueeze(0)  # (1, 4, K)
    g = torch.where(alive_a, g_surv, g_born[:, None, None])  # (B, 4, K)
    m = torch.where(alive_a.unsqueeze(-1), m_surv, ((lo + hi) / 2).expand_as(m_surv))
    mu = torch.where(alive_a.unsqueeze(-1), mu_surv, mu_born[:, None, None, :])
    combos = torch.tensor([[0, 0], [0, 1], [1, 0], [1, 1]], dtype=torch.bool)  # (E, K)
    log_pe = existence.log_prob_exists(combos[None, None], alive_a[:, :, None]).sum(-1)  # (1, 4, E)
    e = combos.to(DT)[None, None]  # (1, 1, E, K)
    ge = e * g[:, :, None, :]  # (B, 4, E, K)
    base = math.exp(-L_C) * torch.exp(-L_x * e.sum(-1))  # (1, 1, E)
    lin = L_C / V + L_x * ge.sum(-1)  # (B, 4, E)
    W = log_w0.exp()[:, :, None] * log_pe.exp() * base * lin  # (B, 4, E)
    # E[e_n pos_n (...)]: m_n (L_C/V + L_x sum_{j != n} e_j g_j) + L_x g_n mu_n, for e_n = 1
    other = lin.unsqueeze(-1) - L_x * ge  # (B, 4, E, K)
    pos = e.unsqueeze(-1) * (m[:, :, None] * other.unsqueeze(-1) + L_x * ge.unsqueeze(-1) * mu[:, :, None])
    pos = pos * (log_w0.exp()[:, :, None] * log_pe.exp() * base)[..., None, None]  # (B, 4, E, K, 2)
    Z = W.sum((1, 2))
    e_prev0 = alive_a[..., 0].to(DT).expand(W.shape[:2])  # (B, 4)
    stats = torch.stack([
        (W * e[..., 0]).sum((1, 2)) / Z,
        (W * e[..., 1]).sum((1, 2)) / Z,
        (W * e[..., 0] * e[..., 1]).sum((1, 2)) / Z,
        pos[..., 0, 0].sum((1, 2)) / Z, pos[..., 0, 1].sum((1, 2)) / Z,
        pos[..., 1, 0].sum((1, 2)) / Z, pos[..., 1, 1].sum((1, 2)) / Z,
        (W.sum(-1) * e_prev0).sum(1) / Z,
    ], -1)
    return stats, Z


def _existence_samples(chain: ChainState) -> torch.Tensor:
    """The statistics EX_STATS of each chain, (B, C, len(EX_STATS))."""
    e = chain.exists.to(DT)
    ex = e.unsqueeze(-1) * chain.x[..., [0, 2]]  # (B, C, K, 2)
    return torch.stack([e[..., 0], e[..., 1], e[..., 0] * e[..., 1], ex[..., 0, 0], ex[..., 0, 1],
                        ex[..., 1, 0], ex[..., 1, 1], chain.exists_prev[..., 0].to(DT)], -1)


def _existence_discrepancy(chain: ChainState, exact) -> torch.Tensor:
    """|mean - exact| / se per run and statistic (C independent chains)."""
    f = _existence_samples(chain)
    se = f.std(1) / math.sqrt(f.shape[1])
    return (f.mean(1) - exact).abs() / se


@pytest.mark.parametrize("xi, birth_std, narrowed", [(1.0, None, False), (1.0, 6.0, False), (0.5, 6.0, False),
                                                     (0.5, 6.0, True)],
                         ids=["joint-prior-births", "joint-births-near-points", "mixture-births-near-points",
                              "mixture-births-where-ancestors-inactive"])
def test_existence_moves_converge_to_the_exact_posterior(xi, birth_std, narrowed, gen):
    """Joint draw alone, and a mixture dominated by the per-slot refinement, from the prior.

    Burn-in bound: the joint draw is an independence sampler with proposal ``q`` and ``pi /
    q = p(z | x, e) prod_n r_n / p(z)`` (module docstring of the moves), bounded by ``1 /
    eps``: with n live slots, ``p(z | x, e) <= exp(-(L_C + n L_x)) (L_C / V + n L_x N(0; 0,
    R))`` (all of them on the point) and at most n newborns, each with ``r = p_0 / q_0 <= 1 /
    P_I`` (uniform weight ``P_I`` of q_0), so ``eps = p(z) / max_n [bound_n / P_I^n]`` (no
    ``P_I`` factor for prior births), ``p(z)`` the exact normaliser of ``W``. As in the
    Gaussian tests, ``(1 - xi eps)^m <= 1e-4`` (bias <= 1e-4 times the range of each
    statistic, against 5 se). The mixture converges to pi only if the refinement (half the
    iterations) is pi-invariant too: e.g. dropping ``r_n`` from its ratio inflates births
    near the point.
    """
    motion, sensor, existence, cloud, z, exact, evidence = _existence_problem(birth_std)
    L_C, L_x, V = sensor.clutter_rate, sensor.detection_rate, sensor.volume
    r_max = 1.0 if birth_std is None else 1 / existence.p_uniform
    peak = 1 / (2 * math.pi * float(sensor.R[0, 0]))  # N(0; 0, R)
    bound = max(math.exp(-(L_C + n * L_x)) * (L_C / V + n * L_x * peak) * r_max**n for n in range(K + 1))
    eps = float(evidence.min()) / bound
    iters = _iterations(lambda m: (1 - xi * eps) ** m)
    moves = (("joint", 1.0),) if xi == 1.0 else (("joint", xi), ("refine", 1 - xi))
    template = cloud.x.new_empty(B, EX_C, K, D)
    dynamics = TargetDynamics(motion, existence)
    # narrowed: the candidates drawn only where the ancestor's slot is inactive, as the filter draws them
    known = {"cloud": cloud} if narrowed else {}
    chain = init_chains(cloud, JointNoise.draw(template, dynamics, generator=gen, z=z, **known), z,
                        dynamics=dynamics, sensor=sensor)
    assert float(_existence_discrepancy(chain, exact).max()) > 10  # the start is far from pi
    for move in pick_moves(moves, iters, generator=gen):
        noise = draw_iteration_noise(move, chain.x, dynamics, generator=gen, z=z,
                                     **(dict(known, exists_prev=chain.exists_prev) if narrowed else {}))
        chain, _ = mcmc_iteration(chain, noise, move=move, cloud=cloud, z=z, dynamics=dynamics, sensor=sensor)
    worst = _existence_discrepancy(chain, exact)
    assert float(worst.max()) <= Z_TOL, dict(zip(EX_STATS, worst.max(0).values.tolist()))
    # the cache is the likelihood of the flags and states; dead slots hold x_death
    torch.testing.assert_close(chain.log_lik, sensor.log_likelihood(chain.x, z, chain.exists))
    assert torch.equal(chain.x[~chain.exists], existence.x_death.expand(int((~chain.exists).sum()), D))



def test_existence_refine_uses_the_delta_hook_with_flags(gen):
    """A grid sensor's ``log_likelihood_delta`` (which takes ``exists``/``exists_n``) gives
    the same sweep as full evaluations of ``log p(z | x, e)``: same accept/reject decisions
    and cached log-likelihoods equal to round-off."""
    from torchmcmcpf.models.existence import BirthDeath
    from torchmcmcpf.models.sensors.radar import RangeDopplerBearingTBD

    radar = RangeDopplerBearingTBD.uniform((2300, 3300), (-20, 20), (-15 * math.pi / 180, 15 * math.pi / 180)).to(DT)
    motion = ConstantVelocity(1.0, 2.0, amplitude_q=0.01).to(DT)
    # x_death inside the grid: the delta hook computes the cell coordinates of dead slots too
    existence = BirthDeath(0.3, 0.3, ((2300.0, 3200.0), (-800.0, 800.0)), velocity_std=5.0, dim=5,
                           x_death=torch.tensor([2800.0, 0, 0, 0, 3.0])).to(DT)
    truth = torch.tensor([[[2800.0, -5.0, 100.0, 3.0, 3.0], [2600.0, 4.0, -200.0, 0.0, 3.0]]], dtype=DT)
    z = radar.simulate(truth, generator=gen)
    c = 64
    flags = torch.tensor([[True, False], [True, True], [False, True], [False, False]]).repeat(16, 1)  # (c, K)
    prev = truth.expand(1, c, 2, 5) + torch.randn(1, c, 2, 5, generator=gen, dtype=DT) * torch.tensor(
        [10.0, 1.0, 10.0, 1.0, 0.1], dtype=DT)
    prev = torch.where(flags.unsqueeze(-1), prev, existence.x_death)
    cloud = previous_cloud(prev, torch.full((1, c), -math.log(c), dtype=DT), flags.unsqueeze(0))
    results = []
    for sensor in (radar, Opaque(radar)):
        g = torch.Generator().manual_seed(5)
        template = prev.new_empty(1, c, 2, 5)
        dynamics = TargetDynamics(motion, existence)
        chain = init_chains(cloud, JointNoise.draw(template, dynamics, generator=g, z=z), z, dynamics=dynamics,
                            sensor=sensor)
        noise = RefineNoise.draw(chain.x, dynamics, generator=g, z=z)
        results.append(refine_move(chain, noise, z=z, dynamics=dynamics, sensor=sensor))
    (ref, acc_ref), (full, acc_full) = results
    assert acc_ref.any() and not acc_ref.all()
    assert torch.equal(acc_ref, acc_full) and torch.equal(ref.exists, full.exists)
    torch.testing.assert_close(ref.log_lik, full.log_lik)
    torch.testing.assert_close(ref.log_lik, radar.log_likelihood(ref.x, z, ref.exists))


def test_adapted_random_walk_keeps_the_posterior(gen):
    """The adaptive random walk's frozen kernel (a full per-target covariance fitted to the
    chains' history, :func:`adapted_step`) is a symmetric random walk, so it must leave pi
    invariant: adapt on a burn-in run from the prior, freeze, then start at pi exactly and
    make 100 moves with the Gibbs redraw of the ancestor (the acceptance on this mixture
    target is about 0.15, so that each chain accepts > 10 moves)."""
    from torchmcmcpf.kernels.random_walk import (
        RunningMoments,
        adapted_step,
        prior_covariance,
    )

    sensor = LinearGaussian.position(1.0).to(DT)
    motion, cloud, z, post = _problem(sensor, gen, q=3.0)
    prior = prior_covariance(cloud, motion)
    assert prior.shape == (B, K, D, D)
    scale = adapted_step(prior, DT)
    assert scale.shape == (B, 1, K, D, D)
    chain, moments = _prior_chains(cloud, z, motion, sensor, gen), RunningMoments.zeros(cloud.x[:, :C])
    for _ in range(40):  # burn-in with adaptation
        chain, _ = _run(chain, (("random_walk", 1.0),), 1, cloud=cloud, z=z, motion=motion, sensor=sensor, gen=gen,
                        rw_scale=scale)
        moments = moments.update(chain.x)
        scale = adapted_step(moments.covariance(prior, D + 1.0), DT)
    chain = _exact_chains(post, cloud, z, sensor, gen)
    chain, acc = _run(chain, (("random_walk", 1.0),), 100, cloud=cloud, z=z, motion=motion, sensor=sensor,
                      gen=gen, rw_scale=scale)
    assert (acc["random_walk"] > 10).all()
    _assert_pi(chain, post, cloud)


def _kept_and_stripped(field, seed, joint, check, exclusion=None):
    """Two runs of 30 mixture iterations (joint draw with probability ``joint``, else a sweep)
    from one seed on the births/deaths problem of :func:`_existence_problem`: the first keeps
    the chain state's cache ``field``, the second drops it before every move. ``check(old,
    new, move, sensor, z, before)`` sees every iteration of the first run (``before``: a copy
    of the old chain's ``field`` when a tensor) and returns 1 where it checked the cache;
    returns the two final chains and the count of checks.
    """
    motion, sensor, existence, cloud, z, _, _ = _existence_problem(3.0)
    dynamics = TargetDynamics(motion, existence)
    template = cloud.x.new_empty(B, EX_C, K, D)
    runs, checked = [], 0
    for strip in (False, True):
        g = torch.Generator().manual_seed(seed)
        chain = init_chains(cloud, JointNoise.draw(template, dynamics, generator=g, z=z), z, dynamics=dynamics,
                            sensor=sensor)
        for move in pick_moves((("joint", joint), ("refine", 1 - joint)), 30, generator=g):
            if strip:
                chain = chain._replace(**{field: None})
            noise = draw_iteration_noise(move, chain.x, dynamics, generator=g, z=z)
            before = getattr(chain, field)
            before = before.clone() if torch.is_tensor(before) else None
            new, _ = mcmc_iteration(chain, noise, move=move, cloud=cloud, z=z, dynamics=dynamics, sensor=sensor,
                                    exclusion=exclusion)
            checked += 0 if strip else check(chain, new, move, sensor, z, before)
            chain = new
        runs.append(chain)
    return runs, checked


def test_joint_draw_cache_of_the_exclusion_keeps_the_bits(gen):
    """The exclusion factor an eager joint draw keeps beside the chain (``ChainState.log_phi``)
    equals ``log Phi`` of the chain's state, is not read once another move replaced the state,
    and leaves every decision as recomputing it would (the same bits, births and deaths on)."""
    from torchmcmcpf.models.multitarget import Exclusion, log_exclusion

    exclusion = Exclusion()

    def check(old, new, move, sensor, z, before):
        if new.log_phi is None or new.log_phi[0] is not new.x:
            return 0
        assert torch.equal(new.log_phi[2], log_exclusion(exclusion, sensor, new.x, new.exists))
        return 1

    runs, kept = _kept_and_stripped("log_phi", 11, 0.6, check, exclusion)
    assert kept > 5  # the joint draws kept it
    for a, b in zip(runs[0][:7], runs[1][:7]):
        assert (a is None and b is None) or torch.equal(a, b)


def test_chains_keep_the_point_intensity_cache(gen):
    """The point sensor's intensities kept beside the chains (``ChainState.cache``, made by the
    joint draw with its likelihood, advanced by the sweeps' accepted moves) stay the intensity
    of the chains' state to round-off, a move leaves its input chain's cache as it was, and
    the decisions are those of sweeps that make their own cache each time."""
    def check(old, new, move, sensor, z, before):
        assert torch.equal(old.cache, before)  # the input chain is not changed
        torch.testing.assert_close(new.cache, sensor.amplitude_cache(new.x, new.exists, z), rtol=1e-12, atol=0.0)
        torch.testing.assert_close(new.log_lik, sensor.log_likelihood(new.x, z, new.exists))
        return int(move == "refine")

    runs, checked = _kept_and_stripped("cache", 12, 0.5, check)
    assert checked > 5
    assert torch.equal(runs[0].x, runs[1].x) and torch.equal(runs[0].exists, runs[1].exists)


def test_refine_slot_int_and_tensor_slot_agree():
    """The eager sweep's Python-int slot (views, one slot rewritten) and the compiled program's
    tensor slot (gathers, selects over every slot) give the same bits: births and deaths in
    clutter, the point sensor's intensity cache and the exclusion term, every slot in turn."""
    from torchmcmcpf.kernels.moves import joint_move, refine_slot
    from torchmcmcpf.models.multitarget import Exclusion
    from torchmcmcpf.scenarios.septier import septier

    g = torch.Generator().manual_seed(5)
    scn = septier(2, 2, generator=g)
    motion, sensor, dynamics = scn.motion, scn.sensor, TargetDynamics(scn.motion, scn.existence)
    z = type(scn.measurements)(*(t[1] for t in scn.measurements))
    k = scn.alive.shape[-1]
    cloud = previous_cloud(torch.zeros(2, 30, k, 4, dtype=DT), torch.full((2, 30), -math.log(30), dtype=DT),
                           torch.zeros(2, 30, k, dtype=torch.bool), motion=motion)
    like = cloud.x.new_empty(2, 64, k, 4)
    chain = init_chains(cloud, JointNoise.draw(like, dynamics, generator=g, z=z, cloud=cloud), z, dynamics=dynamics,
                        sensor=sensor)
    for _ in range(4):  # joint draws: chains with newborns, some of them accepted
        chain, _ = joint_move(chain, JointNoise.draw(like, dynamics, generator=g, z=z, cloud=cloud), cloud=cloud, z=z,
                              dynamics=dynamics, sensor=sensor)
    assert chain.exists.any() and not chain.exists.all()
    noise = RefineNoise.draw(chain.x, dynamics, generator=g, z=z, exists=chain.exists_prev)
    x_prop, e_prop, r_prop = dynamics.propagate(chain.x_prev, chain.exists_prev, noise.eps, noise.birth,
                                                noise.relocation)
    log_ratio = r_prop - chain.log_ratio
    state = (chain.x, chain.log_lik, chain.exists, chain.log_ratio)
    cache = sensor.amplitude_cache(chain.x, chain.exists, z)
    accepted = []
    for n in range(k):
        args = (*state, x_prop, e_prop, r_prop, log_ratio, noise.u)
        by_int = refine_slot(*args, n, z, cache.clone(), sensor=sensor, exclusion=Exclusion())
        by_tensor = refine_slot(*args, torch.full(chain.log_lik.shape, n), z, cache.clone(), sensor=sensor,
                                exclusion=Exclusion())
        for a, b in zip(by_int[:5], by_tensor[:5]):
            assert torch.equal(a, b)
        assert by_int[5][0] is None and by_tensor[5][0] is None  # the point sensor's change: every entry
        assert torch.equal(by_int[5][1], by_tensor[5][1])
        accepted.append(by_int[4])
        state = by_int[:4]
        cache = sensor.update_amplitude_cache(cache, *by_int[5], by_int[4])
    flags = torch.stack(accepted, -1)
    assert flags.any() and not flags.all()  # a mix of accepted and rejected updates
