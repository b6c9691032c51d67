"""STFM learns the GS-to-RS transform with its fields (settings.learn_geometry): the fields in the
GS camera's coordinates, the RS term and the output through the learned transform."""
from dataclasses import replace

import numpy as np
import pytest
import torch

from rngcam.recon.methods import selfcal
from rngcam.recon.methods.stfm import STFMSettings, make_stfm
from rngcam.recon.methods.stfm.learned import geometry_report
from rngcam.recon.methods.stfm.stage_configs import FitConfig

TRUTH = selfcal.similarity(0.45, -0.3)  # GS pixel p sees the scene at S p


def _fit(problem, steps, **kw):
    kw = {"learn_geometry": "shift", **kw}
    settings = STFMSettings(preset="fast", dynamic_base="none", seed=0, **kw)
    method = make_stfm(problem.to(torch.float32), settings)
    for _ in range(steps):
        method.step()
    return method


def _flat_border_problem(matrix, size=32, taper_px=6):
    """A noiseless static scene, smooth texture fading to a constant over `taper_px` at the borders
    (what the GS frames do not see beyond their edge is then known), its GS frames seeing it at
    `matrix`. At a white texture's or a textured border, the learned shift falls short of the truth
    (0.35 / 0.27 of 0.45 px): no interpolation resamples those exactly."""
    import cv2

    from tests.tiny_scenes import static_scene_problem

    rng = np.random.default_rng(3)
    yy, xx = np.mgrid[0:size, 0:size] / size
    edge = np.minimum.reduce([np.arange(size)[None, :] + 0 * yy, size - 1 - np.arange(size)[None, :] + 0 * yy,
                              np.arange(size)[:, None] + 0 * xx, size - 1 - np.arange(size)[:, None] + 0 * xx])
    fade = np.minimum(1, edge / taper_px)

    def texture():
        t = cv2.GaussianBlur(rng.random((size, size)), (0, 0), 1.5, borderType=cv2.BORDER_REFLECT)
        return (t - t.min()) / (t.max() - t.min())

    scene = np.stack([0.5 + fade * (0.2 * np.sin(2 * np.pi * (3 * xx + 2 * yy) + k) + 0.1 * texture())
                      for k in range(3)])
    p, _ = static_scene_problem(scene)
    return replace(p, b_gs=selfcal.warp(p.b_gs, matrix))


@pytest.fixture(scope="module")
def shifted():
    return _flat_border_problem(TRUTH)


@pytest.fixture(scope="module")
def learned(shifted):
    return _fit(shifted, 300)


def test_the_pose_matrix_is_the_similarity_and_its_inverse_undoes_the_warp():
    pose = torch.tensor([0.4, -0.2, 0.02 * 16, 0.01 * 16], dtype=torch.float64)  # rotation, log scale x radius 16
    m = selfcal.pose_matrix(pose, 16).numpy()
    want = selfcal.similarity(0.4, -0.2, 0.02, float(np.exp(0.01)))
    np.testing.assert_allclose(m, want, atol=1e-12)
    rng = np.random.default_rng(0)
    yy, xx = np.mgrid[0:32, 0:32] / 32
    smooth = torch.from_numpy(np.sin(2 * np.pi * (xx + 0.5 * yy))[None, None] + 0.01 * rng.random((1, 1, 32, 32)))
    back = selfcal.warp(selfcal.warp(smooth, np.linalg.inv(m)), m)
    inner = (..., slice(4, -4), slice(4, -4))
    assert float((back - smooth)[inner].abs().max()) < 0.02
    seen = selfcal.inside(torch.as_tensor(selfcal.similarity(1.5, 0.0)), 32, 32)
    assert float(seen[:, :-2].min()) == 1 and float(seen[:, -1].max()) == 0  # the last column samples outside


def test_a_known_shift_is_learned_with_the_fields(shifted, learned):
    geometry = learned.learned_geometry()
    assert geometry["start"]["shift_px"] == [0.0, 0.0]
    np.testing.assert_allclose(geometry["end"]["shift_px"], [0.45, -0.3], atol=0.07)
    assert geometry["end"]["rotation_deg"] == 0 and geometry["end"]["scale"] == pytest.approx(1, abs=1e-12)  # held
    # the output is in RS coordinates: it matches the truth better than the same fit without the pose
    without = _fit(shifted, 300, learn_geometry="off")
    assert without.learned_geometry() is None and not without.learned_pose.learned

    def error(m):
        inner = (..., slice(4, -4), slice(4, -4))
        return float((m.estimate() - shifted.truth.float())[inner].norm() / shifted.truth.float()[inner].norm())

    assert error(learned) < 0.6 * error(without)
    assert learned.residuals()["rs"] < without.residuals()["rs"]


def test_a_fit_holds_the_pose_it_starts_while_its_fields_settle_and_not_one_it_is_given(shifted):
    fresh = _fit(shifted, FitConfig().pose_hold_steps)
    assert float(fresh.learned_pose.parameter.detach().abs().max()) < 1e-12
    for _ in range(10):
        fresh.step()
    assert float(fresh.learned_pose.parameter.detach()[:2].abs().max()) > 0.02
    given = _fit(shifted, 0)
    given.start_pose(torch.tensor([0.2, 0.0, 0.0, 0.0]))
    for _ in range(10):
        given.step()
    assert float((given.learned_pose.parameter.detach()[:2] - torch.tensor([0.2, 0.0])).abs().max()) > 0.005  # not held


def test_it_is_reported_in_the_settings_the_notes_and_carried_by_a_checkpoint(shifted, learned):
    out = learned.resolved_settings()
    assert out["gs_geometry"]["end"] == learned.learned_geometry()["end"]
    assert any(n.startswith("GS-to-RS transform learned with the fields: shift (+0.") for n in learned.notes)
    state = learned.state_dict()
    fresh = make_stfm(shifted.to(torch.float32), replace(learned.settings))
    assert fresh.learned_geometry()["end"]["shift_px"] == [0.0, 0.0]
    fresh.load_state_dict(state)
    np.testing.assert_allclose(fresh.learned_geometry()["end"]["shift_px"], out["gs_geometry"]["end"]["shift_px"])


def test_a_transform_applied_before_the_fit_is_the_start_of_the_learned_one():
    applied = {"applied": True, "refined": selfcal.describe(selfcal.similarity(0.2, 0.1))}
    pose = torch.tensor([0.1, 0.0, 0.0, 0.0])
    g = geometry_report(pose, 16, applied)
    np.testing.assert_allclose(g["start"]["shift_px"], [0.2, 0.1], atol=1e-9)
    np.testing.assert_allclose(g["end"]["shift_px"], [0.3, 0.1], atol=1e-6)
    kept = {**applied, "transform_not_applied": "self_calibrate=gains"}
    assert geometry_report(pose, 16, kept)["start"]["shift_px"] == [0.0, 0.0]
    assert geometry_report(None, 16, applied) is None


def test_similarity_learns_rotation_and_scale_too(shifted):
    turned = _flat_border_problem(selfcal.similarity(0.3, -0.2, np.radians(0.8), 1.01))
    end = _fit(turned, 300, learn_geometry="similarity").learned_geometry()["end"]
    np.testing.assert_allclose(end["shift_px"], [0.3, -0.2], atol=0.1)
    assert end["rotation_deg"] == pytest.approx(0.8, abs=0.2) and end["scale"] == pytest.approx(1.01, abs=0.004)


def test_no_pose_is_learned_without_both_cameras_or_with_hard_anchoring(shifted):
    for kw in ({"no_gs": True}, {"no_rs": True}, {"gs_anchor": "hard"}):
        method = _fit(shifted, 2, **kw)
        assert not method.learned_pose.learned and method.learned_geometry() is None
        assert float(method.learned_pose.parameter.detach().abs().max()) == 0
