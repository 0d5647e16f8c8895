"""Command line: ``python -m torchmcmcpf {demo, reproduce, bench}``.

- ``demo``: the 10-target ground-radar scenario of Bocquel et al. (2012) filtered by the
  multitarget SIR TBD particle filter (``--filter ipmcmc``: the IP-MCMC-PF); prints the position RMSE and the track loss rate
  and writes ``metrics.json`` and ``tracks.png``.
- ``reproduce NAME``: run one of the studies in :mod:`torchmcmcpf.experiments`
  (``reproduce --list`` lists them).
- ``bench``: how to run the benchmarks.
"""

from __future__ import annotations

import argparse
import sys
from typing import Optional, Sequence

from .experiments._common import (
    StepTimer,
    add_common_arguments,
    generator,
    positive_int,
    prepare_out,
    save_figure,
    write_metrics,
)

DEMO_DEFAULTS = dict(particles=1000, runs=2, steps=20, targets=10)


def _build_filter(name: str, scenario, num_particles: int):
    """The demo's filters: the SIR baseline, or IP-MCMC-PF with paper 000's 50 chains and
    burn-in 100 (N/2 chains when N < 100: R-hat needs two kept samples per chain)."""
    from .filters import IPMCMCFilter, SIRFilter

    if name == "sir":
        return SIRFilter(scenario.motion, scenario.sensor, num_particles)
    return IPMCMCFilter(scenario.motion, scenario.sensor, num_particles,
                        num_chains=min(50, max(1, num_particles // 2)), burn_in=100)


def _demo_parser(sub) -> None:
    p = sub.add_parser(
        "demo",
        help="SIR particle filter on the 10-target ground-radar scenario",
        description=(
            "Filter the ground-radar TBD scenario of Bocquel, Driessen and Bagchi (2012, Table I) "
            "with the multitarget SIR particle filter, print the position RMSE (labels matched) "
            "and the track loss rate, and write metrics.json and tracks.png. The defaults "
            "(1000 particles, 2 runs, 20 steps, 10 targets) take well under a minute on 2 CPU cores."
        ),
    )
    p.add_argument("--particles", type=positive_int, default=DEMO_DEFAULTS["particles"],
                   help="particles N (default: %(default)s)")
    p.add_argument("--runs", type=positive_int, default=DEMO_DEFAULTS["runs"],
                   help="Monte Carlo runs B, filtered as one batch (default: %(default)s)")
    p.add_argument("--steps", type=positive_int, default=DEMO_DEFAULTS["steps"],
                   help="time steps T (default: %(default)s)")
    p.add_argument("--targets", type=positive_int, default=DEMO_DEFAULTS["targets"],
                   help="targets K (default: %(default)s)")
    p.add_argument("--filter", choices=("sir", "ipmcmc"), default="sir",
                   help="sir: multitarget SIR PF (default); ipmcmc: IP-MCMC-PF, 50 chains, "
                        "burn-in 100 (N must be a multiple of the chains)")
    add_common_arguments(p, name="demo", quick=False)
    p.set_defaults(command=_demo)


def _demo(args: argparse.Namespace) -> dict:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from .metrics import position_rmse, track_loss
    from .plotting import plot_rmse, plot_tracks
    from .scenarios import ground_radar

    out = prepare_out(args.out)
    g = generator(args.device, args.seed)
    scenario = ground_radar(args.targets, args.steps, args.runs, generator=g, device=args.device)
    filt = _build_filter(args.filter, scenario, args.particles).to(args.device)
    init = scenario.initial_particles(args.particles, generator=g)
    with StepTimer(args.device, steps=args.steps) as timer:
        result = filt(scenario.measurements, init=init, generator=g, progress=args.progress)
    rmse = position_rmse(result.mean, scenario.truth, match=True)
    lost = track_loss(result.mean, scenario.truth, match=True)
    metrics = {
        "scenario": "ground_radar (Bocquel et al. 2012, Table I)",
        "filter": type(filt).__name__,
        "labels": "matched per run by the whole-track optimal assignment (metrics.match_tracks)",
        "grid": list(scenario.sensor.frame_shape),
        "rmse_overall_m": rmse.overall,
        "rmse_per_step_m": rmse.per_step,
        "rmse_per_run_m": rmse.per_run,
        "track_loss_rate": lost.float().mean(),
        "lost_runs": lost,
        "seconds_per_step": timer.seconds_per_step,
    }
    path = write_metrics(out, metrics, args=args)

    fig, (ax_tracks, ax_rmse) = plt.subplots(1, 2, figsize=(11, 4.5))
    plot_tracks(ax_tracks, scenario.truth, result.mean, run=0)
    ax_tracks.set_title(f"run 0: true (solid) and {type(filt).__name__} estimates (dashed), N = {args.particles}")
    plot_rmse(ax_rmse, rmse.per_step, dt=scenario.dt)
    ax_rmse.set_title(f"position RMSE over {args.runs} run(s), labels matched")
    save_figure(fig, out, "tracks.png")

    print(f"ground radar: K={args.targets} targets, T={args.steps} steps, B={args.runs} runs, "
          f"N={args.particles} particles, {type(filt).__name__}, grid {'x'.join(map(str, scenario.sensor.frame_shape))}, "
          f"device {args.device}")
    print(f"position RMSE (labels matched): {float(rmse.overall):.2f} m")
    print(f"track loss rate (max error > 20 m): {float(lost.float().mean()):.0%} "
          f"({int(lost.sum())}/{args.runs} runs)")
    print(f"seconds per step: {timer.seconds_per_step:.3f}")
    print(f"wrote {path} and {out / 'tracks.png'}")
    return metrics


def _reproduce(argv: Sequence[str]) -> dict:
    from . import experiments

    pre = argparse.ArgumentParser(
        prog="python -m torchmcmcpf reproduce", add_help=False,
        description="Run a study of torchmcmcpf.experiments; --list shows them.",
    )
    pre.add_argument("name", nargs="?", help="experiment NAME (see --list)")
    pre.add_argument("--list", action="store_true", help="list the experiments and exit")
    pre.add_argument("-h", "--help", action="store_true")
    known, rest = pre.parse_known_args(argv)
    found = experiments.discover()
    if known.list or (known.name is None and not known.help):
        width = max((len(n) for n in found), default=0)
        for name, module in found.items():
            print(f"{name:<{width}}  {module.DESCRIPTION}")
        if not found:
            print("no experiments found in torchmcmcpf/experiments/")
        if not known.list:
            pre.error("the experiment NAME is required (listed above)")
        return {}
    if known.name is None:
        pre.print_help()
        return {}
    if known.name not in found:
        pre.error(f"argument name: unknown experiment {known.name!r}; choose from {sorted(found)}")
    module = found[known.name]
    parser = argparse.ArgumentParser(prog=f"python -m torchmcmcpf reproduce {known.name}",
                                     description=module.DESCRIPTION)
    add_common_arguments(parser, name=known.name)
    if hasattr(module, "add_arguments"):
        module.add_arguments(parser)
    args = parser.parse_args(rest + (["--help"] if known.help else []))
    args.name = known.name
    args.out = prepare_out(args.out)
    result = module.run(args)
    print(f"{known.name}: wrote {args.out}")
    for key, value in result.items():
        if isinstance(value, (int, float, str)):
            print(f"  {key}: {value}")
    return result


def _bench(args: argparse.Namespace) -> dict:
    print("Benchmarks use pytest-benchmark; from the repository root run:\n"
          "    pytest benchmarks/ --benchmark-only\n"
          "(add --benchmark-compare to compare with a saved run; see benchmarks/README.md).")
    return {}


def main(argv: Optional[Sequence[str]] = None) -> int:
    """Entry point of ``python -m torchmcmcpf`` and of the ``torchmcmcpf`` script.

    Returns 0 on success (results are in the output directory's ``metrics.json``);
    argument errors exit with status 2 and a message naming the argument.
    """
    argv = list(sys.argv[1:] if argv is None else argv)
    argv = [str(a) for a in argv]  # allow Path arguments in-process
    if argv[:1] == ["reproduce"]:
        _reproduce(argv[1:])
        return 0
    parser = argparse.ArgumentParser(
        prog="python -m torchmcmcpf",
        description="MCMC-based particle filters for multi-target track-before-detect.",
    )
    sub = parser.add_subparsers(dest="cmd", required=True, metavar="{demo,reproduce,bench}")
    _demo_parser(sub)
    sub.add_parser("reproduce", help="run a study of torchmcmcpf.experiments (reproduce --list)")
    sub.add_parser("bench", help="how to run the benchmarks").set_defaults(command=_bench)
    args = parser.parse_args(argv)
    args.command(args)
    return 0


if __name__ == "__main__":
    sys.exit(main())
