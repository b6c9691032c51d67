"""bench/gpu_check.py's CPU half (`--quick`): a scene simulated, reconstructed in a child of its own and
written as one table row with its figures, as the GPU check does on a lent GPU."""

from __future__ import annotations

import json
import math
from pathlib import Path

import pytest

from bench import gpu_check


@pytest.mark.slow
def test_the_quick_check_runs_a_scene_on_its_own_device_and_writes_its_row(tmp_path, monkeypatch):
    # the run names its own device, as the check's CPU baseline does: it wins over --device. The limit only
    # guards a hung child: 120 s timed out beside a load of 6 (the run takes ~15 s on an idle machine)
    monkeypatch.setattr(gpu_check, "QUICK", [("sineball 32 quick", "sineball", "32",
                                              {"max_iters": 10, "device": "cpu", "threads": 2}, 900)])
    rc = gpu_check.main(["-o", str(tmp_path), "--device", "cuda", "--quick", "--skip-tests", "--skip-step",
                         "--only", "sineball"])
    assert rc == 0
    rows = json.loads((tmp_path / "gpu_check.json").read_text())["rows"]
    assert [r["label"] for r in rows] == ["sineball 32 quick"]
    row = rows[0]
    assert row["status"] == "ok" and row["ended_by"] == "iterations" and row["iterations"] == 10
    assert row["device"] == "cpu" and row["peak_gpu_gib"] is None
    assert math.isfinite(row["psnr_db"]) and row["psnr_db"] > 15
    assert row["centroid_error_median_px"] >= 0 and row["wall_s"] > row["setup_s"] > 0
    assert row["level_steps"] == []  # 32 px runs on one level
    assert row["stop"] == ""  # ended by its iteration cap: no own-stop line (the status column says why)
    table = (tmp_path / "gpu_check.md").read_text()
    assert "| sineball 32 quick | cpu |" in table


def test_only_keeps_runs_by_label_prefix_and_a_failed_simulation_is_a_row(tmp_path, monkeypatch):
    monkeypatch.setattr(gpu_check, "simulate_all", lambda out, runs, limit: None)  # no bundle made
    rc = gpu_check.main(["-o", str(tmp_path), "--device", "cpu", "--quick", "--skip-tests", "--skip-step",
                         "--only", "smoke 32"])
    assert rc == 1  # a row that is not ok
    rows = json.loads((tmp_path / "gpu_check.json").read_text())["rows"]
    assert [r["label"] for r in rows] == ["smoke 32 quick"]
    assert rows[0]["status"].startswith("no bundle")
    assert "smoke 32 quick" in (tmp_path / "gpu_check.md").read_text()


def test_the_steps_column_splits_a_coarse_to_fine_run_by_level():
    rows = [{"label": "paper", "iterations": 1386, "level_steps": [900, 300, 186]},
            {"label": "one level", "iterations": 820, "level_steps": [820]},
            {"label": "failed", "status": "recon failed (1)"}]
    lines = gpu_check.table(rows, "a device").splitlines()
    assert "| paper |  |" in lines[4] and "| 1386 (900 + 300 + 186) |" in lines[4]
    assert "| 820 |" in lines[5] and "(" not in lines[5].split("|")[5]
    assert "recon failed (1)" in lines[6]


def test_a_whole_label_keeps_that_row_alone_and_threads_reach_every_run(tmp_path, monkeypatch):
    seen = []
    monkeypatch.setattr(gpu_check, "simulate_all", lambda out, runs, limit: None)
    monkeypatch.setattr(gpu_check, "reconstruction",
                        lambda out, label, scene, size, settings, limit, device: seen.append((label, settings))
                        or {"label": label, "status": "ok"})
    monkeypatch.setattr(gpu_check, "FULL", [("a 64", "a", "64", {}, 9), ("a 64, 2 threads", "a", "64", {"threads": 2}, 9),
                                            ("b 64", "b", "64", {}, 9), ("b 128", "b", "128", {}, 9)])
    assert gpu_check.main(["-o", str(tmp_path), "--skip-tests", "--skip-step", "--only", "a 64,b", "--threads", "4"]) == 0
    assert seen == [("a 64", {"threads": 4}), ("b 64", {"threads": 4}), ("b 128", {"threads": 4})]
    seen.clear()
    assert gpu_check.main(["-o", str(tmp_path), "--skip-tests", "--skip-step", "--only", "a 64,", "--threads", "4"]) == 0
    assert [label for label, _ in seen] == ["a 64"]  # a trailing comma's empty word keeps nothing more


def test_two_runs_of_one_bundle_simulate_it_once(tmp_path, monkeypatch):
    started = []

    class Proc:
        def __init__(self, cmd, **_kw):
            started.append(cmd)

        def communicate(self, timeout=None):
            return ("", None)

    monkeypatch.setattr(gpu_check.subprocess, "Popen", Proc)
    gpu_check.simulate_all(tmp_path, [("a 60", "smoke", "228x342", {}, 9), ("a 120", "smoke", "228x342", {}, 9),
                                      ("b", "smoke", "64", {}, 9)], 10)
    assert [cmd[cmd.index("--size") + 1] for cmd in started] == ["228x342", "64"]


def test_a_profiled_run_lists_where_its_time_went(tmp_path, monkeypatch, capsys):
    import rngcam

    def fake_reconstruct(bundle, method, out, **kwargs):
        assert "profile" not in kwargs  # the check's own switch never reaches reconstruct
        Path(out).mkdir(parents=True, exist_ok=True)
        from rngcam.recon.methods.selfcal import line_search

        line_search(lambda x: (x - 0.3) ** 2, 0.0, 1.0, 0.1, 0.01, 0.2)  # some rngcam work to profile
        (Path(out) / "metrics.json").write_text(json.dumps({"iterations": 1, "status": "ok"}))

    monkeypatch.setattr(rngcam, "reconstruct", fake_reconstruct)
    gpu_check.child("b.h5", str(tmp_path / "o"), "cpu", json.dumps({"max_iters": 1, "profile": True}))
    row = json.loads(capsys.readouterr().out.split("ROW ", 1)[1])
    assert any("line_search" in line for line in row["profile_top"]), row["profile_top"]


@pytest.mark.slow
def test_the_step_row_counts_a_steps_operations_and_times_it_on_the_device(tmp_path, monkeypatch):
    """The row of bench/ops_per_step.py's figures, on the smallest grid's bundles (here the quick 32 px one, on
    the CPU): operations and milliseconds a step for each coarse-to-fine level, in the table's status."""
    monkeypatch.setattr(gpu_check, "QUICK", [("smoke 32 quick", "smoke", "32", {"max_iters": 2}, 120)])
    assert gpu_check.main(["-o", str(tmp_path), "--device", "cpu", "--quick", "--skip-tests", "--only", "smoke"]) == 0
    rows = json.loads((tmp_path / "gpu_check.json").read_text())["rows"]
    assert [r["label"] for r in rows] == ["32 px step (ops, ms)", "smoke 32 quick"]
    step = rows[0]
    assert step["status"] == "ok" and step["device"] == "cpu" and step["steps_levels"]
    for level in step["steps_levels"]:
        assert level["bundle"] == "smoke-32" and level["ops"] > 100 and level["ms"] > 0
    assert "smoke-32 1:" in step["summary"] and " ops, " in step["summary"]
    assert "32 px step (ops, ms)" in (tmp_path / "gpu_check.md").read_text()
