"""What traces a study's ``metrics.json`` to the run that made it, and the file itself.

``write_metrics(out, metrics, *, settings, options, shards)`` writes ``out/metrics.json``:
``{"settings": ..., "device": device_name, "torch": version, "provenance": ..., **metrics}``
with tensors, numpy values, paths and devices made JSON (:func:`to_jsonable`).
``"provenance"`` (command line, seed, shard layout, device, threads, versions, host, time)
and every key holding ``seconds`` are the only parts that change between two runs of the
same command.
"""

from __future__ import annotations

import dataclasses
import json
import math
import os
import platform
import shlex
import subprocess
import sys
import time
from collections.abc import Mapping
from pathlib import Path
from typing import Any

import numpy as np
import torch

from .._version import __version__
from ._options import RunOptions

__all__ = ["device_name", "to_jsonable", "provenance", "write_metrics"]


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
    """Convert tensors (to numbers or nested lists), numpy values, paths, devices, dataclasses
    and containers to JSON types; NaN and infinities become ``None``.
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
    if dataclasses.is_dataclass(obj) and not isinstance(obj, type):
        return to_jsonable(dataclasses.asdict(obj))
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



def provenance(options: RunOptions | None = None, device: str | torch.device | None = None,
               shards: Mapping[str, Any] | None = None) -> dict:
    """What traces a ``metrics.json`` to the run that made it: command line, seed, shard
    layout (``shards``, the layout :func:`~torchmcmcpf.experiments._shards.run_shards`
    returns), device, threads, versions, wall time (since ``options.started``).
    """
    versions = {"torchmcmcpf": __version__, "git_commit": _git_commit(), "torch": torch.__version__,
                "numpy": np.__version__, "python": platform.python_version()}
    if "ray" in sys.modules:
        versions["ray"] = sys.modules["ray"].__version__
    return {
        "command": (options.command_line if options is not None else None)
        or shlex.join([Path(sys.argv[0]).name, *sys.argv[1:]]),
        "seed": None if options is None else options.seed,
        "shards": None if shards is None else dict(shards),
        "device": device_name(device),
        "threads": (options.threads if options is not None else None) or torch.get_num_threads(),
        "versions": versions,
        "host": platform.node(),
        "finished_utc": time.strftime("%Y-%m-%dT%H:%M:%SZ", time.gmtime()),
        "wall_seconds": None if options is None else time.perf_counter() - options.started,
    }


def write_metrics(out: str | Path, metrics: Mapping[str, Any], *, settings: Mapping[str, Any] | None = None,
                  options: RunOptions | None = None, shards: Mapping[str, Any] | None = None,
                  device: str | torch.device | None = None) -> Path:
    """Write ``out/metrics.json`` with the settings, the device, the provenance and ``metrics``.

    Parameters
    ----------
    out : output directory (created if needed).
    metrics : the study's results (tensors allowed).
    settings : what ran, stored under ``"settings"`` (callables dropped); by default the
        recorded ``options``.
    options : how it ran (:class:`~torchmcmcpf.experiments._options.RunOptions`): seed,
        threads, command line and start time for the provenance.
    shards : the shard layout, when the study ran in shards.
    device : where it ran; defaults to ``options.device``.

    Returns
    -------
    the path of the file.
    """
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    if settings is None:
        settings = options.recorded() if options is not None else {}
    settings = {k: v for k, v in settings.items() if not callable(v)}
    if device is None and options is not None:
        device = options.device
    payload = {"settings": settings, "device": device_name(device), "torch": torch.__version__,
               "provenance": provenance(options, device, shards), **metrics}
    path = out / "metrics.json"
    path.write_text(json.dumps(to_jsonable(payload), indent=2) + "\n")
    return path
