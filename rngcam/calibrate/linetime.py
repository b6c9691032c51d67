"""RS line time: measured from an LED's flicker, or estimated from SensorReadoutTime.

No camera feature reports the line time. Two ways to get it:

- Readout time (rough): a rolling-shutter sensor's readout time grows by one line time per
  row, so the line time is the slope of SensorReadoutTime against ROI height (least squares
  over two or more heights). The vendor calls SensorReadoutTime a rough estimate, so this is one.
- Flicker (measured): a generator channel drives an LED with a square wave of known frequency
  while the RS camera takes a frame of it through the diffuser. Row r starts exposing r line
  times after row 0, so the LED's on/off cycles lay bands along the rows whose frequency (cycles
  per row) is line time x LED frequency. Each row's light is divided by the same row of a frame
  with the LED steady on (which removes the caustic and the vignetting; saturated and dark
  pixels left out), and the bands' frequency is fitted: the periodogram's peak, refined by least
  squares of a Fourier series (fundamental and harmonics, over a slow quadratic baseline), its
  uncertainty from the fit's curvature. Two LED frequencies cross-check each other (aliasing or
  an LED that does not follow the generator shows as disagreement).
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


# --------------------------------------------------------------------------- flicker

TARGET_ROWS_PER_PERIOD = 40.0  # one LED period over tens of rows: many samples per band
MIN_PERIODS = 5.0  # bands across the frame at the first frequency (small sensors get shorter periods)
MIN_ROWS_PER_PERIOD = 3.0  # below this the bands alias
EXPOSURE_PERIODS = 1 / 3  # the RS exposure should span at most this much of an LED period
SECOND_FREQUENCY = 1.25  # the cross-check frequency, as a multiple of the first
MAX_SATURATED = 0.02  # fraction of the pixels saturated in either frame before the shot is refused
MIN_MODULATION = 0.02  # the bands' fundamental amplitude against the mean ratio
MIN_SNR = 20.0  # the bands' fundamental amplitude against the row noise
MAX_OFF_NOMINAL = 0.2  # a line time further than this from the rig's nominal one is refused
MAX_DISAGREEMENT = 0.005  # the two frequencies' line times may differ by this (relative) at most
HARMONICS = 9


@dataclass(frozen=True)
class FlickerPlan:
    """The LED frequencies (Hz) and the band periods (rows) they give at the nominal line time."""

    frequencies_hz: tuple[float, ...]
    rows_per_period: tuple[float, ...]
    nominal_line_time_s: float
    exposure_s: float


def plan_flicker(nominal_line_time_s: float, rows: int, exposure_s: float,
                 rows_per_period: float | None = None) -> FlickerPlan:
    """Two LED frequencies: bands of about TARGET_ROWS_PER_PERIOD rows (at least as long as three
    exposures, at least MIN_PERIODS of them across the frame), and SECOND_FREQUENCY times that.
    Refused in one line when the bands would alias or the exposure would wash them out."""
    lt = nominal_line_time_s
    if rows_per_period is None:
        rows_per_period = min(max(TARGET_ROWS_PER_PERIOD, exposure_s / (EXPOSURE_PERIODS * lt)), rows / MIN_PERIODS)
    periods = (float(rows_per_period), float(rows_per_period) / SECOND_FREQUENCY)
    if periods[1] < MIN_ROWS_PER_PERIOD:
        raise RngcamError(f"LED bands of {periods[1]:.2f} rows would alias (at least {MIN_ROWS_PER_PERIOD:g} rows per "
                          f"period): use --rows-per-period {MIN_ROWS_PER_PERIOD * SECOND_FREQUENCY:g} or more")
    if rows / periods[0] < 2:
        raise RngcamError(f"LED bands of {periods[0]:.1f} rows: fewer than two across the {rows} rows; "
                          f"use --rows-per-period {rows / MIN_PERIODS:.0f} or less")
    shortest = min(periods) * lt
    if exposure_s > 0.6 * shortest:
        raise RngcamError(f"the RS exposure ({exposure_s * 1e6:.0f} us) washes out LED bands of "
                          f"{shortest * 1e6:.0f} us: shorten the exposure to "
                          f"{EXPOSURE_PERIODS * shortest * 1e6:.0f} us "
                          "or less, or use a larger --rows-per-period")
    return FlickerPlan(tuple(1.0 / (p * lt) for p in periods), periods, lt, exposure_s)


def row_ratio(flicker: np.ndarray, steady: np.ndarray, black_dn: float, max_dn: float) -> tuple[np.ndarray, float]:
    """(per-row light of `flicker` / light of `steady` (NaN for unusable rows), fraction of the
    pixels saturated in either). Rows first; any further axes (columns, colours) are pooled;
    saturated pixels and those under 5 % of the steady frame's brightest are left out."""
    f = np.asarray(flicker, np.float64).reshape(len(flicker), -1)
    s = np.asarray(steady, np.float64).reshape(len(steady), -1)
    if f.shape != s.shape:
        raise RngcamError(f"the flicker frame {flicker.shape} and the steady frame {steady.shape} differ in shape")
    saturated = (f >= max_dn) | (s >= max_dn)
    level = np.percentile(s - black_dn, 99)
    lit = (s - black_dn) > 0.05 * level if level > 0 else np.zeros_like(saturated)
    use = lit & ~saturated
    num = np.where(use, f - black_dn, 0.0).sum(axis=1)
    den = np.where(use, s - black_dn, 0.0).sum(axis=1)
    enough = use.sum(axis=1) >= max(1, min(8, f.shape[1] // 4))
    ratio = np.full(len(f), np.nan)
    ratio[enough] = num[enough] / den[enough]
    return ratio, float(saturated.mean())


@dataclass(frozen=True)
class BandFit:
    """frequency: cycles per row; sigma its 1-sigma uncertainty; modulation: fundamental
    amplitude / mean; snr: fundamental amplitude / row noise."""

    frequency: float
    sigma: float
    modulation: float
    snr: float
    rows: int


def _design(r: np.ndarray, f: float, n: int) -> np.ndarray:
    x = (r - (n - 1) / 2) / max(n, 1)
    cols = [np.ones_like(x), x, x * x]
    for h in range(1, HARMONICS + 1):
        if h * f >= 0.5:
            break
        cols += [np.cos(2 * np.pi * h * f * r), np.sin(2 * np.pi * h * f * r)]
    return np.stack(cols, axis=1)


def _solve(r, y, f, n):
    a = _design(r, f, n)
    coef, *_ = np.linalg.lstsq(a, y, rcond=None)
    resid = y - a @ coef
    return float(resid @ resid), coef, a.shape[1]


def fit_bands(ratio: np.ndarray) -> BandFit:
    """The bands' frequency along the rows (module doc): periodogram peak, then least squares."""
    from scipy.optimize import minimize_scalar  # heavy: scipy

    y_all = np.asarray(ratio, np.float64)
    r = np.flatnonzero(np.isfinite(y_all)).astype(np.float64)
    n = len(y_all)
    if len(r) < max(16, 0.5 * n):
        raise RngcamError(f"only {len(r)} of {n} rows have usable light (the rest dark or saturated): aim the LED at "
                          "the diffuser, raise its level or lower the exposure")
    y = y_all[r.astype(int)]
    base = np.polyval(np.polyfit(r, y, 2), r)
    pad = 16 * n
    grid = np.zeros(pad)
    grid[r.astype(int)] = y - base
    power = np.abs(np.fft.rfft(grid)) ** 2
    freqs = np.fft.rfftfreq(pad)
    power[freqs < 1.5 / n] = 0
    f0 = float(freqs[int(np.argmax(power))])
    half = 1.0 / n
    res = minimize_scalar(lambda f: _solve(r, y, f, n)[0], bounds=(max(f0 - half, 0.5 / n), min(f0 + half, 0.499)),
                          method="bounded", options={"xatol": 1e-12})
    f = float(res.x)
    rss, coef, p = _solve(r, y, f, n)
    dof = max(len(r) - p - 1, 1)
    s2 = max(rss / dof, 1e-300)
    h = 1e-3 / n
    curv = (_solve(r, y, f + h, n)[0] - 2 * rss + _solve(r, y, f - h, n)[0]) / h**2
    sigma = float(np.sqrt(2 * s2 / curv)) if curv > 0 else float("inf")
    amp = float(np.hypot(coef[3], coef[4])) if p > 4 else 0.0
    mean = float(coef[0])
    return BandFit(f, sigma, amp / abs(mean) if mean else 0.0, amp / np.sqrt(s2), len(r))


@dataclass(frozen=True)
class FlickerResult:
    """The line time (s) and its 1-sigma uncertainty, and each frame's (frequency, fit)."""

    line_time_s: float
    uncertainty_s: float
    statistical_s: float
    disagreement_s: float
    per_frequency_s: tuple[float, ...]
    fits: tuple[tuple[float, BandFit], ...]
    saturated: float = 0.0  # fraction of the pixels saturated (left out of the rows' light)


def _weak(fit: BandFit, plan: FlickerPlan) -> str | None:
    if fit.modulation >= MIN_MODULATION and fit.snr >= MIN_SNR:
        return None
    period = 1 / max(plan.frequencies_hz)
    return (f"the LED bands are too weak (modulation {fit.modulation:.1%}, S/N {fit.snr:.0f}; need "
            f"{MIN_MODULATION:.0%} and {MIN_SNR:.0f}): raise the LED's brightness (generator high level, a smaller "
            f"series resistor, the LED nearer the diffuser), darken the room, or shorten the RS exposure "
            f"({plan.exposure_s * 1e6:.0f} us) below {EXPOSURE_PERIODS * period * 1e6:.0f} us")


def flicker_line_time(fits, plan: FlickerPlan, saturated: float = 0.0) -> FlickerResult:
    """Combine each frame's band fit ((LED frequency Hz, BandFit) pairs) into the line time, or
    refuse in one line: saturated, too weak, aliased / far from nominal, frequencies disagreeing."""
    if saturated > MAX_SATURATED:
        raise RngcamError(f"{saturated:.1%} of the pixels are saturated with the LED on (at most {MAX_SATURATED:.0%}): "
                          "lower the LED's level (generator high level, a larger series resistor), the RS "
                          "exposure or its gain")
    for _, fit in fits:
        why = _weak(fit, plan)
        if why:
            raise RngcamError(why)
    nominal = plan.nominal_line_time_s
    values = [(nu, fit.frequency / nu, fit.sigma / nu) for nu, fit in fits]
    for nu, lt, _ in values:
        if abs(lt / nominal - 1) > MAX_OFF_NOMINAL:
            raise RngcamError(f"the bands at {nu:.6g} Hz give a line time of {lt * 1e6:.4g} us, "
                              f"{lt / nominal - 1:+.0%} from the rig's nominal {nominal * 1e6:.4g} us: aliased bands "
                              "or a wrong nominal value; "
                              "set cameras.rs.line_time_s nearer the datasheet's row time, or use a larger "
                              "--rows-per-period")
    per = []
    for nu in dict.fromkeys(v[0] for v in values):
        group = [(lt, s) for f, lt, s in values if f == nu]
        w = np.array([1 / s**2 for _, s in group])
        per.append((float(np.sum(w * [lt for lt, _ in group]) / w.sum()), float(1 / np.sqrt(w.sum()))))
    w = np.array([1 / s**2 for _, s in per])
    mean = float(np.sum(w * [lt for lt, _ in per]) / w.sum())
    stat = float(1 / np.sqrt(w.sum()))
    spread = float(max(lt for lt, _ in per) - min(lt for lt, _ in per))
    if spread > max(MAX_DISAGREEMENT * mean, 6 * np.sqrt(sum(s**2 for _, s in per))):
        raise RngcamError(f"the two LED frequencies give line times {spread / mean:.2%} apart "
                          f"({', '.join(f'{lt * 1e6:.4f}' for lt, _ in per)} us): aliased bands or an LED that "
                          "does not follow the generator; check the wiring and use a larger --rows-per-period")
    return FlickerResult(mean, float(np.hypot(stat, spread / 2)), stat, spread, tuple(lt for lt, _ in per),
                         tuple(fits), saturated)
