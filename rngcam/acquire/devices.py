"""Listing what is connected: cameras per backend and serial ports.

Discovery is explicit: genicam loads only the producer file it is given; pylon can be held to
one transport layer (e.g. BaslerCamEmu). Unrestricted pylon discovery broadcasts on GigE
networks, so the CLI only does it when asked for the pylon backend.
"""

from __future__ import annotations

from dataclasses import dataclass

from rngcam.acquire.camera import CameraInfo
from rngcam.errors import HardwareError


@dataclass(frozen=True)
class SerialPortInfo:
    device: str
    description: str
    hwid: str


def list_serial_ports() -> list[SerialPortInfo]:
    from serial.tools import list_ports

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


def list_cameras(backend: str, cti: str | None = None, pylon_transport: str | None = None,
                 rig=None) -> list[CameraInfo]:
    """Cameras of one backend; HardwareError (one line) when the backend is unavailable."""
    if backend == "mock":
        return list_mock_cameras(rig)
    if backend == "pylon":
        from rngcam.acquire.pylon_camera import list_pylon_cameras

        return list_pylon_cameras(pylon_transport)
    if backend == "genicam":
        from rngcam.acquire.genicam_camera import list_genicam_cameras

        return list_genicam_cameras(cti)
    raise HardwareError(f"unknown backend {backend!r} (genicam, pylon or mock)")
