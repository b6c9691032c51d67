"""--fidelity fine and lab: captures finer than the grid, binned as the rig bins, with the true
calibration errors recorded."""

import numpy as np
import pytest
from click.testing import CliRunner

from rngcam.cli import main
from rngcam.errors import RngcamError
from rngcam.formats.bundle import read_bundle
from rngcam.physics.psf import magnify, normalise
from rngcam.physics.sensor import frame_to_measurement
from rngcam.physics.timing import RollingShutterTiming, VideoGrid
from rngcam.sim import fidelity as fm
from rngcam.sim.scenes import render_scene
from rngcam.sim.simulate import simulate

SIZE = 16


def rs_meas(b):
    return frame_to_measurement(b.rs.frames[0], b.rs.pixel_format, b.rs.black_level_dn, b.rs.bit_depth,
                                b.rs.exposure_s, b.meta["dt_s"])


def test_bin_time_and_space_are_means():
    v = np.arange(2 * 8 * 4 * 6, dtype=np.float64).reshape(2, 8, 4, 6)
    t = fm.bin_time(v, 2)
    np.testing.assert_allclose(t[:, 1], v[:, 4:8].mean(axis=1))
    s = fm.bin_space(v)
    np.testing.assert_allclose(s[0, 0, 1, 2], v[0, 0, 2:4, 4:6].mean())


def test_fine_is_the_rig_binning_of_a_finer_truth(tmp_path):
    grid_b = simulate("sineball", tmp_path / "g.h5", size=SIZE, noise=False, fidelity="grid")
    fine_b = simulate("sineball", tmp_path / "f.h5", size=SIZE, noise=False, fidelity="fine")
    assert fine_b.meta["fidelity"] == "fine" and fine_b.meta["fine"] == {"space": 2, "time": 4}
    k = fine_b.meta["n_frames"]
    assert fine_b.truth.video.shape == (3, k, SIZE, SIZE) and abs(k - grid_b.meta["n_frames"]) <= 1
    # The truth is the mean of the 2x finer, 4x faster render over each grid pixel and frame.
    fgrid = VideoGrid(fine_b.meta["dt_s"] / 4, 4 * k)
    kt = {"key_times_s": fine_b.meta["key_times_s"]}
    fine = render_scene("sineball", fgrid, 2 * SIZE, 0, **kt)
    np.testing.assert_allclose(fine_b.truth.video, fm.bin_space(fm.bin_time(fine, k)), atol=1e-6)
    # Not the inverse crime: the RS image differs from the grid operator applied to that truth
    # (sub-row timing, sub-pixel detail), but only by a few percent.
    assert fine_b.rs.frames.shape[1:3] == (2 * SIZE, 2 * SIZE) and fine_b.meta["grid_bin"] == 2
    assert fine_b.rs.line_time_s == pytest.approx(grid_b.rs.line_time_s / 2)
    rs_f, rs_g = fm.bin_space(rs_meas(fine_b)), rs_meas(grid_b)
    rel = np.linalg.norm(rs_f - rs_g) / np.linalg.norm(rs_g)
    assert 1e-3 < rel < 0.1
    # Exact calibration: identity transform, unit gains, no defects.
    tc = fine_b.meta["truth_calibration"]
    assert tc["shift_px"] == [0.0, 0.0] and tc["gs_gains"] == [1.0, 1.0, 1.0] and tc["rs_defects"]["hot"] == []


def test_each_grid_row_bins_sensor_rows_with_their_own_start_times():
    # A video lit only in one sub-frame: grid row i sees it through two sensor rows, 104 us apart.
    dt, k = 208e-6, 12
    grid = VideoGrid(dt, k)
    fgrid = VideoGrid(dt / 4, 4 * k)
    video = np.zeros((1, 4 * k, 16, 4))
    video[:, 13] = 1.0  # sub-frame 13: [3.25, 3.5) grid frames
    psf = np.zeros((1, 3, 3))
    psf[0, 1, 1] = 1
    from rngcam.physics.timing import GlobalShutterTiming

    rs, _ = fm.fine_measure(video, psf, grid, fgrid, dt / 2, 2 * dt, GlobalShutterTiming((0.0,), dt), fm.LabErrors())
    rs = fm.bin_space(np.repeat(rs, 2, axis=-1))  # the rows as the reconstruction bins them
    # Sensor row r exposes [r * 104 us, r * 104 us + 416 us): rows 0..6 see sub-frame 13 (in units of dt:
    # [r/2, r/2 + 2) overlaps [3.25, 3.5) for r = 3..6), each for a quarter frame.
    rows = RollingShutterTiming(dt / 2, 2 * dt, 16).weights(fgrid)[:, 13] * (fgrid.dt_s / dt)
    np.testing.assert_allclose(rs[0, :, 0], rows.reshape(8, 2).mean(axis=1))
    assert rs[0, 1, 0] == pytest.approx(0.125) and rs[0, 2, 0] == pytest.approx(0.25) and rs[0, 4, 0] == 0


def test_lab_records_the_errors_it_applied(tmp_path):
    b = simulate("smoke", tmp_path / "l.h5", size=SIZE, seed=3, fidelity="lab")
    b = read_bundle(tmp_path / "l.h5")
    tc = b.meta["truth_calibration"]
    drawn = fm.LabErrors.draw(3)
    assert tc["shift_px"] == pytest.approx(list(drawn.shift_px))
    assert np.hypot(*tc["shift_px"]) == pytest.approx(fm.LAB_MAGNITUDES["shift_px"])
    assert abs(tc["rotation_deg"]) == fm.LAB_MAGNITUDES["rotation_deg"]
    assert all(0.015 <= abs(g - 1) <= 0.03 for g in tc["gs_gains"])
    assert tc["line_time_s"] == pytest.approx(b.rs.line_time_s * tc["line_time_scale"])
    # Hot pixels read far above their neighbours in every GS frame; dead ones read the black level.
    for y, x in tc["gs_defects"]["hot"]:
        assert (b.gs.frames[:, y, x].astype(int) - int(b.gs.black_level_dn) >= 200).all()
    for y, x in tc["rs_defects"]["dead"]:
        assert (b.rs.frames[0, y, x] == b.rs.black_level_dn).all()
    # The stored PSF is a noisy measurement of the fine capture's (noise and background).
    fine = simulate("smoke", tmp_path / "f.h5", size=SIZE, seed=3, fidelity="fine")
    diff = np.abs(np.asarray(b.calibration.psf) - fine.calibration.psf).max()
    assert diff > 0.003 * fine.calibration.psf.max()


def test_the_calibrated_family_draws_the_lab_directions_at_what_calibration_leaves():
    lab, cal = fm.LabErrors.draw(5), fm.LabErrors.draw(5, fm.CALIBRATED_MAGNITUDES)
    m = fm.CALIBRATED_MAGNITUDES
    assert np.hypot(*cal.shift_px) == pytest.approx(m["shift_px"]) and m["shift_px"] < fm.LAB_MAGNITUDES["shift_px"]
    direction = np.array(lab.shift_px) / fm.LAB_MAGNITUDES["shift_px"]
    assert np.array(cal.shift_px) / m["shift_px"] == pytest.approx(direction)
    assert np.sign(cal.rotation_deg) == np.sign(lab.rotation_deg) and abs(cal.rotation_deg) == m["rotation_deg"]
    assert abs(cal.line_time_scale - 1) == pytest.approx(m["line_time"])
    assert np.sign(cal.line_time_scale - 1) == np.sign(lab.line_time_scale - 1)
    assert cal.psf_noise == m["psf_noise"] < lab.psf_noise
    # what no calibration measures stays as the lab family draws it
    assert (cal.gs_gains, cal.psf_background, cal.vignetting, cal.distortion_k1) == (
        lab.gs_gains, lab.psf_background, lab.vignetting, lab.distortion_k1)


def test_lab_gs_frames_carry_the_drawn_gains_and_shift():
    # A smooth scene: the GS frame's mean over the middle is the fine one's times the gain, and a
    # pure shift moves a ramp by exactly that many pixels.
    h = w = 32
    dt = 208e-6
    grid, fgrid = VideoGrid(dt, 4), VideoGrid(dt / 4, 16)
    ramp = np.broadcast_to(np.linspace(0, 1, 2 * w)[None, None, None], (3, 16, 2 * h, 2 * w)).copy()
    from rngcam.physics.timing import GlobalShutterTiming

    gs_t = GlobalShutterTiming((0.0,), dt)
    psf = np.zeros((3, 3, 3))
    psf[:, 1, 1] = 1
    err = fm.LabErrors(shift_px=(0.5, 0.0), gs_gains=(1.02, 0.97, 1.0))
    _, plain = fm.fine_measure(ramp, psf, grid, fgrid, dt, dt, gs_t, fm.LabErrors())
    _, lab = fm.fine_measure(ramp, psf, grid, fgrid, dt, dt, gs_t, err)
    step = 1 / (2 * w - 1) * 2  # the ramp's rise per grid pixel (2 sensor pixels)
    mid = (slice(None), 0, slice(16, 48), slice(16, 48))
    np.testing.assert_allclose(lab[mid] / np.array(err.gs_gains)[:, None, None] - plain[mid], 0.5 * step, rtol=1e-3)


def test_lab_gs_frames_of_a_textured_scene_are_exact_where_the_map_is_exact():
    # Fine texture (random pixels) through the GS warp: with gains only the map is the identity and
    # every pixel is the plain frame's times its gain; a whole-pixel shift moves every pixel
    # inside the border by exactly that much (OpenCV 5.0's bicubic remap of float64 images wrote
    # wrong values at hundreds of such pixels).
    from rngcam.physics.timing import GlobalShutterTiming

    h = w = 32
    dt = 208e-6
    grid, fgrid = VideoGrid(dt, 4), VideoGrid(dt / 4, 16)
    rng = np.random.default_rng(3)
    texture = np.broadcast_to(rng.random((3, 1, 2 * h, 2 * w)), (3, 16, 2 * h, 2 * w)).copy()
    gs_t = GlobalShutterTiming((0.0,), dt)
    psf = np.zeros((3, 3, 3))
    psf[:, 1, 1] = 1
    _, plain = fm.fine_measure(texture, psf, grid, fgrid, dt, dt, gs_t, fm.LabErrors())
    gains = fm.LabErrors(gs_gains=(1.02, 0.97, 1.0))
    _, lab = fm.fine_measure(texture, psf, grid, fgrid, dt, dt, gs_t, gains)
    np.testing.assert_allclose(lab, plain * np.array(gains.gs_gains)[:, None, None, None], rtol=1e-5, atol=1e-6)
    _, moved = fm.fine_measure(texture, psf, grid, fgrid, dt, dt, gs_t, fm.LabErrors(shift_px=(1.0, 0.0)))
    # S(p) = p + 1 grid px: GS sensor pixel x sees the scene at x + 2 sensor pixels
    np.testing.assert_allclose(moved[..., 4:-4, 4:-6], plain[..., 4:-4, 6:-4], rtol=1e-5, atol=1e-6)


def test_the_true_gs_to_rs_homography_registers_lab_gs_frames_at_the_sensor_resolution(tmp_path):
    """The lab GS frames warped by `true_gs_to_rs` as a bundle's calibration is applied (at the sensor's
    resolution, then binned: rngcam.recon.gridding) match the fine capture's; the identity does not."""
    from dataclasses import replace

    from rngcam.recon.problem import build_problem

    err = fm.LabErrors(shift_px=(0.6, -0.45), rotation_deg=0.5, scale=1.01)
    fine = simulate("smoke", tmp_path / "f.h5", size=32, seed=1, fidelity="fine", noise=False)
    lab = simulate("smoke", tmp_path / "l.h5", size=32, seed=1, fidelity="lab", lab_errors=err, noise=False)
    h = fm.true_gs_to_rs(lab.meta["truth_calibration"], lab.gs.frames.shape[1:3])
    assert h[:2, :2] == pytest.approx(1.01 * np.array([[np.cos(np.radians(0.5)), -np.sin(np.radians(0.5))],
                                                       [np.sin(np.radians(0.5)), np.cos(np.radians(0.5))]]))
    registered = build_problem(replace(lab, calibration=replace(lab.calibration, gs_to_rs=h))).b_gs.numpy()
    plain, exact = build_problem(lab).b_gs.numpy(), build_problem(fine).b_gs.numpy()
    inner = (slice(None), slice(None), slice(3, -3), slice(3, -3))

    def rel(a):
        return np.linalg.norm(a[inner] - exact[inner]) / np.linalg.norm(exact[inner])
    assert rel(registered) < 0.04 and rel(plain) > 5 * rel(registered)  # 0.028 and 0.21 (bilinear, then binned)


def test_bad_fidelity_is_one_clear_error(tmp_path):
    with pytest.raises(RngcamError, match="fidelity"):
        simulate("smoke", tmp_path / "x.h5", size=SIZE, fidelity="exact")
    with pytest.raises(RngcamError, match="bayer"):
        simulate("smoke", tmp_path / "x.h5", size=SIZE, fidelity="lab", bayer=True)
    res = CliRunner().invoke(main, ["simulate", "smoke", "-o", str(tmp_path / "y.h5"), "--fidelity", "exact"])
    assert res.exit_code != 0 and "Traceback" not in res.output


def test_cli_fidelity_lab(tmp_path):
    res = CliRunner().invoke(main, ["simulate", "sineball", "-o", str(tmp_path / "s.h5"), "--size", str(SIZE),
                                    "--fidelity", "lab"])
    assert res.exit_code == 0, res.output
    assert read_bundle(tmp_path / "s.h5").meta["fidelity"] == "lab"


def test_binned_psf_is_centred_like_the_binned_frames():
    # A point's own sensor pixel is the PSF's centre pixel (Hp // 2): binned 2x2 that pixel lies in
    # the left/top half of grid pixel h // 2, whose centre is half a sensor pixel further on. The
    # grid PSF puts the point's light in the grid pixel the binned frames put the point in.
    from rngcam.formats.bundle import Bundle, Calibration
    from rngcam.recon.gridding import grid_psf

    raw = np.zeros((1, 32, 32))
    raw[0, 16, 16] = 1.0
    b = Bundle(rs=None, gs=None, calibration=Calibration(psf=raw))
    psf = grid_psf(b, 2, 1)
    assert psf.shape[-2:] == (17, 17)  # one grid pixel past 32 / 2: the outer ring (physics.psf.bin_psf)
    assert np.unravel_index(np.argmax(psf[0]), psf.shape[-2:]) == (8, 8) and psf[0, 8, 8] > 0.99
    # Light one raw pixel left of the centre is half a grid pixel left: split evenly.
    raw[0, 16, 16], raw[0, 16, 15] = 0.0, 1.0
    psf = grid_psf(Bundle(rs=None, gs=None, calibration=Calibration(psf=raw)), 2, 1)
    assert psf[0, 8, 7] == pytest.approx(psf[0, 8, 8], rel=1e-6)


def test_a_psf_handed_over_at_another_scale_is_the_true_one_magnified(tmp_path):
    fine = simulate("sineball", tmp_path / "f.h5", size=SIZE, seed=0, fidelity="fine")
    large = simulate("sineball", tmp_path / "l.h5", size=SIZE, seed=0, fidelity="lab",
                     lab_errors=fm.LabErrors(psf_scale=1.05))
    assert read_bundle(tmp_path / "l.h5").meta["truth_calibration"]["psf_scale"] == 1.05
    true, stored = (np.asarray(b.calibration.psf, np.float64) for b in (fine, large))

    np.testing.assert_allclose(normalise(stored), magnify(true, 1.05), rtol=1e-4, atol=1e-7 * true.max())
    assert np.abs(normalise(stored) - normalise(true)).max() > 0.05 * normalise(true).max()  # a real change
    np.testing.assert_array_equal(large.rs.frames, fine.rs.frames)  # the capture itself is unchanged
