"""Where trials and batch items run: one after another in this process, or as Ray tasks.

Both backends take a task function `fn(item, shared) -> dict` (module level, so Ray can ship
it) and return one dict per item in order. A task that crashes its process, or raises, gives
{"status": "failed", "message": ...} for that item; the others go on. Ray is optional
(`pip install 'rngcam[cluster]'`); `make_backend` falls back to in-process runs without it.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Protocol

from rngcam.errors import RngcamError
from rngcam.sweeps.ray_backend import RayBackend
from rngcam.sweeps.tasks import OnResult, TaskFn, failed


class Backend(Protocol):
    name: str
    threads_per_task: int | None  # torch threads a task should use (None: leave as is)

    def map(self, fn: TaskFn, items: list, shared: object = None, on_result: OnResult | None = None) -> list[dict]:
        """fn(item, shared) for every item; results in item order."""

    def close(self) -> None: ...


class SequentialBackend:
    """Runs every task here, in order: the fallback without Ray, and the reference for tests."""

    name = "in-process, one task after another"
    # One torch thread per task in both backends: results are then bit-identical between them,
    # and small fits gain nothing from more (on a loaded machine OpenMP spinning costs 10-60x).
    threads_per_task = 1

    def map(self, fn: TaskFn, items: list, shared: object = None, on_result: OnResult | None = None) -> list[dict]:
        results = []
        for i, item in enumerate(items):
            try:
                res = fn(item, shared)
            except Exception as exc:  # noqa: BLE001 - one bad item must not stop the others
                res = failed(f"{type(exc).__name__}: {exc}".splitlines()[0])
            results.append(res)
            if on_result is not None:
                on_result(i, res)
        return results

    def close(self) -> None:
        pass


def ray_available() -> bool:
    try:
        import ray  # noqa: F401  # optional: cluster extra
    except ImportError:
        return False
    return True


def make_backend(use_ray: bool | None = None, address: str | None = None, num_cpus: int | None = None,
                 gpus_per_task: float = 0.0, echo: Callable[[str], None] = print) -> Backend:
    """Ray when asked for (use_ray=True or an address) or, by default, when installed; else in-process."""
    if use_ray is False:
        if address:
            raise RngcamError("--address needs Ray; drop --no-ray")
        return SequentialBackend()
    if not ray_available():
        if use_ray or address:
            raise RngcamError("Ray is not installed: pip install 'rngcam[cluster]' (or run without --address)")
        echo("Ray is not installed (pip install 'rngcam[cluster]'): running tasks one after another in this process")
        return SequentialBackend()

    return RayBackend(address=address, num_cpus=num_cpus, gpus_per_task=gpus_per_task)
