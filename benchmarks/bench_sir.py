"""One SIR step on the ground radar (paper 000 Table I, 10 targets): windowed vs whole-grid
likelihood, eager vs ``torch.compile`` of the windowed likelihood, Np = 500 and 5000.

    .venv/bin/pytest benchmarks/bench_sir.py --benchmark-only --benchmark-group-by=group
    .venv/bin/pytest benchmarks/bench_sir.py -m "not compile"     # eager only

Groups are per particle count (``sir-step-N<Np>``), so the ratios read off one table. The
sensor is the scenario's (87 x 22 x 32 cells with the default 20 frames, float32, window 3,
point spreads truncated to the boxes); a step is systematic resampling, the motion prior and
the likelihood weights (:func:`torchmcmcpf.filters.sir.sir_step`). ``compiled`` compiles the
sensor's windowed log-likelihood only (the step draws from a generator, which cannot be
traced). The whole-grid path runs one round (seconds per step at Np = 5000).
"""

from __future__ import annotations

import math

import pytest
import torch

from torchmcmcpf.filters.sir import sir_step
from torchmcmcpf.scenarios.ground_radar import ground_radar
from torchmcmcpf.state import ParticleState

TARGETS = 10


class CompiledWindow:
    """A sensor whose ``log_likelihood`` is the compiled windowed path of ``sensor``."""

    def __init__(self, sensor):
        self.log_likelihood = torch.compile(sensor.log_likelihood_window, dynamic=False)


@pytest.fixture(scope="module")
def scenario():
    return ground_radar(TARGETS, 20, 1, generator=torch.Generator().manual_seed(0))


def _bench(benchmark, scn, n, variant, sensor, rounds):
    x0 = scn.initial_particles(n, generator=torch.Generator().manual_seed(1))
    state = ParticleState(x0, torch.full(x0.shape[:2], -math.log(n), dtype=x0.dtype))
    z = scn.measurements[0]

    def step():
        return sir_step(state, z, motion=scn.motion, sensor=sensor, generator=torch.Generator().manual_seed(2))

    benchmark.group = f"sir-step-N{n}"
    benchmark.extra_info.update(variant=variant, particles=n, targets=TARGETS, frame=list(scn.sensor.frame_shape))
    with torch.no_grad():
        step()  # warm-up (and compilation)
        out, info = benchmark.pedantic(step, rounds=rounds, iterations=1)
    assert out.x.shape == x0.shape and torch.isfinite(info.log_evidence).all()


@pytest.mark.parametrize("n", [500, 5000])
@pytest.mark.parametrize("path", ["window", "grid"])
def test_sir_step_eager(benchmark, scenario, path, n):
    sensor = scenario.sensor
    sensor.method = path
    try:
        _bench(benchmark, scenario, n, f"{path}-eager", sensor, rounds=10 if path == "window" else 1)
    finally:
        sensor.method = "window"


@pytest.mark.compile
@pytest.mark.parametrize("n", [500, 5000])
def test_sir_step_window_compiled(benchmark, scenario, n):
    _bench(benchmark, scenario, n, "window-compiled", CompiledWindow(scenario.sensor), rounds=10)
