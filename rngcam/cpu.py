"""This machine's idle CPUs, and how many torch threads a run takes on them.

torch's CPU thread pool assumes its cores are free. When other processes keep them busy, its
threads wait for each other at every parallel region behind preempted peers, and a run slows
several-fold where one thread would only share (bench/realistic.md, "Threads under load"). So
`auto` takes no more threads than the cores other processes leave idle, measured over a short
window when the run starts.
"""

from __future__ import annotations

import contextlib
import math
import os
import time
from collections.abc import Callable, Iterator
from pathlib import Path

import torch

SAMPLE_S = 0.1  # the window over which other processes' CPU use is measured


def usable_cpus() -> list[int]:
    """The CPUs this process may run on (its affinity), else all of them."""
    try:
        return sorted(os.sched_getaffinity(0))
    except (AttributeError, OSError):
        return list(range(os.cpu_count() or 1))


def _cpu_times(cpus: list[int]) -> dict[int, tuple[int, int]]:
    """(busy, total) jiffies per CPU in `cpus` from /proc/stat; {} where it cannot be read."""
    times = {}
    try:
        lines = Path("/proc/stat").read_text().splitlines()
    except OSError:
        return {}
    for line in lines:
        name, *fields = line.split()
        if not name.startswith("cpu") or name == "cpu" or not name[3:].isdigit():
            continue
        cpu = int(name[3:])
        if cpu in cpus:
            values = [int(v) for v in fields[:8]]
            idle = values[3] + values[4]  # idle + iowait
            times[cpu] = (sum(values) - idle, sum(values))
    return times


def busy_cores(sample_s: float = SAMPLE_S) -> float | None:
    """How many of this process's usable CPUs other work kept busy over `sample_s` (this process
    is waiting meanwhile); None where /proc/stat cannot be read."""
    cpus = usable_cpus()
    before = _cpu_times(cpus)
    if not before:
        return None
    time.sleep(sample_s)
    after = _cpu_times(cpus)
    busy = 0.0
    for cpu, (b0, t0) in before.items():
        b1, t1 = after.get(cpu, (b0, t0))
        busy += (b1 - b0) / (t1 - t0) if t1 > t0 else 0.0
    return busy


def choose_threads(threads: int | str = "auto", busy: Callable[[], float | None] | None = None) -> tuple[int, str]:
    """The torch thread count for a run, and a line saying why where `auto` lowered it ('' otherwise).

    An int is taken as it is. `auto`: torch's current count (what the caller or OMP_NUM_THREADS set),
    lowered to the usable CPUs that other processes leave idle, at least one."""
    if threads != "auto":
        return int(threads), ""
    current = torch.get_num_threads()
    cpus = len(usable_cpus())
    if current <= 1:
        return current, ""
    taken = (busy or busy_cores)()
    if taken is None:
        return current, ""
    idle = max(0.0, min(current, cpus) - max(0.0, taken - max(0, cpus - current)))
    n = max(1, min(current, math.floor(idle + 0.5)))
    if n >= current:
        return current, ""
    return n, (f"threads: {n} of {current} ({taken:.1f} of {cpus} CPUs busy with other work; "
               f"a torch thread on a busy CPU stalls the others; the threads setting chooses the count)")


@contextlib.contextmanager
def torch_threads(n: int) -> Iterator[None]:
    """torch runs `n` intra-op threads inside the block; the caller's count is restored after."""
    before = torch.get_num_threads()
    if n != before:
        torch.set_num_threads(n)
    try:
        yield
    finally:
        if torch.get_num_threads() != before:
            torch.set_num_threads(before)
