"""IP-MCMC-PF time per step on the ground radar (paper 000 Table II setting: Np = 500 and
5000, 50 chains, burn-in 100, 10 targets): windowed likelihood eager and compiled, against our
own whole-grid eager path, in the same run.

    .venv/bin/pytest benchmarks/bench_ipmcmc.py --benchmark-only --benchmark-group-by=group

Each exchange iteration scores the moved slot by ``sensor.log_likelihood_delta`` (the cells
of its old and new box, point spreads truncated to the boxes; for the whole grid, two
whole-grid evaluations). No R-hat extensions (``max_extensions=0``), so every variant does
the same ``burn_in + Np / 50`` iterations. The whole-grid path is timed with ``burn_in = 0``
(``Np / 50`` iterations, one round): multiply by ``(100 + Np / 50) / (Np / 50)`` (11 at
Np = 500) for a full step; the cost is linear in the number of iterations. Set
``BENCH_IPMCMC_BURN_IN`` to shorten the windowed chains too. ``window-eager-hmc`` adds the
HMC refinement (``HMCRefine(step_size=0.15, num_leapfrog=5, every=20)``: 6 transitions per
step; Np = 500 only), the README's "HMC as a move" comparison. ``window-compiled-no-cache``
turns the chains' amplitude cache off (``sensor.amplitude_cache`` returning ``None``): every
move then sums the other targets' spreads at its two boxes (``log_likelihood_delta``), the
reference for the cache's speed-up. ``test_ipmcmc_step_cuda`` (GPU only) compares the
captured segment with one CUDA graph per iteration.
"""

import dataclasses
import os

import pytest
import torch

from torchmcmcpf.filters.ipmcmc import IPMCMCFilter
from torchmcmcpf.filters.partitioned import PartitionedSIRFilter
from torchmcmcpf.kernels.hmc_refine import HMCRefine
from torchmcmcpf.models.multitarget import Recapture
from torchmcmcpf.scenarios.ground_radar import ground_radar

CHAINS, TARGETS = 50, 10
BURN_IN = int(os.environ.get("BENCH_IPMCMC_BURN_IN", "100"))


@pytest.fixture(scope="module")
def scenario():
    return ground_radar(TARGETS, 20, 1, generator=torch.Generator().manual_seed(0))


@pytest.mark.parametrize("variant", ["window-eager", "window-compiled", "window-compiled-no-cache", "window-eager-hmc",
                                     "grid-eager-no-burn-in"])
@pytest.mark.parametrize("n", [500, 5000])
def test_ipmcmc_step(benchmark, scenario, variant, n):
    if variant.startswith("grid") and n > 500:
        pytest.skip("whole grid: timed at Np = 500 only (seconds per iteration at 50 chains)")
    if variant.endswith("hmc") and n > 500:
        pytest.skip("HMC refinement: timed at Np = 500 only")
    sensor = scenario.sensor
    sensor.method = "grid" if variant.startswith("grid") else "window"
    if variant.endswith("no-cache"):
        sensor.amplitude_cache = lambda *args, **kwargs: None  # an instance attribute: the cache off
    burn_in = 0 if variant.startswith("grid") else BURN_IN
    try:
        x0 = scenario.initial_particles(n, generator=torch.Generator().manual_seed(1))
        hmc = HMCRefine(step_size=0.15, num_leapfrog=5, every=20) if variant.endswith("hmc") else None
        filt = IPMCMCFilter(scenario.motion, sensor, n, num_chains=CHAINS, burn_in=burn_in, max_extensions=0,
                            compile_step="compiled" in variant, hmc=hmc)
        state = filt.init(x0)
        z = scenario.measurements[0]
        with torch.no_grad():
            filt.step(state, z, generator=torch.Generator().manual_seed(1))  # warm-up, compilation
            benchmark.group = f"ipmcmc-step-N{n}"
            benchmark.extra_info.update(variant=variant, iterations_per_step=burn_in + n // CHAINS)
            benchmark.pedantic(lambda: filt.step(state, z, generator=torch.Generator().manual_seed(2)),
                               rounds=1 if variant.startswith("grid") else 3, iterations=1)
    finally:
        sensor.method = "window"
        sensor.__dict__.pop("amplitude_cache", None)


@pytest.mark.skipif(not torch.cuda.is_available(), reason="needs CUDA")
@pytest.mark.parametrize("variant", ["captured-segment", "per-iteration-graphs"])
@pytest.mark.parametrize("b", [1, 100])
def test_ipmcmc_step_cuda(benchmark, variant, b):
    """On a GPU, Np = 5000, compiled: each segment of MH iterations captured as one CUDA graph
    (``runtime.Program.capture``, what ``compile_step=True`` does) against one graph replay per
    iteration (the kernel without its ``capture``), B = 1 and B = 100 runs.
    """
    n = 5000
    scn = ground_radar(TARGETS, 20, b, generator=torch.Generator("cuda").manual_seed(0), device="cuda")
    x0 = scn.initial_particles(n, generator=torch.Generator("cuda").manual_seed(1))
    filt = IPMCMCFilter(scn.motion, scn.sensor, n, num_chains=CHAINS, burn_in=BURN_IN, max_extensions=0,
                        compile_step=True).to("cuda")
    if variant == "per-iteration-graphs":
        program = filt.bound.program
        filt._bound = dataclasses.replace(filt.bound, program=lambda *args: program(*args))  # no capture(): a replay
    state, z = filt.init(x0), scn.measurements[0]

    def step():
        filt.step(state, z, generator=torch.Generator("cuda").manual_seed(2))
        torch.cuda.synchronize()

    with torch.no_grad():
        step()  # warm-up: compilation, capture
        benchmark.group = f"ipmcmc-step-cuda-N{n}-B{b}"
        benchmark.extra_info.update(variant=variant, device=torch.cuda.get_device_name())
        benchmark.pedantic(step, rounds=5, iterations=1)


TERMS = {"paper": dict(exclusion=None, recapture=None), "exclusion": dict(recapture=None),
         "recapture": dict(exclusion=None), "default": {},
         "default-independent-sources": dict(recapture=Recapture(p_same_source=0.0)),
         "default-joint-pairs": dict(joint_pairs=1.5)}


@pytest.mark.parametrize("compiled", [False, True], ids=["eager", "compiled"])
@pytest.mark.parametrize("terms", list(TERMS))
@pytest.mark.parametrize("n", [500, 5000])
def test_ipmcmc_step_multitarget_terms(benchmark, scenario, terms, compiled, n):
    """The cost of the multitarget prior's terms (issue 22): the public ``filt.step`` with the
    paper's factorised target and exchange move, with exclusion only, with re-capture only
    (relocation noise drawn from the frame's peaks, every 10th iteration a two-slot move) and
    with both (the default), and the default with the two-slot move's slots from independent
    particles (``p_same_source = 0``: no sources kept in the chains), and the default with joint
    pairs (``joint_pairs = 1.5``: a paired slot's proposal made in each iteration from its
    pair's source), Np = 500 and 5000, 50 chains, 10 targets, no R-hat extensions.
    Compare within one run: ``--benchmark-group-by=group``.
    """
    x0 = scenario.initial_particles(n, generator=torch.Generator().manual_seed(1))
    filt = IPMCMCFilter(scenario.motion, scenario.sensor, n, num_chains=CHAINS, burn_in=BURN_IN, max_extensions=0,
                        compile_step=compiled, **TERMS[terms])
    state = filt.init(x0)
    z = scenario.measurements[0]
    with torch.no_grad():
        filt.step(state, z, generator=torch.Generator().manual_seed(1))  # warm-up, compilation
        benchmark.group = f"ipmcmc-terms-N{n}-{'compiled' if compiled else 'eager'}"
        benchmark.extra_info.update(terms=terms, threads=torch.get_num_threads())
        benchmark.pedantic(lambda: filt.step(state, z, generator=torch.Generator().manual_seed(2)), rounds=3,
                           iterations=1)


@pytest.mark.parametrize("terms", ["plain", "exclusion", "default"])
@pytest.mark.parametrize("n", [500, 5000])
def test_partitioned_step_terms(benchmark, scenario, terms, n):
    """The partitioned PF's public ``filt.step`` on the same 10-target radar, eager: without
    the multitarget prior's terms, with exclusion only, and with the default exclusion and
    re-capture (one partition a step draws a share of its particles from the frame's peaks;
    :mod:`torchmcmcpf.filters.partitioned`). Compare within one run:
    ``--benchmark-group-by=group``; the floor is the slot changes of ``B N K`` boxes.
    """
    kw = {"plain": dict(exclusion=None, recapture=None), "exclusion": dict(recapture=None), "default": {}}[terms]
    filt = PartitionedSIRFilter(scenario.motion, scenario.sensor, n, **kw)
    state = filt.init(scenario.initial_particles(n, generator=torch.Generator().manual_seed(1)))
    z = scenario.measurements[0]
    with torch.no_grad():
        filt.step(state, z, generator=torch.Generator().manual_seed(1))  # warm-up
        benchmark.group = f"partitioned-terms-N{n}"
        benchmark.extra_info.update(terms=terms, threads=torch.get_num_threads())
        benchmark.pedantic(lambda: filt.step(state, z, generator=torch.Generator().manual_seed(2)), rounds=5,
                           iterations=1)
