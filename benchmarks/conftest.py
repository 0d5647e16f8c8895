"""Every benchmark sets torch's thread count and records it (``extra_info['threads']``).

``BENCH_THREADS=n`` sets it (default: torch's current count, i.e. ``OMP_NUM_THREADS`` or the
number of cores). On a shared 2-core machine a second busy process makes torch's threads spin
and small ops become up to 100x slower: compare figures within one run (README.md).
"""

import os

import pytest
import torch

from torchmcmcpf.runtime import tune_cpu_allocator

#: every figure is taken with freed memory kept for reuse, as the command line runs
#: (torchmcmcpf.runtime; ``BENCH_TUNE_ALLOCATOR=0`` to measure glibc's default)
ALLOCATOR_TUNED = os.environ.get("BENCH_TUNE_ALLOCATOR", "1") != "0" and tune_cpu_allocator()


@pytest.fixture(autouse=True)
def _set_and_record_threads(request):
    threads = int(os.environ.get("BENCH_THREADS", torch.get_num_threads()))
    torch.set_num_threads(threads)
    if "benchmark" in request.fixturenames:
        info = request.getfixturevalue("benchmark").extra_info
        info["threads"], info["cpu_allocator_tuned"] = threads, ALLOCATOR_TUNED
    yield
