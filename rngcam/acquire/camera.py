"""The camera protocol every backend implements, and the values it passes around.

Life cycle: open (by serial number) -> configure (settings; returns the features read back)
-> arm (flush stale buffers, start) -> wait_ready -> [software_trigger] -> fetch (finite
timeout) ... -> disarm -> close. Cameras are context managers: leaving the block disarms and
closes them whatever happened, so a failed capture leaves them safe.
"""

from __future__ import annotations

import time
from abc import ABC, abstractmethod
from dataclasses import dataclass, field

import numpy as np


@dataclass(frozen=True)
class CameraSettings:
    """What to configure. None leaves a feature as the camera has it.

    roi: (width, height, offset_x, offset_y) in pixels. trigger_source: "Software", "Line1", ...
    or None for free-running (trigger mode off). White balance is always switched off (raw data).
    shutter_mode: "Rolling" for the RS camera (set where the camera has a writable ShutterMode,
    e.g. ace USB's Global / Rolling / GlobalResetRelease; recorded either way).
    """

    exposure_s: float | None = None
    gain_db: float | None = None
    pixel_format: str | None = None
    roi: tuple[int, int, int, int] | None = None
    trigger_source: str | None = None
    trigger_activation: str = "RisingEdge"
    line_debouncer_s: float | None = None
    chunk_timestamps: bool = False
    shutter_mode: str | None = None

    @classmethod
    def from_config(cls, cfg, role: str | None = None) -> CameraSettings:
        """From a rngcam.config.CameraConfig; the RS role asks for a rolling shutter."""
        return cls(exposure_s=cfg.exposure_s, gain_db=cfg.gain_db, pixel_format=cfg.pixel_format,
                   roi=(cfg.roi.width, cfg.roi.height, cfg.roi.offset_x, cfg.roi.offset_y),
                   trigger_source=cfg.trigger.source, trigger_activation=cfg.trigger.activation,
                   line_debouncer_s=cfg.trigger.debouncer_s, chunk_timestamps=cfg.chunk_timestamps,
                   shutter_mode="Rolling" if role == "rs" else None)


@dataclass(frozen=True)
class CameraInfo:
    """Identity of a camera as its transport layer reports it."""

    backend: str
    model: str
    serial: str
    interface: str = ""
    vendor: str = ""


@dataclass
class Frame:
    """One fetched frame: raw data in its native dtype plus what the camera said about it.

    trigger_time_s is only known to simulated cameras (seconds after the generator fired).
    start_ticks: the camera's clock when this exposure started, from chunk data (start_source
    says which: "ExposureStart chunk", "FrameStart chunk", "Timestamp chunk") or, as a last
    resort, the transport layer's frame timestamp ("transport timestamp"); None when unknown.
    host_s: the host clock (Camera.host_time) read right after the grab.
    """

    data: np.ndarray
    pixel_format: str
    frame_id: int | None = None
    timestamp_s: float | None = None
    exposure_s: float | None = None
    trigger_time_s: float | None = None
    start_ticks: int | None = None
    start_source: str | None = None
    host_s: float | None = None


@dataclass
class Configured:
    """Result of configure(): every feature read back, and warnings on differences."""

    features: dict = field(default_factory=dict)
    warnings: list[str] = field(default_factory=list)

    @property
    def exposure_s(self) -> float | None:
        return self.features.get("exposure_s")


class Camera(ABC):
    """Base class of the backends (genicam, pylon, mock)."""

    backend = "abstract"
    tick_s = 1e-9  # seconds per tick of the camera's timestamp counter (nominal)

    def __init__(self, serial: str, label: str = "camera"):
        self.serial = str(serial)
        self.label = f"{label} camera {self.serial}"
        self.info: CameraInfo | None = None
        self.configured: Configured | None = None
        self.armed = False

    @abstractmethod
    def open(self) -> CameraInfo:
        """Find the camera by serial number and open it; HardwareError lists those found."""

    @abstractmethod
    def configure(self, settings: CameraSettings) -> Configured:
        """Set every feature in `settings` and read each back."""

    @abstractmethod
    def arm(self) -> None:
        """Flush stale buffers and start acquisition (frames then come on triggers)."""

    def wait_ready(self, timeout_s: float = 1.0) -> None:  # noqa: B027 (a default, not abstract)
        """Block until the camera accepts a trigger (default: ready once armed)."""

    @abstractmethod
    def software_trigger(self) -> None:
        """Issue one software trigger (only with trigger source Software)."""

    @abstractmethod
    def fetch(self, timeout_s: float, what: str = "frame") -> Frame:
        """The next frame, or HardwareError naming this camera and `what` after timeout_s."""

    @abstractmethod
    def disarm(self) -> None:
        """Stop acquisition (never raises)."""

    @abstractmethod
    def close(self) -> None:
        """Release the camera (never raises)."""

    def line_time_s(self) -> float | None:
        """The RS line time the camera reports or that can be measured, else None."""
        return None

    def host_time(self) -> float:
        """The host clock exposure starts are mapped to (monotonic seconds)."""
        return time.monotonic()

    def latch_ticks(self) -> int | None:
        """The camera's timestamp counter latched now, or None where it has no latch (a GenICam
        camera reads it through rngcam.acquire.features.latch_ticks)."""
        return None

    def latch_clock(self) -> tuple[float, int] | None:
        """(host time, camera ticks) at one instant, from the camera's timestamp latch, or None
        where the camera has none."""
        before = self.host_time()
        ticks = self.latch_ticks()
        after = self.host_time()
        return None if ticks is None else (0.5 * (before + after), ticks)

    def __enter__(self) -> Camera:
        self.open()
        return self

    def __exit__(self, *exc) -> None:
        try:
            self.disarm()
        finally:
            self.close()
