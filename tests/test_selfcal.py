"""Self-calibration: hot/dead pixels found in the data, the GS-to-RS transform and gains refined."""

import numpy as np
import pytest
import torch

from rngcam.recon import selfcal
from rngcam.recon.defects import outliers
from rngcam.recon.problem import build_problem
from rngcam.sim.fidelity import LabErrors
from rngcam.sim.simulate import simulate


def test_outliers_find_fixed_pattern_spikes_not_texture():
    rng = np.random.default_rng(0)
    yy, xx = np.mgrid[0:32, 0:32]
    texture = 0.5 + 0.3 * ((xx // 4 + yy // 4) % 2) + 0.01 * rng.standard_normal((3, 2, 32, 32))  # checkerboard
    frames = texture.copy()
    frames[:, :, 5, 7] += 0.5  # hot in both frames
    frames[1, :, 20, 20] = 0.0  # dead in one channel
    frames[:, 0, 12, 12] += 0.5  # a spike in one frame only: the scene, not the sensor
    found = outliers(frames)
    assert set(map(tuple, np.argwhere(found))) == {(5, 7), (20, 20)}


def test_lab_bundle_defects_leave_the_data_term(tmp_path):
    b = simulate("sineball", tmp_path / "l.h5", size=64, seed=1, fidelity="lab",
                 lab_errors=LabErrors(hot_fraction=0.002, dead_fraction=0.0))
    p = build_problem(b)
    hot = {(y // 2, x // 2) for y, x in b.meta["truth_calibration"]["rs_defects"]["hot"]}
    masked = {tuple(a) for a in np.argwhere(~p.rs_valid.numpy().all(axis=0))}
    assert len(hot & masked) >= 0.75 * len(hot) and len(masked - hot) <= 1
    assert any("hot or dead" in n for n in p.notes)
