"""The grid sensors' GPU forms (the dense windowed form's broadcast products, no bmm, no
top-k) equal the CPU's, in float64, eager and compiled. Skipped without CUDA (CI has none);
run on a GPU with ``pytest tests/models/test_grid_cuda.py``.
"""

import pytest
import torch

from torchmcmcpf.scenarios.ground_radar import ground_radar

pytestmark = pytest.mark.skipif(not torch.cuda.is_available(), reason="needs CUDA")


@pytest.mark.parametrize("compiled", [False, True], ids=["eager", "compiled"])
def test_window_and_delta_on_cuda_equal_cpu(compiled):
    g = torch.Generator().manual_seed(5)
    scn = ground_radar(10, 1, 2, generator=g)
    sensor = scn.sensor.double()
    x = scn.initial_particles(64, generator=g).double()
    z = scn.measurements[0].double()
    slot = torch.randint(10, (2, 64), generator=g)
    x_n = torch.take_along_dim(x, slot[..., None, None], 2)[:, :, 0] + 20 * torch.randn(
        2, 64, 5, generator=g, dtype=torch.float64)
    want_w, want_d = sensor.log_likelihood_window(x, z), sensor.log_likelihood_delta(x, x_n, slot, z)
    gpu = sensor.to("cuda")
    window, delta = gpu.log_likelihood_window, gpu.log_likelihood_delta
    if compiled:
        window = torch.compile(window, fullgraph=True, dynamic=False)
        delta = torch.compile(delta, fullgraph=True, dynamic=False)
    got_w = window(x.cuda(), z.cuda()).cpu()
    got_d = delta(x.cuda(), x_n.cuda(), slot.cuda(), z.cuda()).cpu()
    torch.testing.assert_close(got_w, want_w, rtol=1e-12, atol=1e-9 * want_w.abs().max().item())
    torch.testing.assert_close(got_d, want_d, rtol=1e-12, atol=1e-9 * want_d.abs().max().item())
