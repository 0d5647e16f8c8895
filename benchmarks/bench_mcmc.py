"""One time step of the sequential MCMC particle filter vs the number of chains C.

    .venv/bin/pytest benchmarks/bench_mcmc.py --benchmark-only --benchmark-group-by=group

``mcmc-step-<sensor>``: :func:`torchmcmcpf.filters.mcmc.mcmc_step` at fixed N with C in
{1, 10, 50, 100} chains, burn-in 0 and thinning 1, so a step runs N / C iterations of the
kernel (paper 004's mixture: joint draw w.p. 0.75, else a per-target refinement sweep).
Fewer, wider iterations amortise the per-iteration overhead of eager PyTorch: the ratios
between the C values within one run are the result. Timings on a shared machine are noisy.

Adding a sensor: write a function ``(generator) -> Problem`` and register it in
``PROBLEMS``; every benchmark here is parametrised over that dict (e.g. the radar grid with
10 targets, whose per-target refinement uses the sensor's ``log_likelihood_delta``).
"""

from __future__ import annotations

import math
import os
from typing import Callable, NamedTuple

import pytest
import torch

from torchmcmcpf import ConstantVelocity, LinearGaussian
from torchmcmcpf.filters.mcmc import mcmc_step
from torchmcmcpf.models.base import MotionModel, SensorModel
from torchmcmcpf.state import ParticleState

N = int(os.environ.get("BENCH_MCMC_PARTICLES", "1000"))
CHAINS = (1, 10, 50, 100)


class Problem(NamedTuple):
    """One time step to filter: models, the previous cloud ``(B, N, K, D)`` and a frame."""

    motion: MotionModel
    sensor: SensorModel
    state: ParticleState
    z: torch.Tensor


def linear_gaussian(generator: torch.Generator, B: int = 1, K: int = 10) -> Problem:
    """K constant-velocity targets observed in position with unit noise (float32)."""
    motion, sensor = ConstantVelocity(1.0, 1.0), LinearGaussian.position(1.0)
    truth = torch.randn(B, K, 4, generator=generator) * 50
    x = truth.unsqueeze(1) + torch.randn(B, N, K, 4, generator=generator)
    z = sensor.simulate(motion.sample(truth, generator=generator), generator=generator)
    return Problem(motion, sensor, ParticleState(x, torch.full((B, N), -math.log(N))), z)


#: sensor name -> problem factory; extend with other sensors (radar grid, ...).
PROBLEMS: dict[str, Callable[[torch.Generator], Problem]] = {
    "linear-gaussian": linear_gaussian,
}


@pytest.fixture(scope="module", params=list(PROBLEMS))
def problem(request):
    return request.param, PROBLEMS[request.param](torch.Generator().manual_seed(0))


@pytest.mark.parametrize("num_chains", CHAINS)
def test_mcmc_step(benchmark, problem, num_chains):
    name, (motion, sensor, state, z) = problem
    benchmark.group = f"mcmc-step-{name}"
    benchmark.extra_info.update(N=N, C=num_chains, iterations=N // num_chains, K=state.num_targets)
    g = torch.Generator().manual_seed(1)

    def step():
        return mcmc_step(state, z, motion=motion, sensor=sensor, generator=g, num_chains=num_chains,
                         burn_in=0, thinning=1, moves="mixture")

    out, info = benchmark.pedantic(step, rounds=3, iterations=1, warmup_rounds=1)
    assert out.x.shape == state.x.shape
