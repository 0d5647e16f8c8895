"""HMC move of paper 003 (Maroulas and Stinis 2010): autograd vs closed-form gradient, and
the whole filter step vs the generic particle filter, in the same run.

    .venv/bin/pytest benchmarks/bench_hmc.py --benchmark-only --benchmark-group-by=group

1. ``hmc-move``: 100 HMC rounds of one leapfrog step of 0.1 (the paper's setting) over the
   process noise ``u`` of B x N x K chains, one per target slot, with the potential of
   paper 003 eq. 29 for a given association (linear position sensor). Gradient from
   ``torch.autograd`` against the closed form
   ``d/du log target = c sigma (z - H(A x + G u)) / s_obs^2 - u`` (``c = [T^2/2]``).
2. ``filter-step``: one step of the paper-003 scenario (4 targets, exact association over
   24 permutations, linear sensor) for the improved filter (N = 100, 100 HMC rounds) and
   the generic particle filter (N = 120, and N = 12000); the ratio of the times gives the
   number of generic-PF particles that costs as much as the improved filter.

Timings on a shared machine are noisy; compare ratios within one run.
"""

import math
import os

import pytest
import torch

from torchmcmcpf.filters.resample_move import ResampleMoveFilter
from torchmcmcpf.kernels.hmc import hmc
from torchmcmcpf.models.sensors.association import PointFrame
from torchmcmcpf.scenarios import maroulas as M
from torchmcmcpf.state import ParticleState

B = int(os.environ.get("BENCH_HMC_RUNS", "10"))
N, K = 100, 4
D64 = torch.float64


@pytest.fixture(scope="module")
def move_problem():
    g = torch.Generator().manual_seed(0)
    motion = M.WhiteAccelerationMotion()
    x_prev = torch.randn(B, N, K, 4, generator=g, dtype=D64) * 50
    z = (motion.propagate(x_prev, torch.randn(B, N, K, 2, generator=g, dtype=D64))[..., [0, 2]]
         + torch.randn(B, N, K, 2, generator=g, dtype=D64))
    G = motion.G.to(D64)[[0, 2]]  # (2, 2): position rows of B sigma
    mean_pos = motion.mean(x_prev)[..., [0, 2]]

    def log_target(u):  # eq. 29 with s_obs = 1, one chain per slot: (B, N, K)
        r = z - mean_pos - u @ G.mT
        return -0.5 * r.square().sum(-1) - 0.5 * u.square().sum(-1)

    def grad(u):
        return (z - mean_pos - u @ G.mT) @ G - u

    return log_target, grad, torch.zeros(B, N, K, 2, dtype=D64)


@pytest.mark.parametrize("gradient", ["autograd", "closed-form"])
def test_hmc_move(benchmark, move_problem, gradient):
    log_target, grad, u0 = move_problem
    benchmark.group = "hmc-move"
    benchmark.extra_info.update(chains=B * N * K, rounds=100, gradient=gradient)
    benchmark.pedantic(
        lambda: hmc(u0, log_target, step_size=0.1, num_leapfrog=1, num_steps=100,
                    generator=torch.Generator().manual_seed(1),
                    grad_fn=grad if gradient == "closed-form" else None),
        rounds=3, iterations=1, warmup_rounds=1)


@pytest.fixture(scope="module")
def step_problem():
    g = torch.Generator().manual_seed(0)
    sensor = M.paper_sensor("linear")
    data = M.simulate(B, 10, sensor=sensor, generator=g)
    return sensor, data


@pytest.mark.parametrize("variant, n, hmc_steps", [("improved", 100, 100), ("generic", 120, 0),
                                                   ("generic", 12000, 0)])
def test_filter_step(benchmark, step_problem, variant, n, hmc_steps):
    sensor, data = step_problem
    g = torch.Generator().manual_seed(1)
    t = 8  # 4 targets alive
    x = M.birth_particles(sensor, data.z_slot[t - 1], n, generator=g)
    state = ParticleState(x, torch.full((B, n), -math.log(n), dtype=D64), data.alive[t].unsqueeze(1).expand(B, n, K))
    frame = PointFrame(data.frames.z[t], data.frames.mask[t])
    filt = ResampleMoveFilter(M.WhiteAccelerationMotion(), sensor, n, num_hmc_steps=hmc_steps)
    benchmark.group = "filter-step"
    benchmark.extra_info.update(variant=variant, particles=n, runs=B, hmc_steps=hmc_steps)
    benchmark.pedantic(lambda: filt.step(state, frame, generator=torch.Generator().manual_seed(2)),
                       rounds=3, iterations=1, warmup_rounds=1)
