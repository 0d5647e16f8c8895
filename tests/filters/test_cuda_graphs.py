"""``filters.base.compile_kernel`` on a GPU: CUDA graphs give the plain compiled results.

Skipped without CUDA (CI has none); run on a GPU with ``pytest tests/filters/test_cuda_graphs.py``.
The MCMC filters keep every iteration's chain state (R-hat trace, kept samples), so a graph
replay that overwrote earlier outputs would change the result: these tests would see it.
"""

import pytest
import torch

from torchmcmcpf.filters import IPMCMCFilter, MCMCFilter, SIRFilter
from torchmcmcpf.filters.base import compile_kernel
from torchmcmcpf.scenarios.ground_radar import ground_radar

pytestmark = pytest.mark.skipif(not torch.cuda.is_available(), reason="needs CUDA")


def _run(make, graphs: bool):
    scn = ground_radar(3, 3, 2, generator=torch.Generator("cuda").manual_seed(0), device="cuda")
    x0 = scn.initial_particles(200, generator=torch.Generator("cuda").manual_seed(1))
    filt = make(scn).to("cuda")
    if not graphs:  # the same kernels without CUDA graphs
        filt._compiled = filt._kernel(lambda f: torch.compile(f, fullgraph=True, dynamic=False))
    return filt(scn.measurements, init=x0, generator=torch.Generator("cuda").manual_seed(2))


@pytest.mark.parametrize("make", [
    lambda s: IPMCMCFilter(s.motion, s.sensor, 200, num_chains=10, burn_in=10, compile_step=True),
    lambda s: MCMCFilter(s.motion, s.sensor, 200, num_chains=10, burn_in=5, moves="mixture", compile_step=True),
    lambda s: SIRFilter(s.motion, s.sensor, 200, compile_step=True),
], ids=["ipmcmc", "mcmc", "sir"])
def test_graphs_match_plain_compile(make):
    graphed, plain = _run(make, True), _run(make, False)
    torch.testing.assert_close(graphed.state.x, plain.state.x, rtol=0, atol=0)
    torch.testing.assert_close(graphed.mean, plain.mean, rtol=0, atol=0)


def test_outputs_survive_the_next_replay():
    f = compile_kernel(lambda x: x * 2.0)
    a = f(torch.ones(4, device="cuda"))
    b = f(torch.full((4,), 3.0, device="cuda"))
    assert a.tolist() == [2.0] * 4 and b.tolist() == [6.0] * 4
