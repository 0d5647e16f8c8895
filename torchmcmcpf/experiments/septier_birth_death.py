"""Unknown, time-varying number of targets: the setting of Septier, Pang, Carmi and Godsill
(paper 001): 5000 x 5000 m, up to 5 targets with random births and deaths, nearly constant
velocity, point measurements in Poisson clutter (:mod:`torchmcmcpf.scenarios.septier`).

What runs
---------
- SIR PF with existence (:class:`~torchmcmcpf.filters.sir.SIRFilter` with a
  :class:`~torchmcmcpf.models.existence.BirthDeath` model, births near the measurements),
- MCMC-PF (:class:`~torchmcmcpf.filters.mcmc.MCMCFilter`, paper 001's adapted algorithm:
  joint draw w.p. 0.75, else a refinement sweep over the slots; ``N / 2`` chains keeping 2
  samples each after ``burn_in`` iterations),
- IP-MCMC-PF (:class:`~torchmcmcpf.filters.ipmcmc.IPMCMCFilter`, exchange moves with the
  existence chain; ``N / 10`` chains, ``2 burn_in`` iterations of burn-in, R-hat
  extensions),

all with the same birth proposal, every particle starting with all slots inactive.

Estimates: per slot the existence probability, the expected number of targets (their sum)
and, for the slots with existence probability > 0.5, the mean given existence
(:func:`~torchmcmcpf.models.existence.existence_estimate`).

Writes ``metrics.json`` (per-step OSPA and GOSPA, c = 100 m, p = 2, averaged over the runs;
mean true and expected number of targets per step; their time averages; the mean
cardinality error; seconds per step; the device), ``tracks.png`` (run 0, one panel per
filter), ``cardinality.png`` (every filter) and ``ospa.png``.

The runs are cut into shards of ``--shard-size`` runs (5, quick 1), each from the generator
of ``(seed, shard index)`` (:func:`run_shard`), so ``--workers N`` on Ray writes the same
numbers.
"""

from __future__ import annotations

import argparse

import torch

from .. import metrics
from ..filters.ipmcmc import IPMCMCFilter
from ..filters.mcmc import MCMCFilter
from ..filters.sir import SIRFilter
from ..models.base import MotionModel, SensorModel
from ..models.existence import BirthDeath
from ..scenarios.septier import septier
from ..typing import X, Y
from ._common import StepTimer, defaults_help, np_label, positive_int, run_shards, save_figure, write_metrics

NAME = "septier-birth-death"
DESCRIPTION = "Septier et al. setting: up to 5 targets with births/deaths in Poisson clutter (OSPA, GOSPA, cardinality)"

QUICK = dict(runs=3, steps=25, particles=300, burn_in=10, shard_size=1)
FULL = dict(runs=20, steps=60, particles=2000, burn_in=20, shard_size=5)
CUTOFF, ORDER = 100.0, 2.0
FILTERS = ("SIR PF", "MCMC-PF", "IP-MCMC-PF")
OUTPUTS = ("metrics.json", "tracks.png", "cardinality.png", "ospa.png", "shards")


def add_arguments(parser: argparse.ArgumentParser) -> None:
    """Add this experiment's options (``--runs``, ``--steps``, ...) to ``parser``; each help
    text shows the full and the ``--quick`` default.
    """

    def h(key: str, what: str) -> str:
        return defaults_help(FULL, QUICK, key, what)

    parser.add_argument("--runs", type=positive_int, help=h("runs", "Monte Carlo runs"))
    parser.add_argument("--steps", type=positive_int, help=h("steps", "time steps"))
    parser.add_argument("--particles", type=positive_int, help=h("particles", "particles Np"))
    parser.add_argument("--burn-in", dest="burn_in", type=positive_int,
                        help=h("burn_in", "MCMC-PF burn-in per step; IP-MCMC-PF uses twice it"))


def _config(args: argparse.Namespace) -> dict:
    cfg = dict(QUICK if args.quick else FULL)
    for key in cfg:
        if getattr(args, key, None) is not None:
            cfg[key] = getattr(args, key)
    cfg["quick"] = bool(args.quick)
    return cfg


def _divisor_at_most(n: int, c: int) -> int:
    """The largest divisor of ``n`` that is ``<= c`` (a chain count that divides N)."""
    return max(d for d in range(1, max(1, min(n, c)) + 1) if n % d == 0)


def _masked_positions(x: torch.Tensor, keep: torch.Tensor) -> torch.Tensor:
    """(T, B, K, D) -> (T, B, K, D) with NaN wherever ``keep`` is False (breaks plot lines)."""
    return torch.where(keep.unsqueeze(-1), x, torch.full_like(x, float("nan")))


def _filters(cfg: dict, motion: MotionModel, sensor: SensorModel, existence: BirthDeath) -> dict:
    n, burn_in = cfg["particles"], cfg["burn_in"]
    return {
        "SIR PF": SIRFilter(motion, sensor, num_particles=n, existence=existence),
        "MCMC-PF": MCMCFilter(motion, sensor, num_particles=n, num_chains=_divisor_at_most(n, n // 2),
                              burn_in=burn_in, existence=existence),
        "IP-MCMC-PF": IPMCMCFilter(motion, sensor, num_particles=n, num_chains=max(2, _divisor_at_most(n, n // 10)),
                                   burn_in=2 * burn_in, existence=existence),
    }


def run_shard(cfg: dict, runs: range, *, generator: torch.Generator, device: torch.device,
              progress: bool = False) -> tuple[dict, dict]:
    """Simulate the runs ``runs`` and filter them with every filter (one batch).

    Returns
    -------
    ``per_run`` with ``"truth"`` ``(R, T, K, 4)`` (NaN where absent), ``"true_count"``
    ``(R, T)`` and per filter ``f``: ``"f|ospa"``, ``"f|gospa"``, ``"f|count"`` (expected
    number of targets), ``"f|cardinality_error"`` ``(R, T)`` and ``"f|estimate"``
    ``(R, T, K, 4)`` (NaN where the existence probability is <= 0.5); ``seconds`` per filter.
    """
    scn = septier(len(runs), cfg["steps"], generator=generator)
    scn = scn._replace(truth=scn.truth.to(device))
    motion, sensor, existence = scn.motion.to(device), scn.sensor.to(device), scn.existence.to(device)
    b, k = scn.alive.shape[1:]
    init = torch.zeros((b, cfg["particles"], k, 4), dtype=torch.float64, device=device)
    per_run = {"truth": _masked_positions(scn.truth, scn.alive).movedim(1, 0),
               "true_count": scn.true_count.movedim(1, 0)}
    seconds = {}
    for name, filt in _filters(cfg, motion, sensor, existence).items():
        with StepTimer(device, cfg["steps"]) as timer:
            res = filt(scn.measurements, init=init, generator=generator, progress=progress)
        seconds[name] = timer.seconds
        present = res.exists_prob > 0.5  # (T, B, K)
        est_pos, true_pos = res.mean[..., [X, Y]], scn.truth[..., [X, Y]]
        count = res.exists_prob.sum(-1)  # (T, B)
        per_run[f"{name}|ospa"] = metrics.ospa(est_pos, true_pos, c=CUTOFF, p=ORDER, x_mask=present,
                                              y_mask=scn.alive).T
        per_run[f"{name}|gospa"] = metrics.gospa(est_pos, true_pos, c=CUTOFF, p=ORDER, x_mask=present,
                                                y_mask=scn.alive).T
        per_run[f"{name}|count"] = count.T
        per_run[f"{name}|cardinality_error"] = metrics.cardinality_error(count, scn.true_count).T
        per_run[f"{name}|estimate"] = _masked_positions(res.mean, present).movedim(1, 0)
    return per_run, seconds


def aggregate(cfg: dict, per_run: dict, seconds: dict) -> dict:
    """Per filter: per-step means over the runs and their time averages."""
    results = {}
    for name in FILTERS:
        o, g, c = (per_run[f"{name}|{m}"] for m in ("ospa", "gospa", "count"))
        results[name] = {
            "ospa_per_step": o.mean(0), "gospa_per_step": g.mean(0), "expected_count_per_step": c.mean(0),
            "ospa": o.mean(), "gospa": g.mean(), "cardinality_error": per_run[f"{name}|cardinality_error"].mean(),
            "seconds_per_step": seconds[name] / cfg["steps"],
        }
    return results


def summary(payload: dict) -> str:
    """Headline table: OSPA, GOSPA, cardinality error per filter."""
    lines = ["| filter | OSPA [m] | GOSPA [m] | cardinality error | s / step |", "|---|---|---|---|---|"]
    for name, r in payload["results"].items():
        lines.append(f"| {name} | {float(r['ospa']):.1f} | {float(r['gospa']):.1f} | "
                     f"{float(r['cardinality_error']):.2f} | {r['seconds_per_step']:.3f} |")
    return "\n".join(lines) + "\n"


def run(args: argparse.Namespace) -> dict:
    """Run the study in shards (see the module docstring); writes into ``args.out``."""
    import sys

    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from ..plotting import plot_cardinality, plot_rmse, plot_tracks

    cfg = _config(args)
    device = args.device
    shards = run_shards(sys.modules[__name__], cfg, args)
    cfg = {**cfg, "shard_size": shards.layout["shard_size"]}
    results = aggregate(cfg, shards.per_run, shards.seconds)
    pr, n, quick = shards.per_run, cfg["particles"], " (quick)" if cfg["quick"] else ""
    runs = pr["true_count"].shape[0]
    true_count = pr["true_count"].double().mean(0)

    fig, axes = plt.subplots(1, len(FILTERS), figsize=(5.5 * len(FILTERS), 5.5), squeeze=False,
                             layout="constrained")
    for ax, name in zip(axes[0], FILTERS):
        plot_tracks(ax, pr["truth"][0], pr[f"{name}|estimate"][0], estimate_label=np_label(name, n))
        ax.set_title(f"{name} (existence > 0.5)")
    fig.suptitle(f"run 0: true tracks (solid) and estimates (dashed){quick}")
    save_figure(fig, args.out, "tracks.png", quick=cfg["quick"])
    fig, ax = plt.subplots(figsize=(7, 4))
    plot_cardinality(ax, true_count, {f"{np_label(name, n)}: expected number": results[name]["expected_count_per_step"]
                                      for name in FILTERS})
    ax.set_title(f"mean number of targets over {runs} runs{quick}")
    save_figure(fig, args.out, "cardinality.png", quick=cfg["quick"])
    fig, axes = plt.subplots(1, 2, figsize=(11, 4), layout="constrained")
    plot_rmse(axes[0], {np_label(k, n): r["ospa_per_step"] for k, r in results.items()},
              ylabel=f"OSPA (c = {CUTOFF:g} m, p = {ORDER:g}) [m]")
    plot_rmse(axes[1], {np_label(k, n): r["gospa_per_step"] for k, r in results.items()},
              ylabel=f"GOSPA (c = {CUTOFF:g} m, p = {ORDER:g}, alpha = 2) [m]")
    fig.suptitle(f"mean over {runs} runs{quick}")
    save_figure(fig, args.out, "ospa.png", quick=cfg["quick"])

    payload = {"config": cfg, "cutoff": CUTOFF, "order": ORDER, "true_count_per_step": true_count,
               "results": results}
    write_metrics(args.out, payload, args=args, device=device)
    return payload
