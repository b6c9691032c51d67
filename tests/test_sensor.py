"""Sensor model: radiometry, noise statistics, saturation, Bayer mosaic, seeding."""

import numpy as np
import pytest

from rngcam.physics.sensor import (
    SensorModel,
    demosaic_bin,
    frame_to_measurement,
    mosaic_rggb,
    to_operator_units,
)

EXPOSURE_S = 650e-6
DT_S = 208e-6
SCALE = EXPOSURE_S / DT_S  # operator units of a static unit-intensity scene


def test_noiseless_round_trip_within_quantisation():
    sensor = SensorModel(bit_depth=12, black_level_dn=64, full_well_e=10_000)
    rng = np.random.default_rng(1)
    # Intensities that stay below saturation once the black level is added.
    y = rng.uniform(0.0, 0.95, size=(3, 16, 20)) * SCALE
    dn = sensor.capture(y, EXPOSURE_S, DT_S, noise=False)
    assert dn.shape == (16, 20, 3) and dn.dtype == np.uint16
    back = to_operator_units(dn, 64, 12, EXPOSURE_S, DT_S)
    assert back.dtype == np.float32
    half_dn = 0.5 / sensor.max_dn * SCALE
    np.testing.assert_allclose(np.moveaxis(back, -1, 0), y, atol=half_dn * 1.001, rtol=0)


def test_static_unit_scene_is_full_scale():
    sensor = SensorModel(black_level_dn=0)
    dn = sensor.capture(np.full((3, 4, 4), SCALE), EXPOSURE_S, DT_S, noise=False)
    assert np.all(dn == sensor.max_dn)
    dn_half = sensor.capture(np.full((3, 4, 4), 0.5 * SCALE), EXPOSURE_S, DT_S, noise=False)
    assert np.all(np.abs(dn_half.astype(float) - 0.5 * sensor.max_dn) <= 0.5)


def test_shot_noise_matches_poisson_on_flat_field():
    # Full well = max DN, so one electron is one DN and no read noise: DN - black ~ Poisson(mean).
    sensor = SensorModel(bit_depth=12, black_level_dn=100, full_well_e=4095, read_noise_e=0.0)
    mean_e = 400.0
    y = np.full((1, 200, 200), mean_e / 4095 * SCALE)
    dn = sensor.capture(y, EXPOSURE_S, DT_S, rng=np.random.default_rng(7)).astype(np.float64) - 100
    n = dn.size
    assert abs(dn.mean() - mean_e) < 5 * np.sqrt(mean_e / n)
    # The sample variance of n Poisson draws has sd ~ sqrt(2/n) * var (Gaussian approximation).
    assert abs(dn.var() - mean_e) < 5 * np.sqrt(2.0 / n) * mean_e


def test_read_noise_adds_variance():
    sensor = SensorModel(bit_depth=16, black_level_dn=1000, full_well_e=65535, read_noise_e=10.0)
    dn = sensor.capture(np.zeros((1, 200, 200)), EXPOSURE_S, DT_S, rng=3).astype(np.float64)
    assert abs(dn.mean() - 1000) < 0.5
    assert abs(dn.std() - 10.0) < 0.5


def test_saturation_and_extremes_are_clipped_and_finite():
    sensor = SensorModel(bit_depth=10, black_level_dn=32)
    y = np.stack([np.full((8, 8), -5.0), np.full((8, 8), 1e30), np.full((8, 8), 2.0 * SCALE)])
    for noise in (False, True):
        dn = sensor.capture(y, EXPOSURE_S, DT_S, rng=0, noise=noise)
        assert dn.max() <= 1023 and dn.min() >= 0
        assert np.all(dn[..., 1] == 1023) and np.all(dn[..., 2] == 1023)
    dark = sensor.capture(y, EXPOSURE_S, DT_S, noise=False)[..., 0]
    assert np.all(dark == 32)


@pytest.mark.parametrize("bad", [np.nan, np.inf, -np.inf])
def test_non_finite_input_raises(bad):
    y = np.zeros((3, 4, 4))
    y[1, 2, 3] = bad
    with pytest.raises(ValueError, match="NaN or Inf"):
        SensorModel().capture(y, EXPOSURE_S, DT_S)
    with pytest.raises(ValueError, match="NaN or Inf"):
        to_operator_units(y, 64, 12, EXPOSURE_S, DT_S)


def test_invalid_parameters_raise():
    with pytest.raises(ValueError):
        SensorModel(bit_depth=17)
    with pytest.raises(ValueError):
        SensorModel(full_well_e=0)
    with pytest.raises(ValueError):
        SensorModel(bit_depth=8, black_level_dn=300)
    with pytest.raises(ValueError):
        SensorModel().capture(np.zeros((4, 4)), EXPOSURE_S, DT_S)
    with pytest.raises(ValueError):
        SensorModel(channel_gain=(1.0, 1.0)).capture(np.zeros((3, 4, 4)), EXPOSURE_S, DT_S)
    with pytest.raises(ValueError):
        to_operator_units(np.zeros(3), 0, 12, 0.0, DT_S)


def test_channel_gain_scales_each_colour():
    sensor = SensorModel(black_level_dn=0, channel_gain=(1.0, 0.5, 0.25))
    dn = sensor.capture(np.full((3, 4, 4), 0.8 * SCALE), EXPOSURE_S, DT_S, noise=False).astype(float)
    np.testing.assert_allclose(dn[0, 0] / dn[0, 0, 0], [1.0, 0.5, 0.25], atol=1e-3)


def test_bayer_mosaic_layout_and_binning():
    img = np.stack([np.full((4, 6), 1.0), np.full((4, 6), 2.0), np.full((4, 6), 3.0)])
    raw = mosaic_rggb(img)
    np.testing.assert_array_equal(raw[:2, :2], [[1.0, 2.0], [2.0, 3.0]])
    rng = np.random.default_rng(0)
    colour = rng.uniform(size=(3, 5, 7))
    # A colour image repeated over 2x2 cells survives mosaic + bin exactly.
    up = np.repeat(np.repeat(colour, 2, axis=1), 2, axis=2)
    np.testing.assert_allclose(demosaic_bin(mosaic_rggb(up)), colour, rtol=1e-6)
    with pytest.raises(ValueError):
        demosaic_bin(np.zeros((5, 4)))
    with pytest.raises(ValueError):
        mosaic_rggb(np.zeros((2, 4, 4)))


def test_bayer_capture_matches_binned_measurement():
    sensor = SensorModel(bayer=True, black_level_dn=64)
    colour = np.random.default_rng(2).uniform(0, 0.9, size=(3, 6, 8)) * SCALE
    up = np.repeat(np.repeat(colour, 2, axis=1), 2, axis=2)
    raw = sensor.capture(up, EXPOSURE_S, DT_S, noise=False)
    assert raw.shape == (12, 16) and sensor.pixel_format == "BayerRG12"
    meas = frame_to_measurement(raw, "BayerRG12", 64, 12, EXPOSURE_S, DT_S)
    assert meas.shape == (3, 6, 8)
    np.testing.assert_allclose(meas, colour, atol=0.5 / 4095 * SCALE * 1.001)


def test_frame_to_measurement_colour_and_mono():
    frame = np.arange(24, dtype=np.uint16).reshape(2, 4, 3) + 64
    meas = frame_to_measurement(frame, "RGB12", 64, 12, EXPOSURE_S, DT_S)
    assert meas.shape == (3, 2, 4)
    np.testing.assert_allclose(meas[1, 0, 0], 1 / 4095 * SCALE, rtol=1e-6)
    assert frame_to_measurement(frame[..., 0], "Mono12", 64, 12, EXPOSURE_S, DT_S).shape == (1, 2, 4)


def test_seeds_are_reproducible():
    sensor = SensorModel()
    y = np.full((3, 16, 16), 0.3 * SCALE)
    a = sensor.capture(y, EXPOSURE_S, DT_S, rng=42)
    b = sensor.capture(y, EXPOSURE_S, DT_S, rng=np.random.default_rng(42))
    c = sensor.capture(y, EXPOSURE_S, DT_S, rng=43)
    np.testing.assert_array_equal(a, b)
    assert np.any(a != c)
