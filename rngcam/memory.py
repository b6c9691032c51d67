"""This process's memory figures, honest under fork/exec.

Peak memory is read from /proc/self/status (VmHWM: the high-water mark of this process's own
address space, which starts afresh at exec). `ru_maxrss` is only the fallback where /proc is
missing: Linux carries the parent's peak over fork and exec into it, so a child of a large
process reports at least the parent's size.
"""

from __future__ import annotations

import ctypes
import functools
import gc
import os
import resource
import threading
from collections.abc import Iterator
from contextlib import contextmanager
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


@functools.cache
def _glibc():
    """The process's own C library where it is glibc (malloc_trim and mallopt), else None; looked up
    once (heap_reuse calls it twice a solver step)."""
    try:
        libc = ctypes.CDLL(None)
        libc.malloc_trim, libc.mallopt  # noqa: B018 (glibc only)
    except (OSError, AttributeError):
        return None
    return libc


def release_free_memory(collect: bool = True) -> None:
    """Hand the C heap's free pages back to the system (glibc's malloc_trim, well under a
    millisecond; nothing elsewhere), after collecting garbage cycles with `collect` (~0.1 s).
    Tensors under glibc's mmap threshold (up to 32 MiB), and every tensor inside `heap_reuse`,
    live in the heap; once freed, their pages stay in RSS until trimmed."""
    if collect:
        gc.collect()
    libc = _glibc()
    if libc is not None:
        libc.malloc_trim(0)


# glibc's largest mmap threshold: outside `heap_reuse` a buffer at least this large is mapped afresh,
# so the heap's free pages would add to the peak beside it; a smaller one may reuse them.
LARGE_BUFFER_BYTES = 32 * 2**20


def release_before(nbytes: int) -> None:
    """`release_free_memory(collect=False)` before a buffer of `nbytes` comes, where that buffer is
    large enough to be mapped afresh. At 64 px a trim before each stop test's video cost the next
    step ~10 ms of page faults (4 % of the run; bench/convergence.md)."""
    if nbytes >= LARGE_BUFFER_BYTES:
        release_free_memory(collect=False)


# mallopt's parameters (glibc's malloc.h) and the defaults they are handed back
_M_TRIM_THRESHOLD, _M_MMAP_THRESHOLD, _M_MMAP_MAX = -1, -3, -4
_GLIBC_MMAP_MAX = 65536
_GLIBC_TRIM_THRESHOLD = 128 * 1024
_reuse_lock = threading.Lock()
_reuse_depth = 0


def _mallopt(param: int, value: int) -> None:
    libc = _glibc()
    if libc is not None:
        libc.mallopt(param, value)


@contextmanager
def heap_reuse() -> Iterator[None]:
    """For the duration, every C allocation comes from the heap and a freed one stays there for the
    next (glibc's mallopt: no mmap, no trimming on free); `release_free_memory` hands the pages back.
    glibc maps a buffer over 32 MiB afresh and unmaps it on free, so at 228x342 each step's
    temporaries were faulted in again page by page: 0.3-0.4 M faults and 0.7-0.9 s of system time a
    2.5 s step (bench/convergence.md). Around steps only: around a set-up at 456x684 the heap kept
    blocks it could not reuse and the peak rose 19 %. Nested and concurrent uses (an ensemble's lanes)
    share one setting; the last to leave restores glibc's (its mmap threshold then stays where the
    set-up's frees had raised it: glibc stops adjusting it once a threshold is set)."""
    global _reuse_depth
    with _reuse_lock:
        _reuse_depth += 1
        if _reuse_depth == 1:
            _mallopt(_M_MMAP_MAX, 0)
            _mallopt(_M_TRIM_THRESHOLD, 2**31 - 1)
    try:
        yield
    finally:
        with _reuse_lock:
            _reuse_depth -= 1
            if _reuse_depth == 0:
                _mallopt(_M_MMAP_MAX, _GLIBC_MMAP_MAX)
                _mallopt(_M_TRIM_THRESHOLD, _GLIBC_TRIM_THRESHOLD)


# A one-off phase's buffers from this size up are mapped afresh (and handed back on free)
RETURNED_BUFFER_BYTES = 2**20


@contextmanager
def returned_on_free() -> Iterator[None]:
    """For one-off work (a run's last estimate, its metrics and outputs): the heap's free pages are
    handed back before and after, and a C allocation of RETURNED_BUFFER_BYTES or more that the heap's
    free blocks cannot hold is mapped afresh and handed back when freed (glibc's mmap threshold), so a
    phase's temporaries do not stay beside the next phase's: at the paper grid the finish's phases had
    raised the process's peak step by step (bench/convergence.md). The threshold is left alone while
    `heap_reuse` holds the setting; glibc's largest (LARGE_BUFFER_BYTES) is set back after."""
    with _reuse_lock:
        active = _reuse_depth == 0
        if active:
            _mallopt(_M_MMAP_THRESHOLD, RETURNED_BUFFER_BYTES)
    release_free_memory(collect=False)
    try:
        yield
    finally:
        if active:
            with _reuse_lock:
                _mallopt(_M_MMAP_THRESHOLD, LARGE_BUFFER_BYTES)
        release_free_memory(collect=False)
