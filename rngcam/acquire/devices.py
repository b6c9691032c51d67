"""Listing what is connected: cameras per backend and serial ports.

Discovery is explicit: genicam loads only the producer file it is given; pylon can be held to
one transport layer (e.g. BaslerCamEmu); aravis opens the addresses it is given (its discovery
broadcasts on every interface, so it runs only when asked). Unrestricted pylon or aravis
discovery broadcasts on GigE networks, so the CLI only does it when asked for that backend.
"""

from __future__ import annotations

from dataclasses import dataclass

from rngcam.acquire.camera import CameraInfo
from rngcam.backends import CAMERAS
from rngcam.errors import HardwareError


@dataclass(frozen=True)
class SerialPortInfo:
    device: str
    description: str
    hwid: str


def list_serial_ports() -> list[SerialPortInfo]:
    from serial.tools import list_ports  # heavy: pyserial, kept off the capture commands' start

    return [SerialPortInfo(p.device, p.description or "", p.hwid or "")
            for p in sorted(list_ports.comports(), key=lambda p: p.device)]


def list_mock_cameras(rig=None) -> list[CameraInfo]:
    """The mock cameras a rig plugs in (those of rigs/mock.yaml when no rig is given)."""
    if rig is None:
        return [CameraInfo("mock", "Mock acA5472-17uc", "MOCK-RS-0001", "simulated", "rngcam"),
                CameraInfo("mock", "Mock acA1920-155uc", "MOCK-GS-0001", "simulated", "rngcam")]
    cams = rig.config.cameras
    return [CameraInfo("mock", c.model or f"mock {role.upper()}", c.serial, "simulated", "rngcam")
            for role, c in (("rs", cams.rs), ("gs", cams.gs)) if c.backend == "mock"]


def list_cameras(backend: str, rig=None, **options) -> list[CameraInfo]:
    """Cameras of one backend (rngcam.backends); HardwareError (one line) when it is unknown or
    unavailable. `options` go to the backend's lister (cti, pylon_transport, address ...)."""
    from rngcam.acquire.factory import load_backend  # heavy: factory loads cv2, h5py, torch

    spec = CAMERAS.get(backend)
    if spec is None:
        raise HardwareError(f"unknown backend {backend!r} ({', '.join(CAMERAS)})")
    return load_backend(spec).list_cameras(rig=rig, **options)
