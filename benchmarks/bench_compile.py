"""Cold compile time of every filter's ``compile_step=True`` kernel (issue 9).

    .venv/bin/python -m pytest benchmarks/bench_compile.py --benchmark-only --benchmark-group-by=group

One round per filter, caches off (``torch._dynamo.reset()`` and inductor's on-disk caches
disabled), on the ground radar with 5 targets (87 x 22 x 32 cells, float32, the windowed
likelihood and its one-slot delta): the time of the first ``filt.step`` with
``compile_step=True`` minus nothing, i.e. compile + one step; ``extra_info["eager_step_s"]``
holds one eager step of the same filter, so compile time ~ first step - eager step.
What compiles is one kernel: one SIR step without its draws, one MCMC iteration (every move
of the mixture), one IP-MCMC exchange iteration, one HMC transition (leapfrog with
``torch.func.grad``), never the Python loops over iterations, so the cost does not grow with
the burn-in or the number of particles (shapes are static: a new N or B recompiles).
"""

from __future__ import annotations

import time

import pytest
import torch

from torchmcmcpf.filters import (
    IPMCMCFilter,
    MCMCFilter,
    PartitionedSIRFilter,
    PMMHFilter,
    ResampleMoveFilter,
    SIRFilter,
)
from torchmcmcpf.scenarios.ground_radar import ground_radar

TARGETS, N = 5, 200

FILTERS = {
    "sir": lambda m, s, c: SIRFilter(m, s, N, compile_step=c),
    "mcmc": lambda m, s, c: MCMCFilter(m, s, N, num_chains=20, burn_in=5, compile_step=c),
    "ipmcmc": lambda m, s, c: IPMCMCFilter(m, s, N, num_chains=20, burn_in=5, max_extensions=0, compile_step=c),
    "resample_move": lambda m, s, c: ResampleMoveFilter(m, s, N, num_hmc_steps=3, compile_step=c),
    "partitioned": lambda m, s, c: PartitionedSIRFilter(m, s, N, compile_step=c),
    "pmmh": lambda m, s, c: PMMHFilter(m, s, N, num_candidates=4, compile_step=c),
}


@pytest.fixture(scope="module")
def scenario():
    return ground_radar(TARGETS, 5, 1, generator=torch.Generator().manual_seed(0))


@pytest.mark.compile
@pytest.mark.parametrize("name", FILTERS)
def test_cold_compile(benchmark, scenario, name):
    x0 = scenario.initial_particles(N, generator=torch.Generator().manual_seed(1))
    z = scenario.measurements[0]
    eager = FILTERS[name](scenario.motion, scenario.sensor, False)
    t0 = time.perf_counter()
    eager.step(eager.init(x0), z, generator=torch.Generator().manual_seed(2))
    eager_s = time.perf_counter() - t0

    def first_compiled_step():
        torch._dynamo.reset()
        filt = FILTERS[name](scenario.motion, scenario.sensor, True)
        return filt.step(filt.init(x0), z, generator=torch.Generator().manual_seed(2))

    benchmark.group = "cold-compile"
    benchmark.extra_info.update(filter=name, eager_step_s=eager_s, targets=TARGETS, particles=N,
                                threads=torch.get_num_threads())
    with torch._inductor.config.patch(force_disable_caches=True):
        state, _ = benchmark.pedantic(first_compiled_step, rounds=1, iterations=1)
    assert state.x.shape == x0.shape
