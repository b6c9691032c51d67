"""Where shared data lives: the folder `shared/data` next to the repository, or $RNGCAM_DATA."""

from __future__ import annotations

import os
from pathlib import Path


def shared_data() -> Path:
    """The shared data folder (PSFs, video clips); the RNGCAM_DATA environment variable overrides it."""
    override = os.environ.get("RNGCAM_DATA")
    if override:
        return Path(override).expanduser().resolve()
    return (Path(__file__).resolve().parents[1] / ".." / "shared" / "data").resolve()
