"""The track refit: where a run whose motion came from the translation search ends unexplained, a
second whole run from a search with half the turn penalty, kept where it explains the RS image
better; bounded to one; resumable; a tampered checkpoint refused; the search's penalty scaled."""

from dataclasses import replace

import pytest
from test_psf_edge import _Fit, _run, _through_checkpoint, problems  # noqa: F401 (the fixture)

from rngcam.errors import RngcamError
from rngcam.recon.methods.stfm import motion_search
from rngcam.recon.methods.stfm.edge_refit import EdgeRefit
from rngcam.recon.methods.stfm.row_gain_refit import RowGainRefit
from rngcam.recon.methods.stfm.run_state import RunState
from rngcam.recon.methods.stfm.stage_configs import StopConfig, TrackRefitConfig
from rngcam.recon.methods.stfm.track_refit import TrackRefit

NOISE = 0.01


def _refit(first_rs, second_rs):
    made = []

    def another(scale, report):
        made.append((scale, report))
        return _Fit(second_rs, "second video", noise=NOISE)

    return TrackRefit(_Fit(first_rs, "first video", noise=NOISE), None, another), made


@pytest.mark.parametrize("second_rs, kept", [(0.0102, 1), (0.015, 0)])
def test_a_run_left_unexplained_is_made_again_with_a_smaller_turn_penalty_and_the_better_one_kept(second_rs, kept):
    method, made = _refit(0.0143, second_rs)
    method.step()
    assert method.converged() is None and len(made) == 1 and made[0][0] == TrackRefitConfig().turn_scale
    assert made[0][1]["refits"][0]["ratio"] == pytest.approx(1.43)
    _run(method)
    assert len(made) == 1 and method.report["kept"] == kept
    assert method.residuals()["rs"] == (0.0143, second_rs)[kept]
    assert method.estimate() == ("first video", "second video")[kept]
    line = method.notes[-1]
    assert line.startswith("motion search with a smaller turn penalty (the first run ended at 0.0143, 1.43x its "
                           "noise level): a second run, the search's turn penalty x0.5")
    assert f"ended at {second_rs:.4f}; the {('first', 'second')[kept]} run kept" in line
    out = method.resolved_settings()
    assert out["track_refits"]["kept"] == kept and out["track_refits"]["turn_scale"] == (1.0, 0.5)[kept]
    from rngcam.recon.result import split_results

    settings, results = split_results(out)  # metrics.json: the stage's report a result, its switch a setting
    assert results["track_refits"]["kept"] == kept and settings["track_refit"] is True


def test_no_second_run_where_the_first_ends_near_its_noise_level():
    method, made = _refit(0.0114, 0.001)  # 1.14x: kept balls ended at 1.0x-1.13x
    _run(method)
    assert not made and method.report["kept"] == 0
    assert method.notes == ["a note"]  # nothing said where nothing was made
    assert method.report["why"] == f"the first run's RS residual is within {StopConfig.explained_ratio}x its noise level"
    assert method.resolved_settings()["track_refits"]["refits"] == []


class _Members:
    """A run whose fits (an ensemble's members) started from searched tracks."""

    def __init__(self, tracks):
        self.members = [type("Member", (), {"motion_track_px": t})() for t in tracks]


@pytest.mark.parametrize("moved", [False, True])
def test_a_second_run_from_the_first_runs_very_tracks_is_built_but_not_run(moved):
    """The softer search found the same tracks for every fit: the second run would repeat the first
    step for step, so it is not run; a track moved anywhere: it is."""
    import torch

    tracks = [torch.tensor([[0.0, 1.0], [2.0, 3.0]]), torch.tensor([[0.5, 1.0], [2.0, 4.0]])]
    again = [t.clone() for t in tracks]
    if moved:
        again[1][1, 0] += 1.0
    first = _Fit(0.0143, "first video", noise=NOISE)
    first.members = _Members(tracks).members
    made = []

    def another(scale, report):
        made.append(scale)
        fit = _Fit(0.0102, "second video", noise=NOISE)
        fit.members = _Members(again).members
        return fit

    method = TrackRefit(first, None, another)
    _run(method)
    assert len(made) == 1  # built: the search is part of the build
    if moved:
        assert method.report["kept"] == 1 and method.estimate() == "second video"
        return
    assert method.report["refits"] == [] and method.report["kept"] == 0
    assert method.report["why"].endswith("a second run would repeat it")
    assert method.estimate() == "first video" and method.notes == ["a note"]


def test_a_run_resumed_in_the_second_run_makes_it_again_and_a_tampered_one_is_refused(tmp_path):
    method, _ = _refit(0.0143, 0.0102)
    method.step()
    method.converged()
    state = _through_checkpoint(method, tmp_path)
    again, made = _refit(0.0143, 0.0102)
    again.load_state_dict(state)
    assert len(made) == 1 and made[0][0] == TrackRefitConfig().turn_scale and again.residuals()["rs"] == 0.0102
    _run(again)
    assert again.report["kept"] == 1
    for bad in ({"track_made": {1: 0.0}}, {"track_made": {1: "import os"}}, {"track_made": {}}, {"track_best": 3}):
        with pytest.raises(RngcamError, match="track refit stage is not as rngcam writes it"):
            _refit(0.0143, 0.0102)[0].load_state_dict({**state, **bad})


def test_stfm_is_wrapped_where_the_motion_is_searched_and_the_row_gain_stage_does_not_apply(problems):  # noqa: F811
    from rngcam.recon.methods.stfm.recipe import make_stfm
    from rngcam.recon.methods.stfm.settings import STFMSettings

    wrong, matched = problems
    settings = STFMSettings(self_calibrate="gains", preset="prior", subframes=1)  # the stages themselves
    method = make_stfm(matched, settings)
    assert isinstance(method, TrackRefit) and method._fits[0].state.search_turn_scale == 1
    second = method._make_refit(TrackRefitConfig().turn_scale, {"refits": [], "kept": 0})
    assert not isinstance(second, TrackRefit)  # the whole run again, never a third
    assert second.state.search_turn_scale == 0.5 and not second.settings.track_refit
    assert not second.settings.preset_refit  # a later fit of a stage: the preset refit wraps the whole run only
    assert "motion search: turn penalty x0.5" in second.notes
    assert not any("turn penalty" in n for n in method._fits[0].notes)
    said = [n for n in second.notes if n.startswith("self-calibration")]
    assert said[0].startswith("self-calibration (gains) through the motion search with its turn penalty x0.5")
    assert isinstance(make_stfm(wrong, settings), RowGainRefit)  # a PSF found too large: that stage instead
    wrapped = make_stfm(wrong, replace(settings, row_gain_refit=False))
    assert isinstance(wrapped, TrackRefit) and isinstance(wrapped._fits[0], EdgeRefit)
    psf = wrong.psf * 0 + 1 / wrong.psf[0].numel()
    assert not isinstance(wrapped._fits[0]._make_refit(psf, {"scale": 0.95}), TrackRefit)  # a later fit: not wrapped
    assert not isinstance(make_stfm(matched, replace(settings, track_refit=False)), TrackRefit)
    assert not isinstance(make_stfm(matched, replace(settings, preset="fast")), TrackRefit)  # motion from flow


def test_the_search_charges_turns_by_the_runs_scale(problems, monkeypatch):  # noqa: F811
    from rngcam.recon.methods.stfm.recipe import make_stfm
    from rngcam.recon.methods.stfm.settings import STFMSettings

    _, matched = problems
    turns = []
    viterbi = motion_search._viterbi
    monkeypatch.setattr(motion_search, "_viterbi", lambda cost, move, turn, speed: turns.append(turn) or
                        viterbi(cost, move, turn, speed))
    for scale in (1.0, 0.5):
        make_stfm(matched, STFMSettings(preset="prior", track_refit=False, fits=1), state=RunState(search_turn_scale=scale))
    assert len(turns) == 2 and turns[1] == pytest.approx(0.5 * turns[0]) and turns[0] > 0
