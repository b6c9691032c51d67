"""Bad input never misleads (issue 20): each row of the issue's table as a bundle edited by hand
(h5py) from a small simulated one, through `rngcam inspect` and `rngcam recon`.

Tests named test_stfm_* hold STFM to the same promises; STFM applies Problem.rs_valid_mask() /
gs_valid_mask() to its residuals once its package split lands.
"""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import h5py
import numpy as np
import pytest
import torch
from click.testing import CliRunner

from rngcam.cli import main
from rngcam.errors import ConfigError, RngcamError
from rngcam.evaluate import stress_cases as edits
from rngcam.formats.bundle import read_bundle
from rngcam.recon.methods.coarse_to_fine import coarsen
from rngcam.recon.metrics import error_visibility, error_visibility_caveats
from rngcam.recon.problem import build_problem
from rngcam.recon.runner import ReconSettings, reconstruct
from rngcam.sim.simulate import simulate

TV3D_ITERS = "150"


@pytest.fixture(scope="module")
def clean(tmp_path_factory) -> Path:
    """A 32 px simulated sineball bundle (12-bit, black level 64, noise on)."""
    torch.set_num_threads(1)
    path = tmp_path_factory.mktemp("clean") / "clean.h5"
    simulate("sineball", path, size=32, seed=0)
    return path


def edited(clean: Path, tmp_path: Path, name: str, *hooks) -> Path:
    path = tmp_path / f"{name}.h5"
    shutil.copy(clean, path)
    for hook in hooks:
        hook(path)
    return path


def cli(*args: str):
    return CliRunner().invoke(main, list(args))


def one_error_line(result) -> str:
    assert result.exit_code == 2, result.output
    lines = [line for line in result.output.splitlines() if line.strip()]
    assert "Traceback" not in result.output
    return lines[-1]


def recon(bundle: Path, out: Path, method: str = "tv3d", *extra: str) -> tuple[dict, str]:
    iters = ["--iters", TV3D_ITERS] if method == "tv3d" else []
    res = cli("recon", str(bundle), "--method", method, "-o", str(out), "--quiet", *iters, *extra)
    assert res.exit_code == 0, res.output
    return json.loads((out / "metrics.json").read_text()), res.output


# ----------------------------------------------------------------------------- row 1: bit depth


def test_values_above_the_declared_full_scale_fail_inspect_and_recon(clean, tmp_path):
    bad = edited(clean, tmp_path, "x16", edits.scale_values(16))  # 12-bit declared, MSB-aligned values
    line = one_error_line(cli("inspect", str(bad)))
    assert "above the 12-bit full scale of 4,095 DN" in line and "bit_depth" in line
    out = tmp_path / "out"
    line = one_error_line(cli("recon", str(bad), "--method", "tv3d", "-o", str(out)))
    assert "above the 12-bit full scale" in line
    assert not out.exists()


# ----------------------------------------------------------------------------- row 2: saturated GS frame


def test_a_saturated_gs_frame_is_reported_left_out_and_costs_under_1_db(clean, tmp_path):
    sat = edited(clean, tmp_path, "sat", edits.saturate_gs_frame(1))
    res = cli("inspect", str(sat), "--json")
    assert res.exit_code == 0, res.output
    summary = json.loads(res.stdout)
    assert summary["pixels"]["gs"][1]["saturated_fraction"] == 1.0
    assert summary["pixels"]["gs"][0]["saturated_fraction"] == 0.0
    assert any("GS frame 2 is left out" in p and "saturated" in p for p in summary["problems"])
    without = edited(clean, tmp_path, "without", edits.remove_gs_frame(1))
    for method in ("tv3d", "interp"):
        m_sat, text = recon(sat, tmp_path / f"sat-{method}", method)
        m_without, _ = recon(without, tmp_path / f"without-{method}", method)
        assert "left out: GS frame 2 (saturated" in text
        assert {"component": "GS frame 2", "reason": "saturated: 100.0 % of its pixels at full scale"} \
            in m_sat["left_out"]
        assert abs(m_sat["psnr_db"] - m_without["psnr_db"]) <= 1.0, (method, m_sat["psnr_db"], m_without["psnr_db"])


# ----------------------------------------------------------------------------- row 3: dead RS frame


def test_an_rs_frame_below_the_black_level_is_left_out_not_fitted(clean, tmp_path):
    dead = edited(clean, tmp_path, "dead", edits.edit_frames("rs", lambda x: x * 0))
    res = cli("inspect", str(dead))
    assert res.exit_code == 0 and "the RS image is left out of the reconstruction (dead" in res.output
    tv, text = recon(dead, tmp_path / "tv3d")
    gs_only, _ = recon(dead, tmp_path / "interp", "interp")
    assert "left out: RS image (dead: 100.0 % of its pixels at 0 DN" in text
    assert "rs" not in tv["error_visibility"]  # nothing vouches for the RS fit: it was not fitted
    assert tv["psnr_db"] > gs_only["psnr_db"] - 3.0  # the issue: 13 dB below interp


# ----------------------------------------------------------------------------- row 4: absurd timing


def test_an_absurd_line_time_stops_before_allocating_with_one_line(clean, tmp_path):
    fast = edited(clean, tmp_path, "1ns", edits.set_attr("rs", "line_time_s", 1e-9))
    res = cli("inspect", str(fast))
    assert res.exit_code == 0, res.output
    assert "recon --method stfm would refuse this bundle" in res.output and "--max-frames" in res.output
    out = tmp_path / "out"
    for method in ("tv3d", "interp"):
        line = one_error_line(cli("recon", str(fast), "--method", method, "-o", str(out)))
        assert "650,031 frames" in line and "raise --max-frames" in line
    assert not out.exists()


def test_the_memory_limit_names_its_figure(clean, tmp_path):
    line = one_error_line(cli("recon", str(clean), "--method", "tv3d", "--max-memory", "0.0001",
                              "-o", str(tmp_path / "o")))
    assert "tv3d would need about" in line and "--max-memory 0.0 GiB" in line and "coarser --bin" in line
    assert not (tmp_path / "o").exists()


def test_running_out_of_memory_is_one_line(clean, tmp_path, monkeypatch):
    def exhausted(*args, **kwargs):
        raise MemoryError

    monkeypatch.setattr("rngcam.recon.runner.build_problem", exhausted)
    line = one_error_line(cli("recon", str(clean), "--method", "tv3d", "-o", str(tmp_path / "o")))
    assert line.startswith("error: tv3d ran out of memory") and "--bin" in line


# ----------------------------------------------------------------------------- row 5: GS outside the window


@pytest.mark.parametrize("where", ["before", "after"])
def test_gs_frames_before_and_after_the_rs_window_get_the_same_treatment(clean, tmp_path, where):
    if where == "before":
        hook = edits.set_gs_triggers(lambda t, end: edits.set_at(t, 0, -end))
        frame = "GS frame 1"
    else:
        hook = edits.set_gs_triggers(lambda t, end: edits.set_at(t, len(t) - 1, 2 * end))
        frame = "GS frame 3"
    path = edited(clean, tmp_path, where, hook)
    res = cli("inspect", str(path))
    assert res.exit_code == 0, res.output
    [warning] = [line.split("problem", 1)[1].strip() for line in res.output.splitlines()
                 if line.startswith("problem")]
    assert warning.startswith("warning: 1 GS exposure(s) outside the RS exposure window")
    metrics, text = recon(path, tmp_path / "r")
    assert text.splitlines()[0] == warning  # repeated first
    assert metrics["warnings"] == [warning]
    [left] = [e for e in metrics["left_out"] if e["component"] == frame]
    assert "misses the RS exposure window" in left["reason"]
    assert metrics["frames"] == 35  # the grid covers the RS window, as for the clean bundle


def test_a_gs_exposure_straddling_t0_extends_the_grid_before_t0(clean, tmp_path):
    path = edited(clean, tmp_path, "straddle", edits.set_gs_triggers(lambda t, end: edits.set_at(t, 0, -300e-6)))
    problem = build_problem(read_bundle(path))
    assert problem.time_origin_s == pytest.approx(-208e-6 * 2)  # two whole frames before T0
    assert problem.frame_times_s[0] < 0 < problem.frame_times_s[2]
    assert problem.b_gs.shape[1] == 3 and problem.left_out == []
    # its whole exposure is on the grid: the weights sum to exposure / dt
    np.testing.assert_allclose(problem.gs_weights.sum(1).numpy(), 650e-6 / 208e-6)
    # a coarse-to-fine level keeps the clock: its frames are the fine frames' pairs, before T0 too
    coarse = coarsen(problem, 2)
    fine_times = problem.frame_times_s
    np.testing.assert_allclose(coarse.frame_times_s[:2], [fine_times[0:2].mean(), fine_times[2:4].mean()])


def test_an_rs_trigger_after_t0_is_an_error(clean, tmp_path):
    path = edited(clean, tmp_path, "late-rs", lambda p: edits._write_dataset(p, "rs/trigger_times_s", np.array([1e-3])))
    line = one_error_line(cli("inspect", str(path)))
    assert "T0, the RS trigger, so it must be 0" in line


# ----------------------------------------------------------------------------- saturation costs little


def _patch_pair(clean, tmp_path):
    patch = edited(clean, tmp_path, "patch", edits.saturate_rs_patch(0.04))
    with h5py.File(patch) as f:
        assert 0.03 <= float((f["rs/frames"][()] >= 4095).mean()) <= 0.05
    return patch


def test_a_saturated_rs_patch_costs_tv3d_at_most_2_db(clean, tmp_path):
    patch = _patch_pair(clean, tmp_path)
    m_clean, _ = recon(clean, tmp_path / "clean")
    m_patch, text = recon(patch, tmp_path / "patch")
    assert "of the RS pixels left out of the data term" in text
    assert 0.03 <= m_patch["masked_fraction"]["rs"] <= 0.06
    assert m_clean["psnr_db"] - m_patch["psnr_db"] <= 2.0, (m_clean["psnr_db"], m_patch["psnr_db"])


def test_stfm_a_saturated_rs_patch_costs_at_most_2_db(clean, tmp_path):
    patch = _patch_pair(clean, tmp_path)
    opts = ("--set", "fit.base=video", "--time-budget", "60")
    m_clean, _ = recon(clean, tmp_path / "clean", "stfm", *opts)
    m_patch, _ = recon(patch, tmp_path / "patch", "stfm", *opts)
    assert m_clean["psnr_db"] - m_patch["psnr_db"] <= 2.0, (m_clean["psnr_db"], m_patch["psnr_db"])


def test_saturated_pixels_leave_the_tv3d_data_term(clean, tmp_path):
    """The masked fit does not see the patch: its RS residual on the valid pixels is unchanged
    by any value written into the saturated ones."""
    from rngcam.recon.methods.tv3d import TV3D

    problem = build_problem(read_bundle(_patch_pair(clean, tmp_path))).to(torch.float32)
    assert problem.rs_valid is not None and not bool(problem.rs_valid.all())
    method = TV3D(problem)
    before = method.objective(method.estimate())
    problem.b_rs[~problem.rs_valid] = 1e6
    assert TV3D(problem).objective(method.estimate()) == pytest.approx(before, rel=1e-6)


# ----------------------------------------------------------------------------- error visibility


def test_error_visibility_does_not_vouch_for_mis_scaled_data(clean, tmp_path):
    wrong_black = edited(clean, tmp_path, "black", edits.set_attr("rs", "black_level_dn", 0.0))
    problem = build_problem(read_bundle(wrong_black))
    seen = error_visibility(problem, problem.truth)
    assert np.isnan(seen["rs"]) and seen["gs"] == 0.0
    [caveat] = error_visibility_caveats(problem)
    assert "RS data differ from the truth's prediction" in caveat
    good = build_problem(read_bundle(clean))
    assert error_visibility_caveats(good) == [] and error_visibility(good, good.truth)["rs"] == 0.0


# ----------------------------------------------------------------------------- options


@pytest.mark.parametrize("args", [("--time-budget", "-5"), ("--time-budget", "0"), ("--iters", "-3"),
                                  ("--time-budget", "nan"), ("--max-frames", "0"), ("--bin", "0")])
def test_bad_options_fail_at_parse_time_and_leave_no_folder(clean, tmp_path, args):
    out = tmp_path / "out"
    res = cli("recon", str(clean), "--method", "tv3d", "-o", str(out), *args)
    assert res.exit_code == 2 and "Traceback" not in res.output
    assert f"Invalid value for '{args[0]}'" in res.output
    assert not out.exists()


def test_recon_settings_refuse_figures_that_cannot_be_meant():
    for kwargs in ({"time_budget_s": -5.0}, {"time_budget_s": 0.0}, {"max_iters": -3}, {"max_frames": 0}):
        with pytest.raises(ConfigError):
            ReconSettings(method="tv3d", **kwargs)


def test_a_bundle_with_nothing_usable_is_refused_in_one_line(clean, tmp_path):
    gone = edited(clean, tmp_path, "gone", edits.edit_frames("rs", lambda x: x * 0 + 4095),
                  edits.edit_frames("gs", lambda x: x * 0 + 4095))
    with pytest.raises(RngcamError, match="no measurement carries anything"):
        reconstruct(gone, tmp_path / "o", ReconSettings(method="tv3d", max_iters=2, progress=False))


# ----------------------------------------------------------------------------- capture: hardware safe


@pytest.mark.parametrize("failure,said", [(MemoryError, "ran out of memory after firing shot 1/1"),
                                          (KeyboardInterrupt, "interrupted (Ctrl-C) after firing shot 1/1"),
                                          (ZeroDivisionError, "failed: ZeroDivisionError: injected after firing")])
def test_capture_failure_after_arming_leaves_the_hardware_safe_in_one_line(tmp_path, monkeypatch, failure, said):
    """The mock rig with the fake generator on a pty; a failure injected after "fired"."""
    from rngcam.acquire.fake_generator import FakeGenerator
    from rngcam.acquire.mock_camera import MockCamera
    seen = {"outputs": None, "closed": []}
    stop, close = FakeGenerator.stop, MockCamera.close

    def spy_stop(self):
        seen["outputs"] = {n: ch.output for n, ch in self.channels.items()}
        stop(self)

    def spy_close(self):
        seen["closed"].append(self.armed)
        close(self)

    def broken_fetch(self, *args, **kwargs):
        raise failure("injected") if failure is not KeyboardInterrupt else failure()

    monkeypatch.setattr(FakeGenerator, "stop", spy_stop)
    monkeypatch.setattr(MockCamera, "close", spy_close)
    monkeypatch.setattr(MockCamera, "fetch", broken_fetch)
    out = tmp_path / "shot.h5"
    res = CliRunner().invoke(main, ["capture", "--rig", str(Path(__file__).parents[1] / "rigs" / "mock.yaml"),
                                    "-o", str(out)])
    line = one_error_line(res)
    assert line.startswith("error: capture ") and said in line
    assert "hardware safe: cameras disarmed, generator outputs off" in line
    assert "fired" in res.output and not out.exists() and list(tmp_path.iterdir()) == []
    assert seen["outputs"] == {1: False, 2: False} and seen["closed"] == [False, False]


# ----------------------------------------------------------------------------- frame statistics


def test_frame_statistics_and_which_frames_are_beyond_use():
    from rngcam import pixels

    rng = np.random.default_rng(0)
    lit = rng.integers(100, 4000, size=(16, 16, 3))
    dark_noisy = np.clip(rng.normal(64, 2, size=(16, 16, 3)).round(), 0, None)  # a dark scene: kept
    s = pixels.frame_stats(lit, 12, 64)
    assert s.saturated == 0 and s.valid == 1 and pixels.unusable_reason(s, True) is None
    assert pixels.unusable_reason(pixels.frame_stats(dark_noisy, 12, 64), True) is None
    at_black = np.full((16, 16, 3), 64)  # every pixel at the black level
    assert pixels.unusable_reason(pixels.frame_stats(at_black, 12, 64), others_see_light=False) is None
    assert pixels.unusable_reason(pixels.frame_stats(at_black, 12, 64), others_see_light=True).startswith("dark")
    assert pixels.unusable_reason(pixels.frame_stats(np.full((16, 16, 3), 1000), 12, 64), True).startswith("flat")
    half = lit.copy()
    half[:8] = 4095
    s = pixels.frame_stats(half, 12, 64)
    assert s.saturated == pytest.approx(0.5) and pixels.unusable_reason(s, True) is None  # masked, not dropped
    assert pixels.value_problems("RS", [pixels.frame_stats(lit * 16, 12, 64)], 12)[0].startswith(
        "RS pixel values reach")
    bad = pixels.invalid_pixels(np.array([0, 64, 4094, 4095]), 12, 64)
    assert bad.tolist() == [True, False, False, True]


@pytest.mark.parametrize("name,methods", [("GS frame 2 saturated", ("tv3d-haar", "interp")),
                                          ("RS all 0 DN (below black)", ("tv3d-haar", "blend")),
                                          ("RS line time 0.1 ns", ("tv3d-haar", "blend")),
                                          ("GS frame before the RS window", ("tv3d-haar", "blend")),
                                          ("every GS frame saturated (GS-only)", ("blend",)),
                                          ("GS frame 2 bottom quarter 0 DN", ("tv3d-haar",))])
def test_bench_stress_bad_input_cases_pass(tmp_path, name, methods):
    from rngcam.evaluate.stress import StressSettings, run_case
    from rngcam.evaluate.stress_cases import stress_cases

    [case] = [c for c in stress_cases() if c.name == name]
    rows = run_case(case, list(methods), StressSettings(tv3d_iters=6, time_cap_s=10.0), tmp_path)
    assert len(rows) == 1 + len(methods)
    assert all(r["outcome"] != "FAILED" for r in rows), rows


def test_what_the_capture_warned_about_travels_to_inspect_recon_and_metrics(clean, tmp_path):
    def warn(path):
        with h5py.File(path, "r+") as f:
            meta = json.loads(f.attrs["meta"])
            meta["warnings"] = ["RS camera line time is 200 us but the rig says 208 us"]
            f.attrs["meta"] = np.bytes_(json.dumps(meta).encode())

    path = edited(clean, tmp_path, "warned", warn)
    expected = "warning: capture: RS camera line time is 200 us but the rig says 208 us"
    assert expected in cli("inspect", str(path)).output
    metrics, text = recon(path, tmp_path / "r", "blend")
    assert text.splitlines()[0] == expected and metrics["warnings"] == [expected]


def test_a_lab_sized_mock_scene_is_refused_before_arming(tmp_path):
    rig_path = Path(__file__).parents[1] / "rigs" / "mock.yaml"
    text = rig_path.read_text().replace("roi: {width: 64, height: 64}", "roi: {width: 4096, height: 4096}")
    text = text.replace("line_time_s: 208.0e-6", "line_time_s: 4.0e-6")
    (tmp_path / "big.yaml").write_text(text)
    (tmp_path / "out").mkdir()
    res = cli("capture", "--rig", str(tmp_path / "big.yaml"), "-o", str(tmp_path / "out" / "x.h5"))
    line = one_error_line(res)
    assert "the mock scene would need about" in line and "smaller cameras.rs.roi" in line
    assert "armed" not in res.output and list((tmp_path / "out").iterdir()) == []
