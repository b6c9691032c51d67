"""A finished fit lets go of what only its steps need (Method.end_fit) through every wrapper, and still
gives its video, components and reports."""

import gc

import numpy as np
import pytest
import torch
from test_stfm import scene_problem

from rngcam.recon.loop import LoopSettings, run
from rngcam.recon.methods.stfm.recipe import make_stfm
from rngcam.recon.methods.stfm.settings import STFMSettings


@pytest.fixture(scope="module")
def sineball16():
    return scene_problem("sineball", 16)


def _optimisers() -> list:
    gc.collect()
    return [o for o in gc.get_objects() if issubclass(type(o), torch.optim.Optimizer)]  # FlatAdam is one


@pytest.mark.parametrize("settings", [
    dict(preset="prior", fits=1, start_floor=True),  # the floor around one fit
    dict(preset="fast", fits=2, refine=False, start_floor=True),  # an ensemble's members
], ids=["one fit", "ensemble"])
def test_end_fit_lets_every_optimiser_go_and_keeps_the_outputs(sineball16, settings):
    method = make_stfm(sineball16, STFMSettings(seed=0, **settings))
    run(method, LoopSettings(max_iters=4, log_every_s=1e9))
    assert _optimisers(), "the fit's optimisers should be alive while it can step"
    video = method.estimate().detach().clone()
    parts = {k: np.array(v) for k, v in method.components().items()}
    method.end_fit()
    assert _optimisers() == []  # their gradients and moments went with them
    assert torch.allclose(method.estimate(), video, atol=1e-6)  # made again from the same (averaged) weights
    for key, value in method.components().items():
        assert np.allclose(value, parts[key], atol=1e-6), key
    assert method.resolved_settings()  # the reports read the fields, not the optimiser
    assert isinstance(method.notes, list)


def test_coarse_to_fine_ends_the_level_it_is_on():
    from test_grid_shapes import _toy_problem

    from rngcam.recon.methods.coarse_to_fine import CoarseToFine
    from rngcam.recon.methods.tv3d import TV3D, TV3DSettings

    ended = []

    class Recorded(TV3D):
        def end_fit(self):
            ended.append(self)

    p = _toy_problem().to(torch.float32)
    m = CoarseToFine(p, lambda q, x0: Recorded(q, TV3DSettings(), x0=x0), (2, 1), max_level_steps=3)
    run(m, LoopSettings(max_iters=2))  # still on the coarse level
    m.end_fit()
    assert ended == [m.method]
