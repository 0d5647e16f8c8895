"""The library's select against ATen's (benchmarks/README.md, births and deaths): ``where`` of
the moves' layouts (a chain's accept flag over its ``(K, D)`` state, a slot's flag over its
``D`` coordinates, a flat select with a scalar), a packed block read back (``unpacked``), each
by the C loop and by ``torch.where`` (the same bits); and what a user times, the births/deaths
MCMC-PF's public ``forward`` (``reproduce septier-birth-death``'s filter, B = 10 runs, 3 steps
after 30) with the loops and with every select left to ATen (``MIN_ELEMENTS`` above every size).
Compare within one run, one thread:

    BENCH_THREADS=1 pytest benchmarks/bench_select.py --benchmark-only --benchmark-group-by=group

The floor of a select is a copy of its output (``clone``, grouped with it).
"""

import pytest
import torch

from torchmcmcpf._native import select
from torchmcmcpf.experiments._shards import shard_generator
from torchmcmcpf.experiments.septier_birth_death import BirthDeathSettings, _filters, our_problem
from torchmcmcpf.scenarios.septier import septier

G = torch.Generator().manual_seed(0)
B, C, K, D = 10, 1000, 5, 4  # the births/deaths MCMC-PF's chains
X, Y = torch.randn(B, C, K, D, generator=G), torch.randn(B, C, K, D, generator=G)
ROW, SLOT = torch.rand(B, C, generator=G) < 0.5, torch.rand(B, C, K, generator=G) < 0.5
LAYOUTS = {
    "accept over (K, D)": (ROW[:, :, None, None], X, Y),
    "slot over D": (SLOT[..., None], X, Y),
    "flat with a scalar": (SLOT, X[..., 0].contiguous(), 0.0),
}
WAYS = {"ours": select.where, "aten": torch.where, "copy (floor)": lambda c, a, b: a.clone()}


@pytest.mark.parametrize("way", list(WAYS))
@pytest.mark.parametrize("layout", list(LAYOUTS))
def test_where(benchmark, layout, way):
    c, a, b = LAYOUTS[layout]
    benchmark.group = f"where {layout}"
    benchmark(WAYS[way], c, a, b)


@pytest.mark.parametrize("way", ["ours", "aten"])
def test_unpacked(benchmark, way, monkeypatch):
    flags = torch.rand(B, C * K, generator=G) < 0.4
    width, place = select.packed_places(flags)
    block = torch.randn(B, width, D, generator=G)
    fill = torch.randn(D, generator=G).expand(B, C * K, D)
    if way == "aten":
        monkeypatch.setattr(select, "MIN_ELEMENTS", 1 << 62)
    benchmark.group = "unpacked (B, C K, D)"
    benchmark(select.unpacked, block, place, flags, fill)


@pytest.mark.parametrize("way", ["ours", "aten"])
def test_birth_death_mcmc_forward(benchmark, way, monkeypatch):
    cfg = BirthDeathSettings(stonesoup=False)
    scn = septier(10, cfg.steps, generator=shard_generator("cpu", 0, 0))  # the study's first shard
    b, k = scn.alive.shape[1:]
    motion, sensor, existence, z = our_problem(scn, cfg, torch.device("cpu"))
    init = torch.zeros((b, cfg.particles, k, 4), dtype=z.z.dtype)
    warm, timed = (type(z)(*(t[a:e] for t in z)) for a, e in ((0, 30), (30, 33)))
    filt = _filters(cfg, motion, sensor, existence)["MCMC-PF"]
    if way == "aten":
        monkeypatch.setattr(select, "MIN_ELEMENTS", 1 << 62)
    with torch.inference_mode():
        state = filt(warm, init=init, generator=torch.Generator().manual_seed(0)).state
        benchmark.group = "births/deaths MCMC-PF forward, 3 steps of 10 runs"
        benchmark.extra_info.update(select=way, steps=3, runs=b)
        benchmark.pedantic(lambda: filt(timed, init=state, generator=torch.Generator().manual_seed(1)), rounds=3,
                           iterations=1)
