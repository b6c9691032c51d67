"""Helpers for material that may come from someone else (a bundle, a result folder, a rig).

Text read from such a file is shown as text (`printable`), and files are written into a folder
without following a link someone planted there (`write_new`, `open_own`).
"""

from __future__ import annotations

import contextlib
import os
import re
import tempfile
from pathlib import Path

from rngcam.errors import RngcamError

# C0 and C1 control characters and DEL; a newline or tab from a file is shown escaped too, so one
# line of ours stays one line, and a terminal escape sequence cannot erase or forge what we print.
TEMP_SUFFIX = ".rngcam-tmp"  # our temporary files: .<name>.<random>.rngcam-tmp

_CONTROL = re.compile(r"[\x00-\x1f\x7f-\x9f\u2028\u2029\u202a-\u202e\u2066-\u2069]")


def printable(text: object, limit: int = 500) -> str:
    """`text` as one printable line: control characters escaped (\\n, \\x1b, \\u202e), at most `limit` characters."""
    s = str(text)
    if len(s) > limit:
        s = s[:limit] + "..."
    return _CONTROL.sub(lambda m: m.group().encode("unicode_escape").decode("ascii"), s)


def open_own(path: Path, mode: str = "wb", *, replace: bool = True):
    """Open `path` for writing without following a symlink at its name.

    A link (or any non-regular file) at `path` is refused in one line; with `replace` an existing
    regular file is truncated (the run's own earlier output), otherwise it is refused too.
    Modes: 'wb', 'w', 'ab', 'a'.
    """
    path = Path(path)
    flags = os.O_WRONLY | os.O_CREAT | getattr(os, "O_NOFOLLOW", 0) | getattr(os, "O_CLOEXEC", 0)
    if "a" in mode:
        flags |= os.O_APPEND
    elif replace:
        flags |= os.O_TRUNC
    else:
        flags |= os.O_EXCL
    try:
        st = os.lstat(path)
    except FileNotFoundError:
        st = None
    if st is not None and (not _regular(st) or st.st_nlink > 1):
        raise RngcamError(f"refusing to write {path}: it is a link or not a regular file")
    try:
        fd = os.open(path, flags, 0o644)
    except FileExistsError:
        raise RngcamError(f"refusing to replace {path}: it exists (pass --overwrite to replace it)") from None
    except OSError as exc:
        if exc.errno in (getattr(os, "ELOOP", -1), getattr(os, "EMLINK", -1)):
            raise RngcamError(f"refusing to write {path}: it is a link") from None
        raise
    if not _regular(os.fstat(fd)):
        os.close(fd)
        raise RngcamError(f"refusing to write {path}: not a regular file")
    return os.fdopen(fd, mode)


def write_new(path: Path, data: bytes | str, *, replace: bool = True) -> None:
    """Write `data` (text as UTF-8) to `path` atomically: a fresh temporary file beside it, then a
    rename, which replaces a planted link itself rather than what it points to. Without `replace`
    an existing `path` is refused in one line."""
    path = Path(path)
    if not replace and os.path.lexists(path):
        raise RngcamError(f"refusing to replace {path}: it exists (pass --overwrite to replace it)")
    blob = data.encode("utf-8") if isinstance(data, str) else data
    fd, tmp = tempfile.mkstemp(prefix=f".{path.name}.", suffix=TEMP_SUFFIX, dir=path.parent)
    try:
        with os.fdopen(fd, "wb") as f:
            f.write(blob)
        os.replace(tmp, path)
    except BaseException:
        Path(tmp).unlink(missing_ok=True)
        raise


def temp_beside(path: Path) -> Path:
    """A fresh, uniquely named temporary file beside `path` (created empty, O_EXCL); the caller
    fills it and `os.replace`s it onto `path`, or `clean_temps` removes it on a later run."""
    fd, tmp = tempfile.mkstemp(prefix=f".{Path(path).name}.", suffix=TEMP_SUFFIX, dir=Path(path).parent)
    os.close(fd)
    return Path(tmp)


def clean_temps(folder: Path) -> list[Path]:
    """Remove the temporary files an interrupted write of ours left in `folder` (never following links)."""
    gone = []
    for p in Path(folder).glob(f".*{TEMP_SUFFIX}"):
        if p.is_symlink() or p.is_file():
            p.unlink(missing_ok=True)
            gone.append(p)
    return gone


def _regular(st: os.stat_result) -> bool:
    import stat

    return stat.S_ISREG(st.st_mode)


@contextlib.contextmanager
def replacing(path: Path, *, replace: bool = True):
    """Yield a fresh temporary path beside `path` for a writer that opens files by name (h5py,
    tifffile, PyAV, matplotlib); once it is written it is renamed onto `path` (a planted link is
    replaced, never followed), and on failure removed. Without `replace` an existing `path` is
    refused in one line, before and (atomically, by a hard link) after the write."""
    path = Path(path)
    if not replace and os.path.lexists(path):
        raise RngcamError(f"refusing to replace {path}: it exists (pass --overwrite to replace it)")
    tmp = temp_beside(path)
    try:
        yield tmp
        if replace:
            os.replace(tmp, path)
        else:
            try:
                os.link(tmp, path, follow_symlinks=False)
            except FileExistsError:
                raise RngcamError(f"refusing to replace {path}: it exists (pass --overwrite to replace it)") from None
    finally:
        tmp.unlink(missing_ok=True)


def same_file(a: Path, b: Path) -> bool:
    """True when `a` and `b` name the same file: the same path, or (through links) the same inode."""
    if os.path.abspath(a) == os.path.abspath(b):
        return True
    try:
        return os.path.samefile(a, b)
    except OSError:
        return False
