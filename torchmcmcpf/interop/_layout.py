"""What the exporters share: component names, optional imports, argument checks, and the
fields of a result they read.

The exporters read a result through the protocols :class:`Cloud`, :class:`Info` and
:class:`Result` (the fields of :class:`~torchmcmcpf.state.ParticleState`,
:class:`~torchmcmcpf.state.StepInfo` and :class:`~torchmcmcpf.state.FilterResult`), not
through those classes: so :mod:`torchmcmcpf.state` can offer ``FilterResult.to_xarray`` and
its siblings by importing this package, and no import runs the other way (the layer order
of ``tests/test_layers.py``). A filter's own state with ``x``, ``log_w`` and ``exists``
exports as well as a ``ParticleState``.
"""

from __future__ import annotations

import importlib
from types import ModuleType
from typing import Any, Protocol

from .._validation import as_int, check_positive_int
from ..typing import Tensor


class Cloud(Protocol):
    """A weighted cloud: ``x (B, N, K, D)``, ``log_w (B, N)``, ``exists (B, N, K)`` or None
    (a step's :class:`~torchmcmcpf.state.ParticleState`; with a leading ``T`` in a history).
    """

    @property
    def x(self) -> Tensor: ...

    @property
    def log_w(self) -> Tensor: ...

    @property
    def exists(self) -> Tensor | None: ...


class Info(Protocol):
    """Per-step diagnostics (:class:`~torchmcmcpf.state.StepInfo`), ``(T, B, ...)`` in a result."""

    @property
    def ess(self) -> Tensor: ...

    @property
    def log_evidence(self) -> Tensor: ...

    @property
    def acceptance(self) -> Tensor: ...

    @property
    def extras(self) -> dict: ...


class Result(Protocol):
    """What a filter's ``forward`` returns (:class:`~torchmcmcpf.state.FilterResult`)."""

    @property
    def mean(self) -> Tensor: ...

    @property
    def state(self) -> Any: ...

    @property
    def info(self) -> Info: ...

    @property
    def log_evidence(self) -> Tensor: ...

    @property
    def exists_prob(self) -> Tensor | None: ...

    @property
    def cov(self) -> Tensor | None: ...

    @property
    def history(self) -> Cloud | None: ...

    @property
    def meta(self) -> dict | None: ...

#: names of the per-target state components, in the layout of :mod:`torchmcmcpf.typing`
COMPONENTS = ("x", "vx", "y", "vy", "rho")


def component_names(dim: int) -> list[str]:
    """Names of the ``dim`` components of a target state: ``x, vx, y, vy`` (+ ``rho``, the
    amplitude or power, when D = 5); ``c5, c6, ...`` beyond.
    """
    dim = check_positive_int(dim, "dim")
    return [*COMPONENTS[:dim], *(f"c{i}" for i in range(len(COMPONENTS), dim))]


def optional(module: str, package: str) -> ModuleType:
    """Import an optional dependency, or an ``ImportError`` saying how to install it."""
    try:
        return importlib.import_module(module)
    except ImportError as err:
        raise ImportError(f"{module} is needed here: pip install '{package}' (or 'torchmcmcpf[interop]')") from err


def check_index(value: object, name: str, size: int, what: str) -> int:
    """``value`` as an index into ``size`` items (negative counts from the end); a
    ``ValueError`` naming ``name`` otherwise.
    """
    i = as_int(value)
    if i is None or not -size <= i < size:
        raise ValueError(f"{name} must be an integer in [-{size}, {size}) ({what}), got {value!r}")
    return i % size
