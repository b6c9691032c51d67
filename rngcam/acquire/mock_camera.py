"""Physics-based mock cameras: frames rendered from a scene with rngcam.physics.

A `MockWorld` holds the scene (rendered once by rngcam.sim.scenes on the video grid that starts
at T0, the RS camera's trigger), the PSF in front of the RS sensor, and the mock devices that
are "plugged in". A `MockCamera` behaves like a hardware-triggered machine-vision camera: it
must be armed, it accepts a trigger edge on its input line only when ready (a GS camera is
busy for exposure + readout, so triggers in between are missed, as on a real sensor), and a
fetch waits for a frame with a finite timeout. Its frame is a real simulated measurement:

- RS: RollingShutter(psf, RollingShutterTiming(line time, exposure, rows, trigger).weights) v
- GS: GlobalShutter(GlobalShutterTiming(trigger, exposure).weights) v

mapped to DN by rngcam.physics.sensor.SensorModel (noise seeded per camera and frame).

For calibration (rngcam.calibrate) the world can show a static `target` instead of the scene:
"point" (a point source), "chart" (a textured card on a dark surround) or "dark"; frames are
then the static forward model, whatever the trigger time. A GS device may carry a true GS-to-RS
transform (it sees the scene point H p at its pixel p) and every device per-channel gains
(SensorModel.channel_gain).

With `bin` > 1 (the rig's recon.grid_bin) the world renders the scene and both measurements on
the reconstruction grid (sensor size / bin, the RS rows binned exactly as the reconstruction
models them) and makes sensor-size frames by repeating each grid pixel bin x bin, noise added
per sensor pixel a strip of rows at a time: a lab-size frame (3648x5472) then costs tens of MB of
scratch, not the tens of GB a sensor-resolution scene would, and the truth is on the grid. The
RS device has a small feature map (Height, SensorReadoutTime) so its line time is measured as on a
real camera, and as roughly: like the vendor's figure, the mock's SensorReadoutTime is
overhead + (1 + readout_bias) x Height x the true line time, so its slope is off by `readout_bias`
(the rig's mock.readout_time_bias).

During calibration the world can also show a light a generator channel drives (`light`, e.g.
FakeGenerator.light for one channel: the line-time LED facing the diffuser): a glow (a smooth
spot times the diffuser's caustic, the PSF) whose brightness follows the channel's voltage in
time; each RS row sees it integrated over its own exposure, which starts one true line time
after the previous row's.
"""

from __future__ import annotations

import threading
import time
from collections.abc import Callable
from dataclasses import dataclass

import cv2
import numpy as np
import torch

from rngcam.acquire.camera import Camera, CameraInfo, CameraSettings, Configured, Frame
from rngcam.acquire.features import estimate_line_time_s
from rngcam.acquire.mock_clock import TICK_S, MockTiming
from rngcam.acquire.mock_features import MockFeatures
from rngcam.errors import HardwareError
from rngcam.physics.operators import GlobalShutter, PSFConvolution, rolling_shutter_for
from rngcam.physics.psf import bin_psf
from rngcam.physics.sensor import SensorModel
from rngcam.physics.timing import GlobalShutterTiming, RollingShutterTiming, VideoGrid, readout_lines
from rngcam.sim.scenes import render_scene
from rngcam.sim.targets import chart_image, point_source

TRIGGER_LINES = ("Line1", "Line2", "Line3", "Line4")
EXPOSURE_STEP_S = 1e-6  # exposure is set in whole microseconds, like a Basler ace
STATIC_TARGETS = ("point", "chart", "dark")
CHART_BRIGHTNESS = 0.7  # the chart's brightest point, in units of full scale at unit gain
LED_FORWARD_V = 1.8  # the mock LED lights above this voltage, its brightness linear in the excess
LED_REFERENCE_V = 5.0  # the voltage at which the LED shows led_level


@dataclass(frozen=True)
class MockDevice:
    """A plugged-in mock camera: identity and sensor physics."""

    serial: str
    model: str
    kind: str  # "rs" or "gs"
    sensor: SensorModel
    noise: bool = True
    seed: int = 0
    line_time_s: float | None = None  # RS only: the sensor's true line time
    readout: str = "top-down"  # RS only: the readout order (physics.timing.READOUTS)
    readout_s: float = 1e-3
    gs_to_rs: tuple[tuple[float, ...], ...] | None = None  # GS only: true GS pixel -> RS pixel map
    readout_bias: float = 0.0  # RS only: SensorReadoutTime's slope is (1 + bias) x line_time_s
    led_level: float = 0.0  # brightness of a generator-driven LED at LED_REFERENCE_V (full scale)


class MockWorld:
    """The scene both mock cameras see, its video grid, the RS PSF, and the plugged devices."""

    def __init__(self, scene: str, size, grid: VideoGrid, psf: np.ndarray | None,
                 seed: int = 0, key_times_s=None, options: dict | None = None, bin: int = 1):
        """`size`: the sensor, N (square) or (rows, cols); `psf` on the sensor grid."""
        self.rows, self.cols = (int(size), int(size)) if np.isscalar(size) else (int(size[0]), int(size[1]))
        self.bin = int(bin)
        if self.bin < 1 or self.rows % self.bin or self.cols % self.bin:
            raise HardwareError(f"mock sensor {self.cols}x{self.rows} does not bin by {bin}")
        self.size, self.grid, self.seed = self.rows, grid, seed  # size: sensor rows
        self.scene = scene
        self.key_times_s = None if key_times_s is None else [float(t) for t in key_times_s]
        self.options = dict(options or {})
        self.psf = None if psf is None else np.asarray(psf, dtype=np.float64)
        self.devices: dict[str, MockDevice] = {}
        self.t0_s: float | None = None  # generator-clock time of the RS trigger
        self.target: str | None = None  # a static calibration target shown instead of the scene
        self.light: Callable | None = None  # () -> FakeGenerator.Light or None: the LED's waveform now
        self.timing = MockTiming()  # the cameras' clocks and exposure-start delays (mock_clock)
        self.epoch_s = time.monotonic()  # the world's (host) clock starts here
        self._video: np.ndarray | None = None
        self._grid_psf: np.ndarray | None = None
        self._lock = threading.Lock()

    @property
    def grid_shape(self) -> tuple[int, int]:
        return self.rows // self.bin, self.cols // self.bin

    def grid_psf(self) -> np.ndarray:
        """The PSF on the grid, binned from the sensor PSF as the reconstruction does."""
        if self._grid_psf is None:
            self._grid_psf = self.psf if self.bin == 1 else bin_psf(self.psf, self.bin)
        return self._grid_psf

    def plug(self, device: MockDevice) -> None:
        self.devices[device.serial] = device

    def video(self) -> np.ndarray:
        """The truth video (3, K, H, W) float32 on `grid` (H, W = sensor size / bin), rendered once."""
        with self._lock:
            if self._video is None:
                opts = dict(self.options)
                if self.key_times_s is not None:
                    opts.setdefault("key_times_s", self.key_times_s)
                self._video = render_scene(self.scene, self.grid, self.grid_shape, self.seed, **opts)
            return self._video

    def static_image(self, device: MockDevice) -> np.ndarray:
        """(3, N, N) intensity of the static `target` as `device` sees it (scene coordinates
        are RS pixels; a GS device with gs_to_rs sees the scene point H p at pixel p)."""
        if self.target not in STATIC_TARGETS:
            raise HardwareError(f"unknown mock target {self.target!r} (choose from {', '.join(STATIC_TARGETS)})")
        n = self.size
        if (self.rows, self.cols) != (n, n) or self.bin != 1:
            raise HardwareError("mock calibration targets need a square mock sensor with grid_bin 1")
        h = None if device.gs_to_rs is None else np.asarray(device.gs_to_rs, np.float64)
        if self.target == "dark":
            return np.zeros((3, n, n))
        if self.target == "chart":
            return CHART_BRIGHTNESS * chart_image(n, h, seed=self.seed)
        if self.psf is None:
            raise HardwareError("the mock point source needs the RS PSF to set its brightness")
        img = point_source(n, float(self.psf.max()))
        return img if h is None else warp_seen(img, h)

    def relative(self, t_s: float, who: str) -> float:
        """Generator-clock time -> time after T0, checked to lie on the video grid."""
        if self.t0_s is None:
            raise HardwareError(f"{who}: the mock scene has no T0 (the RS camera was never triggered)")
        return t_s - self.t0_s

    def check_inside(self, start_s: float, end_s: float, who: str) -> None:
        span = self.grid.n_frames * self.grid.dt_s
        if start_s < -1e-12 or end_s > span * (1 + 1e-9):
            raise HardwareError(f"{who}: exposure [{start_s * 1e3:.3f}, {end_s * 1e3:.3f}] ms lies "
                                f"outside the mock scene's interval [0, {span * 1e3:.3f}] ms after T0")


def warp_seen(img: np.ndarray, gs_to_rs: np.ndarray) -> np.ndarray:
    """(C, N, N) scene on the RS grid -> what a camera with pixel p -> scene point H p sees."""
    n_h, n_w = img.shape[-2:]
    return np.stack([cv2.warpPerspective(np.ascontiguousarray(c, np.float64), gs_to_rs, (n_w, n_h),
                                         flags=cv2.INTER_LINEAR | cv2.WARP_INVERSE_MAP,
                                         borderMode=cv2.BORDER_CONSTANT, borderValue=0.0) for c in img])


def led_brightness(volts: float, level: float) -> float:
    """The mock LED's brightness (full-scale units) at `volts` across LED and resistor."""
    return level * max(0.0, volts - LED_FORWARD_V) / (LED_REFERENCE_V - LED_FORWARD_V)


def square_on_fraction(starts_s: np.ndarray, exposure_s: float, frequency_hz: float) -> np.ndarray:
    """Fraction of [start, start + exposure] during which a 50 % square wave (high during the
    first half of each period from t = 0) is high."""
    def high_time(t):  # time spent high in [0, t], in periods
        u = t * frequency_hz
        k = np.floor(u)
        return 0.5 * k + np.minimum(u - k, 0.5)

    s = np.asarray(starts_s, np.float64)
    return (high_time(s + exposure_s) - high_time(s)) / (exposure_s * frequency_hz)


class MockCamera(Camera):
    backend = "mock"

    def __init__(self, serial: str, label: str, world: MockWorld):
        super().__init__(serial, label)
        self.world = world
        self.device: MockDevice | None = None
        self.settings: CameraSettings | None = None
        self.exposure_s = 0.0
        self.missed_triggers = 0
        self._pending: list[float] = []  # trigger times (generator clock) not yet fetched
        self._busy_until_s = -np.inf
        self._frame_count = 0  # frame ids, from 0 after each arm
        self._frames_rendered = 0  # since open: seeds the noise, so every shot has fresh noise
        self._opened_at = 0.0
        self._cv = threading.Condition()
        self.features: MockFeatures | None = None  # RS only

    # --- protocol ---
    def open(self) -> CameraInfo:
        dev = self.world.devices.get(self.serial)
        if dev is None:
            found = ", ".join(f"{d.model} ({s})" for s, d in self.world.devices.items()) or "none"
            raise HardwareError(f"{self.label}: no mock camera with serial {self.serial}; found: {found}")
        self.device = dev
        self._opened_at = time.monotonic()
        if dev.kind == "rs":
            self.features = MockFeatures(self.world.size, dev.line_time_s, dev.readout_bias)
        self.info = CameraInfo("mock", dev.model, dev.serial, "simulated", "rngcam")
        return self.info

    def _dev(self) -> MockDevice:
        if self.device is None:
            raise HardwareError(f"{self.label}: not open")
        return self.device

    def configure(self, settings: CameraSettings) -> Configured:
        dev = self._dev()
        out = Configured()
        want = dev.sensor.pixel_format
        if settings.pixel_format not in (None, want):
            raise HardwareError(f"{self.label}: pixel format {settings.pixel_format!r} not supported "
                                f"(this mock sensor gives {want!r})")
        n, n_cols = self.world.rows, self.world.cols
        if settings.roi is not None and tuple(settings.roi) != (n_cols, n, 0, 0):
            raise HardwareError(f"{self.label}: ROI {settings.roi} not supported; the mock sensor is "
                                f"{n_cols}x{n} (offsets 0)")
        if settings.trigger_source not in (None, "Software", *TRIGGER_LINES):
            raise HardwareError(f"{self.label}: TriggerSource {settings.trigger_source!r} unknown")
        if settings.trigger_activation not in ("RisingEdge", "FallingEdge"):
            raise HardwareError(f"{self.label}: TriggerActivation {settings.trigger_activation!r} unknown")
        exposure = settings.exposure_s if settings.exposure_s is not None else 1e-3
        self.exposure_s = max(1, round(exposure / EXPOSURE_STEP_S)) * EXPOSURE_STEP_S
        self.settings = settings
        gain_db = settings.gain_db or 0.0
        out.features = {
            "PixelFormat": want, "Width": n_cols, "Height": n, "OffsetX": 0, "OffsetY": 0,
            "ExposureTime": self.exposure_s * 1e6, "exposure_s": self.exposure_s,
            "Gain": gain_db, "gain_db": gain_db,
            "TriggerSelector": "FrameStart",
            "TriggerMode": "Off" if settings.trigger_source is None else "On",
            "TriggerSource": settings.trigger_source, "TriggerActivation": settings.trigger_activation,
            "BalanceWhiteAuto": "Off", "BlackLevel": dev.sensor.black_level_dn,
            "DeviceModelName": dev.model, "DeviceSerialNumber": dev.serial,
            "MockNoise": dev.noise, "MockSeed": dev.seed, "MockFullWell_e": dev.sensor.full_well_e,
            "MockReadNoise_e": dev.sensor.read_noise_e,
        }
        if dev.kind == "gs":  # the mock GS says how long its readout takes, as a real camera does
            out.features["SensorReadoutTime"] = round(dev.readout_s * 1e6, 2)
        if dev.kind == "rs":
            out.features["SensorReadoutTime"] = self.features.get("SensorReadoutTime")
        if settings.chunk_timestamps:  # ExposureStart chunk ticks, as on an ace 2
            out.features |= {"ChunkModeActive": True, "ChunkTimestamp": True, "ChunkTimestampEvent": "ExposureStart"}
        if settings.exposure_s is not None and abs(self.exposure_s - settings.exposure_s) > 1e-12:
            out.warnings.append(f"{self.label}: ExposureTime is {self.exposure_s * 1e6:g} us "
                                f"(asked for {settings.exposure_s * 1e6:g})")
        self.configured = out
        return out

    def line_time_s(self) -> float | None:
        dev = self._dev()
        return estimate_line_time_s(self.features) if dev.kind == "rs" else None

    tick_s = TICK_S

    def host_time(self) -> float:
        return time.monotonic() - self.world.epoch_s

    def latch_clock(self) -> tuple[float, int] | None:
        """The mock latch: exact (the world's clock and this camera's counter at one instant)."""
        if not self.world.timing.latch:
            return None
        now = self.host_time()
        return now, self.world.timing.clocks[self._dev().kind].ticks(now)

    def arm(self) -> None:
        if self.settings is None:
            raise HardwareError(f"{self.label}: arm before configure")
        with self._cv:
            self._pending.clear()  # stale frames are flushed
            self._busy_until_s = -np.inf
            self._frame_count = 0
            self.missed_triggers = 0
            self.armed = True

    def wait_ready(self, timeout_s: float = 1.0) -> None:
        """With software triggers, wait until the sensor has finished its last exposure and readout."""
        if self.settings is None or self.settings.trigger_source != "Software":
            return
        wait = self._busy_until_s - (time.monotonic() - self._opened_at)
        if wait > timeout_s:
            raise HardwareError(f"{self.label}: not ready for a trigger within {timeout_s:g} s")
        if wait > 0:
            time.sleep(wait)

    def software_trigger(self) -> None:
        if self.settings is None or self.settings.trigger_source != "Software":
            raise HardwareError(f"{self.label}: TriggerSource is not Software")
        self._trigger(time.monotonic() - self._opened_at)

    def hardware_input(self, pulses) -> None:
        """Edges arriving on the trigger line (from the fake generator): a list of Pulse."""
        s = self.settings
        if s is None or s.trigger_source not in TRIGGER_LINES:
            return
        for p in pulses:
            self._trigger(p.rise_s if s.trigger_activation == "RisingEdge" else p.fall_s)

    def _busy_s(self) -> float:
        dev = self._dev()
        if dev.kind == "rs":
            rows = self.world.cols if dev.readout == "columns" else self.world.rows
            return float(readout_lines(dev.readout, rows).max()) * dev.line_time_s + self.exposure_s + dev.readout_s
        return self.exposure_s + dev.readout_s

    def _trigger(self, t_s: float) -> None:
        with self._cv:
            if not self.armed:
                return
            if t_s < self._busy_until_s:
                self.missed_triggers += 1  # overtriggered: the sensor is still busy
                return
            self._busy_until_s = t_s + self._busy_s()
            if self._dev().kind == "rs" and self.world.t0_s is None:
                self.world.t0_s = t_s
            self._pending.append(t_s)
            self._cv.notify_all()

    def fetch(self, timeout_s: float, what: str = "frame") -> Frame:
        with self._cv:
            if not self.armed:
                raise HardwareError(f"{self.label}: fetch of {what} while not armed")
            if not self._cv.wait_for(lambda: self._pending, timeout=timeout_s):
                extra = f", {self.missed_triggers} trigger(s) missed while busy" if self.missed_triggers else ""
                raise HardwareError(f"{self.label}: no {what} within {timeout_s:g} s "
                                    f"(no trigger arrived{extra})")
            t_s = self._pending.pop(0)
            index = self._frame_count
            self._frame_count += 1
            self._frames_rendered += 1
            noise_index = self._frames_rendered
        dev, timing = self._dev(), self.world.timing
        start = t_s + timing.start_delay_s(dev.kind, index)  # the exposure starts after its trigger
        data = self.render(start, noise_index)
        chunks = self.settings is not None and self.settings.chunk_timestamps
        return Frame(data=data, pixel_format=dev.sensor.pixel_format, frame_id=index,
                     timestamp_s=self._opened_at + t_s, exposure_s=self.exposure_s, trigger_time_s=t_s,
                     start_ticks=timing.clocks[dev.kind].ticks(start) if chunks else None,
                     start_source="ExposureStart chunk" if chunks else None,
                     host_s=start + self.exposure_s + dev.readout_s)

    def render(self, t_s: float, index: int) -> np.ndarray:
        """The raw frame for an exposure triggered at generator time t_s (index seeds the noise)."""
        dev, world = self._dev(), self.world
        n = world.size
        if world.target is not None:
            y = self._render_static(dev)
            if dev.kind == "rs" and world.light is not None:
                y = y + self._render_led(dev, t_s)
        elif world.bin > 1:
            return self._render_binned(dev, t_s, index)
        elif dev.kind == "rs":
            rel = world.relative(t_s, self.label)
            video = torch.from_numpy(world.video()).double()
            if world.psf is None:
                raise HardwareError(f"{self.label}: the mock RS camera needs a PSF")
            rows = world.cols if dev.readout == "columns" else n
            timing = RollingShutterTiming(dev.line_time_s, self.exposure_s, rows=rows, trigger_s=rel,
                                          readout=dev.readout)
            world.check_inside(rel, timing.end_s, self.label)
            op = rolling_shutter_for(torch.from_numpy(world.psf), torch.from_numpy(timing.weights(world.grid)),
                                     (n, world.cols), transposed=timing.transposed)
            y = op.A(video).numpy()
        else:
            rel = world.relative(t_s, self.label)
            video = torch.from_numpy(world.video()).double()
            timing = GlobalShutterTiming((rel,), self.exposure_s)
            world.check_inside(rel, timing.end_s, self.label)
            y = GlobalShutter(torch.from_numpy(timing.weights(world.grid)), 3, (n, world.cols)).A(video)[:, 0].numpy()
            if dev.gs_to_rs is not None:
                y = warp_seen(y, np.asarray(dev.gs_to_rs, np.float64))
        return self._sensor().capture(y, self.exposure_s, world.grid.dt_s,
                                      rng=np.random.default_rng([dev.seed, index]), noise=dev.noise)

    def _sensor(self) -> SensorModel:
        sensor = self._dev().sensor
        if self.settings and self.settings.gain_db:
            g = 10 ** (self.settings.gain_db / 20)
            base = sensor.channel_gain or (1.0, 1.0, 1.0)
            sensor = SensorModel(sensor.bit_depth, sensor.black_level_dn, sensor.full_well_e,
                                 sensor.read_noise_e, tuple(g * b for b in base), sensor.bayer)
        return sensor

    def _render_binned(self, dev: MockDevice, t_s: float, index: int, strip_rows: int = 256) -> np.ndarray:
        """The frame rendered on the grid (world.bin > 1), repeated bin x bin to the sensor size,
        noise drawn per sensor pixel a strip of rows at a time."""
        world, b = self.world, self.world.bin
        h, w = world.grid_shape
        rel = world.relative(t_s, self.label)
        video = torch.from_numpy(world.video()).double()
        if dev.kind == "rs":
            if world.psf is None:
                raise HardwareError(f"{self.label}: the mock RS camera needs a PSF")
            timing = RollingShutterTiming(dev.line_time_s, self.exposure_s, rows=w if dev.readout == "columns" else h,
                                          rows_per_bin=b, trigger_s=rel, readout=dev.readout)
            world.check_inside(rel, timing.end_s, self.label)
            op = rolling_shutter_for(torch.from_numpy(world.grid_psf()), torch.from_numpy(timing.weights(world.grid)),
                                     (h, w), transposed=timing.transposed)
            y = op.A(video).numpy()
        else:
            timing = GlobalShutterTiming((rel,), self.exposure_s)
            world.check_inside(rel, timing.end_s, self.label)
            y = GlobalShutter(torch.from_numpy(timing.weights(world.grid)), 3, (h, w)).A(video)[:, 0].numpy()
            if dev.gs_to_rs is not None:  # the sensor-pixel map, conjugated to grid pixels
                scale = np.array([[b, 0, (b - 1) / 2], [0, b, (b - 1) / 2], [0, 0, 1.0]])
                y = warp_seen(y, np.linalg.inv(scale) @ np.asarray(dev.gs_to_rs, np.float64) @ scale)
        sensor, rng = self._sensor(), np.random.default_rng([dev.seed, index])
        step = b * max(1, strip_rows // b)
        out = None
        for r0 in range(0, world.rows, step):
            part = y[:, r0 // b:(r0 + step) // b].repeat(b, axis=1).repeat(b, axis=2)
            raw = sensor.capture(part, self.exposure_s, world.grid.dt_s, rng=rng, noise=dev.noise)
            if out is None:
                out = np.empty((world.rows, *raw.shape[1:]), raw.dtype)
            out[r0:r0 + raw.shape[0]] = raw
        return out

    def _render_static(self, dev: MockDevice) -> np.ndarray:
        """Operator units (3, N, N) of the static target: a static scene s gives
        exposure / dt x (PSF conv s) on the RS sensor and exposure / dt x s on a GS sensor."""
        world = self.world
        img = world.static_image(dev)
        scale = self.exposure_s / world.grid.dt_s
        if dev.kind != "rs":
            return scale * img
        if world.psf is None:
            raise HardwareError(f"{self.label}: the mock RS camera needs a PSF")
        conv = PSFConvolution(torch.from_numpy(world.psf), (world.rows, world.cols), channels=3)
        return scale * conv.A(torch.from_numpy(img)).numpy()

    def _render_led(self, dev: MockDevice, t_s: float) -> np.ndarray:
        """Operator units (3, H, W) of the generator-driven LED's glow: each row integrates the
        LED's brightness over its own exposure, row r starting r true line times after t_s."""
        world = self.world
        light = world.light()
        if light is None or dev.led_level <= 0:
            return np.zeros((3, world.rows, world.cols))
        high = led_brightness(light.high_v, dev.led_level)
        if light.waveform == "square":
            low = led_brightness(light.low_v, dev.led_level)
            starts = t_s + np.arange(world.rows) * dev.line_time_s
            on = square_on_fraction(starts, self.exposure_s, light.frequency_hz)
            rows = low + (high - low) * on
        else:
            rows = np.full(world.rows, high)
        scale = self.exposure_s / world.grid.dt_s
        return scale * self._led_pattern() * rows[None, :, None]

    def _led_pattern(self) -> np.ndarray:
        """(3, H, W), peak 1: a broad spot through the diffuser, half of it the caustic (the PSF)."""
        world = self.world
        y, x = np.mgrid[0:world.rows, 0:world.cols]
        r2 = ((y - (world.rows - 1) / 2) / world.rows) ** 2 + ((x - (world.cols - 1) / 2) / world.cols) ** 2
        spot = np.exp(-r2 / (2 * 0.5 ** 2))
        caustic = np.ones((3, world.rows, world.cols))
        if world.psf is not None and world.psf.shape[-2:] == (world.rows, world.cols):
            p = world.psf if world.psf.shape[0] == 3 else np.repeat(world.psf[:1], 3, axis=0)
            caustic = p / np.maximum(p.max(axis=(1, 2), keepdims=True), 1e-30)
        return spot[None] * (0.5 + 0.5 * caustic)

    def disarm(self) -> None:
        with self._cv:
            self.armed = False
            self._pending.clear()

    def close(self) -> None:
        self.disarm()
        self.device = None
