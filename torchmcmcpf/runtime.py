"""Process-level settings for fast batched CPU steps.

The windowed TBD likelihood of a batched step holds per-cell temporaries of tens of MB (at
N = 5000 particles and K = 10 targets, ``(N * K, 7, 49)`` float32 blocks of 68-98 MB). glibc's
``malloc`` serves blocks above its mmap threshold (128 KiB to 32 MiB, adaptive) with fresh
``mmap`` pages and returns them to the system when they are freed, so every call faults in and
zeroes its temporaries again. Measured on the 2-core CPU of benchmarks/README.md, compiled
windowed log-likelihood of the ground radar (N = 5000, K = 10): 190 ms per call by default,
89 ms after :func:`tune_cpu_allocator`; the fused ``log I0`` over 1.7e7 cells alone: 32 -> 12
ms. The command line (``python -m torchmcmcpf ...``) and the benchmarks call it; a library user
calls it once at start-up, or starts Python with ``THP_MEM_ALLOC_ENABLE=1`` (torch's own
switch: transparent huge pages for its CPU allocations, most of the same gain; it must be set
before torch allocates anything).
"""

from __future__ import annotations

import ctypes
import ctypes.util
import sys

from ._validation import check_positive_int

__all__ = ["tune_cpu_allocator"]

#: glibc ``mallopt`` parameters (malloc.h)
_M_TRIM_THRESHOLD, _M_MMAP_THRESHOLD = -1, -3


def tune_cpu_allocator(max_block: int = 2**30) -> bool:
    """Keep freed CPU memory in the process for reuse (glibc's ``malloc`` only).

    Sets glibc's mmap threshold and trim threshold to ``max_block`` bytes with ``mallopt``:
    blocks up to that size come from the heap and freed memory stays there, so the next step
    reuses warm pages instead of faulting in new ones. The process's resident memory then
    stays near its peak instead of shrinking between steps, and the peak can grow by heap
    fragmentation: measured +19% (1.04 -> 1.24 GB) over ten eager radar SIR steps at N = 5000
    followed by three IP-MCMC-PF steps at B = 10 in one process. Affects the whole process,
    from the call on; call it once.

    Parameters
    ----------
    max_block : int > 0
        Largest block served from the heap, in bytes (default 1 GiB).

    Returns
    -------
    bool: True when applied; False on a platform without glibc's ``mallopt`` (macOS, musl,
    Windows), where nothing changes.
    """
    max_block = check_positive_int(max_block, "max_block")
    if not sys.platform.startswith("linux"):
        return False
    try:
        libc = ctypes.CDLL(ctypes.util.find_library("c") or "libc.so.6")
        mallopt = libc.mallopt
    except (OSError, AttributeError):
        return False
    mallopt.argtypes, mallopt.restype = [ctypes.c_int, ctypes.c_int], ctypes.c_int
    value = min(max_block, 2**31 - 1)
    return bool(mallopt(_M_MMAP_THRESHOLD, value)) and bool(mallopt(_M_TRIM_THRESHOLD, value))
