"""The mock rig behind the device factory (rngcam.acquire.factory; it implements `Devices`):
one `MockWorld` (the rig's mock scene on the video grid, seen through the rig's PSF) with both
mock cameras plugged in, each with the sensor physics of its rig section
(rngcam.acquire.resolve.MockTruth)."""

from __future__ import annotations

from dataclasses import replace

from rngcam.acquire.camera import Camera
from rngcam.acquire.devices import list_mock_cameras
from rngcam.acquire.mock_camera import MockCamera, MockDevice, MockWorld
from rngcam.acquire.mock_clock import MockTiming
from rngcam.acquire.resolve import ROLES, ResolvedRig
from rngcam.errors import ConfigError
from rngcam.formats.bundle import Truth
from rngcam.physics.sensor import SensorModel
from rngcam.physics.timing import VideoGrid
from rngcam.video_plan import default_max_memory_bytes


class MockDevices:
    """Mock cameras in one simulated world; they render frames from the scene."""

    kind = "mock"

    def __init__(self, resolved: ResolvedRig):
        self.resolved = resolved
        rig, c = resolved.rig, resolved.rig.config
        _, gs_timing, self.grid = resolved.timing()
        rs_roi, grid_bin = c.cameras.rs.roi, c.recon.grid_bin
        h, w = rs_roi.height // grid_bin, rs_roi.width // grid_bin  # the mock renders on the grid
        need = 3 * self.grid.n_frames * h * w * 4 * 3  # the float32 truth video, the frames rendered from it
        if need > default_max_memory_bytes():
            raise ConfigError(f"{rig.path}: the mock scene would need about {need / 2**30:,.1f} GiB "
                              f"({self.grid.n_frames} frames of {h}x{w}x3), more than this machine can "
                              "spare: use a smaller cameras.rs.roi or a larger recon.grid_bin for the mock rig")
        self.world = MockWorld(c.mock.scene, (rs_roi.height, rs_roi.width), self._world_grid(), resolved.rig_psf,
                               seed=c.mock.seed, key_times_s=list(gs_timing.centres_s()), options=c.mock.options,
                               bin=grid_bin)
        self.world.timing = MockTiming.from_config(c.mock)
        truth = resolved.mock
        for role in ROLES:
            cam = getattr(c.cameras, role)
            m = truth.sensors[role]
            sensor = SensorModel(bit_depth=cam.bit_depth, black_level_dn=m.black_level_dn,
                                 full_well_e=m.full_well_e, read_noise_e=m.read_noise_e,
                                 channel_gain=None if m.channel_gain is None else tuple(m.channel_gain))
            if sensor.pixel_format != cam.pixel_format:
                raise ConfigError(f"{rig.path}: cameras.{role}.pixel_format: mock cameras deliver "
                                  f"{sensor.pixel_format}, not {cam.pixel_format}")
            misaligned = role == "gs" and m.misalignment is not None
            self.world.plug(MockDevice(cam.serial, cam.model or f"mock {role.upper()}", role, sensor,
                                       noise=m.noise, seed=m.seed,
                                       line_time_s=truth.line_time_s if role == "rs" else None,
                                       readout=cam.readout,
                                       readout_s=m.readout_s,
                                       readout_bias=truth.readout_bias if role == "rs" else 0.0,
                                       led_level=truth.led_level,
                                       gs_to_rs=tuple(map(tuple, truth.gs_to_rs)) if misaligned else None))

    def _world_grid(self) -> VideoGrid:
        """The bundle's grid, lengthened (same dt) when the sensor's true line time ends its
        window later than the resolved one says, or a GS exposure starts late (mock.gs_start_offset_s):
        the scene then lasts as long as the real exposures; the truth in the bundle is the
        bundle's grid (`truth`)."""
        c, truth = self.resolved.rig.config, self.resolved.mock
        rs, gs, grid = self.resolved.timing()
        real = replace(rs, line_time_s=truth.line_time_s)
        longer = VideoGrid.covering(real, gs.shifted(MockTiming.from_config(c.mock).latest_delay_s()), dt_s=grid.dt_s)
        return longer if longer.n_frames > grid.n_frames else grid

    def camera(self, role: str) -> Camera:
        cfg = getattr(self.resolved.rig.config.cameras, role)
        return MockCamera(cfg.serial, role.upper(), self.world)

    def show(self, target: str) -> bool:
        self.world.target = target
        return True

    def drive_light(self, source) -> bool:
        """Show the cameras a light whose waveform `source()` tells (None: no light)."""
        self.world.light = source
        return True

    def begin_shot(self) -> None:
        self.world.t0_s = None

    def truth(self) -> Truth:
        video = self.world.video()[:, :self.grid.n_frames]
        return Truth(video=video, frame_times_s=self.grid.edges_s()[:-1], dt_s=self.grid.dt_s)


def make_devices(resolved: ResolvedRig) -> MockDevices:
    """The factory's entry point (rngcam.backends): the mock builds its whole world at once."""
    return MockDevices(resolved)


def list_cameras(rig=None, **_options):
    """The mock cameras a rig plugs in (those of rigs/mock.yaml without a rig)."""
    return list_mock_cameras(rig)
