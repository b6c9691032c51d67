"""Basler pylon backend (pypylon, the optional extra `rngcam[pylon]`).

`transport` restricts discovery to one pylon transport layer, e.g. "BaslerCamEmu" (the
camera emulator, which needs PYLON_CAMEMU set before the layer is created; this backend sets
it to 1 when absent). Without it every layer is searched, which on GigE broadcasts discovery
packets: tests always name the emulator layer.
"""

from __future__ import annotations

import os

from rngcam.acquire.camera import Camera, CameraInfo, CameraSettings, Configured, Frame
from rngcam.acquire.features import FeatureMap, apply_settings, estimate_line_time_s, latch_ticks
from rngcam.errors import HardwareError

EMULATOR_TL = "BaslerCamEmu"


def _pylon():
    try:
        from pypylon import genicam, pylon  # optional: pylon extra
    except ImportError:
        raise HardwareError("the pylon backend needs pypylon: pip install 'rngcam[pylon]'") from None
    return pylon, genicam


def _transport_layer(transport: str | None):
    """(factory, layer or None). The emulator layer needs PYLON_CAMEMU before creation."""
    pylon, _ = _pylon()
    factory = pylon.TlFactory.GetInstance()
    if transport is None:
        return factory, None
    if transport == EMULATOR_TL:
        os.environ.setdefault("PYLON_CAMEMU", "1")
    tl = factory.CreateTl(transport)
    if tl is None:
        raise HardwareError(f"pylon transport layer {transport!r} is not available")
    return factory, tl


def list_pylon_cameras(transport: str | None = None) -> list[CameraInfo]:
    """Cameras pylon sees (on one transport layer when given)."""
    factory, tl = _transport_layer(transport)
    devices = (tl or factory).EnumerateDevices()
    return [CameraInfo("pylon", d.GetModelName(), d.GetSerialNumber(), d.GetDeviceClass(),
                       d.GetVendorName()) for d in devices]


class PylonFeatures(FeatureMap):
    def __init__(self, node_map):
        self.nm = node_map
        _, self.genicam = _pylon()

    def _node(self, name):
        try:
            return self.nm.GetNode(name)
        except Exception:  # noqa: BLE001
            return None

    def readable(self, name):
        n = self._node(name)
        try:
            return n is not None and self.genicam.IsReadable(n)
        except Exception:  # noqa: BLE001 - a "not found" node raises on access checks
            return False

    def writable(self, name):
        n = self._node(name)
        try:
            return n is not None and self.genicam.IsWritable(n)
        except Exception:  # noqa: BLE001
            return False

    def get(self, name):
        return self._node(name).Value

    def set(self, name, value):
        self._node(name).Value = value

    def execute(self, name):
        self._node(name).Execute()

    def minimum(self, name):
        try:
            return self._node(name).Min
        except Exception:  # noqa: BLE001
            return None

    def entries(self, name):
        try:
            return list(self._node(name).Symbolics)
        except Exception:  # noqa: BLE001
            return None


class PylonCamera(Camera):
    backend = "pylon"

    def __init__(self, serial: str, label: str = "camera", transport: str | None = None):
        super().__init__(serial, label)
        self.transport = transport
        self._cam = None
        self._tick_s = 1e-9  # USB3 ace timestamps count nanoseconds
        self.pixel_format = ""

    def open(self) -> CameraInfo:
        pylon, _ = _pylon()
        factory, tl = _transport_layer(self.transport)
        devices = list((tl or factory).EnumerateDevices())
        match = [d for d in devices if d.GetSerialNumber() == self.serial]
        if not match:
            found = ", ".join(f"{d.GetModelName()} ({d.GetSerialNumber()})" for d in devices) or "none"
            where = f" on transport layer {self.transport}" if self.transport else ""
            raise HardwareError(f"{self.label}: no pylon camera with serial {self.serial}{where}; "
                                f"found: {found}")
        d = match[0]
        try:
            self._cam = pylon.InstantCamera((tl or factory).CreateDevice(d))
            self._cam.Open()
        except Exception as exc:  # noqa: BLE001 - e.g. camera opened by another program
            raise HardwareError(f"{self.label}: cannot open ({str(exc).splitlines()[0]})") from None
        self.features = PylonFeatures(self._cam.GetNodeMap())
        if self.features.readable("GevTimestampTickFrequency"):
            self._tick_s = 1.0 / float(self.features.get("GevTimestampTickFrequency"))
        self.tick_s = self._tick_s
        self.info = CameraInfo("pylon", d.GetModelName(), d.GetSerialNumber(), d.GetDeviceClass(),
                               d.GetVendorName())
        return self.info

    def _require_open(self):
        if self._cam is None:
            raise HardwareError(f"{self.label}: not open")
        return self._cam

    def configure(self, settings: CameraSettings) -> Configured:
        cam = self._require_open()
        if cam.IsGrabbing():
            cam.StopGrabbing()
        self.configured = apply_settings(self.features, settings, self.label)
        self.pixel_format = str(self.features.get("PixelFormat"))
        return self.configured

    def line_time_s(self) -> float | None:
        cam = self._require_open()
        return None if cam.IsGrabbing() else estimate_line_time_s(self.features)

    def latch_ticks(self) -> int | None:
        fm = getattr(self, "features", None)
        return None if fm is None else latch_ticks(fm)

    def arm(self) -> None:
        pylon, _ = _pylon()
        cam = self._require_open()
        if cam.IsGrabbing():
            cam.StopGrabbing()  # a fresh start drops any frame still queued from before
        try:
            cam.MaxNumBuffer.Value = 16
        except Exception:  # noqa: BLE001 - not every device/stream exposes it
            pass
        cam.StartGrabbing(pylon.GrabStrategy_OneByOne)
        self.armed = True

    def wait_ready(self, timeout_s: float = 1.0) -> None:
        pylon, _ = _pylon()
        cam = self._require_open()
        if not cam.CanWaitForFrameTriggerReady():
            return
        if not cam.WaitForFrameTriggerReady(int(timeout_s * 1000), pylon.TimeoutHandling_Return):
            raise HardwareError(f"{self.label}: not ready for a trigger within {timeout_s:g} s")

    def software_trigger(self) -> None:
        self._require_open().ExecuteSoftwareTrigger()

    def fetch(self, timeout_s: float, what: str = "frame") -> Frame:
        pylon, _ = _pylon()
        cam = self._require_open()
        if not cam.IsGrabbing():
            raise HardwareError(f"{self.label}: fetch of {what} while not armed")
        result = cam.RetrieveResult(max(1, int(timeout_s * 1000)), pylon.TimeoutHandling_Return)
        host_s = self.host_time()
        if result is None or not result.IsValid():
            raise HardwareError(f"{self.label}: no {what} within {timeout_s:g} s (no trigger arrived?)")
        try:
            if not result.GrabSucceeded():
                raise HardwareError(f"{self.label}: {what} failed: {result.GetErrorDescription()} "
                                    f"(code {result.GetErrorCode():#x})")
            data = result.GetArray().copy()
            stamp = _chunk_timestamp(result)
            source = None
            if stamp is not None:
                event = (self.configured.features.get("ChunkTimestampEvent") if self.configured else None)
                source = f"{event or 'Timestamp'} chunk"
            else:
                stamp = result.GetTimeStamp() or None  # the emulator reports 0: no timestamp
                source = None if stamp is None else "transport timestamp"
            exposure_us = _chunk_value(result, "ChunkExposureTime")
            return Frame(data=data, pixel_format=self.pixel_format, frame_id=int(result.GetBlockID()),
                         timestamp_s=None if stamp is None else stamp * self._tick_s,
                         start_ticks=stamp, start_source=source, host_s=host_s,
                         exposure_s=(exposure_us * 1e-6 if exposure_us is not None
                                     else (self.configured.exposure_s if self.configured else None)))
        finally:
            result.Release()

    def disarm(self) -> None:
        self.armed = False
        try:
            if self._cam is not None and self._cam.IsGrabbing():
                self._cam.StopGrabbing()
        except Exception:  # noqa: BLE001 - disarming must never raise
            pass

    def close(self) -> None:
        if self._cam is not None:
            try:
                self._cam.Close()
                self._cam.DestroyDevice()
            except Exception:  # noqa: BLE001
                pass
            self._cam = None


def _chunk_value(result, name: str):
    try:
        node = getattr(result, name)
        return float(node.Value)
    except Exception:  # noqa: BLE001 - no chunk data in this result
        return None


def _chunk_timestamp(result):
    """The exposure-start ticks a result's chunk data carries (ace 2 / dart, then ace classic)."""
    for name in ("BslChunkTimestampValue", "ChunkTimestamp"):
        value = _chunk_value(result, name)
        if value is not None:
            return int(value)
    return None


def emulator_serve_images(camera: PylonCamera, path) -> None:
    """Camera emulator only: serve frames from an image file or a folder of them (cycled in
    name order). For exact 12-bit data write 16-bit PNGs holding value << 4."""
    fm = camera.features
    for name, value in (("TestImageSelector", "Off"), ("ImageFileMode", "On"), ("ImageFilename", str(path))):
        if not fm.writable(name):
            raise HardwareError(f"{camera.label}: feature {name} is missing (not the pylon camera emulator?)")
        fm.set(name, value)


def make_camera(cfg, role: str) -> PylonCamera:
    """The factory's entry point (rngcam.backends)."""
    return PylonCamera(cfg.serial, role.upper(), transport=cfg.pylon_transport)


def list_cameras(pylon_transport: str | None = None, **_options) -> list[CameraInfo]:
    return list_pylon_cameras(pylon_transport)
