"""`rngcam bench`: a tiny end-to-end run of the runner (one scene, two methods, a 1 s budget),
the time-to-PSNR levels, the scene list, and that each run's peak memory is its own."""

from __future__ import annotations

import csv
import math
import subprocess
import sys

import numpy as np
import pytest
from click.testing import CliRunner

from rngcam.cli import main
from rngcam.errors import RngcamError
from rngcam.evaluate.compare import BenchSettings, add_level_times, run_bench, time_to_level
from rngcam.evaluate.scenes import bench_scenes
from rngcam.sim.scenes import default_clip_path


def test_time_to_level_is_the_first_solve_time_at_or_above_the_level():
    log = [{"solve_s": 0.5, "psnr_db": 18.0}, {"solve_s": 1.0, "psnr_db": 20.5},
           {"solve_s": 2.0, "psnr_db": 19.0}, {"solve_s": 3.0, "psnr_db": 22.0}]
    assert time_to_level(log, 20.0) == 1.0
    assert time_to_level(log, 21.0) == 3.0
    assert math.isnan(time_to_level(log, 30.0))
    assert math.isnan(time_to_level([{"solve_s": 1.0, "psnr_db": float("nan")}], 0.0))


def test_levels_start_at_the_best_gs_only_psnr():
    rows = [{"method": "blend", "psnr_db": 18.0, "log": [{"solve_s": 0.01, "psnr_db": 18.0}]},
            {"method": "interp", "psnr_db": 19.0, "log": [{"solve_s": 0.2, "psnr_db": 19.0}]},
            {"method": "tv3d", "psnr_db": 22.5,
             "log": [{"solve_s": 1.0, "psnr_db": 19.5}, {"solve_s": 4.0, "psnr_db": 22.5}]}]
    levels = add_level_times(rows)
    assert levels == {"t_gs_s": 19.0, "t_gs+1dB_s": 20.0, "t_gs+3dB_s": 22.0}
    assert rows[2]["t_gs_s"] == 1.0 and rows[2]["t_gs+1dB_s"] == 4.0 and rows[2]["t_gs+3dB_s"] == 4.0
    assert rows[1]["t_gs_s"] == 0.2 and math.isnan(rows[1]["t_gs+1dB_s"])
    assert math.isnan(rows[0]["t_gs_s"])


def test_scene_list_has_the_procedural_scenes_every_clip_and_extra_clips(tmp_path):
    # without a data folder: the short clip that ships in rngcam/data
    assert [s.name for s in bench_scenes(None)] == ["sineball", "smoke", default_clip_path().stem]
    (tmp_path / "videos").mkdir()
    for name in ("b_clip", "a_clip"):
        np.savez(tmp_path / "videos" / f"{name}.npz", frames=np.zeros((9, 16, 16, 3), np.uint8))
    assert [s.name for s in bench_scenes(tmp_path)] == ["sineball", "smoke", "a_clip", "b_clip"]
    extra = tmp_path / "mine.npz"
    np.savez(extra, frames=np.zeros((9, 16, 16, 3), np.uint8))
    assert bench_scenes(tmp_path, (extra,))[-1].name == "mine"
    assert [s.name for s in bench_scenes(tmp_path, only=("smoke",))] == ["smoke"]
    with pytest.raises(RngcamError, match="unknown scene"):
        bench_scenes(tmp_path, only=("nope",))
    with pytest.raises(RngcamError, match="does not exist"):
        bench_scenes(tmp_path, (tmp_path / "missing.npz",))


def test_child_peak_memory_does_not_include_the_parent():
    """ru_maxrss of a child includes the parent's size at fork; the worker's figure must not."""
    ballast = np.ones(300 * 2**20 // 8)  # 300 MB touched in this process
    code = "from rngcam.memory import peak_rss_bytes; print(peak_rss_bytes())"
    child = int(subprocess.run([sys.executable, "-c", code], capture_output=True, text=True,
                               check=True).stdout)
    assert ballast.sum() > 0
    assert child < 150 * 2**20


def test_tiny_bench_end_to_end(tmp_path):
    settings = BenchSettings(size=16, time_budget_s=1.0, methods=("tv3d", "blend"))
    scenes = bench_scenes(None, only=("sineball",))
    rows = run_bench(tmp_path, scenes, settings, echo=lambda _m: None)
    assert [(r["scene"], r["method"], r["status"]) for r in rows] == [("sineball", "tv3d", "ok"),
                                                                      ("sineball", "blend", "ok")]
    tv3d, blend = rows
    assert tv3d["iterations"] > 1 and blend["iterations"] == 1
    assert tv3d["seconds"] <= settings.time_budget_s + 1.0
    assert all(np.isfinite(r["psnr_db"]) and 0 < r["ssim"] <= 1 for r in rows)
    assert all(60 < r["peak_rss_mb"] < 4000 and 0 <= r["added_rss_mb"] < r["peak_rss_mb"] for r in rows)
    assert blend["t_gs_s"] == pytest.approx(blend["seconds"])  # the only GS-only run sets the level
    with open(tmp_path / "results.csv") as fh:
        table = list(csv.DictReader(fh))
    assert [r["method"] for r in table] == ["tv3d", "blend"]
    assert {"psnr_db", "psnr_intermediate_db", "ssim", "ssim_intermediate", "t_gs_s", "t_gs+1dB_s",
            "t_gs+3dB_s", "seconds", "peak_rss_mb"} <= set(table[0])
    md = (tmp_path / "results.md").read_text()
    assert "## sineball" in md and "| tv3d | ok |" in md and "errors_sineball.png" in md
    assert (tmp_path / "errors_sineball.png").stat().st_size > 10_000
    assert (tmp_path / "runs" / "sineball" / "tv3d" / "recon.h5").is_file()


def test_cli_rejects_bad_options():
    runner = CliRunner()
    res = runner.invoke(main, ["bench", "--time-budget", "0"])
    assert res.exit_code == 2 and "--time-budget" in res.output
    res = runner.invoke(main, ["bench", "--method", "nope"])
    assert res.exit_code == 2
