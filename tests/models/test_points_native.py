"""The point sensor's Gaussian sums by the C loops (torchmcmcpf.models.sensors._points_native)
against the tensor path in float64: the same intensities, moves and data densities to
round-off, NaN kept, the same bits at any thread count and inside a compiled graph."""

from __future__ import annotations

import math

import pytest
import torch

from torchmcmcpf import _native
from torchmcmcpf.models.sensors import _points_native as native
from torchmcmcpf.models.sensors.points import PoissonClutterPoints, log_near_points
from torchmcmcpf.typing import PointFrame

pytestmark = pytest.mark.skipif(not _native.available(), reason="no C compiler: the tensor path runs")


def scene(seed: int, diagonal: bool = True, n: int = 60, K: int = 5, M: int = 41):
    """3 runs of ``n`` samples of ``K`` slots on a 5 km area, frames of up to ``M`` points
    (some padded), a third of the points near the first sample's slots so that terms are
    not all flushed, some slots inactive. Returns ``sensor, x (3, n, K, 4) float64, frame,
    exists``."""
    R = torch.tensor([[100.0, 0.0], [0.0, 100.0]]) if diagonal else torch.tensor([[120.0, 40.0], [40.0, 90.0]])
    sensor = PoissonClutterPoints(10.0, 4.0, ((0, 5000), (0, 5000)), R=R)
    g = torch.Generator().manual_seed(seed)
    x = torch.rand(3, n, K, 4, generator=g, dtype=torch.float64) * torch.tensor([5000.0, 10, 5000, 10])
    x[:, n // 2:] = x[:, :1] + 15 * torch.randn(3, n - n // 2, K, 4, generator=g, dtype=torch.float64)
    pts = torch.rand(3, M, 2, generator=g, dtype=torch.float64) * 5000
    near = x[:, 0, :, [0, 2]].repeat(1, M // (3 * K) + 1, 1)[:, : M // 3]
    pts[:, : M // 3] = near + 10 * torch.randn(near.shape, generator=g, dtype=torch.float64)
    mask = torch.rand(3, M, generator=g) > 0.2
    mask[2, M // 2:] = False  # a run with fewer points
    exists = torch.rand(3, n, K, generator=g) > 0.3
    return sensor, x, PointFrame(pts, mask), exists


def both(fn):
    """``fn()`` by the C loops and on tensors."""
    ours = fn()
    with _native.tensor_path():
        return ours, fn()


def test_exponential_matches_libm_and_flushes():
    """The loops' ``exp`` within 2 ulps of ``torch.exp`` (float64) on ``[-700, 709]``; exactly
    0 below ``e^-700`` and at ``-inf`` (as :func:`points._exp_`), NaN kept."""
    t = torch.cat([torch.linspace(-700, 709, 200_001, dtype=torch.float64),
                   torch.tensor([-700.0, -700.0000001, -745.0, -1e300, -math.inf, math.nan], dtype=torch.float64)])
    out = native.elementwise("exp", t)
    ref = torch.where(t < -700, 0.0, t.exp())
    finite = ref > 0
    rel = ((out - ref).abs() / ref)[finite]
    assert float(rel.max()) <= 2 * torch.finfo(torch.float64).eps
    assert torch.equal(out[~finite & ~t.isnan()], torch.zeros_like(out[~finite & ~t.isnan()]))
    assert out[-1].isnan()


def test_logarithm_matches_libm():
    """The loops' ``log`` within 2 ulps of ``torch.log`` (float64) from subnormals to the
    largest double, and libm's values at 0, negatives, inf and NaN."""
    g = torch.Generator().manual_seed(0)
    t = torch.cat([torch.exp(torch.empty(200_000, dtype=torch.float64).uniform_(-740, 709, generator=g)),
                   torch.linspace(0.5, 2.0, 100_001, dtype=torch.float64),
                   torch.tensor([5e-324, 2.2250738585072014e-308, 1.0, 1.7976931348623157e308], dtype=torch.float64)])
    ours, ref = native.elementwise("log", t), t.log()
    err = (ours - ref).abs() / ref.abs().clamp(min=torch.finfo(torch.float64).tiny)
    assert float(err[ref != 0].max()) <= 2 * torch.finfo(torch.float64).eps
    assert float((ours - ref)[ref == 0].abs().max()) <= 1e-16  # at 1: log 1 = 0 exactly, or within an ulp of 1
    special = torch.tensor([0.0, -0.0, -1.0, math.inf, -math.inf, math.nan], dtype=torch.float64)
    torch.testing.assert_close(native.elementwise("log", special), special.log(), rtol=0, atol=0, equal_nan=True)


@pytest.mark.parametrize("diagonal", [True, False])
@pytest.mark.parametrize("dtype", [torch.float64, torch.float32])
@pytest.mark.parametrize("with_exists", [True, False])
def test_intensity_and_log_likelihood_match_the_tensor_path(diagonal, dtype, with_exists):
    """The intensities (the chains' cache) to 1e-9 relative and the log-likelihood to 1e-7
    nats: the tensor path's own error (its squares expanded into a matrix product) is about
    1e-11; a slot counted twice or a point missed moves an intensity by a whole term."""
    sensor, x, z, exists = scene(1 + diagonal, diagonal)
    x, e = x.to(dtype), exists if with_exists else None
    ours, theirs = both(lambda: sensor.intensity(x, z.z.to(dtype), e))
    assert ours.dtype == torch.float64 and ours.shape == (3, 60, 41)
    torch.testing.assert_close(ours, theirs, rtol=1e-9, atol=0)
    ours, theirs = both(lambda: sensor.log_likelihood(x, z, e))
    torch.testing.assert_close(ours, theirs, rtol=0, atol=1e-7)
    assert float((ours - sensor.log_likelihood(x, z, e)).abs().max()) == 0  # deterministic


@pytest.mark.parametrize("moved", [1, 2])
@pytest.mark.parametrize("dtype", [torch.float64, torch.float32])
def test_cached_move_matches_the_tensor_path_and_two_evaluations(moved, dtype):
    """A move of one or two slots (with births and deaths) read from the cache: the delta
    against the tensor path's and against the difference of two whole log-likelihoods
    (float64) to 1e-6 nats (the tensor path's terms carry about 1e-11 of relative error, and
    a move's log-ratios reach tens of nats); the change against the difference of the two
    intensities to 1e-12 (absolute; that reference's own round-off is 1e-14). A term of the
    wrong sign or slot moves a delta by nats."""
    sensor, x, z, exists = scene(3)
    x = x.to(dtype)
    g = torch.Generator().manual_seed(4)
    B, n, K = exists.shape
    slots = torch.rand(B, n, K, generator=g).argsort(-1)[..., :moved]  # distinct slots
    x_n = x.gather(2, slots[..., None].expand(-1, -1, -1, 4)) + 20 * torch.randn(B, n, moved, 4, generator=g).to(dtype)
    e_n = torch.rand(B, n, moved, generator=g) > 0.4
    if moved == 1:
        slots, x_n, e_n = slots[..., 0], x_n[:, :, 0], e_n[..., 0]
    cache = sensor.amplitude_cache(x, exists, z)
    ours, theirs = both(lambda: sensor.log_likelihood_delta_cached(cache, x, x_n, slots, z, exists, e_n))
    torch.testing.assert_close(ours[0], theirs[0], rtol=0, atol=1e-6 if dtype == torch.float64 else 1e-4)
    idx = slots if moved > 1 else slots[..., None]
    new = (x_n if moved > 1 else x_n[:, :, None]).double()
    after = x.double().scatter(2, idx[..., None].expand(*idx.shape, 4), new)
    e_after = exists.scatter(2, idx, e_n if moved > 1 else e_n[..., None])
    with _native.tensor_path():
        exact = sensor.log_likelihood(after, z, e_after) - sensor.log_likelihood(x.double(), z, exists)
        lam = sensor.intensity(after, z.z, e_after) - sensor.intensity(x.double(), z.z, exists)
    torch.testing.assert_close(ours[0].double(), exact, rtol=0, atol=1e-6 if dtype == torch.float64 else 1e-3)
    assert float(lam.abs().max()) > 1e-4  # the moves change intensities (here up to 3.6e-3; clutter 4e-7)
    torch.testing.assert_close(ours[2], lam, rtol=0, atol=1e-12)


@pytest.mark.parametrize("diagonal", [True, False])
def test_data_density_matches_the_tensor_path(diagonal):
    """``log_near_points`` for positions near the points, far from all of them (the loop's
    second pass), off the area, in a run without points, and NaN: within 1e-9 of the tensor
    path, the same ``-inf`` and NaN."""
    sensor, x, z, _ = scene(5, diagonal)
    pts, mask = z.z, z.mask.clone()
    mask[1] = False  # a run without points: the uniform part only
    g = torch.Generator().manual_seed(6)
    near = pts[:, :13].repeat(1, 4, 1) + 10 * torch.randn(3, 52, 2, generator=g, dtype=torch.float64)
    far = torch.tensor([[-4000.0, -4000.0], [9000.0, 2500.0], [2500.0, 12000.0]], dtype=torch.float64)
    pos = torch.cat([near, far.expand(3, -1, -1), torch.full((3, 1, 2), math.nan, dtype=torch.float64)], 1)
    for p_uniform in (0.05, 0.0):
        ours, theirs = both(lambda: log_near_points(pos, pts, mask, W=sensor.W, p_uniform=p_uniform,
                                                    area=sensor.area, diagonal=diagonal))
        torch.testing.assert_close(ours, theirs, rtol=1e-9, atol=1e-9, equal_nan=True)
        # NaN where the run has points; the run without points scores the uniform part only (-inf off the area)
        assert ours[[0, 2], -1].isnan().all() and ours[1, -1] == -math.inf and bool(torch.isfinite(ours[0, :-1]).all())
    assert bool((ours[0, -4:-1] > -math.inf).all())  # far, off the area: near terms of -1e5 nats, not -inf


def test_same_bits_over_threads_and_inside_a_compiled_graph(at_threads, count_native_calls):
    """Each sample's sums are the same at 1 and 2 threads; a ``fullgraph`` compile of the
    log-likelihood calls the loop (counted) and gives eager's bits."""
    sensor, x, z, exists = scene(7, n=400)
    one, two = (at_threads(lambda: sensor.log_likelihood(x, z, exists), n) for n in (1, 2))
    assert torch.equal(one, two)
    compiled = torch.compile(lambda x, e: sensor.log_likelihood(x, z, e), fullgraph=True)
    compiled(x, exists)
    calls = count_native_calls()
    out = compiled(x, exists)
    assert "points_intensity" in calls
    assert torch.equal(out, sensor.log_likelihood(x, z, exists))


def test_gradients_take_the_tensor_path():
    """With a gradient to record the loops stand aside: the log-likelihood is differentiable
    and its value the loops' to round-off."""
    sensor, x, z, exists = scene(8, n=10)
    xg = x.clone().requires_grad_(True)
    assert not native.applies(xg) and native.applies(x)
    out = sensor.log_likelihood(xg, z, exists)
    out.sum().backward()
    assert xg.grad is not None and bool(torch.isfinite(xg.grad).all())
    torch.testing.assert_close(out.detach(), sensor.log_likelihood(x, z, exists), rtol=0, atol=1e-7)


def test_nan_state_stays_nan():
    """A NaN position gives NaN intensities, log-likelihood and move, never a silent value."""
    sensor, x, z, exists = scene(9, n=4)
    x[0, 1, 0, 0] = math.nan
    e = torch.ones_like(exists)
    lam = sensor.intensity(x, z.z, e)
    assert lam[0, 1].isnan().all() and not lam[0, 0].isnan().any()
    assert sensor.log_likelihood(x, z, e)[0, 1].isnan()
    cache = sensor.amplitude_cache(x, e, z)
    delta = sensor.log_likelihood_delta_cached(cache, x, x[:, :, 1], torch.ones(3, 4, dtype=torch.long), z, e)[0]
    assert delta[0, 1].isnan() and not delta[0, 0].isnan()
