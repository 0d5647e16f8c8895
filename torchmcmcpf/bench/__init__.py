"""The headline benchmarks of ``python -m torchmcmcpf bench`` (issues 12 and 26), in one run.

Every figure times what a user calls: the public :meth:`~torchmcmcpf.filters.base.Filter.step`
and :meth:`~torchmcmcpf.filters.base.Filter.forward` (per step), never a private method.
Each is the minimum over repeated calls (warm-up and compilation excluded), timed with the
device synchronised; figures compared with each other are timed in turn within the same
rounds (:func:`time_interleaved`). ``per_run_s`` divides by the B runs of the batch. Written
to ``bench.json`` (device name, torch version, thread count, every figure),
``bench.md`` (the table) and ``bench_scaling.png`` (time per step against N, K and B, log-log).

Headlines (``--quick``: tiny sizes, eager, one repeat, seconds):

- radar TBD SIR step, B = 1, N = 5000, K = 10, compiled kernel (ground radar of paper 000);
- IP-MCMC-PF step, Np = 5000, 50 chains, burn-in 100, K = 10, B = 1, compiled; and Np = 500
  with B = 1 and B = 10 runs (the per-run cost of a batch);
- sequential MCMC-PF step, C = 50 chains, N = 5000, K = 10 (burn-in 0, thinning 1, the
  mixture moves of paper 004), compiled;
- point-measurement SIR (one target, known association, :class:`LinearGaussian` position
  sensor, :class:`ConstantVelocity` motion, systematic resampling at every step), N = 5000,
  B = 1 and B = 100, through ``forward`` and ``step``, eager and compiled, and the pure step
  function :func:`~torchmcmcpf.filters.sir_step` (what ``step``'s checks add), against
  Stone Soup 1.9.1's ``ParticlePredictor`` + ``ParticleUpdater`` + ``SystematicResampler`` on
  the same model in each documented way of giving the weights (the fastest is kept; Stone
  Soup loops over the runs);
- the same model against ``particles`` (Chopin's SMC library): bootstrap filter, systematic
  resampling at every step, T = 25, N = 2000, B = 100 runs (``particles`` loops over them),
  with both log-evidences compared with the exact Kalman value of each run.

The R-hat extensions of the IP-MCMC-PF are off (``max_extensions=0``) so that a step always
runs ``burn_in + Np / C`` iterations. Use :func:`run` from Python, or the command line.

``bench.json`` (``schema`` :data:`SCHEMA`) holds a ``machine`` record (:func:`machine`: its
``name``, the CPU model and core count or the GPU; ``cpu``, ``cores``, ``torch``, ``threads``,
``device_type``, ``python``, ``platform``, ``date``) and every figure with its ``seconds`` per
step, ``per_run_s``, ``params``, ``kind`` (``ours``, ``floor`` or ``peer``), its ``floor`` (the
floor figure's name) and ``floor_s``, ``target_s``, ``note`` and ``check``.

The guard against regressions (issue 49): a stored run, kept in ``benchmarks/`` with its
machine named, and every later run compared with it (:func:`compare`), so that a change that
slows a step shows in the closing note of ``bench``::

    # once, on a quiet machine (the lead engineer; then commit the file)
    python -m torchmcmcpf bench --threads 2 --save          # -> benchmarks/reference-cpu.json
    # after a change: at the stored run's thread count (--threads overrides)
    python -m torchmcmcpf bench --compare                   # <- benchmarks/reference-cpu.json
    python -m torchmcmcpf bench --compare OTHER.json --threshold 1.2

``--compare`` reads the stored run before anything is timed (a missing, non-JSON or malformed
file is a one-line error naming ``--compare``), prints after the table each figure's time now
and stored and their ratio, now / stored (and the ratio of the figure's multiples of its floor,
which divides out the machine's own speed), flags a figure of ours above ``--threshold``
(1.10) as SLOWER, lists the figures in one run only, warns when the machines (both named),
torch, the thread counts or the sizes differ, and ends on one line naming the slower figures.
It also writes ``bench_compare.md`` and keeps the comparison under the result's
``comparison``. With ``--device cuda`` the stored run is ``benchmarks/reference-cuda.json``.
No reference is committed until one is measured on a quiet machine: one from a busy machine
would flag noise.
"""

from __future__ import annotations

import datetime
import gc
import json
import math
import os
import platform
import time
from collections.abc import Callable
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, Any

import torch

from .peers import (
    POINT_M0,
    POINT_MODEL,
    STONESOUP_WEIGHTS,
    _point_track,
    evidence_errors,
    kalman_log_evidence,
    particles_runs,
    point_filter,
    point_floor,
    point_sir_forward,
    point_sir_step,
    radar_floor,
    stonesoup_step,
)
from .results import (
    KINDS,
    SCHEMA,
    SLOWER,
    check_result,
    compare,
    comparison_markdown,
    comparison_summary,
    figure_kind,
    load_result,
    reference_path,
)

if TYPE_CHECKING:
    from ..filters.base import Filter
    from ..scenarios.ground_radar import Scenario
    from ..typing import Measurement

__all__ = ["Figure", "run", "time_step", "time_interleaved", "radar_problem", "stonesoup_step", "point_filter",
           "point_sir_forward", "point_sir_step", "point_floor", "radar_floor", "particles_runs", "kalman_log_evidence",
           "evidence_errors", "TARGETS_S", "POINT_M0", "POINT_MODEL", "KINDS", "SCHEMA", "SLOWER", "check_result",
           "compare", "comparison_markdown", "comparison_summary", "figure_kind", "load_result", "reference_path",
           "write_result"]

#: issue 12's targets on a 2-core CPU [s per step] (per run for the batched IP-MCMC-PF)
TARGETS_S = {"radar-sir": 0.030, "ipmcmc-5000": 0.040, "ipmcmc-500-B10": 0.015, "mcmc-pf": 0.2}
#: issue 12's aim on one GPU: the IP-MCMC-PF step at Np = 5000 for all 100 runs of Table II
#: in <= 10 ms, i.e. 0.1 ms per run (figure ``ipmcmc-5000-B100``, measured with --device cuda)
GPU_TARGETS_S = {"ipmcmc-5000-B100": 0.010 / 100}
#: point SIR (issue 26): Stone Soup's fastest configuration / ours (public path) at least this, by B
TARGET_SPEEDUP = {1: 5.0, 100: 20.0}
#: the bootstrap filter of ``particles`` per run / ours per run (B runs batched) at least this, by B
TARGET_SPEEDUP_PARTICLES = {100: 20.0}


@dataclass
class Figure:
    """One measured figure: ``seconds`` per step for the whole batch of ``params['B']`` runs.

    ``kind``: ``"ours"`` (a step of this library, what a regression slows), ``"floor"`` (what
    no implementation of the step can avoid, :func:`radar_floor`, :func:`point_floor`) or
    ``"peer"`` (another library on the same problem). ``floor`` names the figure of this
    one's floor and ``floor_s`` is its time (``None`` where none was measured).
    """

    name: str
    seconds: float
    params: dict
    target_s: float | None = None
    note: str = ""
    check: dict = field(default_factory=dict)
    kind: str = "ours"
    floor: str | None = None
    floor_s: float | None = None
    per_run_s: float = field(init=False)

    def __post_init__(self):
        self.per_run_s = self.seconds / self.params.get("B", 1)


def _sync(device: torch.device) -> None:
    if device.type == "cuda":
        torch.cuda.synchronize(device)


def time_step(step: Callable[[], object], *, repeats: int, device: torch.device, warmup: int = 1) -> float:
    """Minimum wall time [s] of ``step()`` over ``repeats`` calls after ``warmup`` calls
    (compilation happens in the warm-up): :func:`time_interleaved` of one variant.
    """
    return time_interleaved({"step": step}, repeats=repeats, device=device, warmup=warmup)["step"]


def time_interleaved(steps: dict[str, Callable[[], object]], *, repeats: int, device: torch.device,
                     warmup: int = 1, per_call: int = 1, block_s: float = 0.05) -> dict[str, float]:
    """Minimum wall time [s] of each of ``steps`` over ``repeats`` rounds, the variants called
    in turn within each round (so that a burst of load on a shared machine hits them alike),
    divided by ``per_call`` (the steps one call makes). Warm-up calls first (compilation).

    As ``timeit``, Python's garbage collector is run before each timed block and kept off
    during it (otherwise the call after Stone Soup's paid for its objects: a public step at
    B = 1 measured 10-30 ms instead of 0.4), and a block is as many consecutive calls as take
    about ``block_s`` (from a call timed after the warm-up; one call when ``warmup = 0``), as
    ``timeit``'s ``autorange`` loops: a lone call right after the collection runs cold, 1-3 ms
    slower on the 2-core CPU (the public point SIR step at B = 1: 1.57 ms alone against 0.59
    in a block of 20, Stone Soup's step 2.8 against 2.0; at B = 100 the floor 9.1 against 6.4).
    """
    def per_call_s(fn: Callable[[], object], calls: int) -> float:
        """Wall time of ``calls`` consecutive calls, divided by ``calls``."""
        _sync(device)
        start = time.perf_counter()
        for _ in range(calls):
            fn()
        _sync(device)
        return (time.perf_counter() - start) / calls

    best = dict.fromkeys(steps, math.inf)
    block = dict.fromkeys(steps, 1)
    with torch.no_grad():
        for name, fn in steps.items():
            for _ in range(warmup):
                fn()
            if warmup:  # one more call, warm, sizes the block
                block[name] = max(1, min(100, math.ceil(block_s / max(per_call_s(fn, 1), 1e-9))))
        for _ in range(repeats):
            for name, fn in steps.items():
                gc.collect()  # the garbage of the previous block (Stone Soup makes much) is not this one's
                gc.disable()  # as timeit: no collection inside a timed block
                try:
                    best[name] = min(best[name], per_call_s(fn, block[name]))
                finally:
                    gc.enable()
    return {name: t / per_call for name, t in best.items()}


# -- radar TBD filters -------------------------------------------------------------------------
def radar_problem(n: int, k: int, b: int, device: torch.device, seed: int = 0) -> tuple[Scenario, torch.Tensor]:
    """The ground radar of paper 000 (K targets, B runs, 20 frames, windowed likelihood) and
    its initial cloud ``(B, N, K, 5)``: ``(scenario, x0)``.
    """
    from ..scenarios import ground_radar

    g = torch.Generator(device).manual_seed(seed)
    scn = ground_radar(k, 20, b, generator=g, device=device)
    return scn, scn.initial_particles(n, generator=g)


def filter_step(filt: Filter, x0: torch.Tensor, z: Measurement, device: torch.device, seed: int = 1
                ) -> Callable[[], object]:
    """One step of ``filt`` from ``x0`` on the frame ``z`` through the public
    :meth:`~torchmcmcpf.filters.base.Filter.step` (every call from the same initial state,
    which the filter made with :meth:`~torchmcmcpf.filters.base.Filter.init` and so checks
    cheaply).
    """
    filt = filt.to(device)
    state = filt.init(x0)
    g = torch.Generator(device).manual_seed(seed)
    return lambda: filt.step(state, z, generator=g)


def radar_sir(n: int, k: int, b: int, compiled: bool, device: torch.device) -> Callable[[], object]:
    from ..filters import SIRFilter

    scn, x0 = radar_problem(n, k, b, device)
    return filter_step(SIRFilter(scn.motion, scn.sensor, n, compile_step=compiled), x0, scn.measurements[0], device)


def radar_ipmcmc(n: int, k: int, b: int, compiled: bool, device: torch.device, *, chains: int,
                 burn_in: int) -> Callable[[], object]:
    from ..filters import IPMCMCFilter

    scn, x0 = radar_problem(n, k, b, device)
    filt = IPMCMCFilter(scn.motion, scn.sensor, n, num_chains=chains, burn_in=burn_in, max_extensions=0,
                        compile_step=compiled)
    return filter_step(filt, x0, scn.measurements[0], device)


def radar_mcmc(n: int, k: int, b: int, compiled: bool, device: torch.device, *, chains: int
               ) -> Callable[[], object]:
    from ..filters import MCMCFilter

    scn, x0 = radar_problem(n, k, b, device)
    filt = MCMCFilter(scn.motion, scn.sensor, n, num_chains=chains, burn_in=0, thinning=1, moves="mixture",
                      compile_step=compiled)
    return filter_step(filt, x0, scn.measurements[0], device)


#: sizes of the full run (the issue's headline figures) and of ``--quick`` (seconds, for tests)
FULL: dict[str, Any] = dict(n=5000, k=10, chains=50, burn_in=100, n_small=500, b_small=10, b_gpu=100, point_b=(1, 100),
            point_steps=10, point_rounds=9, particles=dict(n=2000, b=100, steps=25), repeats=5,
            slow_repeats=3, compiled=True, sweep_n=(500, 1000, 2000, 5000), sweep_k=(1, 2, 5, 10),
            sweep_b=(1, 2, 5, 10), sweep_base=dict(n=1000, k=10, b=1), sweep_burn_in=20)
QUICK: dict[str, Any] = dict(n=200, k=2, chains=10, burn_in=5, n_small=100, b_small=3, b_gpu=2, point_b=(1, 10),
             point_steps=3, point_rounds=1, particles=dict(n=200, b=4, steps=5), repeats=1,
             slow_repeats=1, compiled=False, sweep_n=(50, 100, 200), sweep_k=(1, 2, 4), sweep_b=(1, 2, 4),
             sweep_base=dict(n=100, k=2, b=1), sweep_burn_in=2)


def cpu_model() -> str:
    """The CPU's model name (``/proc/cpuinfo``; else what :mod:`platform` says)."""
    name = platform.processor() or platform.machine()
    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.startswith("model name"):
                return line.split(":", 1)[1].strip()
    except OSError:
        pass
    return name


def device_name(device: torch.device) -> str:
    """The GPU's name, or the CPU's model name (``/proc/cpuinfo``) and core count."""
    if device.type == "cuda":
        return torch.cuda.get_device_name(device)
    return f"{cpu_model()} ({os.cpu_count()} logical CPUs)"


def machine(device: torch.device) -> dict:
    """The ``machine`` record of ``bench.json``: what a figure depends on besides the code.
    ``name`` identifies the machine (:func:`device_name`: the GPU, or the CPU model and its
    logical CPUs); ``cpu`` and ``cores`` the host; ``threads`` torch's intra-op threads;
    ``date`` when the run ended (UTC, ISO 8601).
    """
    return dict(name=device_name(device), device_type=device.type, cpu=cpu_model(), cores=os.cpu_count(),
                torch=torch.__version__, threads=torch.get_num_threads(), python=platform.python_version(),
                platform=platform.platform(),
                date=datetime.datetime.now(datetime.timezone.utc).isoformat(timespec="seconds"))


def run(device: str = "cpu", *, quick: bool = False, threads: int | None = None,
        out: Path | None = None, stonesoup: bool = True, scaling: bool = True,
        log: Callable[[str], None] = print, compare_with: str | Path | None = None,
        threshold: float = SLOWER) -> dict:
    """Run the headline benchmarks; write ``bench.json``, ``bench.md`` and ``bench_scaling.png``
    under ``out`` (when given). Returns the ``bench.json`` dictionary.

    Parameters
    ----------
    device : ``"cpu"`` or ``"cuda"``.
    quick : tiny sizes, eager, one repeat (seconds; for tests).
    threads : ``torch.set_num_threads`` for the whole run (default: torch's current count).
    stonesoup : compare with Stone Soup (skipped, with a note, when it is not installed).
    scaling : the sweeps over N, K and B and their plot.
    compare_with : a stored ``bench.json`` (e.g. ``benchmarks/reference-cpu.json``), read
        before anything is timed (:func:`load_result`; a bad file is a ``ValueError``): the
        run is compared with it (:func:`compare`, flagging ratios above ``threshold``), the
        comparison kept under the result's ``comparison`` and written to ``bench_compare.md``.
    """
    from ..runtime import tune_cpu_allocator

    stored = None if compare_with is None else load_result(compare_with)
    dev = torch.device(device)
    allocator_tuned = tune_cpu_allocator()
    if dev.type == "cuda" and not torch.cuda.is_available():
        raise ValueError(f"device is {device!r} but torch.cuda.is_available() is False")
    if threads is not None:
        torch.set_num_threads(int(threads))
    cfg = QUICK if quick else FULL
    compiled = cfg["compiled"]
    figures: list[Figure] = []
    started = time.perf_counter()

    def add(fig: Figure) -> None:
        figures.append(fig)
        extra = f" ({fig.per_run_s * 1e3:.2f} ms per run)" if fig.params.get("B", 1) > 1 else ""
        log(f"[{time.perf_counter() - started:6.1f} s] {fig.name}: {fig.seconds * 1e3:.2f} ms per step{extra}"
            f"  {fig.params}")

    n, k, c = cfg["n"], cfg["k"], cfg["chains"]
    target = (lambda name: None) if quick else TARGETS_S.get  # the targets are for the full sizes
    log(f"torchmcmcpf bench on {device_name(dev)}, torch {torch.__version__}, {torch.get_num_threads()} threads"
        f"{', CPU allocator tuned' if allocator_tuned else ''}"
        f"{', quick sizes' if quick else ''}")
    sensor = radar_problem(1, k, 1, dev)[0].sensor
    box = math.prod(sensor.geometry.window_sizes)  # cells per box

    def radar(name: str, step: Callable[[], object], params: dict, repeats: int, terms: int,
              target_s: float | None = None, note: str = "") -> None:
        """Time a radar step and its arithmetic floor (:func:`radar_floor` of ``terms``)."""
        secs = time_step(step, repeats=repeats, device=dev)
        floor = time_step(radar_floor(terms, sensor, dev, compiled=compiled), repeats=cfg["repeats"], device=dev)
        add(Figure(name, secs, params, target_s, note=(f"{note}; " if note else "") + f"{secs / floor:.1f}x the floor",
                   floor=f"{name}-floor", floor_s=floor))
        add(Figure(f"{name}-floor", floor, dict(params, terms=terms), note="arithmetic floor (bench.radar_floor)",
                   kind="floor"))

    def moves(n_: int, b_: int) -> int:  # the IP-MCMC-PF's one-slot moves: 2 boxes, 2 log ratios per cell
        return b_ * (cfg["burn_in"] + n_ // c) * c * 4 * box

    radar("radar-sir", radar_sir(n, k, 1, compiled, dev), dict(N=n, K=k, B=1, compiled=compiled), cfg["repeats"],
          n * k * box, target("radar-sir"))
    ip = dict(chains=c, burn_in=cfg["burn_in"])
    radar(f"ipmcmc-{n}", radar_ipmcmc(n, k, 1, compiled, dev, **ip),
          dict(N=n, C=c, burn_in=cfg["burn_in"], K=k, B=1, compiled=compiled), cfg["slow_repeats"], moves(n, 1),
          target("ipmcmc-5000"))
    ns, bs = cfg["n_small"], cfg["b_small"]
    for b in (1, bs):
        radar(f"ipmcmc-{ns}-B{b}", radar_ipmcmc(ns, k, b, compiled, dev, **ip),
              dict(N=ns, C=c, burn_in=cfg["burn_in"], K=k, B=b, compiled=compiled), cfg["slow_repeats"], moves(ns, b),
              target("ipmcmc-500-B10") if b > 1 else None, "target per run" if b > 1 and not quick else "")
    if dev.type == "cuda":  # the GPU aim: every run of the Table II study in one batch
        bg = cfg["b_gpu"]
        radar(f"ipmcmc-{n}-B{bg}", radar_ipmcmc(n, k, bg, compiled, dev, **ip),
              dict(N=n, C=c, burn_in=cfg["burn_in"], K=k, B=bg, compiled=compiled), cfg["slow_repeats"],
              moves(n, bg), None if quick else GPU_TARGETS_S["ipmcmc-5000-B100"],
              "" if quick else "GPU aim: all 100 runs in <= 10 ms (target per run)")
    # the MCMC-PF's mixture kernel (burn-in 0, N / C iterations per chain): a joint draw
    # (probability 0.75) evaluates one full likelihood, K boxes of one log ratio per cell; a
    # refinement sweep (0.25) K one-slot changes of 2 boxes x 2 log ratios: expected terms
    from ..filters.mcmc import MOVE_PRESETS

    mix = dict(MOVE_PRESETS["mixture"])
    radar("mcmc-pf", radar_mcmc(n, k, 1, compiled, dev, chains=c), dict(N=n, C=c, K=k, B=1, compiled=compiled),
          cfg["slow_repeats"], round((n // c) * c * k * box * (mix["joint"] + 4 * mix["refine"])), target("mcmc-pf"))
    stonesoup = _point_figures(cfg, dev, add, quick, stonesoup, log)
    _particles_figures(cfg, dev, add, quick, log)
    sweeps = {}
    if scaling:
        sweeps = _sweeps(cfg, dev, log, started)
    result: dict[str, Any] = dict(
        schema=SCHEMA, machine=machine(dev), device=device_name(dev), device_type=dev.type, torch=torch.__version__,
        threads=torch.get_num_threads(), quick=quick, python=platform.python_version(),
        cpu_allocator_tuned=allocator_tuned, seconds_total=time.perf_counter() - started,
        figures=[asdict(f) for f in figures], scaling=sweeps)
    if stored is not None:
        result["comparison"] = compare(result, stored, threshold=threshold, source=str(compare_with))
    if out is not None:
        out = Path(out)
        out.mkdir(parents=True, exist_ok=True)
        write_result(result, out / "bench.json")
        (out / "bench.md").write_text(markdown(result))
        written = [out / "bench.json", out / "bench.md"]
        if sweeps:
            plot_scaling(sweeps, out / "bench_scaling.png", title=f"{result['device']}, {result['threads']} threads")
            written.append(out / "bench_scaling.png")
        if stored is not None:
            (out / "bench_compare.md").write_text(comparison_markdown(result["comparison"]))
            written.append(out / "bench_compare.md")
        log(f"wrote {', '.join(map(str, written))}")
    return result


def write_result(result: dict, path: str | Path) -> Path:
    """Write a result of :func:`run` as JSON to ``path`` (parents created): ``bench.json``, or a
    stored run such as ``benchmarks/reference-cpu.json``. Returns the path.
    """
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(json.dumps(result, indent=2) + "\n")
    return path


def _point_figures(cfg: dict, dev: torch.device, add: Callable[[Figure], None], quick: bool, stonesoup: bool,
                   log: Callable[[str], None]) -> bool:
    """Point SIR at N = ``cfg['n']`` for each B of ``cfg['point_b']``: ours through the public
    ``forward`` (per step) and ``step``, eager and (full size) compiled, the pure step function
    (what ``step``'s checks add), against Stone Soup in each of its weight configurations,
    all timed in turn in the same rounds. Returns whether Stone Soup is available.
    """
    n, steps = cfg["n"], cfg["point_steps"]
    modes = (False, True) if cfg["compiled"] else (False,)
    for b in cfg["point_b"]:
        forward = {f"point-sir{'-compiled' if c else ''}-B{b}": point_sir_forward(n, b, steps, dev, compile_step=c)
                   for c in modes}
        single = {f"point-sir-step{'-compiled' if c else ''}-B{b}": point_sir_step(n, b, steps + 2, dev, compile_step=c)
                  for c in modes}
        single[f"point-sir-kernel-B{b}"] = point_sir_step(n, b, steps + 2, dev, public=False)
        single[f"point-floor-B{b}"] = point_floor(n, b, dev)
        peers = {}
        if stonesoup:
            try:
                peers = {w: stonesoup_step(n, b, steps + 2, w) for w in STONESOUP_WEIGHTS}
            except ImportError as err:
                log(f"Stone Soup skipped: {err} (pip install 'torchmcmcpf[bench]')")
                stonesoup = False
        rounds = cfg["point_rounds"]
        times = time_interleaved(forward, repeats=rounds, device=dev, per_call=steps)
        times.update(time_interleaved({**single, **{f"stonesoup[{w}]": f for w, f in peers.items()}},
                                      repeats=rounds, device=dev))
        kernel, floor = times[f"point-sir-kernel-B{b}"], times[f"point-floor-B{b}"]
        ours = {}
        for name in (*forward, *single):
            secs = times[name]
            path = ("pure sir_step" if "kernel" in name else "floor" if "floor" in name
                    else "public step" if "step" in name else "public forward")
            note = "" if path == "floor" else f"{secs / floor:.2f}x the floor"
            if path == "public step":
                note += f"; step / pure sir_step = {secs / kernel:.3f}"
            if path.startswith("public"):
                ours[name] = secs
            is_floor = path == "floor"
            add(Figure(name, secs, dict(N=n, B=b, compiled="compiled" in name, path=path), note=note,
                       kind="floor" if is_floor else "ours", floor=None if is_floor else f"point-floor-B{b}",
                       floor_s=None if is_floor else floor))
        if not peers:
            continue
        configs = {w: times[f"stonesoup[{w}]"] for w in peers}
        fastest = min(configs, key=configs.__getitem__)
        best_ours = min(ours, key=ours.__getitem__)
        ratio = configs[fastest] / ours[best_ours]
        wanted = None if quick else TARGET_SPEEDUP.get(b)
        add(Figure(f"stonesoup-B{b}", configs[fastest], dict(N=n, B=b, weights=fastest),
                   note=f"Stone Soup's fastest / ours ({best_ours}) = {ratio:.1f}x"
                   + (f" (target >= {wanted:g}x: {'met' if ratio >= wanted else 'not met'})" if wanted else ""),
                   check={"configurations_s": configs, "ours": best_ours, "ratio": ratio}, kind="peer",
                   floor=f"point-floor-B{b}", floor_s=floor))
    return stonesoup


def _particles_figures(cfg: dict, dev: torch.device, add: Callable[[Figure], None], quick: bool,
                       log: Callable[[str], None]) -> None:
    """Our SIR filter (B runs in one batch, public ``forward``) against ``particles`` (one run
    at a time) on the point problem with ``cfg['particles']`` sizes, per run, with both
    log-evidences against the exact Kalman value of each run.
    """
    p = cfg["particles"]
    n, b, steps = p["n"], p["b"], p["steps"]
    exact = kalman_log_evidence(_point_track(b, steps)[1])
    try:
        theirs = particles_runs(n, b, steps)
    except ImportError as missing:
        log(f"particles skipped: {missing} (pip install 'torchmcmcpf[bench]')")
        return
    modes = (False, True) if cfg["compiled"] else (False,)
    ours: dict[str, float] = {}
    for c in modes:
        filt, z, x0 = point_filter(n, b, steps, dev, compile_step=c)
        g = torch.Generator(dev).manual_seed(2)
        results: list[Any] = [None]
        name = f"particles-ours{'-compiled' if c else ''}-B{b}"
        secs = time_interleaved({name: lambda: results.__setitem__(0, filt(z, init=x0, generator=g))},
                                repeats=cfg["slow_repeats"], device=dev, per_call=steps)[name]
        ours[name] = secs
        err = evidence_errors(results[0].log_evidence, exact)
        add(Figure(name, secs, dict(N=n, B=b, T=steps, compiled=c, path="public forward"),
                   note=f"log-evidence - Kalman: median {err['median']:+.3f}, IQR {err['iqr']:.3f}",
                   check={"log_evidence_error": err}))
    log_z: list[torch.Tensor] = []
    secs = time_interleaved({"particles": lambda: log_z.append(theirs())}, repeats=1, device=torch.device("cpu"),
                            warmup=0, per_call=steps)["particles"]
    err = evidence_errors(log_z[-1], exact)
    best = min(ours, key=ours.__getitem__)
    ratio = secs / ours[best]
    wanted = None if quick else TARGET_SPEEDUP_PARTICLES.get(b)
    add(Figure(f"particles-B{b}", secs, dict(N=n, B=b, T=steps),
               note=f"particles / ours ({best}) = {ratio:.1f}x"
               + (f" (target >= {wanted:g}x: {'met' if ratio >= wanted else 'not met'})" if wanted else "")
               + f"; log-evidence - Kalman: median {err['median']:+.3f}, IQR {err['iqr']:.3f}",
               check={"log_evidence_error": err, "ours": best, "ratio": ratio}, kind="peer"))


def _sweeps(cfg: dict, dev: torch.device, log: Callable[[str], None], started: float) -> dict:
    """Time per step (eager) of the radar SIR step and of the IP-MCMC-PF step (burn-in
    ``sweep_burn_in``) against N, K and B, one axis at a time from ``sweep_base``.
    """
    base = cfg["sweep_base"]
    chains = min(cfg["chains"], min(cfg["sweep_n"]) // 2)
    makers = {
        "SIR": lambda n, k, b: radar_sir(n, k, b, False, dev),
        f"IP-MCMC-PF (C={chains}, burn-in {cfg['sweep_burn_in']})":
            lambda n, k, b: radar_ipmcmc(n, k, b, False, dev, chains=chains, burn_in=cfg["sweep_burn_in"]),
    }
    sweeps: dict = {}
    for axis, values in (("N", cfg["sweep_n"]), ("K", cfg["sweep_k"]), ("B", cfg["sweep_b"])):
        sweeps[axis] = {}
        for label, make in makers.items():
            times = []
            for v in values:
                p = dict(base, **{axis.lower(): v})
                times.append(time_step(make(p["n"], p["k"], p["b"]), repeats=cfg["slow_repeats"], device=dev))
            sweeps[axis][label] = dict(values=list(values), seconds=times, fixed={a: base[a.lower()] for a in "NKB"
                                                                                  if a != axis})
            log(f"[{time.perf_counter() - started:6.1f} s] sweep {axis} {label}: "
                + ", ".join(f"{v}: {t * 1e3:.1f} ms" for v, t in zip(values, times)))
    return sweeps


def markdown(result: dict) -> str:
    """The ``bench.md`` table: one row per figure, with the issue's target where it has one."""
    lines = [f"Device: {result['device']}; torch {result['torch']}; {result['threads']} threads"
             f"{'; --quick sizes' if result['quick'] else ''}"
             f"{'; CPU allocator tuned' if result.get('cpu_allocator_tuned') else ''}. Minimum over repeats, one run.",
             "",
             "| benchmark | settings | ms per step | ms per run | target | |", "|---|---|---:|---:|---|---|"]
    for f in result["figures"]:
        p = ", ".join(f"{a}={b}" for a, b in f["params"].items())
        target = f"<= {f['target_s'] * 1e3:g} ms" if f["target_s"] else ""
        ok = ""
        if f["target_s"]:
            figure = f["per_run_s"] if f["params"].get("B", 1) > 1 else f["seconds"]
            ok = "met" if figure <= f["target_s"] else "not met"
        lines.append(f"| {f['name']} | {p} | {f['seconds'] * 1e3:.2f} | {f['per_run_s'] * 1e3:.3f} | {target} | "
                     f"{ok}{'; ' if ok and f['note'] else ''}{f['note']} |")
    return "\n".join(lines) + "\n"


def plot_scaling(sweeps: dict, path: Path, title: str = "") -> None:
    """Log-log time per step against N, K and B (one panel each) with a slope-1 guide."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    import matplotlib.ticker

    fig, axes = plt.subplots(1, 3, figsize=(13, 4), layout="constrained")
    for ax, (axis, lines) in zip(axes, sweeps.items()):
        for label, d in lines.items():
            ax.loglog(d["values"], [t * 1e3 for t in d["seconds"]], "o-", label=label)
            v0, t0 = d["values"][0], d["seconds"][0] * 1e3
            ax.loglog(d["values"], [t0 * v / v0 for v in d["values"]], ":", color="grey", lw=1)
        values = next(iter(lines.values()))["values"]
        ax.set_xticks(values, [str(v) for v in values])
        ax.xaxis.set_minor_locator(matplotlib.ticker.NullLocator())
        fixed = ", ".join(f"{a}={v}" for a, v in next(iter(lines.values()))["fixed"].items())
        ax.set(xlabel=axis, ylabel="ms per step", title=f"vs {axis} ({fixed}); dotted: linear")
        ax.legend(fontsize=8)
    fig.suptitle(title)
    fig.savefig(path, dpi=110)
    plt.close(fig)


