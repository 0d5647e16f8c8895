"""Monte Carlo studies that regenerate the papers' tables and figures.

Each public module here holds one study: a :class:`~torchmcmcpf.experiments._study.Study`
subclass with its settings dataclass, and ``STUDY``, its instance (see
:mod:`torchmcmcpf.experiments._study` for the contract). They are found by :func:`discover`,
so adding a study means adding a module, nothing else:

    python -m torchmcmcpf reproduce --list
    python -m torchmcmcpf reproduce --help          # the options every study shares
    python -m torchmcmcpf reproduce NAME [--quick] [--out DIR] [--device cpu|cuda] [--seed S]
    python -m torchmcmcpf reproduce NAME --workers N [--ray-address ADDR] [--shard-size S]

A study whose runs are independent defines ``run_shard`` (its runs in fixed-size shards,
each with the generator of ``(seed, shard index)``), so it runs the same in this process or
on Ray. Modules whose name starts with ``_`` are the shared machinery, not studies:
``_study`` (the base and its settings), ``_options`` (the command line), ``_shards`` (the
shard runner, here or on Ray), ``_provenance`` (``metrics.json``), ``_figures``.
"""

from __future__ import annotations

import importlib
import pkgutil
import warnings

from ._study import Study

__all__ = ["discover", "Study"]


def discover() -> dict[str, Study]:
    """Import every study module of this package.

    Returns
    -------
    dict ``name -> study`` (each module's ``STUDY``), sorted by name. A module that fails to
    import or has no ``STUDY`` (a :class:`Study`) is skipped with a ``RuntimeWarning`` naming
    it (one broken study does not hide the others); two studies with the same name raise
    ``ValueError``.
    """
    found: dict[str, Study] = {}
    where: dict[str, str] = {}
    for info in pkgutil.iter_modules(__path__):
        if info.name.startswith("_"):
            continue
        try:
            module = importlib.import_module(f"{__name__}.{info.name}")
        except Exception as err:  # report and go on: other studies still run
            warnings.warn(f"experiment module {info.name!r} failed to import: {err!r}", RuntimeWarning,
                          stacklevel=2)
            continue
        study = getattr(module, "STUDY", None)
        if not isinstance(study, Study):
            warnings.warn(f"experiment module {info.name!r} has no STUDY (a Study); skipped", RuntimeWarning,
                          stacklevel=2)
            continue
        if study.name in found:
            raise ValueError(f"experiments {where[study.name]} and {module.__name__} share the name {study.name!r}")
        found[study.name], where[study.name] = study, module.__name__
    return dict(sorted(found.items()))
