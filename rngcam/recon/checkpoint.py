"""A result folder's checkpoint and the rules for writing into a folder.

A checkpoint (`checkpoint.pt`) carries, next to the loop's state, the identity of the run that
wrote it: the bundle's sha256, the method and every setting that changes what is fitted (the
method's settings, the grid, the held-out split). `--resume` continues only a checkpoint whose
identity matches the new run's; anything else is refused in one line before the folder is
touched. `--overwrite` removes every file a run writes (and only those) before it starts.
"""

from __future__ import annotations

import json
import os
from pathlib import Path

import torch

from rngcam.errors import RngcamError

CHECKPOINT_NAME = "checkpoint.pt"
LOG_NAME = "recon.log"
# Every file a reconstruction writes into its folder (report.html: the report of the folder).
OUTPUT_NAMES = ("recon.h5", "video.tif", "preview.mp4", "preview.json", "errors.csv", "errors.png", "metrics.json",
                CHECKPOINT_NAME, CHECKPOINT_NAME + ".partial", LOG_NAME, "report.html")
CHECKPOINT_FORMAT = 2  # 1: no identity (before resume was checked)


def identity(bundle_sha256: str | None, method: str, fitted: dict) -> dict:
    """What a checkpoint must match to be resumed: bundle, method and the fitted settings."""
    return {"bundle_sha256": bundle_sha256, "method": method,
            "settings": json.loads(json.dumps(fitted, sort_keys=True, default=str))}


def save(path: Path, payload: dict) -> None:
    """Write `payload` (with CHECKPOINT_FORMAT) atomically: a partial file, then a rename."""
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_name(path.name + ".partial")
    torch.save({**payload, "format": CHECKPOINT_FORMAT}, tmp)
    os.replace(tmp, path)


def load(path: Path) -> dict:
    """The checkpoint at `path`; RngcamError (one line) when it cannot be read."""
    try:
        return torch.load(path, weights_only=False)  # tensors back on the device they were saved from
    except Exception as exc:  # noqa: BLE001 - any failure to read is the same for the user
        raise RngcamError(f"cannot read the checkpoint {path}: {type(exc).__name__}: {exc}") from None


def mismatch(saved: dict, want: dict) -> str:
    """'' when the saved identity matches `want`, else what differs, in a few words."""
    have = saved.get("identity")
    if have is None:
        return "it was written by an older rngcam and does not say which bundle and settings it fits"
    if have["bundle_sha256"] != want["bundle_sha256"]:
        return (f"it fits another bundle (sha256 {str(have['bundle_sha256'])[:12]}..., this one is "
                f"{str(want['bundle_sha256'])[:12]}...)")
    if have["method"] != want["method"]:
        return f"it is {have['method']}'s, not {want['method']}'s"
    differ = _differences(have["settings"], want["settings"])
    if differ:
        return "its settings differ: " + ", ".join(f"{k} {a!r} there, {b!r} now" for k, a, b in differ[:3])
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
        return json.loads((out / "metrics.json").read_text()).get("method")
    except (OSError, ValueError, AttributeError):
        return None


def prepare(out: Path, want: dict, resume: bool, overwrite: bool) -> dict | None:
    """Check that a run may write into `out` and clear what it replaces; returns the checkpoint to
    resume from (None: start afresh). Every refusal is one RngcamError line, raised before any
    file in `out` is touched."""
    if out.exists() and not out.is_dir():
        raise RngcamError(f"output folder {out} is a file")
    full = out.is_dir() and any(out.iterdir())
    if resume:
        ckpt = out / CHECKPOINT_NAME
        if not ckpt.is_file():
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
    if full and not overwrite:
        hint = " (or --resume to continue from its checkpoint)" if (out / CHECKPOINT_NAME).is_file() else ""
        raise RngcamError(f"output folder {out} is not empty; pass --overwrite to replace what is in it{hint}")
    for name in OUTPUT_NAMES if full else ():
        (out / name).unlink(missing_ok=True)
    return None
