"""One batched pairwise-Kalman update of the group model (Septier et al. 2009, eqs. 42-58).

N = 4000 particles, N_max = K = 4 slots, B = 1 run, float64; every particle has its own
(random) pair of structures and existence patterns, so the transition is assembled per
particle (merges, splits, births, deaths, repulsion). One update = the configuration's
affine transition (``VirtualLeaderMotion.transition``) + ``pairwise_kalman_predict`` +
``pairwise_kalman_update``. Eager vs ``torch.compile`` in one group:

    pytest benchmarks/bench_group.py --benchmark-only --benchmark-group-by=group
"""

from __future__ import annotations

import pytest
import torch

from torchmcmcpf.models.group import (
    GroupExistence,
    KalmanStats,
    VirtualLeaderMotion,
    group_structures,
    pairwise_kalman_predict,
    pairwise_kalman_update,
)

N, K = 4000, 4


def problem():
    g = torch.Generator().manual_seed(0)
    motion = VirtualLeaderMotion(0.0006, 0.05, 0.001, 0.001, 0.2, 0.5, 5.0, 8.0, 12.0)
    existence = GroupExistence(0.2, 0.05, ((0, 5000), (0, 5000)))
    table = group_structures(K)
    pick = torch.randint(0, table.shape[0], (2, 1, N), generator=g)
    lp, lab = table[pick[0]], table[pick[1]]
    ep = torch.rand(1, N, K, generator=g) < 0.8
    e = torch.rand(1, N, K, generator=g) < 0.8
    pos_prev = 2000 + 500 * torch.rand(1, N, K, 2, generator=g, dtype=torch.float64)
    pos = pos_prev + 10 * torch.randn(1, N, K, 2, generator=g, dtype=torch.float64)
    A = torch.randn(1, N, 3 * K, 3 * K, generator=g, dtype=torch.float64)
    stats = KalmanStats(torch.randn(1, N, 2, 3 * K, generator=g, dtype=torch.float64),
                        A @ A.mT + torch.eye(3 * K, dtype=torch.float64))
    return motion, existence, (stats.mean, stats.cov, pos_prev, pos, lp, lab, ep, e)


def make_update(motion, existence):
    def update(mean, cov, pos_prev, pos, lp, lab, ep, e):
        tr = motion.transition(pos_prev, lp, lab, ep, e, existence=existence)
        pred = pairwise_kalman_predict(KalmanStats(mean, cov), pos_prev, tr)
        log_pred, stats = pairwise_kalman_update(pred, pos)
        return log_pred, stats.mean, stats.cov
    return update


def _run(benchmark, fn, args):
    with torch.no_grad():
        fn(*args)  # warm-up (and compilation)
        out = benchmark.pedantic(fn, args=args, rounds=10, iterations=1)
    assert out[0].shape == (1, N) and torch.isfinite(out[0]).all()


def test_pairwise_kalman_update_eager(benchmark):
    motion, existence, args = problem()
    benchmark.group = f"group-pairwise-kalman-N{N}-K{K}"
    _run(benchmark, make_update(motion, existence), args)


@pytest.mark.compile
def test_pairwise_kalman_update_compiled(benchmark):
    motion, existence, args = problem()
    benchmark.group = f"group-pairwise-kalman-N{N}-K{K}"
    _run(benchmark, torch.compile(make_update(motion, existence), dynamic=False), args)
