"""The rig's cameras opened for calibration shots: software-triggered frames of a static target.

No trigger generator is needed: the target does not move, so each camera is triggered by
software, one frame at a time, waiting until it is ready. The cameras come from acquire's
device factory, so the mock rig is just another backend. `show(target, instruction)` sets the
target up: a backend that can (the mock) shows a point source, the chart or darkness itself;
otherwise the operator is asked through `ask` (the command line waits for Enter; with no
`ask`, it assumes the target is already in place and says so).
"""

from __future__ import annotations

import contextlib
import dataclasses
from collections.abc import Callable

import numpy as np

from rngcam.acquire.camera import Camera, CameraSettings, Configured
from rngcam.acquire.factory import Devices, open_devices
from rngcam.acquire.resolve import ResolvedRig
from rngcam.config import CameraConfig
from rngcam.errors import HardwareError
from rngcam.physics.sensor import frame_to_measurement

Progress = Callable[[str], None]
READY_TIMEOUT_S = 2.0


class Bench:
    """Context manager: opens the rig's cameras (`roles`), configures them for software
    triggers, and closes them (disarmed) on exit whatever happened."""

    def __init__(self, resolved: ResolvedRig, roles=("rs", "gs"), progress: Progress = print,
                 ask: Callable[[str], None] | None = None):
        """`resolved`: the rig's values (rngcam.acquire.resolve); its `rig_psf` is the mock
        world's optics, so resolve without the PSF when only features are needed."""
        self.resolved, self.rig = resolved, resolved.rig
        self.roles, self.progress, self.ask = tuple(roles), progress, ask
        self.devices: Devices | None = None
        self.cams: dict[str, Camera] = {}
        self.configured: dict[str, Configured] = {}
        self._stack = contextlib.ExitStack()

    def config(self, role: str) -> CameraConfig:
        return getattr(self.rig.config.cameras, role)

    def __enter__(self):
        try:
            self.devices = open_devices(self.resolved)
            for role in self.roles:
                cfg = self.config(role)
                cam = self._stack.enter_context(self.devices.camera(role))
                self.cams[role] = cam
                settings = dataclasses.replace(CameraSettings.from_config(cfg), trigger_source="Software",
                                               chunk_timestamps=False)
                self.configured[role] = cam.configure(settings)
                for w in self.configured[role].warnings:
                    self.progress(f"warning: {w}")
                self.progress(f"{role} camera: {cam.info.model} serial {cam.info.serial} ({cfg.backend}), "
                              f"exposure {self.exposure_s(role) * 1e6:g} us, software trigger")
        except BaseException:
            self._stack.close()
            raise
        return self

    def __exit__(self, *exc) -> None:
        self._stack.close()

    def camera(self, role: str) -> Camera:
        if role not in self.cams:
            raise HardwareError(f"the {role.upper()} camera is not open on this bench")
        return self.cams[role]

    def exposure_s(self, role: str) -> float:
        return float(self.configured[role].exposure_s or self.config(role).exposure_s)

    def black_level_dn(self, role: str) -> float:
        return self.resolved.black_level_dn[role]

    def show(self, target: str, instruction: str) -> None:
        """Put `target` ("point", "chart" or "dark") in front of the cameras."""
        if self.devices.show(target):
            self.progress(f"{self.devices.kind}: showing the {target} target")
        elif self.ask is not None:
            self.ask(instruction)
        else:
            self.progress(f"assuming: {instruction}")

    def grab(self, role: str, count: int) -> list[np.ndarray]:
        """`count` raw frames from one camera, one software trigger each."""
        cam, cfg = self.camera(role), self.config(role)
        frames = []
        cam.arm()
        try:
            for i in range(count):
                cam.wait_ready(READY_TIMEOUT_S)
                cam.software_trigger()
                frames.append(cam.fetch(cfg.fetch_timeout_s, f"{role.upper()} frame {i + 1} of {count}").data)
        finally:
            cam.disarm()
        return frames

    def measurement(self, role: str, frames: list[np.ndarray]) -> np.ndarray:
        """Mean of raw frames in operator units (C, H, W) on a grid of dt = exposure (so a
        static scene of intensity v reads v), Bayer binned 2x2 per colour."""
        cfg = self.config(role)
        e = self.exposure_s(role)
        return np.mean([frame_to_measurement(f, cfg.pixel_format, self.black_level_dn(role), cfg.bit_depth,
                                             e, e) for f in frames], axis=0)
