"""Radar TBD likelihood: windowed fast path vs whole-grid reference, eager vs torch.compile.

Table-I-like grid (2300-3300 m at 10 m, -20..20 m/s at 2 m/s, -15..15 deg at 1 deg:
101 x 21 x 31 cells), K = 10 targets, B = 1 run, float32, window 3 (the default).
Groups are per particle count, so the ratios window / grid / compiled read off one table.

    pytest benchmarks/bench_likelihood.py --benchmark-group-by=group
    pytest benchmarks/bench_likelihood.py -m "not compile"     # eager only

Variants: ``window`` (on the CPU in float32 the C loop of
:mod:`torchmcmcpf.models.sensors.grid.native`), ``window-tensors`` (the tensor path the loop
replaced there, and which every other device, dtype and autograd runs: neighbour slots, a box
sums only the targets whose boxes overlap it), ``window-dense`` (the tensor path with
``max_neighbours = K - 1``: every target summed in every box, the O(N K^2 W^3) cost of the
windowed path before neighbour slots), ``grid`` (the whole-grid reference).

Also: ``log I0`` of float32 arguments, ``i0e`` vs the polynomial approximation (eager and
compiled); the change of the likelihood when one slot of 50 chains moves
(``log_likelihood_delta`` with neighbour slots and dense, vs two windowed calls); and the
independent-partition weights (every slot of one reference moved on its own: one amplitude
grid of the reference vs a one-slot delta per sample and slot); and the
point-measurement Gaussian (``LinearGaussian``, precomputed whitening vs the per-call
triangular solve it replaced), B = 100 runs x N = 5000.

Every benchmark records ``torch.get_num_threads()`` in ``extra_info``: on a shared 2-core
machine a busy neighbour makes torch's threads spin, so compare variants within one run.
"""

from __future__ import annotations

import math

import pytest
import torch

from torchmcmcpf.models.sensors.grid import native
from torchmcmcpf.models.sensors.linear import LinearGaussian
from torchmcmcpf.models.sensors.radar import RangeDopplerBearingTBD, log_i0, log_i0_approx

K = 10
DEG = math.pi / 180


def problem(n: int):
    sens = RangeDopplerBearingTBD.uniform((2300, 3300), (-20, 20), (-15 * DEG, 15 * DEG))
    g = torch.Generator().manual_seed(0)
    r = 2400 + 800 * torch.rand(1, K, generator=g)
    b = (-12 + 24 * torch.rand(1, K, generator=g)) * DEG
    v = 5 * torch.randn(2, 1, K, generator=g)
    rho = torch.full((1, K), sens.amplitude_from_snr(13.0))
    xt = torch.stack([r * torch.cos(b), v[0], r * torch.sin(b), v[1], rho], -1)
    z = sens.simulate(xt, generator=g)
    x = xt[:, None] + torch.tensor([5.0, 1.0, 5.0, 1.0, 0.5]) * torch.randn(1, n, K, 5, generator=g)
    return sens, x, z


@pytest.fixture(autouse=True)
def _threads(benchmark):
    benchmark.extra_info["threads"] = torch.get_num_threads()


def _sensor_path(sens, path):
    """The bound method of a variant; ``window-dense`` forces every target into every box,
    ``window-tensors`` and ``window-dense`` run without the C loop."""
    if path == "window-dense":
        sens.max_neighbours = K - 1
    if path in ("window-tensors", "window-dense"):
        fn = sens.log_likelihood_window

        def tensors(x, z):
            with native.tensor_path():
                return fn(x, z)
        return tensors
    return getattr(sens, f"log_likelihood_{path}")


def _run(benchmark, fn, x, z, rounds):
    with torch.no_grad():
        fn(x, z)  # warm-up (and compilation)
        out = benchmark.pedantic(fn, args=(x, z), rounds=rounds, iterations=1)
    assert out.shape == (1, x.shape[1]) and torch.isfinite(out).all()


@pytest.mark.parametrize("n", [500, 5000])
@pytest.mark.parametrize("path", ["window", "window-tensors", "window-dense", "grid"])
def test_likelihood_eager(benchmark, path, n):
    sens, x, z = problem(n)
    benchmark.group = f"radar-likelihood-N{n}-K{K}"
    fn = _sensor_path(sens, path)
    _run(benchmark, fn, x, z, rounds=5 if path.startswith("window") or n <= 500 else 1)


@pytest.mark.compile
@pytest.mark.parametrize("n", [500, 5000])
@pytest.mark.parametrize("path", ["window", "window-tensors", "window-dense", "grid"])
def test_likelihood_compiled(benchmark, path, n):
    sens, x, z = problem(n)
    benchmark.group = f"radar-likelihood-N{n}-K{K}"
    fn = torch.compile(_sensor_path(sens, path), dynamic=False)
    _run(benchmark, fn, x, z, rounds=5 if path.startswith("window") or n <= 500 else 1)


# ----------------------------------------------------------------------------- log I0
def _log_i0_exact(u):
    a = u.abs()
    return torch.log(torch.special.i0e(a)) + a


# one delta at C = 50; the crossing MCMC-PF's one-slot change at Np = 2000 (5 runs x 1000
# chains x 640 cells); one windowed call at N = 5000
@pytest.mark.parametrize("n", [70_000, 3_200_000, 17_000_000])
@pytest.mark.parametrize("variant", ["i0e-eager", "approx-eager", "blocks-eager", "approx-compiled"])
def test_log_i0(benchmark, variant, n):
    """``log I0`` of float32 arguments: ``torch.special.i0e`` (the float64 path) against the
    Abramowitz-Stegun polynomial used for float32 (:func:`~torchmcmcpf.models.sensors.radar.log_i0_approx`)
    in one call, and :func:`~torchmcmcpf.models.sensors.radar.log_i0` (what the sensor calls:
    eager without autograd, the polynomial block by block, each in the cache)."""
    u = 60 * torch.rand(n, generator=torch.Generator().manual_seed(0))
    fn = {"i0e-eager": _log_i0_exact, "approx-eager": log_i0_approx, "blocks-eager": log_i0,
          "approx-compiled": torch.compile(log_i0_approx, dynamic=False)}[variant]
    benchmark.group = f"log-i0-{n}"
    fn(u)
    benchmark.pedantic(fn, args=(u,), rounds=5, iterations=1)


# ----------------------------------------------------------------------------- one-slot delta
@pytest.mark.parametrize(
    "variant", ["delta-eager", "delta-compiled", "delta-dense-eager", "delta-dense-compiled", "window-eager-twice"]
)
def test_one_slot_change(benchmark, variant):
    """Change of the log-likelihood when one of K = 10 slots moves, for C = 50 chains: the
    ``log_likelihood_delta`` hook (neighbour slots, or dense: every target in both boxes)
    against two windowed evaluations."""
    sens, x, z = problem(50)
    if "dense" in variant:
        sens.max_neighbours = K - 1
    x_n = x[:, :, 3] + torch.tensor([3.0, 0.5, 3.0, 0.5, 0.0])
    x_new = x.clone()
    x_new[:, :, 3] = x_n
    slot = torch.tensor(3)
    benchmark.group = "one-slot-change-C50-K10"
    if variant == "window-eager-twice":
        fn = lambda: sens.log_likelihood_window(x_new, z) - sens.log_likelihood_window(x, z)  # noqa: E731
    else:
        delta = sens.log_likelihood_delta
        if variant.endswith("compiled"):
            delta = torch.compile(delta, dynamic=False, fullgraph=True)
        fn = lambda: delta(x, x_n, slot, z)  # noqa: E731
    with torch.no_grad():
        fn()
        benchmark.pedantic(fn, rounds=20, iterations=1)


# ----------------------------------------------------------------------------- every slot of one reference
@pytest.mark.parametrize("variant", ["reference-grid-eager", "reference-grid-compiled", "deltas-eager",
                                     "deltas-compiled"])
def test_slot_changes(benchmark, variant):
    """The independent-partition filter's weights: every slot of one reference moved on its
    own, N = 500 candidates x K = 10 slots. ``reference-grid``: the grid sensor's
    ``log_likelihood_slot_changes`` (one amplitude grid of the reference, one box per slot);
    ``deltas``: the base class's form, one ``log_likelihood_delta`` per sample and slot with
    the reference repeated (what the filter did before)."""
    from torchmcmcpf.models.base import SensorModel

    sens, x, z = problem(500)
    ref = x[:, 0].clone()  # not a view of x: torch.cond refuses branch inputs that alias
    fn = sens.log_likelihood_slot_changes if variant.startswith("reference") else (
        lambda r, y, f: SensorModel.log_likelihood_slot_changes(sens, r, y, f))
    if variant.endswith("compiled"):
        fn = torch.compile(fn, dynamic=False)
    benchmark.group = "slot-changes-N500-K10"
    with torch.no_grad():
        out = fn(ref, x, z)
        benchmark.pedantic(fn, args=(ref, x, z), rounds=5, iterations=1)
    assert out.shape == (1, 500, K) and torch.isfinite(out).all()


# ----------------------------------------------------------------------------- point measurements
def _solve_reference(sensor, x, z):
    """The per-call triangular solve that precomputed whitening replaced (old-style path)."""
    r = (z[:, None] - x @ sensor.H.mT).unsqueeze(-1)
    L = sensor.L.expand(r.shape[:-2] + sensor.L.shape)
    white = torch.linalg.solve_triangular(L, r, upper=False).squeeze(-1)
    return (sensor._log_norm - 0.5 * white.square().sum(-1)).sum(-1)


@pytest.mark.parametrize("variant", ["whitened", "triangular-solve"])
def test_linear_gaussian(benchmark, variant):
    """``LinearGaussian`` log-likelihood, B = 100 runs x N = 5000 particles, one target,
    float32: precomputed whitening against the per-call triangular solve."""
    g = torch.Generator().manual_seed(0)
    sensor = LinearGaussian.position(10.0)
    x = 100 * torch.randn(100, 5000, 1, 4, generator=g)
    z = 100 * torch.randn(100, 1, 2, generator=g)
    fn = sensor.log_likelihood if variant == "whitened" else (lambda x, z: _solve_reference(sensor, x, z))
    torch.testing.assert_close(fn(x, z), _solve_reference(sensor, x, z), rtol=1e-4, atol=1e-2)
    benchmark.group = "linear-gaussian-B100-N5000"
    benchmark.pedantic(fn, args=(x, z), rounds=20, iterations=1)
