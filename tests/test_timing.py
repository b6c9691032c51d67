"""Shutter weights: exact overlaps, the paper's 0/1 indicator when aligned, trapezoids when binned."""

import numpy as np
import pytest
from hypothesis import example, given, settings
from hypothesis import strategies as st

from rngcam.physics.timing import (
    GlobalShutterTiming,
    RollingShutterTiming,
    VideoGrid,
    interval_weights,
)

REF_LINE_S = 13e-6


def test_aligned_rs_equals_rect_indicator():
    dt = REF_LINE_S * 16
    rs = RollingShutterTiming(line_time_s=dt, exposure_s=4 * dt, rows=228)
    grid = VideoGrid.covering(rs)
    assert grid.n_frames == 231  # the reference prototype's frame count
    w = rs.weights(grid)
    expected = np.zeros((228, 231))
    for i in range(228):
        expected[i, i:i + 4] = 1.0
    assert np.array_equal(w, expected)


def test_reference_rig_binned_weights_are_trapezoids():
    rs = RollingShutterTiming(line_time_s=REF_LINE_S, exposure_s=650e-6, rows=228, rows_per_bin=16)
    grid = VideoGrid.covering(rs)
    w = rs.weights(grid)
    assert grid.dt_s == pytest.approx(208e-6)
    np.testing.assert_allclose(w.sum(axis=1), 650 / 208, rtol=1e-12)
    # Every row bin has the same shape shifted by one frame.
    np.testing.assert_allclose(w[10, 10:16], w[11, 11:17], atol=1e-12)
    # Trapezoid: rises over the first frame, flat at 1 in the middle, falls at the end.
    row = w[0]
    assert 0 < row[0] < 1 and row[1] == pytest.approx(1.0) and row[2] == pytest.approx(1.0)
    assert 0 < row[3] < 1 and row[4] > 0 and np.all(row[6:] == 0)


def _brute_force_weights(starts, ends, dt, n_frames, samples=20000):
    out = np.zeros((len(starts), n_frames))
    for i, (a, b) in enumerate(zip(starts, ends)):
        t = a + (np.arange(samples) + 0.5) * (b - a) / samples
        k = np.floor(t / dt).astype(int)
        np.add.at(out[i], k[k < n_frames], (b - a) / samples / dt)
    return out


@settings(max_examples=40, deadline=None)
@given(
    line_us=st.floats(1.0, 50.0),
    exposure_lines=st.floats(0.05, 40.0),
    rows=st.integers(1, 12),
    rows_per_bin=st.integers(1, 5),
    trigger_lines=st.floats(0.0, 7.0),
    dt_factor=st.sampled_from([None, 0.37, 1.0, 2.5]),
)
def test_rs_weights_exact_for_random_timings(line_us, exposure_lines, rows, rows_per_bin,
                                             trigger_lines, dt_factor):
    line = line_us * 1e-6
    rs = RollingShutterTiming(line_time_s=line, exposure_s=exposure_lines * line, rows=rows,
                              rows_per_bin=rows_per_bin, trigger_s=trigger_lines * line)
    dt = None if dt_factor is None else dt_factor * rs.grid_dt_s
    grid = VideoGrid.covering(rs, dt_s=dt)
    w = rs.weights(grid)
    assert w.shape == (rows, grid.n_frames)
    np.testing.assert_allclose(w.sum(axis=1), rs.exposure_s / grid.dt_s, rtol=1e-9)
    assert np.all(w >= 0) and np.all(w <= 1 + 1e-12)
    # The grid covers the last exposure, and not by a whole spare frame.
    assert grid.n_frames * grid.dt_s >= rs.end_s * (1 - 1e-9)
    assert (grid.n_frames - 1) * grid.dt_s < rs.end_s
    # Equal to brute-force integration of the exposure indicators, averaged over the bin.
    starts, ends = rs.sensor_row_windows()
    brute = _brute_force_weights(starts.ravel(), ends.ravel(), grid.dt_s, grid.n_frames)
    brute = brute.reshape(rows, rows_per_bin, -1).mean(axis=1)
    np.testing.assert_allclose(w, brute, atol=2e-3 * max(1.0, exposure_lines))


@settings(max_examples=30, deadline=None)
@given(triggers=st.lists(st.floats(0.0, 5e-3), min_size=1, max_size=5),
       exposure=st.floats(1e-6, 2e-3), dt=st.floats(5e-6, 5e-4))
# A short exposure starting a rounding error after an edge: only its start is snapped.
@example(triggers=[4e-15], exposure=1e-6, dt=5e-4)
def test_gs_weights_sum_to_exposure(triggers, exposure, dt):
    gs = GlobalShutterTiming(trigger_s=tuple(triggers), exposure_s=exposure)
    grid = VideoGrid.covering(None, gs, dt_s=dt)
    w = gs.weights(grid)
    assert w.shape == (len(triggers), grid.n_frames)
    np.testing.assert_allclose(w.sum(axis=1), exposure / dt, rtol=1e-9)


def test_gs_aligned_frame_is_indicator():
    dt = 1e-4
    gs = GlobalShutterTiming(trigger_s=(0.0, 5 * dt), exposure_s=3 * dt)
    grid = VideoGrid(dt_s=dt, n_frames=10)
    w = gs.weights(grid)
    assert np.array_equal(w[0], [1, 1, 1, 0, 0, 0, 0, 0, 0, 0])
    assert np.array_equal(w[1], [0, 0, 0, 0, 0, 1, 1, 1, 0, 0])


def test_exposure_shorter_than_a_line_and_longer_than_readout():
    short = RollingShutterTiming(line_time_s=10e-6, exposure_s=1e-6, rows=8)
    g = VideoGrid.covering(short)
    np.testing.assert_allclose(short.weights(g).sum(1), 0.1, rtol=1e-12)
    long = RollingShutterTiming(line_time_s=10e-6, exposure_s=1e-3, rows=8)
    g = VideoGrid.covering(long)
    assert g.n_frames == 107
    np.testing.assert_allclose(long.weights(g).sum(1), 100.0, rtol=1e-12)


def test_interval_weights_partial_overlaps():
    w = interval_weights([0.5], [2.25], dt=1.0, n_frames=4)
    np.testing.assert_allclose(w, [[0.5, 1.0, 0.25, 0.0]])


@pytest.mark.parametrize("kwargs", [
    dict(line_time_s=0.0, exposure_s=1e-3, rows=4),
    dict(line_time_s=1e-5, exposure_s=-1.0, rows=4),
    dict(line_time_s=1e-5, exposure_s=float("nan"), rows=4),
    dict(line_time_s=1e-5, exposure_s=1e-3, rows=0),
    dict(line_time_s=1e-5, exposure_s=1e-3, rows=4, rows_per_bin=0),
    dict(line_time_s=1e-5, exposure_s=1e-3, rows=4, trigger_s=-1e-3),
])
def test_invalid_rs_timing_is_rejected(kwargs):
    with pytest.raises(ValueError):
        RollingShutterTiming(**kwargs)


def test_invalid_gs_timing_is_rejected():
    with pytest.raises(ValueError):
        GlobalShutterTiming(trigger_s=(float("nan"),), exposure_s=1e-3)
    with pytest.raises(ValueError):
        GlobalShutterTiming(trigger_s=(0.0,), exposure_s=0.0)
