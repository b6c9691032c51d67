"""GenTL backend: any GenICam camera through a GenTL producer (.cti) with harvesters.

The producer file comes from the rig (`cti:`) or the RNGCAM_CTI environment variable. Only
that producer is loaded, so discovery never touches other transport layers. One Harvester
per producer file is shared by the cameras of a process (a producer is initialised once).
"""

from __future__ import annotations

import os
import threading
import time
from pathlib import Path

import numpy as np

from rngcam.acquire import libraries
from rngcam.acquire.camera import Camera, CameraInfo, CameraSettings, Configured, Frame
from rngcam.acquire.features import FeatureMap, apply_settings, estimate_line_time_s, latch_ticks
from rngcam.errors import HardwareError
from rngcam.untrusted import printable

CTI_ENV = "RNGCAM_CTI"

_harvesters: dict[str, list] = {}  # cti path -> [Harvester, users]
_lock = threading.Lock()


def resolve_cti(cti: str | Path | None, key: str | None = None) -> Path:
    """The producer file to load: the argument, else $RNGCAM_CTI; it must exist. `key` names the
    rig field it came from: a rig's producer must be in a vendor's location or named by the user
    (rngcam.acquire.libraries)."""
    chosen = cti or os.environ.get(CTI_ENV)
    if not chosen:
        raise HardwareError(f"the genicam backend needs a GenTL producer (.cti): set 'cti' in "
                            f"the rig or the {CTI_ENV} environment variable")
    path = Path(chosen).expanduser()
    if cti and key:
        libraries.check(path, key, "GenTL producer")
    if not path.is_file():
        raise HardwareError(f"GenTL producer file not found: {printable(path)}")
    return path.resolve()


def _acquire_harvester(cti: Path):
    try:
        from harvesters.core import Harvester  # heavy: harvesters
    except ImportError:
        raise HardwareError("the genicam backend needs harvesters: pip install harvesters") from None
    key = str(cti)
    with _lock:
        if key not in _harvesters:
            libraries.probe(cti, "GenTL producer")  # a producer that crashes on load: one line, not our crash
            h = Harvester()
            try:
                h.add_file(key, check_existence=True, check_validity=True)
                h.update()
            except Exception as exc:  # noqa: BLE001 - a broken producer raises GenTL errors
                h.reset()
                raise HardwareError(f"cannot load GenTL producer {cti}: {exc}") from None
            _harvesters[key] = [h, 0]
        _harvesters[key][1] += 1
        return _harvesters[key][0]


def _release_harvester(cti: Path) -> None:
    key = str(cti)
    with _lock:
        entry = _harvesters.get(key)
        if entry is None:
            return
        entry[1] -= 1
        if entry[1] <= 0:
            try:
                entry[0].reset()
            finally:
                del _harvesters[key]


def _info(d) -> CameraInfo:
    return CameraInfo("genicam", d.model or "", d.serial_number or "", d.tl_type or "", d.vendor or "")


def list_genicam_cameras(cti: str | Path | None = None, key: str | None = None) -> list[CameraInfo]:
    """Cameras the given producer (only that one) reports; `key`: the rig field it came from."""
    path = resolve_cti(cti, key)
    h = _acquire_harvester(path)
    try:
        return [_info(d) for d in h.device_info_list]
    finally:
        _release_harvester(path)


class HarvestersFeatures(FeatureMap):
    def __init__(self, node_map):
        from genicam import genapi  # optional: genicam extra

        self.nm, self.genapi = node_map, genapi

    def _node(self, name):
        try:
            return getattr(self.nm, name)
        except Exception:  # noqa: BLE001 - missing feature
            return None

    def readable(self, name):
        n = self._node(name)
        return n is not None and self.genapi.is_readable(n)

    def writable(self, name):
        n = self._node(name)
        return n is not None and self.genapi.is_writable(n)

    def get(self, name):
        return self._node(name).value

    def set(self, name, value):
        self._node(name).value = value

    def execute(self, name):
        self._node(name).execute()

    def minimum(self, name):
        try:
            return self._node(name).min
        except Exception:  # noqa: BLE001
            return None

    def entries(self, name):
        try:
            return list(self._node(name).symbolics)
        except Exception:  # noqa: BLE001
            return None


class GenicamCamera(Camera):
    backend = "genicam"

    def __init__(self, serial: str, label: str = "camera", cti: str | Path | None = None, key: str | None = None):
        super().__init__(serial, label)
        self.cti = resolve_cti(cti, key)
        self._h = None
        self._ia = None
        self.pixel_format = ""

    def open(self) -> CameraInfo:
        self._h = _acquire_harvester(self.cti)
        devices = list(self._h.device_info_list)
        match = [d for d in devices if str(d.serial_number) == self.serial]
        if not match:
            found = ", ".join(f"{d.model} ({d.serial_number})" for d in devices) or "none"
            self.close()
            raise HardwareError(f"{self.label}: no camera with serial {self.serial} on producer "
                                f"{self.cti.name}; found: {found}")
        try:
            self._ia = self._h.create({"serial_number": match[0].serial_number})
        except Exception as exc:  # noqa: BLE001 - access denied, busy ...
            self.close()
            raise HardwareError(f"{self.label}: cannot open ({str(exc).splitlines()[0]})") from None
        self.features = HarvestersFeatures(self._ia.remote_device.node_map)
        self.info = _info(match[0])
        return self.info

    def _require_open(self):
        if self._ia is None:
            raise HardwareError(f"{self.label}: not open")
        return self._ia

    def configure(self, settings: CameraSettings) -> Configured:
        ia = self._require_open()
        if ia.is_acquiring():
            ia.stop()
        self.configured = apply_settings(self.features, settings, self.label)
        self.pixel_format = str(self.features.get("PixelFormat")) if self.features.readable("PixelFormat") else ""
        return self.configured

    def line_time_s(self) -> float | None:
        ia = self._require_open()
        return None if ia.is_acquiring() else estimate_line_time_s(self.features)

    def latch_ticks(self) -> int | None:
        fm = getattr(self, "features", None)
        return None if fm is None else latch_ticks(fm)

    def arm(self) -> None:
        ia = self._require_open()
        if ia.is_acquiring():
            ia.stop()  # stopping discards buffers still queued from an earlier run
        ia.num_buffers = max(ia.num_buffers, 8)
        ia.start()
        self.armed = True

    def wait_ready(self, timeout_s: float = 1.0) -> None:
        """Poll AcquisitionStatus(FrameTriggerWait) where the camera has it (SFNC)."""
        fm = self.features
        if not (fm.writable("AcquisitionStatusSelector") and fm.readable("AcquisitionStatus")):
            return
        fm.set("AcquisitionStatusSelector", "FrameTriggerWait")
        deadline = time.monotonic() + timeout_s
        while not fm.get("AcquisitionStatus"):
            if time.monotonic() > deadline:
                raise HardwareError(f"{self.label}: not ready for a trigger within {timeout_s:g} s")
            time.sleep(0.001)

    def software_trigger(self) -> None:
        if not self.features.writable("TriggerSoftware"):
            raise HardwareError(f"{self.label}: has no TriggerSoftware command")
        self.features.execute("TriggerSoftware")

    def fetch(self, timeout_s: float, what: str = "frame") -> Frame:
        ia = self._require_open()
        if not ia.is_acquiring():
            raise HardwareError(f"{self.label}: fetch of {what} while not armed")
        buffer = ia.try_fetch(timeout=timeout_s)
        host_s = self.host_time()
        if buffer is None:
            raise HardwareError(f"{self.label}: no {what} within {timeout_s:g} s (no trigger arrived?)")
        try:
            c = buffer.payload.components[0]
            per_pixel = round(c.num_components_per_pixel) or 1
            shape = (c.height, c.width) if per_pixel == 1 else (c.height, c.width, per_pixel)
            data = np.array(c.data, copy=True).reshape(shape)
            frame_id = _maybe(lambda: int(buffer.module.frame_id))
            stamp_ns = _maybe(lambda: int(buffer.timestamp_ns))
            ticks, source = self._start_ticks(stamp_ns)
            return Frame(data=data, pixel_format=str(c.data_format), frame_id=frame_id,
                         timestamp_s=None if stamp_ns is None else stamp_ns * 1e-9,
                         start_ticks=ticks, start_source=source, host_s=host_s,
                         exposure_s=self.configured.exposure_s if self.configured else None)
        finally:
            buffer.queue()

    def _start_ticks(self, transport_ns: int | None) -> tuple[int | None, str | None]:
        """The exposure-start ticks of the frame just fetched: its chunk data (harvesters
        attaches it to the node map) where enabled, else the transport timestamp (ns)."""
        if self.configured and self.configured.features.get("ChunkTimestamp"):
            for name in ("BslChunkTimestampValue", "ChunkTimestamp"):
                value = self.features.get_or_none(name)
                if value is not None:
                    freq = self.features.get_or_none("GevTimestampTickFrequency")
                    self.tick_s = 1.0 / float(freq) if freq else 1e-9
                    event = self.configured.features.get("ChunkTimestampEvent") or "Timestamp"
                    return int(value), f"{event} chunk"
        if transport_ns:
            self.tick_s = 1e-9
            return int(transport_ns), "transport timestamp"
        return None, None

    def disarm(self) -> None:
        self.armed = False
        try:
            if self._ia is not None and self._ia.is_acquiring():
                self._ia.stop()
        except Exception:  # noqa: BLE001 - disarming must never raise
            pass

    def close(self) -> None:
        if self._ia is not None:
            try:
                self._ia.destroy()
            except Exception:  # noqa: BLE001
                pass
            self._ia = None
        if self._h is not None:
            self._h = None
            _release_harvester(self.cti)


def _maybe(read):
    """A buffer property some producers do not support (they raise NotAvailable)."""
    try:
        return read()
    except Exception:  # noqa: BLE001
        return None


def make_camera(cfg, role: str) -> GenicamCamera:
    """The factory's entry point (rngcam.backends)."""
    return GenicamCamera(cfg.serial, role.upper(), cti=cfg.cti, key=f"cameras.{role}.cti")


def list_cameras(cti: str | Path | None = None, rig=None, **_options) -> list[CameraInfo]:
    """The cameras of `cti` (the command line's), else of the producers the rig's genicam
    cameras name (each loaded once), else of $RNGCAM_CTI."""
    if cti or rig is None:
        return list_genicam_cameras(cti)
    cams = rig.config.cameras
    named = {}
    for role, cfg in (("rs", cams.rs), ("gs", cams.gs)):
        if cfg.backend == "genicam" and cfg.cti:
            named.setdefault(str(Path(cfg.cti).expanduser().resolve()), (cfg.cti, f"cameras.{role}.cti"))
    if not named:
        return list_genicam_cameras(None)
    found = []
    for chosen, key in named.values():
        found += [c for c in list_genicam_cameras(chosen, key) if c not in found]
    return found
