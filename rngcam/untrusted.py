"""Helpers for material that may come from someone else (a bundle, a result folder, a rig).

Such a file is opened by descriptor, never following a link and never a FIFO or device, and
checked on that descriptor (`open_untrusted`, `read_untrusted`); text read from it is shown as
text (`printable`); files are written into a folder without following a link someone planted
there (`write_new`, `open_own`).
"""

from __future__ import annotations

import contextlib
import errno
import json
import os
import re
import stat
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


class UntrustedFileError(RngcamError):
    """A file from someone else is a link, not a regular file, too large or unreadable."""


_READ_FLAGS = (os.O_RDONLY | getattr(os, "O_NOFOLLOW", 0) | getattr(os, "O_NONBLOCK", 0)
               | getattr(os, "O_CLOEXEC", 0) | getattr(os, "O_NOCTTY", 0))
_DIR_FLAGS = (os.O_RDONLY | getattr(os, "O_DIRECTORY", 0) | getattr(os, "O_NOFOLLOW", 0)
              | getattr(os, "O_CLOEXEC", 0))


def _open_below(path: Path, within: Path) -> int:
    """A descriptor for `path`, opened one component at a time from `within` (the folder the user
    named) so that no link anywhere below `within` is followed."""
    parts = Path(os.path.relpath(os.path.abspath(path), os.path.abspath(within))).parts
    if not parts or parts[0] == os.pardir:
        raise UntrustedFileError(f"{printable(path)}: not inside {printable(within)}")
    dir_fd = os.open(within, _DIR_FLAGS & ~getattr(os, "O_NOFOLLOW", 0))
    try:
        for part in parts[:-1]:
            try:
                nxt = os.open(part, _DIR_FLAGS, dir_fd=dir_fd)
            except (NotADirectoryError, OSError) as exc:
                if stat.S_ISLNK(os.lstat(part, dir_fd=dir_fd).st_mode):
                    raise OSError(errno.ELOOP, "a link") from None
                raise exc from None
            os.close(dir_fd)
            dir_fd = nxt
        return os.open(parts[-1], _READ_FLAGS, dir_fd=dir_fd)
    finally:
        os.close(dir_fd)


def open_untrusted(path: str | os.PathLike, max_bytes: int | None = None, *, what: str = "file",
                   within: str | os.PathLike | None = None, error: type[RngcamError] = UntrustedFileError):
    """Open a file that may come from someone else for reading, as a binary file object.

    The name is opened once, by descriptor (O_NOFOLLOW: a symlink at the name is refused;
    O_NONBLOCK: a FIFO cannot block the open), and the checks are made on that descriptor
    (`fstat`: only a regular file; its size at most `max_bytes`), so nothing can be swapped in
    between the check and the read: read from the returned object only. With `within` (the folder
    the user named), no link in any folder between it and `path` is followed either. Anything
    refused raises `error` (one line naming the file and the reason). Read at most `max_bytes`
    (the file may still grow): `read_untrusted` does.
    """
    path = Path(path)
    shown = printable(path)
    try:
        fd = _open_below(path, Path(within)) if within is not None else os.open(path, _READ_FLAGS)
    except FileNotFoundError:
        raise error(f"{what} not found: {shown}") from None
    except OSError as exc:
        if exc.errno in (errno.ELOOP, errno.EMLINK):
            raise error(f"refusing to read {shown}: it is a link (only plain files are read; name the file it "
                        "points to)") from None
        if exc.errno == errno.ENOTDIR:
            raise error(f"{what} not found: {shown} (a part of its path is not a folder)") from None
        if exc.errno in (errno.ENXIO, errno.EWOULDBLOCK):
            raise error(f"refusing to read {shown}: it is not a regular file") from None
        raise error(f"cannot read {shown}: {printable(exc.strerror or exc, 100)}") from None
    try:
        st = os.fstat(fd)
        if not stat.S_ISREG(st.st_mode):
            kind = "a folder" if stat.S_ISDIR(st.st_mode) else "not a regular file (a FIFO, device or socket)"
            raise error(f"refusing to read {shown}: it is {kind}")
        if max_bytes is not None and st.st_size > max_bytes:
            raise error(f"refusing to read {shown}: {st.st_size:,} bytes, above the limit of {max_bytes:,} "
                        f"for a {what}")
        if hasattr(os, "set_blocking"):
            os.set_blocking(fd, True)
        return os.fdopen(fd, "rb")
    except BaseException:
        os.close(fd)
        raise


def read_untrusted(path: str | os.PathLike, max_bytes: int, *, what: str = "file",
                   within: str | os.PathLike | None = None,
                   error: type[RngcamError] = UntrustedFileError) -> bytes:
    """The bytes of a file from someone else, through `open_untrusted`: at most `max_bytes`
    (a file that grows past it while read is refused too)."""
    with open_untrusted(path, max_bytes, what=what, within=within, error=error) as fh:
        try:
            data = fh.read(max_bytes + 1)
        except OSError as exc:
            raise error(f"cannot read {printable(path)}: {printable(exc.strerror or exc, 100)}") from None
    if len(data) > max_bytes:
        raise error(f"refusing to read {printable(path)}: above the limit of {max_bytes:,} bytes for a {what}")
    return data


def read_untrusted_text(path: str | os.PathLike, max_bytes: int, *, what: str = "file",
                        within: str | os.PathLike | None = None,
                        error: type[RngcamError] = UntrustedFileError) -> str:
    """`read_untrusted` decoded as UTF-8 (undecodable bytes shown as U+FFFD)."""
    return read_untrusted(path, max_bytes, what=what, within=within, error=error).decode("utf-8", "replace")


MAX_NESTING = 64  # levels of lists and mappings in JSON or YAML from a file (rngcam writes < 10)
MAX_YAML_CHARS = 256 * 2**10  # a rig's YAML: rigs are a few KiB; PyYAML takes seconds per MiB


def load_json(text: str | bytes, what: str, *, max_nesting: int = MAX_NESTING,
              error: type[RngcamError] = UntrustedFileError):
    """JSON text from a file parsed, and its nesting checked (`error`, one line naming `what`,
    when it is not JSON or nests deeper than `max_nesting`)."""
    try:
        value = json.loads(text)
    except (ValueError, RecursionError) as exc:  # RecursionError: deeper than Python's stack
        reason = str(exc).splitlines()[0] if str(exc) else "nested too deeply"
        raise error(f"{printable(what)} is not valid JSON ({printable(reason, 200)})") from None
    if nesting(value) > max_nesting:
        raise error(f"{printable(what)} nests deeper than {max_nesting} levels; refused")
    return value


def nesting(value) -> int:
    """How deeply lists, tuples and dicts nest in `value` (0: a scalar), without recursion."""
    deepest, stack = 0, [(value, 1)]
    while stack:
        item, depth = stack.pop()
        children = item.values() if isinstance(item, dict) else item if isinstance(item, (list, tuple)) else None
        if children is None:
            continue
        deepest = max(deepest, depth)
        stack.extend((c, depth + 1) for c in children)
    return deepest


def check_yaml_shape(text: str, what: str, *, max_chars: int = MAX_YAML_CHARS, max_nesting: int = MAX_NESTING,
                     error: type[RngcamError] = UntrustedFileError) -> None:
    """`error` (one line naming `what`) when YAML `text` is longer than `max_chars` or nests deeper
    than `max_nesting`, found from the parser's events (no recursion, nothing built); a syntax
    error raises yaml.YAMLError, for the caller to say where."""
    import yaml  # heavy: yaml, kept off the command line's start (every command imports this module)

    if len(text) > max_chars:
        raise error(f"{printable(what)}: {len(text):,} characters of YAML, above the limit of {max_chars:,}")
    depth = 0
    for event in yaml.parse(text, Loader=getattr(yaml, "CSafeLoader", yaml.SafeLoader)):
        if isinstance(event, (yaml.MappingStartEvent, yaml.SequenceStartEvent)):
            depth += 1
            if depth > max_nesting:
                raise error(f"{printable(what)}: YAML nested deeper than {max_nesting} levels; refused")
        elif isinstance(event, (yaml.MappingEndEvent, yaml.SequenceEndEvent)):
            depth -= 1


def load_yaml(text: str, what: str, *, error: type[RngcamError] = UntrustedFileError):
    """YAML text from a file (a rig, a bundle's rig text) parsed safely after `check_yaml_shape`;
    `error` (one line) when it is too long, too deep or not YAML."""
    import yaml  # heavy: yaml, kept off the command line's start (every command imports this module)

    try:
        check_yaml_shape(text, what, error=error)
        return yaml.safe_load(text)
    except (yaml.YAMLError, RecursionError) as exc:
        problem = getattr(exc, "problem", None) or (str(exc).splitlines() or ["nested too deeply"])[0]
        raise error(f"{printable(what)}: not valid YAML ({printable(problem, 200)})") from None


def same_open_file(fh, path: str | os.PathLike) -> bool:
    """True when `path` (not following a link at its name) is still the file open as `fh`."""
    try:
        a, b = os.fstat(fh.fileno()), os.lstat(path)
    except OSError:
        return False
    return (a.st_dev, a.st_ino) == (b.st_dev, b.st_ino)


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
        if exc.errno in (errno.ELOOP, errno.EMLINK):
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
