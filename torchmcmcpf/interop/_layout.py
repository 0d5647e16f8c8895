"""What the exporters share: component names, optional imports, argument checks."""

from __future__ import annotations

import importlib
from types import ModuleType

from .._validation import as_int, check_positive_int

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
