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
