"""Independent fits stepped side by side: one Python thread each, one torch thread per operation.

At 64 px a fit's step is thousands of small operations; torch's second thread buys little on them,
while two fits in two threads, each single-threaded, share the cores well (bench/convergence.md
has the figures). The fits must
share no mutable state: each has its own fields, optimiser and random generator, so a fit's
trajectory is the same whether it steps alone or beside another.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from concurrent.futures import ThreadPoolExecutor, wait
from typing import TypeVar

import torch

T = TypeVar("T")


def lane_count(jobs: int) -> int:
    """How many jobs a round runs side by side: one per torch thread the run was given."""
    return max(1, min(jobs, torch.get_num_threads()))


class Lanes:
    """Runs a round of jobs, each in its own thread with torch at one thread meanwhile; a single
    job runs in the calling thread with torch's threads as they are."""

    def __init__(self):
        self._pool: ThreadPoolExecutor | None = None
        self._width = 0

    def run(self, jobs: Sequence[Callable[[], T]]) -> list[T]:
        if len(jobs) <= 1:
            return [job() for job in jobs]
        if self._pool is None or self._width < len(jobs):
            self.close()
            self._pool, self._width = ThreadPoolExecutor(len(jobs), thread_name_prefix="rngcam-lane"), len(jobs)
        threads = torch.get_num_threads()
        torch.set_num_threads(1)
        try:
            futures = [self._pool.submit(job) for job in jobs]
            try:
                wait(futures)
            except BaseException:  # an interrupt: no job may still change its fit once the caller goes on
                wait(futures)
                raise
            return [f.result() for f in futures]
        finally:
            torch.set_num_threads(threads)

    def close(self) -> None:
        if self._pool is not None:
            self._pool.shutdown(wait=True)
            self._pool = None
