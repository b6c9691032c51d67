"""Reading an HDF5 file that may come from someone else (a bundle, a recon.h5, a calibration file).

HDF5 can point outside the file: a dataset's bytes may live in another file (external storage,
absolute paths allowed), a link may name an object of another file (external link) or another
path (soft link), and a virtual dataset maps other files' datasets. Any of these would let a
shared file read the reader's own files, so `open_untrusted` walks the whole file once and
refuses it, in one line naming what it found, unless every object is reached by hard links and
every dataset keeps its bytes in the file. The file itself is opened by descriptor
(`rngcam.untrusted.open_untrusted`: no link, no FIFO or device) and HDF5 reads that same open
file, so nothing can be swapped in after the check.

Compressed data is checked before HDF5 inflates any of it: only the filters rngcam writes or
h5py ships without plugins (gzip, lzf, shuffle, fletcher32, scale-offset) are accepted, so HDF5
never searches its plugin folders; a chunk may not be larger than its dataset; and every
compressed chunk is inflated once here into a buffer of the chunk's size, so a stream that would
inflate past it (a compression bomb) is refused. Shapes and dtypes are believed only after
`checked_dataset` compared them with limits, before anything is read.
"""

from __future__ import annotations

import contextlib
import ctypes
import math
import os
import time
import zlib
from pathlib import Path

import h5py
import numpy as np

from rngcam.errors import RngcamError
from rngcam.memory import total_memory_bytes
from rngcam.untrusted import UntrustedFileError, printable
from rngcam.untrusted import open_untrusted as open_untrusted_file

MAX_SIDE = 8192  # pixels: the largest frame (or PSF) side the rig's cameras deliver
MAX_CHANNELS = 4
MAX_OBJECTS = 10_000  # groups and datasets in one file
MAX_DEPTH = 16
MAX_ATTR_ELEMENTS = 1_000_000  # elements (or bytes of text) in one attribute
MAX_TEXT_ELEMENTS = 64  # strings of variable length in one attribute (each is read to be measured)
MAX_TEXT_CHARS = 16 * 2**20  # characters of one text attribute (rig YAML, JSON settings)
MEMORY_FRACTION = 0.8  # of the machine's memory: the most one file's arrays may declare


class UnsafeFileError(RngcamError):
    """An HDF5 file points outside itself, or declares more than it may."""


def memory_limit_bytes() -> int:
    """The most bytes one array of a shared file may declare: a fraction of this machine's memory."""
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
    plist = d.id.get_create_plist()
    if plist.get_external_count() > 0:
        raise UnsafeFileError(f"{path}: '{where}' keeps its data in an external file; refused")
    _check_filters(d, plist, where, path)


# The filters read: HDF5's own gzip, shuffle, fletcher32 and scale-offset and h5py's LZF (none
# needs a plugin). szip and n-bit are left out: rngcam never writes them, and their parameters
# size HDF5's output buffer from the file.
ALLOWED_FILTERS = {h5py.h5z.FILTER_DEFLATE: "gzip", h5py.h5z.FILTER_SHUFFLE: "shuffle",
                   h5py.h5z.FILTER_FLETCHER32: "fletcher32", h5py.h5z.FILTER_SCALEOFFSET: "scale-offset",
                   h5py.h5z.FILTER_LZF: "lzf"}
_INFLATING = (h5py.h5z.FILTER_DEFLATE, h5py.h5z.FILTER_LZF)
CHUNK_SLACK_BYTES = 2**20  # a chunk may pass its dataset's edges only while this small (h5py's own
# chunks of a resizable dataset)
_STREAM_SLACK = 64  # bytes a chunk's stream may hold past its data (a checksum, a scale-offset header)


def _pipeline(plist) -> list[tuple[int, tuple]]:
    return [(int(code), tuple(cd)) for code, _, cd, _ in
            (plist.get_filter(i) for i in range(plist.get_nfilters()))]


def _check_filters(d: h5py.Dataset, plist, where: str, path: Path) -> None:
    """Refuse an unknown filter, a chunk larger than its dataset or filter parameters that size a
    buffer past the chunk, before HDF5 decodes anything."""
    pipeline = _pipeline(plist)
    for code, _ in pipeline:
        if code not in ALLOWED_FILTERS:
            raise UnsafeFileError(f"{path}: '{where}' uses HDF5 filter {code}, which rngcam does not read "
                                  f"(only {', '.join(ALLOWED_FILTERS.values())}); refused")
    if d.chunks is None:
        return
    chunk_elements = elements(d.chunks)
    chunk_bytes = chunk_elements * d.dtype.itemsize
    declared = elements(d.shape or ()) * d.dtype.itemsize
    if chunk_bytes > max(declared, CHUNK_SLACK_BYTES):
        raise UnsafeFileError(f"{path}: '{where}' keeps its data in chunks of {_size(chunk_bytes)}, larger than "
                              f"the dataset ({_size(declared)}); refused")
    for code, cd in pipeline:
        if code == h5py.h5z.FILTER_SCALEOFFSET and (len(cd) < 5 or cd[2] > chunk_elements or cd[4] > 8):
            raise UnsafeFileError(f"{path}: '{where}' has scale-offset parameters past its chunk; refused")
        if code == h5py.h5z.FILTER_LZF and len(cd) >= 3 and cd[2] > chunk_bytes + _STREAM_SLACK:
            raise UnsafeFileError(f"{path}: '{where}' has LZF parameters past its chunk; refused")


def check_inflation(d: h5py.Dataset, where: str) -> None:
    """UnsafeFileError when a compressed chunk of `d` is stored larger than its data or inflates
    past its chunk's size: every chunk is inflated here once, into a buffer of that size."""
    if d.chunks is None:
        return
    pipeline = _pipeline(d.id.get_create_plist())
    if not any(code in _INFLATING for code, _ in pipeline):
        return
    chunk_bytes = elements(d.chunks) * d.dtype.itemsize
    limit = chunk_bytes + _STREAM_SLACK
    chunks: list = []
    d.id.chunk_iter(chunks.append)
    for info in chunks:
        if info.size > limit + limit // 8:  # neither gzip nor LZF grows data that much
            raise UnsafeFileError(f"'{where}': a chunk is stored in {info.size:,} bytes for {chunk_bytes:,} bytes of "
                                  "data; refused")
        mask, raw = d.id.read_direct_chunk(info.chunk_offset)
        for i in reversed(range(len(pipeline))):
            code, cd = pipeline[i]
            if mask & (1 << i):
                continue
            if code == h5py.h5z.FILTER_FLETCHER32:
                raw = raw[:-4]
            elif code == h5py.h5z.FILTER_DEFLATE:
                raw = _bounded_inflate(raw, limit, where)
            elif code == h5py.h5z.FILTER_LZF:
                raw = _bounded_lzf(raw, limit, where)
            elif code == h5py.h5z.FILTER_SHUFFLE:
                raw = _unshuffle(raw, int(cd[0]) if cd else d.dtype.itemsize)
            else:  # scale-offset: decodes into a buffer its checked parameters size
                break


def _bounded_inflate(raw: bytes, limit: int, where: str) -> bytes:
    inflater = zlib.decompressobj()
    try:
        out = inflater.decompress(raw, limit + 1)
    except zlib.error as exc:
        raise UnsafeFileError(f"'{where}': a gzip chunk is damaged ({printable(exc, 100)})") from None
    if len(out) > limit or inflater.unconsumed_tail:
        raise UnsafeFileError(f"'{where}': a gzip chunk inflates past its chunk's size (a compression bomb); "
                              "refused")
    return out


def _lzf_decoder():
    """h5py's own LZF decoder (the one its filter calls), or None where this build does not export it."""
    try:
        lib = ctypes.CDLL(h5py.h5z.__file__)
        fn = lib.lzf_decompress
    except (OSError, AttributeError):
        return None
    fn.restype = ctypes.c_uint
    fn.argtypes = (ctypes.c_char_p, ctypes.c_uint, ctypes.c_void_p, ctypes.c_uint)
    return fn


_LZF = _lzf_decoder()


def _bounded_lzf(raw: bytes, limit: int, where: str) -> bytes:
    if _LZF is None:
        raise UnsafeFileError(f"'{where}': LZF chunks cannot be checked with this h5py; refused")
    out = ctypes.create_string_buffer(max(1, limit))
    n = _LZF(raw, len(raw), out, limit)
    if n == 0 and raw:
        raise UnsafeFileError(f"'{where}': an LZF chunk is damaged or inflates past its chunk's size "
                              "(a compression bomb); refused")
    return out.raw[:n]


def _unshuffle(raw: bytes, itemsize: int) -> bytes:
    if itemsize <= 1 or len(raw) % itemsize:
        return raw
    return np.frombuffer(raw, np.uint8).reshape(itemsize, -1).T.tobytes()


PROBE_SECONDS = 5.0  # a child reading a file's metadata: ample for any file rngcam writes
_PROBED: set[tuple] = set()  # (device, inode, size, mtime) of files whose metadata a child read whole
_HUNG: set[tuple] = set()  # ... and of those on which it hung


def probe_metadata(fd: int, path: Path) -> None:
    """UnsafeFileError when HDF5 itself does not finish reading the metadata of the file open as
    `fd` (every object, attribute and chunk index) within PROBE_SECONDS: some damaged files send
    the library into a loop no signal can break (a global heap with a zero-sized object), so a
    forked child reads them first and is killed when it hangs. Once per file and process; where
    there is no fork, no probe."""
    st = os.fstat(fd)
    key = (st.st_dev, st.st_ino, st.st_size, st.st_mtime_ns)
    hung = UnsafeFileError(f"{printable(path)}: the HDF5 library does not finish reading its metadata within "
                           f"{PROBE_SECONDS:g} s (a damaged file); refused")
    if key in _HUNG:
        raise hung
    if key in _PROBED or not hasattr(os, "fork"):
        return
    with h5py._objects.phil:  # h5py's lock, held across the fork: no other thread holds it in the child
        pid = os.fork()
    if pid == 0:  # the child: read everything HDF5 keeps about the file, then leave at once
        try:
            with h5py.File(f"/proc/self/fd/{fd}", "r") as f:
                _read_metadata(f)
        finally:
            os._exit(0)
    deadline = time.monotonic() + PROBE_SECONDS
    try:
        while not os.waitpid(pid, os.WNOHANG)[0]:
            if time.monotonic() > deadline:
                _HUNG.add(key)
                raise hung
            time.sleep(0.002)
        pid = 0
    finally:
        if pid:
            os.kill(pid, 9)
            os.waitpid(pid, 0)
    _PROBED.add(key)


def _read_metadata(f: h5py.File) -> None:
    """Every object's attributes (those `check_attr` allows) and chunk index, in the probe's child."""
    def visit(name, obj):
        for attr in list(obj.attrs):
            with contextlib.suppress(Exception):
                check_attr(obj, attr)
                obj.attrs[attr]
        if isinstance(obj, h5py.Dataset) and obj.chunks is not None:
            obj.id.chunk_iter(lambda info: None)

    with contextlib.suppress(Exception):
        visit("/", f)
        audit(f, Path("probe"))
    with contextlib.suppress(Exception):
        f.visititems(visit)


def open_h5_file(path: str | Path, what: str = "HDF5 file",
                 within: str | Path | None = None) -> h5py.File:
    """`path` opened read-only by HDF5 through one descriptor (`rngcam.untrusted.open_untrusted`:
    a link, FIFO or device is refused in one line, UntrustedFileError) that HDF5 reads itself, so
    no file swapped in at the name after the check is read; nothing audited yet. OSError as
    h5py raises it when the file is not HDF5."""
    path = Path(path)
    with open_untrusted_file(path, what=what, within=within) as fh:
        proc = f"/proc/self/fd/{fh.fileno()}"
        if os.path.exists(proc):  # HDF5 opens the very file behind the descriptor (its own copy of it)
            probe_metadata(fh.fileno(), path)
            f = h5py.File(proc, "r")
        else:
            f = h5py.File(path, "r")
        try:
            same = os.fstat(f.id.get_vfd_handle()), os.fstat(fh.fileno())
        except (OSError, TypeError, ValueError):
            same = None
        if same is None or (same[0].st_dev, same[0].st_ino) != (same[1].st_dev, same[1].st_ino):
            f.close()
            raise UntrustedFileError(f"refusing to read {printable(path)}: it was replaced while it was opened")
    return f


def open_untrusted(path: str | Path, what: str = "HDF5 file", within: str | Path | None = None) -> h5py.File:
    """Open `path` read-only (by descriptor, `open_h5_file`) after checking it points nowhere
    outside itself (UnsafeFileError, one line, otherwise; RngcamError when it cannot be opened
    at all)."""
    path = Path(path)
    try:
        f = open_h5_file(path, what, within)
    except OSError as exc:
        reason = str(exc).splitlines()[0] if str(exc) else type(exc).__name__
        raise RngcamError(f"{printable(path)} is not a readable {what} ({printable(reason, 200)})") from None
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
    try:
        _audit_dataset(d, where, Path("file"))
    except UnsafeFileError as exc:  # said with the file's name by whoever opened it
        raise UnsafeFileError(str(exc).split(": ", 1)[1]) from None
    check_shape(where, d.shape, d.dtype, max_elements, dtypes, ndims, sides, channel_axis)
    _check_stored(d, where)
    check_inflation(d, where)
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
    (elements, or bytes of a fixed-length string), before it is read; text of variable length
    (whose declared item size says nothing of its length) is allowed only in a few elements,
    and is read and measured by its real length (MAX_TEXT_CHARS)."""
    aid = obj.attrs.get_id(name)
    shape = aid.shape or ()
    n = elements(shape) if shape else 1
    size = n * max(1, aid.dtype.itemsize)
    where = printable(f"{obj.name}@{name}", 200)
    if n > MAX_ATTR_ELEMENTS or size > 16 * MAX_ATTR_ELEMENTS:
        raise UnsafeFileError(f"attribute '{where}' declares {n:,} elements ({size:,} bytes); refused")
    if aid.get_type().get_class() in (h5py.h5t.VLEN, h5py.h5t.REFERENCE) or (
            aid.get_type().get_class() == h5py.h5t.STRING and aid.get_type().is_variable_str()):
        if n > MAX_TEXT_ELEMENTS:
            raise UnsafeFileError(f"attribute '{where}' holds {n:,} texts of variable length; refused")
        value = obj.attrs[name]  # bounded by the file's own bytes
        length = sum(len(v) for v in np.ravel(np.asarray(value, dtype=object)) if isinstance(v, (str, bytes)))
        if length > MAX_TEXT_CHARS:
            raise UnsafeFileError(f"attribute '{where}' holds {length:,} characters of text, above "
                                  f"{MAX_TEXT_CHARS:,}; refused")


def file_format(path: str | Path) -> str:
    """An HDF5 file's `format` attribute (rngcam-bundle, rngcam-recon, rngcam-calibration), or ''
    where the file is not HDF5, is damaged or has none; only that attribute is read, checked first."""
    try:
        with open_h5_file(path) as f:
            if "format" not in f.attrs:
                return ""
            check_attr(f, "format")
            value = f.attrs["format"]
    except (OSError, ValueError, TypeError, KeyError, RuntimeError, RngcamError):  # damaged: not ours to say
        return ""
    return value.decode() if isinstance(value, bytes) else str(value)
