"""Command line: ``python -m torchmcmcpf {demo, reproduce, bench}``.

- ``demo``: the 10-target ground-radar scenario of Bocquel et al. (2012) filtered by the
  IP-MCMC-PF (``--filter sir``: the multitarget SIR baseline, which loses the targets);
  prints the position RMSE and the track loss rate and writes ``metrics.json`` and
  ``tracks.png``.
- ``reproduce NAME``: run one of the studies in :mod:`torchmcmcpf.experiments`
  (``reproduce --list`` lists them, ``reproduce --help`` the common options) and print
  its headline table; ``--workers N`` runs its shards of runs on Ray (studies that define
  ``run_shard``; the others refuse the shard options with a one-line error).
- ``bench``: the headline benchmarks of :mod:`torchmcmcpf.bench` (radar SIR, IP-MCMC-PF and
  MCMC-PF steps, point SIR against Stone Soup, scaling in N, K and B); writes ``bench.json``,
  ``bench.md`` and ``bench_scaling.png``. ``--quick``: tiny sizes, seconds. ``--compare
  [FILE]``: each figure's ratio to a stored run (``benchmarks/reference-cpu.json``, written by
  ``--save``), timed at the stored run's thread count unless ``--threads`` says otherwise, the
  slower ones flagged in the closing note.

Errors are one line on stderr naming the argument (exit status 2): argparse's own, the
cross-option checks, and any ``ValueError`` the run raises (a study's settings refused by a
filter, a shard that failed on bad input). ``TORCHMCMCPF_TRACEBACK=1`` shows the traceback
instead.
"""

from __future__ import annotations

import argparse
import contextlib
import os
import shlex
import sys
import time
from collections.abc import Iterator, Sequence
from pathlib import Path
from typing import TYPE_CHECKING

from .experiments._figures import np_label, save_figure
from .experiments._options import (
    SHARD_OPTIONS,
    RunOptions,
    add_common_arguments,
    add_shard_arguments,
    nonnegative_int,
    out_dir,
    positive_int,
    prepare_out,
)
from .experiments._provenance import write_metrics
from .experiments._shards import ShardError
from .experiments._study import StepTimer, generator

if TYPE_CHECKING:
    from matplotlib.figure import Figure

    from .filters.base import Filter
    from .metrics import RMSE
    from .scenarios.ground_radar import Scenario
    from .state import FilterResult

DEMO_DEFAULTS = dict(particles=1000, runs=2, steps=20, targets=10, chains=50, burn_in=100)
#: ``demo --quick``: one run of 5 steps, 500 particles (seconds)
DEMO_QUICK = dict(particles=500, runs=1, steps=5, targets=10, chains=50, burn_in=100)
#: seconds per step of the IP-MCMC-PF at the two presets, measured on a quiet 2-core CPU
#: (``--no-progress``, 1 torch thread, 2026-12-07 23:30 UTC, AMD EPYC, with the radar's C
#: loop and the MCMC iteration's overhead cut: 0.14-0.16 and 0.07-0.08 in four runs, against
#: 0.24-0.25 and 0.26-0.28 for the code of that afternoon): what the demo announces before it runs
DEMO_SECONDS_PER_STEP = {"default": 0.15, "quick": 0.08}
DEMO_OUTPUTS = ("metrics.json", "tracks.png")
FILTER_NAMES = {"ipmcmc": "IP-MCMC-PF", "sir": "SIR PF"}


def _build_filter(args: argparse.Namespace, scenario: Scenario) -> Filter:
    """The demo's filters: IP-MCMC-PF with paper 000's 50 chains and burn-in 100 (by
    default), or the SIR baseline.
    """
    from .filters import IPMCMCFilter, SIRFilter

    if args.filter == "sir":
        return SIRFilter(scenario.motion, scenario.sensor, num_particles=args.particles)
    return IPMCMCFilter(scenario.motion, scenario.sensor, num_particles=args.particles,
                        num_chains=args.chains, burn_in=args.burn_in)


def torch_threads() -> int:
    """The intra-op thread count of torch (imported here: the parser stays light)."""
    import torch

    return torch.get_num_threads()


def _resolve_demo(args: argparse.Namespace) -> None:
    """Fill the sizes not given on the command line from the preset (``--quick`` or not)."""
    preset = DEMO_QUICK if args.quick else DEMO_DEFAULTS
    for key, value in preset.items():
        if getattr(args, key) is None:
            setattr(args, key, value)


def load_average() -> tuple[float, int]:
    """``(1-minute load average, CPU cores)`` of this machine; ``(0.0, 1)`` where the
    platform has no load average (Windows). The demo's one reading of the load (tests
    replace it).
    """
    try:
        return os.getloadavg()[0], os.cpu_count() or 1
    except (OSError, AttributeError):
        return 0.0, 1


#: the torch thread count the demo picks by itself on a loaded machine (``--threads`` not given)
LOADED_THREADS = 1


def demo_threads(args: argparse.Namespace) -> tuple[int | None, str | None]:
    """The torch thread count the demo sets, and why (a line to print, or ``None``).

    ``--threads`` given: that count, no note. Otherwise, when the load average exceeds the
    cores and torch would use more than :data:`LOADED_THREADS` threads: that many (torch's
    threads spin under contention, which made a step of the default demo 38.5 s instead of
    0.5 s on a busy 2-core machine, issue 52), with a note saying so. Else ``None``: torch's
    own count.
    """
    if args.threads:
        return args.threads, None
    load, cores = load_average()
    current = torch_threads()
    if load > cores and current > LOADED_THREADS:
        return LOADED_THREADS, (f"note: load average {load:.1f} on {cores} cores: running torch on {LOADED_THREADS} "
                                f"thread instead of {current} (its threads spin under contention, which can make "
                                "each step 10x slower); --threads N overrides")
    return None, None


def demo_expectation(args: argparse.Namespace) -> str | None:
    """What the demo announces before it runs: the expected time at a preset's sizes, and a
    note when the load average exceeds the cores (other processes slow it down); ``None``
    when there is nothing to say. The thread count is :func:`demo_threads`'s business (it
    has already been set when this runs).
    """
    lines = []
    for name, preset in (("quick", DEMO_QUICK), ("default", DEMO_DEFAULTS)):
        if args.filter == "ipmcmc" and all(getattr(args, k) == v for k, v in preset.items()):
            per_step = DEMO_SECONDS_PER_STEP[name]
            total = per_step * args.steps
            lines.append(f"expected: about {total:.1f} s of filtering" if total < 1 else
                         f"expected: about {total:.0f} s of filtering")
            lines[-1] += f" ({per_step:.2f} s per step) on a quiet 2-core CPU"
            break
    load, cores = load_average()
    if load > cores and (args.threads or torch_threads()) > 1:
        lines.append(f"note: load average {load:.1f} on {cores} cores: other processes compete for the CPU and "
                     "torch's threads spin under contention, which can make each step 10x slower; --threads 1 "
                     "avoids most of it")
    elif load > cores:
        lines.append(f"note: load average {load:.1f} on {cores} cores: other processes compete for the CPU, so "
                     "expect this to run slower")
    return "\n".join(lines) or None


def _check_demo(parser: argparse.ArgumentParser, args: argparse.Namespace) -> None:
    """Errors argparse cannot see option by option (one line each, exit status 2), all
    before the output folder is touched: the filter's settings are built here once, so a
    value the filter refuses (``--chains 1``) fails as an argument error.
    """
    if args.filter == "ipmcmc":
        from .filters.ipmcmc import IPMCMCSettings

        try:
            IPMCMCSettings(num_chains=args.chains, burn_in=args.burn_in)
        except ValueError as err:
            parser.error(f"argument --{str(err).split(' ', 1)[0].replace('num_chains', 'chains').replace('_', '-')}: "
                         f"{err}")
        if args.particles % args.chains:
            parser.error(f"argument --particles: {args.particles} particles do not divide into "
                         f"--chains {args.chains}; use a multiple of {args.chains}")
        if args.particles // args.chains < 2:
            parser.error(f"argument --particles: {args.particles} particles in --chains {args.chains} leave "
                         f"{args.particles // args.chains} per chain; R-hat needs at least 2")


def _demo_parser(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser(
        "demo",
        help="IP-MCMC-PF on the 10-target ground-radar scenario (--filter sir: the SIR baseline)",
        description=(
            "Filter the ground-radar TBD scenario of Bocquel, Driessen and Bagchi (2012, Table I) "
            "with the IP-MCMC-PF (or, --filter sir, the multitarget SIR particle filter, which "
            "loses these targets), print the position RMSE (labels matched) and the track loss "
            "rate, and write metrics.json and tracks.png. Defaults: 1000 particles in 50 chains, "
            "burn-in 100, 2 runs, 20 steps, 10 targets: about 10 s on a quiet 2-core CPU (0.5 s per "
            "step); --quick: 1 run, 5 steps, 500 particles, about 1 s. Other processes on the cores "
            "slow it down many times over (torch's threads spin): when the load is high and --threads is not "
            "given, the demo runs torch on 1 thread and says so."
        ),
    )
    p.add_argument("--particles", type=positive_int,
                   help=f"particles N (default: {DEMO_DEFAULTS['particles']}, quick: {DEMO_QUICK['particles']})")
    p.add_argument("--runs", type=positive_int,
                   help=f"Monte Carlo runs B, filtered as one batch (default: {DEMO_DEFAULTS['runs']}, "
                        f"quick: {DEMO_QUICK['runs']})")
    p.add_argument("--steps", type=positive_int,
                   help=f"time steps T (default: {DEMO_DEFAULTS['steps']}, quick: {DEMO_QUICK['steps']})")
    p.add_argument("--targets", type=positive_int,
                   help=f"targets K (default: {DEMO_DEFAULTS['targets']}, quick: {DEMO_QUICK['targets']})")
    p.add_argument("--filter", choices=("ipmcmc", "sir"), default="ipmcmc",
                   help="ipmcmc: IP-MCMC-PF (default); sir: multitarget SIR PF, the baseline")
    p.add_argument("--chains", type=positive_int,
                   help="IP-MCMC-PF chains C; --particles must be a multiple of it, with at least 2 "
                        f"particles per chain (default: {DEMO_DEFAULTS['chains']})")
    p.add_argument("--burn-in", type=nonnegative_int,
                   help=f"IP-MCMC-PF burn-in iterations per step (default: {DEMO_DEFAULTS['burn_in']})")
    p.add_argument("--quick", action="store_true",
                   help="one run of 5 steps with 500 particles: about 1 s of filtering on a quiet 2-core CPU "
                        "(the default: about 10 s)")
    add_common_arguments(p, name="demo", quick=False, shards=False)
    p.set_defaults(command=_demo)


def demo_figure(scenario: Scenario, result: FilterResult, rmse: RMSE, args: argparse.Namespace) -> Figure:
    """The demo's figure: run 0's true and estimated tracks, and the RMSE over time."""
    import matplotlib.pyplot as plt

    from .plotting import plot_rmse, plot_tracks

    label = np_label(FILTER_NAMES[args.filter], args.particles)
    fig, (ax_tracks, ax_rmse) = plt.subplots(1, 2, figsize=(12, 4.8), layout="constrained")
    plot_tracks(ax_tracks, scenario.truth, result.mean, run=0, estimate_label=label)
    ax_tracks.set_title("run 0: true (solid), estimated (dashed)")
    plot_rmse(ax_rmse, {label: rmse.per_step}, dt=scenario.dt)
    ax_rmse.set_title(f"position RMSE, {args.runs} run(s), labels matched")
    fig.suptitle(f"{args.targets} targets, {args.steps} steps, {label}")
    return fig


def _demo(args: argparse.Namespace) -> dict:
    import matplotlib

    matplotlib.use("Agg")

    out = prepare_out(args.out, DEMO_OUTPUTS)
    threads, why = demo_threads(args)
    if why:
        print(why, flush=True)
    with torch_threads_set(threads):
        args.threads = threads or args.threads  # recorded in metrics.json; the expectation's note knows it
        return _run_demo(args, out)


@contextlib.contextmanager
def torch_threads_set(threads: int | None) -> Iterator[None]:
    """``torch.set_num_threads(threads)`` for the block (nothing when ``None``), the previous
    count restored after it (``main`` called in-process, as the tests do, leaves torch as it was).
    """
    import torch

    previous = torch.get_num_threads()
    if threads:
        torch.set_num_threads(threads)
    try:
        yield
    finally:
        if threads:
            torch.set_num_threads(previous)


def _run_demo(args: argparse.Namespace, out: Path) -> dict:
    """The demo proper, in the output folder ``out``, with its thread count set."""
    import torch

    from . import runtime
    from .metrics import position_rmse, track_loss
    from .scenarios import ground_radar

    if args.memory_budget:
        runtime.set_memory_budget(args.memory_budget)
    g = generator(args.device, args.seed)
    scenario = ground_radar(args.targets, args.steps, args.runs, generator=g, device=args.device)
    filt = _build_filter(args, scenario).to(args.device)
    init = scenario.initial_particles(args.particles, generator=g)
    note = demo_expectation(args)
    if note:
        print(note, flush=True)
    # no gradients: inference mode drops autograd's per-operation work (docs/performance.md)
    with StepTimer(args.device, steps=args.steps) as timer, torch.inference_mode():
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
    hidden = ("started", "command_line")
    path = write_metrics(out, metrics, settings={k: v for k, v in vars(args).items() if k not in hidden},
                         options=RunOptions.from_namespace(args))
    save_figure(demo_figure(scenario, result, rmse, args), out, "tracks.png")

    chains = f" in {args.chains} chains" if args.filter == "ipmcmc" else ""
    print(f"ground radar: K={args.targets} targets, T={args.steps} steps, B={args.runs} runs, "
          f"N={args.particles} particles{chains}, {type(filt).__name__}, "
          f"grid {'x'.join(map(str, scenario.sensor.frame_shape))}, device {args.device}")
    print(f"position RMSE (labels matched): {float(rmse.overall):.2f} m")
    print(f"track loss rate (max error > 20 m): {float(lost.float().mean()):.0%} "
          f"({int(lost.sum())}/{args.runs} runs)")
    print(f"seconds per step: {timer.seconds_per_step:.3f}")
    print(f"wrote {path} and {out / 'tracks.png'}")
    return metrics


def _reproduce_help_parser(found: dict) -> argparse.ArgumentParser:
    """``reproduce --help``: the name, --list and the options common to every study."""
    width = max((len(n) for n in found), default=0)
    listing = "\n".join(f"  {n:<{width}}  {s.description}" for n, s in found.items())
    parser = argparse.ArgumentParser(
        prog="python -m torchmcmcpf reproduce",
        formatter_class=argparse.RawDescriptionHelpFormatter,
        description="Run a Monte Carlo study of torchmcmcpf.experiments, write metrics.json and its "
                    "figures, and print its headline table.",
        epilog=f"studies:\n{listing}\n\nstudy options: python -m torchmcmcpf reproduce NAME --help",
    )
    parser.add_argument("name", nargs="?", help="study NAME (see --list)")
    parser.add_argument("--list", action="store_true", help="list the studies and exit")
    add_common_arguments(parser, name="NAME", shards=False)
    add_shard_arguments(parser, studies=[n for n, s in found.items() if s.sharded])
    return parser


def _reproduce(argv: Sequence[str], command_line: str, started: float) -> dict:
    from . import experiments

    pre = argparse.ArgumentParser(prog="python -m torchmcmcpf reproduce", add_help=False)
    pre.add_argument("name", nargs="?")
    pre.add_argument("--list", action="store_true")
    pre.add_argument("-h", "--help", action="store_true")
    known, rest = pre.parse_known_args(argv)
    found = experiments.discover()
    if known.list or (known.name is None and not known.help):
        width = max((len(n) for n in found), default=0)
        for name, each in found.items():
            print(f"{name:<{width}}  {each.description}")
        if not found:
            print("no experiments found in torchmcmcpf/experiments/")
        if not known.list:
            pre.error("the experiment NAME is required (listed above)")
        return {}
    if known.name is None:
        _reproduce_help_parser(found).print_help()
        return {}
    if known.name not in found:
        pre.error(f"argument name: unknown experiment {known.name!r}; choose from {sorted(found)}")
    study = found[known.name]
    parser = argparse.ArgumentParser(prog=f"python -m torchmcmcpf reproduce {known.name}",
                                     description=study.description)
    add_common_arguments(parser, name=known.name, shards=study.sharded,
                         shard_size=study.defaults_text("shard_size") if study.sharded else None)
    given = [a.split("=", 1)[0] for a in rest if a.split("=", 1)[0] in SHARD_OPTIONS]
    if given and not study.sharded:
        parser.error(f"argument {given[0]}: {known.name} does not run in shards, so it has no {given[0]}; "
                     f"the studies that do: {', '.join(n for n, s in found.items() if s.sharded)}")
    study.add_arguments(parser.add_argument_group(f"options of {known.name}"))
    args = parser.parse_args(rest + (["--help"] if known.help else []))
    if getattr(args, "ray_address", None) and not args.workers:
        parser.error("argument --ray-address: needs --workers N (how many shards run at once)")
    try:  # inconsistent settings: a one-line argument error, not a traceback
        settings = study.settings_from(args)
    except ValueError as err:
        parser.error(str(err))
    try:
        out = prepare_out(args.out, study.outputs)
    except ValueError as err:
        parser.error(f"argument --{err}")
    options = RunOptions.from_namespace({**vars(args), "out": out, "command_line": command_line, "started": started})
    result = study.run(settings, options)
    print(f"\n{known.name}: wrote {out}")
    print(study.summary(result) or headline_table(result))
    if getattr(settings, "quick", False):  # the figures are stamped too; the terminal says it here
        print("\nQUICK RUN: tiny sizes (seconds, for checking that the study runs). These figures are not "
              "comparable with each other, the full study's or the papers'; run without --quick for those.")
    return result


def headline_table(result: dict) -> str:
    """The headline table of a study without its own ``summary``: its scalar results (numbers,
    strings, 0-d tensors, one level of nested dicts) as a two-column markdown table.
    """
    import torch

    rows = []

    def add(key: str, value: object) -> None:
        if torch.is_tensor(value) and value.dim() == 0:
            value = value.item()
        if isinstance(value, float):
            rows.append((key, f"{value:.4g}"))
        elif isinstance(value, (int, str)):
            rows.append((key, str(value)))

    for key, value in result.items():
        if isinstance(value, dict):
            for sub, inner in value.items():
                add(f"{key}.{sub}", inner)
        else:
            add(key, value)
    return "\n".join(["| quantity | value |", "| --- | --- |", *(f"| {k} | {v} |" for k, v in rows)])


BENCH_OUTPUTS = ("bench.json", "bench.md", "bench_scaling.png", "bench_compare.md")
#: how long the full ``bench`` takes on 2 quiet cores, as benchmarks/README.md measured it (the
#: one figure the help, the README and the benchmarks README state)
BENCH_MINUTES = "3-6"


def _ratio_above_1(text: str) -> float:
    """An argparse type: a ratio > 1 (``--threshold``)."""
    try:
        value = float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"{text!r} is not a number") from None
    if not 1 < value < float("inf"):
        raise argparse.ArgumentTypeError(f"{text!r} is not a ratio above 1 (e.g. 1.10: 10% slower)")
    return value


def _bench_parser(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser(
        "bench",
        help="headline benchmarks: write bench.json, bench.md and bench_scaling.png",
        description=(
            "Time one step of the radar SIR PF (N=5000, K=10, compiled), the IP-MCMC-PF (Np=5000, "
            "50 chains, burn-in 100; Np=500 with B=1 and B=10 runs), the sequential MCMC-PF (C=50, "
            "N=5000) and point-measurement SIR against Stone Soup (N=5000, B=1 and B=100); sweep N, "
            "K and B. Minimum over repeats. Writes bench.json (device, torch version, thread count, "
            "figures), bench.md (the table) and bench_scaling.png (log-log scaling), under results/bench "
            "unless --out says otherwise. It also times the point SIR through forward and step against "
            "Stone Soup and particles (T=25, N=2000, B=100, with the log-evidence against the Kalman value). "
            f"About {BENCH_MINUTES} minutes on 2 quiet CPU cores (benchmarks/README.md); --quick takes seconds. "
            "Compare figures within one run: on a "
            "busy machine torch's threads spin (benchmarks/README.md). The detailed benchmarks are "
            "pytest-benchmark files: pytest benchmarks/ --benchmark-only."
        ),
        epilog=(
            "Guard against regressions: --compare FILE prints, after the table, each figure's ratio "
            "now / stored beside both times (and bench_compare.md), flags a figure of ours above "
            "--threshold (1.10) as SLOWER, warns when the machines, torch, thread counts or sizes differ, "
            "and ends on one line saying which figures got slower. The stored CPU run is "
            "benchmarks/reference-cpu.json (--compare and --save without FILE use it; "
            "reference-cuda.json with --device cuda): write it on a quiet machine with "
            "'python -m torchmcmcpf bench --threads 2 --save' and commit it; compare a change with "
            "'python -m torchmcmcpf bench --compare', which runs at the stored run's thread count unless "
            "--threads says otherwise."
        ),
    )
    p.add_argument("--device", choices=("cpu", "cuda"), default="cpu", help="device (default: %(default)s)")
    p.add_argument("--quick", action="store_true", help="tiny sizes, eager, one repeat (seconds)")
    p.add_argument("--threads", type=positive_int, default=None,
                   help="torch.set_num_threads for the run (default: the stored run's count with --compare, "
                        "else torch's current count); recorded")
    p.add_argument("--out", type=out_dir, default=Path("results") / "bench",
                   help="output directory (default: results/bench); files of the same name are replaced")
    p.add_argument("--no-stonesoup", action="store_true", help="skip the Stone Soup comparison")
    p.add_argument("--compare", nargs="?", const="", metavar="FILE",
                   help="compare with a stored run (a bench.json; no FILE: benchmarks/reference-<device>.json), "
                        "read before anything is timed")
    p.add_argument("--threshold", type=_ratio_above_1, default=None, metavar="RATIO",
                   help="with --compare: flag a figure of ours slower than RATIO x the stored run (default: 1.10)")
    p.add_argument("--save", nargs="?", const="", metavar="FILE",
                   help="also write the result (bench.json) to FILE, a stored run for a later --compare "
                        "(no FILE: benchmarks/reference-<device>.json)")
    p.set_defaults(command=_bench)


def _bench_files(args: argparse.Namespace) -> tuple[Path | None, Path | None, int | None]:
    """``--compare`` and ``--save`` as paths (no FILE: the stored reference of the device),
    checked before anything is timed: a ``ValueError`` naming the argument otherwise; and the
    thread count the stored run was timed at (its ``threads``; None without ``--compare`` or
    where it records none), at which a ``--compare`` without ``--threads`` runs: figures timed
    at another count differ by the count (one thread against two: 1.1-1.5x on the radar steps).
    """
    from .bench import load_result, reference_path

    stored = save = stored_threads = None
    if args.compare is not None:
        stored = Path(args.compare) if args.compare else reference_path(args.device)
        try:
            threads = load_result(stored).get("threads")
        except ValueError as err:
            raise ValueError(f"argument --compare: {err}") from None
        if isinstance(threads, int) and not isinstance(threads, bool) and threads > 0:
            stored_threads = threads
    elif args.threshold is not None:
        raise ValueError("argument --threshold: needs --compare (the stored run to compare with)")
    if args.save is not None:
        save = Path(args.save) if args.save else reference_path(args.device)
        if not args.save and args.quick:
            raise ValueError(f"argument --save: a --quick run is no reference; give a FILE other than {save}")
        if save.is_dir():
            raise ValueError(f"argument --save: {str(save)!r} is a directory, expected a file")
        for parent in save.parents:
            if parent.exists():
                if not parent.is_dir():
                    raise ValueError(f"argument --save: {str(save)!r} lies under {str(parent)!r}, which is a file")
                break
    return stored, save, stored_threads


def _bench(args: argparse.Namespace) -> dict:
    from .bench import SLOWER, comparison_markdown, run, write_result

    if args.device == "cuda":
        import torch

        if not torch.cuda.is_available():
            raise SystemExit("error: argument --device: cuda requested but torch.cuda.is_available() is False")
    stored, save, stored_threads = _bench_files(args)
    threads = args.threads
    if threads is None and stored_threads is not None:  # like for like: the stored run's thread count
        threads = stored_threads
        print(f"--compare: {threads} thread{'s' if threads > 1 else ''}, as the stored run {stored} "
              "(--threads to change)", flush=True)
    out = prepare_out(args.out, BENCH_OUTPUTS)
    result = run(args.device, quick=args.quick, threads=threads, out=out, stonesoup=not args.no_stonesoup,
                 log=lambda line: print(line, flush=True), compare_with=stored, threshold=args.threshold or SLOWER)
    if save is not None:
        stored_run = {k: v for k, v in result.items() if k != "comparison"}
        print(f"saved the run to {write_result(stored_run, save)} (a stored run for --compare)")
    print((out / "bench.md").read_text())
    if "comparison" in result:  # the closing note: which figures got slower than the stored run
        print(comparison_markdown(result["comparison"]), end="")
    return result


@contextlib.contextmanager
def _one_line_errors(prog: str) -> Iterator[None]:
    """Turn a ``ValueError`` (bad input, by the library's convention) or a failed shard into
    one ``error:`` line on stderr and exit status 2 (1 for a shard that failed otherwise);
    ``TORCHMCMCPF_TRACEBACK=1`` lets the exception through with its traceback.
    """
    try:
        yield
    except (ValueError, ShardError) as err:
        if os.environ.get("TORCHMCMCPF_TRACEBACK"):
            raise
        bad_input = isinstance(err, ValueError) or isinstance(err.__cause__, ValueError) or ": ValueError: " in str(err)
        message = " ".join(str(err).split())  # one line, whatever the exception's text
        print(f"{prog}: error: {message} (TORCHMCMCPF_TRACEBACK=1 shows the traceback)", file=sys.stderr)
        raise SystemExit(2 if bad_input else 1) from None


def main(argv: Sequence[str] | None = None) -> int:
    """Entry point of ``python -m torchmcmcpf`` and of the ``torchmcmcpf`` script.

    Returns 0 on success (results are in the output directory's ``metrics.json``);
    argument errors exit with status 2 and a message naming the argument.
    """
    from .runtime import tune_cpu_allocator

    started = time.perf_counter()
    tune_cpu_allocator()  # large per-step temporaries reuse warm pages (torchmcmcpf.runtime)
    argv = list(sys.argv[1:] if argv is None else argv)
    argv = [str(a) for a in argv]  # allow Path arguments in-process
    command_line = shlex.join(["python", "-m", "torchmcmcpf", *argv])
    if argv[:1] == ["reproduce"]:
        name = argv[1] if len(argv) > 1 and not argv[1].startswith("-") else ""
        with _one_line_errors(f"python -m torchmcmcpf reproduce {name}".rstrip()):
            _reproduce(argv[1:], command_line, started)
        return 0
    parser = argparse.ArgumentParser(
        prog="python -m torchmcmcpf",
        description="MCMC-based particle filters for multi-target track-before-detect.",
    )
    sub = parser.add_subparsers(dest="cmd", required=True, metavar="{demo,reproduce,bench}")
    _demo_parser(sub)
    sub.add_parser("reproduce", help="run a study of torchmcmcpf.experiments (reproduce --list)")
    _bench_parser(sub)
    args = parser.parse_args(argv)
    args.command_line, args.started = command_line, started
    if args.cmd == "demo":
        _resolve_demo(args)
        _check_demo(sub.choices["demo"], args)
    with _one_line_errors(f"python -m torchmcmcpf {args.cmd}"):
        args.command(args)
    return 0


if __name__ == "__main__":
    sys.exit(main())
