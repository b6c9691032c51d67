"""Sensor figures from camera datasheets, for cameras that do not report their readout time.

The GS camera's shortest trigger spacing is its exposure plus its readout (non-overlapped
triggering). A camera that has SensorReadoutTime says so itself; otherwise the rig's
`readout_s`, else the figure here for the camera's model, scaled to the ROI's rows (readout time
is proportional to the rows read on these sensors), each with its source.
"""

from __future__ import annotations

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
