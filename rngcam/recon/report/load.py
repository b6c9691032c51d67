"""Read what a report shows from a recon folder (recon.h5, metrics.json, errors.csv) and, for the
truth, from the bundle whose path and sha256 recon.h5 records."""

from __future__ import annotations

import csv
import hashlib
import io
import math
import os
from dataclasses import dataclass, field
from pathlib import Path

import h5py
import numpy as np

from rngcam import h5safe
from rngcam.errors import ConfigError, RngcamError
from rngcam.formats.bundle import open_bundle
from rngcam.recon.metrics_schema import check_metrics
from rngcam.untrusted import load_json, open_untrusted, printable, read_untrusted

RECON_FORMAT = "rngcam-recon"
MAX_TEXT_BYTES = 16 * 2**20  # metrics.json, errors.csv: far above what a run writes
MAX_FRAMES = 1_000_000
TEXT_ATTRS = ("format", "rngcam_version", "created_utc", "bundle_sha256", "bundle_path", "capture_utc",
              "settings", "left_out")
NUMBER_ATTRS = ("frame_interval_s", "fps", "rs_noise_level", "pixel_size_m")
# dataset -> (dimensions, side axes): checked before anything is read
_SHAPES = {"video": ((4,), (2, 3)), "key_frames": ((4,), (2, 3)), "rs_image": ((3,), (1, 2)),
           "frame_times_s": ((1,), ()), "key_frame_times_s": ((1,), ())}


@dataclass
class Run:
    """One reconstruction as the report sees it; arrays are (C, K, H, W) linear intensity."""

    folder: Path
    method: str
    video: np.ndarray
    frame_times_s: np.ndarray
    attrs: dict
    settings: dict
    metrics: dict
    log: list[dict]
    key_frames: np.ndarray | None = None  # (C, G, H, W)
    key_times_s: np.ndarray = field(default_factory=lambda: np.zeros(0))
    rs_image: np.ndarray | None = None  # (C, H, W)
    components: dict[str, np.ndarray] = field(default_factory=dict)
    left_out: list = field(default_factory=list)

    @property
    def dt_s(self) -> float:
        dt = float(self.attrs.get("frame_interval_s", math.nan))
        if not math.isfinite(dt) and self.frame_times_s.size > 1:
            dt = float(np.median(np.diff(self.frame_times_s)))
        return dt


def _text(value) -> str:
    return value.decode() if isinstance(value, bytes) else str(value)


def _floats(row: dict) -> dict:
    out = {}
    for k, v in row.items():
        if v in ("", None):
            continue
        try:
            out[k] = float(v)
        except ValueError:
            out[k] = v
    return out


def is_recon_file(path: str | Path) -> bool:
    """True when `path` is an HDF5 file whose `format` attribute says rngcam-recon."""
    return h5safe.file_format(path) == RECON_FORMAT


def _dataset(f: h5py.Group, name: str) -> h5py.Dataset:
    """recon.h5's dataset `name` after its declared shape and dtype were checked (nothing read)."""
    if name.startswith("components/"):  # a method's named parts: any small rank, frames as the video's
        group, leaf = f["components"], name.split("/", 1)[1]
        ndims, sides, channel_axis = (1, 2, 3, 4), (-2, -1), None
    else:
        group, leaf = f, name
        ndims, sides = _SHAPES.get(name, ((3, 4), (-2, -1)))
        channel_axis = 0 if ndims != (1,) else None
    limit = MAX_FRAMES if ndims == (1,) else 2**62
    d = h5safe.checked_dataset(group, leaf, limit, "uif", ndims, sides, channel_axis)
    if d.ndim == 4 and d.shape[1] > MAX_FRAMES:
        raise h5safe.UnsafeFileError(f"'{name}' declares {d.shape[1]:,} frames, above {MAX_FRAMES:,}")
    return d


def read_json_file(path: Path, default, within: Path | None = None):
    """A JSON file of a recon folder, `default` when absent; RngcamError (one line) when it is a
    link or not a regular file, too large, nested too deeply or not JSON of `default`'s type.
    Read by descriptor (`read_untrusted`); `within`: the folder the user named."""
    path = Path(path)
    if not os.path.lexists(path):
        return default
    text = read_untrusted(path, MAX_TEXT_BYTES, what="JSON file", within=within, error=RngcamError)
    value = load_json(text, str(path), error=RngcamError)
    if not isinstance(value, type(default)):
        raise RngcamError(f"{path} holds a JSON {type(value).__name__}, expected a {type(default).__name__}")
    return value


def read_metrics(folder: Path) -> dict:
    """`folder`/metrics.json ({} when absent), every field rngcam reads of its type (the schema
    the writer shares, `metrics_schema`); RngcamError, one line, otherwise."""
    path = Path(folder) / "metrics.json"
    try:
        return check_metrics(read_json_file(path, {}, within=folder), str(path))
    except ValueError as exc:
        raise RngcamError(printable(exc, 300)) from None


def read_errors_csv(folder: Path) -> list[dict]:
    """`folder`/errors.csv as rows of numbers ([] when absent), read by descriptor."""
    path = Path(folder) / "errors.csv"
    if not os.path.lexists(path):
        return []
    data = read_untrusted(path, MAX_TEXT_BYTES, what="CSV file", within=folder, error=RngcamError)
    try:
        return [_floats(r) for r in csv.DictReader(io.StringIO(data.decode("utf-8", "replace")))]
    except csv.Error as exc:
        raise RngcamError(f"{path} is not a readable CSV ({printable(exc, 200)})") from None


class H5Frames:
    """A (C, K, ...) dataset of an HDF5 file read on demand: `shape`, `ndim`, and indexing whose
    first two entries pick channels and frames (each read opens the file and reads those frames
    only), so a page is built a chunk of frames at a time, not from a copy of the whole video."""

    def __init__(self, path: Path, name: str, shape: tuple[int, ...]):
        self.path, self.name, self.shape = Path(path), name, tuple(shape)
        self.ndim = len(self.shape)

    def __getitem__(self, key) -> np.ndarray:
        key = key if isinstance(key, tuple) else (key,)
        frames = key[1] if len(key) > 1 else slice(None)
        with h5safe.open_untrusted(self.path, "recon file", within=self.path.parent) as f:
            d = _dataset(f, self.name)
            if tuple(d.shape) != self.shape:
                raise RngcamError(f"{self.path} changed while it was being read")
            if isinstance(frames, (slice, int, np.integer)):
                return d[key]
            frames = np.asarray(frames)  # h5py reads increasing, distinct indices; others via their sort
            order, inverse = np.unique(frames, return_inverse=True)
            data = d[(slice(None), order)]
        return data[(slice(None), inverse.reshape(frames.shape), *key[2:])][key[0]]

    def __array__(self, dtype=None, copy=None) -> np.ndarray:
        data = self[:]
        return data if dtype is None else data.astype(dtype, copy=False)


def read_recon_h5(path: str | Path, video: bool = True, lazy: bool = False) -> dict:
    """recon.h5's attributes (settings and left_out decoded) and arrays (`video` False: no video;
    `lazy`: the video and the components as `H5Frames`, read a chunk of frames at a time)."""
    path = Path(path)
    if not os.path.lexists(path):
        raise RngcamError(f"{path}: no such recon file")
    with h5safe.open_untrusted(path, "recon file", within=path.parent) as f:
        try:
            return _read_recon(f, path, video, lazy)
        except RngcamError as exc:
            raise RngcamError(f"{path}: {exc}" if str(path) not in str(exc) else str(exc)) from None
        except (OSError, RuntimeError, KeyError, ValueError, TypeError, OverflowError, RecursionError) as exc:
            reason = printable(str(exc).splitlines()[0] if str(exc) else type(exc).__name__, 200)
            raise RngcamError(f"{path} is damaged or not an rngcam recon file ({reason})") from None
        except MemoryError:
            raise RngcamError(f"{path}: not enough memory to read it") from None


def _read_recon(f: h5py.File, path: Path, video: bool, lazy: bool) -> dict:
    for name in f.attrs:
        h5safe.check_attr(f, name)
    if _text(f.attrs.get("format", "")) != RECON_FORMAT:
        raise RngcamError(f"{path} is not an rngcam recon file (format attribute "
                          f"{printable(repr(_text(f.attrs.get('format', ''))), 100)})")
    attrs = {k: (_text(v) if isinstance(v, (bytes, str)) else v) for k, v in f.attrs.items()}
    for key in TEXT_ATTRS:
        if key in attrs and not isinstance(attrs[key], str):
            raise RngcamError(f"attribute {key!r} is not text")
    for key in NUMBER_ATTRS:
        if key in attrs and not (np.ndim(attrs[key]) == 0 and np.asarray(attrs[key]).dtype.kind in "uif"):
            raise RngcamError(f"attribute {key!r} is not a number")
    for key, kind in (("settings", dict), ("left_out", list)):
        value = load_json(attrs.get(key) or ("{}" if key == "settings" else "[]"), f"attribute {key!r}",
                          error=RngcamError)
        if not isinstance(value, kind):
            raise RngcamError(f"attribute {key!r} is not a JSON {kind.__name__}")
        attrs[key] = value
    out = {"attrs": attrs, "shape": tuple(_dataset(f, "video").shape)}
    out["frame_times_s"] = _dataset(f, "frame_times_s")[()]
    for name in ("key_frame_times_s", "key_frames", "rs_image"):
        if name in f:
            out[name] = _dataset(f, name)[()]
    comps = f["components"] if "components" in f else {}
    if not isinstance(comps, (dict, h5py.Group)):
        raise RngcamError("'components' is not a group")
    checked = {k: _dataset(f, f"components/{k}") for k in comps}
    out["components"] = {k: H5Frames(path, f"components/{k}", d.shape) if lazy and d.ndim == 4 else d[()]
                         for k, d in checked.items()}
    if video:
        out["video"] = H5Frames(path, "video", out["shape"]) if lazy else _dataset(f, "video")[()]
    return out


def load_run(folder: str | Path, lazy: bool = True) -> Run:
    """The recon folder's run; RngcamError (one line) when it holds no recon.h5. `lazy`: its video
    and components stay in recon.h5 and are read a chunk of frames at a time (`H5Frames`)."""
    folder = Path(folder)
    if folder.is_file() and folder.name.endswith(".h5"):
        folder = folder.parent
    h5 = read_recon_h5(folder / "recon.h5", lazy=lazy)
    metrics = read_metrics(folder)
    log = read_errors_csv(folder)
    settings = h5["attrs"]["settings"]
    method = metrics.get("method") or settings.get("method") or folder.name
    return Run(folder=folder, method=method, video=h5["video"], frame_times_s=h5["frame_times_s"],
               attrs=h5["attrs"], settings=settings, metrics=metrics, log=log,
               key_frames=h5.get("key_frames"), key_times_s=h5.get("key_frame_times_s", np.zeros(0)),
               rs_image=h5.get("rs_image"), components=h5["components"], left_out=h5["attrs"]["left_out"])


def _to_grid(video: np.ndarray, shape: tuple) -> np.ndarray | None:
    """The truth (C, T, h, w) on the recon's (C, K, H, W) grid by block averaging, or None."""
    c, k, h, w = shape
    if video.shape[0] != c or video.shape[1] != k or video.shape[2] % h or video.shape[3] % w:
        return None
    fy, fx = video.shape[2] // h, video.shape[3] // w
    if fy == fx == 1:
        return np.asarray(video, np.float32)  # no copy of a float32 truth on the same grid
    return video.reshape(c, k, h, fy, w, fx).mean(axis=(3, 5)).astype(np.float32)


def load_truth(run: Run, check_hash: bool = True, bundle: str | Path | None = None) -> tuple[np.ndarray | None, str]:
    """The bundle's truth on the run's grid (None when there is none) and a line saying where it
    came from or why it is missing. Read into float32 directly, as the bundle stores it.

    The truth comes only from `bundle` (one the user named) or from the bundle recon.h5 records
    when that file's sha256 is the one recorded beside it: a path in a file from someone else is
    a hint, never a reason to show another file's content. Without `check_hash` the recorded
    path is not read at all."""
    recorded = Path(str(run.attrs.get("bundle_path") or ""))
    if bundle is None and (not str(recorded) or str(recorded) == "."):
        return None, "recon.h5 does not record its bundle's path (written by an older rngcam)"
    if bundle is None and not check_hash:
        return None, (f"the bundle recon.h5 names ({recorded}) is read only with its sha256 checked; "
                      "name it with --bundle")
    path = Path(bundle) if bundle is not None else recorded
    if not os.path.lexists(path):
        return None, f"the bundle {path} is no longer there"
    try:
        with open_untrusted(path, what="bundle", error=RngcamError) as fh:
            if bundle is None and _sha256(fh) != run.attrs.get("bundle_sha256"):
                return None, f"the bundle at {path} has changed since this reconstruction (sha256 differs)"
            return _truth_of(path, fh, run)
    except RngcamError as exc:
        return None, f"the bundle cannot be read: {exc}"


def _sha256(fh) -> str:
    digest = hashlib.sha256()
    for block in iter(lambda: fh.read(2**20), b""):
        digest.update(block)
    return digest.hexdigest()


def _truth_of(path: Path, fh, run: Run) -> tuple[np.ndarray | None, str]:
    """The truth of the bundle at `path`, which must still be the file open as `fh`."""
    with open_bundle(path) as bundle:
        if bundle.truth is None:
            return None, f"{path.name} has no ground truth (a real capture)"
        video = bundle.truth.video
        if isinstance(video, h5py.Dataset):
            held, checked = os.fstat(video.file.id.get_vfd_handle()), os.fstat(fh.fileno())
            if (held.st_dev, held.st_ino) != (checked.st_dev, checked.st_ino):
                return None, f"the bundle at {path} was replaced while it was read; left out"
        shape = tuple(video.shape)
        on_grid = (_to_grid(np.asarray(video, np.float32), run.video.shape)
                   if shape[:2] == tuple(run.video.shape[:2]) else None)
    if on_grid is None:
        return None, (f"the truth {shape} does not match this video's grid {run.video.shape} "
                      f"(another bin?); left out")
    return on_grid, f"truth from {path}"


def load_runs(folders: list[str | Path]) -> list[Run]:
    """Runs of one bundle (ConfigError, one line, when their bundles' sha256 differ)."""
    if not folders:
        raise ConfigError("name at least one recon folder")
    runs = [load_run(f) for f in folders]
    hashes = {r.attrs.get("bundle_sha256") for r in runs}
    if len(hashes) > 1:
        names = ", ".join(f"{r.folder.name} ({str(r.attrs.get('bundle_sha256'))[:8]})" for r in runs)
        raise ConfigError(f"these reconstructions are of different bundles: {names}")
    shapes = {r.video.shape for r in runs}
    if len(shapes) > 1:
        raise ConfigError("these reconstructions are on different grids (" +
                          ", ".join(f"{r.folder.name} {r.video.shape}" for r in runs) + "); compare one bin")
    return runs
