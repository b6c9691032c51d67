"""PSF loading, bias, area resampling, normalisation and the spectral-support figure."""

from pathlib import Path

import cv2
import h5py
import numpy as np
import pytest
import tifffile

from rngcam.physics import psf as P

SHARED_PSF = Path(__file__).resolve().parents[1] / ".." / "shared" / "data" / "psf"


def _caustic(h=40, w=50, seed=0):
    rng = np.random.default_rng(seed)
    img = np.full((h, w), 20.0)
    for _ in range(30):
        img[rng.integers(5, h - 5), rng.integers(5, w - 5)] += rng.uniform(100, 1000)
    return img


@pytest.mark.parametrize("suffix", [".tif", ".png", ".npy", ".h5"])
def test_load_formats_round_trip(tmp_path, suffix):
    img = _caustic().astype(np.uint16)
    path = tmp_path / f"psf{suffix}"
    if suffix == ".tif":
        tifffile.imwrite(path, img)
    elif suffix == ".png":
        cv2.imwrite(str(path), img)
    elif suffix == ".npy":
        np.save(path, img)
    else:
        with h5py.File(path, "w") as f:
            f["psf"] = img
    loaded = P.load_psf(path)
    assert loaded.shape == (1, *img.shape) and loaded.dtype == np.float64
    np.testing.assert_array_equal(loaded[0], img)


def test_colour_png_is_rgb_channel_first(tmp_path):
    rgb = np.zeros((6, 8, 3), np.uint8)
    rgb[..., 0] = 200  # red
    cv2.imwrite(str(tmp_path / "c.png"), cv2.cvtColor(rgb, cv2.COLOR_RGB2BGR))
    loaded = P.load_psf(tmp_path / "c.png")
    assert loaded.shape == (3, 6, 8) and loaded[0].min() == 200 and loaded[2].max() == 0


def test_missing_and_unsupported_files(tmp_path):
    with pytest.raises(FileNotFoundError):
        P.load_psf(tmp_path / "nope.tif")
    (tmp_path / "x.bmp").write_bytes(b"0")
    with pytest.raises(ValueError, match="unsupported"):
        P.load_psf(tmp_path / "x.bmp")


def test_bias_auto_uses_dark_corners():
    img = _caustic()[None]
    out, bias = P.subtract_bias(img, "auto")
    assert bias == pytest.approx(20.0)
    assert out.min() == 0.0


def test_area_resample_is_box_mean_for_integer_factor():
    img = np.random.default_rng(1).random((1, 12, 18))
    out = P.resample(img, (4, 6))
    np.testing.assert_allclose(out[0], img[0].reshape(4, 3, 6, 3).mean(axis=(1, 3)))


def test_prepare_normalises_each_channel_to_one():
    img = np.stack([_caustic(seed=s) for s in range(3)])
    out, _ = P.prepare_psf(img, (16, 20), crop=0.8)
    assert out.shape == (3, 16, 20)
    np.testing.assert_allclose(out.sum(axis=(1, 2)), 1.0)
    mono, _ = P.prepare_psf(_caustic(), (8, 8), channels=3)
    assert mono.shape == (3, 8, 8)


def test_psf_without_signal_is_a_clear_error():
    with pytest.raises(ValueError, match="no positive signal"):
        P.prepare_psf(np.full((1, 10, 10), 5.0), (4, 4), bias=5.0)


def test_spectral_support_extremes():
    delta = np.zeros((1, 16, 16))
    delta[0, 3, 4] = 1
    assert P.spectral_support(delta) == 1.0
    assert P.spectral_support(np.ones((1, 16, 16))) == pytest.approx(1 / (16 * 9))
    assert P.spectral_support(np.zeros((1, 4, 4))) == 0.0


def test_real_psf_prepares_with_reported_support():
    path = SHARED_PSF / "diffusercam_tutorial_psf_sample.tif"
    if not path.is_file():
        pytest.skip(f"shared PSF data not present at {path}")
    raw = P.load_psf(path)
    psf, bias = P.prepare_psf(raw, (64, 64))
    assert 20 < bias < 50  # PROVENANCE: background about 34
    assert np.isfinite(psf).all() and psf.min() >= 0
    assert 0.0 < P.spectral_support(psf) < 0.05
