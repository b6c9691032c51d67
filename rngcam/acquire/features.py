"""GenICam feature handling shared by the harvesters and pypylon backends.

Basler names differ between ace USB (SFNC 2: ExposureTime, Gain in dB) and ace GigE (older
names: ExposureTimeAbs, GainRaw in device units). `apply_settings` tries the names in order,
sets what the settings ask for, reads every feature back and reports what is in force.
Each backend supplies a small `FeatureMap` adapter over its node map.
"""

from __future__ import annotations

import math
from abc import ABC, abstractmethod

from rngcam.acquire.camera import CameraSettings, Configured
from rngcam.errors import HardwareError

EXPOSURE_US = ("ExposureTime", "ExposureTimeAbs")  # float, microseconds
GAIN_DB = ("Gain", "GainAbs")  # float, dB
GAIN_RAW = "GainRaw"  # integer device units (ace GigE)
DEBOUNCER_US = ("LineDebouncerTime", "LineDebouncerTimeAbs")
AUTO_OFF = ("ExposureAuto", "GainAuto", "BalanceWhiteAuto")
# Read-only features worth recording with a capture when the camera has them.
INFO = ("DeviceVendorName", "DeviceModelName", "DeviceSerialNumber", "DeviceFirmwareVersion",
        "SensorReadoutTime", "ResultingFrameRate", "ResultingFrameRateAbs", "BlackLevel",
        "BlackLevelRaw", "SensorWidth", "SensorHeight", "PixelSize", "DeviceLinkSpeed")
REL_TOL = 0.01  # read-back values further than this from the request produce a warning


class FeatureMap(ABC):
    """Minimal access to a GenICam node map."""

    @abstractmethod
    def readable(self, name: str) -> bool: ...

    @abstractmethod
    def writable(self, name: str) -> bool: ...

    @abstractmethod
    def get(self, name: str): ...

    @abstractmethod
    def set(self, name: str, value) -> None: ...

    @abstractmethod
    def execute(self, name: str) -> None: ...

    def minimum(self, name: str):
        """The smallest allowed value of a numeric feature, when known."""
        return

    def entries(self, name: str) -> list[str] | None:
        """The values an enumeration feature offers now, when known."""
        return

    def first_writable(self, names) -> str | None:
        return next((n for n in names if self.writable(n)), None)

    def get_or_none(self, name: str):
        try:
            return self.get(name) if self.readable(name) else None
        except Exception:  # noqa: BLE001 - informational read only
            return None


def _one_line(exc: Exception) -> str:
    text = str(exc).strip().splitlines()[0] if str(exc).strip() else type(exc).__name__
    return text[:160]


def _plain(value):
    """Node values as JSON-able Python values."""
    if isinstance(value, (bool, int, float, str)) or value is None:
        return value
    try:
        return float(value)
    except (TypeError, ValueError):
        return str(value)


class _Applier:
    def __init__(self, fm: FeatureMap, label: str):
        self.fm, self.label = fm, label
        self.out = Configured()

    def set(self, name: str, value, required: bool = True):
        if not self.fm.writable(name):
            if required:
                raise HardwareError(f"{self.label}: feature {name} is missing or not writable")
            return None
        try:
            self.fm.set(name, value)
        except Exception as exc:  # noqa: BLE001 - GenICam raises its own exception types
            raise HardwareError(f"{self.label}: setting {name} = {value!r} failed: {_one_line(exc)}") from None
        back = _plain(self.fm.get(name))
        self.out.features[name] = back
        self.check(name, value, back)
        return back

    def check(self, name: str, wanted, back) -> None:
        if isinstance(wanted, (int, float)) and not isinstance(wanted, bool):
            if not math.isclose(float(back), float(wanted), rel_tol=REL_TOL, abs_tol=1e-9):
                self.out.warnings.append(f"{self.label}: {name} is {back} (asked for {wanted})")
        elif str(back) != str(wanted):
            self.out.warnings.append(f"{self.label}: {name} is {back!r} (asked for {wanted!r})")


def apply_settings(fm: FeatureMap, s: CameraSettings, label: str) -> Configured:
    """Set the features of `s` on a GenICam camera (not acquiring), read them back."""
    a = _Applier(fm, label)
    # Trigger mode off first: some features are locked while the camera waits for triggers.
    _all_triggers_off(fm, a)
    if s.shutter_mode is not None:
        _set_shutter_mode(fm, a, s.shutter_mode)
    for name in AUTO_OFF:
        a.set(name, "Off", required=False)
    if s.pixel_format is not None:
        a.set("PixelFormat", s.pixel_format)
    if s.roi is not None:
        width, height, ox, oy = s.roi
        a.set("OffsetX", 0, required=False)
        a.set("OffsetY", 0, required=False)
        a.set("Width", width)
        a.set("Height", height)
        a.set("OffsetX", ox, required=ox != 0)
        a.set("OffsetY", oy, required=oy != 0)
    if s.exposure_s is not None:
        name = fm.first_writable(EXPOSURE_US)
        if name is None:
            raise HardwareError(f"{label}: no exposure feature ({' / '.join(EXPOSURE_US)})")
        back = a.set(name, s.exposure_s * 1e6)
        a.out.features["exposure_s"] = float(back) * 1e-6
    if s.gain_db is not None:
        _set_gain(fm, a, s.gain_db)
    if s.trigger_source is not None:
        a.set("TriggerMode", "On")
        a.set("TriggerSource", s.trigger_source)
        a.set("TriggerActivation", s.trigger_activation, required=s.trigger_activation != "RisingEdge")
    if s.line_debouncer_s is not None and s.trigger_source not in (None, "Software"):
        if fm.writable("LineSelector"):
            a.set("LineSelector", s.trigger_source, required=False)
        name = fm.first_writable(DEBOUNCER_US)
        if name is None:
            a.out.warnings.append(f"{label}: no line debouncer feature; debouncer not set")
        else:
            a.set(name, s.line_debouncer_s * 1e6)
    if s.chunk_timestamps:
        _enable_chunk_timestamps(fm, a)
    for name in INFO:
        value = fm.get_or_none(name)
        if value is not None:
            a.out.features.setdefault(name, _plain(value))
    if "exposure_s" not in a.out.features:
        name = next((n for n in EXPOSURE_US if fm.readable(n)), None)
        if name is not None:
            a.out.features["exposure_s"] = float(fm.get(name)) * 1e-6
    return a.out


def _all_triggers_off(fm: FeatureMap, a: _Applier) -> None:
    """TriggerMode Off under every TriggerSelector (ace USB also has FrameBurstStart, others
    AcquisitionStart ...: one left on holds the camera), each recorded as TriggerMode[selector];
    FrameStart stays selected, the only trigger a capture uses."""
    if fm.writable("TriggerSelector"):
        for selector in fm.entries("TriggerSelector") or []:
            if selector == "FrameStart":
                continue
            try:
                fm.set("TriggerSelector", selector)
            except Exception:  # noqa: BLE001 - an entry not selectable now
                continue
            if fm.writable("TriggerMode"):
                a.set("TriggerMode", "Off")
                a.out.features[f"TriggerMode[{selector}]"] = a.out.features.pop("TriggerMode")
        a.set("TriggerSelector", "FrameStart", required=False)
    if fm.writable("TriggerMode"):
        a.set("TriggerMode", "Off")


def _set_shutter_mode(fm: FeatureMap, a: _Applier, mode: str) -> None:
    """ShutterMode where the camera has it (ace USB: Global, Rolling, GlobalResetRelease), read
    back and recorded; a camera without it keeps its sensor's only mode (nothing to record)."""
    if fm.writable("ShutterMode"):
        offered = fm.entries("ShutterMode")
        if offered is None or mode in offered:
            a.set("ShutterMode", mode)
            return
        a.out.warnings.append(f"{a.label}: ShutterMode offers {', '.join(offered)}, not {mode}; left as is")
    value = fm.get_or_none("ShutterMode")
    if value is not None:
        a.out.features["ShutterMode"] = _plain(value)
        if str(value) != mode:
            a.out.warnings.append(f"{a.label}: ShutterMode is {value!r} and cannot be set to {mode!r}")


def _set_gain(fm: FeatureMap, a: _Applier, gain_db: float) -> None:
    name = fm.first_writable(GAIN_DB)
    if name is not None:
        a.out.features["gain_db"] = float(a.set(name, gain_db))
    elif fm.writable(GAIN_RAW):
        # GainRaw has device-specific units; only "no gain" (its minimum) is unambiguous.
        if gain_db != 0:
            raise HardwareError(f"{a.label}: only GainRaw (device units) is available; set "
                                "gain_db to 0 or configure GainRaw on the camera")
        lowest = fm.minimum(GAIN_RAW)
        a.set(GAIN_RAW, lowest if lowest is not None else 0)
    else:
        a.out.warnings.append(f"{a.label}: no gain feature; gain left as is")


# Chunk timestamps, newest naming first: ace 2 / dart pick the event with
# BslChunkTimestampSelector and report BslChunkTimestampValue; ace classic has one ChunkTimestamp
# (the frame-start trigger's time).
TIMESTAMP_EVENTS = ("ExposureStart", "FrameStart")
# Timestamp latches: (command, value) per generation: ace 2 / USB, then GigE.
LATCHES = (("TimestampLatch", "TimestampLatchValue"), ("GevTimestampControlLatch", "GevTimestampValue"))


def _enable_chunk_timestamps(fm: FeatureMap, a: _Applier) -> None:
    """Per-frame exposure-start timestamps as chunk data when the camera supports it; records
    ChunkTimestampEvent (ExposureStart, FrameStart) so a frame says what its ticks mark."""
    if not fm.writable("ChunkModeActive"):
        a.out.warnings.append(f"{a.label}: no chunk mode; frame timestamps from the transport layer")
        return
    a.set("ChunkModeActive", True)
    try:
        ok = fm.writable("ChunkSelector")
        if ok:
            fm.set("ChunkSelector", "Timestamp")
            fm.set("ChunkEnable", True)
            a.out.features["ChunkTimestamp"] = True
            a.out.features["ChunkTimestampEvent"] = _select_timestamp_event(fm)
    except Exception:  # noqa: BLE001
        ok = False
    if not ok:
        fm.set("ChunkModeActive", False)
        a.out.features["ChunkModeActive"] = False
        a.out.warnings.append(f"{a.label}: chunk timestamps unavailable; using transport-layer timestamps")


def _select_timestamp_event(fm: FeatureMap) -> str:
    """ExposureStart (else FrameStart) under BslChunkTimestampSelector where the camera has it;
    an ace classic's ChunkTimestamp marks the frame start."""
    if not fm.writable("BslChunkTimestampSelector"):
        return "FrameStart"
    offered = fm.entries("BslChunkTimestampSelector")
    for event in TIMESTAMP_EVENTS:
        if offered is None or event in offered:
            try:
                fm.set("BslChunkTimestampSelector", event)
                return event
            except Exception:  # noqa: BLE001 - an entry not selectable now
                continue
    return str(fm.get_or_none("BslChunkTimestampSelector") or "FrameStart")


def latch_ticks(fm: FeatureMap) -> int | None:
    """The camera's timestamp counter latched now (either generation's names), or None."""
    for command, value in LATCHES:
        if fm.writable(command) and fm.readable(value):
            try:
                fm.execute(command)
                return int(fm.get(value))
            except Exception:  # noqa: BLE001 - a latch that fails is no latch
                return None
    return None


def estimate_line_time_s(fm: FeatureMap) -> float | None:
    """RS line time from SensorReadoutTime at two ROI heights (no feature reports it directly).

    line time = change of readout time / change of height. The height is restored.
    Returns None when the camera has no SensorReadoutTime or the height cannot change.
    """
    if not (fm.readable("SensorReadoutTime") and fm.writable("Height")):
        return None
    h1 = int(fm.get("Height"))
    r1 = float(fm.get("SensorReadoutTime"))
    h2 = max(h1 // 2, 2)
    if h2 == h1:
        return None
    try:
        fm.set("Height", h2)
        h2 = int(fm.get("Height"))
        r2 = float(fm.get("SensorReadoutTime"))
    finally:
        fm.set("Height", h1)
    if h1 == h2 or r1 == r2:
        return None
    return (r1 - r2) / (h1 - h2) * 1e-6
