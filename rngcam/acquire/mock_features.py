"""The mock RS camera's feature map (rngcam.acquire.mock_camera): a writable Height and a
SensorReadoutTime as rough as the vendor's."""

from __future__ import annotations

from rngcam.acquire.features import FeatureMap
from rngcam.errors import HardwareError

READOUT_OVERHEAD_S = 12.5e-6  # constant part of the mock RS SensorReadoutTime


class MockFeatures(FeatureMap):
    """The mock RS sensor's feature map: a writable Height and its SensorReadoutTime (us),
    whose slope is (1 + bias) x the true line time (module doc)."""

    def __init__(self, rows: int, line_time_s: float, bias: float = 0.0):
        self.rows, self.line_time_s, self.height = int(rows), float(line_time_s), int(rows)
        self.bias = float(bias)

    def readable(self, name: str) -> bool:
        return name in ("Height", "SensorReadoutTime")

    def writable(self, name: str) -> bool:
        return name == "Height"

    def get(self, name: str):
        if name == "Height":
            return self.height
        if name == "SensorReadoutTime":  # reported to 0.01 us, like a camera's float feature
            return round((READOUT_OVERHEAD_S + self.height * self.line_time_s * (1 + self.bias)) * 1e6, 2)
        raise HardwareError(f"mock RS camera has no feature {name!r}")

    def set(self, name: str, value) -> None:
        if name != "Height" or not 2 <= int(value) <= self.rows:
            raise HardwareError(f"mock RS camera: cannot set {name} to {value!r}")
        self.height = int(value)

    def execute(self, name: str) -> None:
        raise HardwareError(f"mock RS camera has no command {name!r}")
