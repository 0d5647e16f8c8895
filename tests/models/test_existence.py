"""Existence chain (paper 004 eq. 25), birth densities and the existence estimate."""

import math

import pytest
import torch

from torchmcmcpf.models import ConstantVelocity
from torchmcmcpf.models.existence import BirthDeath, BirthNoise
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


def test_birth_candidates_are_drawn_where_a_slot_can_be_born(gen):
    """The birth noise draws a candidate, and scores it (a sum over the frame's points), only
    where its uniform can turn an inactive slot on (``may_be_born``), each run's candidates
    packed in order into one block drawn by the dense code; elsewhere ``x_death`` and ratio 0,
    which no transition reads (NaN there changes nothing)."""
    bd = BirthDeath(0.1, 0.05, AREA, velocity_std=3.0, birth_std=20.0, p_uniform=0.2).double()
    bd = bd.with_proposal((0.3, 0.1))
    pts = torch.tensor([[[100.0, 100.0], [900.0, 400.0], [0.0, 0.0]],
                        [[500.0, 250.0], [0.0, 0.0], [0.0, 0.0]]], dtype=torch.float64)
    frame = PointFrame(pts, torch.tensor([[True, True, False], [True, False, False]]))
    x = torch.zeros(2, 400, 3, 4, dtype=torch.float64)
    exists = torch.rand(2, 400, 3, generator=gen) < 0.5
    motion = ConstantVelocity(1.0, 1.0).double()
    eps, noise = bd.draw_noise(x, motion, frame, generator=torch.Generator().manual_seed(2))
    u = noise.u
    can = bd.may_be_born(u)
    assert 0 < int(can.sum()) < can.numel() and torch.equal(can, u < 0.3)
    counts = can.flatten(1).sum(-1)
    assert counts[0] != counts[1]  # two runs' blocks of different lengths
    width = int(counts.max())
    block_x, block_r = bd._draw_births((2, width), frame, generator=_after_uniforms(u, motion), dtype=u.dtype,
                                       device=u.device)
    for r in range(2):  # the run's candidates, in order, are its block's first columns
        got = noise.x[r][can[r]]
        assert torch.equal(got, block_x[r, :int(counts[r])])
        assert torch.equal(noise.log_ratio[r][can[r]], block_r[r, :int(counts[r])])
    assert torch.equal(noise.x[~can], bd.x_death.double().expand(int((~can).sum()), 4))
    assert torch.equal(noise.log_ratio[~can], torch.zeros(int((~can).sum()), dtype=torch.float64))
    # the ratio is the candidate's own: log p_0 - log q_0 at its position
    pos = noise.x[..., [0, 2]]
    assert torch.allclose(noise.log_ratio[can], bd._log_birth_ratio(pos, pts, frame.mask, 20.0)[can])
    unread = noise._replace(x=torch.where(can.unsqueeze(-1), noise.x, math.nan),
                            log_ratio=torch.where(can, noise.log_ratio, math.nan))
    for from_prior in (False, True):
        ref = bd.propagate(x, exists, eps, noise, motion=motion, from_prior=from_prior)
        got = bd.propagate(x, exists, eps, unread, motion=motion, from_prior=from_prior)
        assert all(torch.equal(a, b) for a, b in zip(ref, got))
    # with the ancestors' flags, only their inactive slots draw
    narrow = BirthNoise.draw(x, bd, frame, generator=torch.Generator().manual_seed(3), exists=exists)
    drawn = bd.can_be_born(narrow.u, exists)
    assert torch.equal(narrow.x[~drawn], bd.x_death.double().expand(int((~drawn).sum()), 4))
    assert bool((narrow.log_ratio[drawn] != 0).all())


def _after_uniforms(u, motion):
    """The generator of ``draw_noise`` after its uniforms and motion noise (seed 2)."""
    g = torch.Generator().manual_seed(2)
    torch.rand(u.shape, generator=g, dtype=u.dtype)
    torch.randn(u.shape + (motion.noise_dim,), generator=g, dtype=u.dtype)
    return g


def test_a_simulated_scene_draws_every_slot_candidate():
    """``BirthDeath.sample`` (the scenes' simulator) draws a newborn candidate for every slot,
    so a seed's scene does not depend on which slots the filters' draws skip: the same as
    uniforms, motion noise and every slot's candidate from ``p_0`` drawn in that order."""
    bd = BirthDeath(0.3, 0.2, AREA, velocity_std=3.0).double()
    motion = ConstantVelocity(1.0, 1.0).double()
    x = torch.zeros(2, 50, 3, 4, dtype=torch.float64)
    exists = torch.rand(2, 50, 3, generator=torch.Generator().manual_seed(0)) < 0.5
    got_x, got_e = bd.sample(x, exists, motion=motion, generator=torch.Generator().manual_seed(5))
    g = torch.Generator().manual_seed(5)
    u = torch.rand(x.shape[:-1], generator=g, dtype=torch.float64)
    eps = torch.randn(x.shape[:-1] + (motion.noise_dim,), generator=g, dtype=torch.float64)
    pos = bd.uniform_position(torch.rand(x.shape[:-1] + (2,), generator=g, dtype=torch.float64))
    vel = torch.randn(x.shape[:-1] + (2,), generator=g, dtype=torch.float64)
    ref_x, ref_e, _ = bd.propagate(x, exists, eps, BirthNoise(u, bd._newborn(pos, vel), torch.zeros_like(u)),
                                   motion=motion)
    born = ref_e & ~exists
    assert 0 < int(born.sum())
    assert torch.equal(got_x, ref_x) and torch.equal(got_e, ref_e)
