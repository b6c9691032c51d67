"""Reading an HDF5 file that may come from someone else (a bundle, a recon.h5, a calibration file).

HDF5 can point outside the file: a dataset's bytes may live in another file (external storage,
absolute paths allowed), a link may name an object of another file (external link) or another
path (soft link), and a virtual dataset maps other files' datasets. Any of these would let a
shared file read the reader's own files, so `open_untrusted` walks the whole file once and
refuses it, in one line naming what it found, unless every object is reached by hard links and
every dataset keeps its bytes in the file. Shapes and dtypes are believed only after
`checked_dataset` compared them with limits, before anything is read.
"""

from __future__ import annotations

import math
from pathlib import Path

import h5py
import numpy as np

from rngcam.errors import RngcamError
from rngcam.untrusted import printable

MAX_SIDE = 8192  # pixels: the largest frame (or PSF) side the rig's cameras deliver
MAX_CHANNELS = 4
MAX_OBJECTS = 10_000  # groups and datasets in one file
MAX_DEPTH = 16
MAX_ATTR_ELEMENTS = 1_000_000  # elements (or bytes of text) in one attribute
MEMORY_FRACTION = 0.8  # of the machine's memory: the most one file's arrays may declare


class UnsafeFileError(RngcamError):
    """An HDF5 file points outside itself, or declares more than it may."""


def memory_limit_bytes() -> int:
    """The most bytes one array of a shared file may declare: a fraction of this machine's memory."""
    from rngcam.memory import total_memory_bytes

    return int(MEMORY_FRACTION * total_memory_bytes())


def audit(f: h5py.File, path: Path) -> None:
    """Refuse a soft/external link, external storage or a virtual dataset anywhere in `f`."""
    seen: set = set()
    count = 0
    stack: list[tuple[h5py.Group, int]] = [(f, 0)]
    while stack:
        group, depth = stack.pop()
        if depth > MAX_DEPTH:
            raise UnsafeFileError(f"{path}: groups nested deeper than {MAX_DEPTH} levels")
        for name in group:
            count += 1
            if count > MAX_OBJECTS:
                raise UnsafeFileError(f"{path}: more than {MAX_OBJECTS:,} objects")
            where = printable(f"{group.name.rstrip('/')}/{name}", 200)
            link = group.get(name, getlink=True)
            if isinstance(link, h5py.ExternalLink):
                raise UnsafeFileError(f"{path}: '{where}' is an external link (to another file); refused")
            if isinstance(link, h5py.SoftLink):
                raise UnsafeFileError(f"{path}: '{where}' is a soft link; only hard links are read")
            if not isinstance(link, h5py.HardLink):
                raise UnsafeFileError(f"{path}: '{where}' is a link of an unknown kind; refused")
            obj = group[name]
            if isinstance(obj, h5py.Dataset):
                _audit_dataset(obj, where, path)
            elif isinstance(obj, h5py.Group):
                addr = h5py.h5o.get_info(obj.id).addr
                if addr in seen:  # a hard link back up the tree: a loop, walked once
                    continue
                seen.add(addr)
                stack.append((obj, depth + 1))


def _audit_dataset(d: h5py.Dataset, where: str, path: Path) -> None:
    if d.is_virtual:
        raise UnsafeFileError(f"{path}: '{where}' is a virtual dataset (data mapped from other files); refused")
    if d.id.get_create_plist().get_external_count() > 0:
        raise UnsafeFileError(f"{path}: '{where}' keeps its data in an external file; refused")


def open_untrusted(path: str | Path, what: str = "HDF5 file") -> h5py.File:
    """Open `path` read-only after checking it points nowhere outside itself (UnsafeFileError, one
    line, otherwise; RngcamError when it cannot be opened at all)."""
    path = Path(path)
    try:
        f = h5py.File(path, "r")
    except OSError as exc:
        reason = str(exc).splitlines()[0] if str(exc) else type(exc).__name__
        raise RngcamError(f"{path} is not a readable {what} ({reason})") from None
    try:
        audit(f, path)
    except UnsafeFileError:
        f.close()
        raise
    except (OSError, RuntimeError, KeyError, ValueError, TypeError, RecursionError) as exc:
        f.close()
        reason = str(exc).splitlines()[0] if str(exc) else type(exc).__name__
        raise RngcamError(f"{path} is damaged ({printable(reason, 200)})") from None
    return f


def elements(shape: tuple[int, ...]) -> int:
    return math.prod(int(s) for s in shape)


def checked_dataset(group: h5py.Group, name: str, max_elements: int, dtypes: str = "uifb",
                    ndims: tuple[int, ...] | None = None, sides: tuple[int, ...] = (),
                    channel_axis: int | None = None) -> h5py.Dataset:
    """`group[name]` as a dataset whose declared shape and dtype are within limits and whose bytes
    are in the file, nothing read yet; UnsafeFileError (one line) otherwise. `dtypes`: allowed
    numpy kinds; `sides`: axes (rows, columns) of at most MAX_SIDE; `channel_axis`: an axis of at
    most MAX_CHANNELS."""
    where = printable(f"{group.name.rstrip('/')}/{name}", 200)
    link = group.get(name, getlink=True)
    if link is None:
        raise UnsafeFileError(f"missing dataset '{where}'")
    if not isinstance(link, h5py.HardLink):
        raise UnsafeFileError(f"'{where}' is not a plain (hard-linked) object; refused")
    d = group[name]
    if not isinstance(d, h5py.Dataset):
        raise UnsafeFileError(f"'{where}' is not a dataset")
    _audit_dataset(d, where, Path(group.file.filename))
    check_shape(where, d.shape, d.dtype, max_elements, dtypes, ndims, sides, channel_axis)
    _check_stored(d, where)
    return d


COMPRESSION_RATIO = 1100  # above what gzip (about 1030:1 at best) or LZF reach on any data


def _check_stored(d: h5py.Dataset, where: str) -> None:
    """UnsafeFileError when the file holds far fewer bytes than the dataset declares: data never
    written (a crafted shape over empty storage) or a compressed size no compressor reaches."""
    declared = elements(d.shape) * d.dtype.itemsize
    if declared == 0:
        return
    stored = d.id.get_storage_size()
    plist = d.id.get_create_plist()
    filters = {plist.get_filter(i)[0] for i in range(plist.get_nfilters())}
    packed = bool(filters - {h5py.h5z.FILTER_SHUFFLE, h5py.h5z.FILTER_FLETCHER32})
    floor = declared // COMPRESSION_RATIO if packed else declared
    if stored < floor:
        raise UnsafeFileError(f"'{where}' declares {_size(declared)} ({tuple(d.shape)} {d.dtype}) but the "
                              f"file stores {_size(stored)} of it; refused")


def _size(n: int) -> str:
    return f"{n / 2**30:,.1f} GiB" if n >= 2**30 else f"{n:,} bytes"


def check_shape(where: str, shape, dtype, max_elements: int, dtypes: str = "uifb",
                ndims: tuple[int, ...] | None = None, sides: tuple[int, ...] = (),
                channel_axis: int | None = None) -> None:
    """UnsafeFileError (one line) when a declared `shape`/`dtype` is past the limits."""
    if shape is None:
        raise UnsafeFileError(f"'{where}' has no data (an empty dataspace)")
    shape = tuple(int(s) for s in shape)
    try:
        dtype = np.dtype(dtype)
    except TypeError:
        raise UnsafeFileError(f"'{where}' has a dtype numpy cannot read") from None
    if dtype.kind not in dtypes or dtype.itemsize > 8 or dtype.fields is not None or dtype.subdtype:
        raise UnsafeFileError(f"'{where}' has dtype {dtype}, expected one of kinds {dtypes!r}")
    if ndims is not None and len(shape) not in ndims:
        raise UnsafeFileError(f"'{where}' has shape {shape}, expected {' or '.join(map(str, ndims))} dimensions")
    if len(shape) >= 2 and any(-len(shape) <= a < len(shape) and shape[a] > MAX_SIDE for a in sides):
        raise UnsafeFileError(f"'{where}' declares shape {shape}: a side above {MAX_SIDE:,} px")
    if channel_axis is not None and channel_axis < len(shape) and shape[channel_axis] > MAX_CHANNELS:
        raise UnsafeFileError(f"'{where}' declares shape {shape}: more than {MAX_CHANNELS} channels")
    n = elements(shape)
    if n > max_elements:
        raise UnsafeFileError(f"'{where}' declares shape {shape} ({n:,} elements), above the limit of "
                              f"{max_elements:,}")
    if n * dtype.itemsize > memory_limit_bytes():
        raise UnsafeFileError(f"'{where}' declares shape {shape} of {dtype} ({_size(n * dtype.itemsize)}), "
                              "more than this machine's memory allows")


def read_small(group: h5py.Group, name: str, max_elements: int = 1_000_000, dtypes: str = "uifb",
               ndims: tuple[int, ...] | None = None) -> np.ndarray:
    """A small dataset read whole after `checked_dataset`."""
    return checked_dataset(group, name, max_elements, dtypes, ndims)[()]


def check_attr(obj, name: str) -> None:
    """UnsafeFileError when attribute `name` of `obj` declares more than MAX_ATTR_ELEMENTS
    (elements, or bytes of a fixed-length string), before it is read."""
    aid = obj.attrs.get_id(name)
    shape = aid.shape or ()
    n = elements(shape) if shape else 1
    size = n * max(1, aid.dtype.itemsize)
    if n > MAX_ATTR_ELEMENTS or size > 16 * MAX_ATTR_ELEMENTS:
        where = printable(f"{obj.name}@{name}", 200)
        raise UnsafeFileError(f"attribute '{where}' declares {n:,} elements ({size:,} bytes); refused")


def file_format(path: str | Path) -> str:
    """An HDF5 file's `format` attribute (rngcam-bundle, rngcam-recon, rngcam-calibration), or ''
    where the file is not HDF5, is damaged or has none; only that attribute is read, checked first."""
    try:
        with h5py.File(path, "r") as f:
            if "format" not in f.attrs:
                return ""
            check_attr(f, "format")
            value = f.attrs["format"]
    except (OSError, ValueError, TypeError, KeyError, RuntimeError, RngcamError):  # damaged: not ours to say
        return ""
    return value.decode() if isinstance(value, bytes) else str(value)
