"""Host memory policy: keep freed blocks for reuse instead of handing them back to the kernel.

XLA:CPU allocates every execution's outputs and temporaries afresh. glibc serves blocks above
its mmap threshold with new mappings and unmaps them on free, so each training step faulted in
and zero-filled the same few hundred MB again: 71k page faults per step at 156k surfels
(192x144). Served from the heap and never trimmed, the freed blocks are reused as they are:
that step ran 1.11x faster, for 1-12% more peak memory (benchmarks/results/train_speed.json,
"host memory policy").
"""

from __future__ import annotations

import ctypes
import os
import sys

M_TRIM_THRESHOLD = -1  # glibc's mallopt parameters (malloc.h)
M_MMAP_MAX = -4
TRIM_THRESHOLD = 2**31 - 1  # the largest value mallopt takes: freed memory stays with the process
OPT_OUT = "GHSPLAT_SYSTEM_MALLOC"  # set to 1 to leave the C library's policy as it is


def reuse_freed_memory() -> bool:
    """Make glibc's malloc serve large blocks from the heap (no mmap) and never trim it.
    Process-wide; the peak resident size stays what the largest step needs. Returns whether
    the policy was applied: False off glibc, or when $GHSPLAT_SYSTEM_MALLOC is set to 1."""
    if not sys.platform.startswith("linux") or os.environ.get(OPT_OUT, "0") not in ("", "0"):
        return False
    try:
        libc = ctypes.CDLL(None)
        if not hasattr(libc, "gnu_get_libc_version"):
            return False  # musl and others ignore or lack these parameters
        mallopt = libc.mallopt
    except (OSError, AttributeError):
        return False
    mallopt.argtypes, mallopt.restype = (ctypes.c_int, ctypes.c_int), ctypes.c_int
    return bool(mallopt(M_MMAP_MAX, 0)) and bool(mallopt(M_TRIM_THRESHOLD, TRIM_THRESHOLD))
