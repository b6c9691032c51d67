"""STFM's translation search (rngcam.recon.methods.stfm.motion_search): where a GS key frame's misfit goes."""

from __future__ import annotations

import pytest
import torch

from rngcam.recon.methods.stfm.motion_search import centre_weights


def test_centre_weights_put_each_key_frame_at_its_exposure_centre():
    w = centre_weights([1.25, 32.5, 9.0], 10 + 30)
    assert torch.allclose(w.sum(1), torch.ones(3))
    centres = (w * torch.arange(w.shape[1])).sum(1)
    assert centres.tolist() == pytest.approx([1.25, 32.5, 9.0])
    assert int((w > 0).sum()) == 2 + 2 + 1  # two frames around a fractional centre, one for a whole one


def test_centre_weights_clamp_centres_outside_the_video():
    w = centre_weights([-0.4, 7.8], 5)
    assert w[0, 0] == 1 and w[1, 4] == 1
    assert torch.allclose(w.sum(1), torch.ones(2))


def _sineball(h=32, w=32):
    from rngcam.recon.problem import problem_from_video
    from rngcam.sim.scenes import render_scene
    from rngcam.sim.simulate import prepare_simulation_psf, simulation_timing

    timing = simulation_timing((h, w))
    video = torch.from_numpy(render_scene("sineball", timing.grid, (h, w), 0)).double()
    psf = prepare_simulation_psf(None, (h, w), (h, w), 0.25).grid
    return problem_from_video(video, torch.from_numpy(psf), timing.rs, timing.gs).to(torch.float32)


def _matte(m) -> float:
    from rngcam.recon.methods.stfm.fields import field_on_grid

    with torch.no_grad():
        raw = field_on_grid(m.model.fields["dynamic"], [m.grid.xs, m.grid.ys])
        return float((1 - torch.sigmoid(raw[..., m.C])).mean())


def test_matte_l1_shrinks_the_moving_layer_to_what_the_data_need():
    from rngcam.recon.methods.stfm import STFMSettings, make_stfm

    p = _sineball()
    plain = make_stfm(p, STFMSettings(preset="prior", matte_l1=0.0, components="all", fits=1))
    sparse = make_stfm(p, STFMSettings(preset="prior", components="all", fits=1))  # the preset's matte_l1
    assert sparse.resolved.matte_l1 > 0 and plain.loss.full_objective()["matte"] == 0.0
    start = _matte(sparse)
    assert sparse.loss.full_objective()["matte"] == pytest.approx(sparse.resolved.matte_l1 * start, rel=1e-4)
    for _ in range(150):
        plain.step()
        sparse.step()
    assert _matte(sparse) < 0.8 * _matte(plain)  # the blurred key frame's wide matte is trimmed
    assert torch.isfinite(sparse.estimate()).all()


def test_matte_l1_is_left_out_where_there_is_no_canonical_image():
    from rngcam.errors import ConfigError
    from rngcam.recon.methods.stfm import STFM, STFMSettings

    p = _sineball(16, 16)
    fast = STFM(p, STFMSettings(dynamic_base="blend", matte_l1=1.0))  # time-dependent dynamic field
    assert fast.loss.full_objective()["matte"] == 0.0
    with pytest.raises(ConfigError):
        STFMSettings(matte_l1=-1.0)
