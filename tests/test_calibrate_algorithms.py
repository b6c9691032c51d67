"""Calibration algorithms on synthetic data with known answers, and the real DiffuserCam pair.

Scenes are small (64 px) so the whole file runs in seconds; the synthetic pair is rendered
the way the mock cameras render it (chart target, SensorModel noise), with a GS camera that
sees the chart through a known similarity and with known per-channel gains.
"""

from __future__ import annotations

import math

import h5py
import numpy as np
import pytest
import torch

from rngcam.calibrate.align import (
    AlignmentError,
    align_images,
    align_pair,
    bin_matrix,
    working_pair,
)
from rngcam.calibrate.deconv import deconvolve, wiener
from rngcam.calibrate.linetime import default_heights, fit_line_time, readout_samples
from rngcam.calibrate.psf import PsfCalibrationError, correlation, estimate_psf
from rngcam.calibrate.whitebalance import estimate_white_balance
from rngcam.errors import HardwareError, RngcamError
from rngcam.formats import calibration as store
from rngcam.paths import HAND_BIAS_DN, HAND_MEASUREMENT, MEASURED_PSF, MEASURED_PSF_BIAS_DN, package_data
from rngcam.physics.geometry import similarity_matrix, similarity_of, transform_error_px
from rngcam.physics.operators import PSFConvolution
from rngcam.physics.psf import load_psf, prepare_psf
from rngcam.physics.sensor import SensorModel, frame_to_measurement
from rngcam.sim.targets import chart_image

N = 64
CENTRE = ((N - 1) / 2, (N - 1) / 2)
PSF_FILE = package_data(MEASURED_PSF)
RAW_FILE = package_data(HAND_MEASUREMENT)  # 4x binned


@pytest.fixture(scope="module")
def psf() -> np.ndarray:
    p, _ = prepare_psf(load_psf(PSF_FILE), (N, N), crop=0.25)  # the mock rig's PSF, zoomed in
    return np.repeat(p, 3, axis=0)


def _measure(y: np.ndarray, rng, frames: int = 8, gains=None) -> np.ndarray:
    """Mean of noisy 12-bit frames of operator-unit image y (exposure = dt), back in those units."""
    sensor = SensorModel(channel_gain=None if gains is None else tuple(gains))
    raw = [sensor.capture(y, 1.0, 1.0, rng) for _ in range(frames)]
    return np.mean([frame_to_measurement(f, "RGB12", 64, 12, 1.0, 1.0) for f in raw], axis=0)


def _static_pair(psf, h_true, gains, seed=0, frames=8):
    rng = np.random.default_rng(seed)
    scene = 0.7 * chart_image(N, seed=seed)
    rs = PSFConvolution(torch.from_numpy(psf), (N, N)).A(torch.from_numpy(scene)).numpy()
    return _measure(rs, rng, frames), _measure(0.7 * chart_image(N, h_true, seed=seed), rng, frames, gains)


# --------------------------------------------------------------------------- geometry


def test_similarity_matrix_and_its_decomposition_round_trip():
    h = similarity_matrix((1.5, -2.25), 2.0, 1.04, CENTRE)
    s = similarity_of(h, (N, N))
    assert s.shift_px == pytest.approx((1.5, -2.25), abs=1e-9)
    assert s.rotation_deg == pytest.approx(2.0, abs=1e-9) and s.scale == pytest.approx(1.04, abs=1e-12)
    # the centre moves by exactly the shift
    centre = np.array([*CENTRE, 1.0])
    assert (h @ centre)[:2] == pytest.approx(np.array(CENTRE) + (1.5, -2.25))


def test_bin_matrix_maps_pixel_centres():
    # raw pixels 0 and 1 bin into pixel 0 whose centre sits at raw 0.5
    assert (bin_matrix(2) @ [0.5, 0.5, 1])[:2] == pytest.approx([0.0, 0.0])
    assert (bin_matrix(4) @ [5.5, 9.5, 1])[:2] == pytest.approx([1.0, 2.0])


# --------------------------------------------------------------------------- deconvolution


def test_deconvolution_objective_never_increases_and_beats_wiener(psf):
    scene = 0.7 * chart_image(N)
    b = PSFConvolution(torch.from_numpy(psf), (N, N)).A(torch.from_numpy(scene)).numpy()
    b = b + np.random.default_rng(1).normal(0, 2e-3, b.shape)
    res = deconvolve(b, psf, tau_rel=1e-3, iters=60)
    obj = np.array(res.objective)
    assert len(obj) == 61 and np.all(np.isfinite(obj)) and np.all(np.isfinite(res.image))
    assert np.all(np.diff(obj) <= 1e-12 * obj[0]) and obj[-1] < 0.5 * obj[0]
    assert res.image.min() >= 0
    assert correlation(res.image, scene) > max(0.95, correlation(wiener(b, psf), scene))


def test_deconvolution_rejects_bad_input(psf):
    b = np.zeros((3, N, N))
    b[0, 0, 0] = np.nan
    with pytest.raises(RngcamError, match="NaN"):
        deconvolve(b, psf, iters=2)
    with pytest.raises(RngcamError, match="2-channel PSF"):
        deconvolve(np.ones((3, N, N)), psf[:2], iters=2)


def test_real_diffusercam_measurement_deconvolves_with_decreasing_objective():
    shape = (1200 // 8, 1600 // 8)  # 8x downsampled, as the DiffuserCam tutorial does
    psf, _ = prepare_psf(load_psf(PSF_FILE), shape, bias=MEASURED_PSF_BIAS_DN)
    b, _ = prepare_psf(load_psf(RAW_FILE), shape, bias=HAND_BIAS_DN)
    res = deconvolve(b, psf, tau_rel=1e-3, iters=12)
    obj = np.array(res.objective)
    assert res.image.shape == (1, *shape) and np.all(np.isfinite(res.image)) and res.image.max() > 0
    assert np.all(np.diff(obj) <= 0) and obj[-1] < 0.5 * obj[0]


# --------------------------------------------------------------------------- alignment and gains


@pytest.mark.parametrize("shift, rotation, scale, seed", [((1.7, -2.3), 1.5, 1.03, 0),
                                                           ((-3.0, 2.5), -3.0, 0.97, 1)])
def test_alignment_recovers_a_known_similarity_and_gains(psf, shift, rotation, scale, seed):
    h_true = similarity_matrix(shift, rotation, scale, CENTRE)
    gains = np.array([1.15, 0.95, 0.85])
    rs, gs = _static_pair(psf, h_true, gains, seed)
    a = align_images(rs, gs, psf, 1.0, init=np.eye(3))
    s = similarity_of(a.gs_to_rs, (N, N))
    assert transform_error_px(a.gs_to_rs, h_true, (N, N)) < 0.5
    assert abs(s.rotation_deg - rotation) < 0.5 and s.scale == pytest.approx(scale, abs=0.005)
    assert a.white_balance * gains == pytest.approx(np.ones(3), rel=0.02)  # Lambda = RS / GS response
    assert a.residual_tiles > 4 and 0 < a.residual_px < 1.0 and 0 < a.uncertainty_px < 0.1
    wb = estimate_white_balance(working_pair(rs, gs, psf), a.gs_to_rs, 1.0)
    assert wb.gains == pytest.approx(a.white_balance, rel=1e-3)


def test_refinement_beats_ecc_alone(psf):
    h_true = similarity_matrix((1.7, -2.3), 1.5, 1.03, CENTRE)
    rs, gs = _static_pair(psf, h_true, np.ones(3))
    ecc_only = align_images(rs, gs, psf, 1.0, init=np.eye(3), refine=False)
    refined = align_images(rs, gs, psf, 1.0, init=np.eye(3))
    assert math.isnan(ecc_only.uncertainty_px)
    assert (transform_error_px(refined.gs_to_rs, h_true, (N, N))
            < transform_error_px(ecc_only.gs_to_rs, h_true, (N, N)))


def test_homography_model_and_binned_working_grid_give_raw_pixel_transforms(psf):
    """A 128-px Bayer-like setup: frames binned by 2 for the working grid; the transform comes
    back in raw pixels."""
    n = 2 * N
    h_true = similarity_matrix((3.0, -2.0), 1.0, 1.02, ((n - 1) / 2, (n - 1) / 2))
    big_psf = np.repeat(np.repeat(psf, 2, axis=1), 2, axis=2) / 4
    rng = np.random.default_rng(5)
    scene = 0.7 * chart_image(n)
    rs = _measure(PSFConvolution(torch.from_numpy(big_psf), (n, n)).A(torch.from_numpy(scene)).numpy(), rng)
    gs = _measure(0.7 * chart_image(n, h_true), rng)
    pair = working_pair(rs, gs, big_psf, max_side=N)
    assert pair.grid["rs_bin"] == 2 and pair.rs.shape == (3, N, N)
    a = align_pair(pair, 1.0, init=np.eye(3), model="homography")
    assert transform_error_px(a.gs_to_rs, h_true, (n, n)) < 1.0  # 0.5 working pixels


def test_alignment_refuses_a_flat_image(psf):
    with pytest.raises(AlignmentError, match="flat"):
        align_images(np.ones((3, N, N)), np.ones((3, N, N)), psf, 1.0)
    with pytest.raises(AlignmentError, match="unknown transform model"):
        align_images(np.ones((3, N, N)), np.ones((3, N, N)), psf, 1.0, model="affine3d")


# --------------------------------------------------------------------------- PSF


def test_psf_estimate_from_noisy_point_source_frames(psf):
    y = psf * (0.6 / psf.max())  # a point source on the sensor axis: its RS image is the PSF
    rng = np.random.default_rng(2)
    sensor = SensorModel()
    frames = [sensor.capture(y, 1.0, 1.0, rng) for _ in range(16)]
    dark = [sensor.capture(np.zeros_like(y), 1.0, 1.0, rng) for _ in range(4)]
    for dark_frames in (None, dark):
        est = estimate_psf(frames, "RGB12", 12, 64.0, dark_frames=dark_frames)
        assert est.psf.sum(axis=(1, 2)) == pytest.approx(np.ones(3))
        assert correlation(est.psf, psf) > 0.99 and est.peak_snr > 50 and not est.warnings
        assert est.peak_fraction == pytest.approx(0.6, abs=0.05)
    assert "dark frame (mean of 4)" == est.dark


def test_psf_estimate_refuses_saturated_dark_or_noisy_frames(psf):
    rng = np.random.default_rng(3)
    sensor = SensorModel()
    hot = [sensor.capture(psf * (3.0 / psf.max()), 1.0, 1.0, rng)]
    with pytest.raises(PsfCalibrationError, match="saturated"):
        estimate_psf(hot, "RGB12", 12, 64.0)
    assert estimate_psf(hot, "RGB12", 12, 64.0, max_saturated=10**6).saturated_pixels > 0
    with pytest.raises(PsfCalibrationError, match="signal"):  # pure noise: no signal, or too little
        estimate_psf([sensor.capture(np.zeros_like(psf), 1.0, 1.0, rng) for _ in range(2)], "RGB12", 12, 64.0)
    faint = [SensorModel(read_noise_e=200).capture(psf * (0.002 / psf.max()), 1.0, 1.0, rng) for _ in range(2)]
    with pytest.raises(PsfCalibrationError, match="signal-to-noise"):
        estimate_psf(faint, "RGB12", 12, 64.0)


def test_bayer_psf_is_binned_per_colour(psf):
    sensor = SensorModel(bayer=True)
    big = np.repeat(np.repeat(psf, 2, axis=1), 2, axis=2)
    frames = [sensor.capture(big * (0.5 / big.max()), 1.0, 1.0, np.random.default_rng(i)) for i in range(8)]
    est = estimate_psf(frames, "BayerRG12", 12, 64.0)
    assert est.psf.shape == (3, N, N) and est.mosaic == 2 and correlation(est.psf, psf) > 0.99


# --------------------------------------------------------------------------- line time


def test_line_time_is_the_slope_of_readout_time_against_height():
    rng = np.random.default_rng(0)
    heights = [3648, 2736, 1824, 912]
    readout = [20e-6 + h * 13.04e-6 + rng.normal(0, 5e-9) for h in heights]
    fit = fit_line_time(heights, readout)
    assert fit.line_time_s == pytest.approx(13.04e-6, rel=1e-4)
    assert fit.overhead_s == pytest.approx(20e-6, abs=1e-7) and fit.residual_s < 1e-8
    with pytest.raises(RngcamError, match="two or more"):
        fit_line_time([100, 100], [1e-3, 1e-3])
    with pytest.raises(RngcamError, match="does not grow"):
        fit_line_time([100, 50], [1e-3, 2e-3])


class _Features:
    """A camera feature map with a Height that clamps to even values."""

    def __init__(self, writable=True):
        self.height, self._writable = 100, writable

    def readable(self, name):
        return name in ("Height", "SensorReadoutTime")

    def writable(self, name):
        return self._writable and name == "Height"

    def get(self, name):
        return self.height if name == "Height" else 7.0 + 2.5 * self.height

    def set(self, name, value):
        self.height = int(value) // 2 * 2


def test_readout_samples_read_back_heights_and_restore_the_roi():
    fm = _Features()
    samples = readout_samples(fm, [100, 51, 26])
    assert samples == [(100, pytest.approx(257e-6)), (50, pytest.approx(132e-6)), (26, pytest.approx(72e-6))]
    assert fm.height == 100
    assert fit_line_time(*zip(*samples)).line_time_s == pytest.approx(2.5e-6)
    with pytest.raises(HardwareError, match="SensorReadoutTime"):
        readout_samples(_Features(writable=False), [100, 50])
    assert default_heights(3648) == [3648, 2736, 1824, 912]
    assert default_heights(64) == [64, 48, 32, 16]


# --------------------------------------------------------------------------- calibration file


def test_calibration_file_parts_update_independently_and_validate(tmp_path):
    path = tmp_path / "lab.calib.h5"
    store.update_calibration(path, rig_name="lab", line_time_s=(13e-6, {"method": "slope", "heights": [4, 2]}))
    cal = store.update_calibration(path, gs_to_rs=(np.diag([2.0, 2.0, 1.0]), {"residual_px": 0.1}),
                                   white_balance=([1.1, 1.0, 0.9], {}))
    assert cal.parts() == ["line_time_s", "gs_to_rs", "white_balance"] and cal.rig_name == "lab"
    assert cal.line_time_s == 13e-6 and cal.provenance["line_time_s"]["heights"] == [4, 2]
    assert cal.provenance["gs_to_rs"]["residual_px"] == 0.1 and "created_utc" in cal.provenance["gs_to_rs"]
    psf = np.random.default_rng(0).random((3, 8, 8))
    store.update_calibration(path, psf=(psf / psf.sum(axis=(1, 2), keepdims=True), {}))
    assert load_psf(path).shape == (3, 8, 8)  # rigs can point calibration.psf.path at the file
    assert not list(tmp_path.glob(".*tmp"))
    with pytest.raises(store.CalibrationFileError, match="white_balance must be"):
        store.update_calibration(path, white_balance=([1.0, -1.0, 1.0], {}))
    assert store.read_calibration(path).white_balance == pytest.approx([1.1, 1.0, 0.9])  # unchanged
    other = tmp_path / "other.h5"
    with h5py.File(other, "w") as f:
        f["x"] = 1
    with pytest.raises(store.CalibrationFileError, match="not an rngcam calibration file"):
        store.read_calibration(other)
    with pytest.raises(store.CalibrationFileError, match="not found"):
        store.read_calibration(tmp_path / "missing.h5")
