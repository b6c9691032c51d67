"""STFM's ensemble members stepped side by side (rngcam.recon.methods.stfm.lanes) follow the same
trajectories as stepped in turn, and a small grid's step evaluates its frames in one graph."""

import threading

import pytest
import torch
from test_stfm import scene_problem

from rngcam.recon.methods.stfm import STFMSettings, make_stfm
from rngcam.recon.methods.stfm.lanes import Lanes, lane_count
from rngcam.recon.methods.stfm.settings import CHUNK_POINTS, MIN_FRAME_CHUNK, chunk_frames


@pytest.fixture(scope="module")
def smoke16():
    return scene_problem("smoke", 16)


def ensemble(problem):
    return make_stfm(problem, STFMSettings(preset="fast", dynamic_base="interp,blend", refine=False,
                                           rows_per_step=4, self_calibrate="off", start_floor=False))


def test_members_side_by_side_take_the_same_steps_as_in_turn(smoke16):
    runs = {}
    for threads in (1, 2):
        torch.set_num_threads(threads)
        m = ensemble(smoke16)
        for _ in range(6):
            m.step()
        assert torch.get_num_threads() == threads  # the lanes give torch its threads back
        runs[threads] = m
    in_turn, side_by_side = runs[1], runs[2]
    assert [f.steps for f in in_turn.members] == [3, 3]  # one member a step, the fewest steps first
    assert [f.steps for f in side_by_side.members] == [6, 6]  # both members each step
    torch.set_num_threads(1)
    for _ in range(6):
        in_turn.step()
    for a, b in zip(in_turn.members, side_by_side.members, strict=True):
        assert a.steps == b.steps == 6
        # the videos (the weights' moving averages); a weight whose gradient is at float rounding's
        # level may differ (Adam's step has the gradient's sign), one that shapes the video may not
        torch.testing.assert_close(a.estimate(), b.estimate(), rtol=1e-4, atol=1e-5)
    torch.testing.assert_close(in_turn.estimate(), side_by_side.estimate(), rtol=1e-4, atol=1e-5)


def test_a_lane_that_fails_is_raised_after_every_lane_has_ended():
    torch.set_num_threads(2)
    ended = threading.Event()

    def slow():
        ended.wait(5)
        return "slow"

    def failing():
        ended.set()
        raise ValueError("lane failed")

    lanes = Lanes()
    with pytest.raises(ValueError, match="lane failed"):
        lanes.run([failing, slow])
    assert ended.is_set() and torch.get_num_threads() == 2
    assert lanes.run([lambda: torch.get_num_threads(), lambda: 1]) == [1, 1]  # torch at one thread inside
    lanes.close()
    assert lane_count(5) == 2 and lane_count(1) == 1


def test_a_small_grid_takes_its_frames_in_one_graph_and_a_large_one_keeps_four():
    assert chunk_frames(STFMSettings(), 64, 64) == CHUNK_POINTS // 4096 > MIN_FRAME_CHUNK
    assert chunk_frames(STFMSettings(), 228, 342) == MIN_FRAME_CHUNK
    assert chunk_frames(STFMSettings(frame_chunk=2), 64, 64) == 2
    m = make_stfm(scene_problem("sineball", 16), STFMSettings(preset="fast", dynamic_base="interp",
                                                              self_calibrate="off", start_floor=False))
    assert m.frame_chunk == CHUNK_POINTS // 256 and m.resolved_settings()["frame_chunk"] == m.frame_chunk
