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
``add_common_arguments(parser, *, name, quick=True)``
    Adds ``--quick`` (unless ``quick=False``), ``--out`` (default ``results/<name>``), ``--device``, ``--seed``,
    ``--no-progress``.
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
``save_figure(fig, out, filename) -> Path``
    Saves and closes a matplotlib figure.
"""

from __future__ import annotations

import argparse
import json
import math
import os
import platform
import time
from pathlib import Path
from typing import Any, Mapping, Optional, Union

import numpy as np
import torch

__all__ = [
    "add_common_arguments",
    "positive_int",
    "device_arg",
    "prepare_out",
    "generator",
    "StepTimer",
    "device_name",
    "to_jsonable",
    "write_metrics",
    "save_figure",
]


def positive_int(text: str) -> int:
    """argparse type: an integer >= 1."""
    try:
        value = int(text)
    except ValueError:
        value = None
    if value is None or value < 1:
        raise argparse.ArgumentTypeError(f"must be an integer >= 1, got {text!r}")
    return value


def device_arg(text: str) -> torch.device:
    """argparse type: ``"cpu"``, ``"cuda"``, ``"cuda:N"``, or ``"auto"`` (CUDA when present)."""
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


def add_common_arguments(parser: argparse.ArgumentParser, *, name: str, quick: bool = True
                         ) -> argparse.ArgumentParser:
    """Add the options every experiment shares (see the module docstring); ``quick=False``
    leaves out ``--quick`` (for commands without a small version, like ``demo``)."""
    if quick:
        parser.add_argument("--quick", action="store_true", help="small version (seconds on a CPU)")
    parser.add_argument("--out", type=Path, default=Path("results") / name,
                        help=f"output directory (default: results/{name})")
    parser.add_argument("--device", type=device_arg, default=torch.device("cpu"),
                        help="cpu (default), cuda, cuda:N or auto")
    parser.add_argument("--seed", type=int, default=0, help="random seed (default: 0)")
    parser.add_argument("--no-progress", dest="progress", action="store_false",
                        help="hide the progress bars")
    return parser


def prepare_out(path: Union[str, Path]) -> Path:
    """Create the output directory (and parents); return it as a Path."""
    path = Path(path)
    path.mkdir(parents=True, exist_ok=True)
    return path


def generator(device: Union[str, torch.device], seed: int) -> torch.Generator:
    """A ``torch.Generator`` on ``device`` seeded with ``seed``."""
    return torch.Generator(device=torch.device(device)).manual_seed(int(seed))


def _sync(device: Optional[torch.device]) -> None:
    if device is not None and torch.device(device).type == "cuda":
        torch.cuda.synchronize(device)


class StepTimer:
    """Wall-clock time of a block, per step; synchronises CUDA before and after.

    >>> with StepTimer(device, steps=T) as timer:       # doctest: +SKIP
    ...     result = filt(z, init=x0, generator=g)
    >>> timer.seconds_per_step                          # doctest: +SKIP
    """

    def __init__(self, device: Optional[Union[str, torch.device]] = None, steps: int = 1):
        self.device = None if device is None else torch.device(device)
        self.steps = positive_int(str(steps))
        self.seconds = float("nan")

    def __enter__(self) -> "StepTimer":
        _sync(self.device)
        self._start = time.perf_counter()
        return self

    def __exit__(self, *exc) -> None:
        _sync(self.device)
        self.seconds = time.perf_counter() - self._start

    @property
    def seconds_per_step(self) -> float:
        return self.seconds / self.steps


def device_name(device: Optional[Union[str, torch.device]] = None) -> str:
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
    containers to JSON types; NaN and infinities become ``None``."""
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


def write_metrics(out: Union[str, Path], metrics: Mapping[str, Any], *,
                  args: Optional[argparse.Namespace] = None,
                  device: Optional[Union[str, torch.device]] = None) -> Path:
    """Write ``out/metrics.json`` with the settings, the device and ``metrics``.

    Parameters
    ----------
    out : output directory (created if needed).
    metrics : the experiment's results (tensors allowed).
    args : the parsed command line, stored under ``"settings"`` (callables dropped).
    device : where it ran; defaults to ``args.device`` when present.

    Returns
    -------
    the path of the file.
    """
    out = prepare_out(out)
    settings = {k: v for k, v in vars(args).items() if not callable(v)} if args is not None else {}
    if device is None:
        device = settings.get("device")
    payload = {"settings": settings, "device": device_name(device), "torch": torch.__version__, **metrics}
    path = out / "metrics.json"
    path.write_text(json.dumps(to_jsonable(payload), indent=2) + "\n")
    return path


def save_figure(fig, out: Union[str, Path], filename: str) -> Path:
    """Save ``fig`` as ``out/filename`` (150 dpi) and close it; return the path."""
    import matplotlib.pyplot as plt

    path = prepare_out(out) / filename
    fig.savefig(path, dpi=150, bbox_inches="tight")
    plt.close(fig)
    return path
