"""STFM's own stop is counted in the data (passes over the RS rows, the residual against the noise
level), never in seconds or in how many fits step side by side: a device that steps a hundred times
slower, or runs its fits in another order, stops at the same step with the same video, as long as
its time budget is not what ends the run."""

import itertools
import time

import torch
from tiny_scenes import tiny_sineball_problem

from rngcam.recon.loop import Clock, LoopSettings, run
from rngcam.recon.methods.stfm import STFMSettings, make_stfm


def _own_stop(problem, threads: int, seconds_per_call: float | None = None, monkeypatch=None):
    """(each fit's steps, how it ended, video) of the fast preset's run on `problem` to its own stop, at
    `threads` torch threads; with `seconds_per_call` every reading of the wall clock moves it on by that
    much (a slow device), under a budget no run here comes near."""
    if seconds_per_call is not None:
        ticks = itertools.count()
        monkeypatch.setattr(time, "perf_counter", lambda: 1000.0 + seconds_per_call * next(ticks))
    before = torch.get_num_threads()
    torch.set_num_threads(threads)
    try:
        torch.manual_seed(0)
        method = make_stfm(problem, STFMSettings(preset="fast", fits=2, seed=0), "cpu")
        result = run(method, LoopSettings(clock=Clock(seconds=1e9), max_iters=4000, progress=False))
        assert result.iterations < 4000
        return method.resolved_settings()["member_steps"], result.ended_by, method.estimate().detach().clone()
    finally:
        torch.set_num_threads(before)
        monkeypatch.undo() if monkeypatch is not None else None


def test_the_own_stop_does_not_depend_on_the_clock_or_the_lanes(monkeypatch):
    problem = tiny_sineball_problem(16).to(torch.float32)
    steps, ended, video = _own_stop(problem, threads=1)
    assert ended == "own_stop" and len(steps) == 4 and min(steps) > 0  # two bases, two fits each
    slow = _own_stop(problem, threads=1, seconds_per_call=0.05, monkeypatch=monkeypatch)
    assert slow[:2] == (steps, ended)
    assert torch.allclose(slow[2], video, atol=1e-5)
    # two fits in two lanes instead of one after the other: fewer rounds (the loop's iterations), the same
    # steps in each fit
    side_by_side = _own_stop(problem, threads=2)
    assert side_by_side[:2] == (steps, ended)
    assert torch.allclose(side_by_side[2], video, atol=1e-4)
