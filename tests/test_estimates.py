"""``state.weighted_cov``: the weighted covariance of each slot against a float64 reference
(NumPy's ``cov`` with ``aweights``), with and without existence flags.
"""

import math

import numpy as np
import torch

from torchmcmcpf.state import weighted_cov, weighted_mean


def _reference(x, w, e):
    """Per run and slot, NumPy's weighted covariance (``bias=True``) over the live particles."""
    b, _, k, d = x.shape
    out = np.zeros((b, k, d, d))
    for i in range(b):  # a reference, over a handful of runs and slots
        for j in range(k):
            live = e[i, :, j]
            if live.sum() > 0:
                out[i, j] = np.cov(x[i, live, j].T, aweights=w[i, live], bias=True)
    return out


def test_weighted_cov_matches_numpy_with_and_without_existence():
    g = torch.Generator().manual_seed(0)
    b, n, k, d = 3, 400, 2, 4
    x = 1000.0 + 3.0 * torch.randn(b, n, k, d, generator=g, dtype=torch.float64)  # far from 0, as positions are
    log_w = torch.randn(b, n, generator=g, dtype=torch.float64)
    w = torch.softmax(log_w, -1)
    mean = weighted_mean(x, log_w)
    ones = np.ones((b, n, k), dtype=bool)
    got = weighted_cov(x, log_w, mean)
    assert got.shape == (b, k, d, d) and torch.equal(got, got.mT)
    np.testing.assert_allclose(got.numpy(), _reference(x.numpy(), w.numpy(), ones), rtol=1e-10, atol=1e-10)

    exists = torch.rand(b, n, k, generator=g) < 0.6
    exists[0, :, 1] = False  # a slot no particle has: zeros, not NaN
    x_dead = x.masked_fill(~exists.unsqueeze(-1), math.inf)  # dead slots hold x_death
    we = w.unsqueeze(-1) * exists
    live_x = x.masked_fill(~exists.unsqueeze(-1), 0.0)
    mean_e = (we.unsqueeze(-1) * live_x).sum(1) / we.sum(1).clamp(min=1e-300)[..., None]
    got = weighted_cov(x_dead, log_w, mean_e, exists)
    assert torch.isfinite(got).all() and (got[0, 1] == 0).all()
    np.testing.assert_allclose(got.numpy(), _reference(x.numpy(), w.numpy(), exists.numpy()), rtol=1e-10, atol=1e-10)


def test_weighted_cov_float32_keeps_the_spread_of_far_particles():
    """Centred before the product: a spread of 1 m at 1e4 m in float32 is not lost."""
    g = torch.Generator().manual_seed(1)
    x = 1e4 + torch.randn(2, 5000, 1, 4, generator=g)
    log_w = torch.zeros(2, 5000)
    got = weighted_cov(x, log_w, weighted_mean(x, log_w))
    ref = _reference(x.double().numpy(), np.full((2, 5000), 1 / 5000), np.ones((2, 5000, 1), dtype=bool))
    np.testing.assert_allclose(got.double().numpy(), ref, rtol=1e-3, atol=1e-3)


def test_densest_place_matches_a_direct_count():
    """The candidates' support (weight of particles with a live slot within the cutoff) equals
    a per-candidate count written out directly, in label order, with the relabelling applied.
    """
    from torchmcmcpf.state import _densest

    g = torch.Generator().manual_seed(1)
    b, n, k, cutoff = 3, 40, 3, 100.0
    pos = 300.0 * torch.rand((b, n, k, 2), generator=g, dtype=torch.float64)
    live = torch.rand((b, n, k), generator=g) < 0.6
    live[2] = False  # no live slot in a row: support 0, the first candidate's label-0 slot
    live[2, 9, 1] = True  # ... then one, off the candidates: still 0
    slot_of = torch.argsort(torch.rand((b, n, k), generator=g), -1)
    log_w = torch.randn((b, n), generator=g, dtype=torch.float64)
    at, support = _densest(pos, None, slot_of, live, log_w, cutoff, candidates=8)
    pick = torch.linspace(0, n - 1, 8).round().to(torch.int64)
    pos_l = torch.take_along_dim(pos, slot_of.unsqueeze(-1), 2)  # label order
    w = torch.softmax(log_w, -1)
    assert float(support[2]) == 0.0 and torch.equal(at[2], pos_l[2, 0, 0])
    for r in range(b):  # the reference, written out: every candidate in label order
        best, best_at = -1.0, None
        for p in pick.tolist():
            for lab in range(k):
                if not live[r, p, lab]:
                    s = 0.0
                else:
                    d = (pos_l[r] - pos_l[r, p, lab]).norm(dim=-1)  # (N, K)
                    s = float((((d <= cutoff) & live[r]).any(-1).double() * w[r]).sum())
                if s > best:
                    best, best_at = s, pos_l[r, p, lab]
        assert math.isclose(float(support[r]), best, rel_tol=1e-12)
        assert torch.equal(at[r], best_at)


def _relabel_reference(cost, cutoff):
    """The relabelling rule written plainly (every row searched, every sweep over all rows):
    the cheapest-label permutation where distinct, else pairwise swaps from the own labels
    until none lowers the cost; the own labels kept unless the result saves > (cutoff/4)^2."""
    b, n, k, _ = cost.shape
    out = torch.empty((b, n, k), dtype=torch.int64)
    for i in range(b):
        for j in range(n):
            c = cost[i, j]
            nearest = c.argmin(-1)
            if sorted(nearest.tolist()) == list(range(k)):
                label = nearest.clone()
            else:
                label = torch.arange(k)
                for _ in range(k * (k - 1) // 2):
                    best, at = 1e-9 * cutoff**2, None
                    for a in range(k):
                        for d in range(a + 1, k):
                            g = c[a, label[a]] + c[d, label[d]] - c[a, label[d]] - c[d, label[a]]
                            if g > best:
                                best, at = g, (a, d)
                    if at is None:
                        break
                    a, d = at
                    label[a], label[d] = label[d].clone(), label[a].clone()
            own = torch.diagonal(c).sum()
            if own - c[torch.arange(k), label].sum() <= (cutoff / 4) ** 2:
                label = torch.arange(k)
            out[i, j] = torch.argsort(label)
    return out


def test_relabel_order_matches_the_plain_rule():
    """The settled rows and the shrinking swap search give the labels of the plain rule, on
    clouds with exchanged labels, close targets and absent slots sharing x_death (ties)."""
    from torchmcmcpf.state import relabel_order

    g = torch.Generator().manual_seed(4)
    b, n, k, cutoff = 3, 60, 4, 100.0
    centres = torch.tensor([[0.0, 0.0], [150.0, 0.0], [0.0, 60.0], [400.0, 400.0]], dtype=torch.float64)
    perm = torch.stack([torch.randperm(k, generator=g) if i % 3 else torch.arange(k) for i in range(b * n)])
    pos = centres[perm].reshape(b, n, k, 2) + 30.0 * torch.randn(b, n, k, 2, generator=g, dtype=torch.float64)
    dead = torch.rand(b, n, k, generator=g) < 0.3
    pos = torch.where(dead.unsqueeze(-1), torch.zeros_like(pos), pos)  # absent slots at x_death = 0
    x = torch.zeros(b, n, k, 4, dtype=torch.float64)
    x[..., 0], x[..., 2] = pos[..., 0], pos[..., 1]
    ref = x[:, 0].clone()
    got = relabel_order(x, ref, cutoff=cutoff)
    d2 = (pos.unsqueeze(-2) - torch.stack([ref[..., 0], ref[..., 2]], -1)[:, None, None]).square().sum(-1)
    cost = d2.clamp(max=cutoff**2)
    assert torch.equal(got, _relabel_reference(cost, cutoff))


def test_densest_place_of_a_cloud_with_repeats_equals_every_particles_own(gen):
    """The densest-place search measures the candidates against the first of each run of equal
    particles only (an MCMC chain repeats its state on a rejected move) and gives each particle
    its run's test: the place and its support are those found from every particle, bit for bit."""
    from torchmcmcpf.state import _densest, _runs

    b, n, k = 3, 400, 4
    pos = torch.rand(b, n, k, 2, generator=gen, dtype=torch.float64) * 500
    keep = torch.rand(b, n, generator=gen) < 0.25  # a new state where True, else the one before
    keep[:, 0] = True
    src = torch.where(keep, torch.arange(n), 0).cummax(1).values
    pos = torch.take_along_dim(pos, src[:, :, None, None], 1)
    pos[1, 7, 2, 0] = float("nan")  # never equal to anything: a first of its own
    x = torch.zeros(b, n, k, 4, dtype=torch.float64)
    x[..., 0], x[..., 2] = pos[..., 0], pos[..., 1]
    runs = _runs(x, None)
    assert runs is not None and runs.x.shape[1] < n
    # a relabelling and flags that are one per run (as the estimate's are), uneven weights
    run_of = runs.rank[:, :, None].expand(b, n, k)  # each particle's run
    slot_of = torch.stack([torch.randperm(k, generator=gen) for _ in range(b * runs.x.shape[1])]).reshape(
        b, -1, k).gather(1, run_of)
    live = (torch.rand(b, runs.x.shape[1], k, generator=gen) < 0.6).gather(1, run_of)
    log_w = torch.randn(b, n, generator=gen, dtype=torch.float64)
    at, support = _densest(pos, runs, slot_of, live, log_w, 100.0)
    at_every, support_every = _densest(pos, None, slot_of, live, log_w, 100.0)
    assert torch.equal(at, at_every) and torch.equal(support, support_every)
    assert bool((support > 0).all())  # a live slot near somewhere: the test compares found places


def test_relabel_order_by_runs_equals_every_particles_own(gen):
    """The estimate's relabelling searches once per run of equal particles (position and
    flags) and copies: the same permutations as :func:`relabel_order` on every particle, on a
    cloud of repeats with flags (a repeat whose flags differ starts a run of its own) and
    float coordinates (the cost's batched product over fewer rows)."""
    from torchmcmcpf.state import _relabel_order_runs, _runs, relabel_order

    b, n, k = 3, 500, 5
    x = torch.randn(b, n, k, 4, generator=gen, dtype=torch.float64) * 60
    e = torch.rand(b, n, k, generator=gen) < 0.7
    keep = torch.rand(b, n, generator=gen) < 0.2
    keep[:, 0] = True
    src = torch.where(keep, torch.arange(n), 0).cummax(1).values
    x, e = torch.take_along_dim(x, src[:, :, None, None], 1), torch.take_along_dim(e, src[:, :, None], 1)
    e[0, 11] = ~e[0, 11]  # flags differ from the particle before: its own run
    ref, ref_e = x[:, 0] + 5.0, torch.ones(b, k, dtype=torch.bool)
    runs = _runs(x, e)
    assert runs is not None and runs.x.shape[1] < n // 2
    want = relabel_order(x, ref, exists=e, reference_exists=ref_e)
    assert torch.equal(_relabel_order_runs(x, ref, runs, exists=e, reference_exists=ref_e), want)
    assert _runs(torch.randn(b, n, k, 4, generator=gen), None) is None  # no repeats: no runs


def test_relabelling_a_cloud_with_repeats_labels_each_repeat_as_its_first(gen):
    """The swap search runs once per run of equal rows and copies the labels to the repeats:
    a cloud of repeated particles gets, particle by particle, the labels of the same cloud
    without repeats (integer coordinates: every cost exact, whatever the batch shape)."""
    from torchmcmcpf.state import relabel_order

    b, n, k, rep = 2, 300, 4, 3
    ref = torch.tensor([[0.0, 0, 0, 0], [20.0, 0, 10, 0], [5.0, 0, 30, 0], [30.0, 0, 25, 0]], dtype=torch.float64)
    ref = ref.expand(b, k, 4)
    perm = torch.rand(b, n, k, generator=gen).argsort(-1)
    x = torch.take_along_dim(ref.unsqueeze(1).expand(b, n, k, 4), perm.unsqueeze(-1), 2).clone()
    x[..., [0, 2]] += torch.randint(-12, 13, (b, n, k, 2), generator=gen).to(x.dtype)
    once = relabel_order(x, ref)
    many = relabel_order(x.repeat_interleave(rep, 1), ref)
    assert torch.equal(many, once.repeat_interleave(rep, 1))
