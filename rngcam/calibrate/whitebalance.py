"""Per-channel GS/RS gains (white balance) from a static pair and a known GS-to-RS transform.

white_balance[c] is the factor that puts GS measurements (operator units) on the RS scale,
the reconstruction's starting Lambda: fitted by least squares so that
white_balance[c] * (e_RS / e_GS) * (PSF conv GS warped onto the RS grid) matches the RS image
(rngcam.calibrate.align.ForwardFit). `rngcam calibrate align` estimates it jointly with the
transform; this re-estimates it alone, e.g. after a lighting or gain change.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from rngcam.calibrate.align import AlignmentError, ForwardFit, WorkingPair


@dataclass(frozen=True)
class WhiteBalance:
    gains: np.ndarray  # (C,)
    misfit: float  # RMS residual of the fit relative to the RS image's RMS


def estimate_white_balance(pair: WorkingPair, gs_to_rs: np.ndarray, exposure_ratio: float) -> WhiteBalance:
    """Gains for a working pair and a raw GS->RS transform; AlignmentError when not positive."""
    fit = ForwardFit(pair.rs, pair.gs, pair.psf, exposure_ratio)
    h = pair.to_work(gs_to_rs)
    gains = fit.gains(fit.predict(h))
    if not np.all(np.isfinite(gains)) or np.any(gains <= 0):
        raise AlignmentError(f"white balance is not positive ({np.round(gains, 4).tolist()}); is the "
                             "GS-to-RS transform right and the target inside both fields of view?")
    return WhiteBalance(gains=gains, misfit=fit.misfit(h))
