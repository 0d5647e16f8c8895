"""A study is a declaration: a :class:`Study` subclass with a frozen settings dataclass.

Each field of the settings holds its full value as the default and, through :func:`option`,
its ``--quick`` value and help text; the study's command-line options, their help (``"<what>
(default <full>, quick <quick>)"``) and the quick/full resolution are derived from those
fields, so they cannot drift from what runs. A study then says what one shard of runs
computes (:meth:`Study.run_shard`) and how the shards become results and figures
(:meth:`Study.summarise`); a study whose runs are not independent defines
:meth:`Study.compute` instead. :meth:`Study.run` is the same for every study: shards
(:mod:`~torchmcmcpf.experiments._shards`, here or on Ray), summary, ``metrics.json``
(:mod:`~torchmcmcpf.experiments._provenance`).

A minimal study, in one file ``torchmcmcpf/experiments/<module>.py``::

    @dataclass(frozen=True)
    class CoinSettings(Settings):
        runs: int = option(100, 4, help="Monte Carlo runs")
        flips: int = option(1000, 10, help="flips per run")
        shard_size: int = option(25, 2, cli=False)

    class Coin(Study[CoinSettings]):
        name = "coin"
        description = "the share of heads of a fair coin"

        def run_shard(self, settings, runs, *, generator, device, progress=False):
            heads = torch.rand(len(runs), settings.flips, generator=generator, device=device) < 0.5
            return {"share": heads.double().mean(1)}, {}

        def summarise(self, settings, shards, out):
            ...  # figures into out
            return {"config": settings.record(), "share": shards.per_run["share"].mean()}

    STUDY = Coin()

Settings and options are frozen: a study receives them and never changes them.
"""

from __future__ import annotations

import argparse
import dataclasses
import math
import time
from collections.abc import Callable, Hashable, Mapping
from dataclasses import MISSING, dataclass, field, fields
from pathlib import Path
from typing import Any, ClassVar, Generic, TypeVar, get_args, get_origin

import torch

from ._options import RunOptions, positive_int
from ._provenance import write_metrics
from ._shards import Shards, run_shards

__all__ = ["Settings", "Study", "option", "rows_option", "in_order", "generator", "StepTimer", "reused", "models_key",
           "cell"]

_SAME = object()


def option(full: Any, quick: Any = _SAME, *, help: str = "", cli: bool = True, record: bool = True,
           **argparse_kw: Any) -> Any:
    """A settings field: ``full`` is its default, ``quick`` its value under ``--quick``
    (default: the same), ``help`` what it is (the help text adds the two values).

    ``cli=False`` keeps it off the study's command line (``shard_size``, a shared option,
    and constants worth recording); ``record=False`` out of :meth:`Settings.record` (a
    switch of how the study runs rather than of what it computes). The option is ``--<name-with-dashes>``; its argparse
    ``type`` and ``nargs`` follow the default (an int: an integer >= 1; a tuple: one or more
    of its element's type; ``False``: a flag) unless given in ``argparse_kw`` (``type``,
    ``choices``, ``metavar``, ``nargs``).
    """
    return field(default=full, metadata={"quick": quick, "help": help, "cli": cli, "record": record,
                                         "argparse": argparse_kw})


def rows_option(rows: tuple[str, ...]) -> Any:
    """The ``--filters`` option of a study whose rows are ``rows`` (default all): each row
    draws from a stream of its own (:func:`~torchmcmcpf.experiments._shards.streams`), so a
    row is the same bits whichever others run.
    """
    return option(rows, choices=rows, metavar="NAME",
                  help=f"the rows to run, among {', '.join(repr(r) for r in rows)} (default all; each row draws "
                       "from a stream of its own, so a row is the same whichever others run)")


def in_order(names: tuple[str, ...], chosen: tuple[str, ...]) -> tuple[str, ...]:
    """The ``chosen`` among ``names``, in the order of ``names`` (the study's own)."""
    return tuple(n for n in names if n in chosen)


def cell(value: Any, digits: int = 2) -> str:
    """A number for a summary table with ``digits`` decimals, or ``-`` where there is none
    (``None``, as stored results hold it, or NaN).
    """
    if value is None or math.isnan(float(value)):
        return "-"
    return f"{float(value):.{digits}f}"


def _fmt(value: Any) -> str:
    if isinstance(value, (tuple, list)):
        return " ".join(f"{x:g}" if isinstance(x, float) else str(x) for x in value)
    return str(value)


@dataclass(frozen=True)
class Settings:
    """Base of every study's settings: ``quick`` records whether the quick values ran.
    ``settings["runs"]`` reads a field as ``settings.runs`` does (notebooks index them).
    """

    quick: bool = option(False, cli=False)

    def __getitem__(self, name: str) -> Any:
        return getattr(self, name)

    def record(self) -> dict[str, Any]:
        """The settings as a study's results record them (``"config"`` of ``metrics.json``):
        every field but those declared with ``record=False``.
        """
        return {f.name: getattr(self, f.name) for f in fields(self) if f.metadata.get("record", True)}


S = TypeVar("S", bound=Settings)
T = TypeVar("T")


class Study(Generic[S]):
    """One Monte Carlo study (module docstring): ``name`` (the command-line name),
    ``description`` (one line for ``reproduce --list``), ``outputs`` (the files it writes,
    for the "replacing" note), and ``run_shard`` + ``summarise`` or ``compute``. Its settings
    dataclass is the parameter of the base, ``class Coin(Study[CoinSettings])``, and
    ``settings_type`` is set from it.
    """

    name: ClassVar[str]
    description: ClassVar[str]
    settings_type: ClassVar[type]
    outputs: ClassVar[tuple[str, ...]] = ("metrics.json",)

    def __init_subclass__(cls, **kwargs: Any) -> None:
        super().__init_subclass__(**kwargs)
        for base in getattr(cls, "__orig_bases__", ()):
            if get_origin(base) is Study and isinstance(get_args(base)[0], type):
                cls.settings_type = get_args(base)[0]

    # ---------------------------------------------------------------- settings

    def settings(self, quick: bool = False, **given: Any) -> S:
        """The full (or ``quick``) values, overridden by ``given`` (``None`` values ignored;
        lists become tuples). Raises ``ValueError`` for settings the study refuses.
        """
        known = {f.name: f for f in fields(self.settings_type)}
        unknown = set(given) - set(known)
        if unknown:
            raise TypeError(f"{self.name}: no setting {', '.join(sorted(unknown))}")
        values: dict[str, Any] = {"quick": bool(quick)}
        for name, f in known.items():
            if name == "quick":
                continue
            q = f.metadata.get("quick", _SAME)
            if quick and q is not _SAME:
                values[name] = q
            value = given.get(name)
            if value is not None:
                values[name] = tuple(value) if isinstance(value, list) else value
        return self.settings_type(**values)

    def settings_from(self, args: argparse.Namespace | Mapping[str, Any]) -> S:
        """:meth:`settings` from a parsed command line (or a mapping): ``quick`` and every
        setting found there; the rest (absent or ``None``) keep their values.
        """
        given = dict(vars(args) if isinstance(args, argparse.Namespace) else args)
        names = {f.name for f in fields(self.settings_type)} - {"quick"}
        return self.settings(bool(given.get("quick", False)), **{k: v for k, v in given.items() if k in names})

    def defaults_text(self, name: str) -> str:
        """``"default <full>, quick <quick>"`` (or ``"default <full>"``) of the setting ``name``."""
        f = next(f for f in fields(self.settings_type) if f.name == name)
        q = f.metadata.get("quick", _SAME)
        return f"default {_fmt(f.default)}" + ("" if q is _SAME else f", quick {_fmt(q)}")

    def add_arguments(self, parser: argparse.ArgumentParser | argparse._ArgumentGroup) -> None:
        """One option per settings field with ``cli=True``, its help ending in the full and
        quick values (:meth:`defaults_text`); argparse default ``None`` (= not given).
        """
        for f in fields(self.settings_type):
            if not f.metadata.get("cli", True):
                continue
            kw = dict(f.metadata.get("argparse", {}))
            default = f.default if f.default is not MISSING else None
            if isinstance(default, bool) and "type" not in kw:  # --name / --no-name: a default True can be turned off
                parser.add_argument("--" + f.name.replace("_", "-"), dest=f.name, action=argparse.BooleanOptionalAction,
                                    default=None, help=f.metadata["help"] if "(default" in f.metadata["help"]
                                    else f"{f.metadata['help']} ({self.defaults_text(f.name)})")
                continue
            element = default[0] if isinstance(default, tuple) and default else default
            if "type" not in kw and "choices" not in kw:
                kw["type"] = positive_int if isinstance(element, int) else type(element)
            if isinstance(default, tuple):
                kw.setdefault("nargs", "+")
            what = f.metadata["help"]
            help_text = what if "(default" in what else f"{what} ({self.defaults_text(f.name)})"
            parser.add_argument("--" + f.name.replace("_", "-"), dest=f.name, default=None, help=help_text, **kw)

    # ---------------------------------------------------------------- the work

    @property
    def sharded(self) -> bool:
        """Whether the study runs in shards (defines :meth:`run_shard`)."""
        return type(self).run_shard is not Study.run_shard

    def run_shard(self, settings: S, runs: range, *, generator: torch.Generator, device: torch.device,
                  progress: bool = False) -> tuple[dict, dict]:
        """The runs ``runs`` with the generator of their shard: ``per_run`` (str -> tensor,
        run dim first) and ``seconds`` (str -> float); see :mod:`~torchmcmcpf.experiments._shards`.
        """
        raise NotImplementedError(f"{self.name} does not run in shards")

    def summarise(self, settings: S, shards: Shards, out: Path) -> dict:
        """The results from every shard's runs (``shards``, with ``settings.shard_size`` the
        size that ran); writes the study's figures and tables into ``out``; returns what
        ``metrics.json`` holds besides the settings and the provenance.
        """
        raise NotImplementedError(f"{self.name} defines run_shard but not summarise")

    def compute(self, settings: S, options: RunOptions) -> dict:
        """The whole study in this process (a study whose runs are not independent defines
        this instead of :meth:`run_shard` and :meth:`summarise`); returns as :meth:`summarise`.
        """
        raise NotImplementedError(f"{self.name} defines neither run_shard nor compute")

    def run(self, settings: S, options: RunOptions) -> dict:
        """Run the study with ``settings`` as ``options`` say, write ``metrics.json`` (the
        options and settings that ran under ``"settings"``, the provenance) and return the
        results.
        """
        options.out.mkdir(parents=True, exist_ok=True)
        layout = None
        if self.sharded:
            shards = run_shards(self, settings, options)
            settings = dataclasses.replace(settings, **{"shard_size": shards.layout["shard_size"]})
            payload = self.summarise(settings, shards, options.out)
            layout = shards.layout
        else:
            payload = self.compute(settings, options)
        write_metrics(options.out, payload, settings={"name": self.name, **options.recorded(),
                                                      **dataclasses.asdict(settings)},
                      options=options, shards=layout)
        return payload

    def run_namespace(self, args: argparse.Namespace) -> dict:
        """:meth:`run` with the settings and options read from an argparse-style namespace
        (a notebook's ``argparse.Namespace(quick=True, out=..., ...)``).
        """
        return self.run(self.settings_from(args), RunOptions.from_namespace(args))

    def summary(self, payload: dict) -> str | None:
        """The headline table ``reproduce`` prints (``None``: its scalar results as a table)."""
        return None


def generator(device: str | torch.device, seed: int) -> torch.Generator:
    """A ``torch.Generator`` on ``device`` seeded with ``seed``."""
    return torch.Generator(device=torch.device(device)).manual_seed(int(seed))


#: the objects :func:`reused` keeps, oldest first
_REUSED: dict[Hashable, Any] = {}
#: how many :func:`reused` keeps (Table II's rows: 4 algorithms x 2 Np x 2 target counts)
REUSED_MAX = 16


def reused(key: Hashable, build: Callable[[], T]) -> T:
    """``build()``, or what it returned for an equal ``key`` earlier in this process.

    A study's shards run one after another in a process (or on a Ray worker); a filter built
    with ``compile_step=True`` compiles its programs on its first call, and a new filter of
    the same class compiles them again: Dynamo keeps compiled code per filter, and Inductor's
    FX-graph cache skips graphs with a ``torch.cond`` (every windowed likelihood of more than
    one block), so a fresh filter pays the whole compilation (Table II's 10-target SIR at
    B = 10, N = 5000: 72 s against 1.5 s for a step). Building each row's filter once per
    process and reusing it in the later shards gives the same bits (filters keep nothing
    between calls but compiled code and caches of it). ``key`` must say everything ``build``
    depends on: the settings, the row, and the models (:func:`models_key`). At most
    :data:`REUSED_MAX` objects are kept; the least recently used goes first.
    """
    if key in _REUSED:
        _REUSED[key] = _REUSED.pop(key)  # the newest again
        return _REUSED[key]
    while len(_REUSED) >= REUSED_MAX:
        del _REUSED[next(iter(_REUSED))]
    _REUSED[key] = obj = build()
    return obj


def models_key(*models: torch.nn.Module) -> tuple:
    """A hashable key equal for models built alike (for :func:`reused`): each model's class,
    its parameters' and buffers' values, dtypes and devices, and its public scalar attributes
    (numbers, strings, tuples). Two scenarios drawn from other random numbers with the same
    settings give equal keys; another grid or noise level does not.
    """
    def one(m: torch.nn.Module) -> tuple:
        tensors = tuple((k, str(v.dtype), str(v.device), tuple(v.detach().cpu().flatten().tolist()))
                        for k, v in m.state_dict().items())
        scalars = tuple((k, v) for k, v in vars(m).items()
                        if not k.startswith("_") and isinstance(v, (bool, int, float, str, tuple)))
        return (type(m).__qualname__, tensors, scalars)
    return tuple(one(m) for m in models)


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
