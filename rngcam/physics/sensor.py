"""Sensor model: operator-unit measurements -> raw digital numbers (DN), and back.

Radiometric convention. The forward operators (rngcam.physics.operators) return measurements
in *operator units*: a static scene of linear intensity v gives exposure_s / dt_s * v (every
exposure weight vector sums to exposure_s / dt_s and the PSF sums to 1). A sensor first maps
operator units y to the normalised signal

    s = y * dt_s / exposure_s        (a static scene of intensity 1.0 gives s = 1 = full scale)

then, per pixel:

    electrons = s * full_well_e * channel_gain[c]       (expected photo-electrons)
    electrons ~ Poisson(electrons) + Normal(0, read_noise_e)   (only when noise=True)
    DN = electrons * (2^bit_depth - 1) / full_well_e + black_level_dn
    DN = clip(round(DN), 0, 2^bit_depth - 1)             (quantisation and saturation)

`to_operator_units` inverts the deterministic part, (DN - black) / (2^bits - 1) *
exposure_s / dt_s, and is what the reconstruction applies to both cameras' frames.

Optional Bayer RGGB mosaic: a (3, H, W) image becomes (H, W) with R at (0, 0), G at (0, 1)
and (1, 0), B at (1, 1) of every 2x2 cell; `demosaic_bin` bins each 2x2 cell back to
(3, H/2, W/2) (G is the mean of its two sites).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

# Signals are clipped here (in units of full scale) before the Poisson draw: far above
# saturation the output is clipped anyway, and numpy's Poisson sampler rejects huge rates.
_MAX_SIGNAL_FULL_SCALE = 4.0

BAYER_FORMATS = ("BayerRG8", "BayerRG10", "BayerRG12", "BayerRG16")


def _check_finite(name: str, arr: np.ndarray) -> None:
    if not np.all(np.isfinite(arr)):
        raise ValueError(f"{name} contains NaN or Inf")


def _check_positive(name: str, value: float) -> None:
    if not (isinstance(value, (int, float, np.floating, np.integer)) and math.isfinite(value)
            and value > 0):
        raise ValueError(f"{name} must be a finite positive number, got {value!r}")


def _check_bit_depth(bit_depth: int) -> None:
    if int(bit_depth) != bit_depth or not 1 <= bit_depth <= 16:
        raise ValueError(f"bit_depth must be an integer in 1..16, got {bit_depth!r}")


def mosaic_rggb(image: np.ndarray) -> np.ndarray:
    """(3, H, W) -> (H, W) Bayer RGGB: R at (0,0), G at (0,1) and (1,0), B at (1,1)."""
    image = np.asarray(image)
    if image.ndim != 3 or image.shape[0] != 3:
        raise ValueError(f"Bayer mosaic needs a (3, H, W) image, got shape {image.shape}")
    out = np.empty(image.shape[1:], dtype=image.dtype)
    out[0::2, 0::2] = image[0, 0::2, 0::2]
    out[0::2, 1::2] = image[1, 0::2, 1::2]
    out[1::2, 0::2] = image[1, 1::2, 0::2]
    out[1::2, 1::2] = image[2, 1::2, 1::2]
    return out


def demosaic_bin(raw: np.ndarray) -> np.ndarray:
    """(H, W) Bayer RGGB -> (3, H/2, W/2) float32 by 2x2 binning per colour (G averaged)."""
    raw = np.asarray(raw)
    if raw.ndim != 2 or raw.shape[0] % 2 or raw.shape[1] % 2:
        raise ValueError(f"Bayer binning needs an (H, W) frame with even sides, got shape {raw.shape}")
    raw = raw.astype(np.float32)
    r = raw[0::2, 0::2]
    g = 0.5 * (raw[0::2, 1::2] + raw[1::2, 0::2])
    b = raw[1::2, 1::2]
    return np.stack([r, g, b])


def to_operator_units(dn, black_level_dn: float, bit_depth: int, exposure_s: float,
                      dt_s: float) -> np.ndarray:
    """Raw DN -> operator units: (dn - black) / (2^bits - 1) * exposure_s / dt_s, float32."""
    _check_bit_depth(bit_depth)
    _check_positive("exposure_s", exposure_s)
    _check_positive("dt_s", dt_s)
    if not math.isfinite(black_level_dn):
        raise ValueError(f"black_level_dn must be finite, got {black_level_dn!r}")
    dn = np.asarray(dn, dtype=np.float64)
    _check_finite("DN frame", dn)
    scale = exposure_s / dt_s / (2 ** int(bit_depth) - 1)
    return ((dn - black_level_dn) * scale).astype(np.float32)


def frame_to_measurement(frame: np.ndarray, pixel_format: str, black_level_dn: float,
                         bit_depth: int, exposure_s: float, dt_s: float) -> np.ndarray:
    """One raw camera frame ((H, W, C) or Bayer (H, W)) -> (C, H', W') float32 operator units.

    Bayer formats are binned 2x2 per colour (so H' = H/2); mono (H, W) gives C = 1.
    """
    frame = np.asarray(frame)
    if pixel_format in BAYER_FORMATS:
        chw = demosaic_bin(frame)
    elif frame.ndim == 3:
        chw = np.moveaxis(frame, -1, 0)
    elif frame.ndim == 2:
        chw = frame[None]
    else:
        raise ValueError(f"a camera frame must be (H, W) or (H, W, C), got shape {frame.shape}")
    return to_operator_units(chw, black_level_dn, bit_depth, exposure_s, dt_s)


@dataclass(frozen=True)
class SensorModel:
    """A linear sensor with shot noise, read noise, black level, quantisation and saturation.

    `channel_gain` scales each colour's electrons (a per-channel sensitivity, e.g. the colour
    filter's quantum efficiency); None means 1 for every channel. With `bayer`, `capture`
    returns the RGGB mosaic of its (3, H, W) input instead of an (H, W, 3) colour frame.
    """

    bit_depth: int = 12
    black_level_dn: float = 64.0
    full_well_e: float = 10_000.0
    read_noise_e: float = 3.0
    channel_gain: tuple[float, ...] | None = None
    bayer: bool = False

    def __post_init__(self):
        _check_bit_depth(self.bit_depth)
        _check_positive("full_well_e", self.full_well_e)
        if not (math.isfinite(self.read_noise_e) and self.read_noise_e >= 0):
            raise ValueError(f"read_noise_e must be finite and >= 0, got {self.read_noise_e!r}")
        if not (math.isfinite(self.black_level_dn) and 0 <= self.black_level_dn < self.max_dn):
            raise ValueError(f"black_level_dn must be in [0, {self.max_dn}), got {self.black_level_dn!r}")
        if self.channel_gain is not None:
            gains = tuple(float(g) for g in self.channel_gain)
            if not all(math.isfinite(g) and g >= 0 for g in gains):
                raise ValueError(f"channel_gain must be finite and >= 0, got {self.channel_gain!r}")
            object.__setattr__(self, "channel_gain", gains)

    @property
    def max_dn(self) -> int:
        return 2 ** int(self.bit_depth) - 1

    @property
    def pixel_format(self) -> str:
        return f"BayerRG{self.bit_depth}" if self.bayer else f"RGB{self.bit_depth}"

    def expected_electrons(self, y: np.ndarray, exposure_s: float, dt_s: float) -> np.ndarray:
        """Mean photo-electrons (C, H, W) float64 for an operator-unit measurement y (C, H, W)."""
        _check_positive("exposure_s", exposure_s)
        _check_positive("dt_s", dt_s)
        y = np.asarray(y, dtype=np.float64)
        if y.ndim != 3:
            raise ValueError(f"a measurement must be (C, H, W), got shape {y.shape}")
        _check_finite("measurement", y)
        signal = np.clip(y * (dt_s / exposure_s), 0.0, _MAX_SIGNAL_FULL_SCALE)
        if self.channel_gain is not None:
            if len(self.channel_gain) != y.shape[0]:
                raise ValueError(f"channel_gain has {len(self.channel_gain)} entries for "
                                 f"{y.shape[0]} channels")
            signal = signal * np.asarray(self.channel_gain)[:, None, None]
        return signal * self.full_well_e

    def capture(self, y: np.ndarray, exposure_s: float, dt_s: float,
                rng: np.random.Generator | int | None = None, noise: bool = True) -> np.ndarray:
        """Operator units (C, H, W) -> raw frame uint16: (H, W, C), or (H, W) RGGB with `bayer`.

        `rng` is a numpy Generator or a seed; noise=False gives the noiseless quantised frame.
        """
        electrons = self.expected_electrons(y, exposure_s, dt_s)
        if self.bayer:
            electrons = mosaic_rggb(electrons)
        else:
            electrons = np.moveaxis(electrons, 0, -1)
        if noise:
            rng = rng if isinstance(rng, np.random.Generator) else np.random.default_rng(rng)
            electrons = rng.poisson(electrons).astype(np.float64)
            if self.read_noise_e > 0:
                electrons += rng.normal(0.0, self.read_noise_e, size=electrons.shape)
        dn = electrons * (self.max_dn / self.full_well_e) + self.black_level_dn
        return np.clip(np.rint(dn), 0, self.max_dn).astype(np.uint16)

    def to_operator_units(self, dn: np.ndarray, exposure_s: float, dt_s: float) -> np.ndarray:
        """This sensor's inverse of the deterministic mapping (see module function)."""
        return to_operator_units(dn, self.black_level_dn, self.bit_depth, exposure_s, dt_s)
