"""Point measurements in Poisson clutter (paper 001, DESIGN.md association-free likelihood)."""

import math

import pytest
import torch

from torchmcmcpf import _native, runtime
from torchmcmcpf.models.base import SensorModel
from torchmcmcpf.models.sensors.points import PointFrame, PoissonClutterPoints, gauss_exponents

AREA = ((0.0, 200.0), (-50.0, 50.0))  # V = 2e4


def sensor(**kw):
    kw = {"noise_std": 3.0, **kw}
    return PoissonClutterPoints(kw.pop("clutter_rate", 5.0), kw.pop("detection_rate", 2.0), AREA, **kw).double()


def brute_force(s, x, z, exists):
    """The formula term by term for one state (K, D) and one set of points (M, 2)."""
    R = s.R
    norm = 1 / (2 * math.pi * torch.linalg.det(R).sqrt())
    total = -(s.clutter_rate + s.detection_rate * float(exists.sum()))
    for zm in z:
        lam = s.clutter_rate / s.volume
        for xn, en in zip(x, exists):
            if en:
                r = zm - torch.stack([xn[0], xn[2]])
                lam = lam + s.detection_rate * norm * torch.exp(-0.5 * r @ torch.linalg.solve(R, r))
        total = total + torch.log(torch.as_tensor(lam, dtype=torch.float64))
    return total


def test_likelihood_matches_the_formula(gen):
    s = sensor(R=torch.tensor([[9.0, 2.0], [2.0, 4.0]], dtype=torch.float64), noise_std=None)
    x = torch.randn(2, 3, 4, 4, generator=gen, dtype=torch.float64) * 20 + torch.tensor([100.0, 0, 0, 0])
    exists = torch.rand(2, 3, 4, generator=gen) < 0.6
    z = torch.randn(2, 5, 2, generator=gen, dtype=torch.float64) * 20 + torch.tensor([100.0, 0])
    ll = s.log_likelihood(x, PointFrame(z, torch.ones(2, 5, dtype=torch.bool)), exists)
    assert ll.shape == (2, 3)
    ref = torch.stack([torch.stack([brute_force(s, x[b, n], z[b], exists[b, n]) for n in range(3)]) for b in range(2)])
    assert torch.allclose(ll, ref, rtol=1e-10, atol=1e-10)
    # no exists: every slot live; a plain tensor frame: every point valid
    assert torch.allclose(s.log_likelihood(x, z), s.log_likelihood(x, z, torch.ones_like(exists)))


def test_intensity_op_and_the_likelihood_without_clutter(gen):
    """The intensity's compiled-code op (fake tensor, autograd) gives the eager bits; without
    clutter the likelihood is the formula by a ``logsumexp`` over the slots (a point far from
    every live slot gives ``-inf``, not NaN).
    """
    from torchmcmcpf.models.sensors.points import _intensity, _intensity_eager

    terms = torch.randn(3, 4, 5, generator=gen, dtype=torch.float64) * 300 - 400
    alive = torch.rand(3, 4, generator=gen) < 0.6
    terms = torch.where(alive.unsqueeze(-1), terms, -math.inf)  # an inactive slot's terms, as the sensor makes them
    torch.library.opcheck(_intensity, (terms.clone().requires_grad_(), 0.01))
    assert torch.equal(_intensity(terms, 0.01), _intensity_eager(terms.clone(), 0.01, in_place=True))
    s = sensor(clutter_rate=0.0)
    x = torch.randn(2, 3, 4, 4, generator=gen, dtype=torch.float64) * 20 + torch.tensor([100.0, 0, 0, 0])
    exists = torch.ones(2, 3, 4, dtype=torch.bool)
    z = torch.randn(2, 5, 2, generator=gen, dtype=torch.float64) * 20 + torch.tensor([100.0, 0])
    ll = s.log_likelihood(x, z, exists)
    ref = torch.stack([torch.stack([brute_force(s, x[b, n], z[b], exists[b, n]) for n in range(3)]) for b in range(2)])
    assert torch.allclose(ll, ref, rtol=1e-10, atol=1e-10)
    assert s.log_likelihood(x, z, torch.zeros_like(exists)).eq(-math.inf).all()


def test_padding_with_mask_changes_nothing(gen):
    s = sensor()
    x = torch.rand(3, 6, 2, 4, generator=gen, dtype=torch.float64) * 100
    exists = torch.rand(3, 6, 2, generator=gen) < 0.5
    z = torch.rand(3, 4, 2, generator=gen, dtype=torch.float64) * 100
    pad = torch.cat([z, torch.randn(3, 3, 2, generator=gen, dtype=torch.float64) * 1e3], 1)
    mask = torch.cat([torch.ones(3, 4, dtype=torch.bool), torch.zeros(3, 3, dtype=torch.bool)], 1)
    perm = torch.randperm(7, generator=gen)
    a = s.log_likelihood(x, z, exists)
    b = s.log_likelihood(x, PointFrame(pad[:, perm], mask[:, perm]), exists)
    assert torch.allclose(a, b, rtol=1e-12, atol=1e-12)
    # a run with no valid point at all: -(L_C + L_x n)
    empty = s.log_likelihood(x, PointFrame(pad, torch.zeros(3, 7, dtype=torch.bool)), exists)
    assert torch.allclose(empty, -(5.0 + 2.0 * exists.double().sum(-1)))


def test_trim_frame_drops_the_padding_no_run_uses(gen):
    """A batch's frame loses the trailing columns that no run's mask marks (one past the last
    valid point anywhere); a column valid in one run stays, and a frame with nothing to drop,
    or without a mask, is returned as is.
    """
    s = sensor()
    pts = torch.rand(3, 7, 2, generator=gen, dtype=torch.float64) * 100
    mask = torch.zeros(3, 7, dtype=torch.bool)
    mask[0, :2], mask[1, 4], mask[2, :1] = True, True, True  # last valid column anywhere: 4
    trimmed = s.trim_frame(PointFrame(pts, mask))
    assert torch.equal(trimmed.z, pts[:, :5]) and torch.equal(trimmed.mask, mask[:, :5])
    x = torch.rand(3, 6, 2, 4, generator=gen, dtype=torch.float64) * 100
    exists = torch.rand(3, 6, 2, generator=gen) < 0.5
    assert torch.allclose(s.log_likelihood(x, trimmed, exists), s.log_likelihood(x, PointFrame(pts, mask), exists),
                          rtol=1e-13, atol=1e-13)
    full = PointFrame(pts, mask | (torch.arange(7) == 6))
    assert s.trim_frame(full) is full and s.trim_frame(pts) is pts
    none = s.trim_frame(PointFrame(pts, torch.zeros_like(mask)))  # no point at all: one masked column left
    assert none.z.shape == (3, 1, 2) and not none.mask.any()
    for frame in (none, PointFrame(pts[:, :0], mask[:, :0])):  # and a frame of no column at all
        assert torch.allclose(s.log_likelihood(x, frame, exists), -(5.0 + 2.0 * exists.double().sum(-1)))


def test_likelihood_is_differentiable(gen):
    s = sensor()
    x = (torch.rand(1, 2, 2, 4, generator=gen, dtype=torch.float64) * 50 + 20).requires_grad_()
    z = PointFrame(x.detach()[0, 0, :, [0, 2]].unsqueeze(0) + 1.0, torch.ones(1, 2, dtype=torch.bool))
    assert torch.autograd.gradcheck(lambda v: s.log_likelihood(v, z), (x,))


def test_simulate_counts_and_positions(gen):
    s = sensor(clutter_rate=3.0, detection_rate=4.0, noise_std=1.0)
    b = 4000
    x = torch.tensor([[50.0, 0, 10, 0], [150.0, 0, -20, 0]], dtype=torch.float64).expand(b, 2, 4)
    exists = torch.tensor([True, False]).expand(b, 2)
    frame = s.simulate(x, exists=exists, generator=gen)
    z, mask = frame
    assert z.shape[:2] == mask.shape and z.shape[-1] == 2 and mask.dtype == torch.bool
    assert torch.equal(z[~mask], torch.zeros_like(z[~mask]))
    # Poisson(3 + 4) points per frame: mean 7, variance 7; 5 standard errors
    count = mask.sum(-1).double()
    assert abs(count.mean().item() - 7.0) < 5 * math.sqrt(7.0 / b)
    assert abs(count.var().item() - 7.0) < 5 * 7.0 * math.sqrt(2.0 / b) + 0.5
    pts = z[mask]
    near_live = (pts - torch.tensor([50.0, 10.0], dtype=torch.float64)).norm(dim=-1) < 5
    # points within 5 sd of the live target: its 4 per frame (+ clutter there, 3 * 25 pi / 2e4)
    expected = (4.0 + 3.0 * 25 * math.pi / 2e4) / 7.0
    assert abs(near_live.double().mean().item() - expected) < 5 * math.sqrt(expected * (1 - expected) / len(pts))
    near_dead = (pts - torch.tensor([150.0, -20.0], dtype=torch.float64)).norm(dim=-1) < 5
    assert near_dead.double().mean().item() < 0.01
    # same seed, same frame
    f1 = s.simulate(x[:5], exists=exists[:5], generator=torch.Generator().manual_seed(3))
    f2 = s.simulate(x[:5], exists=exists[:5], generator=torch.Generator().manual_seed(3))
    assert torch.equal(f1.z, f2.z) and torch.equal(f1.mask, f2.mask)


def test_validate_rejects_bad_input():
    s = sensor()
    z = torch.zeros(2, 3, 2)
    good = PointFrame(z, torch.ones(2, 3, dtype=torch.bool))
    assert s.validate(good, 2) is good
    with pytest.raises(ValueError, match="mask"):
        s.validate(PointFrame(z, torch.ones(2, 4, dtype=torch.bool)), 2)
    with pytest.raises(ValueError, match="mask"):
        s.validate(PointFrame(z, torch.ones(2, 3)), 2)
    bad = z.clone()
    bad[1, 2, 0] = float("nan")
    with pytest.raises(ValueError, match="NaN"):
        s.validate(PointFrame(bad, torch.ones(2, 3, dtype=torch.bool)), 2)
    with pytest.raises(ValueError, match="batch size"):
        s.validate(good, 3)
    with pytest.raises(ValueError, match=r"\(\*, \*, 2\)"):
        s.validate(torch.zeros(2, 3, 3), 2)


@pytest.mark.parametrize("kw, match", [
    (dict(clutter_rate=-1.0), "clutter_rate"), (dict(detection_rate=-0.5), "detection_rate"),
    (dict(noise_std=-1.0), "noise_std"), (dict(noise_std=None, R=torch.tensor([[1.0, 2.0], [2.0, 1.0]])), "R"),
])
def test_bad_settings_raise(kw, match):
    with pytest.raises(ValueError, match=match):
        sensor(**kw)


# ----------------------------------------------------------------------------- the chains' intensity cache
def test_intensity_cache_delta_and_updates_follow_the_chains(gen, monkeypatch):
    """The cached one- and two-slot ratios equal the difference of two full evaluations, and
    adding the accepted moves' changes keeps the cache equal to one made afresh (float64)."""
    s = sensor()
    b, c, k = 2, 6, 4
    x = torch.randn(b, c, k, 4, generator=gen, dtype=torch.float64) * 20 + torch.tensor([100.0, 0, 0, 0])
    exists = torch.rand(b, c, k, generator=gen) < 0.6
    pts = torch.randn(b, 7, 2, generator=gen, dtype=torch.float64) * 20 + torch.tensor([100.0, 0])
    pts[:, 0] = x[:, 0, 0, [0, 2]]  # a point on a slot: its term dominates the clutter there
    z = PointFrame(pts, torch.arange(7).expand(b, 7) < torch.tensor([[7], [5]]))  # run 1 has padding
    cache = s.amplitude_cache(x, exists, z)
    assert cache.shape == (b, c, 7) and cache.dtype == torch.float64
    for moved in (1, 2):
        for _ in range(4):
            slot = torch.stack([torch.randperm(k, generator=gen)[:moved] for _ in range(b * c)]).reshape(b, c, moved)
            x_n = torch.randn(b, c, moved, 4, generator=gen, dtype=torch.float64) * 20 + torch.tensor([100.0, 0, 0, 0])
            e_n = torch.rand(b, c, moved, generator=gen) < 0.5
            delta, cells, change = s.log_likelihood_delta_cached(cache, x, x_n, slot, z, exists, e_n)
            here = torch.nn.functional.one_hot(slot, k).sum(-2).bool()  # (B, C, K)
            x_new, e_new = x.clone(), exists.clone()
            x_new.scatter_(2, slot.unsqueeze(-1).expand(-1, -1, -1, 4), x_n)
            e_new.scatter_(2, slot, e_n)
            ref = s.log_likelihood(x_new, z, e_new) - s.log_likelihood(x, z, exists)
            torch.testing.assert_close(delta, ref, rtol=1e-9, atol=1e-9)
            assert bool(here.any())
            accepted = torch.rand(b, c, generator=gen) < 0.5
            # every entry in order (cells None): the bits of the scatter-add through an index
            # naming each entry, eager (accepted rows only) and compiled-style (every row)
            assert cells is None and change.shape == cache.shape
            every = torch.arange(cache.numel()).reshape(cache.shape)
            generic = SensorModel.update_amplitude_cache(cache.clone(), every, change, accepted)
            with monkeypatch.context() as m:
                m.setattr(runtime, "host_reads", lambda t: False)
                dense = s.update_amplitude_cache(cache.clone(), None, change, accepted)
            assert s.update_amplitude_cache(cache, None, change, accepted) is cache
            assert torch.equal(cache, generic) and torch.equal(cache, dense)
            keep = accepted[..., None, None]
            x = torch.where(keep, x_new, x)
            exists = torch.where(accepted[..., None], e_new, exists)
            torch.testing.assert_close(cache, s.amplitude_cache(x, exists, z), rtol=1e-12, atol=1e-15)
    # one slot given as (B, C, D) with n (B, C)
    d1, _, _ = s.log_likelihood_delta_cached(cache, x, x_n[:, :, 0], slot[:, :, 0], z, exists, e_n[:, :, 0])
    torch.testing.assert_close(d1, s.log_likelihood_delta(x, x_n[:, :, 0], slot[:, :, 0], z, exists, e_n[:, :, 0]))


def test_intensity_cache_needs_the_frame_and_clutter(gen):
    x = torch.zeros(1, 2, 3, 4, dtype=torch.float64)
    z = torch.zeros(1, 4, 2, dtype=torch.float64)
    with pytest.raises(ValueError, match="z is required"):
        sensor().amplitude_cache(x)
    assert sensor(clutter_rate=0.0).amplitude_cache(x, z=z) is None  # an intensity may be 0: no cache
    with pytest.raises(ValueError, match="cache has shape"):
        slot = torch.zeros(1, 2, dtype=torch.int64)
        sensor().log_likelihood_delta_cached(torch.zeros(1, 2, 3), x, x[:, :, 0], slot, z)


def test_data_draws_score_only_where_asked(gen):
    """``scored`` leaves the draws as they are and gives the same ratio where it is True, 0
    elsewhere (the relocation noise scores the draws a proposal can read)."""
    s = sensor()
    pts = torch.randn(3, 6, 2, generator=gen, dtype=torch.float64) * 20 + torch.tensor([100.0, 0])
    z = PointFrame(pts, torch.arange(6).expand(3, 6) < torch.tensor([[6], [2], [0]]))  # run 2 has no point
    scored = torch.rand(3, 5, 4, generator=gen) < 0.3
    full = s.sample_from_data(z, (3, 5, 4), generator=torch.Generator().manual_seed(1), dtype=torch.float64)
    part = s.sample_from_data(z, (3, 5, 4), generator=torch.Generator().manual_seed(1), dtype=torch.float64,
                              scored=scored)
    assert torch.equal(full[0], part[0])
    assert torch.equal(part[1] == 0, ~scored | (full[1] == 0))
    # the same ratios to round-off: the Gaussians' exponents are one matrix product
    # (points.gauss_exponents), whose rounding follows the shape BLAS is given
    torch.testing.assert_close(part[1], torch.where(scored, full[1], 0.0), rtol=1e-13, atol=1e-13)
    none = s.sample_from_data(z, (3, 5, 4), generator=torch.Generator().manual_seed(1), dtype=torch.float64,
                              scored=torch.zeros(3, 5, 4, dtype=torch.bool))
    assert torch.equal(none[0], full[0]) and not none[1].any()  # nothing to score: no sum at all


def test_flushed_exp_and_logsumexp(gen):
    """``_exp_`` is ``exp`` where it exceeds ``e^FLUSH`` and exactly 0 elsewhere (``-inf``
    included), NaN and ``+inf`` kept, bit for bit, in place, on a fresh tensor and
    differentiable (``_exp``); ``_logsumexp_fast`` equals ``torch.logsumexp`` to half an ulp;
    the likelihood's in-place path equals its autograd path bit for bit.
    """
    from torchmcmcpf.models.sensors.points import FLUSH, _exp, _exp_, _logsumexp_fast

    t = torch.cat([torch.randn(4000, generator=gen, dtype=torch.float64) * 500 - 700,
                   torch.tensor([FLUSH, FLUSH + 1e-9, FLUSH - 1e-9, -720.0, -745.2, -1e308, -math.inf, math.inf,
                                 math.nan, 0.0], dtype=torch.float64)])
    plain = t.exp()
    expected = torch.where(plain > math.exp(FLUSH) * (1 + 1e-15), plain, 0.0)  # NaN > x is False: NaN kept below
    expected[t.isnan()] = math.nan
    assert (expected[:4000] == 0).any() and (expected[:4000] > 0).any()  # both sides of the flush
    kept = t.clone()
    for got in (_exp_(t.clone()), _exp_(kept, fresh=True), _exp(t)):
        assert torch.equal(got.nan_to_num(7.0), expected.nan_to_num(7.0))
    assert torch.equal(kept.nan_to_num(7.0), t.nan_to_num(7.0))  # fresh: untouched
    v = t[:4000].reshape(40, 5, 20).clone()
    v[0, :, 0] = -math.inf  # a column without any finite term
    v[1, 2, 3] = math.nan
    torch.testing.assert_close(_logsumexp_fast(v, -2), torch.logsumexp(v, -2), rtol=2.0**-53, atol=0.0,
                               equal_nan=True)
    s = sensor()
    x = torch.randn(2, 30, 4, 4, generator=gen, dtype=torch.float64) * 60 + torch.tensor([100.0, 0, 0, 0])
    exists = torch.rand(2, 30, 4, generator=gen) < 0.6
    z = PointFrame(torch.randn(2, 9, 2, generator=gen, dtype=torch.float64) * 60 + torch.tensor([100.0, 0]),
                   torch.rand(2, 9, generator=gen) < 0.8)
    for e in (exists, None):
        with _native.tensor_path():  # (the C loops, which serve the untracked call, to round-off: test_points_native)
            plain = s.log_likelihood(x, z, e)
        tracked = s.log_likelihood(x.clone().requires_grad_(True), z, e).detach()
        assert torch.equal(plain, tracked)


def test_flushed_exp_in_single_precision(gen):
    """In float32 ``_exp_`` flushes below ``e^FLUSH_SINGLE`` (``-80``: float32's ``exp`` takes
    its slow path below about ``-87.3``, where float64's ``-700`` would leave it), is ``exp``
    above, bit for bit, and the float32 point likelihood matches the float64 one to float32's
    rounding.
    """
    from torchmcmcpf.models.sensors.points import FLUSH, FLUSH_SINGLE, _exp, _exp_, flush_level

    assert flush_level(torch.float64)[0] == FLUSH and flush_level(torch.float32)[0] == FLUSH_SINGLE
    assert -87.3 < FLUSH_SINGLE and flush_level(torch.float32)[1] > torch.finfo(torch.float32).tiny
    t = torch.cat([torch.randn(4000, generator=gen) * 60 - 80,
                   torch.tensor([FLUSH_SINGLE, -79.99, -80.01, -88.0, -104.0, -math.inf, math.inf, math.nan, 0.0])])
    plain = t.exp()
    expected = torch.where(t > FLUSH_SINGLE, plain, 0.0)
    expected[t.isnan()] = math.nan
    assert (expected[:4000] == 0).any() and (expected[:4000] > 0).any()
    assert (plain[(t > -87.0) & (t <= FLUSH_SINGLE)] > 0).any()  # a flushed term that plain exp keeps
    for got in (_exp_(t.clone()), _exp_(t.clone(), fresh=True), _exp(t)):
        assert got.dtype == torch.float32
        assert torch.equal(got.nan_to_num(7.0), expected.nan_to_num(7.0))
    s64 = sensor()
    x = torch.randn(2, 30, 4, 4, generator=gen, dtype=torch.float64) * 60 + torch.tensor([100.0, 0, 0, 0])
    exists = torch.rand(2, 30, 4, generator=gen) < 0.6
    z = PointFrame(torch.randn(2, 9, 2, generator=gen, dtype=torch.float64) * 60 + torch.tensor([100.0, 0]),
                   torch.rand(2, 9, generator=gen) < 0.8)
    want = s64.log_likelihood(x, z, exists)
    got = s64.to(dtype=torch.float32).log_likelihood(x.float(), PointFrame(z.z.float(), z.mask), exists)
    assert got.dtype == torch.float32
    torch.testing.assert_close(got.double(), want, rtol=1e-5, atol=1e-4)


def test_diagonal_whitening_equals_the_matrix_product(gen):
    """With a diagonal ``R`` the whitening, the resolution coordinates and the data draws take a
    product per axis: the same bits as the matrix products they replace."""
    from torchmcmcpf.models.sensors.points import _whiten

    s = sensor(noise_std=7.0)
    assert s.diagonal and not sensor(R=torch.tensor([[9.0, 2.0], [2.0, 4.0]], dtype=torch.float64),
                                     noise_std=None).diagonal
    v = torch.randn(5000, 2, generator=gen, dtype=torch.float64) * torch.tensor([1e-3, 1e4], dtype=torch.float64)
    v[0] = 0.0
    assert torch.equal(_whiten(v, s.W, True), v @ s.W.mT)
    L = torch.linalg.cholesky(s.R)
    assert torch.equal(_whiten(v, L, True), v @ L.mT)


# ----------------------------------------------------------------------------- the exponents as a product
@pytest.mark.parametrize("dtype", [torch.float64, torch.float32])
@pytest.mark.parametrize("diagonal", [True, False])
def test_gauss_exponents_match_the_differences(gen, dtype, diagonal):
    """``gauss_exponents`` (one matrix product of centred, whitened coordinates) equals
    ``const - 0.5 |W (h - z)|^2`` taken as differences, in float64 whatever the positions'
    dtype, on the births/deaths scene's scale (a 5 km square, 10 m noise; exponents down to
    -1e5), to 8 ulp of the largest centred ``|W (h - c)|^2`` (about ``1.25e5`` here; the
    expansion cancels it), with ``-inf`` where ``const`` or the mask says so."""
    area = torch.tensor([[0.0, 5000.0], [0.0, 5000.0]], dtype=torch.float64)
    R = torch.tensor([[100.0, 0.0], [0.0, 100.0]] if diagonal else [[100.0, 30.0], [30.0, 64.0]], dtype=torch.float64)
    W = torch.linalg.inv(torch.linalg.cholesky(R))
    h = (torch.rand(3, 7, 5, 2, generator=gen, dtype=torch.float64) * 5000).to(dtype)
    pts = torch.rand(3, 9, 2, generator=gen, dtype=torch.float64) * 5000
    pts[:, 0] = h[:, 0, 0].double() + 3.0  # a point near a position
    const = torch.randn(3, 7, 5, generator=gen, dtype=torch.float64)
    const[0, 0, 1] = -math.inf
    mask = torch.rand(3, 9, generator=gen) < 0.8
    out = gauss_exponents(h[..., 0], h[..., 1], pts, W=W, diagonal=diagonal, centre=area.mean(-1), const=const,
                          mask=mask)
    assert out.shape == (3, 7, 5, 9) and out.dtype == torch.float64
    r = (h.double().unsqueeze(-2) - pts.reshape(3, 1, 1, 9, 2)) @ W.mT
    ref = const.unsqueeze(-1) - 0.5 * r.square().sum(-1)
    ref = torch.where(mask.reshape(3, 1, 1, 9), ref, -math.inf)
    assert torch.equal(torch.isinf(out), torch.isinf(ref))
    finite = torch.isfinite(ref)
    assert ref[finite].min() < -1e4  # far pairs in the check, and a near one
    assert (ref[finite] > -10).any()
    centred = torch.cat([h.double().reshape(-1, 2), pts.reshape(-1, 2)]) - area.mean(-1)
    bound = 8 * torch.finfo(torch.float64).eps * float((centred @ W.mT).square().sum(-1).max())
    assert bound < 1e-9
    torch.testing.assert_close(out[finite], ref[finite], rtol=0.0, atol=bound)
