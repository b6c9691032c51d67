"""Scenes: shapes, ranges, determinism, and the property each scene exists for."""

import itertools

import cv2
import numpy as np
import pytest

from rngcam.physics.timing import GlobalShutterTiming, RollingShutterTiming, VideoGrid
from rngcam.sim.scenes import (
    FlowInterpolator,
    SceneError,
    choose_clip_start,
    default_clip_path,
    render_scene,
    srgb_to_linear,
)

DT_S, EXPOSURE_S = 208e-6, 650e-6


def simulator_timing(size: int):
    """The simulator's layout: RS over `size` rows, GS key frames at start, middle and end."""
    rs = RollingShutterTiming(line_time_s=DT_S, exposure_s=EXPOSURE_S, rows=size)
    end = (size - 1) * DT_S
    gs = GlobalShutterTiming(trigger_s=(0.0, end / 2, end), exposure_s=EXPOSURE_S)
    return VideoGrid.covering(rs, gs), gs.centres_s()


def textured_clip(path, frames=10, size=48, shift_px=(0, 0, 0, 4, 4, 4, 4, 4, 4), seed=0):
    """An npz clip of a random texture translating right by shift_px[j] between frames j, j+1."""
    rng = np.random.default_rng(seed)
    texture = cv2.GaussianBlur(rng.uniform(0, 255, (size, 3 * size, 3)).astype(np.float32), (0, 0), 1.5)
    texture = np.clip((texture - texture.mean()) * 3 + 128, 0, 255).astype(np.uint8)
    offsets = np.concatenate([[0], np.cumsum(shift_px)])[:frames].astype(int)
    clip = np.stack([texture[:, size - o:2 * size - o] for o in offsets])
    np.savez(path, frames=clip)
    return clip


@pytest.fixture
def clip_file(tmp_path):
    path = tmp_path / "clip.npz"
    textured_clip(path)
    return path


def scene_opts(name, keys, clip_file):
    return {"path": clip_file, "span": 5} if name == "clip" else {"key_times_s": keys}


@pytest.mark.parametrize("name", ["sineball", "smoke", "clip"])
def test_scene_shape_range_and_determinism(name, clip_file):
    grid, keys = simulator_timing(24)
    video = render_scene(name, grid, 24, seed=3, **scene_opts(name, keys, clip_file))
    assert video.shape == (3, grid.n_frames, 24, 24) and video.dtype == np.float32
    assert np.all(np.isfinite(video)) and video.min() >= 0 and video.max() <= 1
    assert video.std() > 0.01  # not blank
    again = render_scene(name, grid, 24, seed=3, **scene_opts(name, keys, clip_file))
    np.testing.assert_array_equal(video, again)
    if name != "clip":  # a clip's content comes from the file, not the seed
        other = render_scene(name, grid, 24, seed=4, **scene_opts(name, keys, clip_file))
        assert np.abs(other - video).max() > 0.05


def ball_centres_x(video: np.ndarray) -> np.ndarray:
    """x of the ball in each frame: centroid of the difference from the median frame."""
    background = np.median(video, axis=1, keepdims=True)
    diff = np.abs(video - background).sum(axis=0)  # (K, H, W)
    mask = diff > 0.5 * diff.max(axis=(1, 2), keepdims=True)
    xs = np.arange(video.shape[-1]) + 0.5
    return np.array([(m.sum(0) * xs).sum() / m.sum() for m in mask])


@pytest.mark.parametrize("size", [24, 32, 64])
def test_sineball_reverses_at_least_twice_between_key_frames(size):
    grid, keys = simulator_timing(size)
    video = render_scene("sineball", grid, size, seed=0, key_times_s=keys)
    x = ball_centres_x(video)
    t = grid.centres_s()
    for a, b in itertools.pairwise(keys):
        inside = (t >= a) & (t <= b)
        steps = np.diff(x[inside])
        steps = steps[np.abs(steps) > 1e-3]
        reversals = int(np.sum(np.sign(steps[1:]) != np.sign(steps[:-1])))
        assert reversals >= 2, f"only {reversals} reversals between key frames at {a:.2e}..{b:.2e} s"
    assert np.ptp(x) > 0.3 * size  # and it really travels


def test_smoke_absent_at_first_key_frame_and_present_later():
    size = 32
    grid, keys = simulator_timing(size)
    video = render_scene("smoke", grid, size, seed=1, key_times_s=keys)
    t = grid.centres_s()
    first = video[:, 0]
    # Everything up to (and a little beyond) the first key frame is the bare background.
    early = t <= keys[0] + 0.2 * (keys[1] - keys[0])
    for k in np.flatnonzero(early):
        np.testing.assert_array_equal(video[:, k], first)
    coverage = [(np.abs(video[:, k] - first).max(axis=0) > 0.05).mean()
                for k in (np.argmin(np.abs(t - keys[1])), len(t) - 1)]
    assert coverage[0] > 0.03 and coverage[1] > coverage[0]


def test_clip_truth_at_source_times_equals_linearised_resized_source(clip_file):
    frames = np.load(clip_file)["frames"]
    span, start, size = 5, 2, 16
    grid = VideoGrid(dt_s=DT_S, n_frames=9)  # centres land on the 5 source frames every 2 frames
    video = render_scene("clip", grid, size, path=clip_file, span=span, start=start)
    for m in range(span):
        expected = cv2.resize(srgb_to_linear(frames[start + m]), (size, size), interpolation=cv2.INTER_AREA)
        np.testing.assert_allclose(video[:, 2 * m], np.moveaxis(expected, -1, 0), atol=1e-6)


def test_flow_interpolation_beats_cross_fade_on_translation(tmp_path):
    clip = textured_clip(tmp_path / "c.npz", frames=2, shift_px=(6,))
    truth_mid = textured_clip(tmp_path / "m.npz", frames=2, shift_px=(3,))[1]
    interp = FlowInterpolator(clip)
    mid = interp(0.5)
    fade = 0.5 * (srgb_to_linear(clip[0]) + srgb_to_linear(clip[1]))
    inner = np.s_[:, 8:-8]  # away from the border that enters the view
    err_flow = np.abs(mid - srgb_to_linear(truth_mid))[inner].mean()
    err_fade = np.abs(fade - srgb_to_linear(truth_mid))[inner].mean()
    assert err_flow < 0.5 * err_fade
    np.testing.assert_array_equal(interp(1.0), srgb_to_linear(clip[1]))


def test_clip_start_defaults_to_the_window_with_most_motion(tmp_path):
    frames = textured_clip(tmp_path / "c.npz")  # static for 3 frames, then moving
    assert choose_clip_start(frames, 4) >= 3
    grid = VideoGrid(dt_s=DT_S, n_frames=4)
    chosen = render_scene("clip", grid, 16, path=tmp_path / "c.npz", span=4)
    explicit = render_scene("clip", grid, 16, path=tmp_path / "c.npz", span=4,
                            start=choose_clip_start(frames, 4))
    np.testing.assert_array_equal(chosen, explicit)


def test_real_clip_renders():
    path = default_clip_path()  # the short car clip shipped in rngcam/data
    grid, _ = simulator_timing(16)
    video = render_scene("clip", grid, 16, path=path, span=8)
    assert video.shape == (3, grid.n_frames, 16, 16) and np.all(np.isfinite(video))
    assert np.abs(video[:, -1] - video[:, 0]).mean() > 1e-3  # something moves


def test_bad_scene_requests_are_clear_errors(tmp_path, clip_file):
    grid, _ = simulator_timing(16)
    with pytest.raises(SceneError, match="unknown scene"):
        render_scene("fireworks", grid, 16)
    with pytest.raises(SceneError, match="does not take"):
        render_scene("sineball", grid, 16, span=3)
    with pytest.raises(SceneError, match="not found"):
        render_scene("clip", grid, 16, path=tmp_path / "missing.npz")
    with pytest.raises(SceneError, match="does not fit"):
        render_scene("clip", grid, 16, path=clip_file, span=50)
    with pytest.raises(SceneError, match="span"):
        render_scene("clip", grid, 16, path=clip_file, span=1)
    np.savez(tmp_path / "bad.npz", frames=np.zeros((4, 8, 8), np.uint8))
    with pytest.raises(SceneError, match="uint8"):
        render_scene("clip", grid, 16, path=tmp_path / "bad.npz")
    with pytest.raises(SceneError, match="size"):
        render_scene("sineball", grid, 4)
    with pytest.raises(SceneError, match="key_times_s"):
        render_scene("smoke", grid, 16, key_times_s=[1e-3])
