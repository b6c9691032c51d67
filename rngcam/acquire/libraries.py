"""Native libraries a rig names: loaded only where the user named them, and tried first in a child.

A rig's `cameras.*.cti` (a GenTL producer, loaded by harvesters) and `generator.visa_library` (a
VISA library, loaded by pyvisa) are shared libraries loaded into this process, so their
constructors run here. A rig copied from elsewhere may name any file, so one outside the vendors'
install locations (`vendor_location`) is refused unless the user names it too: --allow-library,
$RNGCAM_ALLOW_LIBRARY (paths or folders, separated by ':'), $GENICAM_GENTL64_PATH (the GenTL
folders) or $RNGCAM_CTI. Before a library is loaded in-process it is loaded once in a child process
(`probe`), so one that crashes on load is one line instead of a crash of ours.
"""

from __future__ import annotations

import os
import signal
import site
import subprocess
import sys
import sysconfig
from pathlib import Path

from rngcam.errors import ConfigError, HardwareError
from rngcam.untrusted import printable

ALLOW_ENV = "RNGCAM_ALLOW_LIBRARY"
GENTL_ENV = "GENICAM_GENTL64_PATH"
CTI_ENV = "RNGCAM_CTI"
PROBE_TIMEOUT_S = 60.0
# Wheels that ship GenTL producers (pypylon's, the genicam wheel's test producer viky.cti).
_WHEEL_PACKAGES = ("pypylon", "genicam")
_LIB_DIRS = ("/usr/lib", "/usr/lib64", "/usr/local/lib", "/usr/local/lib64", "/lib", "/lib64")

_probed: set[str] = set()


def allow(paths) -> None:
    """Allow these libraries for this process and the processes it starts (--allow-library)."""
    extra = [str(Path(p).expanduser().resolve()) for p in paths]
    if extra:
        current = [p for p in os.environ.get(ALLOW_ENV, "").split(os.pathsep) if p]
        os.environ[ALLOW_ENV] = os.pathsep.join(current + extra)


def _site_dirs() -> list[Path]:
    dirs = set(site.getsitepackages()) | {site.getusersitepackages()}
    dirs |= {sysconfig.get_paths()[k] for k in ("purelib", "platlib")}
    return [Path(d).resolve() for d in dirs if d]


def vendor_location(path: Path) -> bool:
    """True for a library where a vendor's installer puts it: Basler pylon under /opt/pylon*, a
    producer inside the pypylon or genicam wheel, Aravis' GenTL producer or NI-VISA's libvisa in
    the system's library folders."""
    path = Path(path).resolve()
    parts = path.parts
    if len(parts) > 2 and parts[1] == "opt" and parts[2].startswith("pylon"):
        return True
    for d in _site_dirs():
        if any(path.is_relative_to(d / pkg) for pkg in _WHEEL_PACKAGES):
            return True
    in_lib = any(path.is_relative_to(d) for d in _LIB_DIRS) or path.is_relative_to("/usr/local/vxipnp")
    name = path.name.lower()
    return in_lib and (name.startswith("libvisa.so") or ("aravis" in name and name.endswith(".cti")))


def _user_named() -> list[Path]:
    """The files and folders the user named in the environment (and with --allow-library)."""
    entries = os.environ.get(ALLOW_ENV, "").split(os.pathsep) + os.environ.get(GENTL_ENV, "").split(os.pathsep)
    entries.append(os.environ.get(CTI_ENV, ""))
    return [Path(e).expanduser().resolve() for e in entries if e.strip()]


def allowed(path: Path) -> bool:
    """True when `path` is in a vendor location or the user named it (or its folder)."""
    path = Path(path).resolve()
    if vendor_location(path):
        return True
    return any(path == p or (p.is_dir() and path.parent == p) for p in _user_named())


def check(path: Path, key: str, what: str, source: str = "the rig") -> None:
    """Refuse (one line) a library `key` of a rig names outside the vendor locations unless the
    user allowed it; then probe it."""
    path = Path(path).expanduser().resolve()
    if not allowed(path):
        shown = printable(path)
        raise ConfigError(f"{printable(source)}: {key}: refusing to load the {what} {shown}: it is not in a "
                          "vendor's install location and you did not name it (a rig from elsewhere could run "
                          f"code through it); to allow it pass --allow-library {shown} or set {ALLOW_ENV}={shown}")
    probe(path, what)


def probe(path: Path, what: str) -> None:
    """Load `path` in a child process first: a library that crashes or fails on load is one
    HardwareError here rather than a crash of this process. Each path is tried once a process."""
    path = Path(path)
    if str(path) in _probed:
        return
    code = "import ctypes, sys; ctypes.CDLL(sys.argv[1])"
    try:
        res = subprocess.run([sys.executable, "-I", "-S", "-c", code, str(path)], stdin=subprocess.DEVNULL,
                             capture_output=True, text=True, errors="replace", timeout=PROBE_TIMEOUT_S)
    except subprocess.TimeoutExpired:
        raise HardwareError(f"the {what} {printable(path)} did not finish loading within "
                            f"{PROBE_TIMEOUT_S:g} s (tried in a child process)") from None
    if res.returncode < 0:
        try:
            name = f", {signal.Signals(-res.returncode).name}"
        except ValueError:
            name = ""
        raise HardwareError(f"the {what} {printable(path)} crashed when loaded (signal {-res.returncode}{name})")
    if res.returncode != 0:
        last = (res.stderr.strip().splitlines() or ["exit status " + str(res.returncode)])[-1]
        raise HardwareError(f"the {what} {printable(path)} cannot be loaded ({printable(last)})")
    _probed.add(str(path))


def visa_library_path(spec: str | None) -> Path | None:
    """The shared library a pyvisa library spec makes pyvisa load, or None when it loads none
    of the rig's ('@py', '@sim', 'sim', 'definitions.yaml@sim', a bare '@ivi': the system's).
    A bare name without a slash ('libvisa.so.21') is looked up by the dynamic loader in the
    system's folders; it is returned as given."""
    if not spec or spec == "sim":
        return None
    text, at, backend = spec.rpartition("@")
    if not at:
        text, backend = spec, "ivi"
    if backend != "ivi" or not text:
        return None  # a Python backend (pyvisa-py, pyvisa-sim) or the system's VISA
    return Path(text)


def check_visa_library(spec: str | None, key: str = "generator.visa_library", source: str = "the rig") -> None:
    """Check and probe the library a rig's visa_library names (`visa_library_path`)."""
    path = visa_library_path(spec)
    if path is None:
        return
    if "/" not in str(path) and not path.exists():
        if "visa" in path.name.lower():
            return  # a system VISA library by name: the loader searches the system's folders only
        raise ConfigError(f"{printable(source)}: {key}: {printable(spec)} names no file and no VISA library; "
                          "give the library's path")
    check(path, key, "VISA library", source)


def check_rig(rig) -> None:
    """Check every native library the rig names (module doc); ConfigError/HardwareError, one line."""
    source = str(rig.path)
    for role in ("rs", "gs"):
        cfg = getattr(rig.config.cameras, role)
        if cfg.backend == "genicam" and cfg.cti:
            check(Path(cfg.cti).expanduser(), f"cameras.{role}.cti", "GenTL producer", source)
    g = rig.config.generator
    if g.transport == "visa":
        check_visa_library(g.visa_library, source=source)
