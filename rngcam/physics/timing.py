"""Shutter timing: exact exposure weights of RS row bins and GS frames on the video time grid.

Convention (docs/design.md): the video grid starts at the RS trigger T0 = 0; frame k covers
[k*dt, (k+1)*dt). An exposure interval [a, b) becomes a weight vector over frames equal to
its overlap with each frame interval divided by dt. A grid row that bins s sensor rows is
the *mean* of those rows, so its weight is the mean of s shifted rects (a trapezoid), and
every row's weights sum to its exposure / dt (exposure_s, but for global-reset). When exposures
align with the grid the weights are exactly the paper's 0/1 rect indicator.

Readout orders (READOUTS; `RollingShutterTiming.readout`, docs/design.md): when each sensor row
starts and ends exposing. With N sensor rows, line time L and trigger T, row r exposes
[T + s(r) L, T + s(r) L + exposure) where s(r), in lines, is r (top-down), N - 1 - r (bottom-up),
floor(|r - (N - 1) / 2|) (centre-out: two halves read from the centre row outwards, one line time
per row each), min(r, N - 1 - r) (edges-in: two halves read from the top and bottom edges inwards);
global-reset rows all start at T and row r ends at T + exposure + r L. `columns` is top-down
along the sensor's columns, left to right: the timing's rows are the sensor's columns (a
reconstruction problem transposes the image, rngcam.recon.problem).

All arithmetic is done in units of dt (float64) so aligned cases come out exact.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
import torch
from torch import Tensor

# Relative tolerance for deciding that an exposure end falls on a frame edge.
_EDGE_TOL = 1e-9

# Readout orders a rolling-shutter sensor can have (the module docstring gives each one's times).
READOUTS = ("top-down", "bottom-up", "columns", "centre-out", "edges-in", "global-reset")
DEFAULT_READOUT = "top-down"


def check_readout(readout) -> str:
    """`readout` if it names a readout order; ValueError (one line listing them) if not."""
    if not isinstance(readout, str) or readout not in READOUTS:
        shown = repr(readout)[:60]
        raise ValueError(f"readout must be one of {', '.join(READOUTS)}, got {shown}")
    return readout


def readout_lines(readout: str, n_rows: int) -> np.ndarray:
    """(n_rows,) float64: each sensor row's line count s(r) in `readout` (the module docstring):
    its start's offset from the trigger in line times, or for global-reset its end's (beyond the
    exposure). For `columns` the rows are the sensor's columns."""
    check_readout(readout)
    r = np.arange(n_rows, dtype=np.float64)
    if readout == "bottom-up":
        return n_rows - 1 - r
    if readout == "centre-out":
        return np.floor(np.abs(r - (n_rows - 1) / 2))
    if readout == "edges-in":
        return np.minimum(r, n_rows - 1 - r)
    return r  # top-down, columns (the rows are columns), global-reset (ends)


def _positive(name: str, value: float) -> None:
    if not (isinstance(value, (int, float)) and math.isfinite(value) and value > 0):
        raise ValueError(f"{name} must be a finite positive number, got {value!r}")


def _near_edge(x: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The nearest frame edge of times `x` (in frames), and whether x is within rounding of it."""
    nearest = np.round(x)
    return nearest, np.abs(x - nearest) <= _EDGE_TOL * np.maximum(1.0, np.abs(x))


def _snap_interval(a: np.ndarray, b: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Snap an interval (in frames) to frame edges by moving it whole, so its length is kept.

    Snapping each end on its own would change a short exposure's length by up to the snap
    tolerance (an exposure of 0.002 frames starting 1e-11 frames after an edge would grow by
    4e-9 of itself). The interval is anchored at its start if that lies on an edge, else at its
    end; a length within rounding of a whole number of frames becomes that number.
    """
    whole, is_whole = _near_edge(b - a)
    length = np.where(is_whole, whole, b - a)
    a_edge, on_start = _near_edge(a)
    b_edge, on_end = _near_edge(b)
    start = np.where(on_start, a_edge, np.where(on_end, b_edge - length, a))
    end = np.where(on_start | ~on_end, start + length, b_edge)
    return start, end


def interval_weights(starts, ends, dt: float, n_frames: int) -> np.ndarray:
    """Overlap of each interval [starts[i], ends[i]) with each frame [k dt, (k+1) dt), / dt.

    `starts`/`ends` are arrays (any shape, seconds); returns shape (*starts.shape, n_frames).
    """
    _positive("dt", dt)
    a, b = _snap_interval(np.asarray(starts, dtype=np.float64)[..., None] / dt,
                          np.asarray(ends, dtype=np.float64)[..., None] / dt)
    k = np.arange(n_frames, dtype=np.float64)
    # overlap of [a, b) with [k, k+1), in frame units, computed by clipping both ends.
    return np.clip(np.minimum(b, k + 1) - np.maximum(a, k), 0.0, None)


def frames_needed(end_s: float, dt: float) -> int:
    """Number of grid frames needed to cover [0, end_s), tolerant to rounding at an edge."""
    n = end_s / dt
    return max(1, int(math.ceil(n - _EDGE_TOL * max(1.0, n))))


@dataclass(frozen=True)
class RollingShutterTiming:
    """Rolling-shutter camera timing.

    Top-down (the default `readout`), sensor row r starts exposing at trigger_s + r * line_time_s
    for exposure_s; other readout orders are in the module docstring. Grid row i is the mean of
    sensor rows [i*rows_per_bin, (i+1)*rows_per_bin). For readout `columns`, "rows" are the
    sensor's columns throughout.
    """

    line_time_s: float
    exposure_s: float
    rows: int  # grid rows (after binning)
    rows_per_bin: int = 1
    trigger_s: float = 0.0
    readout: str = DEFAULT_READOUT

    def __post_init__(self):
        _positive("line_time_s", self.line_time_s)
        _positive("exposure_s", self.exposure_s)
        if int(self.rows) != self.rows or self.rows < 1:
            raise ValueError(f"rows must be a positive integer, got {self.rows!r}")
        if int(self.rows_per_bin) != self.rows_per_bin or self.rows_per_bin < 1:
            raise ValueError(f"rows_per_bin must be a positive integer, got {self.rows_per_bin!r}")
        if not math.isfinite(self.trigger_s) or self.trigger_s < 0:
            raise ValueError(f"trigger_s must be >= 0 (the grid starts at T0), got {self.trigger_s!r}")
        check_readout(self.readout)

    @property
    def transposed(self) -> bool:
        """Whether the timing's rows are the sensor's columns (readout `columns`)."""
        return self.readout == "columns"

    @property
    def grid_dt_s(self) -> float:
        """The natural video frame duration: one grid row's worth of line time."""
        return self.line_time_s * self.rows_per_bin

    def _lines(self) -> np.ndarray:
        """(rows, rows_per_bin) line counts of the sensor rows (readout_lines)."""
        return readout_lines(self.readout, self.rows * self.rows_per_bin).reshape(self.rows, self.rows_per_bin)

    def sensor_row_windows(self) -> tuple[np.ndarray, np.ndarray]:
        """(starts, ends) in seconds, shape (rows, rows_per_bin)."""
        offsets = self.trigger_s + self._lines() * self.line_time_s
        if self.readout == "global-reset":
            return np.full_like(offsets, self.trigger_s), offsets + self.exposure_s
        return offsets, offsets + self.exposure_s

    @property
    def readout_span_s(self) -> float:
        """From the first row's start to the last one's (global-reset: from the first end to the last)."""
        return float(readout_lines(self.readout, self.rows * self.rows_per_bin).max()) * self.line_time_s

    @property
    def end_s(self) -> float:
        """End of the last sensor row's exposure."""
        return self.trigger_s + self.readout_span_s + self.exposure_s

    def stretched_weights(self, grid: VideoGrid, rows: Tensor, factor: Tensor) -> Tensor:
        """(R, n_frames) weights of grid rows `rows` (R,) when the true line time is `factor` (a
        0-d tensor) times this one, differentiable in `factor`; at factor 1 they are `weights`. An
        exposure reaching past the grid's last edge counts in the last frame (the video held there)."""
        dtype = factor.dtype
        lines = torch.from_numpy(self._lines()).to(dtype=dtype, device=factor.device)[rows.to(factor.device)]
        offsets = (self.trigger_s + lines * (self.line_time_s * factor)) / grid.dt_s  # (R, s) in frames
        if self.readout == "global-reset":
            a = torch.full_like(offsets, self.trigger_s / grid.dt_s)
            b = offsets + self.exposure_s / grid.dt_s
        else:
            a, b = offsets, offsets + self.exposure_s / grid.dt_s
        k = torch.arange(grid.n_frames, dtype=dtype, device=factor.device)
        upper = torch.where(k == grid.n_frames - 1, torch.full_like(k, math.inf), k + 1)
        overlap = (torch.minimum(b[..., None], upper) - torch.maximum(a[..., None], k)).clamp_min(0)
        return overlap.mean(dim=1)

    def weights(self, grid: VideoGrid) -> np.ndarray:
        """(rows, n_frames) weights: mean over the bin's sensor rows of overlap/dt."""
        starts, ends = self.sensor_row_windows()
        if self.rows_per_bin == 1:
            return interval_weights(starts[:, 0], ends[:, 0], grid.dt_s, grid.n_frames)
        # Integer multiples of the line time in units of dt keep aligned cases exact.
        return interval_weights(starts, ends, grid.dt_s, grid.n_frames).mean(axis=1)


@dataclass(frozen=True)
class GlobalShutterTiming:
    """Global-shutter camera: one exposure of exposure_s starting at each trigger time."""

    trigger_s: tuple[float, ...]
    exposure_s: float

    def __post_init__(self):
        _positive("exposure_s", self.exposure_s)
        object.__setattr__(self, "trigger_s", tuple(float(t) for t in self.trigger_s))
        for t in self.trigger_s:
            if not math.isfinite(t):
                raise ValueError(f"GS trigger times must be finite, got {t!r}")

    @property
    def n_frames(self) -> int:
        return len(self.trigger_s)

    @property
    def end_s(self) -> float:
        return max(self.trigger_s, default=0.0) + self.exposure_s

    @property
    def start_s(self) -> float:
        return min(self.trigger_s, default=0.0)

    def overlaps(self, start_s: float, end_s: float) -> np.ndarray:
        """(n_gs_frames,) bool: which exposures overlap the window [start_s, end_s)."""
        t = np.asarray(self.trigger_s, dtype=np.float64)
        return (t < end_s) & (t + self.exposure_s > start_s)

    def subset(self, keep) -> GlobalShutterTiming:
        """The timing of the frames `keep` (indices or a bool mask)."""
        t = np.asarray(self.trigger_s, dtype=np.float64)[np.asarray(keep)]
        return GlobalShutterTiming(tuple(t), self.exposure_s)

    def shifted(self, by_s: float) -> GlobalShutterTiming:
        return GlobalShutterTiming(tuple(t + by_s for t in self.trigger_s), self.exposure_s)

    def weights(self, grid: VideoGrid) -> np.ndarray:
        """(n_gs_frames, n_frames) weights: overlap of each GS exposure with each frame, / dt."""
        t = np.asarray(self.trigger_s, dtype=np.float64)
        return interval_weights(t, t + self.exposure_s, grid.dt_s, grid.n_frames)

    def centres_s(self) -> np.ndarray:
        """Mid-exposure time of each GS frame (where a key frame sits in the video)."""
        return np.asarray(self.trigger_s, dtype=np.float64) + self.exposure_s / 2


@dataclass(frozen=True)
class VideoGrid:
    """The reconstruction's time grid: n_frames frames of dt_s seconds from T0 = 0."""

    dt_s: float
    n_frames: int

    def __post_init__(self):
        _positive("dt_s", self.dt_s)
        if int(self.n_frames) != self.n_frames or self.n_frames < 1:
            raise ValueError(f"n_frames must be a positive integer, got {self.n_frames!r}")

    @classmethod
    def covering(cls, rs: RollingShutterTiming | None, gs: GlobalShutterTiming | None = None,
                 dt_s: float | None = None) -> VideoGrid:
        """The grid that covers every exposure; dt defaults to the RS line time x rows_per_bin."""
        if dt_s is None:
            if rs is None:
                raise ValueError("dt_s is required when there is no rolling-shutter camera")
            dt_s = rs.grid_dt_s
        ends = [c.end_s for c in (rs, gs) if c is not None]
        if not ends:
            raise ValueError("a video grid needs at least one camera's timing")
        return cls(dt_s=float(dt_s), n_frames=frames_needed(max(ends), dt_s))

    @staticmethod
    def frames_before(gs: GlobalShutterTiming | None, dt_s: float) -> int:
        """Whole frames a grid needs before T0 to cover the GS exposures that start before it."""
        if gs is None or gs.n_frames == 0 or gs.start_s >= 0:
            return 0
        return int(math.ceil(-gs.start_s / dt_s - _EDGE_TOL))

    def edges_s(self) -> np.ndarray:
        return np.arange(self.n_frames + 1, dtype=np.float64) * self.dt_s

    def centres_s(self) -> np.ndarray:
        return (np.arange(self.n_frames, dtype=np.float64) + 0.5) * self.dt_s
