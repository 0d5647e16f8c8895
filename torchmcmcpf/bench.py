"""The headline benchmarks of ``python -m torchmcmcpf bench`` (issue 12), in one run.

Each figure is the minimum over repeated calls of one filter step (warm-up and compilation
excluded), timed with the device synchronised; ``per_run_s`` divides by the B runs of the
batch. Written to ``bench.json`` (device name, torch version, thread count, every figure),
``bench.md`` (the table) and ``bench_scaling.png`` (time per step against N, K and B, log-log).

Headlines (``--quick``: tiny sizes, eager, one repeat, seconds):

- radar TBD SIR step, B = 1, N = 5000, K = 10, compiled kernel (ground radar of paper 000);
- IP-MCMC-PF step, Np = 5000, 50 chains, burn-in 100, K = 10, B = 1, compiled; and Np = 500
  with B = 1 and B = 10 runs (the per-run cost of a batch);
- sequential MCMC-PF step, C = 50 chains, N = 5000, K = 10 (burn-in 0, thinning 1, the
  mixture moves of paper 004), compiled;
- point-measurement SIR (one target, known association, :class:`LinearGaussian` position
  sensor, :class:`ConstantVelocity` motion, systematic resampling at every step) against
  Stone Soup 1.9.1's ``ParticlePredictor`` + ``ParticleUpdater`` + ``SystematicResampler``
  on the same model, N = 5000, B = 1 and B = 100 (Stone Soup loops over the runs).

The R-hat extensions of the IP-MCMC-PF are off (``max_extensions=0``) so that a step always
runs ``burn_in + Np / C`` iterations. Use :func:`run` from Python, or the command line.
"""

from __future__ import annotations

import json
import math
import platform
import time
from collections.abc import Callable
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, Any

import torch

if TYPE_CHECKING:
    from .filters.base import Filter
    from .scenarios.ground_radar import Scenario
    from .typing import Measurement

__all__ = ["Figure", "run", "time_step", "radar_problem", "stonesoup_step", "point_sir_step", "TARGETS_S"]

#: issue 12's targets on a 2-core CPU [s per step] (per run for the batched IP-MCMC-PF)
TARGETS_S = {"radar-sir": 0.030, "ipmcmc-5000": 0.040, "ipmcmc-500-B10": 0.015, "mcmc-pf": 0.2}
#: issue 12's aim on one GPU: the IP-MCMC-PF step at Np = 5000 for all 100 runs of Table II
#: in <= 10 ms, i.e. 0.1 ms per run (figure ``ipmcmc-5000-B100``, measured with --device cuda)
GPU_TARGETS_S = {"ipmcmc-5000-B100": 0.010 / 100}
#: point SIR: Stone Soup / ours at least this
TARGET_SPEEDUP = {1: 3.0, 100: 10.0}


@dataclass
class Figure:
    """One measured figure: ``seconds`` per step for the whole batch of ``params['B']`` runs."""

    name: str
    seconds: float
    params: dict
    target_s: float | None = None
    note: str = ""
    per_run_s: float = field(init=False)

    def __post_init__(self):
        self.per_run_s = self.seconds / self.params.get("B", 1)


def _sync(device: torch.device) -> None:
    if device.type == "cuda":
        torch.cuda.synchronize(device)


def time_step(step: Callable[[], object], *, repeats: int, device: torch.device, warmup: int = 1) -> float:
    """Minimum wall time [s] of ``step()`` over ``repeats`` calls after ``warmup`` calls
    (compilation happens in the warm-up).
    """
    with torch.no_grad():
        for _ in range(warmup):
            step()
        _sync(device)
        best = math.inf
        for _ in range(repeats):
            start = time.perf_counter()
            step()
            _sync(device)
            best = min(best, time.perf_counter() - start)
    return best


# -- radar TBD filters -------------------------------------------------------------------------
def radar_problem(n: int, k: int, b: int, device: torch.device, seed: int = 0) -> tuple[Scenario, torch.Tensor]:
    """The ground radar of paper 000 (K targets, B runs, 20 frames, windowed likelihood) and
    its initial cloud ``(B, N, K, 5)``: ``(scenario, x0)``.
    """
    from .scenarios import ground_radar

    g = torch.Generator(device).manual_seed(seed)
    scn = ground_radar(k, 20, b, generator=g, device=device)
    return scn, scn.initial_particles(n, generator=g)


def filter_step(filt: Filter, x0: torch.Tensor, z: Measurement, device: torch.device, seed: int = 1
                ) -> Callable[[], object]:
    """One step of ``filt`` from ``x0`` on the frame ``z``, as :meth:`Filter.forward` runs it
    (arguments validated once, here, not in the timed call).
    """
    filt = filt.to(device)
    state = filt.init(x0)
    filt.validate(state, z, sequence=False)
    g = torch.Generator(device).manual_seed(seed)
    return lambda: filt._step(state, z, g)


def radar_sir(n: int, k: int, b: int, compiled: bool, device: torch.device) -> Callable[[], object]:
    from .filters import SIRFilter

    scn, x0 = radar_problem(n, k, b, device)
    return filter_step(SIRFilter(scn.motion, scn.sensor, n, compile_step=compiled), x0, scn.measurements[0], device)


def radar_ipmcmc(n: int, k: int, b: int, compiled: bool, device: torch.device, *, chains: int,
                 burn_in: int) -> Callable[[], object]:
    from .filters import IPMCMCFilter

    scn, x0 = radar_problem(n, k, b, device)
    filt = IPMCMCFilter(scn.motion, scn.sensor, n, num_chains=chains, burn_in=burn_in, max_extensions=0,
                        compile_step=compiled)
    return filter_step(filt, x0, scn.measurements[0], device)


def radar_mcmc(n: int, k: int, b: int, compiled: bool, device: torch.device, *, chains: int
               ) -> Callable[[], object]:
    from .filters import MCMCFilter

    scn, x0 = radar_problem(n, k, b, device)
    filt = MCMCFilter(scn.motion, scn.sensor, n, num_chains=chains, burn_in=0, thinning=1, moves="mixture",
                      compile_step=compiled)
    return filter_step(filt, x0, scn.measurements[0], device)


# -- point measurements: ours against Stone Soup ------------------------------------------------
POINT_MODEL = dict(dt=1.0, q=0.1, noise_std=1.0)


def _point_track(b: int, steps: int, seed: int = 0) -> tuple[torch.Tensor, torch.Tensor]:
    """Constant-velocity truth ``(steps, B, 4)`` and its noisy position measurements
    ``(steps, B, 2)`` (float64, CPU; both libraries filter the same numbers).
    """
    from .models import ConstantVelocity

    g = torch.Generator().manual_seed(seed)
    motion = ConstantVelocity(POINT_MODEL["dt"], POINT_MODEL["q"]).double()
    x = torch.tensor([0.0, 1.0, 0.0, 1.0], dtype=torch.float64).expand(b, 1, 4)
    truth, z = [], []
    for _ in range(steps):
        x = motion.sample(x, generator=g)
        truth.append(x[:, 0])
        z.append(x[:, 0, ::2] + POINT_MODEL["noise_std"] * torch.randn(b, 2, generator=g, dtype=torch.float64))
    return torch.stack(truth), torch.stack(z)


def point_sir_step(n: int, b: int, steps: int, device: torch.device, dtype: torch.dtype = torch.float32
                   ) -> Callable[[], object]:
    """Our SIR filter on the point problem: each call filters the next measurement (B runs at once)."""
    from .filters import SIRFilter
    from .models import ConstantVelocity, LinearGaussian

    _, z = _point_track(b, steps)
    z = z.to(device=device, dtype=dtype).unsqueeze(2)  # (T, B, K = 1, 2)
    motion = ConstantVelocity(POINT_MODEL["dt"], POINT_MODEL["q"])
    filt = SIRFilter(motion, LinearGaussian.position(POINT_MODEL["noise_std"]), n,
                     resample_method="systematic").to(device=device, dtype=dtype)
    g = torch.Generator(device).manual_seed(1)
    x0 = torch.tensor([0.0, 1.0, 0.0, 1.0], device=device, dtype=dtype) + torch.randn(
        b, n, 1, 4, generator=g, device=device, dtype=dtype)
    init = filt.init(x0)
    filt.validate(init, z, sequence=True)
    state: list[Any] = [init, 0]

    def step():
        s, t = state
        state[0], _ = filt._step(s, z[t % steps], g)
        state[1] = t + 1
        return state[0]

    return step


def stonesoup_step(n: int, b: int, steps: int) -> Callable[[], object]:
    """Stone Soup's particle filter on the same problem: ``ParticlePredictor`` +
    ``ParticleUpdater`` with a ``SystematicResampler`` (resampling at every update), a
    Python loop over the B runs; each call filters the next measurement of every run.
    """
    import datetime

    import numpy as np
    from stonesoup.models.measurement.linear import LinearGaussian as SSLinearGaussian
    from stonesoup.models.transition.linear import CombinedLinearGaussianTransitionModel
    from stonesoup.models.transition.linear import ConstantVelocity as SSConstantVelocity
    from stonesoup.predictor.particle import ParticlePredictor
    from stonesoup.resampler.particle import SystematicResampler
    from stonesoup.types.array import StateVectors
    from stonesoup.types.detection import Detection
    from stonesoup.types.hypothesis import SingleHypothesis
    from stonesoup.types.state import ParticleState as SSParticleState
    from stonesoup.updater.particle import ParticleUpdater

    z = _point_track(b, steps)[1].numpy()
    q, r = POINT_MODEL["q"], POINT_MODEL["noise_std"] ** 2
    transition = CombinedLinearGaussianTransitionModel([SSConstantVelocity(q), SSConstantVelocity(q)])
    sensor = SSLinearGaussian(ndim_state=4, mapping=(0, 2), noise_covar=np.diag([r, r]))
    predictor = ParticlePredictor(transition)
    updater = ParticleUpdater(sensor, resampler=SystematicResampler())
    start = datetime.datetime(2026, 1, 1)
    dt = datetime.timedelta(seconds=POINT_MODEL["dt"])
    rng = np.random.default_rng(1)
    priors = [SSParticleState(StateVectors(np.array([[0.0], [1.0], [0.0], [1.0]]) + rng.standard_normal((4, n))),
                              log_weight=np.full(n, -math.log(n)), timestamp=start) for _ in range(b)]
    t = [0]

    def step():
        k = t[0] % steps
        for i in range(b):  # Stone Soup filters one run at a time
            prediction = predictor.predict(priors[i], timestamp=priors[i].timestamp + dt)
            detection = Detection(z[k, i].reshape(2, 1), timestamp=prediction.timestamp, measurement_model=sensor)
            priors[i] = updater.update(SingleHypothesis(prediction, detection))
        t[0] += 1
        return priors

    return step


# -- the run -------------------------------------------------------------------------------------
#: sizes of the full run (the issue's headline figures) and of ``--quick`` (seconds, for tests)
FULL: dict[str, Any] = dict(n=5000, k=10, chains=50, burn_in=100, n_small=500, b_small=10, b_gpu=100, point_b=(1, 100),
            repeats=5,
            slow_repeats=3, compiled=True, sweep_n=(500, 1000, 2000, 5000), sweep_k=(1, 2, 5, 10),
            sweep_b=(1, 2, 5, 10), sweep_base=dict(n=1000, k=10, b=1), sweep_burn_in=20)
QUICK: dict[str, Any] = dict(n=200, k=2, chains=10, burn_in=5, n_small=100, b_small=3, b_gpu=2, point_b=(1, 10),
             repeats=1,
             slow_repeats=1, compiled=False, sweep_n=(50, 100, 200), sweep_k=(1, 2, 4), sweep_b=(1, 2, 4),
             sweep_base=dict(n=100, k=2, b=1), sweep_burn_in=2)


def device_name(device: torch.device) -> str:
    """The GPU's name, or the CPU's model name (``/proc/cpuinfo``) and core count."""
    if device.type == "cuda":
        return torch.cuda.get_device_name(device)
    name = platform.processor() or platform.machine()
    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.startswith("model name"):
                name = line.split(":", 1)[1].strip()
                break
    except OSError:
        pass
    import os

    return f"{name} ({os.cpu_count()} logical CPUs)"


def run(device: str = "cpu", *, quick: bool = False, threads: int | None = None,
        out: Path | None = None, stonesoup: bool = True, scaling: bool = True,
        log: Callable[[str], None] = print) -> dict:
    """Run the headline benchmarks; write ``bench.json``, ``bench.md`` and ``bench_scaling.png``
    under ``out`` (when given). Returns the ``bench.json`` dictionary.

    Parameters
    ----------
    device : ``"cpu"`` or ``"cuda"``.
    quick : tiny sizes, eager, one repeat (seconds; for tests).
    threads : ``torch.set_num_threads`` for the whole run (default: torch's current count).
    stonesoup : compare with Stone Soup (skipped, with a note, when it is not installed).
    scaling : the sweeps over N, K and B and their plot.
    """
    from .runtime import tune_cpu_allocator

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
    add(Figure("radar-sir", time_step(radar_sir(n, k, 1, compiled, dev), repeats=cfg["repeats"], device=dev),
               dict(N=n, K=k, B=1, compiled=compiled), target("radar-sir")))
    ip = dict(chains=c, burn_in=cfg["burn_in"])
    add(Figure(f"ipmcmc-{n}", time_step(radar_ipmcmc(n, k, 1, compiled, dev, **ip), repeats=cfg["slow_repeats"],
                                        device=dev),
               dict(N=n, C=c, burn_in=cfg["burn_in"], K=k, B=1, compiled=compiled), target("ipmcmc-5000")))
    ns, bs = cfg["n_small"], cfg["b_small"]
    for b in (1, bs):
        add(Figure(f"ipmcmc-{ns}-B{b}",
                   time_step(radar_ipmcmc(ns, k, b, compiled, dev, **ip), repeats=cfg["slow_repeats"], device=dev),
                   dict(N=ns, C=c, burn_in=cfg["burn_in"], K=k, B=b, compiled=compiled),
                   target("ipmcmc-500-B10") if b > 1 else None, note="target per run" if b > 1 and not quick else ""))
    if dev.type == "cuda":  # the GPU aim: every run of the Table II study in one batch
        bg = cfg["b_gpu"]
        add(Figure(f"ipmcmc-{n}-B{bg}",
                   time_step(radar_ipmcmc(n, k, bg, compiled, dev, **ip), repeats=cfg["slow_repeats"], device=dev),
                   dict(N=n, C=c, burn_in=cfg["burn_in"], K=k, B=bg, compiled=compiled),
                   None if quick else GPU_TARGETS_S["ipmcmc-5000-B100"],
                   note="" if quick else "GPU aim: all 100 runs in <= 10 ms (target per run)"))
    add(Figure("mcmc-pf", time_step(radar_mcmc(n, k, 1, compiled, dev, chains=c), repeats=cfg["slow_repeats"],
                                    device=dev),
               dict(N=n, C=c, K=k, B=1, compiled=compiled), target("mcmc-pf")))
    for b in cfg["point_b"]:
        steps = cfg["repeats"] + 1
        ours = time_step(point_sir_step(n, b, steps, dev), repeats=cfg["repeats"], device=dev)
        add(Figure(f"point-sir-B{b}", ours, dict(N=n, B=b, compiled=False)))
        if not stonesoup:
            continue
        try:
            ss = stonesoup_step(n, b, steps)
        except ImportError as err:
            log(f"Stone Soup skipped: {err} (pip install 'torchmcmcpf[bench]')")
            stonesoup = False
            continue
        secs = time_step(ss, repeats=cfg["repeats"], device=torch.device("cpu"))
        wanted = None if quick else TARGET_SPEEDUP.get(b)
        add(Figure(f"stonesoup-B{b}", secs, dict(N=n, B=b), note=f"Stone Soup / ours = {secs / ours:.1f}x"
                   + (f" (target >= {wanted:g}x: {'met' if secs / ours >= wanted else 'not met'})" if wanted else "")))
    sweeps = {}
    if scaling:
        sweeps = _sweeps(cfg, dev, log, started)
    result = dict(device=device_name(dev), device_type=dev.type, torch=torch.__version__,
                  threads=torch.get_num_threads(), quick=quick, python=platform.python_version(),
                  cpu_allocator_tuned=allocator_tuned,
                  seconds_total=time.perf_counter() - started,
                  figures=[asdict(f) for f in figures], scaling=sweeps)
    if out is not None:
        out = Path(out)
        out.mkdir(parents=True, exist_ok=True)
        (out / "bench.json").write_text(json.dumps(result, indent=2))
        (out / "bench.md").write_text(markdown(result))
        if sweeps:
            plot_scaling(sweeps, out / "bench_scaling.png", title=f"{result['device']}, {result['threads']} threads")
        log(f"wrote {out / 'bench.json'}, {out / 'bench.md'}" + (f", {out / 'bench_scaling.png'}" if sweeps else ""))
    return result


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
