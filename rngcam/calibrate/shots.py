"""The rig's cameras opened for calibration shots: software-triggered frames of a static target.

No trigger generator is needed: the target does not move, so each camera is triggered by
software, one frame at a time, waiting until it is ready. `show(target, instruction)` sets the
target up: on the mock rig it tells the mock world to show a point source, the chart or
darkness; on real hardware it asks the operator through `ask` (the command line waits for
Enter; with no `ask`, it assumes the target is already in place and says so).
"""

from __future__ import annotations

import contextlib
import dataclasses
from collections.abc import Callable

import numpy as np

from rngcam.acquire.camera import Camera, CameraSettings, Configured
from rngcam.config import CameraConfig, MockSensor, Rig
from rngcam.errors import HardwareError
from rngcam.physics.sensor import frame_to_measurement

Progress = Callable[[str], None]
READY_TIMEOUT_S = 2.0


class Bench:
    """Context manager: opens the rig's cameras (`roles`), configures them for software
    triggers, and closes them (disarmed) on exit whatever happened."""

    def __init__(self, rig: Rig, roles=("rs", "gs"), progress: Progress = print,
                 ask: Callable[[str], None] | None = None, mock_psf: np.ndarray | None = None,
                 frames: bool = True):
        """`mock_psf`: the rig's PSF on the RS sensor grid when the caller has it already (the
        mock world's optics; loaded from the rig otherwise). frames=False: features only, so
        the mock world needs no optics."""
        self.rig, self.roles, self.progress, self.ask = rig, tuple(roles), progress, ask
        self.mock_psf, self.frames = mock_psf, frames
        self.world = None
        self.cams: dict[str, Camera] = {}
        self.configured: dict[str, Configured] = {}
        self._stack = contextlib.ExitStack()

    @property
    def is_mock(self) -> bool:
        return self.rig.config.cameras.rs.backend == "mock"

    def config(self, role: str) -> CameraConfig:
        return getattr(self.rig.config.cameras, role)

    def __enter__(self):
        from rngcam.acquire.capture import _make_camera, _mock_world, nominal_timing, rs_psf

        try:
            if self.is_mock:
                psf = self.mock_psf
                if psf is None and self.frames:
                    psf = rs_psf(self.rig, self.progress)[0]
                _, gs_timing, grid = nominal_timing(self.rig)
                self.world = _mock_world(self.rig, psf, gs_timing, grid)
            for role in self.roles:
                cfg = self.config(role)
                cam = self._stack.enter_context(_make_camera(cfg, role.upper(), self.world))
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
        cfg = self.config(role)
        return float((cfg.mock or MockSensor()).black_level_dn if cfg.backend == "mock" else cfg.black_level_dn)

    def show(self, target: str, instruction: str) -> None:
        """Put `target` ("point", "chart" or "dark") in front of the cameras."""
        if self.world is not None:
            self.world.target = target
            self.progress(f"mock: showing the {target} target")
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
