"""STFM preset "auto": the layer test on the key frames picks the prior preset for one translating
object and the fast preset otherwise, and the method says which and why."""

from types import SimpleNamespace

import numpy as np
import pytest
import torch
from test_stfm import scene_problem

from rngcam.errors import ConfigError
from rngcam.recon.methods.stfm import STFMSettings, make_stfm
from rngcam.recon.methods.stfm.auto import choose_preset, layer_misfits
from rngcam.recon.methods.stfm.stage_configs import AutoPresetConfig

LAYER_MISFIT_MAX = AutoPresetConfig().layer_misfit_max
from rngcam.recon.methods.stfm.settings import _preset


def key_frames(kind: str, size: int = 24) -> torch.Tensor:
    """(1, 3, size, size) key frames over a textured background: a square that translates, or a
    disc that grows (something appears: no shift of the middle frame explains the others)."""
    rng = np.random.default_rng(0)
    keys = np.repeat(0.3 + 0.1 * rng.random((1, 1, size, size)), 3, axis=1)
    yy, xx = np.mgrid[0:size, 0:size]
    for g in range(3):
        if kind == "translate":
            x0 = 4 + 6 * g
            keys[0, g, 8:14, x0:x0 + 6] = 0.9
        else:
            keys[0, g][(yy - size / 2) ** 2 + (xx - size / 2) ** 2 < (2 + 3 * g) ** 2] = 0.9
    return torch.from_numpy(keys).float()


def test_a_translating_square_is_one_layer_and_a_growing_disc_is_not():
    moving = layer_misfits(key_frames("translate"))
    growing = layer_misfits(key_frames("grow"))
    assert max(moving) < 0.05  # a shift of the middle frame reproduces both other key frames
    assert min(growing) > LAYER_MISFIT_MAX


def test_large_key_frames_are_tested_binned_to_the_scale_the_threshold_was_set_at():
    """At 256 px the test bins by 4 to 64 px: the same misfits as on key frames binned beforehand,
    and the same verdicts as at the small size."""
    for kind in ("translate", "grow"):
        keys = torch.nn.functional.interpolate(key_frames(kind, 64), scale_factor=4, mode="nearest")
        binned = torch.nn.functional.avg_pool2d(keys[0], 4)[None]
        assert layer_misfits(keys) == pytest.approx(layer_misfits(binned), rel=1e-5)
        mask = torch.ones(256, 256)
        assert layer_misfits(keys, mask) == pytest.approx(layer_misfits(binned), rel=1e-5)
    strip = torch.rand(3, 3, 2, 300, generator=torch.Generator().manual_seed(0))  # thinner than the factor its longer side asks: one row
    assert len(layer_misfits(strip)) == 2 and all(m >= 0 for m in layer_misfits(strip))
    assert max(layer_misfits(torch.nn.functional.interpolate(key_frames("translate", 64), scale_factor=4))) < 0.05
    assert min(layer_misfits(torch.nn.functional.interpolate(key_frames("grow", 64), scale_factor=4))) > LAYER_MISFIT_MAX


@pytest.mark.parametrize("scene, preset", [("sineball", "prior"), ("smoke", "fast")])
def test_auto_picks_prior_for_the_ball_and_fast_for_smoke(scene, preset):
    """At 48 px (at 32 px the ball's first key frame reads 0.54: a 4 px ball's shift search is too
    coarse for the worst key frame to pass)."""
    choice = choose_preset(scene_problem(scene, 48))
    assert choice.preset == preset
    assert len(choice.misfits) == 2
    assert ("explains every key frame" in choice.reason) == (preset == "prior")


def test_every_key_frame_must_be_explained_not_their_mean():
    """The last key frame shows, besides the square one shift on, a bar that entered the frame and that
    no shift of the middle frame's layer makes: its misfit is over the threshold while the first
    key frame's is ~0, so their mean is under it. The worst decides: fast, naming that key frame."""
    keys = key_frames("translate")
    keys[0, 2, 17:20, 1:19] = 0.9
    misfits = layer_misfits(keys)
    assert misfits[0] < 0.05 and misfits[1] > LAYER_MISFIT_MAX and sum(misfits) / 2 < LAYER_MISFIT_MAX
    problem = SimpleNamespace(b_gs=keys, mask=None, gs_images=lambda gains: keys)
    choice = choose_preset(problem)
    assert choice.preset == "fast" and "key frame 2 of 2 others" in choice.reason
    keys[0, 2, 17:20, 1:19] = keys[0, 0, 17:20, 1:19]  # the bar gone: one layer explains both
    assert choose_preset(problem).preset == "prior"


def test_make_stfm_auto_says_what_it_chose_and_why():
    problem = scene_problem("sineball", 16)
    method = make_stfm(problem, STFMSettings(preset="auto", components="all"))
    chosen = method.resolved_settings()["preset_choice"]
    assert chosen["preset"] == method.resolved_settings()["preset"]
    assert any(note.startswith(f"preset auto chose {chosen['preset']}") for note in method.notes)
    assert np.isfinite(float(method.step()))


def test_without_two_key_frames_auto_is_fast_and_the_raw_preset_is_refused():
    problem = scene_problem("sineball", 16, with_gs=False)
    assert choose_preset(problem).preset == "fast"
    with pytest.raises(ConfigError):
        _preset("auto", 16, 16, 16)
