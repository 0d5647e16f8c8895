"""IP-MCMC-PF time per step on the ground radar (paper 000 Table II setting: Np = 5000,
50 chains, burn-in 100, 10 targets): windowed likelihood eager and compiled, against our
own whole-grid eager path, in the same run.

    .venv/bin/pytest benchmarks/bench_ipmcmc.py --benchmark-only

One round each (a step is 200 sequential MH iterations; the whole-grid path takes tens of
seconds per step). No R-hat extensions (``max_extensions=0``), so every variant does the
same work. Set ``BENCH_IPMCMC_BURN_IN`` to shorten the chains (the cost is linear in
``burn_in + N / C``).
"""

import os

import pytest
import torch

from torchmcmcpf.filters.ipmcmc import IPMCMCFilter
from torchmcmcpf.scenarios.ground_radar import ground_radar

NP, CHAINS, TARGETS = 5000, 50, 10
BURN_IN = int(os.environ.get("BENCH_IPMCMC_BURN_IN", "100"))


@pytest.fixture(scope="module")
def problem():
    g = torch.Generator().manual_seed(0)
    scn = ground_radar(TARGETS, 2, 1, generator=g)
    x0 = scn.initial_particles(NP, generator=g)
    return scn, x0


@pytest.mark.parametrize("variant", ["window-eager", "window-compiled", "grid-eager"])
def test_ipmcmc_step(benchmark, problem, variant):
    scn, x0 = problem
    sensor = scn.sensor
    method = "grid" if variant.startswith("grid") else "window"
    sensor.method = method
    try:
        filt = IPMCMCFilter(scn.motion, sensor, NP, num_chains=CHAINS, burn_in=BURN_IN, max_extensions=0,
                            compile=variant.endswith("compiled"))
        state = filt.init(x0)
        z = scn.measurements[0]
        if filt.compile:  # compile outside the timed region
            filt.step(state, z, generator=torch.Generator().manual_seed(1))
        benchmark.extra_info.update(variant=variant, iterations_per_step=BURN_IN + NP // CHAINS)
        benchmark.pedantic(lambda: filt.step(state, z, generator=torch.Generator().manual_seed(2)),
                           rounds=1, iterations=1)
    finally:
        sensor.method = "window"
