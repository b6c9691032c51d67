"""Reading arrays from files others made: TIFF, PNG, NPY/NPZ, MATLAB .mat (v5 and v7.3), image
folders and video files, through tifffile, OpenCV/Pillow, numpy, scipy.io, h5py and PyAV.

Every reader checks the declared shape and dtype before decoding (`check_shape`: sides, channels,
elements and this machine's memory), opens no link, and ends a file it cannot read in one line
(SidecarError naming the file). `to_axes` turns what was read into the layout a caller wants.
"""

from __future__ import annotations

import hashlib
import io
import os
import zipfile
from pathlib import Path

import h5py
import numpy as np

from rngcam import h5safe
from rngcam.formats.sidecar import SidecarError
from rngcam.untrusted import printable, read_untrusted

MAX_ELEMENTS = 2**31  # elements of one array read from a file (frames of a stack included)
MAX_FOLDER_FILES = 100_000
IMAGE_SUFFIXES = (".tif", ".tiff", ".png", ".npy")
ARRAY_SUFFIXES = (".tif", ".tiff", ".png", ".npy", ".npz", ".mat")
VIDEO_SUFFIXES = (".mp4", ".avi", ".mkv", ".mov")
# A file's own axis letters -> ours: N frames, H rows, W columns, C channels
AXIS = {"T": "N", "I": "N", "Z": "N", "Q": "N", "N": "N", "Y": "H", "H": "H", "X": "W", "W": "W",
         "C": "C", "S": "C"}


def _checked(where: str, shape, dtype) -> None:
    try:
        h5safe.check_shape(where, shape, dtype, MAX_ELEMENTS, "uif", sides=(-1, -2))
    except h5safe.UnsafeFileError as exc:
        raise SidecarError(str(exc)) from None


def _opened(path: Path, within: Path | None, digests: dict | None) -> io.BytesIO:
    """The bytes of `path` read by descriptor: a regular file, no link followed (below `within`
    neither), at most the memory one array may take (rngcam.untrusted.read_untrusted); in memory,
    so every library reads what was checked, and their sha256 is that of what was read (into
    `digests`, by path)."""
    data = read_untrusted(path, h5safe.memory_limit_bytes(), what="capture file", within=within, error=SidecarError)
    if digests is not None:
        digests[str(path)] = hashlib.sha256(data).hexdigest()
    return io.BytesIO(data)


def _pick(names: list[str], variable: str | None, path: Path) -> str:
    if variable is not None:
        if variable not in names:
            raise SidecarError(f"{path} has no variable {printable(variable, 80)!r} "
                               f"(it has {printable(', '.join(names[:10]), 300) or 'none'})")
        return variable
    if len(names) != 1:
        raise SidecarError(f"{path} holds {len(names)} arrays ({printable(', '.join(names[:10]), 300)}): "
                           "say which with `variable:` in the sidecar")
    return names[0]


def _tiff(path: Path, fh) -> tuple[np.ndarray, str]:
    import tifffile  # heavy: tifffile

    with tifffile.TiffFile(fh) as tif:
        if not tif.series:
            raise SidecarError(f"{path} holds no image")
        series = tif.series[0]
        _checked(str(path), series.shape, series.dtype)
        axes = "".join(AXIS.get(a, "?") for a in series.axes)
        return series.asarray(), axes


def _png(path: Path, fh) -> tuple[np.ndarray, str]:
    import cv2  # heavy: cv2
    from PIL import Image  # optional: Pillow, not declared

    with Image.open(fh) as img:  # the header only: the size before anything is decoded
        w, h = img.size
        channels = len(img.getbands())
    _checked(str(path), (h, w, channels), np.uint16)
    fh.seek(0)
    arr = cv2.imdecode(np.frombuffer(fh.read(), np.uint8), cv2.IMREAD_UNCHANGED)
    if arr is None:
        raise SidecarError(f"{path} cannot be decoded as PNG")
    if arr.ndim == 3:  # OpenCV decodes colour as BGR(A)
        arr = arr[..., [2, 1, 0]] if arr.shape[-1] in (3, 4) else arr
        return np.ascontiguousarray(arr[..., :3]), "HWC"
    return arr, "HW"


def _npy_header(fh, where: str) -> None:
    """Check an .npy stream's declared shape and dtype (the stream is left past the header)."""
    version = np.lib.format.read_magic(fh)
    read = np.lib.format.read_array_header_1_0 if version == (1, 0) else np.lib.format.read_array_header_2_0
    shape, _fortran, dtype = read(fh)
    _checked(where, shape, dtype)


def _npy(path: Path, fh) -> tuple[np.ndarray, str]:
    _npy_header(fh, str(path))
    fh.seek(0)
    return np.load(fh, allow_pickle=False), ""


def _npz(path: Path, fh, variable: str | None) -> tuple[np.ndarray, str]:
    with zipfile.ZipFile(fh) as zf:
        members = {i.filename[:-4]: i for i in zf.infolist() if i.filename.endswith(".npy")}
        name = _pick(sorted(members), variable, path)
        with zf.open(members[name]) as member:
            _npy_header(member, f"{path}:{name}")
        with zf.open(members[name]) as member:
            return np.load(member, allow_pickle=False), ""


def _mat(path: Path, fh, variable: str | None) -> tuple[np.ndarray, str]:
    if fh.read(8) == b"\x89HDF\r\n\x1a\n" or (fh.seek(512) == 512 and fh.read(8) == b"\x89HDF\r\n\x1a\n"):
        fh.seek(0)  # MATLAB v7.3: HDF5 (after a 512-byte header), arrays stored with their axes reversed
        with h5py.File(fh, "r") as f:
            try:
                h5safe.audit(f, path)
            except h5safe.UnsafeFileError as exc:
                raise SidecarError(str(exc)) from None
            names = sorted(k for k in f if not k.startswith("#") and isinstance(f.get(k, getlink=True), h5py.HardLink)
                           and isinstance(f[k], h5py.Dataset))
            name = _pick(names, variable, path)
            try:
                d = h5safe.checked_dataset(f, name, MAX_ELEMENTS, "uif", sides=(0, 1))
            except h5safe.UnsafeFileError as exc:
                raise SidecarError(f"{path}: {exc}") from None
            return np.ascontiguousarray(d[()].T), "mat"
    import scipy.io  # heavy: scipy

    fh.seek(0)
    found = scipy.io.whosmat(fh)
    numeric = {n: (s, c) for n, s, c in found if c not in ("cell", "struct", "object", "char", "sparse", "function")}
    name = _pick(sorted(numeric), variable, path)
    shape, cls = numeric[name]
    _checked(f"{path}:{name}", shape, np.float64)
    fh.seek(0)
    arr = scipy.io.loadmat(fh, variable_names=[name], squeeze_me=False)[name]
    if not isinstance(arr, np.ndarray) or arr.dtype.kind not in "uifb":
        raise SidecarError(f"{path}:{printable(name, 80)} is not a numeric array ({cls})")
    return np.asarray(arr), "mat"


def read_array(path: Path, variable: str | None = None, within: Path | None = None,
               digests: dict | None = None) -> tuple[np.ndarray, str]:
    """(the array in `path`, the axes the file says it has: 'NHW'-style letters, 'mat' for MATLAB's
    column-major order, '' when the file does not say). One line for anything unreadable; with
    `within`, no link below that folder is followed; `digests` gets the sha256 of what was read."""
    path = Path(path)
    suffix = path.suffix.lower()
    readers = {".tif": _tiff, ".tiff": _tiff, ".png": _png, ".npy": _npy}
    if suffix not in ARRAY_SUFFIXES:
        raise SidecarError(f"{path}: unknown file type {printable(suffix, 20)!r} "
                           f"(read: {', '.join(ARRAY_SUFFIXES)}, videos {', '.join(VIDEO_SUFFIXES)})")
    try:
        with _opened(path, within, digests) as fh:
            if suffix in readers:
                arr, axes = readers[suffix](path, fh)
            else:
                arr, axes = (_npz if suffix == ".npz" else _mat)(path, fh, variable)
    except SidecarError:
        raise
    except MemoryError:
        raise SidecarError(f"{path}: not enough memory to read it") from None
    except Exception as exc:  # noqa: BLE001 - any reader's failure on a damaged file is that file's one line
        text = str(exc).splitlines()[0] if str(exc) else type(exc).__name__
        raise SidecarError(f"{path} cannot be read ({printable(text, 200)})") from None
    if arr.dtype.kind == "b":
        arr = arr.astype(np.uint8)
    if arr.dtype.kind not in "uif":
        raise SidecarError(f"{path}: holds {arr.dtype} values, not numbers")
    return arr, axes


def read_folder(folder: Path, digests: dict | None = None) -> tuple[np.ndarray, str]:
    """The images of `folder` (TIFF, PNG, NPY, by name order) stacked as frames."""
    try:
        names = sorted(n for n in os.listdir(folder) if Path(n).suffix.lower() in IMAGE_SUFFIXES
                       and not n.startswith("."))
    except OSError as exc:
        raise SidecarError(f"cannot list {folder}: {exc.strerror or exc}") from None
    if not names:
        raise SidecarError(f"{folder} holds no images ({', '.join(IMAGE_SUFFIXES)})")
    if len(names) > MAX_FOLDER_FILES:
        raise SidecarError(f"{folder} holds {len(names):,} images, more than {MAX_FOLDER_FILES:,}")
    frames, axes = [], None
    for name in names:
        arr, got = read_array(folder / name, within=folder, digests=digests)
        got = got or ("HW" if arr.ndim == 2 else "HWC")
        if frames and (arr.shape != frames[0].shape or arr.dtype != frames[0].dtype):
            raise SidecarError(f"{folder / name} is {arr.shape} {arr.dtype}, the folder's first image "
                               f"{frames[0].shape} {frames[0].dtype}: every frame must match")
        frames.append(arr)
        axes = got
        _checked(str(folder), (len(frames), *arr.shape), arr.dtype)
    return np.stack(frames), "N" + axes


def read_video(path: Path, within: Path | None = None, digests: dict | None = None) -> tuple[np.ndarray, str]:
    """The frames of a video file (N, H, W, 3) uint8, through PyAV."""
    import av  # heavy: av

    frames = []
    try:
        with _opened(Path(path), within, digests) as fh, av.open(fh) as container:
            stream = container.streams.video[0]
            _checked(str(path), (max(1, stream.frames), stream.height, stream.width, 3), np.uint8)
            for frame in container.decode(stream):
                frames.append(frame.to_ndarray(format="rgb24"))
                _checked(str(path), (len(frames), *frames[0].shape), np.uint8)
    except SidecarError:
        raise
    except Exception as exc:  # noqa: BLE001 - a damaged or unknown video is one line
        text = str(exc).splitlines()[0] if str(exc) else type(exc).__name__
        raise SidecarError(f"{path} cannot be read as a video ({printable(text, 200)})") from None
    if not frames:
        raise SidecarError(f"{path} holds no video frames")
    return np.stack(frames), "NHWC"


def read_frames(path: Path, variable: str | None = None, within: Path | None = None,
                digests: dict | None = None) -> tuple[np.ndarray, str]:
    """Frames from a file, a folder of images or a video (as `read_array`)."""
    path = Path(path)
    if path.is_dir() and not path.is_symlink():
        return read_folder(path, digests)
    if path.suffix.lower() in VIDEO_SUFFIXES:
        return read_video(path, within, digests)
    return read_array(path, variable, within, digests)


def default_axes(ndim: int, colour: bool, stack: bool, matlab: bool) -> str:
    """The axes assumed where neither the sidecar nor the file says: one image HW / HWC, a stack
    NHW / NHWC; MATLAB's stacks put the frames last (HWN, HWCN)."""
    if ndim == 2:
        return "HW"
    if ndim == 3:
        if colour:
            return "HWC"
        return "HWN" if matlab else "NHW"
    if ndim == 4:
        return "HWCN" if matlab else "NHWC"
    return "?" * ndim


def to_axes(arr: np.ndarray, have: str, want: str, where: str) -> np.ndarray:
    """`arr` with axes `have` rearranged to `want` (letters N, H, W, C); an axis `want` has and
    `have` lacks is added with length 1; one of `have` that `want` lacks must be of length 1."""
    have = "".join(AXIS.get(a, a) for a in have)
    if len(have) != arr.ndim or len(set(have)) != len(have) or not set(have) <= set("NHWC"):
        raise SidecarError(f"{where}: axes {have!r} do not fit an array of shape {arr.shape} "
                           "(put `axes:` in the sidecar, e.g. HW, HWC, NHW, NHWC, CHW)")
    for axis in [a for a in have if a not in want]:
        i = have.index(axis)
        if arr.shape[i] != 1:
            raise SidecarError(f"{where}: shape {arr.shape} with axes {have} has {arr.shape[i]} along {axis}, "
                               f"expected {want} (one {'frame' if axis == 'N' else 'channel'} here)")
        arr, have = arr.squeeze(i), have.replace(axis, "")
    for axis in want:
        if axis not in have:
            arr, have = arr[..., None], have + axis
    return np.ascontiguousarray(np.transpose(arr, [have.index(a) for a in want]))
