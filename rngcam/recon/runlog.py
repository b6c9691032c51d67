"""A run's log: every line `rngcam recon` prints, and its progress lines, timestamped."""

from __future__ import annotations

import threading
import time
from pathlib import Path

from rngcam.recon import checkpoint


class RunLog:
    """recon.log in the output folder: every line the run prints, and the progress lines. Lines are
    held until `open` (the folder is made only once the bundle has been read and checked)."""

    def __init__(self):
        self.fh, self.held, self.lock = None, [], threading.Lock()

    def open(self, out: Path | None) -> None:
        """Write to `out`'s recon.log from here on; without a folder the lines stay in `held`
        (a Result made in memory carries them, and its `save` writes them)."""
        if out is not None:
            out.mkdir(parents=True, exist_ok=True)
            self.fh = open(out / checkpoint.LOG_NAME, "a", encoding="utf-8")  # noqa: SIM115 - closed by close()
            self.fh.writelines(self.held)
            self.fh.flush()
            self.held = []

    def write(self, line: str) -> None:
        text = f"{time.strftime('%H:%M:%S')} {line}\n"
        with self.lock:  # the set-up heartbeat writes from its thread
            if self.fh is None:
                self.held.append(text)
                return
            self.fh.write(text)
            self.fh.flush()

    def close(self) -> None:
        if self.fh is not None:
            self.fh.close()
