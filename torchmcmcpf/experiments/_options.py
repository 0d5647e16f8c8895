"""The command line of the studies: argparse types, the options every study shares, and
:class:`RunOptions`, those options read once into a frozen record.

A study's own options are derived from its settings dataclass
(:meth:`torchmcmcpf.experiments._study.Study.add_arguments`); what is here is the same for every
study (and for ``python -m torchmcmcpf demo``).
"""

from __future__ import annotations

import argparse
import time
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field, fields
from pathlib import Path
from typing import Any

import torch

__all__ = [
    "positive_int",
    "nonnegative_int",
    "memory_budget_arg",
    "device_arg",
    "out_dir",
    "prepare_out",
    "add_common_arguments",
    "add_shard_arguments",
    "SHARD_OPTIONS",
    "RunOptions",
]


def _int_at_least(text: str, low: int) -> int:
    try:
        value = int(text)
    except ValueError:
        value = None
    if value is None or value < low:
        raise argparse.ArgumentTypeError(f"must be an integer >= {low}, got {text!r}")
    return value


def positive_int(text: str) -> int:
    """An argparse type: an integer >= 1."""
    return _int_at_least(text, 1)


def nonnegative_int(text: str) -> int:
    """An argparse type: an integer >= 0."""
    return _int_at_least(text, 0)


def memory_budget_arg(text: str) -> int:
    """An argparse type: ``--memory-budget`` in bytes, at least
    :data:`~torchmcmcpf.runtime.MIN_MEMORY_BUDGET` (1 MiB; ``10`` is a slip for 10 MB or 10 GB,
    not a budget); a suffix ``k``, ``M`` or ``G`` (powers of 1024) is accepted (``512M``).
    """
    from ..runtime import MIN_MEMORY_BUDGET

    scale = {"k": 2**10, "m": 2**20, "g": 2**30}.get(text[-1:].lower(), 1)
    try:
        value = int(float(text[:-1] if scale > 1 else text) * scale)
    except ValueError:
        value = None
    if value is None or value < MIN_MEMORY_BUDGET:
        raise argparse.ArgumentTypeError(f"must be a number of bytes >= {MIN_MEMORY_BUDGET} (1 MiB; suffixes k, M, "
                                         f"G accepted, e.g. 512M), got {text!r}")
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


def add_common_arguments(parser: argparse.ArgumentParser, *, name: str, quick: bool = True,
                         shards: bool = True, shard_size: str | None = None) -> argparse.ArgumentParser:
    """Add the options every experiment shares (see the module docstring); ``quick=False``
    leaves out ``--quick`` (for commands without a small version, like ``demo``),
    ``shards=False`` the shard and Ray options; ``shard_size`` is the study's default shard
    size as its help says it (``"default 5, quick 1"``).
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
    group.add_argument("--memory-budget", type=memory_budget_arg, default=None, metavar="BYTES",
                       help="bytes of temporaries a grid sensor's likelihood may hold at once (its memory_budget, "
                            "runtime.memory_budget; default: 1 GiB, at least 1 MiB; 512M, 2G accepted); smaller "
                            "blocks of samples, same results")
    group.add_argument("--no-progress", dest="progress", action="store_false",
                       help="hide the progress bars")
    if shards:
        add_shard_arguments(parser, shard_size=shard_size)
    return parser


#: the options that only studies with ``run_shard`` accept
SHARD_OPTIONS = ("--shard-size", "--workers", "--ray-address", "--gpus-per-shard")


def add_shard_arguments(parser: argparse.ArgumentParser, *, shard_size: str | None = None,
                        studies: Sequence[str] = ()) -> argparse.ArgumentParser:
    """Add :data:`SHARD_OPTIONS` (shards of runs, Ray) in their own group. ``shard_size``: the
    study's default shard size for the help; ``studies`` (the names of the sharded studies) goes in
    the group title, for the help of ``reproduce`` itself.
    """
    title = "shards and Ray" + (f" (only {', '.join(studies)})" if studies else "")
    group = parser.add_argument_group(title)
    group.add_argument("--shard-size", type=positive_int, default=None,
                       help="Monte Carlo runs per shard; each shard has its own random stream "
                            "from (seed, shard index), so results depend on it, never on --workers "
                            + (f"({shard_size})" if shard_size else "(default: the study's, see metrics.json)"))
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



@dataclass(frozen=True)
class RunOptions:
    """How a study runs, as opposed to what it computes (its settings): the options every
    study shares, read once from the command line and never changed.

    ``out``, ``device``, ``seed``, ``threads``, ``memory_budget``, ``progress`` and ``quick``
    as in :func:`add_common_arguments`; ``shard_size`` (``None``: the study's own),
    ``workers``, ``ray_address`` and ``gpus_per_shard`` as in :func:`add_shard_arguments`;
    ``command_line`` and ``started`` (a ``time.perf_counter()`` reading) are recorded in the
    provenance of ``metrics.json``.
    """

    out: Path = Path("results")
    device: torch.device = torch.device("cpu")
    seed: int = 0
    threads: int | None = None
    memory_budget: int | None = None
    progress: bool = False
    quick: bool = False
    shard_size: int | None = None
    workers: int | None = None
    ray_address: str | None = None
    gpus_per_shard: float = 1.0
    command_line: str | None = field(default=None, repr=False)
    started: float = field(default_factory=time.perf_counter, repr=False)

    def __post_init__(self) -> None:
        object.__setattr__(self, "out", Path(self.out))
        object.__setattr__(self, "device", torch.device(self.device))

    @classmethod
    def from_namespace(cls, args: argparse.Namespace | Mapping[str, Any]) -> RunOptions:
        """The options found in ``args`` (a parsed command line, or a mapping); the absent
        ones keep their defaults.
        """
        given = vars(args) if isinstance(args, argparse.Namespace) else dict(args)
        return cls(**{f.name: given[f.name] for f in fields(cls) if given.get(f.name) is not None})

    def recorded(self) -> dict[str, Any]:
        """The options as ``metrics.json`` records them under ``"settings"`` (without the
        bookkeeping of the provenance).
        """
        return {f.name: getattr(self, f.name) for f in fields(self) if f.name not in ("command_line", "started")}
