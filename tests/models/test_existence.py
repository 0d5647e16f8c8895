"""Existence chain (paper 004 eq. 25), birth densities and the existence estimate."""

import math

import pytest
import torch

from torchmcmcpf.models import ConstantVelocity
from torchmcmcpf.models.existence import BirthDeath
from torchmcmcpf.models.sensors.points import PointFrame
from torchmcmcpf.state import ParticleState, existence_estimate

AREA = ((0.0, 1000.0), (0.0, 500.0))


def model(**kw):
    kw = {"velocity_std": 3.0, **kw}
    return BirthDeath(0.1, 0.3, AREA, **kw).double()


def test_transition_matrix_and_stationary_distribution():
    bd = model()
    P = bd.transition_matrix()
    assert torch.allclose(P.sum(-1), torch.ones(2, dtype=torch.float64))
    pi1 = bd.stationary()
    assert pi1 == pytest.approx(0.1 / 0.4)
    pi = torch.tensor([1 - pi1, pi1], dtype=torch.float64)
    assert torch.allclose(pi @ P, pi)
    # log_prob_exists is eq. 25, the same matrix
    e_prev = torch.tensor([False, False, True, True])
    e_next = torch.tensor([False, True, False, True])
    assert torch.allclose(bd.log_prob_exists(e_next, e_prev).exp(), P.reshape(-1))


def test_chain_reaches_its_stationary_distribution(gen):
    bd = model()
    motion = ConstantVelocity(1.0, 1.0).double()
    n = 20_000
    x = torch.zeros(4, n // 4, 4, dtype=torch.float64)
    e = torch.zeros(4, n // 4, dtype=torch.bool)  # all inactive: far from stationary
    # After t steps P(e_t = 1) = pi + (1 - P_B - P_D)^t (0 - pi); with t = 40 the bias is
    # 0.6^40 * 0.25 < 1e-9, so the n slots are independent Bernoulli(pi) draws:
    # standard error sqrt(pi (1 - pi) / n) = 3.1e-3; 5 standard errors never fail by chance.
    for _ in range(40):
        x, e = bd.sample(x, e, motion=motion, generator=gen)
    pi = bd.stationary()
    frac = e.double().mean().item()
    assert abs(frac - pi) < 5 * math.sqrt(pi * (1 - pi) / n)
    # inactive slots hold x_death exactly; active ones are finite and moved
    assert torch.equal(x[~e], torch.zeros_like(x[~e]))
    assert bool(torch.isfinite(x).all())


def test_births_from_prior_are_uniform_over_the_area(gen):
    bd = model()
    x = bd.sample_birth((50_000,), generator=gen, dtype=torch.float64)
    assert x.shape == (50_000, 4)
    assert bool((x[:, 0] >= 0).all() & (x[:, 0] <= 1000).all() & (x[:, 2] >= 0).all() & (x[:, 2] <= 500).all())
    # mean of U(0, 1000): 500, sd 1000/sqrt(12)/sqrt(n) = 1.29; velocity sd 3: 5 se bounds
    assert abs(x[:, 0].mean().item() - 500) < 5 * 1000 / math.sqrt(12 * 50_000)
    assert abs(x[:, 1].std().item() - 3.0) < 5 * 3.0 / math.sqrt(2 * 50_000)
    assert torch.allclose(bd.birth_log_prob(x[:3]), torch.full((3,), -math.log(5e5), dtype=torch.float64)
                          + (-0.5 * (x[:3, [1, 3]] / 3).square() - math.log(3 * math.sqrt(2 * math.pi))).sum(-1))


def test_measurement_driven_births_are_importance_weighted_correctly(gen):
    """E_q[p_0/q_0 f] = E_{p_0}[f]: the weight of a birth drawn near the points is right."""
    motion = ConstantVelocity(1.0, 1.0).double()
    pts = torch.tensor([[[100.0, 100.0], [900.0, 400.0], [0.0, 0.0]]], dtype=torch.float64)
    frame = PointFrame(pts, torch.tensor([[True, True, False]]))
    n = 200_000
    x = torch.zeros(1, n, 1, 4, dtype=torch.float64)
    e = torch.zeros(1, n, 1, dtype=torch.bool)
    bd_all = BirthDeath(1.0, 0.0, AREA, velocity_std=3.0, birth_std=20.0, p_uniform=0.2).double()
    x1, e1, log_r = bd_all.propose(x, e, motion=motion, generator=gen, z=frame)
    assert bool(e1.all())
    w = log_r.exp().reshape(-1)
    pos = x1.reshape(n, 4)[:, [0, 2]]
    # f = 1: E_q[w] = 1. f = 1{x < 200}: E = 0.2. The weights are bounded by 1/P_I = 5, so
    # the standard error is at most 5/sqrt(n) = 0.011; 5 of those never fail by chance.
    assert abs(w.mean().item() - 1.0) < 5 * w.std().item() / math.sqrt(n)
    f = (pos[:, 0] < 200).double()
    assert abs((w * f).mean().item() - 0.2) < 5 * (w * f).std().item() / math.sqrt(n)
    # most births sit near the valid points, none near the padded one at (0, 0)
    near = [((pos - pts[0, m]).norm(dim=-1) < 100).double().mean().item() for m in range(3)]
    assert near[0] > 0.35 and near[1] > 0.35 and near[2] < 0.05


def test_propose_is_reproducible_and_log_prob_matches(gen):
    bd = model(birth_std=20.0)
    motion = ConstantVelocity(1.0, 1.0).double()
    x = torch.randn(2, 7, 3, 4, generator=gen, dtype=torch.float64) * 100 + 250
    e = torch.rand(2, 7, 3, generator=gen) < 0.5
    frame = PointFrame(torch.rand(2, 4, 2, generator=gen, dtype=torch.float64) * 500,
                       torch.ones(2, 4, dtype=torch.bool))
    a = bd.propose(x, e, motion=motion, generator=torch.Generator().manual_seed(5), z=frame)
    b = bd.propose(x, e, motion=motion, generator=torch.Generator().manual_seed(5), z=frame)
    for u, v in zip(a, b):
        assert torch.equal(u, v)
    x1, e1, _ = a
    lp = bd.log_prob(x1, e1, x, e, motion=motion)
    expected = bd.log_prob_exists(e1, e) + torch.where(e & e1, motion.log_prob(x1, x), 0.0) \
        + torch.where(~e & e1, bd.birth_log_prob(x1), 0.0)
    assert torch.allclose(lp, expected)


def test_existence_estimate():
    x = torch.tensor([[[[1.0, 0, 2, 0], [0, 0, 0, 0]], [[3.0, 0, 4, 0], [5, 0, 6, 0]]]])  # (1, 2, 2, 4)
    exists = torch.tensor([[[True, False], [True, True]]])
    log_w = torch.log(torch.tensor([[0.25, 0.75]]))
    est = existence_estimate(ParticleState(x, log_w, exists))
    assert torch.allclose(est.exists_prob, torch.tensor([[1.0, 0.75]]))
    assert torch.allclose(est.expected_count, torch.tensor([1.75]))
    assert torch.allclose(est.mean[0, 0], torch.tensor([2.5, 0, 3.5, 0]))
    assert torch.allclose(est.mean[0, 1], torch.tensor([5.0, 0, 6, 0]))
    assert est.present.tolist() == [[True, True]]
    with pytest.raises(ValueError, match="exists"):
        existence_estimate(ParticleState(x, log_w))


@pytest.mark.parametrize("kw, match", [
    (dict(p_birth=1.5), "p_birth"), (dict(p_death=-0.1), "p_death"), (dict(area=((0, 1), (2, 1))), "area"),
    (dict(velocity_std=0.0), "velocity_std"), (dict(birth_std=-1.0), "birth_std"),
])
def test_bad_settings_raise(kw, match):
    args = {"p_birth": 0.1, "p_death": 0.1, "area": AREA, "velocity_std": 1.0, **kw}
    with pytest.raises(ValueError, match=match):
        BirthDeath(args.pop("p_birth"), args.pop("p_death"), args.pop("area"), **args)


def test_birth_ratios_are_taken_where_a_slot_can_be_born(gen):
    """The birth noise scores a candidate (a sum over the frame's points) only where its
    uniform can turn an inactive slot on (``may_be_born``); the candidates, and every ratio a
    transition reads, are those of scoring all of them."""
    bd = BirthDeath(0.1, 0.05, AREA, velocity_std=3.0, birth_std=20.0, p_uniform=0.2).double()
    bd = bd.with_proposal((0.3, 0.1))
    pts = torch.tensor([[[100.0, 100.0], [900.0, 400.0], [0.0, 0.0]]], dtype=torch.float64)
    frame = PointFrame(pts, torch.tensor([[True, True, False]]))
    x = torch.zeros(1, 400, 3, 4, dtype=torch.float64)
    exists = torch.rand(1, 400, 3, generator=gen) < 0.5
    motion = ConstantVelocity(1.0, 1.0).double()
    eps, noise = bd.draw_noise(x, motion, frame, generator=torch.Generator().manual_seed(2))
    u = noise.u
    full_x, full_r = bd._draw_births(u.shape, frame, generator=_after_uniforms(u, motion), dtype=u.dtype,
                                     device=u.device)
    assert torch.equal(noise.x, full_x)
    can = bd.may_be_born(u)
    assert 0 < int(can.sum()) < can.numel() and torch.equal(can, u < 0.3)
    assert torch.equal(noise.log_ratio, torch.where(can, full_r, 0.0))
    for from_prior in (False, True):
        _, _, log_r = bd.propagate(x, exists, eps, noise, motion=motion, from_prior=from_prior)
        _, _, ref = bd.propagate(x, exists, eps, noise._replace(log_ratio=full_r), motion=motion, from_prior=from_prior)
        assert torch.equal(log_r, ref)


def _after_uniforms(u, motion):
    """The generator of ``draw_noise`` after its uniforms and motion noise (seed 2)."""
    g = torch.Generator().manual_seed(2)
    torch.rand(u.shape, generator=g, dtype=u.dtype)
    torch.randn(u.shape + (motion.noise_dim,), generator=g, dtype=u.dtype)
    return g
