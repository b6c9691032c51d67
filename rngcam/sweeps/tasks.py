"""What a sweep or batch task is to a backend: `fn(item, shared) -> dict`, and the result of one
that failed. Both backends (rngcam.sweeps.backend, rngcam.sweeps.ray_backend) stand on this."""

from __future__ import annotations

from collections.abc import Callable

TaskFn = Callable[[object, object], dict]
OnResult = Callable[[int, dict], None]


def failed(message: str) -> dict:
    """The result of a task that raised or whose process died: its status and one line."""
    return {"status": "failed", "message": message}
