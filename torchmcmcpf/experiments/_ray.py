"""The shards of a study on Ray (``--workers N``): imported only then, so a study run in this
process never imports Ray. See :mod:`torchmcmcpf.experiments._shards`.
"""

from __future__ import annotations

import logging
import os
from collections.abc import Callable
from pathlib import Path
from typing import Any

from ._options import RunOptions
from ._shards import ShardedStudy, ShardError, compute_shard, shard_failed

__all__ = ["run_on_ray"]


def _package_root() -> str:
    return str(Path(__file__).resolve().parents[2])


def run_on_ray(todo: list, study: ShardedStudy, settings: Any, options: RunOptions, threads: int,
               on_done: Callable[[int, range, str, dict], None]) -> None:
    """Run the shards ``todo`` [(index, runs, key)] of ``study`` as Ray tasks, at most
    ``options.workers`` in flight; ``on_done(index, runs, key, result)`` as each finishes.
    A local cluster of ``options.workers`` CPUs is started for the call (and shut down after)
    unless Ray is initialised already or ``options.ray_address`` names one. The first failure
    cancels the rest and raises :class:`~torchmcmcpf.experiments._shards.ShardError` naming
    the shard.
    """
    try:
        import ray
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
