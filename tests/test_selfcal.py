"""Self-calibration: hot/dead pixels found in the data, the GS-to-RS transform and gains refined."""
import numpy as np
import pytest
import torch

from rngcam.recon.defects import outliers
from rngcam.recon.methods import selfcal
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


def test_lab_bundle_defects_are_found_at_the_sensor_resolution_and_filled_before_binning(tmp_path):
    errors = LabErrors(hot_fraction=0.004, dead_fraction=0.002)
    b = simulate("sineball", tmp_path / "l.h5", size=32, seed=1, fidelity="lab", lab_errors=errors)
    clean = build_problem(simulate("sineball", tmp_path / "c.h5", size=32, seed=1, fidelity="fine"))
    p = build_problem(b)  # grid_bin 2: each defect is filled from its neighbours, then binned
    truth = b.meta["truth_calibration"]
    assert p.rs_valid is None and any("RS sensor pixels" in n and "before binning" in n for n in p.notes)
    hot = truth["rs_defects"]["hot"]
    # a hot RS pixel adds 200-1500 DN (0.05-0.37 after 2x2 binning); filled, the grid pixel is the clean one's
    assert max(float((p.b_rs - clean.b_rs)[:, y // 2, x // 2].abs().max()) for y, x in hot) < 0.02
    gs_hot = truth["gs_defects"]["hot"] + truth["gs_defects"]["dead"]
    off = [float((p.b_gs - clean.b_gs)[..., y // 2, x // 2].abs().max()) for y, x in gs_hot]
    assert sum(d < 0.03 for d in off) >= 0.75 * len(off)  # texture and the ball hide a few
    unbinned = build_problem(b, grid_bin=1)  # nothing to fill from: the defects leave the data term
    masked = {tuple(a) for a in np.argwhere(~unbinned.rs_valid.numpy().all(axis=0))}
    defects = {tuple(a) for a in hot + truth["rs_defects"]["dead"]}
    assert defects <= masked and any("left out of the data term" in n and "hot or dead" in n for n in unbinned.notes)


def _static_problem(matrix, gains, size=32):
    """A noiseless problem of a static textured scene whose GS frames see it at `matrix` (GS pixel p
    sees the scene at S(p)) with GS/RS `gains`."""
    from rngcam.physics.psf import lenslet_psf
    from rngcam.physics.timing import GlobalShutterTiming, RollingShutterTiming
    from rngcam.recon.problem import problem_from_video

    rng = np.random.default_rng(3)
    yy, xx = np.mgrid[0:size, 0:size] / size
    scene = np.stack([0.5 + 0.2 * np.sin(2 * np.pi * (3 * xx + 2 * yy) + k) + 0.1 * rng.random((size, size))
                      for k in range(3)])
    lt, exp = 208e-6, 650e-6
    rs = RollingShutterTiming(lt, exp, size)
    last = rs.end_s - exp
    gs = GlobalShutterTiming((0.0, last / 2, last), exp)
    from rngcam.physics.timing import VideoGrid

    k = VideoGrid.covering(rs, gs).n_frames
    video = torch.from_numpy(np.repeat(scene[:, None], k, axis=1))
    psf = torch.from_numpy(np.repeat(lenslet_psf((size, size), 4, 16, 3.0, seed=1), 3, axis=0))
    p = problem_from_video(video, psf, rs, gs)
    seen = selfcal.warp(p.b_gs, matrix) / torch.as_tensor(gains)[:, None, None, None]
    from dataclasses import replace

    return replace(p, b_gs=seen)


def test_key_rows_recover_a_known_shift_rotation_and_gain():
    truth = selfcal.similarity(0.35, -0.25, np.radians(0.4), 1.005)
    gains = np.array([1.03, 0.98, 1.01])  # GS signal / RS signal
    p = _static_problem(truth, gains)
    assert [g for g, _ in selfcal.key_rows(p.rs_weights, p.gs_weights)] == [0, 2]
    r = selfcal.register_key_rows(p, free=4)
    est, want = selfcal.describe(r["matrix"]), selfcal.describe(truth)
    np.testing.assert_allclose(est["shift_px"], want["shift_px"], atol=0.1)
    assert est["rotation_deg"] == pytest.approx(0.4, abs=0.1) and est["scale"] == pytest.approx(1.005, abs=0.002)
    np.testing.assert_allclose(r["gains"], gains, rtol=0.02)  # the gains that take GS to the RS scale
    assert r["rs_residual_after"] < 0.2 * r["rs_residual_before"]


def test_calibrate_problem_applies_what_it_refined_and_reports_it():
    truth = selfcal.similarity(0.35, -0.25, np.radians(0.4), 1.005)
    gains = np.array([1.03, 0.98, 1.01])
    p = _static_problem(truth, gains)
    fixed, report = selfcal.calibrate_problem(p, "all")
    assert report["applied"] and "transform_not_applied" not in report
    assert report["start"]["shift_px"] == [0.0, 0.0] and report["start"]["gains"] == [1.0, 1.0, 1.0]
    # The GS frames are corrected as the true values correct them (away from the border), and
    # that correction takes them to the RS scale and coordinates (up to resampling twice).
    exact = _static_problem(np.eye(3), np.ones(3))
    ideal = selfcal._apply(p, truth, gains)
    inner = (slice(None), slice(None), slice(4, -4), slice(4, -4))
    assert (fixed.b_gs - ideal.b_gs)[inner].norm() / ideal.b_gs[inner].norm() < 0.01
    assert (ideal.b_gs - exact.b_gs)[inner].norm() < 0.6 * (p.b_gs - exact.b_gs)[inner].norm()
    lines = selfcal.report_lines(report)
    assert any(s.startswith("GS-to-RS shift (+0.000, +0.000) -> (+0.") and "scale 1.0000 -> 1.005" in s for s in lines)
    assert any(s.startswith("GS/RS gains 1.000/1.000/1.000 -> 1.0") for s in lines)
    kept, rep = selfcal.calibrate_problem(p, "gains")
    assert rep["transform_not_applied"] == "self_calibrate=gains" and rep["refined"]["shift_px"] == [0.0, 0.0]
    assert selfcal.calibrate_problem(p, "off") == (p, None)


def test_tv3d_self_calibrates_on_request_only():
    from rngcam.recon.methods.tv3d import TV3DSettings, make_tv3d

    gains = np.array([1.03, 0.98, 1.01])
    p = _static_problem(np.eye(3), gains).to(torch.float32)
    m = make_tv3d(p, TV3DSettings(self_calibrate="gains", coarse_to_fine=False))
    np.testing.assert_allclose(m.selfcal_report["refined"]["gains"], gains, rtol=0.02)
    assert any(n.startswith("GS/RS gains 1.000/1.000/1.000 -> 1.03") for n in m.notes)
    plain = make_tv3d(p, TV3DSettings(coarse_to_fine=False))
    assert not hasattr(plain, "selfcal_report")


@pytest.mark.parametrize("dx,dy", [(0.0, 0.0), (0.37, -0.81), (-2.6, 1.25), (7.5, -9.2)])
def test_warp_by_a_shift_is_the_bicubic_warp_values_and_gradients(dx, dy):
    """warp_translate (STFM's learned GS-to-RS shift) reproduces grid_sample's bicubic warp by that
    translation, border clamp included (the last shift reaches past the border), and its gradients."""
    torch.manual_seed(3)
    images = torch.rand(2, 3, 11, 13, dtype=torch.float64)

    def both(path):
        x, d = images.clone().requires_grad_(), torch.tensor([dx, dy], dtype=torch.float64, requires_grad=True)
        out = path(x, d)
        weights = torch.linspace(-1, 1, out.numel(), dtype=torch.float64).view_as(out)
        return out.detach(), torch.autograd.grad((out * weights).sum(), [x, d])

    def by_matrix(x, d):
        one, zero = torch.ones((), dtype=x.dtype), torch.zeros((), dtype=x.dtype)
        m = torch.stack([torch.stack([one, zero, d[0]]), torch.stack([zero, one, d[1]]),
                         torch.stack([zero, zero, one])])
        return selfcal.warp(x, m)

    fast, fast_grads = both(selfcal.warp_translate)
    slow, slow_grads = both(by_matrix)
    assert torch.allclose(fast, slow, atol=1e-10)
    for a, b in zip(fast_grads, slow_grads, strict=True):
        assert torch.allclose(a, b, atol=1e-8)
    if dx == dy == 0:
        assert torch.allclose(fast, images, atol=1e-12)
