"""The exclusion factor's change by the C loop (torchmcmcpf.models._exclusion_native) against
the tensor path: the same values to round-off, NaN kept, the floor at coincident slots."""

from __future__ import annotations

import math

import pytest
import torch

from torchmcmcpf import _native
from torchmcmcpf.models import _exclusion_native as native
from torchmcmcpf.models.multitarget import LOG_PHI_FLOOR, Exclusion

pytestmark = pytest.mark.skipif(not _native.available(), reason="no C compiler: the tensor path runs")


def both(fn):
    """``fn()`` by the C loop and on tensors."""
    ours = fn()
    with _native.tensor_path():
        return ours, fn()


def test_log_phi_matches_the_tensor_formula():
    """``log(-expm1(-x))`` within 1e-13 relative of ATen's (float64) from the floor to where
    ``phi`` rounds to 1, both branches of the series' cut at ``x = 1/2``; the floor at 0,
    0 at infinity, NaN kept."""
    ex = Exclusion(1.3)
    g = torch.Generator().manual_seed(0)
    d2 = torch.cat([torch.exp(torch.empty(200_000, dtype=torch.float64).uniform_(-60, 8, generator=g)),
                    torch.tensor([0.0, 2 * 1.3**2 * 0.5, math.inf, math.nan], dtype=torch.float64)])
    ours = native.log_phi(d2, 1 / (2 * 1.3**2), math.exp(LOG_PHI_FLOOR))
    theirs = ex.log_phi(d2)
    finite = torch.isfinite(theirs) & (theirs != 0)
    assert float(((ours - theirs).abs() / theirs.abs())[finite].max()) < 1e-13
    assert ours[-4] == LOG_PHI_FLOOR and ours[-2] == 0 and ours[-1].isnan()


@pytest.mark.parametrize("dtype", [torch.float64, torch.float32])
@pytest.mark.parametrize("shape", [(3, 40, 5, 2), (2, 7, 2, 3)])
@pytest.mark.parametrize("flags", ["both", "old", "none"])
def test_log_change_matches_the_tensor_path(dtype, shape, flags):
    """A move's change against the tensor path: 1e-12 in float64; in float32 the tensor path's
    own round-off (4 ulps of the largest term). Slots close enough to hit the floor, dead
    slots. A dropped pair or a wrong sign moves it by a whole term."""
    g = torch.Generator().manual_seed(sum(shape))
    S, K, r = shape[:-2], shape[-2], shape[-1]
    u = (torch.randn(*shape, generator=g, dtype=torch.float64) * 1.5).to(dtype)
    u[0, 0, 1] = u[0, 0, 0]  # coincident: the floor
    u_n = (torch.randn(*S, r, generator=g, dtype=torch.float64) * 1.5).to(dtype)
    n = torch.randint(0, K, S, generator=g)
    alive = torch.rand(*S, K, generator=g) > 0.3 if flags != "none" else None
    alive_n = torch.rand(*S, generator=g) > 0.3 if flags == "both" else None
    ex = Exclusion(0.8)
    ours, theirs = both(lambda: ex.log_change(u, u_n, n, alive, alive_n))
    assert ours.dtype == dtype and ours.shape == S
    assert float(theirs.abs().max()) > 0.5  # the moves change the factor
    atol = 1e-12 if dtype == torch.float64 else 4 * torch.finfo(dtype).eps * float(theirs.abs().max())
    torch.testing.assert_close(ours, theirs, rtol=0, atol=atol)


@pytest.mark.parametrize("dtype", [torch.float64, torch.float32])
@pytest.mark.parametrize("shape", [(3, 40, 5, 2), (2, 7, 2, 3), (4, 3, 2)])
@pytest.mark.parametrize("with_flags", [True, False])
def test_log_factor_matches_the_tensor_path(dtype, shape, with_flags):
    """A state's whole factor (the joint draws'): against the tensor path, 1e-12 in float64,
    its round-off in float32, with coincident slots at the floor and dead slots."""
    g = torch.Generator().manual_seed(sum(shape) + 7)
    u = (torch.randn(*shape, generator=g, dtype=torch.float64) * 1.5).to(dtype)
    u[..., 1, :] = torch.where(torch.rand(shape[:-2] + (1,), generator=g) < 0.2, u[..., 0, :], u[..., 1, :])
    alive = torch.rand(shape[:-1], generator=g) > 0.3 if with_flags else None
    ex = Exclusion(0.8)
    ours, theirs = both(lambda: ex.log_factor(u, alive))
    assert ours.dtype == dtype and ours.shape == shape[:-2]
    assert float(theirs.abs().max()) > 0.5
    atol = 1e-12 if dtype == torch.float64 else 4 * torch.finfo(dtype).eps * float(theirs.abs().max())
    torch.testing.assert_close(ours, theirs, rtol=0, atol=atol)


def test_same_bits_threads_compiled_and_gradients(at_threads, count_native_calls):
    """The same bits at 1 and 2 threads and inside a ``fullgraph`` compile (the loop called);
    with a gradient to record the tensor path runs (the loop stands aside); NaN kept."""
    g = torch.Generator().manual_seed(5)
    u = torch.randn(4, 300, 4, 2, generator=g, dtype=torch.float64)
    u_n = torch.randn(4, 300, 2, generator=g, dtype=torch.float64)
    n = torch.randint(0, 4, (4, 300), generator=g)
    ex = Exclusion()
    one, two = (at_threads(lambda: ex.log_change(u, u_n, n), k) for k in (1, 2))
    assert torch.equal(one, two)
    compiled = torch.compile(lambda u, u_n: ex.log_change(u, u_n, n), fullgraph=True)
    compiled(u, u_n)
    calls = count_native_calls()
    assert torch.equal(compiled(u, u_n), one) and "exclusion_change" in calls
    ug = u.clone().requires_grad_(True)
    out = ex.log_change(ug, u_n, n)
    out.sum().backward()
    assert ug.grad is not None and bool(torch.isfinite(ug.grad).all())
    torch.testing.assert_close(out.detach(), one, rtol=0, atol=1e-12)
    u[1, 2, 0, 0] = math.nan
    bad = ex.log_change(u, u_n, n)
    assert bad[1, 2].isnan() and not bad[0].isnan().any()


@pytest.mark.parametrize("k", [2, 5, 10])
@pytest.mark.parametrize("with_flags", [True, False])
def test_blocked_sums_are_the_one_at_a_time_sums_to_the_bit(k, with_flags):
    """The loops gather a block of samples' live pairs, take ``log phi`` of them all at once and
    sum each sample's in order: over several blocks (1,500 samples), with dead slots, close and
    coincident pairs (the series) and NaN, the sums are those of the loops' ``log phi``
    (``native.log_phi``) of one pair at a time, added pair by pair in order, bit for bit. The coordinates are
    multiples of 1/64, so every squared distance is exact however the loop adds it."""
    g = torch.Generator().manual_seed(4)
    n, r, inv2s2, xmin = 1500, 2, 0.5, math.exp(LOG_PHI_FLOOR)
    u = torch.randint(0, 384, (n, k, r), generator=g).double() / 64.0
    u[::7, 1] = u[::7, 0] + 0.125  # pairs within the series' range
    u[::11, 1] = u[::11, 0]      # coincident
    u[5, 0, 0] = math.nan
    alive = (torch.rand(n, k, generator=g) < 0.6) if with_flags else torch.ones(n, k, dtype=torch.bool)
    slot = torch.randint(0, k, (n,), generator=g)
    u_n = torch.randint(0, 384, (n, r), generator=g).double() / 64.0
    alive_n = torch.rand(n, generator=g) < 0.5

    def lphi(a, b):
        return native.log_phi((a - b).square().sum(-1, keepdim=True), inv2s2, xmin)[..., 0]

    want_f, want_c = torch.zeros(n, dtype=torch.float64), torch.zeros(n, dtype=torch.float64)
    for i in range(n):  # the reference: one sample, one pair at a time
        for a in range(k):
            for b in range(a + 1, k):
                if alive[i, a] and alive[i, b]:
                    want_f[i] += lphi(u[i, a], u[i, b])
            if a != slot[i] and alive[i, a]:
                new = lphi(u_n[i], u[i, a]) if alive_n[i] else 0.0
                old = lphi(u[i, slot[i]], u[i, a]) if alive[i, slot[i]] else 0.0
                want_c[i] += new - old
    flags = alive.to(torch.uint8) if with_flags else None
    got_f = native.factor(u, flags, inv2s2, xmin)
    got_c = native.change(u, u_n, slot, alive.to(torch.uint8), alive_n.to(torch.uint8), inv2s2, xmin)
    same = lambda x, y: bool(((x == y) | (x.isnan() & y.isnan())).all())  # noqa: E731
    assert same(got_f, want_f) and same(got_c, want_c)
