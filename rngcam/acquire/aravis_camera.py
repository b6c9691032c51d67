"""Aravis backend: GigE Vision and USB3 Vision cameras through libaravis (PyGObject bindings,
Debian's gir1.2-aravis-0.8; `make aravis` installs them, `rngcam doctor` says what is missing).

A camera with an `address` in the rig is opened by IP (`Aravis.Camera.new(ip)`: GVCP unicast to
that address, no discovery). Without one it is found by serial number through Aravis discovery,
which broadcasts on every interface: only on a real rig, never in tests. Features go through
the shared GenICam code (rngcam.acquire.features), so the ace GigE names (ExposureTimeAbs,
GainRaw) and a warning for a feature the camera lacks come with it.
"""

from __future__ import annotations

import numpy as np

from rngcam.acquire.camera import Camera, CameraInfo, CameraSettings, Configured, Frame
from rngcam.acquire.features import FeatureMap, apply_settings, estimate_line_time_s, latch_ticks
from rngcam.errors import HardwareError

N_BUFFERS = 16
INSTALL = "apt-get install gir1.2-aravis-0.8 libgirepository1.0-dev, then `make aravis`"


def aravis():
    """The Aravis 0.8 module; HardwareError (one line: what is missing, how to get it)."""
    try:
        import gi  # optional: aravis extra
    except ImportError:
        raise HardwareError(f"the aravis backend needs PyGObject: {INSTALL}") from None
    try:
        gi.require_version("Aravis", "0.8")
        from gi.repository import Aravis  # optional: aravis extra
    except (ValueError, ImportError):
        raise HardwareError(f"the aravis backend needs Aravis 0.8's introspection data: {INSTALL}") from None
    return Aravis


def check() -> str | None:
    """What stops this backend here (for `rngcam doctor`), or None."""
    try:
        aravis()
    except HardwareError as exc:
        return str(exc)
    return None


def _one_line(exc: Exception) -> str:
    text = getattr(exc, "message", None) or str(exc) or type(exc).__name__
    return text.strip().splitlines()[0][:160]


class AravisFeatures(FeatureMap):
    """GenICam features of an ArvDevice, read and written as the node map's strings."""

    def __init__(self, device, Aravis):
        self.dev, self.A = device, Aravis

    def _node(self, name):
        try:
            node = self.dev.get_feature(name)
            return node if node is not None and node.is_available() and node.is_implemented() else None
        except Exception:  # noqa: BLE001 - GLib errors for a broken node
            return None

    def _mode(self, name):
        node = self._node(name)
        return None if node is None else node.get_actual_access_mode()

    def readable(self, name):
        return self._mode(name) in (self.A.GcAccessMode.RO, self.A.GcAccessMode.RW)

    def writable(self, name):
        return self._mode(name) in (self.A.GcAccessMode.WO, self.A.GcAccessMode.RW)

    def get(self, name):
        text = self._node(name).get_value_as_string()
        for convert in (int, float):
            try:
                return convert(text)
            except ValueError:
                pass
        return {"true": True, "false": False}.get(text.lower(), text)

    def set(self, name, value):
        text = str(value).lower() if isinstance(value, bool) else str(value)
        self._node(name).set_value_from_string(text)

    def execute(self, name):
        self.dev.execute_command(name)

    def minimum(self, name):
        try:
            return self.dev.get_integer_feature_bounds(name)[0]
        except Exception:  # noqa: BLE001
            return None

    def entries(self, name):
        try:
            return list(self.dev.dup_available_enumeration_feature_values_as_strings(name))
        except Exception:  # noqa: BLE001
            return None


def _info(cam, address: str | None) -> CameraInfo:
    def read(getter):
        try:
            return getter() or ""
        except Exception:  # noqa: BLE001
            return ""
    return CameraInfo("aravis", read(cam.get_model_name), read(cam.get_device_serial_number),
                      f"GigE {address}" if address else "aravis", read(cam.get_vendor_name))


def list_cameras(addresses: list[str] | None = None, **_options) -> list[CameraInfo]:
    """Cameras at the given addresses (opened one by one, nothing broadcast); with none, Aravis
    discovery (broadcasts on every interface)."""
    A = aravis()
    found = []
    if addresses:
        for address in addresses:
            try:
                found.append(_info(A.Camera.new(address), address))
            except Exception as exc:  # noqa: BLE001 - GLib.Error: nothing there
                raise HardwareError(f"no GigE Vision camera answers at {address} ({_one_line(exc)})") from None
        return found
    A.update_device_list()
    for i in range(A.get_n_devices()):
        found.append(CameraInfo("aravis", A.get_device_model(i) or "", A.get_device_serial_nbr(i) or "",
                                f"{A.get_device_protocol(i)} {A.get_device_address(i) or ''}".strip(),
                                A.get_device_vendor(i) or ""))
    return found


class AravisCamera(Camera):
    backend = "aravis"

    def __init__(self, serial: str, label: str = "camera", address: str | None = None):
        super().__init__(serial, label)
        self.address = address
        self._cam = self._stream = None
        self.pixel_format = ""
        self._acquiring = False

    def open(self) -> CameraInfo:
        A = aravis()
        self.A = A
        try:
            if self.address:
                self._cam = A.Camera.new(self.address)
            else:
                A.update_device_list()
                ids = [A.get_device_id(i) for i in range(A.get_n_devices())
                       if A.get_device_serial_nbr(i) == self.serial]
                if not ids:
                    found = ", ".join(f"{A.get_device_model(i)} ({A.get_device_serial_nbr(i)})"
                                      for i in range(A.get_n_devices())) or "none"
                    raise HardwareError(f"{self.label}: no camera with serial {self.serial}; found: {found}")
                self._cam = A.Camera.new(ids[0])
        except HardwareError:
            raise
        except Exception as exc:  # noqa: BLE001 - GLib.Error
            where = f"at {self.address}" if self.address else f"with serial {self.serial}"
            raise HardwareError(f"{self.label}: cannot open the camera {where} ({_one_line(exc)})") from None
        self.info = _info(self._cam, self.address)
        if self.info.serial and self.info.serial != self.serial:
            got = self.info.serial
            self.close()
            raise HardwareError(f"{self.label}: the camera at {self.address} has serial {got}, "
                                f"not {self.serial} (check the rig's address and serial)")
        self.features = AravisFeatures(self._cam.get_device(), A)
        return self.info

    def _require_open(self):
        if self._cam is None:
            raise HardwareError(f"{self.label}: not open")
        return self._cam

    def configure(self, settings: CameraSettings) -> Configured:
        self._require_open()
        self._stop()
        self.configured = apply_settings(self.features, settings, self.label)
        self.pixel_format = str(self.features.get("PixelFormat")) if self.features.readable("PixelFormat") else ""
        return self.configured

    def line_time_s(self) -> float | None:
        self._require_open()
        return None if self._acquiring else estimate_line_time_s(self.features)

    def latch_ticks(self) -> int | None:
        fm = getattr(self, "features", None)
        return None if fm is None else latch_ticks(fm)

    def arm(self) -> None:
        cam = self._require_open()
        self._stop()  # a fresh stream: nothing queued from an earlier run survives
        try:
            self._stream = cam.create_stream(None, None)
            payload = cam.get_payload()
            for _ in range(N_BUFFERS):
                self._stream.push_buffer(self.A.Buffer.new_allocate(payload))
            cam.start_acquisition()
        except Exception as exc:  # noqa: BLE001
            raise HardwareError(f"{self.label}: cannot start acquisition ({_one_line(exc)})") from None
        self._acquiring = self.armed = True

    def software_trigger(self) -> None:
        try:
            self._require_open().software_trigger()
        except HardwareError:
            raise
        except Exception as exc:  # noqa: BLE001
            raise HardwareError(f"{self.label}: software trigger failed ({_one_line(exc)})") from None

    def fetch(self, timeout_s: float, what: str = "frame") -> Frame:
        if not self._acquiring:
            raise HardwareError(f"{self.label}: fetch of {what} while not armed")
        while True:
            buffer = self._stream.timeout_pop_buffer(max(1, int(timeout_s * 1e6)))
            if buffer is None:
                raise HardwareError(f"{self.label}: no {what} within {timeout_s:g} s (no trigger arrived?)")
            status = buffer.get_status()
            if status == self.A.BufferStatus.SUCCESS:
                break
            self._stream.push_buffer(buffer)  # an incomplete frame (missing packets): not a frame
            raise HardwareError(f"{self.label}: {what} arrived incomplete ({status.value_nick})")
        host_s = self.host_time()
        try:
            frame = self._frame(buffer)
            frame.host_s = host_s
            return frame
        finally:
            self._stream.push_buffer(buffer)

    def _frame(self, buffer) -> Frame:
        w, h = buffer.get_image_width(), buffer.get_image_height()
        raw = buffer.get_image_data() if hasattr(buffer, "get_image_data") else buffer.get_data()
        per_pixel = len(raw) // (w * h)
        dtype = np.uint16 if per_pixel in (2, 6) else np.uint8
        channels = 3 if per_pixel in (3, 6) else 1
        data = np.frombuffer(bytes(raw), dtype=dtype)[: w * h * channels].copy()
        data = data.reshape((h, w) if channels == 1 else (h, w, channels))
        stamp = buffer.get_timestamp()
        return Frame(data=data, pixel_format=self.pixel_format, frame_id=int(buffer.get_frame_id()),
                     timestamp_s=stamp * 1e-9 if stamp else None,
                     start_ticks=int(stamp) if stamp else None,
                     start_source="transport timestamp" if stamp else None,
                     exposure_s=self.configured.exposure_s if self.configured else None)

    def _stop(self) -> None:
        if self._cam is not None and self._acquiring:
            try:
                self._cam.stop_acquisition()
            except Exception:  # noqa: BLE001 - stopping must never raise
                pass
        self._acquiring = False
        self._stream = None

    def disarm(self) -> None:
        self.armed = False
        self._stop()

    def close(self) -> None:
        self._stop()
        self._cam = None


def make_camera(cfg, role: str) -> AravisCamera:
    """The factory's entry point (rngcam.backends)."""
    return AravisCamera(cfg.serial, role.upper(), address=cfg.address)
