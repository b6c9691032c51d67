"""The row-gain refit: where a run through a PSF the key rows found too large ends unexplained, a
second whole run whose motion search scores each RS row after its own gain, kept where it explains
the RS image better; bounded to one; resumable; a tampered checkpoint refused."""

from dataclasses import replace

import pytest
from test_psf_edge import _Fit, _run, _through_checkpoint, problems  # noqa: F401 (the fixture)

from rngcam.errors import RngcamError
from rngcam.recon.methods.stfm.edge_refit import EdgeRefit
from rngcam.recon.methods.stfm.row_gain_refit import RowGainRefit
from rngcam.recon.methods.stfm.stage_configs import StopConfig

NOISE = 0.01


def _refit(first_rs, second_rs):
    made = []

    def another(row_gains, report):
        made.append((row_gains, report))
        return _Fit(second_rs, "second video", noise=NOISE)

    return RowGainRefit(_Fit(first_rs, "first video", noise=NOISE), None, 0.98, another), made


@pytest.mark.parametrize("second_rs, kept", [(0.0125, 1), (0.015, 0)])
def test_a_run_left_unexplained_is_made_again_with_row_gains_and_the_better_one_kept(second_rs, kept):
    method, made = _refit(0.014, second_rs)
    method.step()
    assert method.converged() is None and len(made) == 1 and made[0][0] is True
    assert made[0][1]["refits"][0]["ratio"] == pytest.approx(1.4)
    _run(method)
    assert len(made) == 1 and method.report["kept"] == kept
    assert method.residuals()["rs"] == (0.014, second_rs)[kept]
    assert method.estimate() == ("first video", "second video")[kept]
    line = method.notes[-1]
    assert line.startswith("motion search with row gains (the whole run; the key rows' PSF scale x0.9800; the first run ended at 0.0140, "
                           "1.40x its noise level)")
    assert f"ended at {second_rs:.4f}; the {('first', 'second')[kept]} run kept" in line
    out = method.resolved_settings()
    assert out["row_gain_refits"]["kept"] == kept and out["row_gain_refits"]["row_gains"] is bool(kept)
    assert out["self_calibration"]["row_gain_refit"]["kept"] == kept and out["row_gain_refit"] is True
    from rngcam.recon.result import split_results

    settings, results = split_results(out)  # metrics.json: the stage's report a result, its switch a setting
    assert results["row_gain_refits"]["kept"] == kept and settings["row_gain_refit"] is True


def test_no_second_run_where_the_first_ends_near_its_noise_level():
    method, made = _refit(0.0114, 0.001)  # 1.14x: the plain search kept the ball at 1.09x and 1.12x
    _run(method)
    assert not made and method.report["kept"] == 0
    assert method.notes[-1] == ("motion search with row gains not tried (the whole run; the key rows' PSF scale x0.9800): the first "
                                f"run's RS residual is within {StopConfig.explained_ratio}x its noise level")


def test_a_run_resumed_in_the_second_run_makes_it_again_and_a_tampered_one_is_refused(tmp_path):
    method, _ = _refit(0.014, 0.0125)
    method.step()
    method.converged()
    state = _through_checkpoint(method, tmp_path)
    again, made = _refit(0.014, 0.0125)
    again.load_state_dict(state)
    assert len(made) == 1 and made[0][0] is True and again.residuals()["rs"] == 0.0125
    _run(again)
    assert again.report["kept"] == 1
    for bad in ({"row_gain_made": {1: "import os"}}, {"row_gain_made": {}}, {"row_gain_best": 3}):
        with pytest.raises(RngcamError, match="row-gain refit stage is not as rngcam writes it"):
            _refit(0.014, 0.0125)[0].load_state_dict({**state, **bad})


def test_stfm_is_wrapped_where_the_key_rows_find_the_psf_too_large_and_the_motion_is_searched(problems):  # noqa: F811
    from rngcam.recon.methods.stfm.recipe import make_stfm
    from rngcam.recon.methods.stfm.settings import STFMSettings

    wrong, matched = problems
    settings = STFMSettings(self_calibrate="gains", preset="prior", subframes=1)  # the stages themselves
    method = make_stfm(wrong, settings)
    assert isinstance(method, RowGainRefit) and isinstance(method._fits[0], EdgeRefit)
    assert not method._fits[0].state.row_gain_search
    second = method._make_refit(True, {"refits": [], "kept": 0})
    assert isinstance(second, EdgeRefit)  # the whole run again, its own PSF-edge stage included ...
    assert second.state.row_gain_search and not second.settings.row_gain_refit  # ... never a third run
    assert "motion search: each RS row scored after its own gain" in second.notes
    assert not any("row gain" in n for n in method._fits[0].notes)
    said = [n for n in second.notes if n.startswith("self-calibration")]
    assert said[0].startswith("self-calibration (gains) through the motion search with row gains")
    psf = wrong.psf * 0 + 1 / wrong.psf[0].numel()
    assert not isinstance(second._make_refit(psf, {"scale": 0.95}), RowGainRefit)  # no third run
    through_edge = method._fits[0]._make_refit(psf, {"scale": 0.95})  # the first run's fit through an edge:
    assert isinstance(through_edge, RowGainRefit) and not through_edge._fits[0].state.row_gain_search  # wrapped
    again = through_edge._make_refit(True, {"refits": [], "kept": 0})
    assert again.state.row_gain_search and not isinstance(again, (EdgeRefit, RowGainRefit))  # as one fit
    assert any(n.startswith("self-calibration (gains) through the motion search with row gains and the PSF with "
                            "its lost edge fitted (shrunk x0.9500)") for n in again.notes)
    through_edge.step()
    through_edge._fits[0].converged = lambda: "stalled"  # ends, and (not yet fitted) far above its noise
    assert through_edge.converged() is None and through_edge._current == 1
    assert through_edge.notes[-1].startswith("motion search with row gains (the fit through the PSF with its lost "
                                             f"edge fitted (shrunk x0.9500); the key rows' PSF scale "
                                             f"x{method.report['key_rows_scale']:.4f}; the first run ended at")
    assert not isinstance(make_stfm(matched, settings), RowGainRefit)
    assert not isinstance(make_stfm(wrong, replace(settings, row_gain_refit=False)), RowGainRefit)
    assert not isinstance(make_stfm(wrong, replace(settings, preset="fast")), RowGainRefit)  # motion from flow
