"""A bundle's frames, PSF and truth on the reconstruction grid (rngcam.recon.problem builds the
Problem from them): each frame in operator units with its invalid pixels, hot and dead pixels,
binning, the GS-to-RS warp.
"""

from __future__ import annotations

from dataclasses import replace

import cv2
import numpy as np
import torch
from torch import Tensor

from rngcam import pixels
from rngcam.errors import BundleError
from rngcam.formats.bundle import Bundle, CameraRecord
from rngcam.physics import psf as psf_mod
from rngcam.physics.sensor import BAYER_FORMATS, frame_to_measurement
from rngcam.physics.timing import VideoGrid

START_RESOLUTION_S = 1e-7  # a measured start this close to its plan is the plan (clock rounding)


def _usable_starts(cam: CameraRecord | None) -> np.ndarray | None:
    """The camera's measured exposure starts, each within START_RESOLUTION_S of its plan snapped
    to it (so rounding never adds a grid frame before T0), or None."""
    if cam is None or cam.exposure_start_s is None:
        return None
    starts = np.asarray(cam.exposure_start_s, np.float64)
    planned = np.asarray(cam.trigger_times_s, np.float64)
    if starts.shape != planned.shape or not np.all(np.isfinite(starts)):
        return None
    return np.where(np.abs(starts - planned) <= START_RESOLUTION_S, planned, starts)


def measured_timing(bundle: Bundle, notes: list[str]) -> Bundle:
    """`bundle` with the GS exposure windows (and the RS trigger offset) at the measured exposure
    starts where the bundle records them (exposure durations as planned), with a note; the
    bundle itself when it records none (an older bundle, a camera without timestamps)."""
    gs = _usable_starts(bundle.gs)
    if gs is None:
        return bundle
    rs = _usable_starts(bundle.rs)
    if np.array_equal(gs, np.asarray(bundle.gs.trigger_times_s, np.float64)) and (
            rs is None or rs[0] == float(np.asarray(bundle.rs.trigger_times_s)[0])):
        return bundle  # measured where planned
    rs_record = bundle.rs if rs is None else replace(bundle.rs, trigger_times_s=rs[:1].copy())
    shift = np.abs(gs - np.asarray(bundle.gs.trigger_times_s, np.float64))
    notes.append(f"GS exposures at their measured starts ({bundle.gs.exposure_start_method or 'method not recorded'}; "
                 f"up to {shift.max() * 1e6:.1f} us from the plan)")
    return replace(bundle, rs=rs_record, gs=replace(bundle.gs, trigger_times_s=gs))


def camera_frames(cam: CameraRecord, dt_s: float, keep=None) -> list[tuple[np.ndarray, np.ndarray]]:
    """Each raw frame (of `keep`, default all) -> ((C, h, w) float32 operator units, (C, h, w)
    bool invalid pixels: saturated or clipped at 0 DN), Bayer binned 2x2 (invalid if any site is)."""
    which = "RS" if cam.line_time_s is not None else "GS"
    indices = range(int(cam.frames.shape[0])) if keep is None else [int(i) for i in keep]
    out = []
    try:
        for i in indices:
            f = np.asarray(cam.frames[i])
            meas = frame_to_measurement(f, cam.pixel_format, cam.black_level_dn, cam.bit_depth,
                                        cam.exposure_s, dt_s)
            bad = pixels.invalid_pixels(f, cam.bit_depth, cam.black_level_dn).astype(np.float32)
            bad = frame_to_measurement(bad, cam.pixel_format, 0.0, 1, 1.0, 1.0) > 0
            out.append((meas, bad))
    except ValueError as exc:  # NaN/Inf or misshapen frames: a bad bundle, not a crash
        raise BundleError(f"the {which} frames are unusable: {exc}") from None
    return out


def bin_frames(img: np.ndarray, factor: int) -> np.ndarray:
    """Box-average (C, H, W) by `factor` (cropping a remainder at the bottom/right)."""
    if factor == 1:
        return img
    c, h, w = img.shape
    h2, w2 = h // factor, w // factor
    if h2 == 0 or w2 == 0:
        raise BundleError(f"cannot bin a {h}x{w} frame by {factor}")
    return img[:, :h2 * factor, :w2 * factor].reshape(c, h2, factor, w2, factor).mean(axis=(2, 4))


def binned_pixels(factor: int) -> np.ndarray:
    """Homography from raw pixel coordinates to coordinates after binning by `factor` (pixel centres)."""
    a = 1.0 / factor
    return np.array([[a, 0, 0.5 * a - 0.5], [0, a, 0.5 * a - 0.5], [0, 0, 1.0]])


def warp_to(img: np.ndarray, homography: np.ndarray | None, shape: tuple[int, int]) -> np.ndarray:
    """Resample a (C, h, w) GS frame onto the RS sensor grid of `shape` with a GS->RS homography."""
    same = img.shape[-2:] == tuple(shape)
    if homography is None or (same and np.allclose(homography, np.eye(3))):
        if not same:
            raise BundleError(f"GS frames are {img.shape[-2:]} but RS is {shape}, and the bundle "
                              "has no GS-to-RS alignment (run `rngcam calibrate align`)")
        return img
    out = [cv2.warpPerspective(ch, np.asarray(homography, np.float64), (shape[1], shape[0]),
                               flags=cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE) for ch in img]
    return np.stack(out)


def valid_or_none(invalid: np.ndarray) -> Tensor | None:
    """The valid-pixel mask (True = used) of `invalid`, or None when every pixel is valid."""
    return None if not invalid.any() else torch.from_numpy(np.ascontiguousarray(~invalid))


def masked_note(name: str, invalid: np.ndarray) -> str | None:
    """The note that says how much of camera `name` is left out, or None when nothing is."""
    if not invalid.any():
        return None
    return (f"{100 * invalid.mean():.2f} % of the {name} pixels left out of the data term "
            "(saturated or clipped at 0 DN: no linear information)")


def sensor_defects(name: str, frames: np.ndarray, factor: int, notes: list[str]) -> np.ndarray:
    """Hot and dead pixels of a camera's frames (C, F, h, w) at the sensor's resolution
    (rngcam.recon.defects). Binned (factor > 1), each is replaced by its neighbours' median in place
    and the returned mask is empty; unbinned, the mask (h, w) marks them invalid. A note either way."""
    from rngcam.recon.defects import fill, outliers  # heavy: defects loads scipy

    bad = outliers(frames)
    if not bad.any():
        return bad
    n = int(bad.sum())
    if factor > 1:
        fill(frames, bad)
        notes.append(f"{n} {name} sensor pixels read far from their neighbours in every frame (hot or dead): "
                     "replaced by their neighbours' median before binning")
        return np.zeros_like(bad)
    notes.append(f"{n} {name} pixels read far from their neighbours in every frame (hot or dead): "
                 "left out of the data term")
    return bad


def grid_psf(bundle: Bundle, grid_bin: int, channels: int) -> np.ndarray:
    """The bundle's PSF binned to the grid, (C, h, w) float64 (BundleError when missing or unusable)."""
    raw = bundle.calibration.psf
    if raw is None:
        raise BundleError("the bundle has no PSF (calibration/psf); run `rngcam calibrate psf`")
    try:
        psf = psf_mod.bin_psf(raw, grid_bin)
    except ValueError as exc:
        raise BundleError(f"the bundle's PSF is unusable: {exc}") from None
    return np.repeat(psf, channels, axis=0) if psf.shape[0] == 1 else psf


def grid_truth(bundle: Bundle, grid: VideoGrid, rs_shape, notes: list[str]) -> Tensor | None:
    """The bundle's truth video as float32 when it matches the grid; else None and a note."""
    if bundle.truth is None:
        return None
    expected = (rs_shape[0], grid.n_frames, rs_shape[1], rs_shape[2])
    shape = tuple(np.shape(bundle.truth.video))
    if shape != expected:
        notes.append(f"truth video {shape} does not match the grid {expected}: metrics against truth skipped")
        return None
    # float32 as the bundle stores it (a float64 copy would double it); metrics accumulate in float64
    video = np.asarray(bundle.truth.video, np.float32)
    if not np.isfinite(video).all():
        notes.append("the truth video has NaN or Inf values: metrics against truth skipped")
        return None
    return torch.from_numpy(video)


def gs_on_rs_grid(bundle: Bundle, kept: list[int], dt_s: float, rs_mosaic: int, factor: int,
                  sensor_shape: tuple[int, int], notes: list[str]) -> tuple[np.ndarray, np.ndarray]:
    """The GS frames `kept`, warped onto the RS sensor and binned by `factor`: (C, G, H, W) operator
    units and their invalid pixels (bool, same shape). Hot and dead pixels as `sensor_defects`."""
    h = None
    if bundle.calibration.gs_to_rs is not None:  # raw GS pixels -> raw RS pixels; re-express after Bayer binning
        gs_mosaic = 2 if bundle.gs.pixel_format in BAYER_FORMATS else 1
        h = np.asarray(bundle.calibration.gs_to_rs, np.float64)
        h = binned_pixels(rs_mosaic) @ h @ np.linalg.inv(binned_pixels(gs_mosaic))
    frames, bad = [], []
    raw = camera_frames(bundle.gs, dt_s, keep=kept)
    stack = np.stack([m for m, _ in raw], axis=1)  # (C, G, h, w): defects are the same in every frame
    gs_defects = sensor_defects("GS", stack, factor, notes)
    for j, (_, invalid) in enumerate(raw):
        invalid |= gs_defects
        frames.append(bin_frames(warp_to(stack[:, j], h, sensor_shape), factor))
        bad.append(bin_frames(warp_to(invalid.astype(np.float32), h, sensor_shape), factor) > 0)
    return np.stack(frames, axis=1), np.stack(bad, axis=1)
