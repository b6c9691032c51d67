"""The reconstruction's video grid and memory, computed from a bundle's timing alone.

`plan_grid` is the one place that turns a bundle's timing into the video grid: which GS frames
take part (a GS exposure that misses the RS exposure window, before it or after it, is left
out), how many frames the grid has (T0 = 0 is the RS trigger; the grid starts earlier by whole
frames when a kept GS exposure starts before T0), and the video's size. It allocates nothing
frame-sized, so `inspect` and `recon` can refuse a video that would not fit before any
method allocates it.
"""

from __future__ import annotations

from dataclasses import dataclass, field, replace

import numpy as np

from rngcam.errors import BundleError, SettingError
from rngcam.formats.bundle import Bundle, camera_channels
from rngcam.memory import total_memory_bytes
from rngcam.physics.sensor import BAYER_FORMATS
from rngcam.physics.timing import GlobalShutterTiming, RollingShutterTiming, VideoGrid
from rngcam.untrusted import printable

DEFAULT_MAX_FRAMES = 100_000
MEMORY_FRACTION = 0.8  # of the machine's memory: the default --max-memory
BASE_BYTES = 430 * 2**20  # the interpreter, torch, OpenCV, h5py, matplotlib (measured: bench/large_grids.md)
# Of BASE_BYTES, the libraries' resident file pages as measured on a settled machine: page cache,
# reclaimable, and larger right after an install (rngcam.memory.mapped_file_bytes).
LIBRARY_BYTES = 165 * 2**20


@dataclass(frozen=True)
class MemoryModel:
    """A method's peak memory for a whole `rngcam recon` run (reading, set-up, solve, metrics and
    outputs), fitted to measured runs (each method's figures and their sources sit beside its
    registry entry): BASE_BYTES, plus `fixed_bytes` that do not grow with the video (learned
    networks, a coarse level's work), `bytes_per_element` per video element (C x K x H x W) and
    `bytes_per_pixel` per grid pixel of one frame (H x W: a step's or a network batch's working
    set over a fixed number of frames)."""

    bytes_per_element: float
    fixed_bytes: float = 0.0
    bytes_per_pixel: float = 0.0


@dataclass(frozen=True)
class GridPlan:
    """The video grid of a bundle: timings shifted so the grid starts at 0, and what was left out.

    origin_s: time of the grid's first edge relative to T0 (<= 0).
    gs_kept: indices of the bundle's GS frames that take part; gs_left_out: (index, reason).
    """

    rs: RollingShutterTiming
    gs: GlobalShutterTiming | None
    grid: VideoGrid
    origin_s: float
    channels: int
    height: int
    width: int
    gs_kept: np.ndarray
    gs_left_out: list[tuple[int, str]] = field(default_factory=list)
    psf_shape: tuple[int, ...] = ()  # the bundle's PSF (C, Hp, Wp) at the sensor's resolution

    @property
    def elements(self) -> int:
        return self.channels * self.grid.n_frames * self.height * self.width

    def describe(self) -> str:
        return (f"{self.grid.n_frames:,} frames of {self.height}x{self.width}x{self.channels} "
                f"at {1 / self.grid.dt_s:,.0f} fps")


def plan_grid(bundle: Bundle, grid_bin: int | None = None, dt_s: float | None = None) -> GridPlan:
    """The grid a reconstruction of `bundle` at `grid_bin` uses; BundleError for impossible timing."""
    cam = bundle.rs
    if cam is None:
        raise BundleError("the bundle has no rolling-shutter camera; the video grid is defined by it")
    mosaic = 2 if cam.pixel_format in BAYER_FORMATS else 1
    if grid_bin is None:
        grid_bin = bundle.meta.get("grid_bin", mosaic)
        if not isinstance(grid_bin, (int, float)) or not (1 <= grid_bin <= 1024) or grid_bin != int(grid_bin):
            raise BundleError(f"the bundle's meta grid_bin must be a whole number from 1 to 1024, "
                              f"got {printable(repr(grid_bin), 60)}")
        grid_bin = int(grid_bin)
    if int(grid_bin) != grid_bin or grid_bin < 1:
        raise SettingError(f"grid_bin must be a positive integer, got {grid_bin!r}", "grid_bin")
    if grid_bin % mosaic:
        raise BundleError(f"grid_bin {grid_bin} must be a multiple of 2 for a Bayer RS frame")
    shape = tuple(np.shape(cam.frames))
    sensor_rows, sensor_cols = shape[1], shape[2]
    rows, cols = sensor_rows // grid_bin, sensor_cols // grid_bin
    if rows < 1 or cols < 1:
        raise BundleError(f"cannot bin a {sensor_rows}x{sensor_cols} RS frame by {grid_bin}")
    try:
        readout = cam.readout
        rs = RollingShutterTiming(line_time_s=float(cam.line_time_s), exposure_s=float(cam.exposure_s),
                                  rows=cols if readout == "columns" else rows, rows_per_bin=grid_bin,
                                  trigger_s=float(np.asarray(cam.trigger_times_s)[0]), readout=readout)
        dt = float(dt_s) if dt_s is not None else rs.grid_dt_s
        gs, kept, left_out = None, np.zeros(0, dtype=int), []
        if bundle.gs is not None:
            all_gs = GlobalShutterTiming(tuple(np.asarray(bundle.gs.trigger_times_s, float)),
                                         float(bundle.gs.exposure_s))
            inside = all_gs.overlaps(rs.trigger_s, rs.end_s)
            kept = np.flatnonzero(inside)
            for i in np.flatnonzero(~inside):
                t = all_gs.trigger_s[i]
                left_out.append((int(i), f"its exposure [{t * 1e3:.3f}, {(t + all_gs.exposure_s) * 1e3:.3f}] ms "
                                         f"misses the RS exposure window [{rs.trigger_s * 1e3:.3f}, "
                                         f"{rs.end_s * 1e3:.3f}] ms"))
            gs = all_gs.subset(kept) if kept.size else None
        before = VideoGrid.frames_before(gs, dt)
        shift = before * dt
        if shift:
            rs = replace(rs, trigger_s=rs.trigger_s + shift)
            gs = gs.shifted(shift)
        grid = VideoGrid.covering(rs, gs, dt_s=dt)
    except (ValueError, OverflowError) as exc:
        raise BundleError(f"the bundle's timing is unusable: {exc}") from None
    psf = bundle.calibration.psf if bundle.calibration is not None else None
    return GridPlan(rs=rs, gs=gs, grid=grid, origin_s=-shift, channels=camera_channels(cam),
                    height=rows, width=cols, gs_kept=kept, gs_left_out=left_out,
                    psf_shape=tuple(int(n) for n in np.shape(psf)) if psf is not None else ())


def method_bytes(plan: GridPlan, memory: MemoryModel) -> int:
    """Estimated peak memory of reconstructing the plan's video with a method of `memory`."""
    return int(BASE_BYTES + memory.fixed_bytes + plan.elements * memory.bytes_per_element
               + plan.height * plan.width * memory.bytes_per_pixel + psf_bytes(plan, memory))


def psf_bytes(plan: GridPlan, memory: MemoryModel) -> int:
    """What the PSF adds to a method's estimate: its float64 copies at the sensor's resolution
    while it is prepared, and the operators' larger FFTs when it is larger than the frame (the
    fitted models hold a frame-sized PSF: FFTs of (2H - 1) x (2W - 1))."""
    if len(plan.psf_shape) < 2:
        return 0
    hp, wp = plan.psf_shape[-2:]
    c = plan.psf_shape[0] if len(plan.psf_shape) == 3 else 1
    raw = 3 * 8 * c * hp * wp  # as_chw's float64 copy, bias subtraction, resampling
    bin_ = plan.rs.rows_per_bin
    gh, gw = max(1, round(hp / bin_)), max(1, round(wp / bin_))
    h, w = plan.height, plan.width
    grow = (h + gh - 1) * (w + gw - 1) / ((2 * h - 1) * (2 * w - 1))
    return int(raw + max(0.0, grow - 1.0) * plan.elements * memory.bytes_per_element)


def default_max_memory_bytes() -> int:
    """The default memory limit: a fraction of this machine's memory."""
    return int(MEMORY_FRACTION * total_memory_bytes())


def gib(n: float) -> str:
    return f"{n / 2**30:,.1f} GiB"


def check_frames(plan: GridPlan, max_frames: int | None = None) -> None:
    """SettingError (one line) when the grid has more than `max_frames` frames."""
    max_frames = DEFAULT_MAX_FRAMES if max_frames is None else max_frames
    k = plan.grid.n_frames
    if k > max_frames:
        raise SettingError(f"the video would have {plan.describe()} (RS line time "
                           f"{plan.rs.line_time_s * 1e6:.4g} us), above max_frames {max_frames:,}: "
                           "check the bundle's timing, or raise max_frames", "max_frames")


def check_size(plan: GridPlan, method: str, memory: MemoryModel, max_frames: int | None = None,
               max_memory_bytes: int | None = None) -> int:
    """Estimated bytes for `method` (named in the error) of `memory`; SettingError (one line naming
    the figure and how to change it) past a limit."""
    check_frames(plan, max_frames)
    return check_memory(method_bytes(plan, memory), f"{method} would need about {{need}} for {plan.describe()}",
                        max_memory_bytes, "use a coarser grid_bin, or raise max_memory_bytes", "grid_bin")


def check_memory(need: int, what: str, max_memory_bytes: int | None = None,
                 fix: str = "raise max_memory_bytes", *settings: str) -> int:
    """`need` if it is within `max_memory_bytes` (None: the default); else SettingError: `what`
    (with {need} for the figure), the limit and `fix`, naming `settings` and max_memory_bytes."""
    max_memory_bytes = default_max_memory_bytes() if max_memory_bytes is None else max_memory_bytes
    if need > max_memory_bytes:
        raise SettingError(f"{what.format(need=gib(need))}, above max_memory_bytes {gib(max_memory_bytes)}: {fix}",
                           "max_memory_bytes", *settings)
    return need
