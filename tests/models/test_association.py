"""Sensors with unknown association (paper 003 eqs. 14-17): exact sum, Metropolis search."""

import itertools
import math

import pytest
import torch

from torchmcmcpf.models.sensors.association import (
    AssociationBearingRange,
    AssociationPosition,
    PointFrame,
    metropolis_association,
    padded_pair_log_likelihood,
    permutations,
)

D64 = torch.float64


def states(shape, gen, scale=50.0):
    return torch.randn(shape + (4,), generator=gen, dtype=D64) * scale


def reference_log_likelihood(pair, exists, mask):
    """Average over injections of existing slots into valid measurements (Python loops)."""
    slots = [k for k in range(pair.shape[0]) if exists[k]]
    meas = [m for m in range(pair.shape[1]) if mask[m]]
    terms = [sum(pair[k, m] for k, m in zip(slots, perm)) for perm in itertools.permutations(meas, len(slots))]
    if not slots:
        return torch.tensor(0.0, dtype=pair.dtype)
    return torch.logsumexp(torch.stack(terms), 0) - math.log(len(terms))


@pytest.mark.parametrize("sensor", [AssociationPosition(1.0), AssociationBearingRange(1e-2, 1.0)])
def test_exact_sum_matches_brute_force(sensor, gen):
    # B = 2 runs, N = 3 particles, K = 4 slots, M = 5 rows; some slots missing, some rows padding
    x = states((2, 3, 4), gen, scale=3.0)
    z = states((2, 5), gen, scale=3.0)[..., :2]
    z = sensor.measure(torch.stack([z[..., 0], z[..., 0], z[..., 1], z[..., 1]], -1)) + 0.3
    exists = torch.tensor([[True, False, True, True]]).expand(2, 3, 4).clone()
    exists[1, 2] = torch.tensor([True, True, False, False])
    mask = torch.tensor([[True, True, False, True, True], [True, False, True, True, False]])
    got = sensor.log_likelihood(x, PointFrame(z, mask), exists)
    pair = sensor.pair_log_likelihood(x, z)
    for b in range(2):
        for n in range(3):
            ref = reference_log_likelihood(pair[b, n], exists[b, n], mask[b])
            torch.testing.assert_close(got[b, n], ref)


def test_one_target_is_a_gaussian(gen):
    sensor = AssociationPosition(torch.tensor([1.5, 0.5]))
    x = states((2, 3, 1), gen)
    z = torch.randn(2, 1, 2, generator=gen, dtype=D64) * 50
    ref = torch.distributions.Normal(x[..., [0, 2]], torch.tensor([1.5, 0.5], dtype=D64)).log_prob(
        z.unsqueeze(1)).sum((-2, -1))
    torch.testing.assert_close(sensor.log_likelihood(x, z), ref)


def test_more_targets_than_measurements_is_impossible(gen):
    sensor = AssociationPosition(1.0)
    x = states((1, 2, 3), gen)
    mask = torch.tensor([[True, True, False]])
    ll = sensor.log_likelihood(x, PointFrame(torch.zeros(1, 3, 2, dtype=D64), mask))
    assert bool(torch.isneginf(ll).all())


def test_too_many_targets_for_the_exact_sum(gen):
    with pytest.raises(ValueError, match="max\\(K, M\\) <= 6"):
        AssociationPosition(1.0).log_likelihood(states((1, 1, 7), gen), torch.zeros(1, 7, 2, dtype=D64))


def test_bearing_residual_wraps(gen):
    sensor = AssociationBearingRange(1e-2, 1.0)
    x = torch.tensor([[[[-100.0, 0.0, 0.001, 0.0]]]], dtype=D64)  # bearing just below +pi
    z = torch.tensor([[[-math.pi + 1e-5, 100.0]]], dtype=D64)  # just above -pi
    ll = sensor.pair_log_likelihood(x, z)
    best = sensor._log_norm  # residual zero
    assert (best - ll).item() < 0.5 * (2e-5 / 1e-2) ** 2 + 1e-9


@pytest.mark.parametrize("sensor", [AssociationPosition(1.0), AssociationBearingRange(1e-2, 1.0)])
def test_to_position_inverts_measure(sensor, gen):
    x = states((3, 4), gen)
    torch.testing.assert_close(sensor.to_position(sensor.measure(x)), x[..., [0, 2]])


@pytest.mark.parametrize("sensor", [AssociationPosition(1.0), AssociationBearingRange(1e-2, 1.0)])
def test_gradcheck_every_likelihood_hmc_uses(sensor, gen):
    x = states((1, 2, 3), gen, scale=5.0).requires_grad_(True)
    z = sensor.measure(states((1, 3), gen, scale=5.0)).detach()
    exists = torch.tensor([[[True, True, False], [True, False, True]]])
    mask = torch.tensor([[True, True, False]])
    frame = PointFrame(z, mask)
    assignment = torch.tensor([[[1, 0, 2], [0, 2, 1]]])
    assert torch.autograd.gradcheck(lambda x: sensor.pair_log_likelihood(x, z), (x,))
    assert torch.autograd.gradcheck(lambda x: sensor.log_likelihood(x, frame, exists), (x,))
    assert torch.autograd.gradcheck(lambda x: sensor.assigned_log_likelihood(x, frame, assignment, exists), (x,))


def test_simulate_shuffles_the_measurements(gen):
    sensor = AssociationPosition(1e-6)
    x = states((500, 3), gen)
    exists = torch.tensor([True, False, True]).expand(500, 3)
    frame = sensor.simulate(x, generator=gen, exists=exists)
    assert frame.z.shape == (500, 3, 2) and frame.mask.shape == (500, 3)
    assert bool(frame.mask[:, :2].all()) and not bool(frame.mask[:, 2].any())
    # the valid rows are the two existing targets, in either order, each order ~ half the time
    first_is_slot0 = (frame.z[:, 0] - x[:, 0, [0, 2]]).abs().max(-1).values < 1e-3
    first_is_slot2 = (frame.z[:, 0] - x[:, 2, [0, 2]]).abs().max(-1).values < 1e-3
    assert bool((first_is_slot0 ^ first_is_slot2).all())
    # Binomial(500, 1/2): 4.5 SE = 4.5 * sqrt(500 / 4) ~ 50
    assert abs(first_is_slot0.sum().item() - 250) < 50


def test_validate():
    sensor = AssociationPosition(1.0)
    sensor.validate(PointFrame(torch.zeros(2, 3, 2), torch.ones(2, 3, dtype=torch.bool)), 2)
    with pytest.raises(ValueError, match="z has shape"):
        sensor.validate(torch.zeros(2, 3, 3))
    with pytest.raises(ValueError, match="mask has dtype"):
        sensor.validate(PointFrame(torch.zeros(2, 3, 2), torch.ones(2, 3)))
    with pytest.raises(ValueError, match="batch size"):
        sensor.validate(torch.zeros(2, 3, 2), 4)
    with pytest.raises(ValueError, match="NaN"):
        sensor.validate(torch.full((2, 3, 2), float("nan")))
    with pytest.raises(ValueError, match="bearing_std"):
        AssociationBearingRange(0.0)


def exact_posterior(square):
    """(..., P!) log-posterior of each permutation and the permutations (P!, P)."""
    perms = permutations(square.shape[-1])
    scores = square[..., torch.arange(square.shape[-1]), perms].sum(-1)
    return torch.log_softmax(scores, -1), perms


def test_metropolis_leaves_the_association_posterior_invariant(gen):
    # One 4x4 problem, 20000 chains started from exact posterior draws: after 20
    # Metropolis swaps each chain is again an exact draw (invariance), so the frequency
    # of each of the 24 assignments is Binomial(n, p)/n: SE sqrt(p (1 - p) / n).
    square = torch.randn(4, 4, generator=gen, dtype=D64) * 1.5
    log_post, perms = exact_posterior(square)
    n = 20000
    start = torch.multinomial(log_post.exp(), n, replacement=True, generator=gen)
    _, last, _ = metropolis_association(square.expand(n, 4, 4), num_iters=20, generator=gen, init=perms[start])
    codes = (last * torch.tensor([64, 16, 4, 1])).sum(-1)
    perm_codes = (perms * torch.tensor([64, 16, 4, 1])).sum(-1)
    freq = (codes.unsqueeze(-1) == perm_codes).to(D64).mean(0)
    p = log_post.exp()
    z = (freq - p) / torch.sqrt(p * (1 - p) / n)
    assert z.abs().max() < 4.5  # 24 cells: false failure probability < 24 * 7e-6
    # and the chains moved
    assert (last != perms[start]).any(-1).to(D64).mean() > 0.2


def test_metropolis_search_finds_the_exact_best_and_agrees_with_exact_sum(gen):
    # Well separated targets: the search from the identity finds the maximum-likelihood
    # association of every particle, and the exact likelihood agrees with the best
    # assignment's up to the (negligible) other assignments: lse - max in [0, log 24].
    sensor = AssociationPosition(1.0)
    truth = states((8, 4), gen, scale=50.0)
    x = truth.unsqueeze(1) + torch.randn(8, 16, 4, 4, generator=gen, dtype=D64)
    z = sensor.simulate(truth, generator=gen).z
    square, log_count = padded_pair_log_likelihood(sensor.pair_log_likelihood(x, z), None, None)
    best, _, best_score = metropolis_association(square, num_iters=60, generator=gen)
    log_post, perms = exact_posterior(square)
    scores = square[..., torch.arange(4), perms].sum(-1)
    assert torch.equal(best, perms[scores.argmax(-1)])
    torch.testing.assert_close(best_score, scores.max(-1).values)
    exact = sensor.log_likelihood(x, z) + log_count  # logsumexp over the 24 assignments
    gap = exact - best_score
    assert bool((gap >= -1e-9).all()) and bool((gap < 1e-3).all())


def test_metropolis_same_seed_same_result(gen):
    square = torch.randn(3, 5, 5, dtype=D64, generator=gen)
    a = metropolis_association(square, num_iters=10, generator=torch.Generator().manual_seed(1))
    b = metropolis_association(square, num_iters=10, generator=torch.Generator().manual_seed(1))
    assert all(torch.equal(u, v) for u, v in zip(a, b))
    with pytest.raises(ValueError, match="num_iters"):
        metropolis_association(square, num_iters=0, generator=gen)
