"""Every acquisition backend rngcam knows, in one table: cameras and generator transports, real
ones and their fake twins.

A backend is one module plus one line here. Camera modules provide
`make_camera(cfg, role) -> Camera` and `list_cameras(**options) -> list[CameraInfo]`;
generator-transport modules provide `open_transport(cfg, stack, progress) -> (transport, fake)`
(`fake`: an in-process instrument that delivers its pulses to simulated cameras, else None).
Rig validation (rngcam.config), the device factory (rngcam.acquire.factory), `rngcam devices`,
`rngcam capture` and `rngcam doctor` all read these tables, so none of them spells a backend.

A *simulated* backend is a fake twin: simulated cameras take their triggers from a simulated
generator (the fake instrument hands them its pulse trains), so the two go together in a rig.
"""

from __future__ import annotations

import importlib
import importlib.util
from dataclasses import dataclass


@dataclass(frozen=True)
class BackendSpec:
    """One backend: its rig name, implementing module, and what it needs to run."""

    name: str
    module: str
    summary: str
    simulated: bool = False
    twin_of: str | None = None  # the real backend a fake twin stands in for
    needs: tuple[str, ...] = ()  # Python modules it imports
    install: str = ""  # how to get what it needs

    def missing(self) -> list[str]:
        """The modules of `needs` this interpreter cannot import (found, not imported)."""
        out = []
        for name in self.needs:
            try:
                found = importlib.util.find_spec(name) is not None
            except (ImportError, ValueError):
                found = False
            if not found:
                out.append(name)
        return out

    def load(self):
        """The implementing module (imported on first use)."""
        return importlib.import_module(self.module)


_ARAVIS_INSTALL = ("apt-get install gir1.2-aravis-0.8 libgirepository1.0-dev, then `make aravis` "
                   "(PyGObject 3.50.2 built against Debian's GObject introspection)")

CAMERAS: dict[str, BackendSpec] = {s.name: s for s in (
    BackendSpec("genicam", "rngcam.acquire.genicam_camera", "any GenICam camera through a GenTL producer (.cti)",
                needs=("harvesters", "genicam"), install="pip install 'rngcam[genicam]'"),
    BackendSpec("pylon", "rngcam.acquire.pylon_camera", "Basler cameras through pylon (pypylon)",
                needs=("pypylon",), install="pip install 'rngcam[pylon]'"),
    BackendSpec("aravis", "rngcam.acquire.aravis_camera", "GigE Vision / USB3 Vision cameras through Aravis",
                needs=("gi",), install=_ARAVIS_INSTALL),
    BackendSpec("aravis-fake", "rngcam.acquire.aravis_fake", "Aravis's fake GigE Vision camera on loopback",
                simulated=True, twin_of="aravis", needs=("gi",), install=_ARAVIS_INSTALL),
    BackendSpec("mock", "rngcam.acquire.mock_backend", "physics-based mock cameras looking at a simulated scene",
                simulated=True),
)}

GENERATORS: dict[str, BackendSpec] = {s.name: s for s in (
    BackendSpec("serial", "rngcam.acquire.scpi", "SCPI over a serial port (RS-232, USB-serial)",
                needs=("serial",), install="pip install pyserial"),
    BackendSpec("visa", "rngcam.acquire.scpi", "SCPI over VISA (USB-TMC, LAN); `visa_library: sim` "
                "runs the instrument definitions in rngcam/acquire/instruments (pyvisa-sim)",
                needs=("pyvisa",), install="pip install 'rngcam[visa]'"),
    BackendSpec("fake", "rngcam.acquire.fake_generator", "a simulated instrument on a pseudo-terminal that "
                "triggers simulated cameras", simulated=True, twin_of="serial"),
)}


def camera_backend(name: str) -> BackendSpec:
    """The camera backend called `name`; ValueError naming the known ones."""
    try:
        return CAMERAS[name]
    except KeyError:
        raise ValueError(f"unknown camera backend {name!r} (known: {', '.join(CAMERAS)})") from None


def generator_transport(name: str) -> BackendSpec:
    """The generator transport called `name`; ValueError naming the known ones."""
    try:
        return GENERATORS[name]
    except KeyError:
        raise ValueError(f"unknown generator transport {name!r} (known: {', '.join(GENERATORS)})") from None
