"""The motion-kind scenes (rngcam.sim.motion_kinds): each renders finite, in range, deterministic,
and shows the motion it is named for."""

import numpy as np
import pytest

from rngcam.sim import motion_kinds as mk
from rngcam.sim.scenes import MOTION_KINDS, SCENES, SceneError, render_scene
from rngcam.sim.simulate import simulation_timing

SIZE = 32


@pytest.fixture(scope="module")
def timing():
    return simulation_timing(SIZE)


def render(name, timing, seed=0, size=SIZE):
    return render_scene(name, timing.grid, size, seed, key_times_s=timing.gs.centres_s())


def key_index(timing, g):
    return int(np.argmin(np.abs(timing.grid.centres_s() - timing.gs.centres_s()[g])))


def test_registered_as_scenes():
    assert set(mk.RENDERERS) == set(MOTION_KINDS)
    assert set(MOTION_KINDS) <= set(SCENES)
    with pytest.raises(SceneError, match="does not take"):
        render_scene("rotation", simulation_timing(16).grid, 16, 0, span=3)


@pytest.mark.parametrize("name", MOTION_KINDS)
def test_renders_finite_in_range_deterministic_and_moving(name, timing):
    video = render(name, timing, seed=3)
    assert video.shape == (3, timing.grid.n_frames, SIZE, SIZE) and video.dtype == np.float32
    assert np.all(np.isfinite(video)) and video.min() >= 0 and video.max() <= 1
    np.testing.assert_array_equal(video, render(name, timing, seed=3))
    assert np.abs(np.diff(video, axis=1)).max() > 0.01  # something moves
    wide = render_scene(name, timing.grid, (SIZE, 48), 3, key_times_s=timing.gs.centres_s())
    assert wide.shape[-2:] == (SIZE, 48)


def test_enter_leave_enters_after_the_first_key_and_leaves_before_the_middle(timing):
    paths = mk.enter_leave_paths(timing.grid, SIZE, timing.gs.centres_s())
    r, half = float(paths["radius"]), float(paths["half"])
    k0, k1 = key_index(timing, 0), key_index(timing, 1)
    assert paths["enter"][k0, 0] < -r and r < paths["enter"][k1, 0] < SIZE - r  # absent, then present
    assert half < paths["leave"][k0, 0] < SIZE - half and paths["leave"][k1, 0] > SIZE + half
    video = render("enter_leave", timing)
    x, y = paths["enter"][k1].astype(int)
    assert np.abs(video[:, k1, y, x] - video[:, k0, y, x]).max() > 0.2  # the disc is there only mid-way


def test_rotation_is_a_rotation_about_the_centre(timing):
    import cv2

    video = render("rotation", timing)
    angles = mk.rotation_angle(timing.grid, timing.gs.centres_s())
    k0, k = 0, 10
    turn = np.degrees(angles[k] - angles[k0])
    m = cv2.getRotationMatrix2D((SIZE / 2 - 0.5, SIZE / 2 - 0.5), turn, 1.0)
    yy, xx = np.mgrid[0:SIZE, 0:SIZE] + 0.5
    inside = np.hypot(xx - SIZE / 2, yy - SIZE / 2) < 0.25 * SIZE
    rotated = np.stack([cv2.warpAffine(np.ascontiguousarray(video[c, k0]), m, (SIZE, SIZE)) for c in range(3)])
    err_rotated = np.abs(rotated - video[:, k])[:, inside].mean()
    err_still = np.abs(video[:, k0] - video[:, k])[:, inside].mean()
    assert err_rotated < 0.5 * err_still
    outside = np.hypot(xx - SIZE / 2, yy - SIZE / 2) > 0.45 * SIZE
    assert np.abs(video[:, k0] - video[:, k])[:, outside].max() < 1e-6  # the backdrop stays


def test_occlusion_hides_the_disc_behind_the_bar():
    timing = simulation_timing(64)
    lay = mk.occlusion_layout(timing.grid, 64, timing.gs.centres_s())
    (x0, x1), r = lay["bar"], float(lay["radius"])
    hidden = np.flatnonzero((lay["x"] - r - 1 > x0) & (lay["x"] + r + 1 < x1))
    assert len(hidden) >= 2 and lay["x"][0] + r < x0  # visible at the first key frame, hidden later
    video = render("occlusion", timing, size=64)
    np.testing.assert_allclose(video[:, hidden[0]], video[:, hidden[-1]], atol=1e-3)  # only the bar shows
    bar = slice(int(np.ceil(x0 + 1)), int(np.floor(x1 - 1)))
    assert np.ptp(video[:, :, :, bar], axis=1).max() < 1e-6  # the bar never changes


def test_crossing_discs_cross_between_key_frames(timing):
    centres, r = mk.crossing_paths(timing.grid, SIZE, 0, timing.gs.centres_s())
    keys = [key_index(timing, g) for g in range(3)]
    n = len(centres)
    gaps = np.array([[np.hypot(*(centres[i] - centres[j]).T) for j in range(n) if j > i] for i in range(n)],
                    dtype=object)
    pair_gaps = np.stack([g for row in gaps for g in row])  # (pairs, K)
    assert pair_gaps.min() < r  # some pair overlaps
    assert pair_gaps[:, keys].min(axis=0).min() > pair_gaps.min()  # not at a key frame


def test_shake_moves_the_whole_frame(timing):
    video = render("shake", timing)
    off = mk.shake_offsets(timing.grid, SIZE, 0, timing.gs.centres_s())
    assert np.abs(np.diff(off, axis=0)).max() > 0.2  # px per frame somewhere
    changed = (np.abs(video[:, 1] - video[:, 0]).max(0) > 1e-3).mean()
    assert changed > 0.5  # global motion: most pixels change between two frames


def test_deform_changes_shape_in_place(timing):
    video = render("deform", timing)
    blob = (video[0] - video[2]) > 0.25  # the reddish blob against the muted backdrop
    area = blob.sum(axis=(1, 2))
    assert area.max() > 1.5 * area.min() > 0
    yy, xx = np.mgrid[0:SIZE, 0:SIZE] + 0.5
    cx = (blob * xx).sum(axis=(1, 2)) / area
    cy = (blob * yy).sum(axis=(1, 2)) / area
    assert np.abs(cx - SIZE / 2).max() < 1.0 and np.abs(cy - SIZE / 2).max() < 1.0


def test_low_light_stays_dim(timing):
    video = render("low_light", timing)
    assert video.max() <= mk.LOW_LIGHT_PEAK + 1e-7 and video.max() > 0.8 * mk.LOW_LIGHT_PEAK


def test_small_fast_is_small_and_fast(timing):
    path, r = mk.small_fast_path(timing.grid, 64, 0, timing.gs.centres_s())
    assert 2 * r <= 3.0
    speed = np.hypot(*np.diff(path, axis=0).T)
    assert np.median(speed) > 1.5  # px per frame at 64 px
    video = render("small_fast", timing, size=64)
    moving = np.abs(video[:, 20] - video[:, 0]).max(0) > 0.2
    assert 0 < moving.sum() < 40


def test_textured_background_is_dense_and_contrasted(timing):
    video = render("textured", timing)
    frame = video[:, 0].mean(0)
    assert np.abs(np.diff(frame, axis=1)).mean() > 0.1
