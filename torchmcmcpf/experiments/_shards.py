"""A study's Monte Carlo runs in fixed-size shards, here or on Ray.

A study whose runs are independent defines ``run_shard(settings, runs, *, generator,
device, progress) -> (per_run, seconds)`` (see :class:`~torchmcmcpf.experiments._study.Study`):
the runs ``runs`` (a ``range`` of run indices) with its settings, returning ``per_run``, a
flat dict ``str -> Tensor`` whose tensors all have the run dim first (``(len(runs), ...)``),
and ``seconds``, a dict ``str -> float`` of compute times. :func:`run_shards` splits
``range(settings.runs)`` into shards of ``shard_size`` runs (a fixed size: never derived
from ``--workers``), gives shard ``i`` the generator :func:`shard_generator` ``(seed, i)``,
stores each finished shard in ``out/shards/shard-<i>.pt`` (an interrupted study resumes from
them), then concatenates ``per_run`` along the run dim and sums ``seconds``.

The stream of every run therefore depends only on ``(seed, shard size, run index)``:
without ``--workers`` (in this process, Ray never imported) and with ``--workers N`` (a local
Ray cluster of N CPUs started for the command, or ``--ray-address`` to join one,
:func:`run_on_ray`) the same numbers come out, so ``metrics.json`` is
identical but for its timings and ``provenance``. A worker receives the study object itself
(pickled by reference to its class) and its frozen settings, nothing looked up by name.
"""

from __future__ import annotations

import contextlib
import dataclasses
import json
import logging
import os
import platform
import time
import zlib
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any, NamedTuple, Protocol

import numpy as np
import torch

from .. import runtime
from ._options import RunOptions, positive_int
from ._provenance import to_jsonable

__all__ = ["ShardError", "Shards", "ShardedStudy", "shard_generator", "shard_layout", "run_shards", "run_on_ray"]


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


class ShardedStudy(Protocol):
    """What :func:`run_shards` needs of a study: its ``name`` and ``run_shard``."""

    @property
    def name(self) -> str: ...

    def run_shard(self, settings: Any, runs: range, *, generator: torch.Generator, device: torch.device,
                  progress: bool = False) -> tuple[dict, dict]: ...


def shard_generator(device: str | torch.device, seed: int, index: int) -> torch.Generator:
    """The generator of shard ``index``: seeded from ``(seed, index)`` through numpy's
    ``SeedSequence`` (independent streams for distinct pairs, none shared with
    :func:`~torchmcmcpf.experiments._study.generator`).
    """
    state = np.random.SeedSequence([int(seed) & (2**63 - 1), int(index), 0x5EED]).generate_state(1, np.uint64)[0]
    return torch.Generator(device=torch.device(device)).manual_seed(int(state) >> 1)


def streams(generator: torch.Generator, names: tuple[str, ...]) -> dict[str, torch.Generator]:
    """One generator per name, on ``generator``'s device: one draw from ``generator``, then
    each name's stream seeded from ``(that draw, the name)`` through numpy's ``SeedSequence``.
    A name's stream does not depend on which other names are asked for, and what one consumer
    (a filter, the frames of a scene) draws does not move what another sees, so a study's
    figures for one filter do not depend on which filters ran before it.
    """
    base = int(torch.randint(2**62, (1,), generator=generator, device=generator.device))
    out = {}
    for name in names:
        state = np.random.SeedSequence([base, zlib.crc32(name.encode())]).generate_state(1, np.uint64)[0]
        out[name] = torch.Generator(device=generator.device).manual_seed(int(state) >> 1)
    return out


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


def compute_shard(study: ShardedStudy, settings: Any, seed: int, index: int, start: int, stop: int, device: str,
                  threads: int | None, progress: bool = False, memory_budget: int | None = None) -> dict:
    """Run one shard (in this process or in a Ray worker); CPU tensors out. ``progress``:
    the filters' own bars (only for a lone shard in this process; else one bar over shards).
    """
    dev = torch.device(device)
    with _num_threads(threads, memory_budget):
        t0 = time.perf_counter()
        per_run, seconds = study.run_shard(settings, range(start, stop), generator=shard_generator(dev, seed, index),
                                           device=dev, progress=progress)
        wall = time.perf_counter() - t0
        used = torch.get_num_threads()
    for key, value in per_run.items():
        if not torch.is_tensor(value) or value.dim() == 0 or value.shape[0] != stop - start:
            shape = tuple(value.shape) if torch.is_tensor(value) else type(value).__name__
            raise ValueError(f"{study.name}: run_shard returned per_run[{key!r}] of shape {shape}, "
                             f"expected ({stop - start}, ...) (run dim first)")
    return {"per_run": {k: v.detach().cpu() for k, v in per_run.items()},
            "seconds": {k: float(v) for k, v in seconds.items()},
            "wall_seconds": wall, "threads": used, "host": platform.node()}


def _settings_dict(settings: Any) -> dict:
    if dataclasses.is_dataclass(settings) and not isinstance(settings, type):
        return dataclasses.asdict(settings)
    return dict(settings)


def _shard_key(name: str, settings: Any, seed: int, shard_size: int, index: int, runs: range,
               device: str | torch.device) -> str:
    """What a stored shard must match to be reused (settings, seed, layout, device type)."""
    return json.dumps(to_jsonable({"study": name, "cfg": _settings_dict(settings), "seed": seed,
                                   "shard_size": shard_size, "index": index, "runs": [runs.start, runs.stop],
                                   "device": torch.device(device).type}), sort_keys=True)


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


def shard_failed(name: str, index: int, runs: range, err: BaseException) -> ShardError:
    """The :class:`ShardError` of shard ``index`` failing with ``err``."""
    cause = getattr(err, "cause", None) or err  # Ray wraps the worker's exception
    return ShardError(f"{name}: shard {index} (runs {runs.start}..{runs.stop - 1}) failed: "
                      f"{type(cause).__name__}: {cause}")


def run_shards(study: ShardedStudy, settings: Any, options: RunOptions) -> Shards:
    """Run ``study.run_shard`` over every shard of ``range(settings.runs)`` (module
    docstring). Shards already in ``options.out/shards`` with the same settings are reused.

    ``settings`` is the study's frozen settings (a dataclass with ``runs`` and
    ``shard_size``; a mapping with those keys also works); ``options.shard_size``, when given,
    replaces ``settings.shard_size``, and each shard receives the settings with the size
    that ran. The returned ``layout`` goes into the provenance of ``metrics.json``.
    """
    from tqdm.auto import tqdm

    name = study.name
    is_record = dataclasses.is_dataclass(settings)
    get = (lambda key: getattr(settings, key)) if is_record else settings.__getitem__
    size = options.shard_size or get("shard_size")
    settings = dataclasses.replace(settings, shard_size=size) if is_record else {**settings, "shard_size": size}
    layout = shard_layout(get("runs"), size)
    seed, device, out = options.seed, options.device, options.out
    results: dict[int, dict] = {}
    todo = []
    for index, runs in enumerate(layout):
        key = _shard_key(name, settings, seed, size, index, runs, device)
        stored = _load_shard(_shard_path(out, index), key)
        if stored is not None:
            results[index] = {**stored, "resumed": True}
        else:
            todo.append((index, runs, key))
    bar = tqdm(total=len(layout), initial=len(results), desc=f"{name} shards", unit="shard",
               disable=not options.progress or len(layout) == 1)

    def on_done(index: int, runs: range, key: str, result: dict) -> None:
        _save_shard(_shard_path(out, index), key, result)
        results[index] = {**result, "resumed": False}
        bar.update(1)

    threads = options.threads or torch.get_num_threads()
    lone = options.progress and len(layout) == 1  # then the filters show progress
    try:
        if options.workers:
            run_on_ray(todo, study, settings, options, threads, on_done)
        else:
            for index, runs, key in todo:
                try:
                    result = compute_shard(study, settings, seed, index, runs.start, runs.stop, str(device), threads,
                                           progress=lone, memory_budget=options.memory_budget)
                except Exception as err:
                    raise shard_failed(name, index, runs, err) from err
                on_done(index, runs, key, result)
    finally:
        bar.close()
    ordered = [results[i] for i in range(len(layout))]
    per_run = {k: torch.cat([r["per_run"][k] for r in ordered]) for k in ordered[0]["per_run"]}
    seconds = {k: sum(r["seconds"][k] for r in ordered) for k in ordered[0]["seconds"]}
    report = {
        "shard_size": size, "num_shards": len(layout), "workers": options.workers,
        "ray_address": options.ray_address if options.workers else None,
        "resumed": sum(r["resumed"] for r in ordered),
        "shards": [{"index": i, "runs": [layout[i].start, layout[i].stop - 1], "threads": r["threads"],
                    "host": r["host"], "wall_seconds": r["wall_seconds"], "resumed": r["resumed"]}
                   for i, r in enumerate(ordered)],
    }
    return Shards(per_run, seconds, report)


def _package_root() -> str:
    return str(Path(__file__).resolve().parents[2])


def run_on_ray(todo: list, study: ShardedStudy, settings: Any, options: RunOptions, threads: int,
               on_done: Callable[[int, range, str, dict], None]) -> None:
    """Run the shards ``todo`` [(index, runs, key)] of ``study`` as Ray tasks, at most
    ``options.workers`` in flight; ``on_done(index, runs, key, result)`` as each finishes.
    A local cluster of ``options.workers`` CPUs is started for the call (and shut down after)
    unless Ray is initialised already or ``options.ray_address`` names one. The first failure
    cancels the rest and raises :class:`ShardError` naming the shard.
    """
    try:
        import ray  # optional (the cluster extra), imported only here: a study without --workers never imports it
    except ImportError as err:
        raise ImportError("--workers needs Ray: pip install 'torchmcmcpf[cluster]'") from err
    name, device = study.name, options.device
    started = False
    if not ray.is_initialized():
        env = {"env_vars": {"PYTHONPATH": os.pathsep.join(filter(None, [_package_root(),
                                                                        os.environ.get("PYTHONPATH")]))}}
        if options.ray_address:
            ray.init(address=options.ray_address, logging_level=logging.ERROR, log_to_driver=False)
        else:
            ray.init(num_cpus=options.workers, include_dashboard=False, logging_level=logging.ERROR,
                     log_to_driver=False, runtime_env=env)
        started = True
    try:
        gpus = float(options.gpus_per_shard) if device.type == "cuda" else 0
        have = ray.cluster_resources()
        if have.get("CPU", 0) < 1 or have.get("GPU", 0) < gpus:  # a task that can never be placed waits forever
            raise ShardError(f"{name}: the Ray cluster has {have.get('CPU', 0):g} CPUs and {have.get('GPU', 0):g} "
                             f"GPUs; each shard needs 1 CPU and {gpus:g} GPUs (--gpus-per-shard)")
        task = ray.remote(compute_shard).options(num_cpus=1, num_gpus=gpus, max_retries=0)
        queue = list(todo)
        running: dict[Any, tuple[int, range, str]] = {}  # Ray ObjectRef -> shard
        while queue or running:
            while queue and len(running) < (options.workers or 1):
                index, runs, key = queue.pop(0)
                ref = task.remote(study, settings, options.seed, index, runs.start, runs.stop, str(device), threads,
                                  False, options.memory_budget)
                running[ref] = (index, runs, key)
            done, _ = ray.wait(list(running), num_returns=1)
            index, runs, key = running.pop(done[0])
            try:
                result = ray.get(done[0])
            except Exception as err:
                for ref in running:
                    ray.cancel(ref, force=True)
                raise shard_failed(name, index, runs, err) from None
            on_done(index, runs, key, result)
    finally:
        if started:
            ray.shutdown()
