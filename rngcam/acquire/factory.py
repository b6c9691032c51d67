"""One factory for the rig's cameras and generator: `open_devices(resolved)` gives capture and
calibration the same face whatever the backend, and `open_generator(rig, stack, progress)` the
function generator on whatever transport, real or fake. Both look the backend up in the table of
rngcam.backends (a new backend is one module and one line there), so nothing else asks which
one it is.

A `Devices` makes each role's camera (enter it to open it), puts a static target in front of
the cameras when it can (`show`: only the mock can; on hardware the operator does), starts a
shot (`begin_shot`) and gives the scene's ground truth when it knows it (`truth`: mock only).
"""

from __future__ import annotations

import contextlib
from collections.abc import Callable
from typing import Protocol

from rngcam.acquire.camera import Camera
from rngcam.acquire.generator import FunctionGenerator
from rngcam.acquire.resolve import ResolvedRig
from rngcam.backends import CAMERAS, GENERATORS, BackendSpec
from rngcam.config import Rig
from rngcam.errors import HardwareError
from rngcam.formats.bundle import Truth


class Devices(Protocol):
    """What capture and calibration use of a rig's cameras, whatever their backend."""

    kind: str
    resolved: ResolvedRig

    def camera(self, role: str) -> Camera:
        """The camera for `role` ("rs" or "gs"), not yet opened (a context manager)."""

    def show(self, target: str) -> bool:
        """Put a static target ("point", "chart", "dark") up; False: someone else must."""

    def begin_shot(self) -> None:
        """Called before each shot's cameras are armed."""

    def truth(self) -> Truth | None:
        """The ground-truth video of the last shot, when the backend knows it."""


def load_backend(spec: BackendSpec):
    """The backend's module; HardwareError (one line: what is missing and how to get it)."""
    missing = spec.missing()
    if missing:
        raise HardwareError(f"backend {spec.name!r} needs {', '.join(missing)} (not installed): {spec.install}")
    try:
        return spec.load()
    except ImportError as exc:
        raise HardwareError(f"backend {spec.name!r} cannot be loaded ({exc}): {spec.install}") from None


class HardwareDevices:
    """Cameras made one by one by their backend module's `make_camera(cfg, role)`."""

    kind = "hardware"

    def __init__(self, resolved: ResolvedRig):
        self.resolved = resolved

    def camera(self, role: str) -> Camera:
        cfg = getattr(self.resolved.rig.config.cameras, role)
        return load_backend(CAMERAS[cfg.backend]).make_camera(cfg, role)

    def show(self, target: str) -> bool:
        return False  # the operator puts it up

    def begin_shot(self) -> None:
        pass

    def truth(self) -> Truth | None:
        return None


def needs_private_network(rig: Rig) -> bool:
    """True when a backend of the rig serves simulated network cameras (rngcam.acquire.netns):
    the process must then run in a network namespace of its own."""
    for name in {rig.config.cameras.rs.backend, rig.config.cameras.gs.backend}:
        spec = CAMERAS[name]
        if spec.simulated and spec.twin_of is not None and not spec.missing():
            module = spec.load()
            if getattr(module, "needs_private_network", lambda r: False)(rig):
                return True
    return False


def open_devices(resolved: ResolvedRig) -> Devices:
    """The rig's devices: a backend that simulates a whole world (the mock: `make_devices`)
    makes them itself, the others camera by camera."""
    module = load_backend(CAMERAS[resolved.rig.config.cameras.rs.backend])
    if hasattr(module, "make_devices"):
        return module.make_devices(resolved)
    return HardwareDevices(resolved)


def open_generator(rig: Rig, stack: contextlib.ExitStack, progress: Callable[[str], None] = print):
    """(FunctionGenerator, fake instrument or None), both closed by `stack`. The transport's
    module opens the line (a fake one serves a simulated instrument first)."""
    g = rig.config.generator
    cams = rig.config.cameras
    channels = (cams.rs.trigger.channel, cams.gs.trigger.channel)
    transport, fake = load_backend(GENERATORS[g.transport]).open_transport(g, stack, progress, channels)
    gen = stack.enter_context(FunctionGenerator(transport, g.dialect, link=g.link))
    progress(f"generator: {gen.identify()} ({g.dialect} over {g.transport})")
    return gen, fake
