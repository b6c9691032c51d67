"""STFM's dynamic bases pinned to a RIFE model ("video_hdv3", "keys_hdv3"): one ensemble member
per RIFE model, each starting exactly at that model's interpolation."""

import numpy as np
import pytest
import torch
from test_stfm import _key_frames, fits, scene_problem, small_settings

from rngcam.errors import ConfigError
from rngcam.recon.methods.stfm import STFMSettings, make_stfm
from rngcam.recon.methods.stfm.bases import _rife_model_of
from rngcam.recon.metrics import psnr


@pytest.fixture(scope="module")
def sineball16():
    return scene_problem("sineball", 16)


def _rife_or_skip(p, model):
    from rngcam.recon.methods.rife import RifeUnavailableError, rife

    try:
        return torch.from_numpy(rife(_key_frames(p), p.gs_times_s, p.frame_times_s, model=model))
    except RifeUnavailableError as exc:
        pytest.skip(f"RIFE {model} weights not installed: {exc}")


def test_the_suffix_names_the_rife_model():
    assert _rife_model_of("video_hdv3") == ("video", "hdv3")
    assert _rife_model_of("keys_hdv3") == ("keys", "hdv3")
    assert _rife_model_of("keys") == ("keys", None)
    STFMSettings(dynamic_base="video,keys,video_hdv3,keys_hdv3")  # valid
    with pytest.raises(ConfigError):
        STFMSettings(dynamic_base="interp_hdv4")


def test_a_video_hdv3_fit_starts_exactly_at_rife_hdv3(sineball16):
    p = sineball16
    hdv3, default = _rife_or_skip(p, "hdv3"), _rife_or_skip(p, None)
    assert psnr(hdv3, default) < 60  # the two models interpolate differently here
    m = make_stfm(p, small_settings(dynamic_base="video_hdv3", no_static=True))
    assert (m.base.source, m.base.model) == ("rife_hdv3", "hdv3")
    assert psnr(m.estimate(), hdv3) > 60


def test_ensemble_keeps_one_member_per_rife_model(sineball16):
    p = sineball16
    _rife_or_skip(p, "hdv3"), _rife_or_skip(p, "4")
    m = make_stfm(p, STFMSettings(components="all", dynamic_base="video,video_hdv3,keys,keys_hdv3", refine=False))
    assert [(f.base.source, f.base.model) for f in fits(m)] == [
        ("rife", "4"), ("rife_hdv3", "hdv3"), ("keys_rife", "4"), ("keys_rife_hdv3", "hdv3")]
    starts = [f.estimate() for f in fits(m)]
    assert psnr(starts[0], starts[1]) < 60 and psnr(starts[2], starts[3]) < 60
    assert torch.allclose(m.estimate(), torch.stack(starts).mean(0), atol=1e-6)


def test_without_hdv3_weights_the_pinned_member_falls_back_to_interpolation(sineball16, monkeypatch):
    from rngcam.recon.methods import rife as rife_mod

    _rife_or_skip(sineball16, "4")

    def no_hdv3():
        raise rife_mod.RifeUnavailableError("HDv3 not installed (test)")

    monkeypatch.setattr(rife_mod, "find_weights", no_hdv3)
    m = make_stfm(sineball16, STFMSettings(components="all", dynamic_base="video,video_hdv3", refine=False))
    assert [(f.base.source, f.base.model) for f in fits(m)] == [("rife", "4"), ("interp", None)]
    assert np.isfinite(m.estimate().numpy()).all()


def test_rife_runs_where_the_fit_runs(monkeypatch, sineball16):
    """A fit on a GPU runs RIFE's network there; a CPU fit on the CPU."""
    from rngcam.recon.methods import rife as rife_mod
    from rngcam.recon.methods.stfm.bases import _base_video, _network_device

    assert _network_device(torch.device("cuda", 1)) == "cuda:1"
    assert _network_device(torch.device("cpu")) == "cpu"
    seen = []

    def fake_rife(frames, gs_times_s, frame_times_s, model=None, device="cpu"):
        seen.append(device)
        return np.zeros((frames.shape[0], len(frame_times_s), *frames.shape[-2:]), np.float32)

    monkeypatch.setattr(rife_mod, "rife", fake_rife)
    p = sineball16
    video, source, why = _base_video(torch.from_numpy(_key_frames(p)), p.gs_times_s, p.frame_times_s, "video",
                                     device="cuda:1")
    assert seen == ["cuda:1"] and source == "rife" and why == "" and video.shape[1] == len(p.frame_times_s)
    make_stfm(p, small_settings(dynamic_base="video"))  # a CPU fit
    assert seen[1:] == ["cpu"]
