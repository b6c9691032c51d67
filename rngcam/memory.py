"""This process's memory figures, honest under fork/exec.

Peak memory is read from /proc/self/status (VmHWM: the high-water mark of this process's own
address space, which starts afresh at exec). `ru_maxrss` is only the fallback where /proc is
missing: Linux carries the parent's peak over fork and exec into it, so a child of a large
process reports at least the parent's size.
"""

from __future__ import annotations

import ctypes
import gc
import os
import resource
from pathlib import Path


def _status_kib(field: str) -> int | None:
    try:
        for line in Path("/proc/self/status").read_text().splitlines():
            if line.startswith(field + ":"):
                return int(line.split()[1])
    except OSError:
        pass
    return None


def peak_rss_bytes() -> int:
    """This process's peak resident set size (VmHWM), or ru_maxrss where /proc is missing."""
    kib = _status_kib("VmHWM")
    return kib * 1024 if kib is not None else resource.getrusage(resource.RUSAGE_SELF).ru_maxrss * 1024


def mapped_file_bytes() -> int:
    """This process's resident file-backed pages now (RssFile: mostly its shared libraries; 0 where
    /proc is missing). How many of a library's pages the kernel maps on a fault depends on the page
    cache, not on the program (more right after the libraries were installed: bench/large_grids.md), so a
    peak compared with a prediction subtracts them."""
    return (_status_kib("RssFile") or 0) * 1024


def current_rss_bytes() -> int:
    """This process's resident set size now (VmRSS; 0 where /proc is missing)."""
    return (_status_kib("VmRSS") or 0) * 1024


def total_memory_bytes() -> int:
    """This machine's physical memory (MemTotal; sysconf where /proc is missing; 8 GiB if neither)."""
    try:
        for line in Path("/proc/meminfo").read_text().splitlines():
            if line.startswith("MemTotal:"):
                return int(line.split()[1]) * 1024
    except (OSError, ValueError, IndexError):
        pass
    try:
        return int(os.sysconf("SC_PAGE_SIZE") * os.sysconf("SC_PHYS_PAGES"))
    except (ValueError, OSError, AttributeError):
        return 8 * 2**30


def release_free_memory(collect: bool = True) -> None:
    """Hand the C heap's free pages back to the system (glibc's malloc_trim, well under a
    millisecond; nothing elsewhere), after collecting garbage cycles with `collect` (~0.1 s).
    Tensors under glibc's mmap threshold (up to 32 MiB, e.g. a coarse level's videos, a step's
    temporaries at 228x342) live in the heap; once freed, their pages stay in RSS until trimmed."""
    if collect:
        gc.collect()
    try:
        trim = ctypes.CDLL(None).malloc_trim  # the process's own libc
    except (OSError, AttributeError):  # not glibc
        return
    trim(0)


# glibc's largest mmap threshold: a buffer at least this large is mapped afresh, so the heap's free
# pages would add to the peak beside it; a smaller one may reuse them.
LARGE_BUFFER_BYTES = 32 * 2**20


def release_before(nbytes: int) -> None:
    """`release_free_memory(collect=False)` before a buffer of `nbytes` comes, where that buffer is
    large enough to be mapped afresh. At 64 px a trim before each stop test's video cost the next
    step ~10 ms of page faults (4 % of the run; bench/convergence.md)."""
    if nbytes >= LARGE_BUFFER_BYTES:
        release_free_memory(collect=False)
