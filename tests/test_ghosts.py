"""The key-frame ghost score (rngcam.evaluate.ghosts) on synthetic moving-ball videos."""

import numpy as np
import pytest

from rngcam.evaluate.ghosts import bracketing_keys, frame_ghost, ghost_scores, ghost_summary

K, N = 21, 32
KEYS = [0, 10, 20]
INTER = [k for k in range(K) if k not in (0, 1, 9, 10, 11, 19, 20)]


def ball_video(xs, size=N, level=1.0):
    yy, xx = np.mgrid[0:size, 0:size] + 0.5
    video = np.full((3, len(xs), size, size), 0.2 * level)
    for k, x in enumerate(xs):
        video[:, k, np.hypot(xx - x, yy - size / 2) < 4] = 0.9 * level
    return video.astype(np.float32)


@pytest.fixture
def truth():
    return ball_video(np.linspace(5, 27, K))


def cross_fade(truth):
    video = truth.copy()
    for a, b in zip(KEYS[:-1], KEYS[1:], strict=True):
        for k in range(a + 1, b):
            s = (k - a) / (b - a)
            video[:, k] = (1 - s) * truth[:, a] + s * truth[:, b]
    return video


def test_truth_scores_zero(truth):
    scores = ghost_scores(truth, truth, KEYS, INTER)
    assert np.nanmax(scores) == 0.0


def test_cross_fade_scores_high_and_hold_higher(truth):
    fade = ghost_summary(ghost_scores(truth, cross_fade(truth), KEYS, INTER))
    assert 0.7 < fade["ghost_mean"] < 0.95  # the nearer key's copy, and the ball missing where it is now
    hold = truth.copy()
    for k in range(K):
        hold[:, k] = truth[:, min(KEYS, key=lambda g: abs(g - k))]
    held = ghost_summary(ghost_scores(truth, hold, KEYS, INTER))
    assert held["ghost_mean"] > 0.95 and held["ghost_mean"] > fade["ghost_mean"]


def test_moved_but_slightly_off_scores_low(truth):
    shifted = ball_video(np.linspace(5, 27, K) + 0.7)  # right content, 0.7 px off
    noisy = shifted + np.random.default_rng(0).normal(0, 0.01, shifted.shape).astype(np.float32)
    assert ghost_summary(ghost_scores(truth, noisy, KEYS, INTER))["ghost_mean"] < 0.2


def test_scale_free_for_dim_scenes(truth):
    dim = truth * 0.03
    a = ghost_scores(truth, cross_fade(truth), KEYS, INTER)
    b = ghost_scores(dim, cross_fade(dim), KEYS, INTER)
    np.testing.assert_allclose(a, b, atol=1e-4)


def test_half_ghost_reads_half():
    t = np.zeros((3, 4, 4))
    key = t.copy()
    key[:, 1, 1] = 1.0
    assert frame_ghost(t, 0.5 * key, [key], floor=0.1) == pytest.approx(0.5)
    assert frame_ghost(t, t, [t], floor=0.1) is None  # nothing moved


def test_static_frames_are_nan_and_summary_skips_them():
    still = np.full((3, 5, 8, 8), 0.4, np.float32)
    still[:, :, 0, 0] = 1.0
    scores = ghost_scores(still, still, [0, 4], [2])
    assert np.isnan(scores).all()
    assert ghost_summary(scores)["ghost_mean"] is None


def test_bracketing_keys_and_shape_check(truth):
    assert bracketing_keys(5, KEYS) == [0, 10]
    assert bracketing_keys(10, KEYS) == [10]
    assert bracketing_keys(25, KEYS) == [20]
    with pytest.raises(ValueError, match="must both be"):
        ghost_scores(truth, truth[:, :5], KEYS, INTER)
