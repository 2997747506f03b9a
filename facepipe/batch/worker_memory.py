"""glibc's allocator on a Dask worker: freed chunk-sized arrays kept for the next chunk.

Dask's nanny starts every worker with ``MALLOC_TRIM_THRESHOLD_=65536`` (its
``distributed.nanny.pre-spawn-environ``, so that freed memory goes back to the system and the
worker's memory reading stays low). Setting that variable also switches off glibc's dynamic mmap
threshold, which would otherwise rise to the size of the arrays a program frees: every array
over 128 KiB (a chunk's positions, frames and details: megabytes each) is then a fresh ``mmap``
whose pages the kernel faults in and zeroes, and is unmapped when freed, chunk after chunk.
Measured on sample-rig takes (20k vertices, 200 frames): ten times the page faults and 60 %
more CPU per take than the same replay in a plain process with the NumPy backend; with OpenCL
on PoCL, 334k page faults a take instead of 8k and 1.9 CPU-seconds instead of 1.1.

:func:`reuse_freed_arrays` sets the two thresholds to where glibc's dynamic rule would take
them for arrays up to its own ceiling (32 MiB on 64-bit systems; larger arrays are mapped and
unmapped as before): arrays up to that size are reused from the heap, and at most twice that
much free memory stays at the top of the heap. Elsewhere (not glibc) it does nothing.
"""

from __future__ import annotations

import ctypes
import ctypes.util
import platform
import threading

# mallopt parameters, from glibc's <malloc.h>
M_TRIM_THRESHOLD = -1
M_MMAP_THRESHOLD = -3
#: glibc's DEFAULT_MMAP_THRESHOLD_MAX on 64-bit systems: the most its dynamic threshold reaches
MMAP_THRESHOLD = 32 << 20
#: glibc's dynamic rule keeps the trim threshold at twice the mmap threshold
TRIM_THRESHOLD = 2 * MMAP_THRESHOLD

_lock = threading.Lock()
_done: bool | None = None


def reuse_freed_arrays() -> bool:
    """Set this process's malloc thresholds (once); whether they were set."""
    global _done
    with _lock:
        if _done is None:
            _done = _set_thresholds()
        return _done


def _set_thresholds() -> bool:
    if platform.system() != "Linux" or platform.libc_ver()[0] != "glibc":
        return False
    try:
        libc = ctypes.CDLL(ctypes.util.find_library("c") or "libc.so.6")
    except OSError:
        return False
    # mallopt returns 1 on success
    return bool(libc.mallopt(M_MMAP_THRESHOLD, MMAP_THRESHOLD)) and bool(libc.mallopt(M_TRIM_THRESHOLD, TRIM_THRESHOLD))
