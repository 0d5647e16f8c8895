"""Table II (and Figs. 3, 5, 6) of Bocquel, Driessen and Bagchi (2012), paper 000.

SIR PF, PMMH and IP-MCMC-PF with Np in {500, 5000} on the ground-radar scenario of Table I,
with one target (Figs. 1-3) and ten targets (Figs. 4-6, Table II), Monte Carlo runs batched.
Writes ``table2.md`` (our table next to the paper's), ``metrics.json`` (RMSE, TLR, seconds
per time step, the device), ``rmse_1_target.png``, ``rmse_10_targets.png`` and
``tracks.png`` (the IP-MCMC-PF tracks of the first run, Fig. 5).

What runs
---------
- SIR PF: :class:`~torchmcmcpf.filters.sir.SIRFilter`, resampling every step.
- IP-MCMC-PF: :class:`~torchmcmcpf.filters.ipmcmc.IPMCMCFilter`, 50 chains, burn-in 100,
  R-hat threshold 1.1, at most ``--max-extensions`` extensions.
- PMMH: :func:`~torchmcmcpf.filters.pmmh.pmmh` on ``theta = log q``, the process-noise
  scale of the filters' motion model (N(0, 1) prior, random-walk std 0.3, started at the
  true value 0), one chain per run, ``--pmmh-iterations`` iterations of which the first
  ``--pmmh-burn-in`` are discarded; each iteration runs an SIR filter with Np particles
  over the whole sequence; the track is the average of the accepted filter means (see
  :mod:`torchmcmcpf.filters.pmmh`). Its seconds per step are the total time over T.

Every filter starts from ``Scenario.initial_particles`` (5 m / 1 m/s / 10 % around the
truth one step before frame 0, labels kept); RMSE and TLR (20 m) use the slot labels.
"""

from __future__ import annotations

import argparse

import torch

from .. import metrics
from ..filters.ipmcmc import IPMCMCFilter
from ..filters.pmmh import ProcessNoiseScale, pmmh, sir_log_evidence
from ..filters.sir import SIRFilter
from ..scenarios.ground_radar import ground_radar
from ._common import StepTimer, generator, positive_int, save_figure, write_metrics

NAME = "bocquel-table2"
DESCRIPTION = "Bocquel et al. 2012 Table II: SIR PF vs PMMH vs IP-MCMC-PF on the ground radar (RMSE, TLR, s/step)"

#: paper 000 Table II (10 targets): (algorithm, Np) -> (RMSE [m], TLR, CPU s per step)
PAPER = {
    ("SIR PF", 500): (6.74, 0.06, 0.5), ("SIR PF", 5000): (6.23, 0.03, 3.8),
    ("PMMH", 500): (5.42, 0.01, 0.6), ("PMMH", 5000): (4.65, 0.00, 2.7),
    ("IP-MCMC-PF", 500): (4.84, 0.00, 0.4), ("IP-MCMC-PF", 5000): (4.61, 0.00, 0.69),
}

QUICK = dict(runs=2, steps=3, particles=(40, 80), chains=10, burn_in=10, targets=(1, 10),
             pmmh_iterations=2, pmmh_burn_in=1, max_extensions=1)
FULL = dict(runs=100, steps=20, particles=(500, 5000), chains=50, burn_in=100, targets=(1, 10),
            pmmh_iterations=6, pmmh_burn_in=2, max_extensions=2)


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--runs", type=positive_int, help="Monte Carlo runs (default 100, quick 2)")
    parser.add_argument("--steps", type=positive_int, help="time steps (default 20, quick 4)")
    parser.add_argument("--particles", type=positive_int, nargs="+", help="Np values (default 500 5000)")
    parser.add_argument("--max-extensions", type=int, help="IP-MCMC-PF R-hat extensions (default 2)")
    parser.add_argument("--pmmh-iterations", type=positive_int, help="PMMH iterations (default 6)")
    parser.add_argument("--pmmh-burn-in", type=int, help="PMMH iterations discarded (default 2)")


def settings(args: argparse.Namespace) -> dict:
    """Quick or full defaults, overridden by the command-line options given."""
    quick = bool(getattr(args, "quick", False))
    cfg = dict(QUICK if quick else FULL)
    for key in ("runs", "steps", "particles", "max_extensions", "pmmh_iterations", "pmmh_burn_in"):
        value = getattr(args, key, None)
        if value is not None:
            cfg[key] = tuple(value) if key == "particles" else value
    if any(n % cfg["chains"] for n in cfg["particles"]):
        raise ValueError(f"--particles {cfg['particles']} must be multiples of {cfg['chains']} chains")
    cfg["quick"] = quick
    return cfg


def _run_pmmh(scn, n, cfg, g, progress):
    base_cv = scn.motion
    c = 1

    def build(theta):
        return ProcessNoiseScale(base_cv, theta[:, 0].exp()), scn.sensor

    def init(m, *, generator):
        return scn.initial_particles(n, generator=generator).repeat_interleave(m // scn.batch_size, dim=0)

    evaluate = sir_log_evidence(build, scn.measurements, init, n, keep_means=True)
    prior = torch.distributions.Normal(0.0, 1.0)
    theta0 = torch.zeros((scn.batch_size, c, 1), device=scn.truth.device, dtype=scn.truth.dtype)
    res = pmmh(evaluate, theta0, log_prior=lambda th: prior.log_prob(th[..., 0]), proposal_std=0.3,
               num_iterations=cfg["pmmh_iterations"], generator=g)
    means = res.aux[cfg["pmmh_burn_in"]:].mean((0, 2))  # (B, T, K, D)
    return means.movedim(1, 0), {"acceptance": res.acceptance.mean(), "theta_mean": res.theta.mean()}


def run_one(num_targets: int, cfg: dict, args) -> dict:
    """All algorithms and Np for one scenario; returns metrics and the estimates."""
    device = getattr(args, "device", torch.device("cpu"))
    g = generator(device, getattr(args, "seed", 0) + num_targets)
    scn = ground_radar(num_targets, cfg["steps"], cfg["runs"], generator=g, device=device)
    progress = bool(getattr(args, "progress", False))
    out, estimates = {}, {}
    for n in cfg["particles"]:
        x0 = scn.initial_particles(n, generator=g)
        filters = {
            "SIR PF": SIRFilter(scn.motion, scn.sensor, n),
            "IP-MCMC-PF": IPMCMCFilter(scn.motion, scn.sensor, n, num_chains=cfg["chains"], burn_in=cfg["burn_in"],
                                       max_extensions=cfg["max_extensions"]),
        }
        for name in ("SIR PF", "PMMH", "IP-MCMC-PF"):
            extra = {}
            with StepTimer(device, steps=cfg["steps"]) as timer:
                if name == "PMMH":
                    est, extra = _run_pmmh(scn, n, cfg, g, progress)
                else:
                    res = filters[name](scn.measurements, init=x0, generator=g, progress=progress)
                    est = res.mean
                    if name == "IP-MCMC-PF":
                        extra = {"rhat_mean": res.info.extras["rhat"].mean(),
                                 "extensions_mean": res.info.extras["extensions"].mean(),
                                 "acceptance": res.info.acceptance.mean()}
            rmse = metrics.position_rmse(est, scn.truth)
            out[f"{name} | {n}"] = {
                "algorithm": name, "num_particles": n,
                "rmse": rmse.overall, "rmse_per_step": rmse.per_step,
                "tlr": metrics.track_loss_rate(est, scn.truth),
                "seconds_per_step": timer.seconds_per_step, **extra,
            }
            estimates[(name, n)] = est
    return {"results": out, "estimates": estimates, "truth": scn.truth}


def table_markdown(results: dict, num_targets: int, with_paper: bool) -> str:
    head = "| Algorithm | Np | RMSE [m] | TLR | s / step |"
    sep = "|---|---|---|---|---|"
    if with_paper:
        head += " paper RMSE [m] | paper TLR | paper CPU s |"
        sep += "---|---|---|"
    lines = [f"**{num_targets} target{'s' if num_targets > 1 else ''}**", "", head, sep]
    for r in results.values():
        row = (f"| {r['algorithm']} | {r['num_particles']} | {float(r['rmse']):.2f} | "
               f"{100 * float(r['tlr']):.0f}% | {r['seconds_per_step']:.3f} |")
        if with_paper:
            p = PAPER.get((r["algorithm"], r["num_particles"]))
            row += " - | - | - |" if p is None else f" {p[0]:.2f} | {100 * p[1]:.0f}% | {p[2]} |"
        lines.append(row)
    return "\n".join(lines) + "\n"


def run(args: argparse.Namespace) -> dict:
    """Run the study (see the module docstring); writes into ``args.out``."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from ..plotting import plot_rmse, plot_tracks

    cfg = settings(args)
    out = args.out
    device = getattr(args, "device", torch.device("cpu"))
    all_results, md = {}, ["# Table II of Bocquel et al. (2012), regenerated", "",
                           f"{cfg['runs']} Monte Carlo runs, {cfg['steps']} steps, device: see metrics.json"
                           + (" (QUICK mode: small settings, not comparable with the paper)" if cfg["quick"] else ""), ""]
    tracks = None
    for k in cfg["targets"]:
        study = run_one(k, cfg, args)
        all_results[f"{k} targets"] = study["results"]
        md.append(table_markdown(study["results"], k, with_paper=(k == 10)))
        fig, ax = plt.subplots(figsize=(6, 4))
        plot_rmse(ax, {key: r["rmse_per_step"] for key, r in study["results"].items()})
        ax.set_title(f"Position RMSE, {k} target(s), {cfg['runs']} runs")
        save_figure(fig, out, f"rmse_{k}_target{'s' if k > 1 else ''}.png")
        if k == max(cfg["targets"]):
            tracks = (study["truth"], study["estimates"][("IP-MCMC-PF", max(cfg["particles"]))])
    fig, ax = plt.subplots(figsize=(6, 5))
    plot_tracks(ax, tracks[0], tracks[1], run=0)
    ax.set_title("IP-MCMC-PF tracks (run 0)")
    save_figure(fig, out, "tracks.png")
    md += ["**Paper 000, Table II** (10 targets, 100 runs; MATLAB R2011b on an Intel Core i7 920)", "",
           "| Algorithm | Np | RMSE [m] | TLR | CPU s / step |", "|---|---|---|---|---|"]
    md += [f"| {a} | {n} | {p[0]:.2f} | {100 * p[1]:.0f}% | {p[2]} |" for (a, n), p in PAPER.items()]
    (out / "table2.md").write_text("\n".join(md) + "\n")
    payload = {"config": cfg, "results": all_results}
    write_metrics(out, payload, args=args, device=device)
    return payload
