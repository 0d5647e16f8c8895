"""Where a crossing step goes: the filters of ``reproduce crossing`` (its full settings, one
shard of 5 runs batched, one thread, eager as the study runs them), three steps timed and one
profiled after two warm steps and split into the parts of issue 49 item 1 as
:mod:`profile_birth_death` splits a births/deaths step. Run from the repository root:

    python benchmarks/profile_crossing.py

Prints, per filter, the unprofiled time per step and run and each part's share of the profiled
step, then each MCMC filter's arithmetic floor per step and run: its cell terms, counted as
``bench`` counts them (``bench.radar_floor``, compiled: one amplitude and one Rician log ratio
per (sample, box cell), nothing else), on the crossing's grid.
"""

from __future__ import annotations

import math

import torch
from profile_birth_death import profile_step, report

from torchmcmcpf.bench import radar_floor, time_step
from torchmcmcpf.experiments._shards import shard_generator
from torchmcmcpf.experiments.crossing import CrossingSettings, _filters
from torchmcmcpf.runtime import tune_cpu_allocator
from torchmcmcpf.scenarios.crossing import crossing

#: the grid sensor's calls: a filter's likelihood part, and inside its bookkeeping's inclusive time
_LIKELIHOOD = [("sensor.py", "log_likelihood"), ("sensor.py", "amplitude_cache"),
               ("sensor.py", "log_likelihood_delta_cached"), ("sensor.py", "log_likelihood_delta"),
               ("sensor.py", "log_likelihood_slot_changes"), ("sensor.py", "log_likelihood_delta_terms"),
               ("sensor.py", "log_likelihood_delta_rows")]

#: filter -> part -> the functions whose inclusive time it is (file suffix, function name)
PARTS = {
    "IP-MCMC-PF": {
        "likelihood arithmetic": _LIKELIHOOD,
        "move bookkeeping": [("exchange.py", "exchange_iteration"), ("exchange.py", "with_accepted_amplitudes")],
        "noise and proposals": [("ipmcmc.py", "draw")],
        "R-hat": [("_convergence.py", "rhat_report")],
        "relabelling and estimation": [("base.py", "_estimate")],
    },
    "MCMC-PF": {
        "likelihood arithmetic": _LIKELIHOOD,
        "move bookkeeping": [("mcmc.py", "mcmc_iteration")],
        "noise and proposals": [("mcmc.py", "draw_iteration_noise"), ("mcmc.py", "relocations")],
        "relabelling and estimation": [("base.py", "_estimate")],
    },
    "partitioned PF": {
        "likelihood arithmetic": _LIKELIHOOD,
        "move bookkeeping": [],
        "relabelling and estimation": [("base.py", "_estimate")],
    },
}
PARTS["IP-MCMC-PF (paper)"] = PARTS["IP-MCMC-PF"]

#: filter -> the functions whose time the bookkeeping's inclusive time holds but another part counts
INNER = {"IP-MCMC-PF": _LIKELIHOOD, "IP-MCMC-PF (paper)": _LIKELIHOOD, "MCMC-PF": _LIKELIHOOD,
         "partitioned PF": []}


def cell_terms(name: str, cfg: CrossingSettings, slots: int, box: int) -> int:
    """Cell terms a step of ``name`` evaluates per run, counted as ``bench`` counts them: the
    IP-MCMC-PF's ``(burn_in + 3 N / C) C`` one-slot moves (the R-hat rule extends every
    crossing step twice by ``N / C``: benchmarks/README.md) of 2 boxes and 2 log ratios a cell; the
    MCMC-PF's ``burn_in / 2 + 2`` iterations of ``N / 2`` chains, a joint draw (0.75) evaluating
    every slot's box once and a sweep (0.25) every slot's old and new box twice; the
    partitioned PF's ``N K`` slot changes against the reference, each of 2 boxes and 2 log
    ratios a cell.
    """
    n = cfg.particles
    if name.startswith("IP-MCMC-PF"):
        chains = n // 10
        return (cfg.burn_in + 3 * (n // chains)) * chains * 4 * box
    if name == "MCMC-PF":
        return math.ceil((cfg.burn_in // 2 + 2) * (n // 2) * (0.75 * slots + 0.25 * 4 * slots) * box)
    return n * slots * 4 * box


def main() -> None:
    torch.set_num_threads(1)
    tune_cpu_allocator()  # as `python -m torchmcmcpf reproduce` runs the study (torchmcmcpf.runtime)
    cfg = CrossingSettings()
    b = 5  # one shard
    g = shard_generator("cpu", 0, 0)
    scn = crossing(2, 6, b, generator=g)
    init = scn.initial_particles(cfg.particles, generator=g)
    z = scn.measurements

    def frames(a: int, e: int) -> torch.Tensor:
        return z[a:e]

    filters = _filters(cfg, scn.motion, scn.sensor)
    for name, parts in PARTS.items():
        report(name, *profile_step(filters[name], frames, init, parts, INNER[name], warm=2, timed=3), b)
    box = math.prod(scn.sensor.geometry.window_sizes)
    print("\nfloors (cell terms, compiled, one thread), ms per step and run:")
    for name in PARTS:
        terms = cell_terms(name, cfg, 2, box)
        seconds = time_step(radar_floor(terms, scn.sensor, torch.device("cpu")), repeats=3,
                            device=torch.device("cpu"))
        print(f"  {name:22s} {terms / 1e6:6.2f} M terms  {1e3 * seconds:7.2f}")


if __name__ == "__main__":
    main()
