"""`rngcam recon` end to end on a mock-rig capture: every output exists and parses."""

import hashlib
import json
from pathlib import Path

import h5py
import numpy as np
import pytest
import tifffile
from click.testing import CliRunner

from rngcam.cli import main

REPO = Path(__file__).resolve().parents[1]


@pytest.fixture(scope="module")
def mock_bundle(tmp_path_factory):
    out = tmp_path_factory.mktemp("cap") / "m.h5"
    res = CliRunner().invoke(main, ["capture", "--rig", str(REPO / "rigs" / "mock.yaml"), "-o", str(out)])
    assert res.exit_code == 0, res.output
    return out


def _sha(path):
    return hashlib.sha256(Path(path).read_bytes()).hexdigest()


@pytest.mark.parametrize("method,extra", [("tv3d", ["--iters", "3"]), ("blend", []), ("interp", [])])
def test_recon_writes_every_output(mock_bundle, tmp_path, method, extra):
    before = _sha(mock_bundle)
    out = tmp_path / method
    res = CliRunner().invoke(main, ["recon", str(mock_bundle), "--method", method, "-o", str(out),
                                    "--quiet", *extra])
    assert res.exit_code == 0, res.output
    assert _sha(mock_bundle) == before  # the bundle is never modified
    metrics = json.loads((out / "metrics.json").read_text())
    for key in ("psnr_db", "ssim", "psnr_intermediate_db", "psnr_dynamic_db", "seconds", "iterations", "peak_rss_bytes",
                "method"):
        assert key in metrics, key
    assert metrics["method"] == method and np.isfinite(metrics["psnr_db"]) and metrics["psnr_db"] > 15
    one_shot = method != "tv3d"
    assert metrics["ended_by"] == ("one_shot" if one_shot else "iterations")
    setup = "" if one_shot else f" (set-up {metrics['setup_seconds']:.1f} s of it)"
    timing = (f"{method}: {'one pass' if one_shot else '3 iterations'} in {metrics['seconds']:.1f} s{setup}, "
              f"{metrics['wall_seconds']:.1f} s to the fit's end")
    assert timing in res.output, res.output
    seen = metrics["error_visibility"]  # the mock bundle is noisy, so both ratios are finite
    assert set(seen) == {"rs", "gs"} and all(np.isfinite(v) and v > 0 for v in seen.values())
    assert f"error seen at {seen['rs']:.2f}x the RS noise / {seen['gs']:.2f}x the GS noise" in res.output
    with h5py.File(out / "recon.h5") as f:
        video = f["video"][()]
        assert video.shape == (3, 67, 64, 64) and np.isfinite(video).all()
        assert f.attrs["bundle_sha256"] == before
        assert json.loads(f.attrs["settings"])["method"] == method
        assert len(f["frame_times_s"]) == 67
    with tifffile.TiffFile(out / "video.tif") as tif:  # an ImageJ hyperstack with the frame interval
        assert tif.series[0].axes == "TCYX" and tif.series[0].shape == (67, 3, 64, 64)
        assert tif.imagej_metadata["finterval"] == pytest.approx(208e-6)
    assert (out / "preview.mp4").stat().st_size > 1000
    assert json.loads((out / "preview.json").read_text())["capture_fps"] == pytest.approx(1 / 208e-6)
    assert (out / "errors.png").read_bytes()[:4] == b"\x89PNG"
    rows = (out / "errors.csv").read_text().splitlines()
    assert rows[0].startswith("iteration,wall_s,solve_s,objective") and len(rows) >= 2


def test_resume_continues_from_checkpoint(mock_bundle, tmp_path):
    out = tmp_path / "r"
    args = ["recon", str(mock_bundle), "--method", "tv3d", "-o", str(out), "--quiet"]
    assert CliRunner().invoke(main, args + ["--iters", "2"]).exit_code == 0
    res = CliRunner().invoke(main, args + ["--iters", "4", "--resume"])
    assert res.exit_code == 0, res.output
    metrics = json.loads((out / "metrics.json").read_text())
    assert metrics["iterations"] == 4 and any("resumed" in e for e in metrics["events"])


def test_clear_errors(tmp_path, mock_bundle):
    missing = CliRunner().invoke(main, ["recon", str(tmp_path / "nope.h5")])
    assert missing.exit_code != 0 and "bundle not found" in missing.output
    junk = tmp_path / "junk.h5"
    junk.write_bytes(b"not hdf5 at all")
    res = CliRunner().invoke(main, ["recon", str(junk), "--method", "blend"])
    assert res.exit_code == 2 and "Traceback" not in res.output
    assert len([ln for ln in res.output.splitlines() if ln.startswith("error:")]) == 1
    bad = CliRunner().invoke(main, ["recon", str(mock_bundle), "--method", "blend", "--tau", "1"])
    assert bad.exit_code != 0 and "--tau does not apply" in bad.output


def test_stfm_base_and_stop_options_reach_the_method(mock_bundle, tmp_path):
    out = tmp_path / "s"
    res = CliRunner().invoke(main, ["recon", str(mock_bundle), "-o", str(out), "--quiet", "--iters", "2",
                                    "--preset", "fast", "--set", "fit.base=interp", "--set", "fit.stop_at_noise=false"])
    assert res.exit_code == 0, res.output
    with h5py.File(out / "recon.h5") as f:
        settings = json.loads(f.attrs["settings"])
    used = settings["method_settings"]
    assert used["base_video"] == "interp" and used["stop_at_noise"] is False and "rs_noise_level" not in used
    metrics = json.loads((out / "metrics.json").read_text())
    assert metrics["method_settings"]["base_video"] == "interp"
    assert metrics["method_results"]["rs_noise_level"] > 0  # found by the run: a result, not a setting
    # the self-calibration report once, with the results (it was in method_settings twice)
    assert not {"selfcal_report", "self_calibration"} & set(metrics["method_settings"])
    assert "refined" in metrics["method_results"]["self_calibration"]
    assert not {"selfcal_report", "self_calibration"} & set(used)
    with h5py.File(out / "recon.h5") as f:  # recon.h5 and the report carry the results too, apart
        assert "self_calibration" in json.loads(f.attrs["results"])["method_results"]
    assert "what the run found" in (out / "report.html").read_text()


def test_stfm_base_list_runs_an_ensemble_and_a_bad_base_is_a_clear_error(mock_bundle, tmp_path):
    out = tmp_path / "e"
    res = CliRunner().invoke(main, ["recon", str(mock_bundle), "-o", str(out), "--quiet", "--iters", "4",
                                    "--preset", "fast", "--set", "fit.base=interp,keys_interp"])
    assert res.exit_code == 0, res.output
    metrics = json.loads((out / "metrics.json").read_text())
    assert metrics["method_settings"]["base_video"] == ["interp", "keys_interp"]
    assert metrics["method_results"]["member_steps"] == [2, 2]  # what the run did, apart from the settings
    bad = CliRunner().invoke(main, ["recon", str(mock_bundle), "-o", str(tmp_path / "b"), "--quiet", "--iters", "1",
                                    "--set", "fit.base=interp,warp"])
    assert bad.exit_code == 2 and "fit.base=interp,warp: dynamic_base must be one of" in bad.output
    assert "Traceback" not in bad.output


@pytest.mark.parametrize("method,args,budget", [("stfm", [], "auto"), ("tv3d", [], "auto"),
                                                ("stfm", ["--time-budget", "7"], 7.0)])
def test_recon_time_budget_defaults_by_method(mock_bundle, tmp_path, monkeypatch, method, args, budget):
    import numpy as np

    from rngcam.recon import runner
    from rngcam.recon.result import Result

    seen = {}

    def fake_solve(source, settings, out, echo, started=None):
        seen["budget"] = settings.time_budget_s
        return Result(np.zeros((1, 1, 1, 1), np.float32), np.zeros(1), {"method": method, "seconds": 0.0,
                                                                        "iterations": 0})

    monkeypatch.setattr(runner, "solve", fake_solve)
    res = CliRunner().invoke(main, ["recon", str(mock_bundle), "--method", method, "-o", str(tmp_path / "o"),
                                    "--quiet", *args])
    assert res.exit_code == 0, res.output
    assert seen["budget"] == budget  # "auto" is resolved once the problem's size is known


def test_recon_settings_budget_auto_is_the_methods_default_and_stays_auto():
    from dataclasses import asdict, replace

    from rngcam.recon.settings import Clock, ReconSettings, resolve

    shape = (3, 67, 64, 64)  # the size the registry's figures are set at
    run = resolve(ReconSettings(), shape, Clock(), finish=False)
    assert run.budget_s == 600.0 and run.clock.seconds == pytest.approx(600.0)  # stfm, the default method
    assert "auto: stfm 600 s at 64 px" in run.budget_how
    assert resolve(ReconSettings(method="tv3d"), shape, Clock(), finish=False).budget_s == 60.0
    # a copy keeps it auto (replace and asdict keep every field): the budget is resolved per problem
    copy = replace(ReconSettings(method="tv3d"), progress=False)
    assert copy.time_budget_s == "auto" and asdict(copy)["time_budget_s"] == "auto"
    big = resolve(copy, (3, 98, 96, 96), Clock())
    assert big.budget_s > 60.0 and big.record()["time_budget_s"] == big.budget_s  # what is recorded is what ran
    assert big.clock.seconds == pytest.approx(big.budget_s - big.finish_s) and big.finish_s > 0
    none = resolve(ReconSettings(method="tv3d", time_budget_s=None, max_iters=3), shape, Clock())
    assert none.budget_s is None and none.clock.seconds is None and not none.clock.expired()
    with pytest.raises(RuntimeError):
        big.clock.limit(5.0)  # one deadline per clock


def test_recon_refuses_a_non_empty_output_folder_unless_told_to_overwrite(mock_bundle, tmp_path):
    out = tmp_path / "o"
    args = ["recon", str(mock_bundle), "--method", "blend", "-o", str(out), "--quiet"]
    assert CliRunner().invoke(main, args).exit_code == 0
    first = (out / "metrics.json").stat().st_mtime_ns
    again = CliRunner().invoke(main, args)
    assert again.exit_code != 0 and "Traceback" not in again.output
    errors = [ln for ln in again.output.splitlines() if ln.startswith("error:")]
    assert len(errors) == 1 and "is not empty; pass --overwrite" in errors[0]
    assert (out / "metrics.json").stat().st_mtime_ns == first  # nothing was touched
    assert CliRunner().invoke(main, [*args, "--overwrite"]).exit_code == 0
    assert (out / "metrics.json").stat().st_mtime_ns != first


def test_an_auto_budget_is_recorded_as_the_seconds_the_run_used(tmp_path):
    """On a 96 px bundle "auto" scales the registry's 64 px figure: recon.h5, metrics.json and the report's
    settings say the seconds recon.log says the run used, and how they were derived (issue 38)."""
    from rngcam.evaluate.synthetic import CaptureSpec, make_psf, moving_square, timings, write_capture

    spec = CaptureSpec(height=96, width=96, exposure_lines=3, gs_frames=3, gs_exposure_lines=3)
    rs, gs, grid = timings(spec)
    bundle = write_capture(moving_square(3, grid.n_frames, 96, 96), make_psf("caustic", 96, 96), rs, gs, grid,
                           tmp_path / "b96.h5", noise=True, seed=0)
    out = tmp_path / "o"
    res = CliRunner().invoke(main, ["recon", str(bundle), "--method", "tv3d", "--iters", "2", "--quiet", "-o", str(out)])
    assert res.exit_code == 0, res.output
    with h5py.File(out / "recon.h5") as f:
        recorded = json.loads(f.attrs["settings"])
        found = json.loads(f.attrs["results"])
    metrics = json.loads((out / "metrics.json").read_text())
    budget = recorded["time_budget_s"]
    # what the run found is beside the settings, not in them
    assert found["status"] == "ok" and found["ended_by"] == "iterations" and "status" not in recorded
    assert budget > 60.0 and metrics["settings"]["time_budget_s"] == budget  # scaled, not tv3d's 64 px 60 s
    assert recorded["time_budget_asked"] == "auto" and recorded["time_budget_how"].startswith("auto: tv3d 60 s at 64 px")
    assert f"time budget {budget:.0f} s" in (out / "recon.log").read_text()
    assert "time_budget_how" in (out / "report.html").read_text()  # the report's "settings as resolved"
