"""Measured exposure starts: camera ticks -> host time -> the RS trigger's timeline.

Each camera stamps a frame with its own tick counter (chunk data: ExposureStart / FrameStart /
Timestamp, else the transport layer's frame timestamp). The counters run on their own
oscillators, so the ticks are first mapped to the host clock:

- latch: the camera's timestamp latch (TimestampLatch / TimestampLatchValue on ace 2 and USB,
  GevTimestampControlLatch / GevTimestampValue on GigE) read with the host clock before arming
  and after fetching: a straight line through those pairs (one pair: the nominal tick length);
- host fit: otherwise a least-squares fit of the frames' ticks against host times taken right
  after each grab, less the exposure; it keeps the readout and transfer time as a bias, and its
  slope is fitted only over a long enough span (else the nominal tick length).

The RS trigger's timeline is then anchored at the RS frame's measured exposure start (its own
trigger-to-exposure delay cannot be seen from its clock and is taken as 0): a GS frame's
measured start is its host time less the RS frame's, so one camera's debouncer and model delay
show as the GS frames' offsets against the plan.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

MIN_FIT_SPAN_S = 1.0  # host-fit slope only over frames spanning at least this long
MAX_SLOPE_RTOL = 1e-3  # a fitted tick length further than this from the nominal one is not believed


@dataclass(frozen=True)
class ClockMap:
    """host seconds = host_ref_s + (ticks - ticks_ref) x tick_s; `method` says how it was found."""

    tick_s: float
    ticks_ref: int
    host_ref_s: float
    method: str

    def host(self, ticks) -> np.ndarray:
        return np.array([self.host_ref_s + (int(t) - self.ticks_ref) * self.tick_s for t in ticks], np.float64)


def _line(hosts: list[float], ticks: list[int], nominal_s: float, fit_slope: bool) -> tuple[float, int, float]:
    """(tick length, reference ticks, host at the reference): least squares, the slope fitted
    only when asked and believable."""
    ref = int(ticks[0])
    x = np.array([int(t) - ref for t in ticks], np.float64)
    y = np.asarray(hosts, np.float64)
    slope = nominal_s
    if fit_slope and np.ptp(x) > 0:
        fitted = float(np.polyfit(x, y, 1)[0])
        if abs(fitted / nominal_s - 1) <= MAX_SLOPE_RTOL:
            slope = fitted
    return slope, ref, float(np.mean(y - slope * x))


def clock_map(latches: list[tuple[float, int]], frames, nominal_tick_s: float,
              exposure_s: float) -> ClockMap | None:
    """The camera's ticks -> host time, from its latches, else from its frames (module doc);
    None when neither gives a point."""
    if latches:
        hosts, ticks = [h for h, _ in latches], [t for _, t in latches]
        slope, ref, host = _line(hosts, ticks, nominal_tick_s, len(set(ticks)) > 1)
        return ClockMap(slope, ref, host, f"latch ({len(latches)} points)")
    pairs = [(f.host_s - exposure_s, f.start_ticks) for f in frames
             if f.host_s is not None and f.start_ticks is not None]
    if not pairs:
        return None
    ticks = [t for _, t in pairs]
    span = (max(ticks) - min(ticks)) * nominal_tick_s
    slope, ref, host = _line([h for h, _ in pairs], ticks, nominal_tick_s, span >= MIN_FIT_SPAN_S)
    return ClockMap(slope, ref, host, f"host fit ({len(pairs)} frames, biased by readout and transfer)")


@dataclass
class MeasuredStarts:
    """Each role's measured exposure starts on the RS trigger's timeline (None: not measured),
    how each was measured, and why any is missing."""

    starts: dict
    methods: dict
    warnings: list


def measure_starts(frames: dict, latches: dict, tick_s: dict, exposure_s: dict) -> MeasuredStarts:
    """`frames`, `latches`, `tick_s`, `exposure_s`: per role ("rs", "gs"). The RS frame anchors
    the timeline (module doc); without it nothing is measured."""
    host, methods, warnings = {}, {}, []
    for role, fs in frames.items():
        sources = {f.start_source for f in fs}
        if not fs or any(f.start_ticks is None for f in fs):
            warnings.append(f"{role.upper()} camera gives no exposure-start timestamps (no chunk data or "
                            "transport timestamp): exposure starts not measured, the plan is used")
            continue
        cmap = clock_map(latches.get(role, []), fs, tick_s[role], exposure_s[role])
        if cmap is None:
            warnings.append(f"{role.upper()} camera: no latch and no host times: exposure starts not measured")
            continue
        host[role] = cmap.host([f.start_ticks for f in fs])
        methods[role] = f"{' / '.join(sorted(s or '?' for s in sources))} ticks; clock: {cmap.method}"
    starts: dict = {role: None for role in frames}
    if "rs" in host:
        anchor = float(host["rs"][0])
        for role, values in host.items():
            starts[role] = values - anchor
    elif host:
        warnings.append("the RS frame's exposure start is not measured, so no GS start can be placed on "
                        "the RS trigger's timeline: the plan is used")
    return MeasuredStarts(starts, {r: m for r, m in methods.items() if starts.get(r) is not None}, warnings)
