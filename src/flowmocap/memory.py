"""The process's memory: its resident size, and handing freed C-heap pages back.

MediaPipe's graphs allocate and free about 0.6 MB per frame of small blocks in their
worker threads; glibc's allocator keeps the freed pages in its arenas, so over a long
video the detection pass's resident size creeps up by far more than it holds (about
90 kB a frame on a 640x480 video, measured). :func:`release_free_memory` (glibc's
``malloc_trim``) hands them back; the detection pass calls it every few dozen frames and
once it has closed its detectors.
"""

from __future__ import annotations

import ctypes
import ctypes.util
import functools
import sys


@functools.cache
def _libc():
    if not sys.platform.startswith("linux"):
        return None
    try:
        libc = ctypes.CDLL(ctypes.util.find_library("c") or "libc.so.6")
        trim = libc.malloc_trim  # glibc only (musl has none)
    except (OSError, AttributeError):
        return None
    trim.argtypes, trim.restype = [ctypes.c_size_t], ctypes.c_int
    return trim


def release_free_memory() -> bool:
    """Give the C heap's free pages back to the system (glibc's ``malloc_trim(0)``,
    a few milliseconds). Returns False where there is no such call (not glibc): then
    nothing happens."""
    trim = _libc()
    if trim is None:
        return False
    trim(0)
    return True


def resident_mb() -> float:
    """This process's resident memory (``VmRSS``) in MB, or NaN where ``/proc`` has none."""
    try:
        with open("/proc/self/status") as f:
            for line in f:
                if line.startswith("VmRSS:"):
                    return int(line.split()[1]) / 1024
    except OSError:
        pass
    return float("nan")
