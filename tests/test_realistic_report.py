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
    shifted = misfit.verdict(0.0250, 0.0245, line_factor=1.0141, learned_shift_px=0.62)["line"]
    assert _misfit_cell({"misfit": shifted}) == f"{misfit.FAR_OFF} (x1.0141; 0.62 px)"
    refit = {"tried": True, "refits": [{"factor": 1.0141}, {"factor": 1.0190}], "kept": 1}
    assert _misfit_cell({"misfit": far, "line_refit": refit}) == (f"{misfit.FAR_OFF} (x1.0141); later fits from "
                                                                   "x1.0141, x1.0190, fit 2 of 3 kept")
    assert _misfit_cell({"misfit": None, "line_refit": {"tried": True, "refits": [], "kept": 0}}) == "ok"
    track = {"tried": True, "refits": [{"turn_scale": 0.5}]}
    assert _misfit_cell({"misfit": None, "track_refit": dict(track, kept=1)}) == "ok; run from a softer search kept"
    assert _misfit_cell({"misfit": not_explained, "track_refit": dict(track, kept=0)}) == (
        f"{misfit.NOT_EXPLAINED} (1.22x); run from a softer search made, first kept")


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


def test_the_seeds_table_pairs_each_seeds_lab_capture_with_its_fine_one():
    from bench.realistic import _seed_of, report_seeds

    def run(db, ball=None):
        return {"psnr_intermediate_db": db} | ({} if ball is None else
                                               {"centroid_error_median_px": ball[0], "centroid_error_p90_px": ball[1]})
    results = {"smoke|fine|default|64": run(28.75), "smoke|all|default|64": run(27.89),
               "smoke|fine|default|64|s1": run(27.00), "smoke|all|default|64|s1": run(27.40),
               "smoke|fine|default|64|s2": run(26.00),  # no lab capture of seed 2: no row
               "smoke|fine|stfm|gains|64|s1": run(20.0),  # another method: not in this table
               "sineball|fine|default|64|s3": run(33.60, (0.69, 2.38)), "sineball|all|default|64|s3": run(31.40, (0.92, 3.88))}
    assert (_seed_of("smoke|fine|default|64|s12"), _seed_of("smoke|fine|default|64")) == (12, 0)
    table = report_seeds(results).splitlines()
    assert "| smoke | 0 | 28.75 | 27.89 | -0.86 | - |" in table
    assert "| smoke | 1 | 27.00 | 27.40 | +0.40 | - |" in table
    assert "| sineball | 3 | 33.60 | 31.40 | -2.20 | 0.69 / 2.38; 0.92 / 3.88 |" in table
    assert "| smoke | mean of 2 | | | -0.23 (-0.86 to +0.40) | |" in table
    assert not any("| 2 |" in row for row in table)
    results["smoke|calibrated|default|64|s1"] = run(26.90)  # the calibrated family's table: its own rows
    calibrated = report_seeds(results, family="calibrated").splitlines()
    assert "| smoke | 1 | 27.00 | 26.90 | -0.10 | - |" in calibrated and "calibrated - fine" in calibrated[0]
    assert not any("| 0 |" in row for row in calibrated)


def test_the_true_geometry_variant_registers_the_gs_frames_by_the_truth(tmp_path):
    from bench.realistic import true_geometry
    from rngcam.recon.problem import build_problem
    from rngcam.sim.fidelity import LabErrors
    from rngcam.sim.simulate import simulate

    b = simulate("smoke", tmp_path / "l.h5", size=16, seed=2, fidelity="lab", lab_errors=LabErrors(shift_px=(0.5, 0.5)))
    found = true_geometry(b)
    assert found["truth_cal"]["shift_px"] == [0.0, 0.0] and found["truth_cal"]["scale"] == 1.0
    plain = build_problem(b).b_gs
    assert found["p"].b_gs.shape == plain.shape and not found["p"].b_gs.allclose(plain, rtol=0.01)
