"""bench/realistic.py's robustness table: the misfit cell shows every verdict the runs can give."""

from bench.realistic import _misfit_cell
from rngcam.recon import misfit


def test_the_misfit_cell_shows_each_verdict():
    assert _misfit_cell({}) == "-"
    assert _misfit_cell({"misfit": None}) == "ok"
    not_explained = misfit.verdict(0.0300, 0.0245)["line"]
    assert _misfit_cell({"misfit": not_explained}) == f"{misfit.NOT_EXPLAINED} (1.22x)"
    cut = misfit.verdict(0.0350, 0.0245, ended_by="budget")["line"]
    assert _misfit_cell({"misfit": cut}) == f"{misfit.NOT_FITTED} (1.43x)"
    far = misfit.verdict(0.0250, 0.0245, line_factor=1.0141)["line"]
    assert _misfit_cell({"misfit": far}) == f"{misfit.FAR_OFF} (x1.0141)"
    refit = {"tried": True, "refits": [{"factor": 1.0141}], "kept": 1}
    assert _misfit_cell({"misfit": far, "line_refit": refit}) == (f"{misfit.FAR_OFF} (x1.0141); second fit at "
                                                                   "x1.0141, fit 2 of 2 kept")
    assert _misfit_cell({"misfit": None, "line_refit": {"tried": True, "refits": [], "kept": 0}}) == "ok"


def test_the_table_shows_the_edge_stage_and_rows_without_gs_only_videos():
    from bench.realistic import _psf_cell, report_default

    base = {"psf_scale_estimate": 0.978, "true_psf_scale": 1.05}
    kept = {"tried": True, "refits": [{"scale": 0.9513}], "kept": 1, "scale": 0.9513}
    assert _psf_cell(dict(base, psf_edge=kept)) == "0.978 (0.952); edge fitted at 0.951, fit 2 of 2 kept"
    assert _psf_cell(dict(base, psf_edge={"tried": True, "refits": [], "kept": 0})).endswith("; no edge fitted")
    assert _psf_cell(base) == "0.978 (0.952)"
    made = {"tried": True, "refits": [{"row_gains": True}]}
    assert _psf_cell(dict(base, row_gain_refit=dict(made, kept=1))) == "0.978 (0.952); row-gain run kept"
    assert _psf_cell(dict(base, row_gain_refit=dict(made, kept=0))).endswith("; row-gain run made, plain kept")
    row = dict(base, steps=2140, events=["stopped at iteration 2140: x"], psnr_intermediate_db=35.88,
               psnr_dynamic_db=25.44, misfit=None, load_before=1.4)
    table = report_default({"sineball|psf+3|default|64": row})
    assert "| sineball | psf+3 | 2,140 (own stop) | 35.88 | - | 25.44 | - | - |" in table
