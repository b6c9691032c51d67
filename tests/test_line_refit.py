"""The line-time refit: later whole fits learning the line time on from the factor the best fit so far
learned off where it started, kept where they explain the RS image better; said against the recorded line
time; bounded; resumable."""

from dataclasses import replace
from types import SimpleNamespace

import pytest
import torch
from test_psf_edge import _Fit as _EdgeFit
from test_psf_edge import _through_checkpoint
from test_stfm_line_time import _moving_capture

from rngcam.errors import RngcamError
from rngcam.recon.methods.stfm import STFMSettings, make_stfm
from rngcam.recon.methods.stfm.line_refit import LineRefit
from rngcam.recon.methods.stfm.stage_configs import LineRefitConfig

MAX_LINE_REFITS = LineRefitConfig().max_refits
from rngcam.recon.methods.stfm.line_time import line_time_lines, line_time_report

RECORDED = 1e-4


class _Fit(_EdgeFit):
    """The PSF-edge tests' stand-in for a whole fit (stops after one step at RS residual `rs`), which
    learned a line-time factor `factor` on top of the timing it was given."""

    def __init__(self, rs, factor):
        super().__init__(rs, None, noise=0.0135)  # 0.0143: 1.06x, explained
        self.factor = factor

    def line_factor(self):
        return self.factor


def _refit(first, later):
    """A LineRefit over stand-ins: the first fit (learned factor, RS residual) and the later fits' in turn."""
    made, later = [], list(later)

    def another(factor, report):
        made.append((factor, report))
        learned, rs = later.pop(0)
        return _Fit(rs, learned)

    problem = SimpleNamespace(rs_timing=SimpleNamespace(line_time_s=RECORDED))
    return LineRefit(_Fit(first[1], first[0]), problem, another, {"psf_edge": True}), made


def _run(method, limit=20):
    for _ in range(limit):
        method.step()
        if method.converged():
            return


def test_later_fits_start_where_the_best_fit_learned_the_line_time_until_it_stays_put():
    method, made = _refit((1.015, 0.0143), [(1.012, 0.0130), (1.003, 0.0125)])
    method.step()
    assert method.converged() is None and [m[0] for m in made] == [1.015]
    _run(method)
    assert [m[0] for m in made] == pytest.approx([1.015, 1.015 * 1.012])
    assert [m[1]["refits"][-1]["from_fit"] for m in made] == [0, 1]
    assert method.report["kept"] == 2 and method.residuals()["rs"] == 0.0125
    assert method.report["factor"] == pytest.approx(1.015 * 1.012)  # what the kept fit started from
    assert "within 1 % of where it started (x1.0272)" in method.report["why"]
    assert method.notes[-1].startswith("line time: 2 more fits learning it on from the line time learned before: "
                                       "from x1.0150 (the first fit's, RS residual 0.0143) ended at 0.0130; from "
                                       "x1.0272 (the second fit's, RS residual 0.0130) ended at 0.0125")
    assert method.notes[-1].endswith("the third fit kept")
    assert method.resolved_settings()["line_refits"]["kept"] == 2
    assert method.resolved_settings()["line_refit"] is True


def test_a_later_fit_that_explains_the_rs_image_less_well_ends_the_chain_and_the_best_is_kept():
    method, made = _refit((1.015, 0.0143), [(1.012, 0.0150)])
    _run(method)
    assert len(made) == 1 and method.report["kept"] == 0 and method.residuals()["rs"] == 0.0143
    assert method.report["why"] == "the fit from x1.0150 explained the RS image less well than the first"
    assert method.notes[-1].endswith("the first fit kept")


def test_the_chain_is_bounded():
    later = [(1.015, 0.014 - 0.001 * k) for k in range(MAX_LINE_REFITS + 2)]
    method, made = _refit((1.015, 0.015), later)
    _run(method)
    assert len(made) == MAX_LINE_REFITS and method.report["why"] == f"{MAX_LINE_REFITS} later fits made"
    assert method.report["kept"] == MAX_LINE_REFITS


def test_from_a_fit_that_ended_unexplained_one_later_fit_and_only_where_the_factor_is_far_off():
    method, made = _refit((1.005, 0.0225), [(1.0, 0.0130)])  # 1.67x: another error moved the line time
    _run(method)
    assert made == [] and method.report["why"] == ("the first fit learned the line time at x1.0050, within 0.7 % of "
                                                   "the recorded one, and ended at 1.15x its noise level or more")
    method, made = _refit((1.015, 0.0225), [(1.012, 0.0200), (1.0, 0.0100)])
    _run(method)
    assert [m[0] for m in made] == [1.015] and method.report["kept"] == 1
    assert method.report["why"] == "1 later fit made (the second fit ended at 1.15x its noise level or more)"


@pytest.mark.parametrize("factor, why", [(1.008, "within 1 % of the recorded one"),
                                         (None, "did not learn the line time"), (1.3, "out of range")])
def test_no_later_fit_where_the_line_time_stays_near_the_recorded_one_is_not_learned_or_absurd(factor, why):
    method, made = _refit((factor, 0.0143), [(1.0, 0.001)])
    _run(method)
    assert made == [] and method.report["kept"] == 0 and why in method.report["why"]
    assert not any(n.startswith("line time:") for n in method.notes)


def test_a_run_resumed_in_a_later_fit_makes_it_again_and_a_tampered_factor_is_refused(tmp_path):
    method, made = _refit((1.014, 0.0143), [(1.0, 0.013)])
    method.step()
    method.converged()
    state = _through_checkpoint(method, tmp_path)
    again, made_again = _refit((1.014, 0.0143), [(1.0, 0.013)])
    again.load_state_dict(state)
    assert [m[0] for m in made_again] == [1.014]
    _run(again)
    assert again.report["kept"] == 1
    for bad in ({"line_made": {1: 5.0}}, {"line_made": {1: float("nan")}}, {"line_current": 3}):
        with pytest.raises(RngcamError, match="line-time refit stage is not as rngcam writes it"):
            _refit((1.014, 0.0143), [(1.0, 0.013)])[0].load_state_dict({**state, **bad})


def test_a_fit_started_off_the_recorded_line_time_reports_against_the_recorded_one():
    timing = SimpleNamespace(line_time_s=RECORDED * 1.01)  # a later fit's: the recorded one stretched by 1.01
    report = line_time_report(timing, 1.004, 1.01)
    assert report["factor"] == pytest.approx(1.01 * 1.004) and report["recorded_s"] == pytest.approx(RECORDED)
    assert report["learned_s"] == pytest.approx(RECORDED * 1.01 * 1.004) and report["started_at"] == 1.01
    assert line_time_lines(report, 10) == [
        "RS line time learned with the fields from x1.0100: 101.4040 us per sensor row (x1.0140 the recorded "
        "100.0000 us); the recorded line time looks off: measure it with `rngcam calibrate linetime --flicker`"]
    assert "started_at" not in line_time_report(timing, 1.0)


@pytest.fixture(scope="module")
def slow_readout():
    return _moving_capture(0.97).to(torch.float32)


def test_make_stfm_wraps_where_the_line_time_is_learned_and_a_later_fit_learns_on_from_the_stretched_timing(
        slow_readout):
    def built(**kw):
        return make_stfm(slow_readout, STFMSettings(**{"preset": "fast", "dynamic_base": "none", "seed": 0,
                                                       "learn_line_time": "on", **kw}))

    method = built()
    assert isinstance(method, LineRefit)
    assert not isinstance(built(learn_line_time="off"), LineRefit)
    assert not isinstance(built(line_refit=False), LineRefit)
    assert not isinstance(built(learn_line_time="auto"), LineRefit)  # auto learns it with prior only
    assert not isinstance(make_stfm(replace(slow_readout, rs_timing=None),
                                    STFMSettings(preset="fast", dynamic_base="none", learn_line_time="on")), LineRefit)
    later = method._make_refit(0.98, dict(method.report))
    assert not isinstance(later, LineRefit)  # the first fit's stage makes every later fit
    p = later.problem
    assert p.rs_timing.line_time_s == pytest.approx(0.98 * slow_readout.rs_timing.line_time_s)
    torch.testing.assert_close(p.rs_weights, slow_readout.rs_weights_at(0.98).to(p.rs_weights))
    for _ in range(3):
        later.step()
    learned = later.line_factor()  # on top of 0.98, and reported against the recorded line time
    report = later.resolved_settings()["line_time"]
    assert learned is not None and report["started_at"] == 0.98
    assert report["factor"] == pytest.approx(0.98 * learned)
    assert report["recorded_s"] == pytest.approx(slow_readout.rs_timing.line_time_s)


def test_the_stages_settings_and_their_reports_land_apart_in_metrics():
    from rngcam.recon.result import split_results

    method, _ = _refit((1.014, 0.0143), [(1.0, 0.013)])
    _run(method)
    settings, results = split_results(method.resolved_settings())  # the kept later fit's, with the run's stages
    assert settings["line_refit"] is True and settings["psf_edge"] is True
    assert results["line_refits"]["kept"] == 1 and "line_refit" not in results and "psf_edge" not in results
