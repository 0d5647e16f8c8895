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
(:func:`~torchmcmcpf.state.existence_estimate`).

Writes ``metrics.json`` (per-step OSPA and GOSPA, c = 100 m, p = 2, averaged over the runs;
mean true and expected number of targets per step; their time averages; the mean
cardinality error; seconds per step; the device), ``tracks.png`` (run 0), ``cardinality.png``
and ``ospa.png``.
"""

from __future__ import annotations

import argparse

import torch

from .. import metrics
from ..filters.ipmcmc import IPMCMCFilter
from ..filters.mcmc import MCMCFilter
from ..filters.sir import SIRFilter
from ..scenarios.septier import septier
from ..typing import X, Y
from ._common import StepTimer, generator, positive_int, save_figure, write_metrics

NAME = "septier-birth-death"
DESCRIPTION = "Septier et al. setting: up to 5 targets with births/deaths in Poisson clutter (OSPA, GOSPA, cardinality)"

QUICK = dict(runs=3, steps=25, particles=300, burn_in=10)
FULL = dict(runs=20, steps=60, particles=2000, burn_in=20)
CUTOFF, ORDER = 100.0, 2.0


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--runs", type=positive_int, help="Monte Carlo runs (default 20, quick 3)")
    parser.add_argument("--steps", type=positive_int, help="time steps (default 60, quick 25)")
    parser.add_argument("--particles", type=positive_int, help="particles (default 2000, quick 300)")
    parser.add_argument("--burn-in", dest="burn_in", type=positive_int,
                        help="MCMC-PF burn-in per step (default 20, quick 10; IP-MCMC-PF uses twice it)")


def _config(args) -> dict:
    cfg = dict(QUICK if args.quick else FULL)
    for key in cfg:
        if getattr(args, key, None) is not None:
            cfg[key] = getattr(args, key)
    return cfg


def _divisor_at_most(n: int, c: int) -> int:
    """The largest divisor of ``n`` that is ``<= c`` (a chain count that divides N)."""
    return max(d for d in range(1, max(1, min(n, c)) + 1) if n % d == 0)


def _masked_positions(x: torch.Tensor, keep: torch.Tensor) -> torch.Tensor:
    """(T, B, K, D) -> (T, B, K, D) with NaN wherever ``keep`` is False (breaks plot lines)."""
    return torch.where(keep.unsqueeze(-1), x, torch.full_like(x, float("nan")))


def run(args: argparse.Namespace) -> dict:
    """Run the study (see the module docstring); writes into ``args.out``."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from ..plotting import plot_cardinality, plot_rmse, plot_tracks

    cfg = _config(args)
    device = args.device
    gen = generator(device, args.seed)
    scn = septier(cfg["runs"], cfg["steps"], generator=gen)
    scn = scn._replace(truth=scn.truth.to(device))
    motion, sensor, existence = (m.to(device) for m in (scn.motion, scn.sensor, scn.existence))
    b, k = scn.alive.shape[1:]
    init = torch.zeros((b, cfg["particles"], k, 4), dtype=torch.float64, device=device)

    n, burn_in = cfg["particles"], cfg["burn_in"]
    filters = {
        "SIR PF": SIRFilter(motion, sensor, n, existence=existence),
        "MCMC-PF": MCMCFilter(motion, sensor, n, num_chains=_divisor_at_most(n, n // 2), burn_in=burn_in,
                              existence=existence),
        "IP-MCMC-PF": IPMCMCFilter(motion, sensor, n, num_chains=max(2, _divisor_at_most(n, n // 10)),
                                   burn_in=2 * burn_in,
                                   existence=existence),
    }
    results, curves = {}, {"ospa": {}, "gospa": {}, "count": {}}
    estimates = {}
    for name, filt in filters.items():
        with StepTimer(device, cfg["steps"]) as timer:
            res = filt(scn.measurements, init=init, generator=gen, progress=args.progress)
        present = res.exists_prob > 0.5  # (T, B, K)
        est_pos, true_pos = res.mean[..., [X, Y]], scn.truth[..., [X, Y]]
        o = metrics.ospa(est_pos, true_pos, c=CUTOFF, p=ORDER, x_mask=present, y_mask=scn.alive)
        g = metrics.gospa(est_pos, true_pos, c=CUTOFF, p=ORDER, x_mask=present, y_mask=scn.alive)
        count = res.exists_prob.sum(-1)  # (T, B)
        card = metrics.cardinality_error(count, scn.true_count)
        curves["ospa"][name], curves["gospa"][name] = o.mean(1), g.mean(1)
        curves["count"][name] = count.mean(1)
        estimates[name] = _masked_positions(res.mean, present)
        results[name] = {
            "ospa_per_step": o.mean(1), "gospa_per_step": g.mean(1),
            "expected_count_per_step": count.mean(1),
            "ospa": o.mean(), "gospa": g.mean(), "cardinality_error": card.mean(),
            "seconds_per_step": timer.seconds_per_step,
        }
    true_count = scn.true_count.double().mean(1)

    fig, ax = plt.subplots(figsize=(6, 6))
    first = next(iter(estimates))
    plot_tracks(ax, _masked_positions(scn.truth, scn.alive), estimates[first], run=0)
    ax.set_title(f"run 0: true tracks and {first} estimates (existence > 0.5)")
    save_figure(fig, args.out, "tracks.png")
    fig, ax = plt.subplots(figsize=(7, 4))
    plot_cardinality(ax, true_count, curves["count"][first], est_label=f"{first}: expected number")
    ax.set_title(f"mean number of targets over {b} runs")
    save_figure(fig, args.out, "cardinality.png")
    fig, axes = plt.subplots(1, 2, figsize=(11, 4))
    plot_rmse(axes[0], curves["ospa"], ylabel=f"OSPA (c = {CUTOFF:g} m, p = {ORDER:g}) [m]")
    plot_rmse(axes[1], curves["gospa"], ylabel=f"GOSPA (c = {CUTOFF:g} m, p = {ORDER:g}, alpha = 2) [m]")
    save_figure(fig, args.out, "ospa.png")

    payload = {"config": cfg, "cutoff": CUTOFF, "order": ORDER, "true_count_per_step": true_count,
               "results": results}
    write_metrics(args.out, payload, args=args, device=device)
    return payload
