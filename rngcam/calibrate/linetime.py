"""RS line time from SensorReadoutTime at several ROI heights.

No camera feature reports the line time. A rolling-shutter sensor's readout time grows by one
line time per row, plus a constant overhead, so the line time is the slope of
SensorReadoutTime against ROI height: fitted by least squares over two or more heights, with
the fit's residual showing whether the camera behaves linearly.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from rngcam.errors import HardwareError, RngcamError


@dataclass(frozen=True)
class LineTimeFit:
    """line_time_s: slope; overhead_s: intercept; residual_s: RMS misfit of the readout times."""

    line_time_s: float
    overhead_s: float
    residual_s: float
    heights: tuple[int, ...]
    readout_s: tuple[float, ...]


def fit_line_time(heights, readout_s) -> LineTimeFit:
    """Least-squares slope of readout time (s) against ROI height (rows)."""
    h = np.asarray(heights, dtype=np.float64)
    r = np.asarray(readout_s, dtype=np.float64)
    if h.shape != r.shape or h.ndim != 1:
        raise RngcamError(f"heights and readout times must be 1-D and equal in length, got {h.shape} and {r.shape}")
    if not (np.all(np.isfinite(h)) and np.all(np.isfinite(r))):
        raise RngcamError("heights and readout times must be finite")
    if len(np.unique(h)) < 2:
        raise RngcamError("the line time needs readout times at two or more different ROI heights")
    slope, intercept = np.polyfit(h, r, 1)
    residual = float(np.sqrt(np.mean((r - (slope * h + intercept)) ** 2)))
    if not slope > 0:
        raise RngcamError(f"SensorReadoutTime does not grow with the ROI height (slope {slope:.3g} s/row); "
                          "the camera may not be a rolling-shutter sensor")
    return LineTimeFit(float(slope), float(intercept), residual,
                       tuple(int(x) for x in h), tuple(float(x) for x in r))


def default_heights(full_height: int, minimum: int = 2, count: int = 4) -> list[int]:
    """`count` heights from the full ROI height down to a quarter of it (even numbers, so
    Bayer sensors accept them), largest first."""
    low = max(minimum, full_height // 4)
    hs = np.linspace(full_height, low, count)
    out = []
    for v in hs:
        even = int(v) - (int(v) % 2)
        if even >= minimum and even not in out:
            out.append(even)
    if full_height not in out:
        out.insert(0, full_height)
    return out


def readout_samples(features, heights) -> list[tuple[int, float]]:
    """Set each ROI height on a camera's feature map (rngcam.acquire.features.FeatureMap), read
    SensorReadoutTime (us) back, and restore the original height. Returns (height, seconds)."""
    if not (features.readable("SensorReadoutTime") and features.writable("Height")):
        raise HardwareError("the RS camera has no readable SensorReadoutTime or no writable Height; "
                            "its line time cannot be measured this way")
    original = int(features.get("Height"))
    samples = []
    try:
        for want in heights:
            features.set("Height", int(want))
            got = int(features.get("Height"))
            samples.append((got, float(features.get("SensorReadoutTime")) * 1e-6))
    finally:
        features.set("Height", original)
    return samples
