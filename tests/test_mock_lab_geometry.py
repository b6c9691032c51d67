"""The mock rig with the lab's geometry (rigs/mock_lab.yaml), scaled down: a non-square sensor,
grid_bin > 1, the scene rendered on the grid, sensor-size frames by repetition, truth on the grid."""

from pathlib import Path

import numpy as np
import pytest

from rngcam.acquire.capture import capture
from rngcam.config import parse_rig
from rngcam.errors import ConfigError
from rngcam.formats.bundle import read_bundle
from rngcam.recon.problem import build_problem

REPO = Path(__file__).resolve().parents[1]
LAB = REPO / "rigs" / "mock_lab.yaml"


def _small_lab(noise: bool = False):
    """5472x3648 / 16 px, 13 us line time -> the same timing at 1/6 of the rows: 96x64 sensor,
    grid_bin 4 -> a 16x24 grid."""
    text = LAB.read_text()
    for old, new in (("{width: 5472, height: 3648}", "{width: 96, height: 64}"),
                     ("grid_bin: 16 ", "grid_bin: 4 "), ("line_time_s: 13.0e-6", "line_time_s: 52.0e-6"),
                     ("[0.0, 23.7e-3, 47.4e-3]", "[0.0, 1.6e-3, 3.2e-3]"),
                     ("readout_s: 1.0e-3", "readout_s: 0.2e-3"), ("fetch_timeout_s: 60.0", "fetch_timeout_s: 5.0"),
                     ("noise: true", f"noise: {str(noise).lower()}")):
        assert old in text, old
        text = text.replace(old, new)
    return parse_rig(text, LAB)


def test_the_lab_mock_rig_parses():
    rig = parse_rig(LAB.read_text(), LAB)
    assert rig.config.recon.grid_bin == 16 and rig.config.cameras.rs.roi.height == 3648


def test_a_mock_roi_that_does_not_bin_is_refused():
    with pytest.raises(ConfigError, match="must divide by recon.grid_bin"):
        parse_rig(_small_lab().text.replace("grid_bin: 4 ", "grid_bin: 5 "), LAB)


def test_lab_geometry_capture_is_the_grid_model_repeated_with_truth_on_the_grid(tmp_path):
    [r] = capture(_small_lab(), tmp_path / "lab.h5", progress=lambda s: None)
    b = read_bundle(r.path)
    assert b.rs.frames.shape == (1, 64, 96, 3) and b.gs.frames.shape == (3, 64, 96, 3)
    rs = b.rs.frames[0]
    # every 4x4 block of sensor pixels repeats one grid pixel (noise off)
    assert (rs == np.repeat(np.repeat(rs[::4, ::4], 4, 0), 4, 1)).all()
    problem = build_problem(b)
    c, k, h, w = problem.shape
    assert (h, w) == (16, 24) and b.truth.video.shape == (3, k, 16, 24) and problem.truth is not None
    # the binned RS image is the reconstruction's forward model of the grid truth (12-bit rounding)
    pred = problem.rs_op().A(problem.truth)
    assert float((pred - problem.b_rs).abs().max()) < 3e-3 * float(pred.abs().max())
    gs_pred = problem.gs_op().A(problem.truth)
    assert float((gs_pred - problem.b_gs).abs().max()) < 3e-3 * float(gs_pred.abs().max())
