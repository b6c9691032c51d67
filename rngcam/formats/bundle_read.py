"""Opening and reading a bundle: every command opens one here, so a missing, unreadable or
inconsistent file gives the same one line everywhere (BundleError)."""

from __future__ import annotations

import contextlib
import hashlib
import json
import os
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import h5py
import numpy as np

from rngcam import h5safe, pixels
from rngcam.errors import BundleError, RngcamError
from rngcam.formats.bundle_schema import (
    DEFAULT_READOUT,
    FORMAT_NAME,
    SCHEMA_VERSION,
    WARNING_PREFIX,
    Bundle,
    Calibration,
    CameraRecord,
    TriggerRecord,
    Truth,
    check_bundle,
    declared_cameras,
    is_warning,
)
from rngcam.untrusted import open_untrusted, printable


class _Fatal(Exception):
    """Stops reading: the file is not a readable bundle at all."""


def check_bundle_path(path: str | os.PathLike) -> Path:
    """`path` as a Path when it names a non-empty file; else the one line every command gives
    for a bundle it cannot open (BundleError)."""
    path = Path(path)
    if not path.exists():
        raise BundleError(f"bundle not found: {path}")
    if not path.is_file():
        raise BundleError(f"not a file: {path}")
    try:
        size = path.stat().st_size
    except OSError as exc:
        raise BundleError(f"cannot read {path}: {exc.strerror or exc}") from None
    if size == 0:
        raise BundleError(f"{path} is empty, not an HDF5 bundle")
    return path


MAX_STORED_FRAMES = 1_000_000  # frames of one camera (and entries of its per-frame arrays)
_BIG = 2**62  # frames and truth: bounded by side, channel and memory limits, not a count
# (group, dataset) -> checked_dataset's limits: max elements, dimensions, side axes, channel axis
_LIMITS: dict[tuple[str, str], tuple[int, tuple[int, ...] | None, tuple[int, ...], int | None]] = {
    ("cam", "frames"): (_BIG, (3, 4), (1, 2), 3),
    ("truth", "video"): (_BIG, (4,), (2, 3), 0),
    ("calibration", "psf"): (h5safe.MAX_CHANNELS * h5safe.MAX_SIDE**2, None, (1, 2), 0),
    ("calibration", "field_stop"): (h5safe.MAX_SIDE**2, None, (0, 1), None),
    ("calibration", "gs_to_rs"): (64, None, (), None),
    ("calibration", "white_balance"): (64, None, (), None),
}


def _limits(group: str, name: str):
    key = ("cam", name) if group in ("/rs", "/gs") and name == "frames" else (group.strip("/"), name)
    return _LIMITS.get(key, (MAX_STORED_FRAMES, None, (), None))


def _open_h5(path: Path) -> h5py.File:
    check_bundle_path(path)
    try:
        f = h5safe.open_h5_file(path, "bundle")
    except RngcamError as exc:
        raise BundleError(str(exc)) from None
    except OSError as exc:
        reason = str(exc).splitlines()[0] if str(exc) else type(exc).__name__
        if "truncated" in reason.lower():
            raise BundleError(f"{path} is truncated ({reason})") from None
        if "already open for write" in reason:
            raise BundleError(f"{path} was not closed cleanly (an interrupted write, "
                              "or a writer still has it open)") from None
        if "signature" in reason.lower():
            raise BundleError(f"{path} is not an HDF5 file") from None
        raise BundleError(f"cannot open {path} as HDF5: {reason}") from None
    try:
        h5safe.audit(f, path)
    except BaseException as exc:
        f.close()
        if isinstance(exc, h5safe.UnsafeFileError):
            raise BundleError(str(exc)) from None
        if isinstance(exc, (OSError, RuntimeError, KeyError, ValueError, TypeError, RecursionError)):
            raise BundleError(f"{path} is damaged or truncated ({_reason(exc)})") from None
        raise
    return f


def _reason(exc: BaseException) -> str:
    """The first line of an exception's text, printable (h5py's can quote the file's bytes)."""
    text = str(exc).splitlines()[0] if str(exc) else type(exc).__name__
    return printable(text, 200)


def _attr_str(attrs: h5py.AttributeManager, name: str) -> str:
    value = attrs[name]
    if isinstance(value, bytes):
        return value.decode("utf-8")
    if isinstance(value, np.ndarray) and value.shape == ():
        value = value[()]
    if not isinstance(value, str):
        raise TypeError(f"attribute {name!r} is not a string")
    return value


class _Reader:
    """Builds a Bundle from an open file, collecting every structural problem on the way."""

    def __init__(self, f: h5py.File, lazy: bool):
        self.f = f
        self.lazy = lazy
        self.problems: list[str] = []
        self.stats: dict[str, list[pixels.FrameStats]] = {}

    def attr(self, g: h5py.Group, name: str, kind: type, default: Any, required: bool = True):
        where = f"'{g.name}'" if g.name != "/" else "root"
        if name not in g.attrs:
            if required:
                self.problems.append(f"missing attribute {name!r} in {where}")
            return default, not required
        h5safe.check_attr(g, name)
        try:
            if kind is str:
                return _attr_str(g.attrs, name), True
            value = g.attrs[name]
            if kind is int:
                if np.ndim(value) != 0 or np.asarray(value).dtype.kind not in "ui":
                    raise ValueError
                return int(value), True
            if np.ndim(value) != 0 or np.asarray(value).dtype.kind not in "uif":
                raise ValueError
            return float(value), True
        except (ValueError, TypeError):
            self.problems.append(f"attribute {name!r} in {where} is not a {kind.__name__}")
            return default, False

    def json_attr(self, g: h5py.Group, name: str, kind: type, default: Any):
        text, ok = self.attr(g, name, str, None)
        if not ok or text is None:
            return default, False
        where = f"'{g.name}'" if g.name != "/" else "root"
        try:
            value = json.loads(text)
        except (ValueError, RecursionError):  # RecursionError: nested deeper than Python's stack
            self.problems.append(f"attribute {name!r} in {where} is not valid JSON")
            return default, False
        if not isinstance(value, kind):
            self.problems.append(f"attribute {name!r} in {where} is not a JSON {kind.__name__}")
            return default, False
        return value, True

    def dataset(self, g: h5py.Group, name: str, required: bool, big: bool = False):
        if name not in g:
            if required:
                self.problems.append(f"missing dataset '{g.name}/{name}'")
            return None, not required
        obj = g[name]
        if not isinstance(obj, h5py.Dataset):
            self.problems.append(f"'{g.name}/{name}' is not a dataset")
            return None, False
        if obj.dtype.kind not in "uifb":
            self.problems.append(f"'{g.name}/{name}' is not numeric (dtype {obj.dtype})")
            return None, False
        limit, ndims, sides, channel_axis = _limits(g.name, name)
        h5safe.checked_dataset(g, name, limit, "uifb", ndims, sides, channel_axis)
        if big and self.lazy:
            return obj, True
        return obj[()], True

    def camera(self, name: str) -> CameraRecord | None:
        if name not in self.f:
            self.problems.append(f"missing group '{name}' ({name.upper()} camera)")
            return None
        g = self.f[name]
        if not isinstance(g, h5py.Group):
            self.problems.append(f"'{name}' is not a group")
            return None
        results = {
            "frames": self.dataset(g, "frames", True, big=True),
            "pixel_format": self.attr(g, "pixel_format", str, ""),
            "bit_depth": self.attr(g, "bit_depth", int, 0),
            "black_level_dn": self.attr(g, "black_level_dn", float, 0.0),
            "exposure_s": self.attr(g, "exposure_s", float, 0.0),
            "trigger_times_s": self.dataset(g, "trigger_times_s", True),
            "line_time_s": self.attr(g, "line_time_s", float, None, required=False),
            "readout": self.attr(g, "readout", str, DEFAULT_READOUT, required=False),  # absent: top-down
            "gain_db": self.attr(g, "gain_db", float, 0.0),
            "model": self.attr(g, "model", str, ""),
            "serial": self.attr(g, "serial", str, ""),
            "timestamps_s": self.dataset(g, "timestamps_s", False),
            "frame_ids": self.dataset(g, "frame_ids", False),
            "features": self.json_attr(g, "features", dict, {}),
            "exposure_start_s": self.dataset(g, "exposure_start_s", False),  # optional: older bundles lack it
        }
        results["exposure_start_method"] = ("", True)
        if results["exposure_start_s"][0] is not None:
            results["exposure_start_method"] = self.attr(g["exposure_start_s"], "method", str, "", required=False)
        if not all(ok for _, ok in results.values()):
            return None
        return CameraRecord(**{k: v for k, (v, _) in results.items()})

    def calibration(self) -> Calibration:
        if "calibration" not in self.f:
            self.problems.append("missing group 'calibration'")
            return Calibration()
        g = self.f["calibration"]
        source, _ = self.attr(g, "psf_source", str, "")
        bias, _ = self.attr(g, "psf_bias", float, 0.0)
        extra, _ = self.json_attr(g, "extra", dict, {})
        arrays = {n: self.dataset(g, n, False)[0]
                  for n in ("psf", "gs_to_rs", "white_balance", "field_stop")}
        return Calibration(psf_source=source, psf_bias=bias, extra=extra, **arrays)

    def trigger(self) -> TriggerRecord | None:
        if "trigger" not in self.f:
            return None
        g = self.f["trigger"]
        generator, ok1 = self.attr(g, "generator", str, "")
        settings, ok2 = self.json_attr(g, "settings", dict, {})
        errors, ok3 = self.json_attr(g, "errors", list, [])
        return TriggerRecord(generator, settings, errors) if ok1 and ok2 and ok3 else None

    def truth(self) -> Truth | None:
        if "truth" not in self.f:
            return None
        g = self.f["truth"]
        video, ok1 = self.dataset(g, "video", True, big=True)
        times, ok2 = self.dataset(g, "frame_times_s", True)
        dt, ok3 = self.attr(g, "dt_s", float, 0.0)
        return Truth(video, times, dt) if ok1 and ok2 and ok3 else None

    def read(self) -> Bundle:
        attrs = self.f.attrs
        for name in ("format", "schema_version"):
            if name in attrs:
                h5safe.check_attr(self.f, name)
        if "format" not in attrs:
            raise _Fatal("not an rngcam bundle (no 'format' attribute; an interrupted write?)")
        try:
            fmt = _attr_str(attrs, "format")
        except TypeError:
            fmt = repr(attrs["format"])
        if fmt != FORMAT_NAME:
            raise _Fatal(f"not an rngcam bundle (format {fmt!r}, expected {FORMAT_NAME!r})")
        if "schema_version" not in attrs:
            raise _Fatal("no 'schema_version' attribute")
        version = attrs["schema_version"]
        if np.ndim(version) != 0 or np.asarray(version).dtype.kind not in "ui":
            raise _Fatal(f"schema_version attribute is not an integer: {version!r}")
        if int(version) != SCHEMA_VERSION:
            raise _Fatal(f"schema version {int(version)}, this rngcam reads {SCHEMA_VERSION}")
        created, _ = self.attr(self.f, "created_utc", str, "")
        writer, _ = self.attr(self.f, "rngcam_version", str, "")
        rig_yaml, _ = self.attr(self.f, "rig_yaml", str, "")
        meta, _ = self.json_attr(self.f, "meta", dict, {})
        rs = self.camera("rs")
        gs = self.camera("gs") if "gs" in self.f or "gs" in declared_cameras(meta) else None
        bundle = Bundle(rs=rs, gs=gs, calibration=self.calibration(), trigger=self.trigger(),
                        truth=self.truth(), rig_yaml=rig_yaml, meta=meta, created_utc=created,
                        rngcam_version=writer)
        self.problems += check_bundle(bundle, skip=frozenset(("rs", "gs")))
        self.stats = pixels.pixel_stats(bundle)
        for name, frames in self.stats.items():  # recon refuses them: say so here already
            bad = [i + 1 for i, st in enumerate(frames) if not st.finite]
            if bad:
                which = ", ".join(map(str, bad[:5])) + (f" (+{len(bad) - 5} more)" if len(bad) > 5 else "")
                self.problems.append(f"the {name.upper()} frames contain NaN or Inf (frame {which}); "
                                     "recon cannot use them")
        self.problems += pixels.pixel_problems(bundle, self.stats, WARNING_PREFIX)
        return bundle


def _read(f: h5py.File, path: Path, lazy: bool) -> tuple[Bundle, list[str], dict]:
    """Bundle, its problems and its pixel statistics; BundleError when the file cannot be read
    as a bundle at all."""
    reader = _Reader(f, lazy)
    try:
        bundle = reader.read()
    except _Fatal as exc:
        raise BundleError(f"{path}: {exc}") from None
    except h5safe.UnsafeFileError as exc:
        raise BundleError(f"{path}: {exc}") from None
    except (OSError, RuntimeError, KeyError, RecursionError) as exc:  # h5py's errors for damaged files
        raise BundleError(f"{path} is damaged or truncated ({_reason(exc)})") from None
    except (ValueError, TypeError, OverflowError) as exc:  # content of a shape/type nobody expects
        raise BundleError(f"{path} has unreadable content ({_reason(exc)})") from None
    except MemoryError:
        raise BundleError(f"{path}: not enough memory to read it") from None
    return bundle, reader.problems, reader.stats


def _raise_on_errors(path: Path, problems: list[str]) -> None:
    errors = [p for p in problems if not is_warning(p)]
    if errors:
        shown = "; ".join(errors[:3])
        more = f" (+{len(errors) - 3} more)" if len(errors) > 3 else ""
        raise BundleError(f"inconsistent bundle {path}: {shown}{more}")


@contextlib.contextmanager
def open_checked(path: str | os.PathLike) -> Iterator[tuple[Bundle, list[str], dict]]:
    """(bundle, its warnings and problems, pixel statistics), frames and truth video left on
    disk while the file is open; BundleError (one line) when it is unusable."""
    path = Path(path)
    with _open_h5(path) as f:
        bundle, problems, stats = _read(f, path, lazy=True)
        _raise_on_errors(path, problems)
        yield bundle, problems, stats


@contextlib.contextmanager
def open_bundle(path: str | os.PathLike) -> Iterator[Bundle]:
    """Open a bundle lazily: frames and truth video stay h5py datasets while the file is open.

    Everything else is read. Raises BundleError like `read_bundle`; warnings are ignored.
    """
    with open_checked(path) as (bundle, _, _):
        yield bundle


def read_bundle(path: str | os.PathLike) -> Bundle:
    """Read a whole bundle into memory; BundleError (one line, naming the file) if it is unusable.

    Warning-level problems (see `validate_bundle`) do not stop reading.
    """
    path = Path(path)
    with _open_h5(path) as f:
        bundle, problems, _ = _read(f, path, lazy=False)
    _raise_on_errors(path, problems)
    return bundle


def read_bundle_with_warnings(path: str | os.PathLike) -> tuple[Bundle, list[str]]:
    """`read_bundle`, plus the warnings `validate_bundle` (and `rngcam inspect`) gives for it."""
    path = Path(path)
    with _open_h5(path) as f:
        bundle, problems, _ = _read(f, path, lazy=False)
    _raise_on_errors(path, problems)
    return bundle, [p for p in problems if is_warning(p)]


def validate_bundle(path: str | os.PathLike) -> list[str]:
    """Every problem found in the file, [] when valid; never raises for a bad file.

    Warning-level problems (still readable) start with 'warning: '.
    """
    path = Path(path)
    try:
        with _open_h5(path) as f:
            _, problems, _ = _read(f, path, lazy=True)
    except BundleError as exc:
        return [str(exc)]
    except OSError as exc:
        return [f"{path}: {exc}"]
    return problems


def bundle_checksum(path: str | os.PathLike) -> str:
    """sha256 of the file's bytes, hex; BundleError (the opener's line) when it cannot be read."""
    path = check_bundle_path(path)
    digest = hashlib.sha256()
    try:
        with open_untrusted(path, what="bundle", error=BundleError) as fh:
            for block in iter(lambda: fh.read(2**20), b""):
                digest.update(block)
    except OSError as exc:
        raise BundleError(f"cannot read {path}: {exc.strerror or exc}") from None
    return digest.hexdigest()
