"""STFM's translation search (rngcam.recon.stfm.motion_search): where a GS key frame's misfit goes."""

from __future__ import annotations

import pytest
import torch

from rngcam.recon.stfm.motion_search import centre_weights


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
