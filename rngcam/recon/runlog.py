"""A run's log: every line `rngcam recon` prints, and its progress lines, timestamped.

Lines may quote a bundle's text (a capture warning, a label): each is written as one printable
line (control characters escaped), so a newline in a bundle cannot forge a line of the log.
"""

from __future__ import annotations

import os
import stat
import threading
import time
from pathlib import Path

from rngcam.errors import RngcamError
from rngcam.recon import checkpoint
from rngcam.untrusted import open_own, open_untrusted, printable, write_new

LINE_LIMIT = 20_000  # characters of one logged line


def log_line(line: str) -> str:
    """`line` as it is logged: timestamped, one printable line."""
    return f"{time.strftime('%H:%M:%S')} {printable(line, LINE_LIMIT)}\n"


def open_log(path: Path):
    """`path` opened for appending (binary) as the run's own file: a link planted at its name is
    removed (what it names is neither read nor written) and a file with other hard links is
    copied into a file of its own first."""
    try:
        st = os.lstat(path)
    except FileNotFoundError:
        st = None
    if st is not None and stat.S_ISLNK(st.st_mode):
        path.unlink()
    elif st is not None and not stat.S_ISREG(st.st_mode):
        raise RngcamError(f"cannot write the log {path}: it is not a regular file")
    elif st is not None and st.st_nlink > 1:
        with open_own_reading(path) as fh:
            write_new(path, fh.read())
    return open_own(path, "ab", replace=True)


def append_lines(path: Path, lines: list[str]) -> None:
    """Append `lines` (each logged as one printable, timestamp-free line) to the log at `path`,
    when the run has one there."""
    if os.path.lexists(path):
        with open_log(path) as fh:
            fh.write("".join(printable(line, LINE_LIMIT) + "\n" for line in lines).encode("utf-8"))


def open_own_reading(path: Path):
    """`path` opened for reading by descriptor: no link, FIFO or device (`open_untrusted`)."""
    return open_untrusted(path, what="log")


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
            self.fh = open_log(out / checkpoint.LOG_NAME)
            self.fh.write("".join(self.held).encode("utf-8"))
            self.fh.flush()
            self.held = []

    def write(self, line: str) -> None:
        text = log_line(line)
        with self.lock:  # the set-up heartbeat writes from its thread
            if self.fh is None:
                self.held.append(text)
                return
            self.fh.write(text.encode("utf-8"))
            self.fh.flush()

    def close(self) -> None:
        if self.fh is not None:
            self.fh.close()
