"""Keep freed memory in the process instead of handing it back to the kernel.

glibc serves every allocation above its mmap threshold (at most 32 MB) with a fresh
``mmap`` and returns it with ``munmap`` on free. The sparse networks allocate and free
tensors of tens of megabytes at every layer (a full scan's point features), so each
of them costs the kernel a fresh run of zeroed pages: SPVCNN's evaluation of 20
full val scans spent 17 s in the kernel against 19 s computing. With mmap off and
no trimming, freed blocks are reused: the same evaluation takes half the time, the
results are bit for bit the same, and the peak resident memory grows (both measured by
``python benchmarks/bench_downstream.py --cpu-paths``).
"""

from __future__ import annotations

import ctypes
import ctypes.util

# mallopt parameter numbers from glibc's <malloc.h>.
M_TRIM_THRESHOLD = -1
M_MMAP_MAX = -4


def keep_freed_memory() -> bool:
    """Turn off mmap-backed allocations and heap trimming; True where glibc took it."""
    name = ctypes.util.find_library("c")
    if name is None:
        return False
    try:
        libc = ctypes.CDLL(name)
        mallopt = libc.mallopt
    except (OSError, AttributeError):  # not glibc (macOS, musl): nothing to tune
        return False
    mallopt.argtypes = [ctypes.c_int, ctypes.c_int]
    return bool(mallopt(M_MMAP_MAX, 0)) and bool(mallopt(M_TRIM_THRESHOLD, 2**31 - 1))
