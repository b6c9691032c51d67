"""Sensor figures from camera datasheets, for cameras that do not report their readout time.

The GS camera's shortest trigger spacing is its exposure plus its readout (non-overlapped
triggering). A camera that has SensorReadoutTime says so itself; otherwise the rig's
`readout_s`, else the figure here for the camera's model, scaled to the ROI's rows (readout time
is proportional to the rows read on these sensors), each with its source.

Row times (`ROW_TIMES`) are the manuals' per-model tables for rolling-shutter sensors, a sanity
check of a measured line time (rngcam calibrate linetime): far from the manual's figure is a
warning. Models the manuals we read do not list say so rather than guess.
"""

from __future__ import annotations

import re
from dataclasses import dataclass


@dataclass(frozen=True)
class SensorFigure:
    """Full-frame readout (1 / the maximum frame rate at full resolution) and where it is from."""

    readout_s: float
    rows: int
    source: str

    def readout_for(self, rows: int) -> float:
        return self.readout_s * min(1.0, rows / self.rows)


DATASHEETS: dict[str, SensorFigure] = {
    # Basler ace U datasheets: maximum frame rate at full resolution.
    "acA1920-155uc": SensorFigure(1 / 164, 1200, "Basler acA1920-155uc datasheet: 164 fps at 1920 x 1200"),
    "acA1920-155um": SensorFigure(1 / 164, 1200, "Basler acA1920-155um datasheet: 164 fps at 1920 x 1200"),
    "acA5472-17uc": SensorFigure(1 / 17, 3648, "Basler acA5472-17uc datasheet: 17 fps at 5472 x 3648"),
    "acA5472-17um": SensorFigure(1 / 17, 3648, "Basler acA5472-17um datasheet: 17 fps at 5472 x 3648"),
}


def datasheet_figure(model: str) -> SensorFigure | None:
    """The figure for a model name (exact, or the first table key the name contains)."""
    if model in DATASHEETS:
        return DATASHEETS[model]
    return next((f for key, f in DATASHEETS.items() if key in model), None)


# --------------------------------------------------------------------------- row times

ROW_TIME_TOLERANCE = 0.05  # a measured line time further than this from the manual's is warned about


@dataclass(frozen=True)
class RowTime:
    """A rolling-shutter model's row time by pixel-format depth ("8", "12p", "12"; "*" for any),
    or none listed (`by_depth` empty) with at most an upper bound from the maximum frame rate."""

    by_depth: dict
    source: str
    upper_bound_s: float | None = None

    def for_format(self, pixel_format: str) -> float | None:
        if "*" in self.by_depth:
            return self.by_depth["*"]
        return self.by_depth.get(format_depth(pixel_format))


# Keyed by model family (the name without its gm/gc/um/uc suffix).
ROW_TIMES: dict[str, RowTime] = {
    # Basler ace USB 3.0 / GigE camera user's manuals, "Rolling shutter" sensor readout: the row time
    # (tRow) per model and pixel format; readout time = tRow x ROI height + a constant.
    "acA3800-14": RowTime({"8": 24.725e-6, "12p": 28.475e-6, "12": 30.975e-6},
                          "Basler ace manual, acA3800-14: tRow 24.725 / 28.475 / 30.975 us at 8 / 12p / 12 bit"),
    "acA1920-25": RowTime({"*": 35.000e-6}, "Basler ace manual, acA1920-25: tRow 35.000 us"),
    "acA2500-14": RowTime({"*": 35.000e-6}, "Basler ace manual, acA2500-14: tRow 35.000 us"),
    # Not listed in the manuals we read; 17 fps at 3648 rows bounds the 8-bit row time from above
    # (the sensor reads every row within a frame period).
    "acA5472-17": RowTime({}, "not listed; Basler acA5472-17 datasheet: 17 fps at 5472 x 3648 bounds it at 8 bit",
                          upper_bound_s=1 / (17 * 3648)),
    # A global-shutter sensor: no rolling row time to check.
    "acA1920-155": RowTime({}, "not listed (global shutter sensor)"),
}

_FAMILY = re.compile(r"^(?:basler\s+)?(aca\d+-\d+)(?:[gu][mc])?$", re.IGNORECASE)


def format_depth(pixel_format: str) -> str:
    """"8", "12p" (packed) or "12" ... from a GenICam pixel format name."""
    digits = "".join(ch for ch in pixel_format if ch.isdigit()) or "8"
    packed = pixel_format.endswith("p") or "Packed" in pixel_format
    return f"{digits}p" if packed and digits != "8" else digits


def row_time(model: str) -> tuple[str, RowTime] | None:
    """(family, RowTime) for a camera's exact model name (a "Basler " prefix allowed), else None."""
    m = _FAMILY.match(model.strip())
    if not m:
        return None
    family = next((k for k in ROW_TIMES if k.lower() == m.group(1).lower()), None)
    return (family, ROW_TIMES[family]) if family else None


def row_time_warning(model: str, pixel_format: str, measured_s: float) -> str | None:
    """A warning when `measured_s` is more than ROW_TIME_TOLERANCE from the manual's row time
    (or above its upper bound); None when it agrees or the model is not in the table."""
    found = row_time(model)
    if found is None:
        return None
    family, rt = found
    listed = rt.for_format(pixel_format)
    if listed is not None and abs(measured_s / listed - 1) > ROW_TIME_TOLERANCE:
        return (f"the measured line time {measured_s * 1e6:.4g} us is {measured_s / listed - 1:+.1%} from the row time "
                f"the manual gives for the {family} at {format_depth(pixel_format)} bit ({listed * 1e6:.3f} us; "
                f"{rt.source}): check the pixel format, binning and the measurement")
    bounded = listed is None and rt.upper_bound_s is not None and format_depth(pixel_format) == "8"
    if bounded and measured_s > rt.upper_bound_s * (1 + ROW_TIME_TOLERANCE):
        return (f"the measured line time {measured_s * 1e6:.4g} us exceeds the {rt.upper_bound_s * 1e6:.2f} us the "
                f"{family}'s maximum frame rate allows ({rt.source}): check the measurement")
    return None
