"""PSF loading, bias, area resampling, normalisation and the spectral-support figure."""

import cv2
import h5py
import numpy as np
import pytest
import tifffile

from rngcam.paths import MEASURED_PSF, package_data
from rngcam.physics import psf as P


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
    raw = P.load_psf(package_data(MEASURED_PSF))
    psf, bias = P.prepare_psf(raw, (64, 64))
    assert 20 < bias < 50  # PROVENANCE: background about 34
    assert np.isfinite(psf).all() and psf.min() >= 0
    assert 0.0 < P.spectral_support(psf) < 0.05


# ----------------------------------------------------------------------------- lenslet diffuser model


def test_lenslet_spots_are_where_the_seed_says():
    from scipy import ndimage

    sensor, fwhm = (128, 160), 3.0
    centres, energy = P.lenslet_spots(sensor, lenslets=20, spot_fwhm_px=fwhm, coverage=0.6, seed=4)
    assert centres.shape == (20, 2) and energy.sum() == pytest.approx(1.0) and energy.min() > 0
    # coverage: every spot in the central 60 % of each side, and together they span most of it
    lo, hi = np.array(sensor) * 0.2, np.array(sensor) * 0.8
    assert np.all(centres >= lo) and np.all(centres <= hi)
    assert np.all(np.ptp(centres, axis=0) > 0.7 * (hi - lo))
    img = P.render_spots(sensor, centres, energy, fwhm)
    assert img.sum() == pytest.approx(1.0, rel=1e-6)  # every spot's light lands on the sensor
    # count: one bright blob per lenslet, each centred where the seed put it
    labels, count = ndimage.label(img > 0.5 * img.max() * energy.min() / energy.max())
    assert count == 20
    found = np.array(ndimage.center_of_mass(img, labels, range(1, count + 1))) + 0.5  # pixel i spans [i, i+1)
    nearest = np.min(np.hypot(*(found[:, None] - centres[None]).transpose(2, 0, 1)), axis=1)
    assert nearest.max() < 0.2
    # size: the brightest spot's full width at half maximum is the one asked for
    for (cy, cx) in centres[:5]:
        y, x = int(cy), int(cx)
        row = img[y, x - 5:x + 6]  # spots are at least two widths (6 px) apart
        above = np.flatnonzero(row > row.max() / 2)
        assert above[-1] - above[0] + 1 == pytest.approx(fwhm, abs=1.01)
    # the same seed gives the same spots, another seed others
    again, _ = P.lenslet_spots(sensor, lenslets=20, spot_fwhm_px=fwhm, coverage=0.6, seed=4)
    other, _ = P.lenslet_spots(sensor, lenslets=20, spot_fwhm_px=fwhm, coverage=0.6, seed=5)
    np.testing.assert_array_equal(again, centres)
    assert not np.allclose(other, centres)


def test_lenslet_binning_conserves_energy_and_same_seed_same_psf():
    rng = np.random.default_rng(0)
    img = rng.random((2, 24, 36))
    binned = P.bin_sum(img, 4)
    assert binned.shape == (2, 6, 9) and binned.sum() == pytest.approx(img.sum())
    assert binned[1, 2, 3] == pytest.approx(img[1, 8:12, 12:16].sum())
    with pytest.raises(ValueError, match="does not bin"):
        P.bin_sum(img, 5)
    a = P.lenslet_psf((32, 32), binning=4, lenslets=12, seed=3)
    assert a.shape == (1, 32, 32) and a.sum() == pytest.approx(1.0) and a.min() >= 0
    np.testing.assert_array_equal(a, P.lenslet_psf((32, 32), binning=4, lenslets=12, seed=3))
    assert not np.allclose(a, P.lenslet_psf((32, 32), binning=4, lenslets=12, seed=9))
    with pytest.raises(ValueError, match="cannot place"):
        P.lenslet_spots((16, 16), lenslets=200, spot_fwhm_px=3.0)


def test_resolvable_fraction_follows_the_noise_floor():
    delta = np.zeros((1, 16, 16))
    delta[0, 5, 7] = 1
    flat = np.full((1, 16, 16), 1 / 256)
    # a delta passes every frequency unattenuated: all clear once contrast x SNR x sqrt(N) / 2 >= 1
    assert P.resolvable_fraction(delta, snr_px=1.0, contrast=0.5) == 1.0  # 0.5 x 1 x 16 / 2 = 4
    assert P.resolvable_fraction(delta, snr_px=0.2, contrast=0.5) == 0.0  # 0.8 < 1
    # a flat box passes only DC and the frequencies its zeros miss (none on a 16 grid but DC)
    assert P.resolvable_fraction(flat, snr_px=1e6) == pytest.approx(1 / (16 * 9))
    assert P.resolvable_fraction(delta, snr_px=float("nan")) == 0.0
    assert P.resolvable_fraction(np.zeros((1, 4, 4)), snr_px=10) == 0.0
    # more signal never clears fewer frequencies
    psf = P.lenslet_psf((32, 32), binning=2, lenslets=30, spot_fwhm_px=2.0, seed=1)
    figures = [P.resolvable_fraction(psf, snr) for snr in (1, 5, 25, 125)]
    assert figures == sorted(figures) and figures[0] < figures[-1]
    assert P.snr_of_mean_signal(100.0, 0.0) == pytest.approx(10.0)


def test_a_psf_file_keeping_its_data_in_another_file_is_refused(tmp_path):
    """A rig's .h5 PSF may come from elsewhere: external storage (the bytes of a file of the reader's)
    is refused in one line and nothing of that file comes back."""
    import h5py

    from rngcam.errors import RngcamError
    from rngcam.physics.psf import load_psf

    secret = tmp_path / "secret.bin"
    secret.write_bytes(np.arange(64 * 64, dtype=np.float64).tobytes())
    with h5py.File(tmp_path / "ext.h5", "w") as f:
        f.create_dataset("psf", shape=(64, 64), dtype="f8", external=[(str(secret), 0, 64 * 64 * 8)])
    with pytest.raises(RngcamError, match="external file"):
        load_psf(tmp_path / "ext.h5")
    with h5py.File(tmp_path / "ok.h5", "w") as f:
        f.create_dataset("calibration/psf", data=np.ones((3, 16, 16)))
    assert load_psf(tmp_path / "ok.h5").shape == (3, 16, 16)


@pytest.mark.parametrize("factor,shape", [(2, (16, 20)), (3, (9, 7)), (2, (15, 11)), (1, (8, 9))])
def test_binned_psf_is_exact_for_a_scene_constant_over_each_grid_pixel(factor, shape):
    # The scene blurred at the sensor's resolution by a PSF that fills the whole sensor (its outer
    # ring included) and binned like the frames equals the grid image blurred by the binned PSF.
    import torch

    from rngcam.physics.operators import PSFConvolution

    rng = np.random.default_rng(factor)
    h, w = shape
    raw = P.normalise(rng.uniform(0.1, 1.0, (1, h * factor, w * factor)))
    img = rng.uniform(0.0, 1.0, (2, h, w))
    sensor = np.repeat(np.repeat(img, factor, -2), factor, -1)
    seen = PSFConvolution(torch.from_numpy(raw), sensor.shape[-2:]).A(torch.from_numpy(sensor)).numpy()
    binned = seen.reshape(2, h, factor, w, factor).mean(axis=(2, 4))
    psf = P.bin_psf(raw, factor)
    assert psf.sum() == pytest.approx(1.0)
    if factor > 1 and h % 2 == 0:
        assert psf.shape[-2] == h + 1  # the outer ring of sensor pixels reaches one grid pixel further
    grid = PSFConvolution(torch.from_numpy(psf), shape).A(torch.from_numpy(img)).numpy()
    np.testing.assert_allclose(grid, binned, rtol=1e-10, atol=1e-12)


def test_binning_a_psf_by_a_non_integer_is_a_clear_error():
    with pytest.raises(ValueError, match="positive integer"):
        P.bin_psf(np.ones((1, 8, 8)), 1.5)


def test_a_psf_file_is_read_by_descriptor_a_link_or_fifo_at_its_name_is_refused(tmp_path):
    import os

    from rngcam.errors import RngcamError
    from rngcam.physics.psf import load_psf

    real = tmp_path / "psf.tif"
    tifffile.imwrite(real, np.arange(12, dtype=np.uint16).reshape(3, 4))
    np.testing.assert_array_equal(load_psf(real)[0], np.arange(12).reshape(3, 4))
    secret = tmp_path / "secret.tif"
    tifffile.imwrite(secret, np.ones((3, 4), np.uint16))
    link = tmp_path / "linked.tif"
    link.symlink_to(secret)
    with pytest.raises(RngcamError, match="link"):
        load_psf(link)
    fifo = tmp_path / "fifo.png"
    os.mkfifo(fifo)
    with pytest.raises((RngcamError, FileNotFoundError)):  # never opened, so never blocks
        load_psf(fifo)
