"""Keep the memory of freed tensors inside the process.

glibc hands every block above its mmap threshold (at most 32 MiB, adapted at run time) back to
the kernel when it is freed, and trims the heap's free top above 128 KiB. A map or a training
step allocates and frees the same large tensors every call, so each call page-faults them in
again: on the 2-core CPU the kernel's share was 14 of 18 s of ``bench/bench_model.py
--map-only`` and the 10,000 x 32 map took 167-193 ms. Raising both thresholds keeps those pages
mapped and reused: 127-129 ms, kernel time 0.6 s; a training step of 5 x 24 interactions on
10,000-point clouds 0.82 -> 0.58 s (bench/RESEARCH.md, "Where the map's time went"). It replaces
restarting the process with ``GLIBC_TUNABLES=glibc.malloc.hugetlb=1``, which gained less
(138 ms, 0.80 s) and could not reach the ROS nodes.

The cost is resident memory: up to ``trim_mib`` of freed heap stays with the process.
``W2E_DEFAULT_MALLOC=1`` leaves glibc's defaults alone.
"""

from __future__ import annotations

import ctypes
import ctypes.util
import logging
import os
import sys

_M_TRIM_THRESHOLD = -1  # mallopt parameter numbers from glibc's malloc.h
_M_MMAP_THRESHOLD = -3

log = logging.getLogger(__name__)
_applied: tuple[int, int] | None = None


def keep_freed_memory(mmap_mib: int = 256, trim_mib: int = 1024) -> bool:
    """Serve blocks below ``mmap_mib`` from the heap and keep up to ``trim_mib`` of its free top.

    Returns whether glibc took the setting (False on other platforms, other C libraries or when
    ``W2E_DEFAULT_MALLOC`` is set). Idempotent; call it once at a process's start."""
    global _applied
    if _applied == (mmap_mib, trim_mib):
        return True
    if os.environ.get("W2E_DEFAULT_MALLOC") or not sys.platform.startswith("linux"):
        return False
    try:
        libc = ctypes.CDLL(ctypes.util.find_library("c") or "libc.so.6")
        mallopt = libc.mallopt
    except (OSError, AttributeError):  # musl and friends have no mallopt
        return False
    mallopt.argtypes, mallopt.restype = [ctypes.c_int, ctypes.c_int], ctypes.c_int
    # an older glibc may refuse a threshold above 32 MiB: the trim threshold alone is most of
    # the gain for the chunked map (129 of 127 ms), so each is set on its own
    mmap_ok = mallopt(_M_MMAP_THRESHOLD, mmap_mib << 20) == 1
    ok = mallopt(_M_TRIM_THRESHOLD, trim_mib << 20) == 1
    if not (mmap_ok and ok):
        log.debug("mallopt refused a threshold (mmap %s, trim %s)", mmap_ok, ok)
    if ok:
        _applied = (mmap_mib, trim_mib)
    return ok
