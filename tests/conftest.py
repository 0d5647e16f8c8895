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
