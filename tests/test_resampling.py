import math

import pytest
import torch

from torchmcmcpf import resampling as rs

WEIGHTS = torch.tensor([0.05, 0.4, 0.0, 0.15, 0.3, 0.1], dtype=torch.float64)


@pytest.mark.parametrize("method", ["systematic", "stratified", "multinomial"])
def test_resampling_is_unbiased(method, gen):
    # R independent resamplings of the same weights, batched as R runs.
    # E[count_i] = N w_i for every scheme. Var(count_i) <= N w_i (1 - w_i) (multinomial is
    # the largest of the three), so the mean over R runs has standard error at most
    # sqrt(N w (1 - w) / R); we allow 5 of those.
    R, N = 4000, WEIGHTS.numel()
    log_w = WEIGHTS.log().expand(R, N)
    idx = rs.resample(log_w, method, generator=gen)
    counts = torch.zeros(R, N, dtype=torch.float64).scatter_add_(1, idx, torch.ones_like(idx, dtype=torch.float64))
    expected = N * WEIGHTS
    se = torch.sqrt(N * WEIGHTS * (1 - WEIGHTS) / R)
    assert torch.all((counts.mean(0) - expected).abs() <= 5 * se + 1e-12)
    assert torch.all(counts[:, 2] == 0)  # a zero weight is never drawn


def test_systematic_offspring_counts_are_floor_or_ceil(gen):
    # Systematic resampling gives each particle floor(N w) or ceil(N w) offspring.
    N = 1000
    w = torch.rand(8, N, generator=gen, dtype=torch.float64)
    w = w / w.sum(-1, keepdim=True)
    idx = rs.resample(w.log(), "systematic", generator=gen)
    counts = torch.zeros_like(w).scatter_add_(1, idx, torch.ones_like(w))
    assert torch.all(counts >= torch.floor(N * w) - 1e-9)
    assert torch.all(counts <= torch.ceil(N * w) + 1e-9)


def test_resample_indices_shape_and_range(gen):
    log_w = torch.randn(3, 50, generator=gen)
    idx = rs.resample(log_w, generator=gen, num_samples=20)
    assert idx.shape == (3, 20) and idx.dtype == torch.int64
    assert int(idx.min()) >= 0 and int(idx.max()) < 50


def test_resample_same_seed_same_indices():
    log_w = torch.randn(4, 100, generator=torch.Generator().manual_seed(0))
    a = rs.resample(log_w, "stratified", generator=torch.Generator().manual_seed(7))
    b = rs.resample(log_w, "stratified", generator=torch.Generator().manual_seed(7))
    assert torch.equal(a, b)


def test_ess_values():
    n = 10
    assert torch.allclose(rs.ess(torch.zeros(2, n)), torch.full((2,), float(n)))
    one_hot = torch.full((1, n), -math.inf)
    one_hot[0, 3] = 0.0
    assert torch.allclose(rs.ess(one_hot), torch.ones(1))
    w = torch.tensor([[0.5, 0.25, 0.25]])
    assert torch.allclose(rs.ess(w.log() + 3.0), torch.tensor([1 / (0.25 + 0.0625 + 0.0625)]))


def test_normalize_survives_total_underflow():
    # Weights that are all numerically zero in linear space (the "numerically zero weights"
    # of Maroulas and Stinis) stay finite in log space.
    log_w = torch.tensor([[-1e4, -1e4 - 1.0, -1e4 - 2.0], [-math.inf] * 3])
    log_w_n, log_mean = rs.normalize(log_w)
    assert torch.isfinite(log_w_n).all()
    assert torch.allclose(log_w_n.exp().sum(-1), torch.ones(2))
    assert torch.isclose(log_mean[0], torch.logsumexp(log_w[0], 0) - math.log(3))
    assert torch.isneginf(log_mean[1])
    idx = rs.resample(log_w_n, generator=torch.Generator().manual_seed(0))
    assert int(idx.max()) < 3


def test_gather_particles():
    x = torch.arange(2 * 4 * 3).reshape(2, 4, 3)
    idx = torch.tensor([[3, 3, 0, 1], [2, 2, 2, 2]])
    out = rs.gather_particles(x, idx)
    assert torch.equal(out[0, 0], x[0, 3]) and torch.equal(out[1, 3], x[1, 2])


def test_resample_bad_input(gen):
    with pytest.raises(ValueError, match="method"):
        rs.resample(torch.zeros(1, 3), "bogus", generator=gen)
    with pytest.raises(ValueError, match="log_w has shape"):
        rs.resample(torch.zeros(3), generator=gen)
    with pytest.raises(ValueError, match="log_w has shape"):
        rs.resample(torch.zeros(0, 3), generator=gen)
    with pytest.raises(ValueError, match="generator"):
        rs.resample(torch.zeros(1, 3), generator=None)
    with pytest.raises(ValueError, match="num_samples"):
        rs.resample(torch.zeros(1, 3), generator=gen, num_samples=0)


@pytest.mark.parametrize("m", [None, 7, 1300])
def test_stratified_points_counting_equals_inverse_cdf(m, gen):
    # The one-pass counting inversion of the sorted points (j + u_j) / M gives the indices
    # of the generic searchsorted inversion (inverse_cdf), zero and dominant weights included.
    B, N = 64, 1000
    log_w = torch.randn(B, N, generator=gen) * torch.linspace(0.1, 30.0, B).unsqueeze(-1)
    log_w[torch.rand(B, N, generator=gen) < 0.3] = -math.inf
    log_w[:, 0] = 0.0
    M = N if m is None else m
    grid = torch.arange(M, dtype=torch.float64)
    u1 = torch.rand(B, 1, generator=gen, dtype=torch.float64)
    uM = torch.rand(B, M, generator=gen, dtype=torch.float64)
    c = rs.cdf(log_w)
    assert torch.equal(rs.systematic(log_w, u1, m), rs.inverse_cdf(c, (grid + u1) / M))
    assert torch.equal(rs.stratified(log_w, uM), rs.inverse_cdf(c, (grid + uM) / M))


def test_stratified_points_edge_uniforms():
    # u = 0 puts every point exactly on a cdf value: cdf_i <= p_j is right-continuous.
    zero = torch.zeros(1, 1, dtype=torch.float64)
    assert torch.equal(rs.systematic(torch.zeros(1, 4), zero), torch.tensor([[0, 1, 2, 3]]))
    log_w = torch.tensor([[0.25, 0.25, 0.5]]).log()
    assert torch.equal(rs.systematic(log_w, zero), torch.tensor([[0, 1, 2]]))
    near_one = torch.full((1, 1), 1.0 - 2.0 ** -53, dtype=torch.float64)
    assert torch.equal(rs.systematic(log_w, near_one), torch.tensor([[1, 2, 2]]))


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_normalize_ess_equals_normalize_and_ess(dtype):
    # one pass for the SIR step's three outputs: normalize's bits, ess() to round-off, and a
    # dead row (every weight -inf) uniform with ESS = N and evidence -inf, not NaN
    g = torch.Generator().manual_seed(0)
    log_w = torch.randn(6, 1000, generator=g, dtype=dtype) * 30
    log_w[1] = -math.inf
    log_w[2, :500] = -math.inf
    log_w[3] -= 1e4
    log_w_norm, log_mean, ess_ = rs.normalize_ess(log_w)
    ref_norm, ref_mean = rs.normalize(log_w)
    assert torch.equal(log_w_norm, ref_norm) and torch.equal(log_mean, ref_mean)
    torch.testing.assert_close(ess_, rs.ess(ref_norm), rtol=1e-5 if dtype == torch.float32 else 1e-12, atol=0)
    assert ess_[1] == 1000 and torch.isneginf(log_mean[1]) and bool((log_w_norm[1] == -math.log(1000)).all())
    assert bool(torch.isfinite(ess_).all()) and bool(((ess_ >= 1) & (ess_ <= 1000)).all())


@pytest.mark.parametrize("weights", ["uniform", "random", "peaked", "half-dead"])
def test_inverse_cdf_by_guide_table_equals_searchsorted(weights):
    """Many points per index (``M >= 4 N``, an MCMC segment's source draws) take the guide
    table: the same indices as ``searchsorted`` on every kind of weights, points on the bins'
    edges, 0 and the largest double below 1 included; weights piled on a few indices leave
    the points to ``searchsorted`` (the table is not used: ``_guided`` says None)."""
    from torchmcmcpf.resampling import _guided

    g = torch.Generator().manual_seed(3)
    b, n, m = 3, 500, 4000
    log_w = {"uniform": torch.zeros(b, n, dtype=torch.float64),
             "random": torch.randn(b, n, generator=g, dtype=torch.float64),
             "peaked": 8.0 * torch.randn(b, n, generator=g, dtype=torch.float64),
             "half-dead": torch.where(torch.rand(b, n, generator=g) < 0.5, 0.0, -math.inf).double()}[weights]
    c = rs.cdf(log_w)
    u = torch.rand(b, m, generator=g, dtype=torch.float64)
    u[0, :n + 1] = torch.arange(n + 1, dtype=torch.float64).clamp(max=n - 1) / n  # every bin's left edge
    u[1, :3] = torch.tensor([0.0, 1.0 - 2.0**-53, 0.5])
    u[2, :n] = c[2]  # the CDF's own entries
    want = torch.searchsorted(c, u, right=True).clamp_(max=n - 1)
    assert torch.equal(rs.inverse_cdf(c, u), want)
    u32 = u.float()
    assert torch.equal(rs.inverse_cdf(c, u32), torch.searchsorted(c, u32.double(), right=True).clamp_(max=n - 1))
    guided = _guided(c, u)
    if weights in ("uniform", "random"):
        assert guided is not None and torch.equal(guided, want)
    else:
        assert guided is None


@pytest.mark.parametrize("weights", ["uniform", "random", "peaked"])
def test_inverse_cdf_with_a_guide_made_once(weights, monkeypatch):
    """A guide table made once (:func:`guide_table`, the MCMC-PF's previous cloud) serves
    few points per index too (``M = N / 2``: a joint draw's ancestors): the indices of
    ``searchsorted``, edges and the CDF's own entries included; weights piled on a few
    indices fall back to it. ``searchsorted`` is counted, so the table is seen to serve."""
    g = torch.Generator().manual_seed(5)
    b, n, m = 3, 400, 200
    log_w = {"uniform": torch.zeros(b, n, dtype=torch.float64),
             "random": torch.randn(b, n, generator=g, dtype=torch.float64),
             "peaked": 8.0 * torch.randn(b, n, generator=g, dtype=torch.float64)}[weights]
    c = rs.cdf(log_w)
    guide = rs.guide_table(c)
    assert guide.lo.shape == (b, n + 1) and guide.padded.shape == (b, n + 1) and guide.scan.dim() == 0
    u = torch.rand(b, m, generator=g, dtype=torch.float64)
    u[0, :101] = torch.arange(101, dtype=torch.float64) / n  # bins' left edges
    u[1, :3] = torch.tensor([0.0, 1.0 - 2.0**-53, 0.5])
    u[2, :m] = c[2, :m]  # the CDF's own entries
    want = torch.searchsorted(c, u, right=True).clamp_(max=n - 1)
    calls = []
    search = torch.searchsorted
    monkeypatch.setattr(torch, "searchsorted", lambda *a, **k: calls.append(1) or search(*a, **k))
    assert torch.equal(rs.inverse_cdf(c, u, guide), want)
    assert calls == ([] if weights != "peaked" else [1])


def test_uniform_pick_equals_the_inverse_cdf_of_equal_weights(gen):
    """A pick among each row's valid entries (valid ones anywhere, rows with none, float32 and
    float64 uniforms) gives the indices the inverse CDF of equal weights on them gives, and
    every valid entry about equally often; the boundaries ``j / n`` go to the upper entry."""
    from torchmcmcpf.resampling import cdf, inverse_cdf, uniform_pick

    b, m, p = 6, 13, 20000
    mask = torch.rand(b, m, generator=gen) < 0.5
    mask[0] = False  # none valid: among all
    mask[1] = True
    mask[2, :] = False
    mask[2, 7] = True  # one valid, not first
    for dtype in (torch.float32, torch.float64):
        u = torch.rand(b, p, generator=gen, dtype=dtype)
        want = inverse_cdf(cdf(torch.where(mask | ~mask.any(-1, keepdim=True), 0.0, float("-inf"))), u)
        got = uniform_pick(mask, u)
        assert torch.equal(got, want)
    assert bool(torch.gather(mask, 1, got)[1:].all())  # valid entries only where there are any
    n = mask[3].sum()
    counts = torch.bincount(got[3], minlength=m)[mask[3]].double()
    # each count Binomial(p, 1/n): within 5 standard deviations
    assert float((counts - p / n).abs().max()) < 5 * math.sqrt(p / n * (1 - 1 / n))
    edges = torch.tensor([[0.0, 1 / 3, 2 / 3, 1 - 2**-53]], dtype=torch.float64)
    three = torch.tensor([[False, True, False, True, True]])
    assert uniform_pick(three, edges).tolist() == [[1, 3, 4, 4]]
    with pytest.raises(ValueError, match="mask must be"):
        uniform_pick(torch.zeros(3, 0, dtype=torch.bool), u[:3])
