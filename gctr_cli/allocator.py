"""Process set-up: let glibc's malloc keep freed memory for the next array.

One registration allocates and frees thousands of short-lived numpy arrays of 0.1-10 MB. By default
glibc hands large free blocks straight back to the kernel (``munmap``, heap trimming), so the next
array of that size is faulted in again page by page, zero-filled by the kernel. In a fresh
``gctr register`` process that cost about 40 ms of a 0.26 s engine run (median ``runtime_s`` 0.26 s
-> 0.22 s on the 20k-point pair of ``make bench-process``; minor page faults of the engine call
21,000 -> 14,500). Raising the two thresholds below keeps freed blocks in the heap for reuse. The
price is that a process holds on to up to :data:`TRIM_THRESHOLD` bytes of free heap after its peak;
the peak itself does not change.

:func:`keep_freed_memory` is called where gctr sets up a process of its own to register pairs:
``gctr register``, the batch pool's workers (and the engine benchmark's per-pair processes, which
measure the engine as those paths run it). The dask LocalCluster that ``gctr batch --executor dask``
starts itself gets the same settings as environment variables (:func:`malloc_environment`), in
place of dask's own default, ``MALLOC_TRIM_THRESHOLD_=65536`` (a dask config that sets the malloc
variables otherwise is kept): with that default every array above 128 kB is mapped and faulted in
afresh, and a pair took 0.29 s instead of 0.18 s (median, the 30 easy pairs of the report set, 2
workers). Workers of an external cluster keep the cluster's settings (see docs/cluster.md). It
changes nothing but the allocator's bookkeeping: the results are bit-identical with and without it.
"""

from __future__ import annotations

import ctypes
import os

__all__ = ["MMAP_THRESHOLD", "TRIM_THRESHOLD", "USER_SETTINGS", "is_set_up", "keep_freed_memory",
           "malloc_environment"]

#: blocks at least this large still get their own ``mmap`` (and go back to the kernel when freed)
MMAP_THRESHOLD = 32 << 20
#: free memory at the top of the heap is returned to the kernel only above this much
TRIM_THRESHOLD = 128 << 20

#: environment variables by which a user tunes glibc's malloc themselves (then gctr leaves it alone)
USER_SETTINGS = ("MALLOC_MMAP_THRESHOLD_", "MALLOC_TRIM_THRESHOLD_")

# mallopt parameters (glibc's malloc.h)
_M_TRIM_THRESHOLD = -1
_M_MMAP_THRESHOLD = -3

_applied: bool | None = None


def keep_freed_memory() -> bool:
    """Set glibc's mmap and trim thresholds for this process (once); True when they are set.

    A no-op returning False on a C library other than glibc (macOS, musl), where ``mallopt`` is
    missing or means something else, and when the user set :data:`USER_SETTINGS`.
    """
    global _applied
    if _applied is None:
        _applied = _set_thresholds()
    return _applied


def is_set_up() -> bool:
    """Whether :func:`keep_freed_memory` set the thresholds in this process."""
    return bool(_applied)


def malloc_environment() -> dict[str, str]:
    """The same settings as environment variables, for worker processes another library starts (the
    dask LocalCluster gctr starts itself: its nanny sets them before the worker process exists, when
    glibc reads them)."""
    return {"MALLOC_MMAP_THRESHOLD_": str(MMAP_THRESHOLD), "MALLOC_TRIM_THRESHOLD_": str(TRIM_THRESHOLD)}


def _set_thresholds() -> bool:
    if any(os.environ.get(name) for name in USER_SETTINGS):
        return False
    try:
        if not os.confstr("CS_GNU_LIBC_VERSION"):
            return False
    except (ValueError, OSError, AttributeError):  # no such name on this platform
        return False
    try:
        mallopt = ctypes.CDLL(None).mallopt
    except (OSError, AttributeError):
        return False
    mallopt.argtypes = (ctypes.c_int, ctypes.c_int)
    mallopt.restype = ctypes.c_int
    mmap_set = mallopt(_M_MMAP_THRESHOLD, MMAP_THRESHOLD)
    trim_set = mallopt(_M_TRIM_THRESHOLD, TRIM_THRESHOLD)
    return bool(mmap_set) and bool(trim_set)
