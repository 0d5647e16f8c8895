"""Monte Carlo studies that regenerate the papers' tables and figures.

Each public module here is an experiment (``NAME``, ``DESCRIPTION``, ``run(args) -> dict``;
see :mod:`torchmcmcpf.experiments._common` for the contract and the shared helpers). They
are found by :func:`discover`, so adding a study means adding a module, nothing else:

    python -m torchmcmcpf reproduce --list
    python -m torchmcmcpf reproduce --help          # the options every study shares
    python -m torchmcmcpf reproduce NAME [--quick] [--out DIR] [--device cpu|cuda] [--seed S]
    python -m torchmcmcpf reproduce NAME --workers N [--ray-address ADDR] [--shard-size S]

A study whose runs are independent also defines ``run_shard`` (its runs in fixed-size
shards, each with the generator of ``(seed, shard index)``), so it runs the same in this
process or on Ray; optional ``summary(payload) -> str`` is the headline table ``reproduce``
prints, ``OUTPUTS`` the file names it writes. Modules whose name starts with ``_`` are
helpers, not experiments.
"""

from __future__ import annotations

import importlib
import pkgutil
import warnings
from types import ModuleType

__all__ = ["discover"]


def discover() -> dict[str, ModuleType]:
    """Import every experiment module of this package.

    Returns
    -------
    dict ``NAME -> module``, sorted by name. A module that fails to import or lacks
    ``NAME``, ``DESCRIPTION`` or ``run`` is skipped with a ``RuntimeWarning`` naming it (one
    broken study does not hide the others); two modules with the same ``NAME`` raise
    ``ValueError``.
    """
    found: dict[str, ModuleType] = {}
    for info in pkgutil.iter_modules(__path__):
        if info.name.startswith("_"):
            continue
        try:
            module = importlib.import_module(f"{__name__}.{info.name}")
        except Exception as err:  # report and go on: other studies still run
            warnings.warn(f"experiment module {info.name!r} failed to import: {err!r}", RuntimeWarning,
                          stacklevel=2)
            continue
        missing = [a for a in ("NAME", "DESCRIPTION", "run") if not hasattr(module, a)]
        if missing:
            warnings.warn(f"experiment module {info.name!r} lacks {', '.join(missing)}; skipped",
                          RuntimeWarning, stacklevel=2)
            continue
        if module.NAME in found:
            raise ValueError(f"experiments {found[module.NAME].__name__} and {module.__name__} "
                             f"share NAME {module.NAME!r}")
        found[module.NAME] = module
    return dict(sorted(found.items()))
