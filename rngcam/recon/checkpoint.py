"""A result folder's checkpoint and the rules for writing into a folder.

A checkpoint (`checkpoint.pt`) carries, next to the loop's state, the identity of the run that
wrote it: the bundle's sha256, the method and every setting that changes what is fitted (the
method's settings, the grid, the held-out split). `--resume` continues only a checkpoint whose
identity matches the new run's; anything else is refused in one line before the folder is
touched. `--overwrite` removes every file a run writes (and only those) before it starts.

A checkpoint may come from someone else (a shared folder), so it is data only: tensors, numbers,
strings, lists and dicts, read with `torch.load(weights_only=True)`, which builds no other object
and runs no code; the loop's part of it is checked before the method's state is used.
"""

from __future__ import annotations

import json
import math
import os
import pickle
import stat
import zipfile
from pathlib import Path

import numpy as np
import torch

from rngcam.errors import RngcamError
from rngcam.h5safe import memory_limit_bytes
from rngcam.untrusted import (
    UntrustedFileError,
    clean_temps,
    load_json,
    open_own,
    open_untrusted,
    printable,
    read_untrusted,
    same_file,
    temp_beside,
)

CHECKPOINT_NAME = "checkpoint.pt"
LOG_NAME = "recon.log"
# Every file a reconstruction writes into its folder (report.html: the report of the folder);
# checkpoint.pt.partial and .metrics.json.partial: an older rngcam's temporary names.
OUTPUT_NAMES = ("recon.h5", "video.tif", "preview.mp4", "preview.json", "errors.csv", "errors.png", "metrics.json",
                CHECKPOINT_NAME, CHECKPOINT_NAME + ".partial", ".metrics.json.partial", LOG_NAME, "report.html")
# 1: no identity (before resume was checked); 2: arbitrary pickled objects (never read now);
# 3: data only (tensors and plain values).
CHECKPOINT_FORMAT = 3
# What a refused checkpoint outside `recon` (a sweep trial's, the loop's own resume) says to do.
RESUME_HINT = "remove it, or use another folder"
OLDER = "it was written by an older rngcam (or not by rngcam) and holds more than data"


def identity(bundle_sha256: str | None, method: str, fitted: dict) -> dict:
    """What a checkpoint must match to be resumed: bundle, method and the fitted settings."""
    return {"bundle_sha256": bundle_sha256, "method": method,
            "settings": json.loads(json.dumps(fitted, sort_keys=True, default=str))}


def save(path: Path, payload: dict) -> None:
    """Write `payload` (with CHECKPOINT_FORMAT), as plain data, atomically: a uniquely named
    temporary file beside it, then a rename (which replaces a planted link, never follows it)."""
    path.parent.mkdir(parents=True, exist_ok=True)
    data = plain({**payload, "format": CHECKPOINT_FORMAT})
    tmp = temp_beside(path)
    try:
        with open_own(tmp, "wb") as f:
            torch.save(data, f)
        os.replace(tmp, path)
    except BaseException:
        tmp.unlink(missing_ok=True)
        raise


class Kept:
    """A tensor in a method's state that the method never changes in place (it replaces it): a
    deep copy of the state (the loop keeps one as its last good state) shares the tensor instead
    of copying a video. `kept(value)` gives the tensor back (or a value that was not wrapped)."""

    __slots__ = ("tensor",)

    def __init__(self, tensor: torch.Tensor):
        self.tensor = tensor

    def __deepcopy__(self, memo) -> Kept:
        return self


def kept(value):
    """The tensor inside a `Kept`, or `value` itself."""
    return value.tensor if isinstance(value, Kept) else value


def plain(obj):
    """`obj` as what weights_only loading reads back: a method state's `Kept` wrappers unwrapped,
    numpy arrays as tensors and numpy scalars as Python numbers, containers rebuilt."""
    if isinstance(obj, Kept):
        return obj.tensor
    if isinstance(obj, np.generic):  # before the Python types: numpy's float64 is a float
        return obj.item()
    if isinstance(obj, torch.Tensor | str | bytes | bool | int | float | type(None) | torch.dtype | torch.device):
        return obj
    if isinstance(obj, dict):
        return {k: plain(v) for k, v in obj.items()}
    if isinstance(obj, list | tuple):
        return [plain(v) for v in obj] if isinstance(obj, list) else tuple(plain(v) for v in obj)
    if isinstance(obj, np.ndarray):
        return torch.from_numpy(np.ascontiguousarray(obj))
    raise TypeError(f"a checkpoint holds data only, not a {type(obj).__name__}")


def load(path: Path, map_location=None, hint: str = "use --overwrite to start again") -> dict:
    """The checkpoint at `path`, read as data only (tensors back on the device they were saved
    from unless `map_location`); RngcamError, one line, when it is not a regular file, holds more
    than data (an older rngcam's, or a crafted one: nothing in it runs), is of another format or
    is not shaped as rngcam writes one; the line ends with `hint`."""
    where = f"cannot resume from {path}"
    try:
        with open_untrusted(path, memory_limit_bytes(), what="checkpoint") as f:
            why = _archive_problem(f)
            if why:
                raise RngcamError(f"{where}: it is not a checkpoint as rngcam writes one ({why}); {hint}")
            f.seek(0)
            saved = torch.load(f, weights_only=True, map_location=map_location)
    except UntrustedFileError as exc:
        raise RngcamError(f"{where}: {str(exc).split(': ', 1)[-1]}; {hint}") from None
    except RngcamError:
        raise
    except pickle.UnpicklingError:
        raise RngcamError(f"{where}: {OLDER}; {hint}") from None
    except Exception as exc:  # noqa: BLE001 - any failure to read is the same for the user
        raise RngcamError(f"{where}: cannot read it ({type(exc).__name__}: {printable(exc, 200)}); "
                          f"{hint}") from None
    fmt = saved.get("format") if isinstance(saved, dict) else None
    if fmt != CHECKPOINT_FORMAT:
        newer = isinstance(fmt, int) and not isinstance(fmt, bool) and fmt > CHECKPOINT_FORMAT
        raise RngcamError(f"{where}: it was written by {'a newer' if newer else 'an older'} rngcam (checkpoint "
                          f"format {printable(fmt, 20)}, this one reads {CHECKPOINT_FORMAT}); "
                          f"{hint}")
    why = _malformed(saved)
    if why:
        raise RngcamError(f"{where}: it is not a checkpoint as rngcam writes one ({why}); "
                          f"{hint}")
    return saved


MAX_RECORDS = 100_000  # records in one checkpoint archive (a state of a few hundred tensors)


def _archive_problem(f) -> str:
    """'' when the open file is a zip archive as torch.save writes one: every record stored, not
    compressed (so nothing inflates before the checkpoint's identity is checked), its declared
    sizes equal and inside the file, in its central directory and its local header alike."""
    size = os.fstat(f.fileno()).st_size
    try:
        infos = zipfile.ZipFile(f).infolist()
    except (zipfile.BadZipFile, zipfile.LargeZipFile, OSError, ValueError, EOFError):
        return "not a zip archive"
    if len(infos) > MAX_RECORDS:
        return f"{len(infos):,} records"
    total = 0
    for info in infos:
        name = printable(info.filename, 60)
        if info.compress_type != zipfile.ZIP_STORED or info.file_size != info.compress_size:
            return f"record {name} is compressed (method {info.compress_type}); rngcam stores records as they are"
        f.seek(info.header_offset)
        local = f.read(30)
        if len(local) < 30 or local[:4] != b"PK\x03\x04" or int.from_bytes(local[8:10], "little") != 0:
            return f"record {name} has a damaged or compressed local header"
        total += info.file_size
        if info.header_offset + info.file_size > size or total > size:
            return f"record {name} declares more bytes than the file holds"
    return ""


_NUMBER = (int, float)
_FIELDS = {"iteration": int, "solve_s": _NUMBER, "wall_s": _NUMBER, "log": list, "events": list,
           "rng": torch.Tensor, "method": (dict, type(None)), "identity": (dict, type(None))}


def _malformed(saved: dict) -> str:
    """'' when the loop's part of `saved` has the types the loop uses, else which field is off."""
    for key, kind in _FIELDS.items():
        value = saved.get(key)
        if not isinstance(value, kind) or isinstance(value, bool):
            return f"its {key!r} is a {type(value).__name__}"
    if saved["iteration"] < 0 or not all(math.isfinite(saved[k]) and saved[k] >= 0 for k in ("solve_s", "wall_s")):
        return "a negative or non-finite count"
    if not all(isinstance(e, str) for e in saved["events"]) or not all(isinstance(r, dict) for r in saved["log"]):
        return "its events or log rows are not text and tables"
    rng = saved["rng"]
    if rng.dtype != torch.uint8 or rng.dim() != 1 or rng.device.type != "cpu":
        return "its random state is not a CPU byte tensor"
    return ""


def mismatch(saved: dict, want: dict) -> str:
    """'' when the saved identity matches `want`, else what differs, in a few words."""
    have = saved.get("identity")
    if not isinstance(have, dict) or not isinstance(have.get("settings"), dict):
        return "it was written by an older rngcam and does not say which bundle and settings it fits"
    if have.get("bundle_sha256") != want["bundle_sha256"]:
        return (f"it fits another bundle (sha256 {printable(have.get('bundle_sha256'), 12)}, this one is "
                f"{str(want['bundle_sha256'])[:12]}...)")
    if have.get("method") != want["method"]:
        return f"it is {printable(have.get('method'), 40)}'s, not {want['method']}'s"
    differ = _differences(have["settings"], want["settings"])
    if differ:
        return "its settings differ: " + ", ".join(
            f"{printable(k, 60)} {printable(repr(a), 60)} there, {b!r} now" for k, a, b in differ[:3])
    return ""


def _differences(a: dict, b: dict, prefix: str = "") -> list[tuple[str, object, object]]:
    """(dotted key, value in a, value in b) for every leaf where two nested dicts differ."""
    out = []
    for k in sorted(set(a) | set(b), key=str):
        x, y = a.get(k), b.get(k)
        if isinstance(x, dict) and isinstance(y, dict):
            out += _differences(x, y, f"{prefix}{k}.")
        elif x != y:
            out.append((f"{prefix}{k}", x, y))
    return out


def folder_method(out: Path) -> str | None:
    """The method whose outputs are in `out` (its metrics.json), or None."""
    try:
        text = read_untrusted(out / "metrics.json", 16 * 2**20, what="metrics.json", within=out)
        method = load_json(text, "metrics.json").get("method")
    except (RngcamError, AttributeError):
        return None
    return printable(method, 40) if method is not None else None


def prepare(out: Path, want: dict, resume: bool, overwrite: bool, inputs: tuple[Path, ...] = ()) -> dict | None:
    """Check that a run may write into `out` and clear what it replaces; returns the checkpoint to
    resume from (None: start afresh). Every refusal is one RngcamError line, raised before any
    file in `out` is touched. `inputs` (the bundle read) are never replaced or removed: an output
    name that is one of them, or leads to one, is refused."""
    if out.exists() and not out.is_dir():
        raise RngcamError(f"output folder {out} is a file")
    full = out.is_dir() and any(out.iterdir())
    if full:
        _refuse_inputs(out, inputs)
        _refuse_odd_entries(out)
    saved = _resumable(out, want, full) if resume else None
    if not resume and full and not overwrite:
        hint = " (or --resume to continue from its checkpoint)" if (out / CHECKPOINT_NAME).is_file() else ""
        raise RngcamError(f"output folder {out} is not empty; pass --overwrite to replace what is in it{hint}")
    if full:
        clean_temps(out)  # an interrupted write's leftovers
        for name in OUTPUT_NAMES:  # a resumed run keeps its files; a link planted at their names goes
            if not resume or (out / name).is_symlink():
                _remove(out / name)
    return saved


def _resumable(out: Path, want: dict, full: bool) -> dict | None:
    """The checkpoint in `out` that this run continues (None: nothing there yet), checked as data
    and against `want` before any of its state is used; one RngcamError line otherwise."""
    ckpt = out / CHECKPOINT_NAME
    if not os.path.lexists(ckpt):
        if not full:
            return None  # nothing there yet: a fresh start loses nothing
        other = folder_method(out)
        whose = f" (it holds {other}'s outputs)" if other and other != want["method"] else ""
        raise RngcamError(f"cannot resume: {out} has no {CHECKPOINT_NAME}{whose}; "
                          f"use another folder, or --overwrite to replace it")
    saved = load(ckpt)
    why = mismatch(saved, want)
    if why:
        raise RngcamError(f"cannot resume from {ckpt}: {why}; use another folder, or --overwrite to start again")
    return saved


def _refuse_inputs(out: Path, inputs: tuple[Path, ...]) -> None:
    """One RngcamError line when an output name in `out` is an input (or a link to one)."""
    for name in OUTPUT_NAMES:
        p = out / name
        if not os.path.lexists(p):
            continue
        for given in inputs:
            if same_file(p, Path(given)):
                raise RngcamError(f"{p} is the bundle this run reads; it would be replaced by an output: "
                                  f"move the bundle or use another output folder")


def _refuse_odd_entries(out: Path) -> None:
    """One RngcamError line when an output name in `out` is neither a file nor a link (a folder, a
    pipe): the run could neither replace nor remove it."""
    for name in OUTPUT_NAMES:
        try:
            mode = os.lstat(out / name).st_mode
        except FileNotFoundError:
            continue
        if not (stat.S_ISREG(mode) or stat.S_ISLNK(mode)):
            raise RngcamError(f"{out / name} is not a file; move it, or use another output folder")


def _remove(p: Path) -> None:
    """Remove the output `p` (a link itself, never what it names); one line if it cannot be."""
    try:
        p.unlink(missing_ok=True)
    except OSError as exc:
        raise RngcamError(f"cannot remove {p} to replace it: {exc.strerror or exc}") from None
