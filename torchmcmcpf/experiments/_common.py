"""Shared plumbing of the experiments (and of ``python -m torchmcmcpf demo``).

An experiment is a module ``torchmcmcpf/experiments/<module>.py`` defining

- ``NAME``: the command-line name, e.g. ``"ling-rmse-vs-snr"``;
- ``DESCRIPTION``: one line shown by ``python -m torchmcmcpf reproduce --list``;
- ``run(args) -> dict``: runs the study, writes ``metrics.json`` and its PNGs into
  ``args.out`` and returns the metrics it wrote;
- optionally ``add_arguments(parser)``: extra command-line options of its own.

``args`` is an ``argparse.Namespace`` with at least (see :func:`add_common_arguments`):
``name`` (str), ``quick`` (bool: a small version for tests, seconds on a CPU), ``out``
(``pathlib.Path``, created before ``run``), ``device`` (``torch.device``), ``seed`` (int)
and ``progress`` (bool: show tqdm bars).

API
---
``add_common_arguments(parser, *, name, quick=True, shards=True)``
    Adds ``--quick`` (unless ``quick=False``), ``--out`` (default ``results/<name>``), ``--device``, ``--seed``,
    ``--threads``, ``--memory-budget``, ``--no-progress`` and, with ``shards=True``, :func:`add_shard_arguments`.
``add_shard_arguments(parser)``
    Adds :data:`SHARD_OPTIONS` (``--shard-size``, ``--workers``, ``--ray-address``,
    ``--gpus-per-shard``): only studies that define ``run_shard`` accept them.
``positive_int(text)``, ``device_arg(text)``
    argparse ``type=`` converters: an integer >= 1; ``"cpu"``, ``"cuda"``, ``"cuda:1"`` or
    ``"auto"`` -> ``torch.device`` (an error naming the option when CUDA is unavailable).
``prepare_out(path) -> Path``
    Creates the output directory.
``generator(device, seed) -> torch.Generator``
    A generator on ``device`` seeded with ``seed``: the one source of randomness.
``StepTimer(device, steps)``
    Context manager timing a block (synchronising CUDA on entry and exit); then
    ``.seconds`` and ``.seconds_per_step``.
``device_name(device) -> str``
    Human-readable processor or GPU name, recorded in every ``metrics.json``.
``to_jsonable(obj)``
    Tensors, numpy values, paths and devices to JSON types (non-finite floats -> ``None``).
``write_metrics(out, metrics, *, args=None, device=None) -> Path``
    Writes ``out/metrics.json``: ``{"settings": vars(args), "device": device_name,
    "torch": version, **metrics}``.
``save_figure(fig, out, filename, *, quick=False) -> Path``
    Saves and closes a matplotlib figure (marked "quick" in quick mode).
``run_shards(module, cfg, args) -> Shards``
    Runs a study's Monte Carlo runs as shards (see below), in this process or on Ray.

Shards
------
A study whose runs are independent also defines

- ``run_shard(cfg, runs, *, generator, device, progress) -> (per_run, seconds)``: run the
  runs ``runs`` (a ``range`` of run indices) with the study settings ``cfg`` and return
  ``per_run``, a flat dict ``str -> Tensor`` whose tensors all have the run dim first
  (``(len(runs), ...)``), and ``seconds``, a dict ``str -> float`` of compute times;
- its ``run(args)`` calls :func:`run_shards`, which splits ``range(cfg["runs"])`` into
  shards of ``--shard-size`` runs (a fixed size: never derived from ``--workers``), gives
  shard ``i`` the generator :func:`shard_generator` ``(seed, i)``, stores each finished
  shard in ``out/shards/shard-<i>.pt`` (an interrupted study resumes from them), then
  concatenates ``per_run`` along the run dim and sums ``seconds``.

The stream of every run therefore depends only on ``(seed, shard size, run index)``:
``--workers 1`` (in this process, Ray never imported) and ``--workers N`` (a local Ray
cluster of N CPUs started for the command, or ``--ray-address`` to join one) compute the
same numbers, so ``metrics.json`` is identical but for its timings and ``provenance``.
"""

from __future__ import annotations

import argparse
import contextlib
import importlib
import json
import logging
import math
import os
import platform
import shlex
import subprocess
import sys
import time
from collections.abc import Callable, Iterator, Mapping, Sequence
from pathlib import Path
from types import ModuleType
from typing import TYPE_CHECKING, Any, NamedTuple

import numpy as np
import torch

from .. import runtime

if TYPE_CHECKING:
    from matplotlib.figure import Figure

__all__ = [
    "add_common_arguments",
    "add_shard_arguments",
    "SHARD_OPTIONS",
    "positive_int",
    "nonnegative_int",
    "device_arg",
    "prepare_out",
    "generator",
    "StepTimer",
    "device_name",
    "to_jsonable",
    "write_metrics",
    "save_figure",
    "out_dir",
    "shard_generator",
    "shard_layout",
    "run_shards",
    "Shards",
    "ShardError",
    "defaults_help",
    "np_label",
]


def positive_int(text: str) -> int:
    """An argparse type: an integer >= 1."""
    try:
        value = int(text)
    except ValueError:
        value = None
    if value is None or value < 1:
        raise argparse.ArgumentTypeError(f"must be an integer >= 1, got {text!r}")
    return value


def nonnegative_int(text: str) -> int:
    """An argparse type: an integer >= 0."""
    try:
        value = int(text)
    except ValueError:
        value = None
    if value is None or value < 0:
        raise argparse.ArgumentTypeError(f"must be an integer >= 0, got {text!r}")
    return value


def device_arg(text: str) -> torch.device:
    """An argparse type: ``"cpu"``, ``"cuda"``, ``"cuda:N"``, or ``"auto"`` (CUDA when present)."""
    if text == "auto":
        return torch.device("cuda" if torch.cuda.is_available() else "cpu")
    try:
        device = torch.device(text)
    except RuntimeError as err:
        raise argparse.ArgumentTypeError(f"expected cpu, cuda, cuda:N or auto, got {text!r}") from err
    if device.type == "cuda" and not torch.cuda.is_available():
        raise argparse.ArgumentTypeError(f"{text!r} requested but CUDA is not available")
    if device.type not in ("cpu", "cuda"):
        raise argparse.ArgumentTypeError(f"expected cpu, cuda, cuda:N or auto, got {text!r}")
    return device


def out_dir(text: str) -> Path:
    """An argparse type: an output directory; an existing file, or a path under a file, is an
    error (a one-line message naming ``--out``).
    """
    path = Path(text)
    if path.exists() and not path.is_dir():
        raise argparse.ArgumentTypeError(f"{text!r} is an existing file, expected a directory")
    for parent in path.parents:
        if parent.exists():
            if not parent.is_dir():
                raise argparse.ArgumentTypeError(f"{text!r} lies under {str(parent)!r}, which is a file")
            break
    return path


def defaults_help(full: Mapping[str, Any], quick: Mapping[str, Any] | None, key: str, what: str) -> str:
    """Help text ``"<what> (default <full>, quick <quick>)"`` read from the study's own
    settings, so the help cannot drift from what runs.
    """

    def fmt(v):
        return " ".join(f"{x:g}" if isinstance(x, float) else str(x) for x in v) if isinstance(v, (tuple, list)) \
            else str(v)

    text = f"{what} (default {fmt(full[key])}"
    return text + (f", quick {fmt(quick[key])})" if quick is not None else ")")


def np_label(name: str, num_particles: int) -> str:
    """Legend label of a filter: ``"<name>, Np = <N>"``."""
    return f"{name}, Np = {num_particles}"


def add_common_arguments(parser: argparse.ArgumentParser, *, name: str, quick: bool = True,
                         shards: bool = True, study: ModuleType | None = None) -> argparse.ArgumentParser:
    """Add the options every experiment shares (see the module docstring); ``quick=False``
    leaves out ``--quick`` (for commands without a small version, like ``demo``),
    ``shards=False`` the shard and Ray options; ``study`` (a module with ``FULL`` and
    ``QUICK`` settings) puts its default shard size in the help.
    """
    group = parser.add_argument_group("options common to all studies")
    if quick:
        group.add_argument("--quick", action="store_true", help="small version (seconds on a CPU)")
    group.add_argument("--out", type=out_dir, default=Path("results") / name,
                       help=f"output directory (default: results/{name}); files of the same name are replaced")
    group.add_argument("--device", type=device_arg, default=torch.device("cpu"),
                       help="cpu (default), cuda, cuda:N or auto")
    group.add_argument("--seed", type=int, default=0, help="random seed (default: 0)")
    group.add_argument("--threads", type=positive_int, default=None,
                       help="torch intra-op threads (default: this process's torch threads)" if not shards else
                            "torch intra-op threads of every shard, here or in a Ray worker (default: this "
                            "process's torch threads, so both compute alike; with --workers on one machine "
                            "use cores / workers)")
    group.add_argument("--memory-budget", type=positive_int, default=None, metavar="BYTES",
                       help="bytes of temporaries a grid sensor's likelihood may hold at once (its memory_budget, "
                            "runtime.memory_budget; default: 1 GiB); smaller blocks of samples, same results")
    group.add_argument("--no-progress", dest="progress", action="store_false",
                       help="hide the progress bars")
    if shards:
        add_shard_arguments(parser, study=study)
    return parser


#: the options that only studies with ``run_shard`` accept
SHARD_OPTIONS = ("--shard-size", "--workers", "--ray-address", "--gpus-per-shard")


def add_shard_arguments(parser: argparse.ArgumentParser, *, study: ModuleType | None = None,
                        studies: Sequence[str] = ()) -> argparse.ArgumentParser:
    """Add :data:`SHARD_OPTIONS` (shards of runs, Ray) in their own group. ``study`` puts its
    default shard size in the help; ``studies`` (the names of the sharded studies) goes in
    the group title, for the help of ``reproduce`` itself.
    """
    title = "shards and Ray" + (f" (only {', '.join(studies)})" if studies else "")
    group = parser.add_argument_group(title)
    group.add_argument("--shard-size", type=positive_int, default=None,
                       help="Monte Carlo runs per shard; each shard has its own random stream "
                            "from (seed, shard index), so results depend on it, never on --workers "
                            + ("(default: the study's, see metrics.json)"
                               if study is None or "shard_size" not in getattr(study, "FULL", {}) else
                               defaults_help(study.FULL, study.QUICK, "shard_size", "")[1:]))
    group.add_argument("--workers", type=positive_int, default=None,
                       help="run the shards on Ray with this many in flight (a local cluster "
                            "started for the command unless --ray-address); without it Ray is "
                            "not imported and the shards run here, one after the other")
    group.add_argument("--ray-address", default=None,
                       help="join this Ray cluster (e.g. ray://host:10001 or auto) instead of "
                            "starting a local one; torchmcmcpf must be importable on its nodes")
    group.add_argument("--gpus-per-shard", type=float, default=1.0,
                       help="GPUs Ray reserves per shard with --device cuda (default: 1)")
    return parser


def prepare_out(path: str | Path, outputs: Sequence[str] = ()) -> Path:
    """Create the output directory (and parents); return it as a Path.

    Raises ``ValueError`` when ``path`` is a file or lies under one. When the directory
    already holds some of ``outputs`` (the file names the command writes), says on stdout
    which ones it replaces.
    """
    try:
        path = out_dir(str(path))
    except argparse.ArgumentTypeError as err:
        raise ValueError(f"out: {err}") from None
    path.mkdir(parents=True, exist_ok=True)
    existing = [n for n in outputs if (path / n).exists()]
    if existing:
        print(f"note: {path} is not empty; replacing {', '.join(existing)}")
    return path


def generator(device: str | torch.device, seed: int) -> torch.Generator:
    """A ``torch.Generator`` on ``device`` seeded with ``seed``."""
    return torch.Generator(device=torch.device(device)).manual_seed(int(seed))


def _sync(device: torch.device | None) -> None:
    if device is not None and torch.device(device).type == "cuda":
        torch.cuda.synchronize(device)


class StepTimer:
    """Wall-clock time of a block, per step; synchronises CUDA before and after.

    >>> with StepTimer(device, steps=T) as timer:       # doctest: +SKIP
    ...     result = filt(z, init=x0, generator=g)
    >>> timer.seconds_per_step                          # doctest: +SKIP
    """

    def __init__(self, device: str | torch.device | None = None, steps: int = 1):
        self.device = None if device is None else torch.device(device)
        self.steps = positive_int(str(steps))
        self.seconds = float("nan")

    def __enter__(self) -> StepTimer:
        _sync(self.device)
        self._start = time.perf_counter()
        return self

    def __exit__(self, *exc: object) -> None:
        _sync(self.device)
        self.seconds = time.perf_counter() - self._start

    @property
    def seconds_per_step(self) -> float:
        return self.seconds / self.steps


def device_name(device: str | torch.device | None = None) -> str:
    """``"cuda: <GPU name>"`` or ``"cpu: <processor>, <n> cores, <m> torch threads"``."""
    device = torch.device("cpu" if device is None else device)
    if device.type == "cuda":
        return f"cuda: {torch.cuda.get_device_name(device)}"
    proc = platform.processor() or platform.machine()
    try:  # the model name is more telling than the architecture on Linux
        with open("/proc/cpuinfo") as f:
            proc = next(line.split(":", 1)[1].strip() for line in f if line.startswith("model name"))
    except (OSError, StopIteration):
        pass
    return f"cpu: {proc}, {os.cpu_count()} cores, {torch.get_num_threads()} torch threads"


def to_jsonable(obj: Any) -> Any:
    """Convert tensors (to numbers or nested lists), numpy values, paths, devices and
    containers to JSON types; NaN and infinities become ``None``.
    """
    if torch.is_tensor(obj):
        obj = obj.detach().cpu()
        return to_jsonable(obj.item() if obj.dim() == 0 else obj.tolist())
    if isinstance(obj, np.ndarray):
        return to_jsonable(obj.tolist())
    if isinstance(obj, np.generic):
        return to_jsonable(obj.item())
    if isinstance(obj, float):
        return obj if math.isfinite(obj) else None
    if isinstance(obj, (bool, int, str)) or obj is None:
        return obj
    if isinstance(obj, (Path, torch.device, torch.dtype)):
        return str(obj)
    if isinstance(obj, Mapping):
        return {str(k): to_jsonable(v) for k, v in obj.items()}
    if isinstance(obj, (list, tuple)):
        return [to_jsonable(v) for v in obj]
    raise TypeError(f"cannot write {type(obj).__name__} to metrics.json")


def _git_commit() -> str | None:
    """The commit of the source tree the package was imported from, or None."""
    root = Path(__file__).resolve().parents[2]
    if not (root / ".git").exists():
        return None
    try:
        out = subprocess.run(["git", "-C", str(root), "rev-parse", "HEAD"], capture_output=True, text=True,
                             timeout=5)
        dirty = subprocess.run(["git", "-C", str(root), "status", "--porcelain", "--untracked-files=no"],
                               capture_output=True, text=True, timeout=5)
    except (OSError, subprocess.SubprocessError):
        return None
    if out.returncode != 0:
        return None
    return out.stdout.strip() + ("+dirty" if dirty.stdout.strip() else "")


def provenance(args: argparse.Namespace | None = None, device: str | torch.device | None = None) -> dict:
    """What traces a ``metrics.json`` to the run that made it: command line, seed, shard
    layout, device, threads, versions, wall time (seconds since ``args.started``).
    """
    from .. import __version__

    settings = vars(args) if args is not None else {}
    versions = {"torchmcmcpf": __version__, "git_commit": _git_commit(), "torch": torch.__version__,
                "numpy": np.__version__, "python": platform.python_version()}
    if "ray" in sys.modules:
        versions["ray"] = sys.modules["ray"].__version__
    started = settings.get("started")
    return {
        "command": settings.get("command_line") or shlex.join([Path(sys.argv[0]).name, *sys.argv[1:]]),
        "seed": settings.get("seed"),
        "shards": settings.get("shard_report"),
        "device": device_name(device),
        "threads": settings.get("threads") or torch.get_num_threads(),
        "versions": versions,
        "host": platform.node(),
        "finished_utc": time.strftime("%Y-%m-%dT%H:%M:%SZ", time.gmtime()),
        "wall_seconds": None if started is None else time.perf_counter() - started,
    }


def write_metrics(out: str | Path, metrics: Mapping[str, Any], *,
                  args: argparse.Namespace | None = None,
                  device: str | torch.device | None = None) -> Path:
    """Write ``out/metrics.json`` with the settings, the device, the provenance and ``metrics``.

    Parameters
    ----------
    out : output directory (created if needed).
    metrics : the experiment's results (tensors allowed).
    args : the parsed command line, stored under ``"settings"`` (callables and the
        bookkeeping keys ``started``, ``command_line``, ``shard_report`` dropped).
    device : where it ran; defaults to ``args.device`` when present.

    Returns
    -------
    the path of the file. ``"provenance"`` (see :func:`provenance`) and every key holding
    ``seconds`` are the only parts that change between two runs of the same command.
    """
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    hidden = ("started", "command_line", "shard_report")
    settings = {k: v for k, v in vars(args).items() if not callable(v) and k not in hidden} if args is not None else {}
    if device is None:
        device = settings.get("device")
    payload = {"settings": settings, "device": device_name(device), "torch": torch.__version__,
               "provenance": provenance(args, device), **metrics}
    path = out / "metrics.json"
    path.write_text(json.dumps(to_jsonable(payload), indent=2) + "\n")
    return path


def save_figure(fig: Figure, out: str | Path, filename: str, *, quick: bool = False) -> Path:
    """Save ``fig`` as ``out/filename`` (150 dpi) and close it; return the path. ``quick``
    stamps "quick mode" on the figure (small settings, not the paper's).
    """
    import matplotlib.pyplot as plt

    if quick:
        fig.text(0.99, 0.005, "quick mode: small settings", ha="right", va="bottom", fontsize="x-small",
                 color="C3")
    path = Path(out) / filename
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=150, bbox_inches="tight")
    plt.close(fig)
    return path


# ---------------------------------------------------------------------------------------
# Shards: a study's Monte Carlo runs in fixed-size groups, here or on Ray
# ---------------------------------------------------------------------------------------


class ShardError(RuntimeError):
    """A shard of a study failed; the message names the shard and its runs."""


class Shards(NamedTuple):
    """The concatenated output of every shard: ``per_run`` (str -> ``(B, ...)`` tensor, run
    dim first, in run order), ``seconds`` (str -> total compute seconds over the shards) and
    ``layout`` (shard size, count, and per shard its runs, threads, seconds, where it ran).
    """

    per_run: dict
    seconds: dict
    layout: dict


def shard_generator(device: str | torch.device, seed: int, index: int) -> torch.Generator:
    """The generator of shard ``index``: seeded from ``(seed, index)`` through numpy's
    ``SeedSequence`` (independent streams for distinct pairs, none shared with
    :func:`generator`).
    """
    state = np.random.SeedSequence([int(seed) & (2**63 - 1), int(index), 0x5EED]).generate_state(1, np.uint64)[0]
    return torch.Generator(device=torch.device(device)).manual_seed(int(state) >> 1)


def shard_layout(num_runs: int, shard_size: int) -> list[range]:
    """``range(num_runs)`` cut into consecutive ranges of ``shard_size`` runs (the last may
    be shorter).
    """
    num_runs, shard_size = positive_int(str(num_runs)), positive_int(str(shard_size))
    return [range(a, min(a + shard_size, num_runs)) for a in range(0, num_runs, shard_size)]


@contextlib.contextmanager
def _num_threads(threads: int | None, memory_budget: int | None = None) -> Iterator[None]:
    """Torch's intra-op threads and the grid sensors' memory budget for the block (then restored)."""
    old, old_budget = torch.get_num_threads(), runtime.memory_budget()
    if threads:
        torch.set_num_threads(int(threads))
    if memory_budget:
        runtime.set_memory_budget(memory_budget)
    try:
        yield
    finally:
        torch.set_num_threads(old)
        runtime.set_memory_budget(old_budget)


def _compute_shard(module_name: str, cfg: dict, seed: int, index: int, start: int, stop: int, device: str,
                   threads: int | None, progress: bool = False, memory_budget: int | None = None) -> dict:
    """Run one shard (in this process or in a Ray worker); CPU tensors out. ``progress``:
    the filters' own bars (only for a lone shard in this process; else one bar over shards).
    """
    module = importlib.import_module(module_name)
    dev = torch.device(device)
    with _num_threads(threads, memory_budget):
        t0 = time.perf_counter()
        per_run, seconds = module.run_shard(cfg, range(start, stop), generator=shard_generator(dev, seed, index),
                                            device=dev, progress=progress)
        wall = time.perf_counter() - t0
        used = torch.get_num_threads()
    for key, value in per_run.items():
        if not torch.is_tensor(value) or value.dim() == 0 or value.shape[0] != stop - start:
            shape = tuple(value.shape) if torch.is_tensor(value) else type(value).__name__
            raise ValueError(f"{module_name}.run_shard returned per_run[{key!r}] of shape {shape}, "
                             f"expected ({stop - start}, ...) (run dim first)")
    return {"per_run": {k: v.detach().cpu() for k, v in per_run.items()},
            "seconds": {k: float(v) for k, v in seconds.items()},
            "wall_seconds": wall, "threads": used, "host": platform.node()}


def _shard_key(name: str, cfg: dict, seed: int, shard_size: int, index: int, runs: range,
               device: str | torch.device) -> str:
    """What a stored shard must match to be reused (settings, seed, layout, device type)."""
    return json.dumps(to_jsonable({"study": name, "cfg": cfg, "seed": seed, "shard_size": shard_size, "index": index,
                                   "runs": [runs.start, runs.stop], "device": torch.device(device).type}),
                      sort_keys=True)


def _shard_path(out: Path, index: int) -> Path:
    return out / "shards" / f"shard-{index:05d}.pt"


def _load_shard(path: Path, key: str) -> dict | None:
    if not path.exists():
        return None
    try:
        stored = torch.load(path, weights_only=True)
    except Exception:  # a shard cut off by an interruption: run it again
        return None
    return stored["result"] if stored.get("key") == key else None


def _save_shard(path: Path, key: str, result: dict) -> None:
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_suffix(".tmp")
    torch.save({"key": key, "result": result}, tmp)
    tmp.replace(path)  # atomic: a half-written shard is never read back


def _shard_failed(name: str, index: int, runs: range, err: BaseException) -> ShardError:
    cause = getattr(err, "cause", None) or err  # Ray wraps the worker's exception
    return ShardError(f"{name}: shard {index} (runs {runs.start}..{runs.stop - 1}) failed: "
                      f"{type(cause).__name__}: {cause}")


def _package_root() -> str:
    return str(Path(__file__).resolve().parents[2])


def _run_on_ray(todo: list, module_name: str, name: str, cfg: dict, args: argparse.Namespace, device: torch.device,
                threads: int, on_done: Callable[[int, range, str, dict], None]) -> None:
    """Run the shards ``todo`` [(index, runs, key)] as Ray tasks, at most ``args.workers``
    in flight; ``on_done(index, runs, key, result)`` as each finishes. The first failure
    cancels the rest and raises :class:`ShardError` naming the shard.
    """
    try:
        import ray
    except ImportError as err:
        raise ImportError("--workers needs Ray: pip install 'torchmcmcpf[cluster]'") from err
    started = False
    if not ray.is_initialized():
        env = {"env_vars": {"PYTHONPATH": os.pathsep.join(filter(None, [_package_root(),
                                                                        os.environ.get("PYTHONPATH")]))}}
        if getattr(args, "ray_address", None):
            ray.init(address=args.ray_address, logging_level=logging.ERROR, log_to_driver=False)
        else:
            ray.init(num_cpus=args.workers, include_dashboard=False, logging_level=logging.ERROR, log_to_driver=False,
                     runtime_env=env)
        started = True
    try:
        gpus = float(getattr(args, "gpus_per_shard", 1.0)) if device.type == "cuda" else 0
        have = ray.cluster_resources()
        if have.get("CPU", 0) < 1 or have.get("GPU", 0) < gpus:  # a task that can never be placed waits forever
            raise ShardError(f"{name}: the Ray cluster has {have.get('CPU', 0):g} CPUs and {have.get('GPU', 0):g} "
                             f"GPUs; each shard needs 1 CPU and {gpus:g} GPUs (--gpus-per-shard)")
        task = ray.remote(_compute_shard).options(num_cpus=1, num_gpus=gpus, max_retries=0)
        queue = list(todo)
        running: dict[Any, tuple[int, range, str]] = {}  # Ray ObjectRef -> shard
        while queue or running:
            while queue and len(running) < args.workers:
                index, runs, key = queue.pop(0)
                ref = task.remote(module_name, cfg, args.seed, index, runs.start, runs.stop, str(device), threads,
                                  False, getattr(args, "memory_budget", None))
                running[ref] = (index, runs, key)
            done, _ = ray.wait(list(running), num_returns=1)
            index, runs, key = running.pop(done[0])
            try:
                result = ray.get(done[0])
            except Exception as err:
                for ref in running:
                    ray.cancel(ref, force=True)
                raise _shard_failed(name, index, runs, err) from None
            on_done(index, runs, key, result)
    finally:
        if started:
            ray.shutdown()


def run_shards(module: ModuleType, cfg: dict, args: argparse.Namespace) -> Shards:
    """Run ``module.run_shard`` over every shard of ``range(cfg["runs"])``; see the module
    docstring. Shards already in ``args.out/shards`` with the same settings are reused.

    ``args`` needs ``seed``, ``out``, ``device``; optional ``shard_size`` (default
    ``cfg["shard_size"]``), ``workers``, ``ray_address``, ``gpus_per_shard``, ``threads``,
    ``progress``. Sets ``args.shard_report`` (recorded in ``metrics.json``).
    """
    from tqdm.auto import tqdm

    name = getattr(module, "NAME", module.__name__)
    seed = int(getattr(args, "seed", 0))
    device = torch.device(getattr(args, "device", "cpu"))
    size = getattr(args, "shard_size", None) or cfg["shard_size"]
    cfg = {**cfg, "shard_size": size}
    layout = shard_layout(cfg["runs"], size)
    out = Path(args.out)
    results: dict[int, dict] = {}
    todo = []
    for index, runs in enumerate(layout):
        key = _shard_key(name, cfg, seed, size, index, runs, device)
        stored = _load_shard(_shard_path(out, index), key)
        if stored is not None:
            results[index] = {**stored, "resumed": True}
        else:
            todo.append((index, runs, key))
    bar = tqdm(total=len(layout), initial=len(results), desc=f"{name} shards", unit="shard",
               disable=not getattr(args, "progress", False) or len(layout) == 1)

    def on_done(index, runs, key, result):
        _save_shard(_shard_path(out, index), key, result)
        results[index] = {**result, "resumed": False}
        bar.update(1)

    workers = getattr(args, "workers", None)
    threads = getattr(args, "threads", None) or torch.get_num_threads()
    lone = bool(getattr(args, "progress", False)) and len(layout) == 1  # then the filters show progress
    try:
        if workers:
            _run_on_ray(todo, module.__name__, name, cfg, args, device, threads, on_done)
        else:
            for index, runs, key in todo:
                try:
                    result = _compute_shard(module.__name__, cfg, seed, index, runs.start, runs.stop, str(device),
                                            threads, progress=lone, memory_budget=getattr(args, "memory_budget", None))
                except Exception as err:
                    raise _shard_failed(name, index, runs, err) from err
                on_done(index, runs, key, result)
    finally:
        bar.close()
    ordered = [results[i] for i in range(len(layout))]
    per_run = {k: torch.cat([r["per_run"][k] for r in ordered]) for k in ordered[0]["per_run"]}
    seconds = {k: sum(r["seconds"][k] for r in ordered) for k in ordered[0]["seconds"]}
    report = {
        "shard_size": size, "num_shards": len(layout), "workers": workers,
        "ray_address": getattr(args, "ray_address", None) if workers else None,
        "resumed": sum(r["resumed"] for r in ordered),
        "shards": [{"index": i, "runs": [layout[i].start, layout[i].stop - 1], "threads": r["threads"],
                    "host": r["host"], "wall_seconds": r["wall_seconds"], "resumed": r["resumed"]}
                   for i, r in enumerate(ordered)],
    }
    args.shard_report = report
    return Shards(per_run, seconds, report)
