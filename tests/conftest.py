import os

import pytest
import torch

if os.environ.get("PYTEST_XDIST_WORKER"):
    # `pytest -n 2` (the README's command): two worker processes on the two cores, one torch
    # thread each; two threads a worker would spin against the other worker's (small ops 20-100x
    # slower). Loaded by every worker before any test runs; the notebooks' kernels and the
    # tests' subprocesses inherit the variable.
    os.environ["OMP_NUM_THREADS"] = "1"
    torch.set_num_threads(1)


@pytest.fixture
def gen():
    """A fresh, seeded generator: every random draw in the tests goes through one."""
    return torch.Generator().manual_seed(1234)
