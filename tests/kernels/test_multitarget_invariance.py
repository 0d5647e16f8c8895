"""Invariance of the moves with the multitarget prior's terms (issue 22): exclusion, the
relocation component with its data-driven proposal, and the IP-MCMC two-slot move.

Two slots on a line (state ``[u]``, D = 1), labelled Gaussian measurements ``z_j = u_j + w``,
a field of view ``[-10, 10]``, and a data-driven density near the measurements: small enough
to integrate the exact targets on a 2-D grid, with every term active (the relocation
component carries a good part of the posterior mass, the exclusion factor changes the
correlation of the two slots). The chains start from the proposal and are compared with the
quadrature moments within the Monte Carlo error of C independent chains.
"""

import math

import pytest
import torch
from _line import DT, FOV, LineSensor, Q, R, log_fov
from torch.utils._pytree import tree_map

from torchmcmcpf.kernels.chains import JointNoise, RefineNoise, previous_cloud
from torchmcmcpf.kernels.exchange import ExchangeChains, draw_exchange_noise, exchange_iteration
from torchmcmcpf.kernels.moves import init_chains, joint_move, refine_move
from torchmcmcpf.models.existence import TargetDynamics
from torchmcmcpf.models.motion import LinearGaussianMotion
from torchmcmcpf.models.multitarget import Exclusion, Recapture


def _grid(h=0.02):
    g = torch.arange(FOV[0] - 4.0, FOV[1] + 4.0 + h / 2, h, dtype=DT)
    return g, h


def _log_normal(x, m, v):
    return -0.5 * (x - m).square() / v - 0.5 * math.log(2 * math.pi * v)


def _moments(log_density):
    """Moments of a density on the 2-D grid: (E u1, E u2, E u1^2, E u2^2, E u1 u2)."""
    g, _ = _grid()
    w = torch.softmax(log_density.flatten(), 0).reshape(log_density.shape)
    u1, u2 = g[:, None], g[None, :]
    return torch.stack([(w * u1).sum(), (w * u2).sum(), (w * u1**2).sum(), (w * u2**2).sum(), (w * u1 * u2).sum()])


def _sample_moments(y):
    """y (C, 2) -> sample moments and their standard errors."""
    f = torch.stack([y[:, 0], y[:, 1], y[:, 0] ** 2, y[:, 1] ** 2, y[:, 0] * y[:, 1]], -1)
    return f.mean(0), f.std(0) / math.sqrt(y.shape[0])


def _common(x_prev, z, exclusion, delta):
    """Likelihood and exclusion on the grid, and the per-slot, per-particle prior pieces."""
    g, _ = _grid()
    u1, u2 = g[:, None], g[None, :]
    log_lik = _log_normal(z[0], u1, R) + _log_normal(z[1], u2, R)
    log_phi = exclusion.log_phi((u1 - u2).square()) if exclusion is not None else torch.zeros_like(log_lik)
    # per particle i and slot j: log[(1 - delta) N(u; x_ij, Q) + delta U(u)] on the grid (N, G)
    pieces = []
    for j in range(2):
        mo = _log_normal(g[None, :], x_prev[:, j, None], Q) + math.log1p(-delta)
        pieces.append(torch.logaddexp(mo, log_fov(g)[None, :] + math.log(delta)))
    return log_lik + log_phi, pieces


def _ipmcmc_target(x_prev, z, exclusion, delta, log_w=None):
    """pi(u) ∝ p(z | u) Phi(u) prod_j sum_i w^i [(1 - delta) N(u_j; x_ij, Q) + delta U(u_j)]
    (uniform weights by default)."""
    base, pieces = _common(x_prev, z, exclusion, delta)
    lw = torch.zeros(x_prev.shape[0], dtype=DT) if log_w is None else log_w
    m = [torch.logsumexp(p + lw[:, None], 0) for p in pieces]
    return base + m[0][:, None] + m[1][None, :]


def _mcmc_target(x_prev, z, exclusion, delta, log_w=None):
    """pi(u) ∝ p(z | u) Phi(u) sum_a w^a prod_j [(1 - delta) N(u_j; x_aj, Q) + delta U(u_j)]
    (uniform weights by default)."""
    base, pieces = _common(x_prev, z, exclusion, delta)
    lw = torch.zeros(x_prev.shape[0], dtype=DT) if log_w is None else log_w
    joint = torch.logsumexp(pieces[0][:, :, None] + pieces[1][:, None, :] + lw[:, None, None], 0)
    return base + joint


def _problem():
    motion = LinearGaussianMotion(torch.eye(1, dtype=DT), Q * torch.eye(1, dtype=DT))
    # N = 3 previous particles; slot 0 is predicted near 0 while its measurement is at 3
    # (the relocation component matters), slot 1 near 1 (the slots' predictions overlap:
    # exclusion and the two-slot move matter). The likelihood is broad enough (R = 2) that
    # an independence sampler from the prediction forgets its start within the iterations
    # run: sup pi / m <= 6 per slot, so 50 updates of a slot leave < 1e-4 of the start.
    x_prev = torch.tensor([[-0.5, 1.5], [0.3, 0.8], [0.0, 2.2]], dtype=DT).unsqueeze(-1)  # (N, K, 1)
    z = torch.tensor([3.0, 1.3], dtype=DT).unsqueeze(-1)  # (K, 1)
    return motion, LineSensor(), x_prev, z


#: Unequal weights of the 3 previous particles (the source draws and the pair's ratio use them).
LOG_W = torch.tensor([0.6, 0.3, 0.1], dtype=DT).log()


def _exchange_chains(exclusion, recapture, *, pair_every, seed, iterations=150, c=6000, x_prev=None, joint=False):
    """Run C chains of the one-slot exchange move with, every ``pair_every``-th iteration, the
    two-slot move (``pair_every = 1``: the two-slot move alone) on the problem (its previous
    particles, or ``x_prev (N, 2, 1)``); the chains start from the proposal. Returns the chains
    and the acceptance rates of the two kernels."""
    motion, sensor, x_problem, z = _problem()
    x_prev = x_problem if x_prev is None else x_prev
    g = torch.Generator().manual_seed(seed)
    b, n, k = 1, x_prev.shape[0], 2
    xp = x_prev.unsqueeze(0).expand(b, n, k, 1)
    zb = z.unsqueeze(0).expand(b, k, 1)
    log_w = LOG_W.unsqueeze(0)
    dyn = TargetDynamics(motion, None, recapture, sensor)
    src = torch.randint(n, (b, c), generator=g)
    x0 = torch.take_along_dim(xp, src[..., None, None], 1)
    y, _, log_r, kind = dyn.propagate_labelled(x0, None, *dyn.draw_noise(x0, zb, generator=g))
    sources = (src.unsqueeze(-1).expand(b, c, k), LOG_W[src].unsqueeze(-1).expand(b, c, k)) \
        if recapture is not None and (recapture.p_same_source > 0 or joint) else (None, None)
    chain = ExchangeChains(y, sensor.log_likelihood(y, zb), None, None if recapture is None else log_r, kind,
                           *sources)
    accepted, pair_acc = 0.0, 0.0
    pairs = torch.tensor([[[False, True], [False, False]]])
    partner = torch.tensor([[1, 0]]) if joint else None
    single = draw_exchange_noise(log_w, iterations, c, k, dynamics=dyn, generator=g, dtype=DT, z=zb, partner=partner)
    double = draw_exchange_noise(log_w, iterations, c, k, dynamics=dyn, generator=g, dtype=DT, z=zb, pairs=pairs,
                                 partner=partner)
    for t in range(iterations):
        two = (t + 1) % pair_every == 0
        nz = tree_map(lambda a: None if a is None else a[t], double if two else single)
        chain, acc, _ = exchange_iteration(chain, xp, None, zb, nz, dynamics=dyn, sensor=sensor, exclusion=exclusion)
        accepted += float(acc.double().mean()) / iterations
        if two:
            pair_acc += float(acc.double().mean()) / (iterations // pair_every)
    torch.testing.assert_close(chain.log_lik, sensor.log_likelihood(chain.y, zb))
    return chain, accepted, pair_acc


@pytest.mark.parametrize("terms", ["exclusion", "recapture", "both", "independent sources"])
def test_exchange_moves_leave_the_extended_target_invariant(terms):
    """The one-slot exchange move and the two-slot move (each with its own proposal
    probability epsilon; both slots from one particle with probability ``p_same_source``),
    with exclusion and/or relocation, target
    ``p(z | u) Phi(u) prod_j [(1 - delta) m_j(u_j) + delta p_0(u_j)]``, unequal weights."""
    _, _, x_prev, z = _problem()
    exclusion = Exclusion(1.5) if terms in ("exclusion", "both") else None
    recapture = Recapture(p_jump=0.2, p_propose=0.3, pair_every=3, p_propose_pair=0.6,
                          p_same_source=0.0 if terms == "independent sources" else 0.7) \
        if terms != "exclusion" else None
    delta = 0.2 if recapture is not None else 1e-300
    chain, accepted, pair_acc = _exchange_chains(exclusion, recapture, pair_every=3, seed=11)
    assert 0.1 < accepted < 0.95 and pair_acc > 0.03  # both kernels move the chains
    exact = _moments(_ipmcmc_target(x_prev[..., 0], z[:, 0], exclusion, delta, LOG_W))
    mean, se = _sample_moments(chain.y[0, :, :, 0])
    assert ((mean - exact).abs() <= 4.5 * se).all(), (mean, exact, se)
    if recapture is not None:  # the relocation component holds a real share of the mass
        assert 0.1 < float((chain.kind == 2).double().mean()) < 0.9


def test_one_sourced_pairs_need_their_ratio(monkeypatch):
    """The two-slot move alone, both slots from one particle with probability 0.9, previous
    particles whose slots are anti-correlated (the joint prediction and the product of the
    slots' marginals differ): the chains hold the factorised target with the pair's source
    ratio (module docstring of :mod:`torchmcmcpf.kernels.exchange`); without the ratio they
    drift towards the joint prediction, tens of standard errors away (the check can fail)."""
    _, _, _, z = _problem()
    x_prev = torch.tensor([[0.0, 3.0], [3.0, 0.0], [1.5, 1.5]], dtype=DT).unsqueeze(-1)
    recapture = Recapture(p_jump=0.2, p_propose=0.3, p_propose_pair=0.3, p_same_source=0.9)
    exact = _moments(_ipmcmc_target(x_prev[..., 0], z[:, 0], None, 0.2, LOG_W))
    chain, _, pair_acc = _exchange_chains(None, recapture, pair_every=1, seed=13, x_prev=x_prev)
    assert pair_acc > 0.1
    same = float((chain.source[..., 0] == chain.source[..., 1]).double().mean())
    assert 0.05 < same < 0.9  # both kinds of pair are held
    mean, se = _sample_moments(chain.y[0, :, :, 0])
    assert ((mean - exact).abs() <= 4.5 * se).all(), (mean, exact, se)
    import torchmcmcpf.kernels.exchange as exchange
    monkeypatch.setattr(exchange, "pair_source_log_ratio", lambda s, lw, rho: torch.zeros_like(lw[..., 0]))
    chain, _, _ = _exchange_chains(None, recapture, pair_every=1, seed=13, x_prev=x_prev)
    mean, se = _sample_moments(chain.y[0, :, :, 0])
    assert ((mean - exact).abs() > 10 * se).any(), (mean, exact, se)


@pytest.mark.parametrize("terms", ["recapture", "both"])
def test_joint_pairs_leave_the_pair_joint_prediction_invariant(terms):
    """Joint pairs (:mod:`torchmcmcpf.kernels.exchange`, "Joint pairs"): the two slots paired,
    one-slot moves that keep the pair's source and two-slot moves from one source target the
    pair's joint prediction ``p(z | u) Phi(u) sum_a w^a prod_j [(1 - delta) f(u_j | x^a_j) +
    delta p_0(u_j)]`` (the MCMC-PF's), not the product of the marginals. The previous particles
    are anti-correlated, so the two targets differ by many standard errors (checked: the check
    can fail), and the chains end with one source per pair."""
    _, _, _, z = _problem()
    x_prev = torch.tensor([[0.0, 3.0], [3.0, 0.0], [1.5, 1.5]], dtype=DT).unsqueeze(-1)
    exclusion = Exclusion(1.5) if terms == "both" else None
    recapture = Recapture(p_jump=0.2, p_propose=0.3, pair_every=3, p_propose_pair=0.6, p_same_source=0.0)
    chain, accepted, pair_acc = _exchange_chains(exclusion, recapture, pair_every=3, seed=17, x_prev=x_prev,
                                                 joint=True)
    assert 0.1 < accepted < 0.95 and pair_acc > 0.03  # both kernels move the chains
    assert bool((chain.source[..., 0] == chain.source[..., 1]).all())
    mean, se = _sample_moments(chain.y[0, :, :, 0])
    exact = _moments(_mcmc_target(x_prev[..., 0], z[:, 0], exclusion, 0.2, LOG_W))
    assert ((mean - exact).abs() <= 4.5 * se).all(), (mean, exact, se)
    factorised = _moments(_ipmcmc_target(x_prev[..., 0], z[:, 0], exclusion, 0.2, LOG_W))
    assert ((factorised - exact).abs() > 10 * se).any(), (factorised, exact, se)


@pytest.mark.parametrize("terms", ["exclusion", "both"])
def test_mcmc_moves_leave_the_extended_target_invariant(terms):
    """The MCMC-PF's joint draw and refinement with exclusion and relocation target
    ``p(z | x) Phi(x) sum_a w^a prod_j [(1 - delta) f(x_j | x^a_j) + delta p_0(x_j)]``."""
    motion, sensor, x_prev, z = _problem()
    exclusion = Exclusion(1.5)
    recapture = Recapture(p_jump=0.2, p_propose=0.3) if terms == "both" else None
    delta = 0.2 if recapture is not None else 1e-300
    g = torch.Generator().manual_seed(12)
    b, c, n, k = 1, 6000, x_prev.shape[0], 2
    xp = x_prev.unsqueeze(0).expand(b, n, k, 1)
    zb = z.unsqueeze(0).expand(b, k, 1)
    cloud = previous_cloud(xp, torch.full((b, n), -math.log(n), dtype=DT))
    template = xp.new_empty((b, c, k, 1))
    dyn = TargetDynamics(motion, None, recapture, sensor)
    chain = init_chains(cloud, JointNoise.draw(template, dyn, generator=g, z=zb), zb, dynamics=dyn, sensor=sensor)
    acc_joint, acc_refine = 0.0, 0.0
    for t in range(160):
        if t % 2:
            chain, acc = joint_move(chain, JointNoise.draw(template, dyn, generator=g, z=zb), cloud=cloud,
                                    z=zb, dynamics=dyn, sensor=sensor, exclusion=exclusion)
            acc_joint += float(acc.double().mean()) / 80
        else:
            chain, acc = refine_move(chain, RefineNoise.draw(template, dyn, generator=g, z=zb), z=zb,
                                     dynamics=dyn, sensor=sensor, exclusion=exclusion)
            acc_refine += float(acc.double().mean()) / 80
    assert acc_joint > 0.05 and acc_refine > 0.1
    exact = _moments(_mcmc_target(x_prev[..., 0], z[:, 0], exclusion, delta))
    mean, se = _sample_moments(chain.x[0, :, :, 0])
    assert ((mean - exact).abs() <= 4.5 * se).all(), (mean, exact, se)


def test_the_terms_change_the_target():
    """The checks above can fail: the exact targets with and without each term differ by
    far more than the Monte Carlo error used there."""
    _, _, x_prev, z = _problem()
    plain = _moments(_ipmcmc_target(x_prev[..., 0], z[:, 0], None, 1e-300))
    excl = _moments(_ipmcmc_target(x_prev[..., 0], z[:, 0], Exclusion(1.5), 1e-300))
    reloc = _moments(_ipmcmc_target(x_prev[..., 0], z[:, 0], None, 0.2))
    assert (excl - plain).abs().max() > 0.2 and (reloc - plain).abs().max() > 0.5
