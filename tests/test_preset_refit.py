"""The preset refit: where the self-check gave the prior preset's run way (its output is the GS-only video),
a second whole run with the fast preset, kept where its output explains the RS image better; one at most;
resumable; a tampered checkpoint refused; the stage only in a prior-preset run with a self-check."""

from dataclasses import replace

import pytest
from test_psf_edge import _Fit, _run, _through_checkpoint, problems  # noqa: F401 (the fixture)

from rngcam.errors import RngcamError
from rngcam.recon.methods.stfm.preset_refit import PresetRefit, gave_way


class _Checked(_Fit):
    """A whole run whose self-check kept its fit or gave way (`gave_way`)."""

    def __init__(self, residual, video, gave_way):
        super().__init__(residual, video)
        self.gave_way = gave_way

    def resolved_settings(self):
        return {"self_calibration": {"mode": "gains"},
                "start_floor": {"video": "blend", "output_is_start": self.gave_way}}


def _refit(first_gave_way, first_rs=0.18, second_rs=0.16):
    made = []

    def another(preset, report):
        made.append((preset, report))
        return _Checked(second_rs, "fast video", False)

    return PresetRefit(_Checked(first_rs, "blend video", first_gave_way), None, another), made


@pytest.mark.parametrize("second_rs, kept", [(0.16, 1), (0.2, 0)])
def test_a_run_the_self_check_gave_way_is_made_again_with_the_fast_preset_and_the_better_one_kept(second_rs, kept):
    method, made = _refit(True, second_rs=second_rs)
    method.step()
    assert method.converged() is None and [m[0] for m in made] == ["fast"]
    _run(method)
    assert len(made) == 1 and method.report["kept"] == kept
    assert method.estimate() == ("blend video", "fast video")[kept]
    line = method.notes[-1]
    assert line.startswith("preset refit: the self-check gave the prior preset's run way (its fit ended at RS "
                           "residual 0.1800, worse than the GS-only video); a second run with the fast preset: its "
                           f"fit ended at {second_rs:.4f}")
    assert line.endswith(f"the {('first', 'second')[kept]} run kept")
    from rngcam.recon.result import split_results

    settings, results = split_results(method.resolved_settings())
    assert results["preset_refits"]["kept"] == kept and results["preset_refits"]["preset"] == ("prior", "fast")[kept]
    assert settings["preset_refit"] is True
    # the output's results are the kept run's: where that is the second, what the first found stays in the report
    first_found = results["preset_refits"].get("first_fit_found")
    if kept:
        assert first_found == {"start_floor": {"video": "blend", "output_is_start": True}}
        assert results["start_floor"]["output_is_start"] is False  # the kept run's own
    else:
        assert first_found is None


def test_no_second_run_where_the_self_check_kept_the_fit():
    method, made = _refit(False)
    _run(method)
    assert not made and method.report["kept"] == 0 and method.notes == ["a note"]
    assert method.report["why"] == "the self-check kept the prior preset's fit"
    assert gave_way(_Checked(0.1, "v", True)) and not gave_way(_Fit(0.1, "v"))  # no self-check: nothing gave way


def test_a_run_resumed_in_the_second_run_makes_it_again_and_a_tampered_one_is_refused(tmp_path):
    method, _ = _refit(True)
    method.step()
    method.converged()
    state = _through_checkpoint(method, tmp_path)
    again, made = _refit(True)
    again.load_state_dict(state)
    assert [m[0] for m in made] == ["fast"] and again.residuals()["rs"] == 0.16
    _run(again)
    assert again.report["kept"] == 1
    for bad in ({"preset_made": {1: "prior"}}, {"preset_made": {1: "import os"}}, {"preset_made": {}}):
        with pytest.raises(RngcamError, match="preset refit stage is not as rngcam writes it"):
            _refit(True)[0].load_state_dict({**state, **bad})


def test_the_stage_wraps_a_prior_preset_run_with_a_self_check_only(problems):  # noqa: F811
    from rngcam.recon.methods.stfm.recipe import make_stfm
    from rngcam.recon.methods.stfm.settings import STFMSettings

    _, matched = problems
    settings = STFMSettings(self_calibrate="gains", preset="prior", subframes=1, start_floor=True, fits=1,
                            track_refit=False)
    method = make_stfm(matched, settings)
    assert isinstance(method, PresetRefit)
    second = method._make_refit("fast", {"refits": [], "kept": 0})
    assert not isinstance(second, PresetRefit)  # the whole run again, never a third
    assert second.resolved_settings()["preset"] == "fast" and "start_floor" in second.resolved_settings()
    for off in ({"preset_refit": False}, {"start_floor": False}, {"preset": "fast"}):
        assert not isinstance(make_stfm(matched, replace(settings, **off)), PresetRefit)
