"""The radar's windowed likelihood by the C loop (torchmcmcpf.models.sensors.grid.native)
against the tensor path: the same sum to float32 round-off, checked against float64."""

from __future__ import annotations

import math
import os
import subprocess
import sys
import textwrap

import pytest
import torch

from torchmcmcpf.models.sensors.grid import native
from torchmcmcpf.models.sensors.radar import RangeDopplerBearingTBD

DEG = math.pi / 180

pytestmark = pytest.mark.skipif(not native.available(), reason="no C compiler: the tensor path runs")


@pytest.fixture
def tensor_path():
    """Within the test, the windowed path runs on tensors (as without a compiler)."""
    def run(fn, *args):
        with native.tensor_path():
            return fn(*args)
    return run


def crowded(K: int, n: int, seed: int, edge: bool = False):
    """A small grid (12 x 9 x 10 cells: boxes overlap and reach its edges), ``K`` targets in
    a cluster (or straddling the grid's edges), 2 runs of ``n`` particles with some slots
    dead, frames simulated from each run's truth. Returns ``sensor, x (2, n, K, 5), z,
    exists``."""
    sensor = RangeDopplerBearingTBD.uniform((2740, 2850), (-8, 8), (-5 * DEG, 4 * DEG))
    g = torch.Generator().manual_seed(seed)
    lo = torch.tensor([2700.0 if edge else 2770.0, -12.0 if edge else -4.0, (-8 if edge else -2) * DEG])
    hi = torch.tensor([2890.0 if edge else 2820.0, 12.0 if edge else 4.0, (7 if edge else 2) * DEG])
    rdb = lo + (hi - lo) * torch.rand(2, K, 3, generator=g, dtype=torch.float64)
    r, d, b = rdb.unbind(-1)
    rho = 2.0 + 4.0 * torch.rand(2, K, generator=g, dtype=torch.float64)
    truth = torch.stack([r * torch.cos(b), d * torch.cos(b), r * torch.sin(b), d * torch.sin(b), rho], -1)
    z = sensor.simulate(truth.float(), generator=g)
    spread = torch.tensor([8.0, 1.5, 8.0, 1.5, 0.5], dtype=torch.float64)
    x = truth[:, None] + spread * torch.randn(2, n, K, 5, generator=g, dtype=torch.float64)
    exists = torch.rand(2, n, K, generator=g) > 0.2
    return sensor, x, z, exists


@pytest.mark.parametrize("K, edge", [(1, False), (3, False), (10, False), (6, True)])
@pytest.mark.parametrize("with_exists", [False, True])
def test_native_matches_the_tensor_path_to_float32_round_off(K, edge, with_exists, tensor_path):
    """Both float32 paths against the float64 tensor path (the exact ``log I0``): the C loop's
    error is at most twice the tensor path's plus 1e-3 nats. The check can fail: a cell of
    the union counted twice or missed, or a neighbour's spread misplaced, moves a sum by the
    cell's ratio, up to tens of nats here."""
    sensor, x, z, exists = crowded(K, 400, seed=K + 10 * edge)
    e = exists if with_exists else None
    assert native.applies(sensor, x.float())
    ours = sensor.log_likelihood(x.float(), z, e)
    theirs = tensor_path(sensor.log_likelihood, x.float(), z, e)
    exact = sensor.log_likelihood(x, z.double(), e)
    assert ours.dtype == torch.float32 and ours.shape == (2, 400)
    err_ours = (ours.double() - exact).abs().max().item()
    err_theirs = (theirs.double() - exact).abs().max().item()
    assert err_ours <= 2 * err_theirs + 1e-3, (err_ours, err_theirs)
    assert exact.abs().max() > 10  # the sums are not trivially small


def test_native_equals_itself_over_threads_and_runs_compiled(at_threads, count_native_calls):
    """Each particle's sum is one thread's: the same bits at one and two threads. Through
    ``torch.compile`` (``fullgraph``: a custom op, no graph break) the loop runs too, on
    coordinates Inductor computed: its ``atan2`` may differ in the last bit, and a box whose
    target sits on a cell boundary then starts one cell over (the truncated tails differ:
    up to 4e-3 nats measured on 5 of these 6,000 sums)."""
    sensor, x, z, exists = crowded(5, 3000, seed=3)
    x = x.float()
    one, two = (at_threads(lambda: sensor.log_likelihood(x, z, exists), n) for n in (1, 2))
    assert torch.equal(one, two)
    compiled = torch.compile(lambda x, z, e: sensor.log_likelihood(x, z, e), fullgraph=True)
    compiled(x, z, exists)  # compiled with the real library in place
    calls = count_native_calls()
    out = compiled(x, z, exists)
    assert calls  # the C loop ran inside the compiled graph
    torch.testing.assert_close(out, one, rtol=1e-4, atol=2e-2)


def test_non_finite_inputs_give_nan_not_a_stray_read():
    """A NaN doppler puts the slot's box at the grid's edge (no read outside the frame) and
    makes the particle's sum NaN; so does a NaN amplitude. The other particles are unchanged."""
    sensor, x, z, _ = crowded(3, 8, seed=4)
    x = x.float()
    clean = sensor.log_likelihood(x, z)
    x[0, 2, 1, 1] = float("nan")
    x[1, 5, 0, 4] = float("nan")
    out = sensor.log_likelihood(x, z)
    assert torch.isnan(out[0, 2]) and torch.isnan(out[1, 5])
    mask = torch.ones_like(out, dtype=torch.bool)
    mask[0, 2] = mask[1, 5] = False
    assert torch.equal(out[mask], clean[mask])


def test_the_tensor_path_serves_what_the_loop_does_not():
    """float64, a gradient to record, and ``torch.func`` transforms take the tensor path."""
    sensor, x, z, _ = crowded(3, 4, seed=5)
    assert not native.applies(sensor, x)  # float64
    xf = x.float().requires_grad_(True)
    assert not native.applies(sensor, xf)
    out = sensor.log_likelihood(xf, z)
    out.sum().backward()
    assert torch.isfinite(xf.grad).all()
    with torch.no_grad():
        assert native.applies(sensor, xf)
    vmapped = torch.func.vmap(lambda v: sensor.log_likelihood(v, z))(x.float()[None])
    assert torch.allclose(vmapped[0], sensor.log_likelihood(x.float(), z), rtol=1e-5, atol=1e-3)


def table1_move(K: int, M: int, n: int, seed: int, small: bool = False):
    """Table I's grid (101 x 21 x 31 cells: the tensor path reads a move's boxes), or with
    ``small`` ``crowded``'s (12 x 9 x 10: the tensor path sums the move over the whole grid),
    ``K`` targets in a cluster, 2 runs of ``n`` chains with dead slots, and a move of ``M``
    distinct slots per chain (new states a few cells away, some slots born or killed). Returns
    ``sensor, x, z, exists, x_n, n_slots, exists_n`` in float32."""
    small_sensor, x, _, exists = crowded(K, n, seed)
    sensor = small_sensor if small else RangeDopplerBearingTBD.uniform((2300, 3300), (-20, 20), (-15 * DEG, 15 * DEG))
    g = torch.Generator().manual_seed(seed + 100)
    z = sensor.simulate(x[:, 0].float(), generator=g)
    x = x.float()
    slots = torch.argsort(torch.rand(2, n, K, generator=g), -1)[..., :M]  # (2, n, M) distinct
    step = torch.tensor([10.0, 1.0, 10.0, 1.0, 0.3])
    old = torch.gather(x, 2, slots[..., None].expand(2, n, M, 5))
    x_n = old + step * torch.randn(2, n, M, 5, generator=g)
    e_n = torch.rand(2, n, M, generator=g) > 0.3
    if M == 1:
        return sensor, x, z, exists, x_n[:, :, 0], slots[..., 0], e_n[..., 0]
    return sensor, x, z, exists, x_n, slots, e_n


@pytest.mark.parametrize("K, M, small", [(1, 1, False), (3, 1, False), (10, 1, False), (10, 2, False), (3, 1, True),
                                         (6, 2, True)])
def test_native_cached_move_matches_the_tensor_path(K, M, small, tensor_path):
    """A move read from the chains' amplitude cache (the IP-MCMC-PF's and the MCMC sweeps'
    one- and two-slot moves): the same cells, the change and the delta within twice the tensor
    path's float32 error against float64 (plus 1e-5 / 1e-3). A cell counted in two boxes of
    the move, or an intersection misplaced, moves the delta by a cell's ratio. On a grid no
    larger than the move's boxes the tensor path sums over the whole grid (no cells; its
    change per grid cell) and the loop over the boxes: the deltas agree."""
    sensor, x, z, exists, x_n, n, e_n = table1_move(K, M, 300, seed=K + M, small=small)
    cache = sensor.amplitude_cache(x, exists, z)
    with torch.no_grad():
        ours = sensor.log_likelihood_delta_cached(cache, x, x_n, n, z, exists=exists, exists_n=e_n)
        theirs = tensor_path(lambda: sensor.log_likelihood_delta_cached(cache, x, x_n, n, z, exists=exists,
                                                                         exists_n=e_n))
        cache64 = sensor.amplitude_cache(x.double(), exists, z)
        exact = sensor.log_likelihood_delta_cached(cache64, x.double(), x_n.double(), n, z, exists=exists,
                                                   exists_n=e_n)
    assert native.applies(sensor, x) and ours[1] is not None
    whole = theirs[1] is None  # the tensor path's whole-grid sum: four boxes outnumber the small grid's cells
    assert whole == (small and M == 2)
    if not whole:
        assert torch.equal(ours[1], theirs[1]) and torch.equal(ours[1], exact[1])
    for i, floor in ((0, 1e-3),) if whole else ((0, 1e-3), (2, 1e-5)):
        err_ours = (ours[i].double() - exact[i]).abs().max().item()
        err_theirs = (theirs[i].double() - exact[i]).abs().max().item()
        assert ours[i].shape == theirs[i].shape and ours[i].dtype == torch.float32
        assert err_ours <= 2 * err_theirs + floor, (i, err_ours, err_theirs)
    assert exact[0].abs().max() > 10
    # the move's delta is the difference of two windowed evaluations (the tensor path's own test, here for the loop)
    moved = x.clone()
    e_after = exists.clone()
    idx = n if M > 1 else n[..., None]
    moved.scatter_(2, idx[..., None].expand(*idx.shape, 5), x_n if M > 1 else x_n[:, :, None])
    e_after.scatter_(2, idx, e_n if M > 1 else e_n[..., None])
    with torch.no_grad():
        z64 = z.double()
        diff = sensor.log_likelihood(moved.double(), z64, e_after) - sensor.log_likelihood(x.double(), z64, exists)
    torch.testing.assert_close(ours[0].double(), diff, rtol=0, atol=0.05)


def test_without_a_compiler_the_tensor_path_runs(tmp_path):
    """A machine without a working compiler: one warning naming the fallback, no native op,
    and the radar's likelihood from the tensor path (in a fresh process: the loop is built
    once per process)."""
    script = textwrap.dedent('''
        import math, warnings, torch
        from torchmcmcpf.models.sensors.grid import native
        from torchmcmcpf.models.sensors.radar import RangeDopplerBearingTBD
        with warnings.catch_warnings(record=True) as seen:
            warnings.simplefilter("always")
            sensor = RangeDopplerBearingTBD.uniform((2740, 2850), (-8, 8), (-5 * math.pi / 180, 4 * math.pi / 180))
        x = torch.tensor([[[[2800.0, 1.0, 0.0, 1.0, 4.0]]]])
        z = sensor.simulate(x[:, 0], generator=torch.Generator().manual_seed(0))
        print(native.available(), native.applies(sensor, x), bool(torch.isfinite(sensor.log_likelihood(x, z)).all()))
        print([str(w.message) for w in seen])
    ''')
    env = dict(os.environ, CC=str(tmp_path / "no-such-compiler"), TORCHMCMCPF_CACHE=str(tmp_path / "cache"))
    out = subprocess.run([sys.executable, "-c", script], env=env, capture_output=True, text=True, timeout=120)
    assert out.returncode == 0, out.stderr
    first, second = out.stdout.strip().splitlines()
    assert first == "False False True"
    assert "building the C loops failed" in second and "the tensor paths are used" in second


@pytest.mark.parametrize("K, small", [(1, False), (3, False), (10, False), (3, True), (10, True)])
def test_native_move_without_cache_matches_the_tensor_path(K, small, tensor_path):
    """A one-slot move without a cache (the MCMC filters' sweeps on the radar): the delta
    within twice the tensor path's float32 error against float64 plus 1e-3, and equal to the
    difference of two windowed evaluations; on the small grid the tensor path sums over the
    whole grid, the loop over the two boxes."""
    sensor, x, z, exists, x_n, n, e_n = table1_move(K, 1, 300, seed=K + 20, small=small)
    with torch.no_grad():
        ours = sensor.log_likelihood_delta(x, x_n, n, z, exists=exists, exists_n=e_n)
        theirs = tensor_path(lambda: sensor.log_likelihood_delta(x, x_n, n, z, exists=exists, exists_n=e_n))
        exact = sensor.log_likelihood_delta(x.double(), x_n.double(), n, z, exists=exists, exists_n=e_n)
        moved = x.double().clone()
        moved[torch.arange(2)[:, None], torch.arange(300), n] = x_n.double()
        e_after = exists.clone()
        e_after[torch.arange(2)[:, None], torch.arange(300), n] = e_n
        z64 = z.double()
        diff = sensor.log_likelihood(moved, z64, e_after) - sensor.log_likelihood(x.double(), z64, exists)
    assert native.applies(sensor, x) and ours.shape == (2, 300) and ours.dtype == torch.float32
    err_ours = (ours.double() - exact).abs().max().item()
    err_theirs = (theirs.double() - exact).abs().max().item()
    assert err_ours <= 2 * err_theirs + 1e-3, (err_ours, err_theirs)
    assert exact.abs().max() > 10
    torch.testing.assert_close(ours.double(), diff, rtol=0, atol=0.05)
    # an int slot, as the sweeps pass it, is the same move
    with torch.no_grad():
        fixed = sensor.log_likelihood_delta(x, x_n, 0, z, exists=exists, exists_n=e_n)
        assert torch.equal(fixed, sensor.log_likelihood_delta(x, x_n, torch.zeros_like(n), z, exists=exists,
                                                              exists_n=e_n))


@pytest.mark.parametrize("M", [1, 2])
def test_a_box_repeated_in_a_move_adds_nothing(M, tensor_path):
    """The loop skips a move's box that an earlier box of the move repeats (the same cells:
    every term there is 0): on small steps, where most new boxes are the old ones, the delta
    and the change agree with the tensor path as on any move, the repeated box's change is 0
    and its cells are the earlier box's (so the cache's update adds 0 there)."""
    sensor, x, z, exists, x_n, n, e_n = table1_move(3, M, 300, seed=7 + M, small=True)
    old = torch.gather(x, 2, (n if M > 1 else n[..., None])[..., None].expand(2, 300, M, 5))
    x_n = (old + 0.05 * ((x_n if M > 1 else x_n[:, :, None]) - old))
    if M == 1:
        x_n = x_n[:, :, 0]
    cache = sensor.amplitude_cache(x, exists, z)
    with torch.no_grad():
        ours = sensor.log_likelihood_delta_cached(cache, x, x_n, n, z, exists=exists, exists_n=e_n)
        theirs = tensor_path(lambda: sensor.log_likelihood_delta_cached(cache, x, x_n, n, z, exists=exists,
                                                                         exists_n=e_n))
        exact = sensor.log_likelihood_delta_cached(sensor.amplitude_cache(x.double(), exists, z), x.double(),
                                                   x_n.double(), n, z, exists=exists, exists_n=e_n)
    delta, cells, change = ours
    flat = cells.flatten(3)  # (2, 300, 2M, V)
    same = (flat[:, :, 1] == flat[:, :, 0]).all(-1)  # the new box of the (first) moved slot is its old one
    assert 0.3 < same.float().mean() < 1.0  # both kinds of move are here
    assert (change.flatten(3)[:, :, 1][same] == 0).all()
    if theirs[1] is not None:
        assert torch.equal(cells, theirs[1])
    for got, want, floor in ((delta, theirs[0], 1e-3),):
        err_ours = (got.double() - exact[0]).abs().max().item()
        err_theirs = (want.double() - exact[0]).abs().max().item()
        assert err_ours <= 2 * err_theirs + floor, (err_ours, err_theirs)
