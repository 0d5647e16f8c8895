"""What the IP-MCMC-PF's default terms cost on the crossing (issue 49 item 5: the defaults
within 1.15x the paper's step): the crossing study's IP-MCMC-PF (Np = 500, 50 chains,
burn-in 100) with its defaults, without the exclusion term, without re-capture, and as paper
000's filter (neither), on seed 0's first shard of 5 runs, public ``forward`` over steps
2-9 from one state after steps 0-1, the four filters in turn in one process, one thread;
CPU time, the best of ``--rounds`` rounds. Run from the repository root:

    python benchmarks/crossing_terms.py            # eager, as the study runs
    python benchmarks/crossing_terms.py --compiled  # compile_step=True (first call timed apart)

Prints ms per step and run for each and its ratio to the paper's filter.
"""

from __future__ import annotations

import argparse
import time

import torch

from torchmcmcpf.experiments._shards import shard_generator
from torchmcmcpf.experiments.crossing import CrossingSettings
from torchmcmcpf.filters import IPMCMCFilter
from torchmcmcpf.runtime import tune_cpu_allocator
from torchmcmcpf.scenarios.crossing import crossing

VARIANTS = {"defaults": {}, "no exclusion": {"exclusion": None}, "no re-capture": {"recapture": None},
            "paper": {"exclusion": None, "recapture": None}}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--compiled", action="store_true", help="compile_step=True")
    parser.add_argument("--rounds", type=int, default=4)
    args = parser.parse_args()
    torch.set_num_threads(1)
    tune_cpu_allocator()
    cfg, b = CrossingSettings(), 5
    g = shard_generator("cpu", 0, 0)
    scn = crossing(2, 12, b, generator=g)
    init = scn.initial_particles(cfg.particles, generator=g)
    z, n = scn.measurements, cfg.particles
    kw = dict(num_chains=n // 10, burn_in=cfg.burn_in)
    filters = {name: IPMCMCFilter(scn.motion, scn.sensor, n, compile_step=args.compiled, **kw, **terms)
               for name, terms in VARIANTS.items()}
    times: dict[str, list[float]] = {name: [] for name in filters}
    with torch.inference_mode():
        state = IPMCMCFilter(scn.motion, scn.sensor, n, **kw)(z[0:2], init=init,
                                                              generator=torch.Generator().manual_seed(0)).state
        for name, f in filters.items():  # warm (and, compiled, the compilation)
            t = time.perf_counter()
            f(z[2:3], init=state, generator=torch.Generator().manual_seed(1))
            print(f"{name:14s} first call {time.perf_counter() - t:6.1f} s")
        for _ in range(args.rounds):
            for name, f in filters.items():
                t = time.process_time()
                f(z[2:10], init=state, generator=torch.Generator().manual_seed(1))
                times[name].append((time.process_time() - t) / 8 / b * 1e3)
    paper = min(times["paper"])
    for name, v in times.items():
        print(f"{name:14s} {min(v):6.1f} ms a step and run  {min(v) / paper:.2f}x the paper's  "
              f"(rounds: {', '.join(f'{x:.1f}' for x in v)})")


if __name__ == "__main__":
    main()
