"""`rngcam bench --stress`: a representative subset of the matrix, and the harness itself
(it must call NaN output, crashes, broken promises and accepted bad input FAILED)."""

from __future__ import annotations

import csv
import math

import numpy as np
import pytest
import torch
from click.testing import CliRunner

from rngcam.cli import main
from rngcam.errors import ConfigError, RngcamError
from rngcam.evaluate import stress
from rngcam.evaluate.stress import (
    StressSettings,
    check_operators,
    classify,
    monotone,
    run_case,
    run_stress,
)
from rngcam.evaluate.stress_cases import BASE, StressCase, stress_cases
from rngcam.evaluate.synthetic import CaptureSpec, make_problem

SHORT = StressSettings(tv3d_iters=6, tv3d_exact_iters=2, stfm_iters=2, time_cap_s=10.0)

# One or two of every group: parameters at their extremes, PSF, timing, data (Problem and
# bundle, valid and invalid) and sizes (incl. 1 frame and > 1000 frames).
SUBSET = {
    "beta=0": ("tv3d-haar",),
    "beta=1e+06": ("tv3d-haar", "stfm-fast"),
    "psi=0": ("tv3d-haar",),
    "psi=1000": ("tv3d-haar", "stfm-fast"),
    "tau=1e+06": ("tv3d-haar",),
    "gs_anchor=hard": ("tv3d-haar",),
    "tau=nan": ("tv3d-haar", "stfm-fast"),
    "psf=delta": ("tv3d-haar",),
    "psf=flat": ("tv3d-haar",),
    "rs exposure 0.3 line": ("tv3d-haar", "blend", "interp"),
    "rs exposure 3x readout": ("tv3d-haar", "blend"),
    "very bright (x1e6)": ("tv3d-haar", "interp"),
    "NaN in b_rs (Problem)": ("tv3d-haar", "stfm-fast"),
    "bundle dark (read noise)": ("tv3d-haar", "stfm-fast", "interp"),
    "bundle saturated": ("tv3d-haar", "blend"),
    "bundle NaN in RS frame": ("tv3d-haar", "blend"),
    "bundle Inf in GS frame": ("interp",),
    "bundle NaN in PSF": ("blend",),
    "tiny 1x1": ("tv3d-haar", "tv3d-exact", "blend", "interp", "stfm-fast"),
    "odd 7x9": ("tv3d-exact", "rife"),
    "non-square 5x16": ("tv3d-haar", "interp"),
    "1 frame": ("tv3d-haar", "blend", "stfm-fast"),
    "1203 frames (4x4)": ("tv3d-haar", "blend"),
    "12-bit declared, values x16": ("blend",),
    "GS frame 2 saturated": ("tv3d-haar", "blend"),
    "RS all 0 DN (below black)": ("tv3d-haar",),
    "RS line time 0.1 ns": ("tv3d-haar",),
    "GS frame 2 bottom quarter 0 DN": ("tv3d-haar",),
}
AVAILABLE = set(stress.available_methods())


def _planned() -> set[tuple[str, str]]:
    return {(c, m) for c, ms in SUBSET.items() for m in ms if m in AVAILABLE}


@pytest.fixture(scope="module")
def subset_rows(tmp_path_factory):
    out = tmp_path_factory.mktemp("stress")
    by_name = {c.name: c for c in stress_cases()}
    rows = []
    for name, methods in SUBSET.items():
        rows += run_case(by_name[name], [m for m in methods if m in AVAILABLE], SHORT, out)
    return rows


def test_subset_covers_every_group():
    groups = {c.group for c in stress_cases() if c.name in SUBSET}
    assert groups == {c.group for c in stress_cases()} - {"reference"}


def test_subset_has_no_failures_and_the_expected_outcomes(subset_rows):
    failed = [(r["case"], r["method"], r["message"]) for r in subset_rows if r["outcome"] == "FAILED"]
    assert not failed
    for r in subset_rows:
        assert r["outcome"] == ("rejected" if r["expect"] == "reject" else "finite"), r
    ran = {(r["case"], r["method"]) for r in subset_rows}
    assert ran >= _planned()


def test_operator_rows_pass_the_adjoint_and_precision_checks(subset_rows):
    ops = [r for r in subset_rows if r["method"] == "operators" and r["outcome"] == "finite"]
    assert len(ops) >= 12
    assert all(r["adjoint_err"] <= stress.ADJOINT_TOL and r["fp32_diff"] <= stress.FP32_TOL for r in ops)


def test_tv3d_objective_is_monotone_in_every_case(subset_rows):
    tv = [r for r in subset_rows if r["method"].startswith("tv3d") and r["outcome"] == "finite"]
    assert tv and all(r["monotone"] for r in tv)


def test_bad_input_is_refused_by_name(subset_rows):
    msgs = {(r["case"], r["method"]): r["message"] for r in subset_rows}
    assert "RS frames" in msgs[("bundle NaN in RS frame", "blend")]
    assert "GS frames" in msgs[("bundle Inf in GS frame", "interp")]
    assert "psf" in msgs[("bundle NaN in PSF", "blend")]
    assert "tau" in msgs[("tau=nan", "tv3d-haar")]


# ----------------------------------------------------------------------------- the harness can fail


def test_nan_output_is_failed():
    row = classify("valid", "blend", lambda: {"video": torch.tensor([1.0, math.nan]), "iterations": 1,
                                              "objectives": [], "status": "ok"}, (RngcamError,))
    assert row["outcome"] == "FAILED" and "non-finite" in row["message"]


def test_crash_is_failed_and_says_where():
    def crash():
        raise IndexError("boom")

    row = classify("valid", "blend", crash, (RngcamError,))
    assert row["outcome"] == "FAILED" and "IndexError" in row["message"] and "test_bench_stress.py" in row["message"]


def test_refusing_valid_input_and_accepting_invalid_input_are_failed():
    def refuse():
        raise ConfigError("no")

    def accept():
        return {"video": torch.zeros(3), "iterations": 1, "objectives": [], "status": "ok"}

    assert classify("valid", "tv3d-haar", refuse, (RngcamError,))["outcome"] == "FAILED"
    assert classify("reject", "tv3d-haar", refuse, (RngcamError,))["outcome"] == "rejected"
    assert classify("reject", "tv3d-haar", accept, (RngcamError,))["outcome"] == "FAILED"


def test_a_traceback_error_is_not_a_clear_refusal_through_a_bundle():
    def value_error():
        raise ValueError("DN frame contains NaN or Inf")

    assert classify("reject", "blend", value_error, (RngcamError,))["outcome"] == "FAILED"
    assert classify("reject", "blend", value_error, (RngcamError, ValueError))["outcome"] == "rejected"


def test_rising_tv3d_objective_is_failed():
    ok, worst = monotone([float("nan"), 3.0, 2.0, 2.0, 1.5])
    assert ok and worst == 0.0
    ok, worst = monotone([3.0, 2.0, 2.5])
    assert not ok and worst == pytest.approx(0.25)
    row = classify("valid", "tv3d-haar", lambda: {"video": torch.zeros(2), "iterations": 3,
                                                  "objectives": [3.0, 2.0, 2.5], "status": "ok"}, (RngcamError,))
    assert row["outcome"] == "FAILED" and "rose" in row["message"]


def test_broken_adjoint_is_caught(monkeypatch):
    problem = make_problem(CaptureSpec(height=6, width=5, exposure_lines=2.0))
    assert check_operators(problem)["adjoint_err"] < 1e-12
    original = stress.Problem.gs_op

    def skewed(self):
        op = original(self)
        op.A_adjoint = lambda b, _f=op.A_adjoint: 1.01 * _f(b)
        return op

    monkeypatch.setattr(stress.Problem, "gs_op", skewed)
    row = stress.operator_row(problem)
    assert row["outcome"] == "FAILED" and "adjoint" in row["message"]


def test_a_method_that_returns_nan_is_reported_failed_in_the_table(tmp_path, monkeypatch):
    def nan_blend(gs, gs_times_s, frame_times_s):
        out = np.asarray(gs)[:, :1].repeat(len(frame_times_s), axis=1).copy()
        out[0, 0, 0, 0] = np.nan
        return out

    monkeypatch.setattr("rngcam.recon.methods.baselines.blend", nan_blend)
    rows = run_stress(tmp_path, SHORT, [StressCase("odd", "size", BASE.with_(height=7, width=9))], ["blend"],
                      echo=lambda _m: None)
    assert [r["outcome"] for r in rows] == ["finite", "FAILED"]
    with open(tmp_path / "results.csv") as fh:
        table = list(csv.DictReader(fh))
    assert table[1]["outcome"] == "FAILED" and "non-finite" in table[1]["message"]
    assert "## FAILED" in (tmp_path / "results.md").read_text()


# ----------------------------------------------------------------------------- command line


def _tiny_matrix(monkeypatch, extra=()):
    cases = [StressCase("tiny", "size", BASE.with_(height=3, width=4, exposure_lines=2.0)), *extra]
    monkeypatch.setattr(stress, "stress_cases", lambda: cases)
    monkeypatch.setattr(stress, "available_methods", lambda: ["tv3d-haar", "blend"])


def test_cli_writes_the_tables(tmp_path, monkeypatch):
    _tiny_matrix(monkeypatch)
    res = CliRunner().invoke(main, ["bench", "--stress", "-o", str(tmp_path)])
    assert res.exit_code == 0, res.output
    assert "0 FAILED" in res.output
    with open(tmp_path / "results.csv") as fh:
        rows = list(csv.DictReader(fh))
    assert [r["method"] for r in rows] == ["operators", "tv3d-haar", "blend"]
    assert {r["outcome"] for r in rows} == {"finite"}
    assert "| tiny | tv3d-haar |" in (tmp_path / "results.md").read_text()


def test_cli_exits_with_an_error_line_when_a_case_fails(tmp_path, monkeypatch):
    accepted = StressCase("psi=2 must be refused", "bad parameter", expect="reject", options={"psi": 2.0},
                          methods=("tv3d-haar",), operators_expect="valid")
    _tiny_matrix(monkeypatch, [accepted])
    res = CliRunner().invoke(main, ["bench", "--stress", "-o", str(tmp_path)])
    assert res.exit_code == 2
    assert "error: 1 stress case(s) FAILED" in res.output


def test_cli_refuses_bench_options_with_stress():
    res = CliRunner().invoke(main, ["bench", "--stress", "--time-budget", "5"])
    assert res.exit_code == 2 and "--time-budget does not apply to --stress" in res.output


def test_real_psf_case_runs_on_the_packaged_psf(tmp_path):
    case = next(c for c in stress_cases() if c.name == "psf=real")
    rows = run_case(case, ["tv3d-haar"], SHORT, tmp_path)
    assert [r["outcome"] for r in rows] == ["finite", "finite"]
