"""One time step of the sequential MCMC particle filter vs the number of chains C.

    .venv/bin/pytest benchmarks/bench_mcmc.py --benchmark-only --benchmark-group-by=group

``mcmc-step-<sensor>``: :func:`torchmcmcpf.filters.mcmc.mcmc_step` at fixed N with C in
{1, 10, 50, 100} chains, burn-in 0 and thinning 1, so a step runs N / C iterations of the
kernel (paper 004's mixture: joint draw w.p. 0.75, else a per-target refinement sweep).
Fewer, wider iterations amortise the per-iteration overhead of eager PyTorch: the ratios
between the C values within one run are the result. Timings on a shared machine are noisy.

Adding a sensor: write a function ``(generator) -> Problem`` and register it in
``PROBLEMS``; every benchmark here is parametrised over that dict. ``radar-window`` is the
ground radar of paper 000 (10 targets, 87 x 22 x 32 cells, float32, windowed likelihood with
truncated spreads): its per-target refinement scores each slot by the sensor's
``log_likelihood_delta`` (the cells of the slot's old and new box). ``radar-grid`` is the same
with the whole-grid reference (each delta two whole-grid evaluations): it runs only the
C values with few iterations (C >= 50), one round.

``mcmc-step-radar-target``: the issue-3 setting, C = 50 chains and N = 5000 (100 iterations
per step), windowed likelihood, eager. ``mcmc-terms-*``: the same setting through the public
``MCMCFilter.step``, eager and compiled, with the paper's factorised target and with the
default exclusion and re-capture (issue 22's cost).
"""

from __future__ import annotations

import math
import os
from collections.abc import Callable
from typing import NamedTuple

import pytest
import torch

from torchmcmcpf import ConstantVelocity, LinearGaussian
from torchmcmcpf.filters.mcmc import MCMCSettings, mcmc_step
from torchmcmcpf.models.base import MotionModel, SensorModel
from torchmcmcpf.scenarios.ground_radar import ground_radar
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


def radar(generator: torch.Generator, method: str = "window", n: int = N) -> Problem:
    """The ground radar of paper 000 with 10 targets; the cloud is the scenario's initial one."""
    scn = ground_radar(10, 20, 1, generator=generator)
    scn.sensor.method = method
    x = scn.initial_particles(n, generator=generator)
    return Problem(scn.motion, scn.sensor, ParticleState(x, torch.full((1, n), -math.log(n))), scn.measurements[0])


#: sensor name -> problem factory.
PROBLEMS: dict[str, Callable[[torch.Generator], Problem]] = {
    "linear-gaussian": linear_gaussian,
    "radar-window": radar,
    "radar-grid": lambda generator: radar(generator, "grid"),
}


@pytest.fixture(scope="module", params=list(PROBLEMS))
def problem(request):
    return request.param, PROBLEMS[request.param](torch.Generator().manual_seed(0))


@pytest.mark.parametrize("num_chains", CHAINS)
def test_mcmc_step(benchmark, problem, num_chains):
    name, (motion, sensor, state, z) = problem
    if name == "radar-grid" and num_chains < 50:
        pytest.skip("whole grid: N / C iterations of full-grid evaluations take minutes; C >= 50 only")
    _bench_step(benchmark, f"mcmc-step-{name}", motion, sensor, state, z, num_chains,
                rounds=1 if name == "radar-grid" else 3)


def _bench_step(benchmark, group, motion, sensor, state, z, num_chains, rounds):
    n = state.x.shape[1]
    benchmark.group = group
    benchmark.extra_info.update(N=n, C=num_chains, iterations=n // num_chains, K=state.x.shape[2])
    g = torch.Generator().manual_seed(1)

    def step():
        return mcmc_step(state, z, motion=motion, sensor=sensor, generator=g,
                         settings=MCMCSettings(num_chains=num_chains, burn_in=0, thinning=1, moves="mixture"))

    with torch.no_grad():
        out, info = benchmark.pedantic(step, rounds=rounds, iterations=1, warmup_rounds=1)
    assert out.x.shape == state.x.shape


def test_mcmc_step_radar_target(benchmark):
    motion, sensor, state, z = radar(torch.Generator().manual_seed(0), n=5000)
    _bench_step(benchmark, "mcmc-step-radar-target", motion, sensor, state, z, 50, rounds=3)


#: The multitarget prior's terms (issue 22), as the IP-MCMC-PF's benchmark names them.
TERMS = {"paper": dict(exclusion=None, recapture=None), "both": {}}


@pytest.mark.parametrize("compiled", [False, True], ids=["eager", "compiled"])
@pytest.mark.parametrize("terms", list(TERMS))
def test_mcmc_step_multitarget_terms(benchmark, terms, compiled):
    """The cost of exclusion and re-capture in the MCMC-PF: the public ``filt.step`` (C = 50,
    N = 5000, burn-in 0, thinning 1: 100 iterations of paper 004's mixture), with the paper's
    factorised target and with both terms (the default: relocations drawn from the frame's
    peaks, in blocks of iterations). Compare within one run: ``--benchmark-group-by=group``.
    """
    from torchmcmcpf.filters.mcmc import MCMCFilter

    motion, sensor, state, z = radar(torch.Generator().manual_seed(0), n=5000)
    filt = MCMCFilter(motion, sensor, 5000, num_chains=50, burn_in=0, thinning=1, moves="mixture",
                      compile_step=compiled, **TERMS[terms])
    start = filt.init(state.x)
    with torch.no_grad():
        filt.step(start, z, generator=torch.Generator().manual_seed(1))  # warm-up, compilation
        benchmark.group = f"mcmc-terms-{'compiled' if compiled else 'eager'}"
        benchmark.extra_info.update(terms=terms, threads=torch.get_num_threads())
        out, _ = benchmark.pedantic(lambda: filt.step(start, z, generator=torch.Generator().manual_seed(2)),
                                    rounds=3, iterations=1)
    assert out.x.shape == state.x.shape
