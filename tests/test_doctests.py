"""Every public class has a runnable docstring example (doctest), so ``help(tp.X)`` can be
pasted: public are the classes named in the ``__all__`` of the package and of its public
subpackages (:data:`MODULES`). The example runs as written, may not skip its lines
(``# doctest: +SKIP``) and shows some output to check (a shape, a value). A class without
one fails unless :data:`EXEMPT` names it with the reason; an exemption whose class has
gained an example fails too, so the list stays true."""

from __future__ import annotations

import doctest
import importlib
import inspect

import pytest

import torchmcmcpf as tp

MODULES = ["torchmcmcpf", "torchmcmcpf.models", "torchmcmcpf.models.group", "torchmcmcpf.filters",
           "torchmcmcpf.filters.group",
           "torchmcmcpf.kernels", "torchmcmcpf.scenarios", "torchmcmcpf.metrics", "torchmcmcpf.diagnostics",
           "torchmcmcpf.state", "torchmcmcpf.resampling", "torchmcmcpf.plotting", "torchmcmcpf.runtime",
           "torchmcmcpf.typing", "torchmcmcpf.models.sensors", "torchmcmcpf.models.sensors.grid",
           "torchmcmcpf.interop"]
#: public classes without an example: name -> why (remove the entry when the example lands)
EXEMPT: dict[str, str] = {
    "Program": "what it does is compile (torch.compile with inductor: seconds on the CPU, and a C++ toolchain); "
               "runtime.compile_program and tests/test_runtime.py show it at work",
}


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


@pytest.mark.parametrize("name", list(CLASSES))
def test_class_example_runs(name):
    cls = CLASSES[name]
    runner = doctest.DocTestRunner(optionflags=FLAGS)
    for test in doctest.DocTestFinder(recurse=False).find(cls, name, globs={}):
        runner.run(test)
    result = runner.summarize(verbose=False)
    assert result.failed == 0, f"{name}: {result.failed} of {result.attempted} lines failed (output above)"


@pytest.mark.parametrize("name", [n for n in CLASSES if n not in EXEMPT])
def test_public_classes_have_a_runnable_example(name):
    found = examples(CLASSES[name])
    assert found, f"{name} has no docstring example: add one (an 'Example' section) or list it in EXEMPT with a reason"
    skipped = [e.source.strip() for e in found if e.options.get(doctest.SKIP)]
    assert not skipped, f"{name} skips {skipped}"
    assert any(e.want for e in found), f"{name}'s example shows no output to check"


@pytest.mark.parametrize("name", list(EXEMPT))
def test_exemptions_are_current(name):
    assert name in CLASSES, f"EXEMPT names {name}, which is not a public class (MODULES)"
    assert EXEMPT[name].strip(), f"EXEMPT[{name!r}] gives no reason"
    assert not examples(CLASSES[name]), f"{name} has an example now: remove it from EXEMPT"


def test_top_level_classes_are_covered():
    assert set(TOP) <= set(CLASSES)
    assert not set(TOP) & set(EXEMPT), "the classes of torchmcmcpf.__all__ are never exempt"
