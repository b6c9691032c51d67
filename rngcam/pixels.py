"""Raw pixel values against a camera's declared format: full scale, saturation, clipping, dead frames.

A raw value at full scale (2^bits - 1) is saturated: the pixel received at least that much light
and says nothing more, so it carries no linear information. A value of 0 DN on a camera whose
black level is above 0 is clipped at the bottom of the range: noise alone never takes a pixel
that far below the black level, so it is dead or the frame is broken. Values above full scale
mean the declared bit depth is wrong (16-bit or MSB-aligned data declared as 12-bit, say): read
as declared, every intensity would be off by a constant factor, silently.

A whole frame is "beyond use" when almost none of its pixels are valid, when every pixel sits at
or below the black level (dark) while another frame of the capture sees light, or when every
pixel has the same value above the black level (a stuck or blank frame: real sensors are noisy).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

# A frame with fewer valid pixels than this fraction is left out of the reconstruction.
MIN_VALID_FRACTION = 0.05
# A constant frame is only called flat when it has at least this many pixels.
FLAT_MIN_PIXELS = 64


def full_scale(bit_depth: int) -> int:
    """The largest raw value of a `bit_depth`-bit pixel."""
    return 2 ** int(bit_depth) - 1


def invalid_pixels(frame: np.ndarray, bit_depth: int, black_level_dn: float) -> np.ndarray:
    """Bool array of frame's shape: True where the raw value is saturated or clipped at 0 DN."""
    frame = np.asarray(frame)
    bad = frame >= full_scale(bit_depth)
    if black_level_dn > 0:
        bad |= frame <= 0
    return bad


@dataclass
class FrameStats:
    """One raw frame's value statistics (fractions of its pixels)."""

    max_dn: float
    saturated: float  # at full scale or above
    dark: float  # at or below the black level
    clipped_low: float  # at 0 DN although the black level is above 0
    flat: bool  # every pixel the same value, above the black level
    finite: bool

    @property
    def valid(self) -> float:
        return max(0.0, 1.0 - self.saturated - self.clipped_low)

    @property
    def all_dark(self) -> bool:
        return self.dark >= 1.0


def frame_stats(frame: np.ndarray, bit_depth: int, black_level_dn: float) -> FrameStats:
    """Statistics of one raw frame (any shape)."""
    f = np.asarray(frame)
    n = max(1, f.size)
    finite = bool(np.all(np.isfinite(f))) if f.dtype.kind == "f" else True
    if not finite:
        f = np.where(np.isfinite(f), f, 0)
    top = full_scale(bit_depth)
    max_dn = float(f.max()) if f.size else 0.0
    clipped = float(np.count_nonzero(f <= 0)) / n if black_level_dn > 0 else 0.0
    flat = bool(f.size >= FLAT_MIN_PIXELS and max_dn == float(f.min()) and black_level_dn < max_dn < top)
    return FrameStats(max_dn=max_dn, saturated=float(np.count_nonzero(f >= top)) / n,
                      dark=float(np.count_nonzero(f <= black_level_dn)) / n, clipped_low=clipped,
                      flat=flat, finite=finite)


def camera_stats(frames, bit_depth: int, black_level_dn: float) -> list[FrameStats]:
    """FrameStats of every frame of a camera (frames: array or h5py dataset, read one at a time)."""
    return [frame_stats(frames[i], bit_depth, black_level_dn) for i in range(int(frames.shape[0]))]


def bit_depth_needed(max_dn: float) -> int:
    return max(1, math.ceil(math.log2(max_dn + 1)))


def value_problems(label: str, stats: list[FrameStats], bit_depth: int) -> list[str]:
    """Problems (errors) of a camera's values against its declared bit depth."""
    if not stats:
        return []
    top = full_scale(bit_depth)
    peak = max(s.max_dn for s in stats)
    if peak <= top:
        return []
    over = [i + 1 for i, s in enumerate(stats) if s.max_dn > top]
    which = "frame " + ", ".join(map(str, over[:5])) if len(stats) > 1 else "the frame"
    return [f"{label} pixel values reach {peak:,.0f} DN in {which}, above the {bit_depth}-bit full scale "
            f"of {top:,} DN: the declared bit depth is wrong (the values need {bit_depth_needed(peak)} "
            f"bits; MSB-aligned data?); set bit_depth to the camera's real format"]


def unusable_reason(stats: FrameStats, others_see_light: bool) -> str | None:
    """Why a frame carries nothing the reconstruction can use, or None when it does."""
    if stats.valid < MIN_VALID_FRACTION:
        if stats.saturated >= stats.clipped_low:
            return f"saturated: {100 * stats.saturated:.1f} % of its pixels at full scale"
        return f"dead: {100 * stats.clipped_low:.1f} % of its pixels at 0 DN, below the black level"
    if stats.flat:
        return f"flat: every pixel {stats.max_dn:g} DN (a stuck or blank frame)"
    if stats.all_dark and others_see_light:
        return "dark: every pixel at or below the black level while the other frames see light"
    return None


def camera_lines(label: str, stats: list[FrameStats]) -> list[str]:
    """One line per frame for a summary: saturated and dark fractions."""
    out = []
    for i, s in enumerate(stats):
        name = label if len(stats) == 1 else f"{label} frame {i + 1}"
        out.append(f"{name}: {100 * s.saturated:.2f} % saturated, {100 * s.dark:.2f} % at or below "
                   f"black, max {s.max_dn:,.0f} DN")
    return out


# --- a whole capture (a rngcam.formats.bundle.Bundle: .rs and .gs camera records)


def _readable_frames(rec) -> bool:
    if rec is None or not hasattr(rec.frames, "dtype"):
        return False
    shape = tuple(np.shape(rec.frames))
    return (len(shape) in (3, 4) and shape[0] >= 1 and np.dtype(rec.frames.dtype).kind in "uif"
            and isinstance(rec.bit_depth, (int, np.integer)) and 1 <= rec.bit_depth <= 32
            and np.ndim(rec.black_level_dn) == 0 and bool(np.isfinite(rec.black_level_dn)))


def pixel_stats(bundle) -> dict[str, list[FrameStats]]:
    """Per camera ("rs", "gs"), each frame's value statistics (frames are read one at a time)."""
    return {name: camera_stats(rec.frames, int(rec.bit_depth), float(rec.black_level_dn))
            for name in ("rs", "gs") if _readable_frames(rec := getattr(bundle, name))}


def unusable_frames(stats: dict[str, list[FrameStats]]) -> dict[tuple[str, int], str]:
    """(camera, frame index) -> why that frame carries nothing the reconstruction can use."""
    every = [(name, i, st) for name, frames in stats.items() for i, st in enumerate(frames)]
    lit_frames = sum(not st.all_dark for _, _, st in every)  # counted once: linear in the frames
    out = {}
    for name, i, st in every:
        lit = lit_frames - (not st.all_dark) > 0  # another frame than this one sees light
        why = unusable_reason(st, lit)
        if why is not None:
            out[(name, i)] = why
    return out


def frame_label(name: str, index: int, count: int) -> str:
    """'the RS image' or 'GS frame 2' (1-based)."""
    if name == "rs":
        return "the RS image" if count == 1 else f"RS frame {index + 1}"
    return f"GS frame {index + 1}"


def pixel_problems(bundle, stats: dict[str, list[FrameStats]],
                   warning_prefix: str = "warning: ") -> list[str]:
    """Values above full scale (errors) and frames beyond use (warnings: they are left out)."""
    problems: list[str] = []
    for name, frames in stats.items():
        rec = getattr(bundle, name)
        problems += value_problems(name.upper(), frames, int(rec.bit_depth))
    if not problems:  # above full scale, the fractions below mean nothing
        for (name, i), why in unusable_frames(stats).items():
            problems.append(f"{warning_prefix}{frame_label(name, i, len(stats[name]))} is left out of "
                            f"the reconstruction ({why})")
    return problems
