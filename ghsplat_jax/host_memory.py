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


MAP_SHARE = 0.5  # release_compiled_programs acts above this share of the kernel's mapping limit
# ... and inside one training run, checked every MAPS_CHECK_EVERY steps (counting the maps takes
# milliseconds): a self-sizing run compiles for every pool, pair buffer and resolution it passes,
# and the third auto run of one `ghsplat run` process (each run starting under MAP_SHARE) hit the
# limit mid-run.
IN_RUN_MAP_SHARE = 0.8
MAPS_CHECK_EVERY = 100


def memory_maps() -> tuple[int, int] | None:
    """(this process's memory mappings, the kernel's per-process limit), or None where the
    kernel does not say (not Linux)."""
    try:
        with open("/proc/self/maps", "rb") as fh:
            count = sum(1 for _ in fh)
        with open("/proc/sys/vm/max_map_count") as fh:
            return count, int(fh.read())
    except (OSError, ValueError):
        return None


def release_compiled_programs(share: float = MAP_SHARE) -> bool:
    """Drop JAX's compiled programs (jax.clear_caches) when this process holds more than `share`
    of the kernel's limit on memory mappings; returns whether it did.

    XLA:CPU maps each compiled program's code and data apart, and keeps them while a cache holds
    the program. A study that trains many models in one process (the full stability preset, 30
    runs) reached 64,882 of Linux's 65,530 mappings; the next compile failed ("LLVM compilation
    error: Cannot allocate memory") and the process hung. Call this between runs: programs
    compile again when next needed (from the persistent cache, where it is on)."""
    maps = memory_maps()
    if maps is None or maps[0] <= share * maps[1]:
        return False
    import gc
    import logging

    import jax

    jax.clear_caches()
    gc.collect()
    after = memory_maps()
    logging.getLogger("ghsplat").info("released JAX's compiled programs: %d -> %s memory mappings (limit %d)",
                                      maps[0], after[0] if after else "?", maps[1])
    return True
