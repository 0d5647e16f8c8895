"""No gradient mode against inference mode (docs/performance.md): the public ``forward`` of the
IP-MCMC-PF on the births/deaths scene (``reproduce septier-birth-death``'s filter, B = 10 runs,
3 steps after 2 warm ones) and the public ``step`` of the eager radar IP-MCMC-PF (Np = 500, 50
chains, 10 targets), each under ``torch.no_grad()`` and ``torch.inference_mode()``, the same
bits. Compare within one run: ``--benchmark-group-by=group``.

    pytest benchmarks/bench_modes.py --benchmark-only --benchmark-group-by=group
"""

import pytest
import torch

from torchmcmcpf import IPMCMCFilter
from torchmcmcpf.experiments._shards import shard_generator
from torchmcmcpf.experiments.septier_birth_death import BirthDeathSettings, _filters
from torchmcmcpf.scenarios import ground_radar
from torchmcmcpf.scenarios.septier import septier

MODES = {"no_grad": torch.no_grad, "inference_mode": torch.inference_mode}


@pytest.mark.parametrize("mode", list(MODES))
def test_birth_death_forward_modes(benchmark, mode):
    cfg = BirthDeathSettings(stonesoup=False)
    scn = septier(10, 5, generator=shard_generator("cpu", 0, 0))
    b, k = scn.alive.shape[1:]
    init = torch.zeros((b, cfg.particles, k, 4), dtype=torch.float64)
    z = scn.measurements
    warm, timed = (type(z)(*(t[a:e] for t in z)) for a, e in ((0, 2), (2, 5)))
    filt = _filters(cfg, scn.motion, scn.sensor, scn.existence)["IP-MCMC-PF"]
    with MODES[mode]():
        state = filt(warm, init=init, generator=torch.Generator().manual_seed(0)).state
        benchmark.group = "modes-birth-death-ipmcmc"
        benchmark.extra_info.update(mode=mode, steps=3, runs=b)
        benchmark.pedantic(lambda: filt(timed, init=state, generator=torch.Generator().manual_seed(1)), rounds=3,
                           iterations=1)


@pytest.mark.parametrize("mode", list(MODES))
def test_radar_ipmcmc_step_modes(benchmark, mode):
    scn = ground_radar(10, 2, 1, generator=torch.Generator().manual_seed(0))
    filt = IPMCMCFilter(scn.motion, scn.sensor, 500, num_chains=50, burn_in=100, max_extensions=0)
    state = filt.init(scn.initial_particles(500, generator=torch.Generator().manual_seed(1)))
    z = scn.measurements[0]
    with MODES[mode]():
        filt.step(state, z, generator=torch.Generator().manual_seed(1))  # warm-up
        benchmark.group = "modes-radar-ipmcmc"
        benchmark.extra_info.update(mode=mode)
        benchmark.pedantic(lambda: filt.step(state, z, generator=torch.Generator().manual_seed(2)), rounds=3,
                           iterations=1)
