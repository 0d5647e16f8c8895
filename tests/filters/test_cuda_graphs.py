"""``runtime.compile_program`` on a GPU: CUDA graphs (per call, and a whole loop captured
by ``Program.capture``) give the plain compiled results.

Skipped without CUDA (CI has none); run on a GPU with ``pytest tests/filters/test_cuda_graphs.py``.
The MCMC filters keep every iteration's chain state (R-hat trace, kept samples), so a graph
replay that overwrote earlier outputs would change the result: these tests would see it.
"""

import pytest
import torch

from torchmcmcpf.filters import IPMCMCFilter, MCMCFilter, SIRFilter
from torchmcmcpf.runtime import compile_program
from torchmcmcpf.scenarios.ground_radar import ground_radar

pytestmark = pytest.mark.skipif(not torch.cuda.is_available(), reason="needs CUDA")


def _run(make, graphs: bool):
    scn = ground_radar(3, 3, 2, generator=torch.Generator("cuda").manual_seed(0), device="cuda")
    x0 = scn.initial_particles(200, generator=torch.Generator("cuda").manual_seed(1))
    filt = make(scn).to("cuda")
    if not graphs:  # the same kernels without CUDA graphs
        filt._bound = filt.bind(filt.motion, filt.sensor, filt.settings, filt.existence,
                                compile=lambda f: torch.compile(f, fullgraph=True, dynamic=False))
    return filt(scn.measurements, init=x0, generator=torch.Generator("cuda").manual_seed(2))


@pytest.mark.parametrize("make, rtol", [
    # the IP-MCMC-PF captures each segment of MH iterations whole: the same compiled kernels
    (lambda s: IPMCMCFilter(s.motion, s.sensor, 200, num_chains=10, burn_in=10, compile_step=True), 0.0),
    # per-call graphs come from a second compilation (mode="reduce-overhead"), whose
    # reductions may round differently (seen on the SIR step's weights: 4e-6 relative, H200)
    (lambda s: MCMCFilter(s.motion, s.sensor, 200, num_chains=10, burn_in=5, moves="mixture", compile_step=True),
     1e-5),
    (lambda s: SIRFilter(s.motion, s.sensor, 200, compile_step=True), 1e-5),
], ids=["ipmcmc", "mcmc", "sir"])
def test_graphs_match_plain_compile(make, rtol):
    graphed, plain = _run(make, True), _run(make, False)
    torch.testing.assert_close(graphed.state.x, plain.state.x, rtol=rtol, atol=0)
    torch.testing.assert_close(graphed.mean, plain.mean, rtol=rtol, atol=0)


def test_outputs_survive_the_next_replay():
    f = compile_program(lambda x: x * 2.0)
    a = f(torch.ones(4, device="cuda"))
    b = f(torch.full((4,), 3.0, device="cuda"))
    assert a.tolist() == [2.0] * 4 and b.tolist() == [6.0] * 4


def _loop(program, x, n):
    out = []
    for _ in range(n):
        x = program(x)
        out.append(x)
    return x, torch.stack(out)


def test_capture_replays_a_loop_and_its_outputs_survive():
    f = compile_program(lambda x: x * 2.0 + 1.0)
    a = f.capture(_loop, torch.ones(4, device="cuda"), 3)
    b = f.capture(_loop, torch.full((4,), 2.0, device="cuda"), 3)  # a replay on new inputs
    assert a[0].tolist() == [15.0] * 4 and a[1][:, 0].tolist() == [3.0, 7.0, 15.0]
    assert b[0].tolist() == [23.0] * 4 and b[1][:, 0].tolist() == [5.0, 11.0, 23.0]
    assert len(f._loops) == 1
    c = f.capture(_loop, torch.ones(5, device="cuda"), 2)  # another signature: another graph
    assert c[0].tolist() == [7.0] * 5 and len(f._loops) == 2
