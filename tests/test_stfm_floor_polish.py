"""The self-check's held-out rows: the motion search reads them, the fit does not."""

from dataclasses import replace

import torch
from tiny_scenes import tiny_sineball_problem

from rngcam.recon.methods.stfm import STFMSettings
from rngcam.recon.methods.stfm.method import STFM


def _noisy(problem, sigma: float, seed: int = 0):
    gen = torch.Generator().manual_seed(seed)
    return replace(problem, b_rs=problem.b_rs + sigma * torch.randn(problem.b_rs.shape, generator=gen))


def _problem():
    return _noisy(tiny_sineball_problem(24).to(torch.float32), 0.002).with_holdout(0.2)


def test_the_motion_search_reads_every_row_the_fit_only_the_fitted():
    p = _problem()
    settings = STFMSettings(preset="prior", fits=1, subframes=1, self_calibrate="off")
    split, whole = STFM(p, settings), STFM(replace(p, rs_train_rows=None), settings)
    assert torch.equal(split.motion_track_px, whole.motion_track_px)
    assert len(split.grid.rs_rows_fit) < p.shape[2] == len(whole.grid.rs_rows_fit)
