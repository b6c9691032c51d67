"""One factory for the rig's cameras: `open_devices(resolved)` gives capture and calibration the
same face whatever the backend (GenTL via harvesters, Basler pylon, or the physics-based mock,
rngcam.acquire.mock_backend), so neither asks which one it is.

A `Devices` makes each role's camera (enter it to open it), puts a static target in front of
the cameras when it can (`show`: only the mock can; on hardware the operator does), starts a
shot (`begin_shot`) and gives the scene's ground truth when it knows it (`truth`: mock only).
"""

from __future__ import annotations

from typing import Protocol

from rngcam.acquire.camera import Camera
from rngcam.acquire.resolve import ResolvedRig
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


class HardwareDevices:
    """Real cameras, opened by serial number."""

    kind = "hardware"

    def __init__(self, resolved: ResolvedRig):
        self.resolved = resolved

    def camera(self, role: str) -> Camera:
        cfg = getattr(self.resolved.rig.config.cameras, role)
        if cfg.backend == "pylon":
            from rngcam.acquire.pylon_camera import PylonCamera

            return PylonCamera(cfg.serial, role.upper(), transport=cfg.pylon_transport)
        from rngcam.acquire.genicam_camera import GenicamCamera

        return GenicamCamera(cfg.serial, role.upper(), cti=cfg.cti)

    def show(self, target: str) -> bool:
        return False  # the operator puts it up

    def begin_shot(self) -> None:
        pass

    def truth(self) -> Truth | None:
        return None


def open_devices(resolved: ResolvedRig) -> Devices:
    """The rig's devices: the mock backend for a mock rig (resolved.mock), else real cameras."""
    if resolved.mock is not None:
        from rngcam.acquire.mock_backend import MockDevices

        return MockDevices(resolved)
    return HardwareDevices(resolved)
