"""Simulator: bundles that read back, match the physics of their truth, and the CLI."""

import numpy as np
import pytest
import torch
from click.testing import CliRunner

from rngcam.cli import main
from rngcam.errors import RngcamError
from rngcam.formats.bundle import read_bundle
from rngcam.physics import psf as psf_mod
from rngcam.physics.operators import GlobalShutter, RollingShutter
from rngcam.physics.sensor import BAYER_FORMATS, demosaic_bin, frame_to_measurement
from rngcam.physics.timing import GlobalShutterTiming, RollingShutterTiming, VideoGrid
from rngcam.sim.simulate import LENSLETS, simulate

SIZE = 24
HALF_DN = 0.5 / 4095 * 650e-6 / 208e-6  # half a 12-bit DN in operator units


@pytest.fixture
def clip_file(tmp_path):
    """A small npz clip: a random texture translating right by 3 px per frame."""
    rng = np.random.default_rng(0)
    texture = rng.integers(0, 256, (32, 96, 3), dtype=np.uint8)
    frames = np.stack([texture[:, 40 - 3 * j:72 - 3 * j] for j in range(10)])
    path = tmp_path / "clip.npz"
    np.savez(path, frames=frames)
    return path


def bundle_physics(b):
    """Timing, grid and grid PSF rebuilt from the bundle's records alone (as a reader would)."""
    grid_bin = b.meta["grid_bin"]
    rs = RollingShutterTiming(line_time_s=b.rs.line_time_s, exposure_s=b.rs.exposure_s,
                              rows=b.rs.frames.shape[1] // grid_bin, rows_per_bin=grid_bin)
    gs = GlobalShutterTiming(trigger_s=tuple(b.gs.trigger_times_s), exposure_s=b.gs.exposure_s)
    grid = VideoGrid.covering(rs, gs)
    raw = np.asarray(b.calibration.psf, np.float64)
    psf = psf_mod.bin_psf(raw, grid_bin)
    return rs, gs, grid, torch.from_numpy(psf)


def measurements(b, dt_s):
    cam = b.rs
    rs = frame_to_measurement(cam.frames[0], cam.pixel_format, cam.black_level_dn, cam.bit_depth,
                              cam.exposure_s, dt_s)
    gs = np.stack([frame_to_measurement(f, b.gs.pixel_format, b.gs.black_level_dn, b.gs.bit_depth,
                                        b.gs.exposure_s, dt_s) for f in b.gs.frames], axis=1)
    return rs, gs


@pytest.mark.parametrize("scene", ["sineball", "smoke", "clip"])
def test_noiseless_bundle_matches_the_forward_model_of_its_truth(scene, tmp_path, clip_file):
    out = tmp_path / f"{scene}.h5"
    opts = {"clip": clip_file, "span": 6} if scene == "clip" else {}
    simulate(scene, out, size=SIZE, seed=2, noise=False, **opts)
    b = read_bundle(out)
    assert b.rs.frames.shape == (1, SIZE, SIZE, 3) and b.rs.frames.dtype == np.uint16
    assert b.gs.frames.shape == (3, SIZE, SIZE, 3) and b.rs.pixel_format == "RGB12"
    assert b.rs.line_time_s == pytest.approx(208e-6) and b.rs.exposure_s == pytest.approx(650e-6)
    rs_t, gs_t, grid, psf = bundle_physics(b)
    truth = b.truth.video
    assert truth.shape == (3, grid.n_frames, SIZE, SIZE) and truth.dtype == np.float32
    assert b.truth.dt_s == pytest.approx(grid.dt_s)
    np.testing.assert_allclose(b.truth.frame_times_s, grid.edges_s()[:-1])
    # Every GS exposure lies inside the RS window.
    assert gs_t.trigger_s[0] >= 0 and gs_t.end_s <= rs_t.end_s + 1e-12
    assert b.meta["scene"] == scene and b.meta["size"] == SIZE and b.meta["noise"] is False
    assert 0 < b.meta["psf_spectral_support"] <= 1
    np.testing.assert_array_equal(b.calibration.white_balance, np.ones(3))
    np.testing.assert_array_equal(b.calibration.gs_to_rs, np.eye(3))

    v = torch.from_numpy(truth.astype(np.float64))
    expected_rs = RollingShutter(psf, torch.from_numpy(rs_t.weights(grid)), SIZE, channels=3).A(v).numpy()
    expected_gs = GlobalShutter(torch.from_numpy(gs_t.weights(grid)), 3, (SIZE, SIZE)).A(v).numpy()
    b_rs, b_gs = measurements(b, grid.dt_s)
    np.testing.assert_allclose(b_rs, expected_rs, atol=HALF_DN * 1.01, rtol=0)
    unsaturated = np.moveaxis(b.gs.frames, -1, 0) < 4095
    assert unsaturated.mean() > 0.9
    np.testing.assert_allclose(b_gs[unsaturated], expected_gs[unsaturated], atol=HALF_DN * 1.01, rtol=0)


def test_bayer_bundle_is_binned_back_to_the_grid(tmp_path):
    size = 16
    out = tmp_path / "bayer.h5"
    simulate("sineball", out, size=size, noise=False, bayer=True)
    b = read_bundle(out)
    assert b.rs.pixel_format in BAYER_FORMATS and b.meta["grid_bin"] == 2
    assert b.rs.frames.shape == (1, 2 * size, 2 * size) and b.gs.frames.shape == (3, 2 * size, 2 * size)
    assert b.rs.line_time_s == pytest.approx(104e-6)
    rs_t, _, grid, psf = bundle_physics(b)
    assert grid.dt_s == pytest.approx(208e-6)
    v = torch.from_numpy(b.truth.video.astype(np.float64))
    b_rs, _ = measurements(b, grid.dt_s)
    assert b_rs.shape == (3, size, size)
    # G samples both sensor rows of a bin: exactly the binned (trapezoid) timing model.
    binned = RollingShutter(psf, torch.from_numpy(rs_t.weights(grid)), size, channels=3).A(v).numpy()
    np.testing.assert_allclose(b_rs[1], binned[1], atol=HALF_DN * 1.01, rtol=0)
    # R sits on even sensor rows only: their own exposure windows.
    sensor_t = RollingShutterTiming(line_time_s=rs_t.line_time_s, exposure_s=rs_t.exposure_s, rows=2 * size)
    even = torch.from_numpy(sensor_t.weights(grid)[0::2])
    red = RollingShutter(psf, even, size, channels=3).A(v).numpy()[0]
    np.testing.assert_allclose(b_rs[0], red, atol=HALF_DN * 1.01, rtol=0)
    assert np.abs(demosaic_bin(b.gs.frames[1].astype(np.float64))).max() > 0


def test_noise_is_seeded_and_realistic(tmp_path):
    quiet = simulate("sineball", tmp_path / "q.h5", size=SIZE, seed=5, noise=False)
    a = simulate("sineball", tmp_path / "a.h5", size=SIZE, seed=5)
    again = simulate("sineball", tmp_path / "b.h5", size=SIZE, seed=5)
    other = simulate("sineball", tmp_path / "c.h5", size=SIZE, seed=6, noise=True)
    np.testing.assert_array_equal(a.rs.frames, again.rs.frames)
    np.testing.assert_array_equal(a.gs.frames, again.gs.frames)
    assert np.any(a.rs.frames != other.rs.frames)
    diff = a.rs.frames.astype(float) - quiet.rs.frames.astype(float)
    # Shot noise at ~1/3 of full scale with 10,000 e- full well: a few DN, zero mean.
    assert 1.0 < diff.std() < 20.0 and abs(diff.mean()) < 0.5


def test_refuses_to_overwrite_without_permission(tmp_path):
    out = tmp_path / "x.h5"
    simulate("sineball", out, size=8, noise=False)
    before = out.read_bytes()
    with pytest.raises(RngcamError, match="already exists"):
        simulate("smoke", out, size=8)
    assert out.read_bytes() == before
    simulate("smoke", out, size=8, overwrite=True)
    assert read_bundle(out).meta["scene"] == "smoke"


def test_defaults_are_package_data_and_lenslets_is_a_rendered_model(tmp_path, monkeypatch):
    monkeypatch.delenv("RNGCAM_DATA", raising=False)
    measured = simulate("clip", tmp_path / "c.h5", size=16, noise=False)  # default clip and PSF
    assert measured.meta["psf_source"] == "package:diffusercam_tutorial_psf.png"
    assert measured.meta["clip"].endswith("bikes_car_short.npz") and measured.meta["psf_model"] is False
    lens = simulate("sineball", tmp_path / "s.h5", size=16, noise=False, psf=LENSLETS)
    assert lens.meta["psf_model"] is True and "lenslet" in lens.calibration.psf_source
    psf = lens.calibration.psf
    assert psf.shape == (3, 16, 16) and np.all(np.isfinite(psf)) and np.allclose(psf.sum(axis=(1, 2)), 1)
    assert "psf" not in (read_bundle(tmp_path / "s.h5").rig_yaml.split("calibration:")[1].split("recon:")[0])
    for b in (measured, lens):  # the PSF figure is in the meta, a fraction
        assert 0 < b.meta["psf_resolvable_fraction"] <= 1 and b.meta["rs_snr_px"] > 1


def test_bad_options_are_clear_errors(tmp_path, clip_file):
    with pytest.raises(RngcamError, match="unknown scene"):
        simulate("fog", tmp_path / "a.h5")
    with pytest.raises(RngcamError, match="PSF file not found"):
        simulate("sineball", tmp_path / "a.h5", size=8, psf=tmp_path / "none.tif")
    with pytest.raises(RngcamError, match="psf-crop"):
        simulate("sineball", tmp_path / "a.h5", size=8, psf_crop=0.0)
    with pytest.raises(RngcamError, match="does not fit"):
        simulate("clip", tmp_path / "a.h5", size=8, clip=clip_file, span=40)
    with pytest.raises(RngcamError, match="only apply"):
        simulate("smoke", tmp_path / "a.h5", size=8, clip=clip_file)
    assert not (tmp_path / "a.h5").exists()


def test_rig_yaml_is_a_valid_rig_and_the_problem_builds(tmp_path):
    config = pytest.importorskip("rngcam.config")
    problem_mod = pytest.importorskip("rngcam.recon.problem")
    simulate("smoke", tmp_path / "s.h5", size=12, noise=False)
    b = read_bundle(tmp_path / "s.h5")
    rig = config.parse_rig(b.rig_yaml).config
    assert rig.mock.scene == "smoke" and rig.cameras.rs.line_time_s == pytest.approx(208e-6)
    p = problem_mod.build_problem(b)
    assert p.truth is not None and tuple(p.truth.shape) == tuple(b.truth.video.shape)
    residual = p.rs_op().A(p.truth) - p.b_rs
    assert float(residual.abs().max()) < HALF_DN * 1.01


def test_cli_simulate(tmp_path, clip_file):
    runner = CliRunner()
    out = tmp_path / "cli.h5"
    args = ["simulate", "sineball", "-o", str(out), "--size", "12", "--no-noise", "--seed", "1"]
    result = runner.invoke(main, args)
    assert result.exit_code == 0, result.output
    assert "spectral support" in result.output and "video frames" in result.output
    assert read_bundle(out).meta["seed"] == 1
    again = runner.invoke(main, args)
    assert again.exit_code == 2 and "error:" in again.output and "--overwrite" in again.output
    assert runner.invoke(main, args + ["--overwrite"]).exit_code == 0
    clip = runner.invoke(main, ["simulate", "clip", "-o", str(tmp_path / "c.h5"), "--size", "12",
                                "--clip", str(clip_file), "--span", "4", "--bayer"])
    assert clip.exit_code == 0, clip.output
    assert "clip start" in clip.output and read_bundle(tmp_path / "c.h5").meta["bayer"] is True
    bad = runner.invoke(main, ["simulate", "fog", "-o", str(tmp_path / "f.h5")])
    assert bad.exit_code == 2
