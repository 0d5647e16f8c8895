"""Point-measurement SIR against its peers, same model, in one run: Stone Soup 1.9.1 (same N,
per step) and particles 0.4 (per run of T steps).

    .venv/bin/pytest benchmarks/bench_stonesoup.py --benchmark-only --benchmark-group-by=group

One target with known association: :class:`ConstantVelocity` motion (q = 0.1, dt = 1),
position measured by :class:`LinearGaussian` (unit noise), systematic resampling at every
step. Ours: :class:`~torchmcmcpf.filters.SIRFilter` with the B runs as one batch (float32,
eager), through the public ``step`` (one frame per call) or ``forward`` (a sequence).
Stone Soup: ``ParticlePredictor`` + ``ParticleUpdater`` with ``SystematicResampler``
(float64 NumPy), a Python loop over the B runs, the weights as a float array (the fastest
of its documented forms in ``bench``). particles: ``SMC`` of ``ssm.Bootstrap`` on
``kalman.MVLinearGauss``, ``resampling="systematic", ESSrmin=1.0``, one run at a time. Groups
``point-sir-B<B>-N<N>`` (per step) and ``particles-B<B>-N<N>-T<T>`` (all B runs): read the
ratio within a group. Issue 26's targets: Stone Soup / ours >= 5x at B = 1 and >= 20x at
B = 100 (N = 5000); particles / ours >= 20x at B = 100 (N = 2000, T = 25).
"""

from __future__ import annotations

import pytest
import torch

from torchmcmcpf import bench

N = 5000
ROUNDS = 10


@pytest.mark.parametrize("library", ["torchmcmcpf", "stonesoup"])
@pytest.mark.parametrize("b", [1, 100])
def test_point_sir_step(benchmark, library, b):
    if library == "stonesoup":
        pytest.importorskip("stonesoup")
        step = bench.stonesoup_step(N, b, ROUNDS + 2)
    else:
        step = bench.point_sir_step(N, b, ROUNDS + 2, torch.device("cpu"))
    benchmark.group = f"point-sir-B{b}-N{N}"
    benchmark.extra_info.update(library=library, B=b, N=N)
    with torch.no_grad():
        benchmark.pedantic(step, rounds=ROUNDS if library == "torchmcmcpf" or b == 1 else 3, iterations=1,
                           warmup_rounds=1)


@pytest.mark.parametrize("library", ["torchmcmcpf", "particles"])
def test_particles_runs(benchmark, library):
    n, b, steps = 2000, 100, 25
    if library == "particles":
        pytest.importorskip("particles")
        run = bench.particles_runs(n, b, steps)
    else:
        filt, z, x0 = bench.point_filter(n, b, steps, torch.device("cpu"))
        g = torch.Generator().manual_seed(2)

        def run():
            return filt(z, init=x0, generator=g).log_evidence
    benchmark.group = f"particles-B{b}-N{n}-T{steps}"
    benchmark.extra_info.update(library=library, B=b, N=n, T=steps)
    with torch.no_grad():
        benchmark.pedantic(run, rounds=1 if library == "particles" else 5, iterations=1, warmup_rounds=1)


@pytest.mark.parametrize("shape", [(4, 4), (2, 4)])
@pytest.mark.parametrize("variant", ["linear_map", "matmul"])
def test_linear_map(benchmark, variant, shape):
    """The per-target linear maps of that step (``F x``, ``L eps``, ``W H x`` over B = 100 runs
    x N = 5000 particles): :func:`~torchmcmcpf.models.base.linear_map` (block-diagonal
    grouping of rows) against the plain ``x @ M.mT``, group ``linear-map-<d>x<D>``.
    """
    from torchmcmcpf.models.base import linear_map

    g = torch.Generator().manual_seed(0)
    x = torch.randn(100, N, 1, shape[1], generator=g)
    M = torch.randn(shape, generator=g)
    fn = (lambda: linear_map(x, M)) if variant == "linear_map" else (lambda: x @ M.mT)
    benchmark.group = f"linear-map-{shape[0]}x{shape[1]}"
    benchmark.extra_info.update(variant=variant, rows=x.numel() // shape[1])
    out = benchmark.pedantic(fn, rounds=20, warmup_rounds=1, iterations=1)
    torch.testing.assert_close(out, x @ M.mT)
