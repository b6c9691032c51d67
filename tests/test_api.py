"""The Python API (`import rngcam`): the README's notebook example, nothing on disk unless asked,
errors that name the setting, the truth kept from every method, Result.save's files."""

from __future__ import annotations

import dataclasses
import json
import os
import re
from pathlib import Path

import numpy as np
import pytest
import torch
from click.testing import CliRunner

import rngcam
from rngcam.cli import main
from rngcam.errors import SettingError
from rngcam.recon import registry
from rngcam.recon.loop import MethodBase
from rngcam.recon.methods.tv3d import TV3DSettings

REPO = Path(__file__).resolve().parents[1]


def readme_example() -> str:
    text = (REPO / "README.md").read_text()
    block = re.search(r"```python\n(import rngcam\n.*?)```", text, re.S)
    assert block, "the README's Python API example is missing"
    return block.group(1)


def test_the_readme_example_runs_in_three_lines_without_touching_disk(shot, tmp_path, monkeypatch):
    code = readme_example()
    lines = [ln for ln in code.splitlines() if ln.strip() and not ln.lstrip().startswith("#")]
    assert len(lines) == 3, code
    monkeypatch.chdir(shot.parent)
    before = sorted(os.listdir(shot.parent))
    scope: dict = {}
    exec(compile(code, "README.md", "exec"), scope)  # noqa: S102 - the README's own example
    r = scope["r"]
    assert sorted(os.listdir(shot.parent)) == before  # nothing written
    assert r.status in ("ok", "budget_before_first_iteration")
    c, t, h, w = r.video.shape
    assert (c, h, w) == (3, 16, 16) and r.video.dtype == np.float32 and np.isfinite(r.video).all()
    assert r.frame_times_s.shape == (t,) and np.all(np.diff(r.frame_times_s) > 0)
    assert r.metrics["method"] == "stfm" and "psnr_db" in r.metrics
    assert isinstance(r.notes, list) and isinstance(r.warnings, list) and isinstance(r.left_out, list)


def test_result_save_writes_the_folder_recon_writes(shot, tmp_path):
    r = rngcam.reconstruct(shot, method="tv3d", max_iters=3, progress=False)
    assert r.status == "ok" and r.metrics["iterations"] == 3
    folder = r.save(tmp_path / "saved")
    for name in ("recon.h5", "video.tif", "preview.mp4", "errors.csv", "errors.png", "metrics.json"):
        assert (folder / name).is_file(), name
    assert json.loads((folder / "metrics.json").read_text())["iterations"] == 3
    logged = (folder / "recon.log").read_text()  # what the run said, though it printed nothing
    assert "set-up: read" in logged and logged.rstrip().endswith(r.summary())
    import h5py

    with h5py.File(folder / "recon.h5") as f:
        np.testing.assert_array_equal(f["video"][()], r.video)
        assert f.attrs["bundle_sha256"] == r.bundle_sha256 != ""


def test_a_missing_pyav_costs_the_preview_alone(shot, tmp_path, monkeypatch):
    import builtins

    real_import = builtins.__import__

    def no_av(name, *args, **kwargs):
        if name == "av":
            raise ModuleNotFoundError("No module named 'av'")
        return real_import(name, *args, **kwargs)

    r = rngcam.reconstruct(shot, method="tv3d", max_iters=2, progress=False)
    monkeypatch.setattr(builtins, "__import__", no_av)
    said: list[str] = []
    folder = r.save(tmp_path / "saved", echo=said.append)
    assert not (folder / "preview.mp4").exists()
    for name in ("recon.h5", "video.tif", "errors.csv", "metrics.json", "recon.log"):
        assert (folder / name).is_file(), name
    assert [line for line in said if line.startswith("warning: preview.mp4 not written (PyAV")], said
    with pytest.warns(UserWarning, match="preview.mp4 not written"):  # without an echo: a Python warning
        r.save(tmp_path / "again")


def test_settings_by_keyword_method_labels_and_an_open_bundle(shot):
    b = rngcam.open_bundle(shot)
    assert b.truth is not None and b.rs is not None and b.path == shot  # the bundle's fields show through
    shown = repr(b)  # a notebook shows a bundle in a few lines, its arrays by shape
    assert len(shown) < 3000 and f"truth=Truth(video=array({tuple(b.truth.video.shape)}, float32)" in shown
    r = rngcam.reconstruct(b, method="tv3d-exact", max_iters=1, beta=3.0, progress=False)
    assert r.metrics["method_settings"]["prox"] == "exact" and r.metrics["method_settings"]["beta"] == 3.0
    from rngcam.api import run_settings

    by_keyword = run_settings("tv3d", preset="exact", beta=3.0)  # preset= names a preset, as "tv3d-exact" does
    assert by_keyword.method_settings == run_settings("tv3d-exact", beta=3.0).method_settings
    with pytest.raises(SettingError, match="preset"):
        run_settings("tv3d-haar", preset="exact")
    lines: list[str] = []
    r = rngcam.reconstruct(b, method="blend", progress=lines.append)
    assert r.metrics["iterations"] == 1 and any("blend:" in ln for ln in lines)


@pytest.mark.parametrize("kwargs, setting", [
    ({"time_budget_s": -1}, "time_budget_s"),
    ({"time_budget_s": float("nan")}, "time_budget_s"),
    ({"max_iters": 0}, "max_iters"),
    ({"device": "gpu"}, "device"),
    ({"threads": 0}, "threads"),
    ({"threads": "many"}, "threads"),
    ({"checkpoint_every_s": 0}, "checkpoint_every_s"),
    ({"holdout": 2.0, "method": "tv3d"}, "holdout"),
    ({"bogus": 1}, "bogus"),
    ({"grid_bin": 0, "method": "blend"}, "grid_bin"),
    ({"max_memory_bytes": 10, "method": "blend"}, "max_memory_bytes"),
    ({"method": "stmf"}, "method"),
    ({"method": "stfm-slow"}, "method"),
    ({"beta": -1.0}, "beta"),
])
def test_errors_name_the_setting_not_a_flag(shot, kwargs, setting):
    assert rngcam.SettingError is SettingError
    with pytest.raises(SettingError) as err:
        rngcam.reconstruct(shot, progress=False, **kwargs)
    assert setting in str(err.value) and "--" not in str(err.value)
    assert setting in err.value.settings


def test_the_command_line_says_the_flag_for_the_same_error(shot, tmp_path):
    res = CliRunner().invoke(main, ["recon", str(shot), "--method", "blend", "--max-memory", "0.0000001",
                                    "-o", str(tmp_path / "o")])
    assert res.exit_code == 2 and "--max-memory" in res.output and "max_memory_bytes" not in res.output


@dataclasses.dataclass
class PeekSettings:
    pass


class Peek(MethodBase):
    """A one-step toy method that records the problem it was given."""

    name = "peek"
    seen: list = []  # noqa: RUF012

    def __init__(self, problem):
        Peek.seen.append(problem)
        self.video = torch.zeros(problem.shape, dtype=problem.b_rs.dtype)

    def step(self):
        return 0.0

    def estimate(self):
        return self.video

    def residuals(self):
        return {}

    def state_dict(self):
        return {"video": self.video.clone()}

    def load_state_dict(self, state):
        self.video = state["video"].clone()

    def reduce_step(self, factor):
        pass


@pytest.fixture
def peek():
    registry.register(registry.MethodEntry("peek", registry.ITERATIVE, PeekSettings,
                                           lambda problem, settings, **_: Peek(problem)))
    Peek.seen.clear()
    yield
    registry.unregister("peek")


def test_the_truth_never_reaches_a_method_but_scores_it(shot, peek):
    from rngcam.formats.bundle import read_bundle
    from rngcam.recon.problem import build_problem

    problem = build_problem(read_bundle(shot))
    assert problem.truth is not None
    for source in (shot, rngcam.open_bundle(shot), problem):
        r = rngcam.reconstruct(source, method="peek", max_iters=1, progress=False)
        assert Peek.seen[-1].truth is None
        assert "psnr_db" in r.metrics  # scored against the truth all the same


def test_simulate_refuses_a_size_that_would_not_fit_before_allocating(tmp_path):
    res = CliRunner().invoke(main, ["simulate", "sineball", "-o", str(tmp_path / "x.h5"), "--size", "10000"])
    assert res.exit_code == 2 and "would need about" in res.output and "--max-memory" in res.output
    assert not (tmp_path / "x.h5").exists()


def test_import_rngcam_stays_light():
    import subprocess
    import sys

    code = "import sys, rngcam; print('torch' in sys.modules, rngcam.__version__)"
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True,
                         env={**os.environ, "PYTHONPATH": str(REPO)}).stdout.split()
    assert out == ["False", rngcam.__version__]
    assert TV3DSettings  # the API's names load on first use: rngcam.reconstruct is rngcam.api.reconstruct
    from rngcam import api

    assert rngcam.reconstruct is api.reconstruct and rngcam.open_bundle is api.open_bundle


def test_recon_batch_takes_auto_as_recon_does_and_checks_the_device(shot, tmp_path):
    args = ["recon-batch", str(shot), "--method", "tv3d", "--iters", "1", "--no-ray", "-o", str(tmp_path / "b")]
    res = CliRunner().invoke(main, [*args, "--time-budget", "auto"])
    assert res.exit_code == 0, res.output
    bad = CliRunner().invoke(main, [*args, "--device", "gpu"])
    assert bad.exit_code == 2 and "must be auto, cpu, cuda or cuda:N" in bad.output


def test_a_long_silent_set_up_still_shows_progress(shot, monkeypatch):
    import time

    from rngcam.recon import runner

    monkeypatch.setattr(runner, "HEARTBEAT_S", 0.05)

    def slow(problem, settings, **_):
        time.sleep(0.5)  # a set-up stage that reports nothing
        return Peek(problem)

    registry.register(registry.MethodEntry("slowpeek", registry.ITERATIVE, PeekSettings, slow))
    try:
        lines: list[str] = []
        r = rngcam.reconstruct(shot, method="slowpeek", max_iters=1, progress=lines.append)
    finally:
        registry.unregister("slowpeek")
    assert r.status == "ok"
    assert sum("set-up: slowpeek still setting up" in ln for ln in lines) >= 3, lines


def test_large_runs_log_psnr_as_they_go_and_ssim_once_at_the_end(shot, monkeypatch):
    from rngcam.recon import runner

    every = rngcam.reconstruct(shot, method="tv3d", max_iters=4, log_every_s=1e-6, progress=False)
    monkeypatch.setattr(runner, "SSIM_EVERY_ROW_MAX_ELEMENTS", 0)  # as if the video were large
    once = rngcam.reconstruct(shot, method="tv3d", max_iters=4, log_every_s=1e-6, progress=False)
    assert len(once.log) >= 3 and all("psnr_db" in row for row in once.log)
    assert not any("ssim" in row for row in once.log[:-1]) and all("ssim" in row for row in every.log)
    final = once.log[-1]
    assert final["iteration"] == 4 and final["ssim"] == pytest.approx(every.log[-1]["ssim"], abs=1e-6)
    assert once.metrics["ssim"] == final["ssim"] and "ssim_intermediate" in once.metrics
