"""The IP-MCMC-PF's R-hat rule by scene (issue 49 item 4): how often it extends a step, what
an extension costs, whether it buys accuracy, and why it does not pass. Run from the
repository root (about 25 minutes on one thread; ``--quick``: a minute):

    python benchmarks/rhat_by_scene.py

Prints, for Table II's 10-target scene (Np = 500, 50 chains, burn-in 100) and the crossing
study's scenes (seed 0's shard generators, shards of 5 runs x 80 steps), with the defaults
(at most 2 extensions) and without extensions, in one process: the share of steps
extended, the median R-hat after the rule, the time per step and run, and on Table II the
RMSE (mean over runs of each run's RMSE, with its standard error) and the track losses.
Then the long-chain reference (Table II, burn-in 1000, no extensions) and, from each filter's
kept states, how far each chain's mean slot position lies from the median of the chains
(which chains disagree, and where their slots sit). Eager, under ``torch.inference_mode()``,
glibc's allocator tuned as ``python -m torchmcmcpf`` tunes it.
"""

from __future__ import annotations

import argparse
import time

import torch

from torchmcmcpf import metrics
from torchmcmcpf.experiments._shards import shard_generator
from torchmcmcpf.filters.ipmcmc import IPMCMCFilter
from torchmcmcpf.runtime import tune_cpu_allocator
from torchmcmcpf.scenarios import crossing, ground_radar

CHAINS = 50
OFF = 10.0  # [m] a chain's mean slot position this far from the chains' median is "off" (a range cell)
#: the rule as the defaults run it, and switched off (the same burn-in)
RULE = {"defaults (at most 2 extensions)": dict(burn_in=100), "no extensions": dict(burn_in=100, max_extensions=0)}


def _run(scn, init, generator: torch.Generator, **kw):
    """One filter over the scene: ``(result, seconds)`` (kept states in ``result.history``)."""
    filt = IPMCMCFilter(scn.motion, scn.sensor, init.shape[1], num_chains=CHAINS, **kw)
    start = time.perf_counter()
    with torch.inference_mode():
        res = filt(scn.measurements, init=init, generator=generator, history=True)
    return res, time.perf_counter() - start


def _chains_off(res, truth: torch.Tensor) -> str:
    """Which chains disagree: each chain's mean slot position over its kept states against
    the median over the chains; where the off slots sit against the true targets.
    """
    xs = res.history.x  # (T, B, N, K, D), slots labelled as the estimate's
    t, b, n, k, _ = xs.shape
    pos = xs[..., [0, 2]].reshape(t, b, CHAINS, n // CHAINS, k, 2).mean(3)  # (T, B, C, K, 2)
    off = (pos - pos.median(2, keepdim=True).values).norm(dim=-1) > OFF  # (T, B, C, K)
    d = (pos.unsqueeze(-2) - truth[..., [0, 2]].unsqueeze(2).unsqueeze(3)).norm(dim=-1)  # (T, B, C, K, K)
    own = torch.diagonal(d, dim1=-2, dim2=-1)
    other = d.masked_fill(torch.eye(k, dtype=torch.bool), float("inf")).min(-1).values
    line = (f"steps with a chain off: {off.any(2).any(-1).float().mean():.1%}, chains off where one is: "
            f"{off.sum(2)[off.any(2)].float().mean():.2f} of {CHAINS}")
    if off.any():
        line += (f"; off slots near another target {(other[off] < OFF).float().mean():.0%}, near their own "
                 f"{(own[off] < OFF).float().mean():.0%}, their median distance to their own "
                 f"{own[off].median():.1f} m")
    return line


def _report(name: str, ex: dict, seconds: float, runs: int, steps: int) -> None:
    """One line per filter from its ``(T, B)`` extras ``rhat``, ``extensions``, ``rhat_dim``."""
    dims = torch.bincount(ex["rhat_dim"].flatten().long(), minlength=5).tolist()
    print(f"  {name}: steps extended {(ex['extensions'] > 0).float().mean():.1%} "
          f"({ex['extensions'].mean():.2f} extensions a step), R-hat median {ex['rhat'].median():.2f}, "
          f"below 1.1 in {(ex['rhat'] < 1.1).float().mean():.1%}, component deciding [x, vx, y, vy, rho] {dims}, "
          f"{1e3 * seconds / runs / steps:.0f} ms a step and run", flush=True)


def table2(runs: int, long_runs: int, steps: int) -> None:
    print(f"Table II, 10 targets, Np = 500 ({runs} runs x {steps} steps; long chains {long_runs} runs)")
    configs = {**RULE, "long chains (burn-in 1000, no extensions)": dict(burn_in=1000, max_extensions=0)}
    for name, kw in configs.items():
        b = long_runs if "long" in name else runs
        scn = ground_radar(10, steps, b, generator=shard_generator("cpu", 0, 0))
        init, truth = scn.initial_particles(500, generator=shard_generator("cpu", 0, 1)), scn.truth
        res, sec = _run(scn, init, shard_generator("cpu", 0, 2), **kw)
        _report(name, res.info.extras, sec, b, steps)
        rmse = metrics.position_error(res.mean, truth).square().mean(-1).mean(0).sqrt()  # (B,)
        lost = metrics.track_loss(res.mean, truth).float().mean()
        print(f"    RMSE {rmse.mean():.2f} +- {rmse.std() / b ** 0.5:.2f} m (runs' mean, standard error), "
              f"lost {lost:.0%}; {_chains_off(res, truth)}")


def crossing_scenes(shards: int, per: int, steps: int) -> None:
    print(f"crossing ({shards} shards of {per} runs x {steps} steps, seed 0)")
    seconds = {name: 0.0 for name in RULE}
    results: dict = {name: [] for name in RULE}
    for s in range(shards):
        g = shard_generator("cpu", 0, s)
        scn = crossing(2, steps, per, generator=g)
        init = scn.initial_particles(500, generator=g)
        for name, kw in RULE.items():
            res, sec = _run(scn, init, torch.Generator().manual_seed(s), **kw)
            seconds[name] += sec
            results[name].append(res)
            if s == 0:
                print(f"    {name}, shard 0: {_chains_off(res, scn.truth)}")
    for name, parts in results.items():
        ex = {key: torch.cat([r.info.extras[key] for r in parts], 1) for key in ("rhat", "extensions", "rhat_dim")}
        _report(name, ex, seconds[name], shards * per, steps)
    first, second = RULE
    print(f"  cost ratio {seconds[first] / seconds[second]:.2f}x")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--quick", action="store_true", help="small sizes (a minute)")
    args = parser.parse_args()
    torch.set_num_threads(1)
    tune_cpu_allocator()
    if args.quick:
        table2(runs=2, long_runs=2, steps=3)
        crossing_scenes(shards=1, per=1, steps=6)
    else:
        table2(runs=20, long_runs=2, steps=20)
        crossing_scenes(shards=4, per=5, steps=80)


if __name__ == "__main__":
    main()
