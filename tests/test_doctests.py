"""Every public class's docstring example runs as written (doctest), so ``help(tp.X)`` can be
pasted. Public: the classes named in the ``__all__`` of the package and of its public
subpackages. The classes of the top-level ``__all__`` must have an example, and it may not
skip its lines (``# doctest: +SKIP``)."""

from __future__ import annotations

import doctest
import importlib
import inspect

import pytest

import torchmcmcpf as tp

MODULES = ["torchmcmcpf", "torchmcmcpf.models", "torchmcmcpf.models.group", "torchmcmcpf.filters",
           "torchmcmcpf.kernels", "torchmcmcpf.scenarios", "torchmcmcpf.metrics", "torchmcmcpf.diagnostics",
           "torchmcmcpf.state", "torchmcmcpf.resampling", "torchmcmcpf.plotting", "torchmcmcpf.runtime",
           "torchmcmcpf.typing"]
#: classes whose example another branch of issue 25 rewrites; remove the entry when it lands
PENDING: dict[str, str] = {}


def public_classes() -> dict[str, type]:
    found = {}
    for name in MODULES:
        module = importlib.import_module(name)
        for attr in getattr(module, "__all__", []):
            obj = getattr(module, attr)
            if inspect.isclass(obj) and obj.__module__.startswith("torchmcmcpf"):
                found[obj.__qualname__] = obj
    return dict(sorted(found.items()))


CLASSES = public_classes()
TOP = sorted(n for n in tp.__all__ if inspect.isclass(getattr(tp, n)))
FLAGS = doctest.ELLIPSIS | doctest.NORMALIZE_WHITESPACE


def examples(cls: type) -> list[doctest.Example]:
    tests = doctest.DocTestFinder(recurse=False).find(cls, cls.__qualname__, globs={})
    return [e for t in tests for e in t.examples]


@pytest.mark.parametrize("name", [pytest.param(n, marks=pytest.mark.skip(reason=PENDING[n])) if n in PENDING else n
                                  for n in CLASSES])
def test_class_example_runs(name):
    cls = CLASSES[name]
    runner = doctest.DocTestRunner(optionflags=FLAGS)
    for test in doctest.DocTestFinder(recurse=False).find(cls, name, globs={}):
        runner.run(test)
    result = runner.summarize(verbose=False)
    assert result.failed == 0, f"{name}: {result.failed} of {result.attempted} lines failed (output above)"


@pytest.mark.parametrize("name", [n for n in TOP if n not in PENDING])
def test_top_level_classes_have_a_runnable_example(name):
    found = examples(getattr(tp, name))
    assert found, f"tp.{name} has no docstring example"
    skipped = [e.source.strip() for e in found if e.options.get(doctest.SKIP)]
    assert not skipped, f"tp.{name} skips {skipped}"
    assert any(e.want for e in found), f"tp.{name}'s example shows no output to check"
