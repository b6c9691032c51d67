"""The mock cameras' clocks and exposure starts (rigs' `mock:` section, rngcam.config.MockSceneConfig).

A real camera stamps each frame with its own tick counter, which is offset from the host clock and
drifts against it, and its exposure starts some time after the trigger edge (the debouncer, a
model-specific delay). The mock models both: `MockTiming` holds each role's `MockClock` and
the GS exposures' delay and jitter; the mock cameras report ExposureStart chunk ticks and have a
timestamp latch (unless the rig switches it off), so capture's mapping (rngcam.acquire.exposure_clock)
is exercised as on a camera. The mock's host clock is its world's clock (the generator's).
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

TICK_S = 1e-9  # the mock counters count nanoseconds, like a USB3 ace
JITTER_SIGMAS = 4.0  # the world's scene is long enough for a start this many sigmas late


@dataclass(frozen=True)
class MockClock:
    """ticks = (host time x (1 + drift) + offset) / TICK_S, rounded."""

    offset_s: float = 0.0
    drift_ppm: float = 0.0

    def ticks(self, host_s: float) -> int:
        return int(round((host_s * (1 + self.drift_ppm * 1e-6) + self.offset_s) / TICK_S))


@dataclass(frozen=True)
class MockTiming:
    """Both roles' clocks, whether they latch, and when GS exposures start after their trigger."""

    clocks: dict = field(default_factory=lambda: {"rs": MockClock(), "gs": MockClock()})
    latch: bool = True
    gs_start_offset_s: float = 0.0
    start_jitter_s: float = 0.0
    seed: int = 0

    @classmethod
    def from_config(cls, mock) -> MockTiming:
        """From a rig's mock section (None: ideal clocks, exposures at the triggers)."""
        if mock is None:
            return cls()
        clocks = {"rs": MockClock(mock.clock_offset_s, mock.clock_drift_ppm),
                  "gs": MockClock(-mock.clock_offset_s, -mock.clock_drift_ppm)}
        return cls(clocks, mock.timestamp_latch, mock.gs_start_offset_s, mock.start_jitter_s, mock.seed)

    def start_delay_s(self, role: str, index: int) -> float:
        """How long after its trigger exposure `index` (from 0 after each arm) of `role` starts."""
        if role != "gs":
            return 0.0
        jitter = 0.0
        if self.start_jitter_s > 0:
            jitter = self.start_jitter_s * float(np.random.default_rng([self.seed, 7, index]).standard_normal())
            jitter = float(np.clip(jitter, -JITTER_SIGMAS * self.start_jitter_s, JITTER_SIGMAS * self.start_jitter_s))
        return self.gs_start_offset_s + jitter

    def latest_delay_s(self) -> float:
        """The latest a GS exposure can start after its trigger (the scene must last that long)."""
        return max(0.0, self.gs_start_offset_s + JITTER_SIGMAS * self.start_jitter_s)
