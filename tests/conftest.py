import os

import pytest
import torch

if os.environ.get("PYTEST_XDIST_WORKER"):
    # `pytest -n auto` (the README's command): a worker process a core, one torch thread each;
    # two threads a worker would spin against the other workers' (small ops 20-100x slower).
    # Loaded by every worker before any test runs; the notebooks' kernels and the
    # tests' subprocesses inherit the variable.
    os.environ["OMP_NUM_THREADS"] = "1"
    torch.set_num_threads(1)


@pytest.fixture
def gen():
    """A fresh, seeded generator: every random draw in the tests goes through one."""
    return torch.Generator().manual_seed(1234)


@pytest.fixture
def at_threads():
    """``run(fn, n)``: ``fn()`` with torch at ``n`` intra-op threads, the count restored after."""
    def run(fn, n):
        threads = torch.get_num_threads()
        try:
            torch.set_num_threads(n)
            return fn()
        finally:
            torch.set_num_threads(threads)
    return run


@pytest.fixture
def count_native_calls(monkeypatch):
    """``calls = count_native_calls()``: from then on, the names of the C loops' functions
    called (``torchmcmcpf._native``) are appended to ``calls``."""
    def start():
        from torchmcmcpf import _native

        calls = []
        lib = _native.library()

        class Counted:
            def __getattr__(self, name):
                calls.append(name)
                return getattr(lib, name)

        monkeypatch.setitem(_native._state, "lib", Counted())
        return calls
    return start
