"""The exclusion factor's C loops (``torchmcmcpf/_native/exclusion.c``) against the tensor
path (``torchmcmcpf._native.tensor_path``), through the model's methods the moves call:
``Exclusion.log_factor`` (a state's whole factor, the joint draws') and ``Exclusion.log_change``
(a slot's move), on the births/deaths MCMC-PF's chains (10 runs x 1000 chains, 5 slots, about
60 % live) and the crossing's (5 runs x 50 chains, 5 slots, all live); float32 states, one
thread. Compare within one run:

    BENCH_THREADS=1 pytest benchmarks/bench_exclusion.py --benchmark-only --benchmark-group-by=group
"""

import pytest
import torch

from torchmcmcpf import _native
from torchmcmcpf.models.multitarget import Exclusion

G = torch.Generator().manual_seed(0)
SCENES = {"births/deaths (10, 1000, 5)": ((10, 1000), 0.6), "crossing (5, 50, 5)": ((5, 50), 1.0)}
PATHS = {"C loop": lambda: torch.no_grad(), "tensors": _native.tensor_path}


def _chains(scene):
    lead, live = SCENES[scene]
    u = torch.rand(lead + (5, 2), generator=G) * 50.0  # resolution coordinates over 50 cells
    alive = torch.rand(lead + (5,), generator=G) < live if live < 1 else None
    return u, alive, torch.rand(lead + (2,), generator=G) * 50.0, torch.randint(0, 5, lead, generator=G)


@pytest.mark.parametrize("path", list(PATHS))
@pytest.mark.parametrize("scene", list(SCENES))
@pytest.mark.parametrize("method", ["log_factor", "log_change"])
def test_exclusion(benchmark, method, scene, path):
    u, alive, u_n, n = _chains(scene)
    args = (u, alive) if method == "log_factor" else (u, u_n, n, alive)
    benchmark.group = f"{method} {scene}"
    with PATHS[path]():
        benchmark(getattr(Exclusion(), method), *args)
