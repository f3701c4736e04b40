"""Keep the memory a training step frees for the next step, instead of handing it back to the system.

A step allocates and frees the same large blocks every time (the head's 23 112-wide gradients, Adam's update,
the batch's targets and activations: megabytes each). glibc serves blocks above its mmap threshold with fresh
pages and trims the heap's top after a free, so every step paid thousands of page faults, a sixth of its time
in the kernel on the 2-core VMs (``bench/results/training.md``). Raising the mmap threshold to its maximum and
the trim threshold far above a step's working set makes each step reuse the last one's pages. Freed memory is
then kept by the process (its resident size stays at its peak), which a training process wants anyway.
"""

from __future__ import annotations

import ctypes
import sys

M_TRIM_THRESHOLD, M_MMAP_THRESHOLD = -1, -3  # glibc's mallopt parameters (malloc.h)
MMAP_THRESHOLD_BYTES = 32 * 1024 * 1024  # the largest glibc accepts on 64-bit systems (HEAP_MAX_SIZE / 2)
TRIM_THRESHOLD_BYTES = 1 << 30  # far above a step's working set, inside mallopt's int


_outcome: list[bool] = []  # keep_freed_memory's result, once it ran


def keep_freed_memory() -> bool:
    """Set glibc's thresholds for this process (once; later calls return the first outcome); False where the C
    library is not glibc (nothing changes)."""
    if not _outcome:
        _outcome.append(_set_thresholds())
    return _outcome[0]


def freed_memory_kept() -> bool:
    """Whether :func:`keep_freed_memory` has changed this process's thresholds (the benchmarks record it per row)."""
    return bool(_outcome) and _outcome[0]


def _set_thresholds() -> bool:
    """The mmap threshold is set first: with the trim threshold set alone, glibc stops raising the mmap threshold
    by itself and every large block is mapped afresh, which is slower than setting neither."""
    if not sys.platform.startswith("linux"):
        return False
    try:
        libc = ctypes.CDLL("libc.so.6")
    except OSError:
        return False
    if not hasattr(libc, "gnu_get_libc_version"):  # another C library (musl): these parameters mean nothing there
        return False
    mallopt = libc.mallopt
    mallopt.argtypes, mallopt.restype = [ctypes.c_int, ctypes.c_int], ctypes.c_int
    return mallopt(M_MMAP_THRESHOLD, MMAP_THRESHOLD_BYTES) == 1 and mallopt(M_TRIM_THRESHOLD,
                                                                             TRIM_THRESHOLD_BYTES) == 1
