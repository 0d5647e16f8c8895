"""Radar TBD likelihood: windowed fast path vs whole-grid reference, eager vs torch.compile.

Table-I-like grid (2300-3300 m at 10 m, -20..20 m/s at 2 m/s, -15..15 deg at 1 deg:
101 x 21 x 31 cells), K = 10 targets, B = 1 run, float32, window 3 (the default).
Groups are per particle count, so the ratios window / grid / compiled read off one table.

    pytest benchmarks/bench_likelihood.py --benchmark-group-by=group
    pytest benchmarks/bench_likelihood.py -m "not compile"     # eager only

Also: ``log I0`` of float32 arguments, ``i0e`` vs the polynomial approximation (eager and
compiled), and the change of the likelihood when one slot of 50 chains moves
(``log_likelihood_delta`` vs two windowed calls).
"""

from __future__ import annotations

import math

import pytest
import torch

from torchmcmcpf.models.sensors.radar import RangeDopplerBearingTBD, log_i0_approx

K = 10
DEG = math.pi / 180


def problem(n: int):
    sens = RangeDopplerBearingTBD.uniform((2300, 3300), (-20, 20), (-15 * DEG, 15 * DEG))
    g = torch.Generator().manual_seed(0)
    r = 2400 + 800 * torch.rand(1, K, generator=g)
    b = (-12 + 24 * torch.rand(1, K, generator=g)) * DEG
    v = 5 * torch.randn(2, 1, K, generator=g)
    xt = torch.stack([r * torch.cos(b), v[0], r * torch.sin(b), v[1], torch.full((1, K), sens.amplitude_from_snr(13.0))], -1)
    z = sens.simulate(xt, generator=g)
    x = xt[:, None] + torch.tensor([5.0, 1.0, 5.0, 1.0, 0.5]) * torch.randn(1, n, K, 5, generator=g)
    return sens, x, z


def _run(benchmark, fn, x, z, rounds):
    with torch.no_grad():
        fn(x, z)  # warm-up (and compilation)
        out = benchmark.pedantic(fn, args=(x, z), rounds=rounds, iterations=1)
    assert out.shape == (1, x.shape[1]) and torch.isfinite(out).all()


@pytest.mark.parametrize("n", [500, 5000])
@pytest.mark.parametrize("path", ["window", "grid"])
def test_likelihood_eager(benchmark, path, n):
    sens, x, z = problem(n)
    benchmark.group = f"radar-likelihood-N{n}-K{K}"
    fn = getattr(sens, f"log_likelihood_{path}")
    _run(benchmark, fn, x, z, rounds=5 if path == "window" or n <= 500 else 1)


@pytest.mark.compile
@pytest.mark.parametrize("n", [500, 5000])
@pytest.mark.parametrize("path", ["window", "grid"])
def test_likelihood_compiled(benchmark, path, n):
    sens, x, z = problem(n)
    benchmark.group = f"radar-likelihood-N{n}-K{K}"
    fn = torch.compile(getattr(sens, f"log_likelihood_{path}"), dynamic=False)
    _run(benchmark, fn, x, z, rounds=5 if path == "window" or n <= 500 else 1)


# ----------------------------------------------------------------------------- log I0
def _log_i0_exact(u):
    a = u.abs()
    return torch.log(torch.special.i0e(a)) + a


@pytest.mark.parametrize("n", [70_000, 17_000_000])  # one delta at C = 50; one windowed call at N = 5000
@pytest.mark.parametrize("variant", ["i0e-eager", "approx-eager", "approx-compiled"])
def test_log_i0(benchmark, variant, n):
    """``log I0`` of float32 arguments: ``torch.special.i0e`` (the float64 path) against the
    Abramowitz-Stegun polynomial used for float32 (:func:`~torchmcmcpf.models.sensors.radar.log_i0_approx`)."""
    u = 60 * torch.rand(n, generator=torch.Generator().manual_seed(0))
    fn = {"i0e-eager": _log_i0_exact, "approx-eager": log_i0_approx,
          "approx-compiled": torch.compile(log_i0_approx, dynamic=False)}[variant]
    benchmark.group = f"log-i0-{n}"
    fn(u)
    benchmark.pedantic(fn, args=(u,), rounds=5, iterations=1)


# ----------------------------------------------------------------------------- one-slot delta
@pytest.mark.parametrize("variant", ["delta-eager", "delta-compiled", "window-eager-twice"])
def test_one_slot_change(benchmark, variant):
    """Change of the log-likelihood when one of K = 10 slots moves, for C = 50 chains: the
    ``log_likelihood_delta`` hook against two windowed evaluations."""
    sens, x, z = problem(50)
    x_n = x[:, :, 3] + torch.tensor([3.0, 0.5, 3.0, 0.5, 0.0])
    x_new = x.clone()
    x_new[:, :, 3] = x_n
    slot = torch.tensor(3)
    benchmark.group = "one-slot-change-C50-K10"
    if variant == "window-eager-twice":
        fn = lambda: sens.log_likelihood_window(x_new, z) - sens.log_likelihood_window(x, z)  # noqa: E731
    else:
        delta = sens.log_likelihood_delta
        if variant == "delta-compiled":
            delta = torch.compile(delta, dynamic=False, fullgraph=True)
        fn = lambda: delta(x, x_n, slot, z)  # noqa: E731
    with torch.no_grad():
        fn()
        benchmark.pedantic(fn, rounds=20, iterations=1)
